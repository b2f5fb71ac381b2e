//! The presenting thread ahead of the renderer, checked by structure, not by time: on a node that
//! may use real-time scheduling (root here and in CI), exactly one thread runs `SCHED_FIFO`, the
//! offscreen presenting thread, at the config's priority; it takes no CPU while it waits (no
//! spin outside a swap's last half millisecond); `present_priority = 0` leaves every thread
//! normal; and the node tells the controller which it is (the report's `presenting threads`).

use isowall_e2e::{free_udp_ports, in_ci, run_in, start_nodes, wait_until};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A one-node wall with `present` added to `[wall]`.
fn wall(dir: &Path, port: u16, present: &str) -> PathBuf {
    let s = format!(
        "[wall]\nname = \"rt\"\ndeadline_ms = 60000\n{present}\n\n\
         [camera]\neye = [60.0, -70.0, 45.0]\ntarget = [23.5, 23.5, 23.5]\nup = [0, 0, 1]\nfov_y = 40.0\n\n\
         [volume]\nsource = \"procedural:torus:32\"\n\n\
         [certificates]\ndir = \"keys\"\n\n\
         [[tiles]]\nname = \"t00\"\nx = 0\ny = 0\nwidth = 32\nheight = 24\n\n\
         [[nodes]]\nname = \"node0\"\naddress = \"127.0.0.1:{port}\"\ntiles = [\"t00\"]\n"
    );
    let path = dir.join("rt.toml");
    std::fs::write(&path, s).unwrap();
    let out = run_in(dir, "isowall", &["keygen", "--config", path.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    path
}

/// Each thread of `pid`: (name, scheduling policy, priority, utime + stime in clock ticks).
fn threads(pid: u32) -> Vec<(String, u32, u32, u64)> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(format!("/proc/{pid}/task")).unwrap().flatten() {
        let Ok(stat) = std::fs::read_to_string(e.path().join("stat")) else { continue };
        let (head, rest) = stat.rsplit_once(')').unwrap();
        let name = head.split_once('(').unwrap().1.to_string();
        // Fields after the name, from field 3 (state): utime 14, stime 15, rt_priority 40, policy 41.
        let f: Vec<&str> = rest.split_whitespace().collect();
        let at = |n: usize| f[n - 3].parse::<u64>().unwrap();
        out.push((name, at(41) as u32, at(40) as u32, at(14) + at(15)));
    }
    out
}

/// Whether a scheduling policy is a real-time one: SCHED_FIFO 1, SCHED_RR 2, SCHED_DEADLINE 6
/// (Mesa's shader-cache thread runs SCHED_IDLE, 3: below every other).
fn real_time(policy: u32) -> bool {
    matches!(policy, 1 | 2 | 6)
}

#[test]
fn only_the_presenting_thread_runs_real_time_and_it_does_not_spin_while_it_waits() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall(dir.path(), free_udp_ports(1)[0], "present_priority = 7");
    let Some(node) = start_nodes(dir.path(), &config, 1).and_then(|mut n| n.pop()) else { return };
    let pid = node.child.id();
    let log = node.log_text();
    if log.contains("real-time (SCHED_FIFO 7) was refused") {
        assert!(!in_ci(), "CI runs as root, where SCHED_FIFO is permitted:\n{log}");
        eprintln!("skipping: this process may not use SCHED_FIFO:\n{log}");
        return;
    }
    assert!(log.contains("the presenting thread runs SCHED_FIFO 7"), "{log}");
    let first = threads(pid);
    let fifo: Vec<_> = first.iter().filter(|t| real_time(t.1)).collect();
    assert_eq!(fifo.len(), 1, "exactly one real-time thread: {first:?}");
    assert_eq!((fifo[0].0.as_str(), fifo[0].1, fifo[0].2), ("presenter", 1, 7), "{first:?}");
    // Waiting for a swap that does not come: asleep, no CPU time.
    std::thread::sleep(Duration::from_secs(2)); // the span measured
    let later = threads(pid);
    let cpu = |ts: &[(String, u32, u32, u64)]| ts.iter().find(|t| t.0 == "presenter").map(|t| t.3).unwrap();
    assert!(
        cpu(&later) - cpu(&first) <= 1,
        "the presenting thread took {} ticks idle",
        cpu(&later) - cpu(&first)
    );
    // A wall driven: still exactly one, and the report says what each node's thread runs as.
    let out = run_in(dir.path(), "isowall", &["orbit", config.to_str().unwrap(), "--frames", "6"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("presenting threads: node0 SCHED_FIFO 7"), "{stdout}");
    let after = threads(pid);
    assert_eq!(after.iter().filter(|t| real_time(t.1)).count(), 1, "{after:?}");
}

#[test]
fn present_priority_0_leaves_every_thread_normal() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall(dir.path(), free_udp_ports(1)[0], "present_priority = 0");
    let Some(node) = start_nodes(dir.path(), &config, 1).and_then(|mut n| n.pop()) else { return };
    let ts = threads(node.child.id());
    assert!(ts.iter().all(|t| !real_time(t.1)), "{ts:?}");
    wait_until("the node's log", Duration::from_secs(10), || {
        let log = node.log_text();
        if log.contains("the presenting thread runs normal (present_priority = 0)") {
            Ok(())
        } else {
            Err(log)
        }
    });
}
