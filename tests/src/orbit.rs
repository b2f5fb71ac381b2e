//! Driving a running wall from the tests: `isowall orbit` then `isowall snapshot`, with the
//! numbers the orbit's report prints (fps, barrier p50/p99), and pixel comparison of snapshots.

use crate::run_in;
use std::path::Path;

/// The number just before `unit` in `text` (`" fps)"` in "(12.3 fps)" gives 12.3).
pub fn number_before(text: &str, unit: &str) -> Option<f64> {
    let at = text.find(unit)?;
    text[..at].split_whitespace().last()?.trim_start_matches('(').parse().ok()
}

/// The number just after `key` in `text`.
pub fn number_after(text: &str, key: &str) -> Option<f64> {
    let at = text.find(key)? + key.len();
    text[at..].split_whitespace().next()?.parse().ok()
}

/// What an orbit's report says.
pub struct OrbitRun {
    pub fps: f64,
    pub barrier_p50_ms: f64,
    pub barrier_p99_ms: f64,
    /// The whole report (stdout).
    pub report: String,
}

/// `isowall orbit` of `frames` (3 degrees a frame) over `config`; asserts that every frame
/// completed.
pub fn orbit(dir: &Path, config: &Path, frames: u32) -> OrbitRun {
    let c = config.to_str().unwrap();
    let out =
        run_in(dir, "isowall", &["orbit", c, "--frames", &frames.to_string(), "--degrees-per-frame", "3"]);
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "orbit over {c} failed:\n{stdout}\n{stderr}");
    assert!(stdout.contains(&format!("frames: {frames} ")), "not every frame completed:\n{stdout}\n{stderr}");
    let barrier = stdout.lines().find(|l| l.starts_with("barrier")).unwrap_or_default();
    OrbitRun {
        fps: number_before(&stdout, " fps)").expect("fps in the report"),
        barrier_p50_ms: number_after(barrier, "p50").expect("barrier p50"),
        barrier_p99_ms: number_after(barrier, "p99").expect("barrier p99"),
        report: stdout.to_string(),
    }
}

/// [`orbit`], then `isowall snapshot` to `dir/png`; asserts the snapshot has all `tiles` tiles.
pub fn orbit_and_snapshot(dir: &Path, config: &Path, frames: u32, png: &str, tiles: usize) -> OrbitRun {
    let run = orbit(dir, config, frames);
    let c = config.to_str().unwrap();
    let out = run_in(dir, "isowall", &["snapshot", c, "--out", png]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains(&format!("{tiles} of {tiles} tiles")),
        "snapshot over {c}:\n{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    run
}
