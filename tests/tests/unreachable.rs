//! Starting a wall: a node that cannot be reached is named, with
//! its address and the reason, as soon as the first attempt fails, and again when the
//! controller gives up. No GPU needed: nothing listens on the nodes' ports.

use isowall_e2e::{free_udp_ports, run_in, wall_config_2x1};

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
