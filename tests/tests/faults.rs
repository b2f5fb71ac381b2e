//! Faults on a running wall (screen space):
//! a node killed with SIGKILL is reported by name within two deadlines while the others go on, and
//! rejoins when restarted, on a plain wall and on a balanced one (`[wall] balance = true`: the
//! dead node's rows of other tiles are placed without it, the next split leaves it out, and it
//! gets its tiles back when it rejoins); the controller killed with SIGKILL leaves the daemons serving, and a new
//! controller drives them without a restart of theirs.

use isowall_e2e::{bin, free_udp_ports, run_in, start_nodes, wall_config, Daemon};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Starts `isowall orbit` with its stderr to `dir/NAME.err`, stdout to `dir/NAME.out`.
fn orbit(dir: &Path, config: &Path, name: &str, frames: u32, fps: u32) -> Child {
    let err = std::fs::File::create(dir.join(format!("{name}.err"))).unwrap();
    let out = std::fs::File::create(dir.join(format!("{name}.out"))).unwrap();
    Command::new(bin("isowall"))
        .arg("orbit")
        .arg(config)
        .args(["--frames", &frames.to_string(), "--fps", &fps.to_string(), "--degrees-per-frame", "2"])
        .stdout(out)
        .stderr(err)
        .stdin(Stdio::null())
        .spawn()
        .unwrap()
}

