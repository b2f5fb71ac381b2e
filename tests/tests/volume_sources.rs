//! Volumes as users bring them, through the real binaries: a DICOM series (a folder of slices,
//! one series chosen among several), time steps (a glob of files, `--step`), and check-config
//! reading a DICOM folder's headers.

use glam::DVec3;
use isowall_e2e::{gpu_ok, run_in, shared_dir};
use isowall_volume::io::dicom_write::SeriesWriter;
use isowall_volume::Volume;
use std::path::Path;

/// Renders `volume` (extra arguments appended) to `out` in `dir`, small and without AO.
fn render(dir: &Path, volume: &str, iso: &str, out: &str, extra: &[&str]) -> Option<Vec<u8>> {
    let mut args = vec!["render", "--volume", volume, "--iso", iso, "--size", "48x36", "--out", out];
    args.extend_from_slice(extra);
    let o = run_in(dir, "isowalld", &args);
    if !gpu_ok(&format!("isowalld render --volume {volume}"), &o) {
        return None;
    }
    Some(std::fs::read(dir.join(out)).expect("the image was written"))
}

#[test]
fn the_ct_as_a_dicom_series_renders_exactly_as_its_nrrd() {
    let Some(shared) = shared_dir() else { return };
    let nrrd = shared.join("data/ct-cranium.nrrd");
    let ct = isowall_volume::io::load(&nrrd, None).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let series = dir.path().join("ct");
    SeriesWriter::new("1.2.826.0.1.3680043.10.20").write(&ct, &series).unwrap();
    // A second series in the same folder: the folder alone is ambiguous.
    let mut other = SeriesWriter::new("1.2.826.0.1.3680043.10.21");
    other.first_number = 1000;
    let small = Volume::new("s", [4, 4, 3], DVec3::ONE, DVec3::ZERO, vec![0.0; 48]).unwrap();
    other.write(&small, &series).unwrap();

    // The NRRD's header says right-anterior-superior, and the series is written with the
    // volume's orientation (rows towards the patient's right, columns anterior): the same
    // patient, so both open on the face by default and render the same pixels.
    let Some(want) = render(dir.path(), nrrd.to_str().unwrap(), "300", "nrrd.png", &[]) else { return };
    let o = run_in(dir.path(), "isowalld", &["render", "--volume", "ct", "--iso", "300", "--size", "48x36"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("holds 2 series"), "{err}");
    assert!(err.contains("1.2.826.0.1.3680043.10.20 (CT, 'isowall', 108 files)"), "{err}");
    let got =
        render(dir.path(), "ct", "300", "dicom.png", &["--series", "1.2.826.0.1.3680043.10.20"]).unwrap();
    assert!(got == want, "the DICOM series renders differently from the NRRD");
    // One file of the series names the series by itself.
    let got = render(dir.path(), "ct/slice_0050.dcm", "300", "file.png", &[]).unwrap();
    assert!(got == want, "one file of the series renders differently from the NRRD");
}

#[test]
fn the_ct_converted_to_ome_zarr_renders_exactly_as_its_nrrd_and_its_levels_within_a_limit() {
    let Some(shared) = shared_dir() else { return };
    let nrrd = shared.join("data/ct-cranium.nrrd");
    let dir = tempfile::tempdir().unwrap();
    let o =
        run_in(dir.path(), "isowalld", &["convert", nrrd.to_str().unwrap(), "ct.ome.zarr", "--chunk", "32"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        out.contains("4 levels (256x256x108, 128x128x54, 64x64x27, 32x32x14)")
            && out.contains("orientation RAS"),
        "{out}"
    );
    // Progress without a terminal: a line at every quarter.
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("isowalld convert: chunk") && err.contains("(100%)"), "{err}");
    // Level 0 is the NRRD, its orientation and placement kept: the same pixels, colour and depth.
    let Some(want) = render(dir.path(), nrrd.to_str().unwrap(), "300", "nrrd.png", &[]) else { return };
    let got = render(dir.path(), "ct.ome.zarr", "300", "zarr.png", &[]).unwrap();
    assert!(got == want, "the converted store renders differently from the NRRD");
    let depth = |volume: &str, out: &str| {
        let o = run_in(
            dir.path(),
            "isowalld",
            &[
                "render", "--volume", volume, "--iso", "300", "--size", "48x36", "--aov", "depth", "--out",
                out,
            ],
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        std::fs::read(dir.path().join(out)).unwrap()
    };
    assert!(depth(nrrd.to_str().unwrap(), "n.pfm") == depth("ct.ome.zarr", "z.pfm"), "depth differs");
    // Through the brick cache, the store read brick by brick within a GPU and a host budget:
    // every pixel is rendered with the bricks it reads at level 0, in passes over screen regions
    // where the pool cannot hold the whole view's, and the picture is the whole volume's, AO
    // included (the camera is given: the default frames the object's box at the resolution of
    // the min/max it has, bricks here, blocks of 8 held whole).
    let camera = ["--eye", "122,-300,80", "--target", "122,122,80", "--ao-samples", "4"];
    let whole = render(dir.path(), "ct.ome.zarr", "300", "whole.png", &camera).unwrap();
    let bricked = |gpu_mb: &str, out: &str| {
        let budgets = ["--gpu-budget-mb", gpu_mb, "--host-budget-mb", "16", "--out", out];
        let args = [
            &["render", "--volume", "ct.ome.zarr", "--iso", "300", "--size", "48x36"][..],
            &camera,
            &budgets,
        ];
        run_in(dir.path(), "isowalld", &args.concat())
    };
    // 2 MiB is a fourteenth of level 0's 28 MB: ray-guided rounds read only the bricks in front
    // of the first hits and their AO reach.
    for gpu_mb in ["64", "8", "2"] {
        let o = bricked(gpu_mb, "b.png");
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(
            o.status.success() && out.contains("ray-guided round(s) in"),
            "{out}{}",
            String::from_utf8_lossy(&o.stderr)
        );
        let one_pass = out.contains(" in 1 pass(es)");
        assert!(one_pass == (gpu_mb == "64"), "pools of 8 and 2 MiB need passes, one of 64 does not: {out}");
        assert!(
            std::fs::read(dir.path().join("b.png")).unwrap() == whole,
            "{gpu_mb} MiB: the picture differs: {out}"
        );
    }
    // A pool smaller than one pixel's bricks is refused with the budget that would do.
    let o = bricked("1", "c.png");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("raise the GPU budget to at least"), "{err}");
    // `info` reads a store's metadata, min/max and coarsest level only: within a limit far
    // below level 0's 28 MB it still tells level 0's grid and range.
    let o = run_in(dir.path(), "isowalld", &["info", "ct.ome.zarr", "--max-volume-bytes", "100000"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("dims: 256 x 256 x 108") && out.contains("of the coarsest level, `3`"), "{out}");
    let ct = isowall_volume::io::load(&nrrd, None).unwrap();
    let (lo, hi) = ct.value_range();
    assert!(out.contains(&format!("level 0's values: {lo} .. {hi}")), "{out}");
    // check-config holds a wall's iso to level 0's range from the store's min/max, even where
    // `[volume] max_bytes` would let it read only the coarsest level (whose means never reach
    // level 0's largest sample).
    let coarsest_max = isowall_volume::io::ome_zarr::OmeZarr::open(&dir.path().join("ct.ome.zarr"))
        .unwrap()
        .read_level(3, 0, &isowall_volume::io::VolumeLimit::default())
        .unwrap()
        .value_range()
        .1;
    assert!(coarsest_max < hi - 1.0, "{coarsest_max} {hi}");
    // `isowall check-config` of a one-node wall of the store with these `[volume]` lines.
    let check = |volume: &str| {
        let config = format!(
            "[wall]\nname = \"z\"\n\n[volume]\nsource = \"ct.ome.zarr\"\n{volume}\n\
             [[tiles]]\nname = \"t\"\nx = 0\ny = 0\nwidth = 64\nheight = 48\n\n\
             [[nodes]]\nname = \"n\"\naddress = \"127.0.0.1:7999\"\ntiles = [\"t\"]\n"
        );
        std::fs::write(dir.path().join("z.toml"), config).unwrap();
        run_in(dir.path(), "isowall", &["check-config", "z.toml"])
    };
    for (iso, ok) in [(300.0, true), (hi as f64 - 1.0, true), (hi as f64 + 10.0, false)] {
        let o = check(&format!("iso = {iso}\nmax_bytes = 100000\n"));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.success(), ok, "iso {iso}: {err}{}", String::from_utf8_lossy(&o.stdout));
        assert!(ok || err.contains("iso"), "{err}");
    }
    // `max_bytes` under every level: refused, unless the nodes read the store through their
    // brick caches (never whole): then its metadata and min/max are what is checked.
    for (budget, ok) in [("", false), ("gpu_budget_mb = 8\n", true)] {
        let o = check(&format!("iso = 300\nmax_bytes = 4\n{budget}"));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.success(), ok, "{budget:?}: {err}{}", String::from_utf8_lossy(&o.stdout));
        assert!(ok || err.contains("max_bytes"), "{err}");
    }
    // Under a limit below level 0, the finest level within it is read, and said.
    let o = run_in(
        dir.path(),
        "isowalld",
        &[
            "render",
            "--volume",
            "ct.ome.zarr",
            "--iso",
            "300",
            "--size",
            "48x36",
            "--max-volume-bytes",
            "4000000",
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success() && err.contains("reading level 1 (128x128x54"), "{err}");
    // Nothing is overwritten.
    let o = run_in(dir.path(), "isowalld", &["convert", nrrd.to_str().unwrap(), "ct.ome.zarr"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("nothing is overwritten"), "{err}");
}

/// A NRRD of a sphere of `radius` voxels in a 16^3 box.
fn sphere_nrrd(path: &Path, radius: f64) {
    let mut bytes =
        b"NRRD0004\ntype: float\ndimension: 3\nsizes: 16 16 16\nendian: little\nencoding: raw\n\n".to_vec();
    for k in 0..16 {
        for j in 0..16 {
            for i in 0..16 {
                let d = DVec3::new(i as f64, j as f64, k as f64) - DVec3::splat(7.5);
                bytes.extend(((radius - d.length()) as f32).to_le_bytes());
            }
        }
    }
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn render_step_n_of_a_glob_is_the_render_of_that_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("steps")).unwrap();
    for (k, r) in [3.0, 5.0, 7.0].iter().enumerate() {
        sphere_nrrd(&dir.path().join(format!("steps/step_{k:04}.nrrd")), *r);
    }
    let glob = "steps/step_*.nrrd";
    let Some(step1) = render(dir.path(), glob, "0", "glob1.png", &["--step", "1"]) else { return };
    let file1 = render(dir.path(), "steps/step_0001.nrrd", "0", "file1.png", &[]).unwrap();
    assert!(step1 == file1, "--step 1 of the glob differs from its second file");
    let step0 = render(dir.path(), glob, "0", "glob0.png", &[]).unwrap();
    assert!(step0 != step1, "steps 0 and 1 are different spheres");
    let o = run_in(dir.path(), "isowalld", &["render", "--volume", glob, "--iso", "0", "--step", "3"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("no time step 3: it matches 3 files"), "{err}");
}

#[test]
fn check_config_reads_a_dicom_folders_headers() {
    let dir = tempfile::tempdir().unwrap();
    // Six slices, so that with one removed the usual step is still the median.
    let v = Volume::new("v", [6, 5, 6], DVec3::new(0.5, 0.5, 2.0), DVec3::ZERO, vec![-1000.0; 180]).unwrap();
    let files = SeriesWriter::new("1.2.3.4.5").write(&v, &dir.path().join("series")).unwrap();
    let config = "[wall]\nname = \"d\"\n\n[volume]\nsource = \"series\"\nseries = \"1.2.3.4.5\"\n\n\
                  [[tiles]]\nname = \"t\"\nx = 0\ny = 0\nwidth = 64\nheight = 48\n\n\
                  [[nodes]]\nname = \"n\"\naddress = \"127.0.0.1:7999\"\ntiles = [\"t\"]\n";
    std::fs::write(dir.path().join("d.toml"), config).unwrap();
    let o = run_in(dir.path(), "isowall", &["check-config", "d.toml"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("volume: DICOM series 1.2.3.4.5 of 6x5x6 slices, spacing 0.5 0.5 2"), "{out}");
    // A missing slice: exit 1, naming the neighbours of the gap.
    std::fs::remove_file(&files[2]).unwrap();
    let o = run_in(dir.path(), "isowalld", &["check-config", "d.toml"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("d.toml: [volume] source:") && err.contains("a gap") && err.contains("slice_0001.dcm"),
        "{err}"
    );
}

#[test]
fn info_tells_a_volumes_grid_range_and_suggested_isos() {
    let dir = tempfile::tempdir().unwrap();
    let o = run_in(dir.path(), "isowalld", &["info", "procedural:sphere:16", "--bars", "4"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("dims: 16 x 16 x 16 (4096 voxels)"), "{out}");
    assert!(out.contains("orientation: none in the file"), "{out}");
    assert!(out.contains("0            the procedural volume's own surface"), "{out}");
    assert!(out.contains("two-class threshold (Otsu"), "{out}");
    assert_eq!(out.lines().filter(|l| l.starts_with("   ") && l.contains("..")).count(), 4, "{out}");
    let Some(shared) = shared_dir() else { return };
    let ct = shared.join("data/ct-cranium.nrrd");
    let o = run_in(dir.path(), "isowalld", &["info", ct.to_str().unwrap()]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("format: NRRD") && out.contains("dims: 256 x 256 x 108"), "{out}");
    assert!(out.contains("orientation: RAS (+x right, +y anterior, +z superior)"), "{out}");
    assert!(out.contains("values: -1024 .. 2986"), "{out}");
    // The skin of a head CT lies between air (-1000) and soft tissue (0-100); its bone above 200.
    let suggested = |what: &str| -> f64 {
        let line = out.lines().find(|l| l.contains(what)).unwrap_or_else(|| panic!("no {what}: {out}"));
        line.split_whitespace().next().unwrap().parse().unwrap()
    };
    let skin = suggested("two-class threshold");
    let bone = suggested("the upper one");
    assert!((-800.0..-100.0).contains(&skin) && (200.0..1000.0).contains(&bone), "{skin} {bone}");
    let o = run_in(dir.path(), "isowalld", &["info", "missing.nrrd"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("missing.nrrd"));
}
