//! `isowalld bench imbalance` as a user runs it, on a tiny two-node wall: every node has its rows
//! in every frame, the shares of a frame add up to one, the slowest/mean ratios lie between 1 and
//! the node count, `--scale` shrinks the work and says by how much, and a bad config is named.

use isowall_e2e::{gpu_ok, run_in, wall_config_2x1};

/// The per node rows of a run: (frame, node, fetches, fetches_full, share_fetches, share_ms).
fn node_rows(stdout: &str) -> Vec<(String, String, u64, u64, f64, f64)> {
    stdout
        .lines()
        .filter(|l| l.starts_with("first,") || l.starts_with("still1,") || l.starts_with("orbit"))
        .filter(|l| l.split(',').count() == 11)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let num = |i: usize| f[i].parse::<f64>().unwrap_or_else(|_| panic!("field {i} of {l}"));
            (f[0].to_string(), f[1].to_string(), num(3) as u64, num(4) as u64, num(9), num(10))
        })
        .collect()
}

fn run_bench(dir: &std::path::Path, config: &str, scale: &str) -> Option<String> {
    let out = run_in(
        dir,
        "isowalld",
        &["bench", "imbalance", "--config", config, "--frames", "2", "--still", "1", "--scale", scale],
    );
    gpu_ok("isowalld bench imbalance", &out).then(|| String::from_utf8_lossy(&out.stdout).into_owned())
}

#[test]
fn every_node_has_its_share_of_every_frame_and_the_ratio_is_bounded() {
    let dir = tempfile::tempdir().unwrap();
    wall_config_2x1(dir.path(), "tiny", &[7400, 7401], 64, 48, 0, 4);
    let Some(full) = run_bench(dir.path(), "tiny.toml", "1") else { return };
    let rows = node_rows(&full);
    let frames = ["first", "still1", "orbit1", "orbit2"];
    assert_eq!(rows.len(), frames.len() * 2, "two nodes a frame:\n{full}");
    for frame in frames {
        let of: Vec<_> = rows.iter().filter(|r| r.0 == frame).collect();
        assert_eq!(of.iter().map(|r| r.1.as_str()).collect::<Vec<_>>(), ["node0", "node1"], "{frame}");
        let (fetch_share, ms_share): (f64, f64) =
            (of.iter().map(|r| r.4).sum(), of.iter().map(|r| r.5).sum());
        assert!((fetch_share - 1.0).abs() < 0.01 && (ms_share - 1.0).abs() < 0.01, "{frame}:\n{full}");
        assert!(of.iter().all(|r| r.3 == r.2), "scale 1 counts the full frame:\n{full}");
    }
    // The torus is seen by both tiles: both fetch.
    assert!(rows.iter().all(|r| r.2 > 0), "{full}");
    let last = full.lines().last().unwrap_or_default();
    let ratios: Vec<f64> = last
        .strip_prefix("imbalance: slowest/mean ")
        .unwrap_or_else(|| panic!("the summary line:\n{full}"))
        .split(|c: char| !(c.is_ascii_digit() || c == '.'))
        .filter_map(|w| w.parse().ok())
        .collect();
    assert_eq!(ratios.len(), 4, "{last}");
    assert!(ratios.iter().all(|r| (1.0..=2.0).contains(r)), "{last}");

    // At half the resolution per axis: about a quarter of the fetches, and the full frame's
    // estimate four times the measured count.
    let Some(half) = run_bench(dir.path(), "tiny.toml", "2") else { return };
    assert!(half.contains("1/2 resolution per axis") && half.contains("about 4x as many"), "{half}");
    let small = node_rows(&half);
    let (a, b): (u64, u64) = (rows.iter().map(|r| r.2).sum(), small.iter().map(|r| r.2).sum());
    assert!(b * 2 < a && b * 8 > a, "fetches {a} at scale 1, {b} at scale 2");
    assert!(small.iter().all(|r| r.3 == 4 * r.2), "{half}");
}

#[test]
fn a_config_that_cannot_be_read_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_in(dir.path(), "isowalld", &["bench", "imbalance", "--config", "missing.toml"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("missing.toml"), "{err}");
}
