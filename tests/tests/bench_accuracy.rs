//! `isowalld bench accuracy` as a user runs it: a real process writing the CSV and the chart.

use isowall_e2e::{gpu_ok, run_in, shared_dir};

const COLUMNS: &str =
    "scene,method,samples,frames,step,ibl,ms,fetches_per_pixel,occlusion_rmse,occlusion_p99,color_rmse";

#[test]
fn quick_accuracy_bench_writes_csv_chart_and_budget_table() {
    // Run outside the checkout: the default scenes' relative `../shared/data` is found all the same.
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("acc");
    let mri = shared_dir().map(|_| "../shared/data/mri-brainsmall.nrrd@40");
    let scenes = ["procedural:sphere-over-plane:16", "missing-file.nrrd@3"]
        .into_iter()
        .chain(mri)
        .collect::<Vec<_>>()
        .join(",");
    let out = run_in(
        dir.path(),
        "isowalld",
        &[
            "bench",
            "accuracy",
            "--quick",
            "--scenes",
            &scenes,
            "--size",
            "32x32",
            "--out",
            out_dir.to_str().unwrap(),
        ],
    );
    if !gpu_ok("isowalld bench accuracy --quick", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    // The missing file is said once, at the start (before the GPU opens), naming where it was
    // looked for; the budget table is printed.
    let skip = format!(
        "skipping 1 of {} scenes, their files are not here: missing-file.nrrd is neither in",
        2 + mri.iter().count()
    );
    assert_eq!(stderr.matches("skipping").count(), 1, "{stderr}");
    let (Some(said), Some(gpu)) = (stderr.find(&skip), stderr.find("GPU device open")) else {
        panic!("missing `{skip}` or the GPU's log line:\n{stderr}");
    };
    assert!(said < gpu, "said only after the GPU opened:\n{stderr}");
    assert!(!stdout.contains("skipping"), "{stdout}");
    assert!(stdout.contains("| 10 ms | 30 ms | 100 ms |"), "{stdout}");
    assert!(
        stdout.contains("| sphere-over-plane | ours |") && stdout.contains("| sphere-over-plane | seed |")
    );

    let csv = std::fs::read_to_string(out_dir.join("accuracy.csv")).expect("accuracy.csv written");
    assert!(csv.contains("submit-to-done") && csv.contains("reference: GPU, ours exact"), "{csv}");
    let mut lines = csv.lines().filter(|l| !l.starts_with('#'));
    assert_eq!(lines.next(), Some(COLUMNS));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert!(rows.len() >= 10, "{csv}");
    for r in &rows {
        assert_eq!(r.len(), 11, "{r:?}");
        assert!(r[0] == "sphere-over-plane" || r[0] == "mri-brainsmall", "{r:?}");
        let num = |i: usize| r[i].parse::<f64>().unwrap_or_else(|_| panic!("column {i} of {r:?}"));
        assert!(num(6) > 0.0 && num(7) > 0.0, "{r:?}");
        for i in 8..11 {
            assert!(num(i).is_finite() && num(i) >= 0.0, "{r:?}");
        }
    }
    if mri.is_some() {
        assert!(rows.iter().any(|r| r[0] == "mri-brainsmall"), "the MRI was not measured:\n{csv}");
    }
    let rows: Vec<Vec<&str>> = rows.into_iter().filter(|r| r[0] == "sphere-over-plane").collect();
    for (method, ibl) in [("seed", "none"), ("ours", "none"), ("ours-stepped", "none"), ("ours", "rays")] {
        assert!(rows.iter().any(|r| r[1] == method && r[5] == ibl), "no {method}/{ibl} row:\n{csv}");
    }
    // Ours converges: at 64 samples its error is well below its error at 4.
    let ours = |n: &str| {
        rows.iter().find(|r| r[1] == "ours" && r[2] == n && r[3] == "1" && r[5] == "none").unwrap()[8]
            .parse::<f64>()
            .unwrap()
    };
    assert!(ours("64") < 0.7 * ours("4"), "{csv}");
    // The primary march on the filtered texture finds the same surface: at every sample count its
    // occlusion error is ours' (the same AO pattern over the same hits), its time on the chart.
    let texture: Vec<&Vec<&str>> = rows.iter().filter(|r| r[1] == "ours-texture").collect();
    assert_eq!(texture.len(), 3, "{csv}");
    for t in texture {
        let o = ours(t[2]);
        let e = t[8].parse::<f64>().unwrap();
        assert!((e - o).abs() <= 0.02 * o + 1e-4, "texture {e} against ours {o} at {} samples:\n{csv}", t[2]);
    }
    assert!(stdout.contains("| sphere-over-plane | ") && stdout.contains("(`ours-texture`)"), "{stdout}");

    let png = image::open(out_dir.join("chart.png")).expect("chart.png written").to_rgb8();
    assert!(png.width() >= 400 && png.height() >= 300);
    let svg = std::fs::read_to_string(out_dir.join("chart.svg")).expect("chart.svg written");
    assert!(svg.starts_with("<svg") && svg.contains("sphere over plane"));
    assert!(svg.contains("ours, texture march"), "the texture march's curve");
    assert!(out_dir.join("summary.txt").exists());
}
