//! A 2x1 wall in real windows: two nodes under one virtual X server
//! (Xvfb), each presenting its tile with wgpu (lavapipe) in a window placed at the tile's spot
//! (`--display window --windowed`). After a 2-frame `isowall demo`, a screenshot of the whole X screen
//! (`xwd -root`) must show, in both tiles' places, the last frame: each part equal to the same
//! part of a single render of that frame's camera, and not to the frame before it (another camera), so both screens show the same frame.
//! The same in object space, where each node renders a brick and a window must show its tile
//! composited from both nodes' bricks (not its own brick's part), with the filter off and on.
//!
//! Outside CI the test skips, with a message, where Xvfb or xwd is missing; under CI=true it must
//! run (`scripts/setup.sh` installs xvfb and x11-apps).

use isowall_e2e::x11::Xvfb;
use isowall_e2e::{free_udp_ports, run_in, set_object_mode, start_nodes_with, wall_config_2x1};
use std::time::{Duration, Instant};

/// A 2-frame demo at 1 fps: frame 0 shows the first key, frame 1 the second (the eye lower:
/// the torus is symmetric about +z, so an orbit would hardly change the image).
const EYES: [[f64; 3]; 2] = [[45.0, -55.0, 35.0], [50.0, -50.0, 5.0]];

/// How the wall of a run renders.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Space {
    Screen,
    /// Object space, the composited tiles filtered (`denoise`) or not.
    Object {
        denoise: bool,
    },
}

#[test]
fn both_tiles_of_a_2x1_wall_show_the_same_frame_on_screen() {
    show_the_last_frame(Space::Screen);
}

#[test]
fn both_tiles_of_a_2x1_object_space_wall_show_the_composited_frame_on_screen() {
    show_the_last_frame(Space::Object { denoise: false });
}

#[test]
fn both_tiles_of_a_2x1_object_space_wall_show_the_filtered_composited_frame_on_screen() {
    show_the_last_frame(Space::Object { denoise: true });
}

fn show_the_last_frame(space: Space) {
    let Some(xvfb) = Xvfb::start_with_xwd(320, 240) else { return };
    let dir = tempfile::tempdir().unwrap();
    let (w, h, bezel) = (48u32, 40u32, 2u32);
    let denoise = space == Space::Object { denoise: true };
    // The filter has something to do where there is occlusion.
    let samples = if denoise { 4 } else { 0 };
    let config = wall_config_2x1(dir.path(), "wall2x1", &free_udp_ports(2), w, h, bezel, samples);
    if let Space::Object { denoise } = space {
        set_object_mode(&config);
        if denoise {
            let text = std::fs::read_to_string(&config).unwrap();
            std::fs::write(&config, text.replacen("[render]\n", "[render]\ndenoise = \"on\"\n", 1)).unwrap();
        }
    }
    let cfg = config.to_str().unwrap();
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", cfg]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let windows = |_| ["--display", "window", "--windowed"].map(String::from).to_vec();
    let Some(daemons) = start_nodes_with(dir.path(), &config, 2, windows, Some(&xvfb.display)) else {
        return;
    };
    let path = format!(
        "[[key]]\ntime = 0\neye = {:?}\ntarget = [15.5, 15.5, 15.5]\n\n[[key]]\ntime = 1\neye = {:?}\ntarget = [15.5, 15.5, 15.5]\n",
        EYES[0], EYES[1]
    );
    std::fs::write(dir.path().join("path.toml"), path).unwrap();
    let out = run_in(dir.path(), "isowall", &["demo", cfg, "--path", "path.toml", "--fps", "1", "--unpaced"]);
    assert!(out.status.success(), "demo failed:\n{}", String::from_utf8_lossy(&out.stderr));

    // Single renders of the whole wall image (two tiles and the mullion) for frames 1 and 2.
    let (fw, fh) = (2 * w + 2 * bezel, h);
    let render = |k: usize, name: &str| {
        let e = EYES[k];
        let out = run_in(
            dir.path(),
            "isowalld",
            &[
                "render",
                "--volume",
                "procedural:torus:32",
                "--size",
                &format!("{fw}x{fh}"),
                "--eye",
                &format!("{:.15},{:.15},{:.15}", e[0], e[1], e[2]),
                "--target",
                "15.5,15.5,15.5",
                "--up",
                "0,0,1",
                "--fov-y",
                "40",
                "--ao-samples",
                &samples.to_string(),
                "--denoise",
                if denoise { "on" } else { "off" },
                "--ibl",
                "bent",
                "--env",
                "sky",
                "--out",
                name,
            ],
        );
        assert!(out.status.success(), "render: {}", String::from_utf8_lossy(&out.stderr));
        image::open(dir.path().join(name)).unwrap().to_rgb8()
    };
    let (last, before) = (render(1, "last.png"), render(0, "before.png"));
    let tile_x = [0u32, w + 2 * bezel];

    // How far the screen's part at `x0` is from `reference`'s: (pixels off by > 2 levels, max).
    let compare = |screen: &isowall_e2e::x11::Rgb, reference: &image::RgbImage, x0: u32| {
        let (mut off, mut max) = (0u32, 0u8);
        for y in 0..h {
            for x in 0..w {
                let a = screen.pixels[(y * screen.width + x0 + x) as usize];
                let b = reference.get_pixel(x0 + x, y).0;
                let d = (0..3).map(|c| a[c].abs_diff(b[c])).max().unwrap_or(0);
                max = max.max(d);
                off += u32::from(d > 2);
            }
        }
        (off, max)
    };
    for x0 in tile_x {
        let (off, _) = compare(
            &isowall_e2e::x11::Rgb { width: fw, height: fh, pixels: before.pixels().map(|p| p.0).collect() },
            &last,
            x0,
        );
        assert!(off > 50, "frames 1 and 2 differ in only {off} pixels of the tile at x={x0}: the test could not tell them apart");
    }
    // The windows show the swap a moment after it was reported: look until they do (20 s).
    let start = Instant::now();
    loop {
        let screen = xvfb.xwd(&["-root"]).unwrap();
        let results: Vec<((u32, u8), (u32, u8))> =
            tile_x.iter().map(|&x0| (compare(&screen, &last, x0), compare(&screen, &before, x0))).collect();
        let ok = results.iter().all(|((off, _), _)| *off <= (w * h) / 100);
        if ok {
            for (x0, ((off, max), (off_before, _))) in tile_x.iter().zip(&results) {
                eprintln!("tile at x={x0}: {off} pixels off the last frame (max {max} levels), {off_before} off the one before");
                assert!(*off_before > 50);
            }
            break;
        }
        if start.elapsed() > Duration::from_secs(20) {
            let img = image::RgbImage::from_fn(screen.width, screen.height, |x, y| {
                image::Rgb(screen.pixels[(y * screen.width + x) as usize])
            });
            let keep = std::env::temp_dir().join(format!("isowall-present-wall-{space:?}.png"));
            let _ = img.save(&keep);
            panic!(
                "the screen does not show the last frame in both tiles: {results:?} (pixels off, max) against \
                 (last, before); screenshot in {}\n{}\n{}",
                keep.display(),
                daemons[0].log_text(),
                daemons[1].log_text()
            );
        }
        std::thread::sleep(Duration::from_millis(250));
    }
}
