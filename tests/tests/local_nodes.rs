//! The local nodes of `isowall up` as an operator's tools end it: SIGTERM (`kill`, `timeout`, a
//! service manager), SIGHUP (a closed terminal) and SIGINT (`kill -INT`, not the terminal's
//! Ctrl-C, which reaches the nodes too) each stop the four `isowalld` children before the
//! controller exits; and a second `up` of a running wall fails without touching the running
//! nodes' logs.

use isowall_e2e::{bin, free_udp_ports, in_ci, run_in, wait_until, wall_config};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// A 2x2 wall of small tiles in `dir`, with its keys.
fn small_wall(dir: &Path) -> PathBuf {
    let config = wall_config(dir, "local", &free_udp_ports(4), 32, 24, 2, 20_000, "keys");
    let out = run_in(dir, "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    config
}

/// `isowall up CONFIG` driving frames for a long while (5 a second), its stderr in `dir/up.err`.
fn long_up(dir: &Path, config: &Path) -> Child {
    let err = std::fs::File::create(dir.join("up.err")).unwrap();
    Command::new(bin("isowall"))
        .current_dir(dir)
        .args(["up", config.to_str().unwrap(), "--frames", "1000000", "--fps", "5"])
        .env_remove("DISPLAY")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(err)
        .spawn()
        .expect("start isowall up")
}

/// Waits until `up`'s wall is up and returns its nodes' pids (from its `started node` lines);
/// `None` (skip) without a Vulkan adapter outside CI.
fn wait_up(dir: &Path, up: &mut Child) -> Option<Vec<u32>> {
    wait_said(dir, up, "wall up in")
}

/// [`wait_up`] for a command that says `marker` on its stderr once its wall is up.
fn wait_said(dir: &Path, up: &mut Child, marker: &str) -> Option<Vec<u32>> {
    let err = || std::fs::read_to_string(dir.join("up.err")).unwrap_or_default();
    // Up, or `up` ended (it says why in its stderr).
    wait_until("the wall up", Duration::from_secs(180), || {
        let text = err();
        if text.contains(marker) || up.try_wait().unwrap().is_some() {
            return Ok(());
        }
        Err(text.lines().last().unwrap_or_default().to_string())
    });
    let text = err();
    if !text.contains(marker) {
        if text.contains("no Vulkan adapter") && !in_ci() {
            eprintln!("skipping: no Vulkan adapter");
            return None;
        }
        panic!("the wall did not come up:\n{text}");
    }
    let pids: Vec<u32> = text
        .lines()
        .filter_map(|l| l.split("(pid ").nth(1)?.split([',', ')']).next()?.trim().parse().ok())
        .collect();
    assert_eq!(pids.len(), 4, "four local nodes started:\n{text}");
    Some(pids)
}

/// Whether process `pid` still runs (gone or a zombie is not running).
fn running(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|s| s.rsplit_once(')').and_then(|(_, r)| r.split_whitespace().next().map(str::to_owned)))
        .is_some_and(|state| state != "Z")
}

fn signal(pid: u32, name: &str) {
    let ok = Command::new("kill").args(["-s", name, &pid.to_string()]).status().unwrap().success();
    assert!(ok, "kill -s {name} {pid}");
}

#[test]
fn a_signal_to_up_stops_its_local_nodes_first() {
    for sig in ["TERM", "HUP", "INT"] {
        let dir = tempfile::tempdir().unwrap();
        let config = small_wall(dir.path());
        let mut up = long_up(dir.path(), &config);
        let Some(nodes) = wait_up(dir.path(), &mut up) else { return };
        assert!(nodes.iter().all(|&p| running(p)));
        signal(up.id(), sig);
        let status = wait_until(&format!("up to exit on SIG{sig}"), Duration::from_secs(30), || {
            up.try_wait().unwrap().ok_or_else(|| "still running".to_string())
        });
        let err = std::fs::read_to_string(dir.path().join("up.err")).unwrap_or_default();
        assert!(!status.success(), "SIG{sig}: up exited {status}");
        assert!(err.contains(&format!("SIG{sig}: stopped 4 local node(s)")), "SIG{sig}:\n{err}");
        let left: Vec<u32> = nodes.iter().copied().filter(|&p| running(p)).collect();
        assert!(left.is_empty(), "SIG{sig}: isowalld {left:?} still run after up exited:\n{err}");
    }
}

#[test]
fn a_second_up_of_a_running_wall_fails_and_keeps_its_nodes_logs() {
    let dir = tempfile::tempdir().unwrap();
    let config = small_wall(dir.path());
    let mut up = long_up(dir.path(), &config);
    let Some(nodes) = wait_up(dir.path(), &mut up) else { return };
    let log = dir.path().join("logs/node0.log");
    let before = std::fs::read_to_string(&log).unwrap();
    assert!(before.contains("ready on"), "{before}");
    let out = run_in(dir.path(), "isowall", &["up", config.to_str().unwrap(), "--frames", "1"]);
    assert!(!out.status.success(), "a second up of a running wall started");
    let after = std::fs::read_to_string(&log).unwrap();
    assert!(after.starts_with(&before), "the running node's log was rewritten:\n{after}");
    assert!(nodes.iter().all(|&p| running(p)), "the running wall's nodes were disturbed");
    signal(up.id(), "TERM");
    wait_until("up to exit", Duration::from_secs(30), || {
        up.try_wait().unwrap().ok_or_else(|| "running".to_string())
    });
    assert!(nodes.iter().all(|&p| !running(p)));
}

#[test]
fn a_session_into_a_pipe_writes_plain_lines_and_its_interrupt_stops_its_nodes() {
    let dir = tempfile::tempdir().unwrap();
    let config = small_wall(dir.path());
    let err = std::fs::File::create(dir.path().join("up.err")).unwrap();
    let mut session = Command::new(bin("isowall"))
        .current_dir(dir.path())
        .args(["session", config.to_str().unwrap(), "--local", "--no-joystick"])
        .env_remove("DISPLAY")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(err)
        .spawn()
        .expect("start isowall session");
    // Said once the wall is connected, the keyboard looked for.
    let Some(nodes) = wait_said(dir.path(), &mut session, "no terminal keyboard") else { return };
    // A few status lines' worth of frames, then the operator's interrupt.
    let mut stdout = session.stdout.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut text = String::new();
        std::io::Read::read_to_string(&mut stdout, &mut text).unwrap();
        text
    });
    std::thread::sleep(Duration::from_secs(3)); // the session's own pace: a status line a second
    signal(session.id(), "INT");
    wait_until("the session to end on SIGINT", Duration::from_secs(30), || {
        session.try_wait().unwrap().ok_or_else(|| "running".to_string())
    });
    let text = reader.join().unwrap();
    assert!(!text.contains('\r') && !text.contains('\u{1b}'), "terminal codes in a pipe: {text:?}");
    assert!(text.lines().any(|l| l.contains(" fps | slowest ")), "no status line: {text:?}");
    let left: Vec<u32> = nodes.iter().copied().filter(|&p| running(p)).collect();
    assert!(left.is_empty(), "isowalld {left:?} still run after the session ended");
}
