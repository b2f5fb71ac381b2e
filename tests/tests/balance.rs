//! Load-balanced screen space (`[wall] balance = true`) over real processes on loopback: a 2x2
//! wall whose split gives idle nodes rows of busy tiles shows exactly the unbalanced wall's
//! picture, and `isowall bench balance` measures the unbalanced and the balanced wall in one run.

use isowall_e2e::{free_udp_ports, gpu_ok, run_in, wall_config};
use std::path::{Path, PathBuf};

/// A 2x2 wall of 64x48 tiles (the torus in the top-left tile, the others sky), its
/// keys made; `balance` on or off, and `render` as the `[render]` section's keys.
fn wall(dir: &Path, name: &str, balance: bool, render: &str) -> PathBuf {
    let config = wall_config(dir, name, &free_udp_ports(4), 64, 48, 3, 120_000, "keys");
    let text = std::fs::read_to_string(&config).unwrap();
    let text = text
        .replacen("[wall]\n", &format!("[wall]\nbalance = {balance}\n"), 1)
        .replacen("eye = [60.0, -70.0, 45.0]", "eye = [45.0, -40.0, 40.0]", 1)
        .replacen("target = [23.5, 23.5, 23.5]", "target = [50.0, 35.0, 5.0]", 1)
        .replacen("ao_samples = 4\nibl = \"bent\"", render, 1);
    std::fs::write(&config, text).unwrap();
    if !dir.join("keys").exists() {
        let out = run_in(dir, "isowall", &["keygen", "--config", config.to_str().unwrap()]);
        assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    }
    config
}

/// The largest `sent p50 N B` of a report's per-node lines under `header`.
fn most_sent(report: &str, header: &str) -> u64 {
    let Some(at) = report.find(header) else { return 0 };
    report[at..]
        .lines()
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| isowall_e2e::orbit::number_after(l, "sent p50"))
        .fold(0.0f64, f64::max) as u64
}

#[test]
fn a_balanced_wall_shows_the_unbalanced_walls_picture_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    // Direct light only: a pixel is the same whatever frames came before it, so the pictures
    // must be equal bit for bit while the split moves rows between nodes (with AO, a rectangle
    // that changes node starts its history afresh: `docs/balance.md`).
    let render = "ao_samples = 0\nibl = \"none\"";
    let mut images = Vec::new();
    for balance in [false, true] {
        let config = wall(dir.path(), if balance { "balanced" } else { "unbalanced" }, balance, render);
        let png = format!("{}.png", if balance { "balanced" } else { "unbalanced" });
        let args =
            ["up", config.to_str().unwrap(), "--frames", "8", "--degrees-per-frame", "3", "--snapshot", &png];
        let out = run_in(dir.path(), "isowall", &args);
        if !gpu_ok("isowall up", &out) {
            return;
        }
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success() && stdout.contains("4 of 4 tiles"),
            "{stdout}\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        if balance {
            // Rows of a busy tile went to another node, and their pixels crossed.
            let sent = most_sent(&stdout, "balance (bytes of rectangles");
            // (an empty message is about 50 bytes; a row of sky compresses to a few).
            assert!(sent > 500, "no node sent rectangles of the torus:\n{stdout}");
            eprintln!("balanced: the most bytes of rectangles a node sent per frame (median): {sent}");
        }
        images.push(image::open(dir.path().join(&png)).unwrap().to_rgb8());
    }
    let (a, b) = (&images[0], &images[1]);
    assert_eq!(a.dimensions(), b.dimensions());
    let differing = a.pixels().zip(b.pixels()).filter(|(p, q)| p != q).count();
    let lit = a.pixels().filter(|p| p.0.iter().map(|&v| u32::from(v)).sum::<u32>() > 200).count();
    assert!(lit > 500, "the torus is in view: {lit} lit pixels");
    assert_eq!(differing, 0, "pixels that differ between the unbalanced and the balanced wall");
}

#[test]
fn bench_balance_measures_the_same_orbit_unbalanced_then_balanced() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall(dir.path(), "bench", false, "ao_samples = 2\nibl = \"bent\"");
    let args = ["bench", "balance", config.to_str().unwrap(), "--frames", "8", "--degrees-per-frame", "2"];
    let out = run_in(dir.path(), "isowall", &args);
    if !gpu_ok("isowall bench balance", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let last = stdout.lines().last().unwrap_or_default();
    let unbalanced = isowall_e2e::orbit::number_after(last, "balance: slowest/mean");
    let balanced =
        last.split(", ").nth(1).and_then(|s| s.split_whitespace().next()).and_then(|s| s.parse::<f64>().ok());
    let (Some(u), Some(b)) = (unbalanced, balanced) else { panic!("no balance line at the end:\n{stdout}") };
    eprintln!("{last}");
    // The config itself is left unbalanced; the bench balances its own copy.
    assert!(std::fs::read_to_string(&config).unwrap().contains("balance = false"));
    assert!(u > 1.2, "the off-centre torus loads one node most: {u}\n{stdout}");
    assert!(b < u - 0.1 && b <= 1.15, "balanced {b} against unbalanced {u}\n{stdout}");
    assert!(
        stdout.contains("== balanced")
            && most_sent(&stdout[stdout.find("== balanced").unwrap()..], "== balanced") > 0
    );
}
