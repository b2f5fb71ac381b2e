//! Scripted demos: `isowall demo --record` on a small local 2x1
//! wall, run twice, writes the same files byte for byte (the frame clock is the frame index, the
//! sample patterns are seeded by pixel and frame, never the clock), and its frames are the moving
//! camera's (no two alike). A bad path is refused with FILE:LINE:COL before any node starts.

use isowall_e2e::{free_udp_ports, gpu_ok, run_in, wall_config_2x1};

const PATH: &str = "\
[[key]]\ntime = 0\neye = [45, -55, 35]\ntarget = [15.5, 15.5, 15.5]\nao_samples = 2\n\n\
[[key]]\ntime = 1\neye = [70, 15, 40]\ntarget = [15.5, 15.5, 15.5]\niso = 0.5\nao_samples = 4\n\n\
[[key]]\ntime = 2\neye = [45, 75, 35]\ntarget = [15.5, 15.5, 12]\nfov = 30\n";

#[test]
fn a_recorded_demo_is_the_same_file_for_file_every_time() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config_2x1(dir.path(), "demo", &free_udp_ports(2), 32, 24, 2, 2);
    std::fs::write(dir.path().join("path.toml"), PATH).unwrap();
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let mut runs = Vec::new();
    for run in ["a", "b"] {
        let out = run_in(
            dir.path(),
            "isowall",
            &[
                "demo",
                config.to_str().unwrap(),
                "--path",
                "path.toml",
                "--local",
                "--fps",
                "1.4",
                "--record",
                run,
            ],
        );
        if !gpu_ok("isowall demo", &out) {
            return;
        }
        let stdout = String::from_utf8_lossy(&out.stdout);
        // 2 s at 1.4 fps: frames at 0, 0.71 and 1.43 s.
        assert!(stdout.contains("wrote 3 frames"), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
        let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir.path().join(run))
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap())
            })
            .collect();
        files.sort();
        runs.push(files);
    }
    let names: Vec<&str> = runs[0].iter().map(|f| f.0.as_str()).collect();
    assert_eq!(names, ["frame-000000.png", "frame-000001.png", "frame-000002.png"]);
    assert_eq!(runs[0].len(), runs[1].len());
    for (a, b) in runs[0].iter().zip(&runs[1]) {
        assert_eq!(a.0, b.0);
        assert!(a.1 == b.1, "{} differs between two recorded runs", a.0);
    }
    // The whole wall (two 32x24 tiles and a 4-pixel mullion), and the camera moves.
    let images: Vec<image::RgbImage> =
        runs[0].iter().map(|f| image::load_from_memory(&f.1).unwrap().to_rgb8()).collect();
    assert_eq!(images[0].dimensions(), (68, 24));
    for i in 0..images.len() {
        for j in i + 1..images.len() {
            let differing = images[i].pixels().zip(images[j].pixels()).filter(|(p, q)| p != q).count();
            assert!(differing > 50, "frames {i} and {j} differ in only {differing} pixels");
        }
    }
}

#[test]
fn a_bad_camera_path_is_refused_with_file_line_and_column() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config_2x1(dir.path(), "demo", &free_udp_ports(2), 32, 24, 2, 2);
    std::fs::write(dir.path().join("path.toml"), PATH.replace("time = 2", "time = 0.5")).unwrap();
    let out =
        run_in(dir.path(), "isowall", &["demo", config.to_str().unwrap(), "--path", "path.toml", "--local"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("path.toml:14:1: key 3 (time 0.5): `time` must increase"), "{err}");
    assert!(!err.contains("started node"), "nodes were started for a bad path: {err}");
}
