//! Presentation in windows: a one-node wall under a virtual X server
//! (Xvfb) with `isowalld run --display window --windowed`. After two frames the tile's window, as
//! an X screenshot (`xwd`) shows it, must hold exactly the tile's image: the one the node's
//! snapshot returns.
//!
//! Outside CI the test skips, with a message, where Xvfb or xwd is missing (`scripts/test.sh` has
//! `scripts/setup.sh` install them: packages xvfb and x11-apps); under CI=true it must run.

use isowall_e2e::x11::Xvfb;
use isowall_e2e::{free_udp_ports, run_in, start_nodes_with};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A one-node wall of one `w`x`h` tile named t00 (the torus, fixed camera, no AO: quick).
fn one_tile_wall(dir: &Path, port: u16, w: u32, h: u32) -> PathBuf {
    let s = format!(
        "[wall]\nname = \"present\"\ndeadline_ms = 60000\n\n\
         [camera]\neye = [60.0, -70.0, 45.0]\ntarget = [23.5, 23.5, 23.5]\nup = [0, 0, 1]\nfov_y = 40.0\n\n\
         [volume]\nsource = \"procedural:torus:48\"\n\n\
         [certificates]\ndir = \"keys\"\n\n\
         [[tiles]]\nname = \"t00\"\nx = 0\ny = 0\nwidth = {w}\nheight = {h}\n\n\
         [[nodes]]\nname = \"node0\"\naddress = \"127.0.0.1:{port}\"\ntiles = [\"t00\"]\n"
    );
    let path = dir.join("present.toml");
    std::fs::write(&path, s).unwrap();
    path
}

#[test]
fn a_window_shows_the_presented_tile_exactly() {
    let Some(xvfb) = Xvfb::start_with_xwd(320, 240) else { return };
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (64u32, 48u32);
    let config = one_tile_wall(dir.path(), free_udp_ports(1)[0], w, h);
    let cfg = config.to_str().unwrap();
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", cfg]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));

    let windows = |_| ["--display", "window", "--windowed"].map(String::from).to_vec();
    let Some(mut daemons) = start_nodes_with(dir.path(), &config, 1, windows, Some(&xvfb.display)) else {
        return;
    };
    let daemon = &mut daemons[0];
    let log = daemon.log_text();
    assert!(log.contains(&format!("presenting tile t00 {w}x{h}")), "no window for t00:\n{log}");

    let out = run_in(dir.path(), "isowall", &["orbit", cfg, "--frames", "2"]);
    assert!(
        out.status.success(),
        "orbit failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let out = run_in(dir.path(), "isowall", &["snapshot", cfg, "--out", "snap.png"]);
    assert!(out.status.success(), "snapshot failed: {}", String::from_utf8_lossy(&out.stderr));
    let snap = image::open(dir.path().join("snap.png")).unwrap().to_rgb8();
    assert_eq!(snap.dimensions(), (w, h));
    let lit = snap.pixels().filter(|p| p.0.iter().map(|&v| v as u32).sum::<u32>() > 200).count();
    assert!(lit > 100, "the torus is hardly in view in the snapshot ({lit} lit pixels)");

    // The present reaches the X server a moment after the node reported it: look until the
    // window shows the frame (or give up after 20 s and report what it shows).
    let title = "isowall present: t00 (node0)";
    let start = Instant::now();
    let (max_diff, shot) = loop {
        let shot = xvfb.xwd(&["-name", title]).unwrap_or_else(|e| panic!("{e}\n{}", daemon.log_text()));
        assert_eq!((shot.width, shot.height), (w, h), "the window is not the tile's size");
        let max_diff = shot
            .pixels
            .iter()
            .zip(snap.pixels())
            .map(|(a, b)| (0..3).map(|c| a[c].abs_diff(b.0[c])).max().unwrap_or(0))
            .max()
            .unwrap_or(0);
        if max_diff <= 1 || start.elapsed() > Duration::from_secs(20) {
            break (max_diff, shot);
        }
        std::thread::sleep(Duration::from_millis(250));
    };
    eprintln!("window vs snapshot: max difference {max_diff} levels");
    if max_diff > 1 {
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb(shot.pixels[(y * w + x) as usize]));
        let keep = std::env::temp_dir().join("isowall-present-window.png");
        let _ = img.save(&keep);
        panic!(
            "the window does not show the tile (max difference {max_diff} levels; screenshot in {}):\n{}",
            keep.display(),
            daemon.log_text()
        );
    }
}