/// Waits until `file` contains `needle`; returns how long it took, or `None` after `timeout`.
fn wait_for(file: &Path, needle: &str, timeout: Duration) -> Option<Duration> {
    let start = Instant::now();
    while start.elapsed() < timeout {
        if std::fs::read_to_string(file).is_ok_and(|t| t.contains(needle)) {
            return Some(start.elapsed());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

#[test]
fn a_killed_node_is_reported_and_rejoins_when_restarted() {
    killed_node_is_reported_and_rejoins(false);
}

#[test]
fn on_a_balanced_wall_a_killed_node_loses_only_its_rows_and_rejoins_when_restarted() {
    killed_node_is_reported_and_rejoins(true);
}

fn killed_node_is_reported_and_rejoins(balance: bool) {
    let dir = tempfile::tempdir().unwrap();
    let deadline_ms = 2000;
    let config = wall_config(dir.path(), "kill", &free_udp_ports(4), 8, 6, 1, deadline_ms, "keys");
    if balance {
        let text = std::fs::read_to_string(&config).unwrap();
        std::fs::write(&config, text.replacen("[wall]\n", "[wall]\nbalance = true\n", 1)).unwrap();
    }
    assert!(run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()])
        .status
        .success());
    let Some(mut daemons) = start_nodes(dir.path(), &config, 4) else { return };
    let mut controller = orbit(dir.path(), &config, "orbit", 120, 10);
    let err = dir.path().join("orbit.err");
    if wait_for(&err, "up (4/4)", Duration::from_secs(60)).is_none() {
        panic!("the wall never had its 4 nodes up:\n{}", std::fs::read_to_string(&err).unwrap_or_default());
    }
    // Frames with all four nodes for a while, so that node1 dies in the middle of a running wall.
    std::thread::sleep(Duration::from_secs(2));
    // SIGKILL node1: it is named (as a straggler at the next deadline) within two deadlines, and
    // reported down once silent for 3 deadlines (or at the QUIC idle timeout, if sooner).
    daemons[1].child.kill().unwrap();
    let named = wait_for(&err, "without node1", Duration::from_millis(2 * deadline_ms + 500));
    let log = std::fs::read_to_string(&err).unwrap_or_default();
    let named = named.unwrap_or_else(|| panic!("node1 was not named within two deadlines:\n{log}"));
    let reported = wait_for(&err, "node node1 is down", Duration::from_secs(15))
        .unwrap_or_else(|| panic!("node1's death was not reported:\n{log}"));
    eprintln!(
        "death to report: named a straggler after {:.0} ms, reported down after {:.0} ms (3 deadlines of silence or the QUIC idle timeout, 5 s, whichever is first)",
        named.as_secs_f64() * 1e3,
        (named + reported).as_secs_f64() * 1e3
    );
    // Restart it: it rejoins.
    daemons[1] = Daemon::start(dir.path(), &config, "node1", &[]);
    assert!(
        daemons[1].wait_ready(Duration::from_secs(60)),
        "node1 did not restart:\n{}",
        daemons[1].log_text()
    );
    let back = wait_for(&err, "node node1 is back", Duration::from_secs(20)).unwrap_or_else(|| {
        panic!("node1 did not rejoin:\n{}", std::fs::read_to_string(&err).unwrap_or_default())
    });
    eprintln!("restart to rejoin: {:.0} ms", back.as_secs_f64() * 1e3);
    let status = controller.wait().unwrap();
    let out = std::fs::read_to_string(dir.path().join("orbit.out")).unwrap();
    let log = std::fs::read_to_string(&err).unwrap();
    // It renders the current state within 3 frames of rejoining: no swap after that goes without it.
    let rejoin: u64 = log
        .split("node node1 is back; it rejoins at frame ")
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no rejoin frame in:\n{log}"));
    let late: Vec<u64> = log
        .lines()
        .filter(|l| l.contains("swap released without") && l.contains("node1"))
        .filter_map(|l| l.split("frame ").nth(1)?.split(':').next()?.parse().ok())
        .filter(|&f| f >= rejoin + 3)
        .collect();
    assert!(late.is_empty(), "node1 rejoined at frame {rejoin} but missed frames {late:?}:\n{log}");
    let missed = log.lines().filter(|l| l.contains("swap released without") && l.contains("node1")).count();
    eprintln!("node1 missed {missed} swaps; rejoined at frame {rejoin} and made every swap from then on");
    assert!(status.success(), "the controller failed:\n{out}\n{log}");
    assert!(out.contains("frames: 120"), "the wall did not go on:\n{out}\n{log}");
    if balance {
        assert!(out.contains("balance (bytes of rectangles"), "the wall did not balance:\n{out}");
    }
    // The others were never reported.
    for other in ["node0", "node2", "node3"] {
        assert!(!log.contains(&format!("node {other} is down")), "{other} reported down:\n{log}");
    }
    // After the rejoin node1 renders again: its tile is in a snapshot of the current frame.
    let snap = run_in(dir.path(), "isowall", &["snapshot", config.to_str().unwrap(), "--out", "after.png"]);
    let text = String::from_utf8_lossy(&snap.stdout);
    let logs: Vec<String> = daemons.iter().map(|d| d.log_text()).collect();
    assert!(
        text.contains("4 of 4 tiles"),
        "{text}\n{}\n{}",
        String::from_utf8_lossy(&snap.stderr),
        logs.join("\n----\n")
    );
}

#[test]
fn a_killed_controller_leaves_the_daemons_serving_a_new_one() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config(dir.path(), "ctl", &free_udp_ports(4), 8, 6, 1, 3000, "keys");
    assert!(run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()])
        .status
        .success());
    let Some(mut daemons) = start_nodes(dir.path(), &config, 4) else { return };
    let mut first = orbit(dir.path(), &config, "first", 1000, 10);
    // Killed once it holds the nodes, so that their connections to it are what it leaves behind.
    let first_err = dir.path().join("first.err");
    if wait_for(&first_err, "up (4/4)", Duration::from_secs(60)).is_none() {
        panic!(
            "the first controller never had its 4 nodes up:\n{}",
            std::fs::read_to_string(&first_err).unwrap_or_default()
        );
    }
    first.kill().unwrap();
    let _ = first.wait();
    // A new controller at once: the daemons refuse it while the killed one's connection lives
    // (one controller at a time) and take it once that connection's idle timeout (5 s) has ended
    // it; `isowall` keeps trying meanwhile.
    let started = Instant::now();
    let out = run_in(dir.path(), "isowall", &["orbit", config.to_str().unwrap(), "--frames", "5"]);
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the second controller failed:\n{stdout}\n{stderr}");
    assert!(stdout.contains("frames: 5"), "{stdout}");
    eprintln!(
        "new controller after a killed one: 5 frames done {:.0} ms after its start",
        started.elapsed().as_secs_f64() * 1e3
    );
    for (i, d) in daemons.iter_mut().enumerate() {
        assert!(d.child.try_wait().unwrap().is_none(), "node{i} exited:\n{}", d.log_text());
    }
}
