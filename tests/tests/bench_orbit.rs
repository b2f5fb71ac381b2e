//! `isowalld bench orbit` as a user runs it, at a tiny size: a real process orbiting a scene in
//! every variant, its summary rows and the `--out` CSV. The reprojected history beats restarting,
//! the renderer spends a reprojected frame's samples by history (pixels take different numbers,
//! about the frame's on average) and the `uniform` ablation takes the frame's everywhere.

use isowall_e2e::{gpu_ok, run_in};

/// The summary rows of a run: variant -> (rmse, rmse_from, spp_from).
fn summary(stdout: &str) -> std::collections::BTreeMap<String, (f64, f64, f64)> {
    stdout
        .lines()
        .filter(|l| !l.starts_with('#') && l.split(',').count() == 8)
        .filter(|l| !l.starts_with("scene,"))
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let num = |i: usize| f[i].parse::<f64>().ok();
            Some((f[1].to_string(), (num(2)?, num(6)?, num(7)?)))
        })
        .collect()
}

#[test]
fn a_tiny_orbit_reports_every_variant_and_spends_samples_by_history() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("orbit.csv");
    let out = run_in(
        dir.path(),
        "isowalld",
        &[
            "bench",
            "orbit",
            "--scenes",
            "procedural:sphere-over-plane:32",
            "--size",
            "48x48",
            "--frames",
            "8",
            "--degrees",
            "3",
            "--from-frame",
            "4",
            "--reference-frames",
            "2",
            "--repeats",
            "1",
            "--out",
            csv.to_str().unwrap(),
        ],
    );
    if !gpu_ok("isowalld bench orbit", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let rows = summary(&stdout);
    for v in ["raw", "reprojected", "denoised", "reprojected+denoised", "raw32", "reprojected/uniform"] {
        assert!(rows.contains_key(v), "no row for {v}:\n{stdout}");
    }
    let (raw, reprojected, uniform) = (rows["raw"], rows["reprojected"], rows["reprojected/uniform"]);
    assert!(reprojected.1 < raw.1, "reprojected {reprojected:?} against raw {raw:?}");
    // Restarting and uniform take the frame's 4 samples; spent by history, the mean differs and
    // stays within the rule's bounds (1 to 16 at 4 a frame).
    assert_eq!((raw.2, uniform.2, rows["raw32"].2), (4.0, 4.0, 32.0), "{stdout}");
    assert!(reprojected.2 != 4.0 && (1.0..=16.0).contains(&reprojected.2), "{stdout}");
    let text = std::fs::read_to_string(&csv).expect("--out written");
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("scene,variant,frame,ms,occlusion_rmse,occlusion_p99,flicker,spp"));
    let reprojected_frames: Vec<Vec<&str>> =
        lines.map(|l| l.split(',').collect::<Vec<_>>()).filter(|f| f[1] == "reprojected").collect();
    assert_eq!(reprojected_frames.len(), 8, "{text}");
    // Frame 0 restarts (the frame's samples everywhere); the moving frames spend by history.
    let spp: Vec<f64> = reprojected_frames.iter().map(|f| f[7].parse().unwrap()).collect();
    assert_eq!(spp[0], 4.0, "{text}");
    assert!(spp[1..].iter().all(|&s| s != 4.0 && s >= 1.0), "{spp:?}");
}
