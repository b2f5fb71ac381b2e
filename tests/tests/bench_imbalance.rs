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

/// `--bands`: every tile also rendered as bands of rows, each its own view; the CSV has every
/// frame's bands of every tile, and a node's bands add up to what its tiles fetched whole (the
/// same rays, cut into rectangles: what a balanced node renders costs what the whole tile did).
#[test]
fn bands_of_a_tile_cost_what_the_tile_did() {
    let dir = tempfile::tempdir().unwrap();
    wall_config_2x1(dir.path(), "tiny", &[7402, 7403], 64, 48, 0, 4);
    let args = ["bench", "imbalance", "--config", "tiny.toml", "--frames", "2", "--still", "1"];
    let out =
        run_in(dir.path(), "isowalld", &[&args[..], &["--bands", "4", "--bands-out", "bands.csv"]].concat());
    if !gpu_ok("isowalld bench imbalance --bands", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let csv = std::fs::read_to_string(dir.path().join("bands.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("frame,tile,node,width,height,band,pixels_full,fetches_full"));
    let bands: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(bands.len(), 4 * 2 * 4, "4 frames x 2 tiles x 4 bands:\n{csv}");
    for (frame, node, fetches, _, _, _) in node_rows(&stdout) {
        let of: Vec<&Vec<&str>> = bands.iter().filter(|b| b[0] == frame && b[2] == node).collect();
        assert_eq!(of.len(), 4, "{frame} {node}");
        let sum: u64 = of.iter().map(|b| b[7].parse::<u64>().unwrap()).sum();
        let pixels: u64 = of.iter().map(|b| b[6].parse::<u64>().unwrap()).sum();
        assert_eq!((sum, pixels), (fetches, 64 * 48), "{frame} {node}:\n{csv}");
    }
    // Without --bands-out, --bands is refused before anything renders.
    let out = run_in(dir.path(), "isowalld", &[&args[..], &["--bands", "4"]].concat());
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--bands-out"));
}
