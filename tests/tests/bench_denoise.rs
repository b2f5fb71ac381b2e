//! `isowalld bench denoise` as a user runs it, at a tiny size: a real process estimating the
//! independent reference, rendering raw and denoised frames, and writing the CSV and the chart.

use isowall_e2e::{gpu_ok, run_in};

const COLUMNS: &str =
    "scene,spp,denoise,ms_per_frame,occlusion_rmse,occlusion_p99,occlusion_bias,pixels,cpu_ms_per_frame";

#[test]
fn tiny_denoise_bench_writes_csv_and_chart_and_the_filter_lowers_the_error() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("den");
    let out = run_in(
        dir.path(),
        "isowalld",
        &[
            "bench",
            "denoise",
            "--scenes",
            "procedural:sphere-over-plane:32",
            "--size",
            "64x64",
            "--pixels",
            "20",
            "--samples",
            "1,4",
            "--repeats",
            "2",
            "--truth-directions",
            "16",
            "--known",
            "no-known-answers.json",
            "--out",
            out_dir.to_str().unwrap(),
        ],
    );
    if !gpu_ok("isowalld bench denoise", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("standard error <="), "{stdout}");
    let csv = std::fs::read_to_string(out_dir.join("denoise.csv")).expect("denoise.csv written");
    assert!(csv.contains("isowall-truth"), "{csv}");
    let mut lines = csv.lines().filter(|l| !l.starts_with('#'));
    assert_eq!(lines.next(), Some(COLUMNS));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 4, "spp 1 and 4, raw and denoised:\n{csv}");
    for r in &rows {
        assert_eq!(r.len(), 9, "{r:?}");
        let num = |i: usize| r[i].parse::<f64>().unwrap_or_else(|_| panic!("column {i} of {r:?}"));
        assert!(num(3) > 0.0 && num(3).is_finite(), "{r:?}");
        for i in 4..7 {
            assert!(num(i).is_finite(), "{r:?}");
        }
        assert!(num(4) >= 0.0 && num(5) >= 0.0 && num(4) <= 1.0, "{r:?}");
        let pixels = num(7);
        assert!((15.0..=20.0).contains(&pixels), "pixels compared: {r:?}");
        assert!(num(8) >= 0.0, "process CPU per frame: {r:?}");
    }
    let rmse = |spp: &str, den: &str| {
        rows.iter().find(|r| r[1] == spp && r[2] == den).unwrap_or_else(|| panic!("no {spp}/{den} row"))[4]
            .parse::<f64>()
            .unwrap()
    };
    assert!(rmse("4", "on") <= rmse("4", "off"), "denoised 4 spp is no closer to the estimate:\n{csv}");
    assert!(rmse("4", "off") < rmse("1", "off"), "raw error does not fall with samples:\n{csv}");
    let svg = std::fs::read_to_string(out_dir.join("chart.svg")).expect("chart.svg written");
    assert!(svg.starts_with("<svg") && svg.contains("denoised") && svg.contains("occlusion RMSE"));
}
