//! Starting a wall: a node that cannot be reached is named, with
//! its address and the reason, as soon as the first attempt fails, and again when the
//! controller gives up. No GPU needed: nothing listens on the nodes' ports.

use isowall_e2e::{bin, free_udp_ports, run_in, wall_config_2x1};
use std::io::BufRead;
use std::process::{Command, Stdio};

#[test]
fn unreachable_nodes_are_named_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "gone", &ports, 16, 8, 0, 0);
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let out = run_in(dir.path(), "isowall", &["orbit", config.to_str().unwrap(), "--frames", "1"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    for (i, port) in ports.iter().enumerate() {
        let named = format!("cannot reach node node{i} (127.0.0.1:{port}): no answer; retrying");
        assert!(err.contains(&named), "missing `{named}` in:\n{err}");
    }
    assert!(err.contains("cannot reach 2 of 2 nodes after"), "{err}");
}

#[test]
fn logs_to_a_redirected_stderr_carry_no_colour_codes() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "plain", &ports, 16, 8, 0, 0);
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    // Trying to reach the nodes logs (rustls, at debug) at once; the first lines are enough.
    let mut child = Command::new(bin("isowall"))
        .current_dir(dir.path())
        .args(["orbit", config.to_str().unwrap(), "--frames", "1"])
        .env("RUST_LOG", "debug")
        .env_remove("NO_COLOR")
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .expect("isowall starts");
    let stderr = std::io::BufReader::new(child.stderr.take().unwrap());
    let mut seen = String::new();
    for line in stderr.lines().map_while(Result::ok) {
        seen.push_str(&line);
        seen.push('\n');
        if line.contains("DEBUG") {
            break;
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    assert!(seen.contains("DEBUG"), "no log line to check:\n{seen}");
    assert!(!seen.contains("\x1b["), "ANSI codes in a redirected stderr:\n{seen:?}");
}

/// A node's port held by another process: its daemon says the address is in use and exits at
/// once, and `isowall up` stops at once with that reason, instead of trying the address (where
/// the other process may answer) until its start timeout.
#[test]
fn a_local_nodes_port_in_use_stops_isowall_up_at_once_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "taken", &ports, 16, 8, 0, 0);
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    // QUIC is UDP: hold node0's port.
    let holder = std::net::UdpSocket::bind(("127.0.0.1", ports[0])).expect("the port is free");
    let started = std::time::Instant::now();
    let out = run_in(
        dir.path(),
        "isowall",
        &["up", config.to_str().unwrap(), "--frames", "1", "--start-timeout", "120"],
    );
    let took = started.elapsed();
    drop(holder);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(took < std::time::Duration::from_secs(30), "took {took:?} of a 120 s start timeout:\n{err}");
    let named = format!("cannot listen on 127.0.0.1:{}: the address is in use", ports[0]);
    assert!(err.contains("local node node0 exited") && err.contains(&named), "missing `{named}`:\n{err}");
    assert!(!err.contains("retrying"), "it tried the address:\n{err}");
}
