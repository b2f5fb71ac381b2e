//! Soak: a 4-node local wall with tiny tiles runs many frames through `isowall up`, which samples
//! every process's resident memory and open descriptors once warm and at the end; neither may grow.
//! Screen space and object space (every node renders its brick for every tile and sends its pixels
//! to the other three each frame). CI runs 1,000 screen-space and 2,000 object-space frames (each
//! well under a minute on lavapipe); `ISOWALL_SOAK_FRAMES=10000` runs the long soak of both (10,000
//! frames each).
//!
//! The orbit turns 3.6 degrees a frame, so the two runs of frames the drift compares (100 frames
//! after warm-up, and the last 100) see the same views. Frame-time drift is printed, not asserted:
//! a shared 2-core machine's timing is too noisy to fail a build on.

use isowall_e2e::{free_udp_ports, gpu_ok, run_in, set_object_mode, wall_config};

/// Memory a process may gain between the warm sample and the end: allocator and driver caches
/// settle in the first frames; a leak of even 8 KiB a frame shows over 1,000 frames.
const RSS_SLACK_KIB: i64 = 6 * 1024;

/// Object-space frames in CI (the object soak's cost is kept near a minute on lavapipe).
const OBJECT_CI_FRAMES: u64 = 2000;

/// Runs `frames` frames of `config` through `isowall up` and checks the resource report: every one
/// of the `processes` sampled grew by at most [`RSS_SLACK_KIB`] and kept its descriptors.
fn soak(dir: &std::path::Path, config: &std::path::Path, frames: u64, processes: usize) {
    let c = config.to_str().unwrap();
    assert!(run_in(dir, "isowall", &["keygen", "--config", c]).status.success());
    let out =
        run_in(dir, "isowall", &["up", c, "--frames", &frames.to_string(), "--degrees-per-frame", "3.6"]);
    if !gpu_ok("isowall up", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}");
    assert!(stdout.contains(&format!("frames: {frames} ")), "not every frame completed:\n{stdout}");
    let lines: Vec<&str> = stdout.lines().filter(|l| l.contains("): rss ")).collect();
    assert_eq!(lines.len(), processes, "the controller and every node are sampled:\n{stdout}");
    for line in lines {
        // "  node0 (pid 12): rss 41.2 -> 41.3 MiB (+120 KiB), fds 12 -> 12"
        let name = line.split_whitespace().next().unwrap();
        let grew: i64 = line
            .split('(')
            .nth(2)
            .and_then(|s| s.split_whitespace().next())
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no growth in {line:?}"));
        let fds: Vec<usize> = line
            .rsplit("fds ")
            .next()
            .unwrap()
            .split(" -> ")
            .map(|s| s.trim().parse().unwrap_or_else(|_| panic!("fds in {line:?}")))
            .collect();
        assert!(grew <= RSS_SLACK_KIB, "{name} grew by {grew} KiB over {frames} frames: {line}");
        assert_eq!(fds[0], fds[1], "{name}'s open descriptors changed: {line}");
    }
}

/// Frames to run: `ISOWALL_SOAK_FRAMES`, else `ci`.
fn frames(ci: u64) -> u64 {
    std::env::var("ISOWALL_SOAK_FRAMES").ok().and_then(|v| v.parse().ok()).unwrap_or(ci)
}

#[test]
fn a_wall_soak_keeps_memory_and_descriptors_flat() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config(dir.path(), "soak", &free_udp_ports(4), 8, 6, 1, 10_000, "keys");
    soak(dir.path(), &config, frames(1000), 5);
}

/// Object space: every node also renders its brick for every tile and sends its pixels to the
/// other three over QUIC each frame (12 peer streams a frame), and composites what arrives.
#[test]
fn an_object_space_soak_keeps_memory_and_descriptors_flat() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config(dir.path(), "osoak", &free_udp_ports(4), 8, 6, 1, 10_000, "keys");
    set_object_mode(&config);
    soak(dir.path(), &config, frames(OBJECT_CI_FRAMES), 5);
}
