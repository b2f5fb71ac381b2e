//! Object space over real processes on loopback: 2 and 4 nodes each render
//! their brick of the volume (with an AO halo) and send each tile's pixels to the node that shows
//! it; the wall snapshot must equal a single render of the whole wall camera, pixels along the
//! cuts included, and each node must hold no more volume than its brick and halo. With
//! `denoise = "on"` the pixels travel in shading form over each tile's canvas (the tile and the
//! filter's guard band) and the owner filters the composited canvas: the snapshot must equal the
//! single denoised render.

use glam::DVec3;
use isowall_e2e::{free_udp_ports, gpu_ok, render_whole, run_in, wall_config};
use isowall_model::bricks::{self, Occupancy};
use isowall_model::{AoRadius, RenderSettings};
use isowall_volume::{BlockMinMax, VolumeSource};

/// The scene: the torus at 48^3 (iso 0), AO radius 10 world units (voxels): wider than a block,
/// so the AO of points near a cut reaches into the neighbour brick.
const VOLUME: &str = "procedural:torus:48";
const AO_RADIUS: f64 = 10.0;

fn object_wall(nodes: usize, compress: bool, denoise: bool) {
    let dir = tempfile::tempdir().unwrap();
    let (w, h, bezel) = (64u32, 48u32, 3u32);
    let config = wall_config(dir.path(), "obj", &free_udp_ports(nodes), w, h, bezel, 120_000, "keys");
    // Object space, with the AO radius spanning the cuts.
    let text = std::fs::read_to_string(&config).unwrap();
    let text = text
        .replacen("[wall]\n", &format!("[wall]\nmode = \"object\"\ncompress = {compress}\n"), 1)
        .replacen("[render]\n", &format!("[render]\nao_radius = {AO_RADIUS}\n"), 1)
        .replacen("[render]\n", if denoise { "[render]\ndenoise = \"on\"\n" } else { "[render]\n" }, 1);
    std::fs::write(&config, text).unwrap();
    let cfg = config.to_str().unwrap();
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", cfg]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let out = run_in(
        dir.path(),
        "isowall",
        &["up", cfg, "--frames", "1", "--snapshot", "wall.png", "--start-timeout", "180"],
    );
    if !gpu_ok("isowall up (object space)", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let logs = || {
        (0..nodes)
            .map(|i| {
                std::fs::read_to_string(dir.path().join(format!("logs/node{i}.log"))).unwrap_or_default()
            })
            .collect::<Vec<_>>()
            .join("\n---\n")
    };
    assert!(
        stdout.contains(&format!("{nodes} of {nodes} tiles")),
        "{stdout}\n{}\n{}",
        String::from_utf8_lossy(&out.stderr),
        logs()
    );
    assert!(stdout.contains("object space"), "no object-space statistics:\n{stdout}");
    // Bricking reports its progress in each node's log (no terminal there, so no bar): both
    // passes, to the end.
    for i in 0..nodes {
        let log = std::fs::read_to_string(dir.path().join(format!("logs/node{i}.log"))).unwrap_or_default();
        for line in ["scanning the volume for the brick split: 100%", "reading the brick and its halo: 100%"]
        {
            assert!(log.contains(line), "node{i}'s log lacks '{line}':\n{log}");
        }
    }

    // The split every node computed, recomputed here from the model.
    let src: VolumeSource = VOLUME.parse().unwrap();
    let stream = src.stream(None).unwrap();
    let info = stream.info().clone();
    let blocks = stream.block_minmax(BlockMinMax::DEFAULT_BLOCK).unwrap();
    let iso = src.natural_iso().unwrap();
    let occ = Occupancy::from_minmax(blocks.block, blocks.counts, &blocks.minmax, iso);
    let split = bricks::split(&occ, info.dims, info.spacing, nodes).unwrap();
    let mut settings = RenderSettings::new(iso);
    settings.ao.radius = AoRadius::World(AO_RADIUS);
    let halo = bricks::halo_voxels(&settings, info.spacing).unwrap();

    // Resident volume bytes per node (reported to the controller) <= brick + halo (as f32), and
    // less than the whole volume.
    let whole_bytes = info.dims.iter().product::<usize>() * 4;
    for (i, b) in split.iter().enumerate() {
        let line = stdout
            .lines()
            .find(|l| l.trim_start().starts_with(&format!("node{i}: sent")))
            .unwrap_or_else(|| panic!("no object-space line for node{i}:\n{stdout}"));
        let resident: usize = line
            .split("resident volume ")
            .nth(1)
            .and_then(|r| r.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no resident bytes in {line:?}"));
        let bound = b.data_samples(halo, info.dims) * 4;
        eprintln!("node{i}: resident {resident} B, brick+halo {bound} B, whole volume {whole_bytes} B");
        assert!(resident <= bound, "node{i} holds {resident} B, more than its brick and halo ({bound} B)");
        assert!(resident < whole_bytes, "node{i} holds the whole volume");
    }

    // The single render of the whole wall image, with its depth.
    let wall_cfg = isowall_model::WallConfig::load(&config).unwrap();
    let (fw, fh) = wall_cfg.wall_size();
    let render = |aov: &str, out: &str, denoise: bool| {
        let radius = AO_RADIUS.to_string();
        let mut extra = vec!["--ao-radius", &radius, "--aov", aov, "--out", out];
        if denoise {
            extra.extend(["--denoise", "on"]);
        }
        assert!(gpu_ok("isowalld render", &render_whole(dir.path(), VOLUME, (fw, fh), 4, &extra)));
    };
    render("color", "whole.png", denoise);
    render("depth", "depth.pfm", false);
    let wall = image::open(dir.path().join("wall.png")).unwrap().to_rgb8();
    let whole = image::open(dir.path().join("whole.png")).unwrap().to_rgb8();
    assert_eq!(wall.dimensions(), (fw, fh));
    let depth = isowall_render::output::read_pfm(&dir.path().join("depth.pfm")).unwrap();
    let in_tile = |x: u32, y: u32| {
        wall_cfg.tiles.iter().any(|t| x >= t.x && x < t.x + t.width && y >= t.y && y < t.y + t.height)
    };

    // Pixels whose surface point lies within the AO radius of a cut plane.
    let cam = isowall_model::Camera {
        eye: DVec3::new(60.0, -70.0, 45.0),
        target: DVec3::splat(23.5),
        up: DVec3::Z,
        fov_y_deg: 40.0,
    };
    let view = isowall_model::View::whole(cam, fw, fh);
    let basis = cam.basis();
    let mut cuts: Vec<(usize, f64)> = Vec::new();
    for b in &split {
        for a in 0..3 {
            if b.hi[a] + 1 < info.dims[a] {
                cuts.push((a, b.hi[a] as f64));
            }
        }
    }
    assert!(!cuts.is_empty());
    let (mut compared, mut max_diff, mut sum_diff, mut lit) = (0u64, 0u8, 0u64, 0u64);
    let (mut near_cut, mut near_cut_max) = (0u64, 0u8);
    for y in 0..fh {
        for x in 0..fw {
            if !in_tile(x, y) {
                continue;
            }
            let (a, b) = (wall.get_pixel(x, y).0, whole.get_pixel(x, y).0);
            let d = (0..3).map(|c| a[c].abs_diff(b[c])).max().unwrap();
            compared += 1;
            max_diff = max_diff.max(d);
            sum_diff += (0..3).map(|c| a[c].abs_diff(b[c]) as u64).sum::<u64>();
            lit += u64::from(b.iter().map(|&v| v as u32).sum::<u32>() > 200);
            // PFM rows go bottom to top.
            let t = depth.data[((fh - 1 - y) * fw + x) as usize];
            if t > 0.0 {
                let p = cam.eye + view.ray_dir(&basis, x, y) * t as f64;
                if cuts.iter().any(|&(axis, c)| (p[axis] - c).abs() <= AO_RADIUS) {
                    near_cut += 1;
                    near_cut_max = near_cut_max.max(d);
                }
            }
        }
    }
    assert!(lit > 150, "the torus is hardly in view ({lit} lit pixels)");
    assert!(near_cut > 100, "only {near_cut} pixels see the surface near a cut");
    let mean = sum_diff as f64 / (3 * compared) as f64;
    eprintln!(
        "{nodes} nodes (compress {compress}): wall vs single render: max {max_diff} levels, mean {mean:.5}; \
         {near_cut} pixels near the cuts, max {near_cut_max}"
    );
    // Tolerance: one 8-bit level anywhere (as in screen space), mean < 0.01; in practice the
    // bricks reproduce the single render's steps and samples exactly (0 differences).
    assert!(max_diff <= 1 && mean < 0.01, "max {max_diff}, mean {mean}");
    assert!(near_cut_max <= 1, "pixels near the cuts differ by up to {near_cut_max}");
    if denoise {
        // The filter ran: the wall is off the unfiltered single render.
        render("color", "raw.png", false);
        let raw = image::open(dir.path().join("raw.png")).unwrap().to_rgb8();
        let moved = wall
            .pixels()
            .zip(raw.pixels())
            .map(|(a, b)| (0..3).map(|c| a.0[c].abs_diff(b.0[c])).max().unwrap())
            .max()
            .unwrap();
        eprintln!("{nodes} nodes, denoised: the filter moved the image by up to {moved} levels");
        assert!(
            moved >= 4,
            "the wall is within {moved} levels of the unfiltered render: did the filter run?"
        );
    }
}

#[test]
fn two_nodes_in_object_space_equal_the_single_render() {
    object_wall(2, true, false);
}

#[test]
fn four_nodes_in_object_space_equal_the_single_render_uncompressed() {
    object_wall(4, false, false);
}

#[test]
fn four_nodes_filtering_the_composited_tiles_equal_the_single_denoised_render() {
    object_wall(4, true, true);
}
