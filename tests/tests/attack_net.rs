//! Attacks on the wall's network, made as a hostile peer on loopback would make them: the real
//! `isowalld` and `isowall` as processes, and real QUIC clients (or a node played by the test)
//! holding the wall's own certificates. One test per kind of attack; each says what the wall must
//! do, fails when it does not, and prints what the attacker achieved (`--nocapture`).
//!
//! - identities: node names that differ only in case are refused by `check-config` and `keygen`;
//!   a CA-signed certificate named `Controller` does not drive a node, one named `NODE1` does not
//!   pass for `node1`;
//! - take-over: a node's certificate, retrying, never knocks the running controller off, nor
//!   does a controller's connection that sends no Hello, nor a second controller (refused with
//!   the reason while the first drives; the next one is served once the first has left); a
//!   controller that says Bye is closed by the node at once, so a lost close holds nothing; a reconnect flood is refused before its
//!   TLS handshakes (per source address) and the wall keeps its frame rate;
//! - bincode limits: messages of every size around 4, 16 and 64 KiB reach the daemon;
//! - limits: connections per identity, streams and flow-control limits, snapshot tiles checked
//!   against their node, a node's reason escaped before the terminal sees it; a node's flood of
//!   unsolicited messages and forged times prints a few lines and stays out of the skew report;
//! - start: a wall with one of four nodes down starts (`orbit`, `up`) and the node joins when it
//!   comes up; in either space a killed node is down within 3 deadlines.

use isowall_e2e::fake_node::{self, runtime, FakeNode};
use isowall_e2e::{
    bin, free_udp_ports, in_ci, run_in, set_object_mode, start_nodes, wait_until, wall_config,
    wall_config_2x1, Daemon,
};
use isowall_model::codec;
use isowall_model::messages::{Message, Role, TileImage};
use isowall_model::node_machine::NodeOutput;
use isowall_net::transport::{self, Channel};
use isowall_net::Identity;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn keygen(dir: &Path, config: &Path) {
    let out = run_in(dir, "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
}

fn addr(port: u16) -> SocketAddr {
    format!("127.0.0.1:{port}").parse().unwrap()
}

/// A process killed when dropped, its stderr in a file.
struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `isowall ARGS...` in `dir` in the background, stdout and stderr to `dir/NAME.out|err`.
fn spawn_isowall(dir: &Path, name: &str, args: &[&str]) -> (Proc, PathBuf, PathBuf) {
    let (out, err) = (dir.join(format!("{name}.out")), dir.join(format!("{name}.err")));
    let child = Command::new(bin("isowall"))
        .current_dir(dir)
        .args(args)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::fs::File::create(&err).unwrap())
        .spawn()
        .unwrap();
    (Proc(child), out, err)
}

fn text(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

/// Waits until `file` holds `needle`; how long that took, or `None` after `timeout`.
fn wait_for(file: &Path, needle: &str, timeout: Duration) -> Option<Duration> {
    let start = Instant::now();
    while start.elapsed() < timeout {
        if text(file).contains(needle) {
            return Some(start.elapsed());
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    None
}

/// The resident set of a process in KiB.
fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("/proc/PID/status");
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).expect("VmRSS");
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

/// Starts the daemons `node0..count` (`None`: no Vulkan adapter outside CI, skip).
fn nodes(dir: &Path, config: &Path, count: usize) -> Option<Vec<Daemon>> {
    start_nodes(dir, config, count)
}

/// Writes `out/NAME.pem|key` (and `ca.pem`): a certificate the wall's CA (`keys/ca.*`, wall
/// `wall`) signs for the DNS name `dns`, the way any keygen that let such a name through would.
fn forge(keys: &Path, wall: &str, dns: &str, out: &Path, file_name: &str) {
    use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair, KeyUsagePurpose};
    std::fs::create_dir_all(out).unwrap();
    std::fs::copy(keys.join("ca.pem"), out.join("ca.pem")).unwrap();
    let ca_key = KeyPair::from_pem(&text(&keys.join("ca.key"))).unwrap();
    // The CA as keygen describes it: the same subject, so the chain links by name and key.
    let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.distinguished_name.push(DnType::CommonName, format!("Isowall wall CA: {wall}"));
    ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::DigitalSignature];
    let issuer = Issuer::new(ca, ca_key);
    let key = KeyPair::generate().unwrap();
    let mut params = CertificateParams::new(vec![dns.to_string()]).unwrap();
    params.distinguished_name.push(DnType::CommonName, dns);
    let cert = params.signed_by(&key, &issuer).unwrap();
    std::fs::write(out.join(format!("{file_name}.pem")), cert.pem()).unwrap();
    std::fs::write(out.join(format!("{file_name}.key")), key.serialize_pem()).unwrap();
    // Private keys are loaded only when no one but their owner may read them.
    {
        use std::os::unix::fs::PermissionsExt;
        let p = out.join(format!("{file_name}.key"));
        std::fs::set_permissions(p, std::fs::Permissions::from_mode(0o600)).unwrap();
    }
}

/// The application close reason of `conn` once the daemon closes it, or how it ended otherwise.
async fn closed(conn: &quinn::Connection, within: Duration) -> String {
    match tokio::time::timeout(within, conn.closed()).await {
        Ok(quinn::ConnectionError::ApplicationClosed(c)) => String::from_utf8_lossy(&c.reason).into_owned(),
        Ok(other) => format!("(no reason: {other})"),
        Err(_) => "(still open)".into(),
    }
}

/// As the controller would: connects to node `node` at `at`, opens the channel, says Hello.
async fn hello_as_controller(
    endpoint: &quinn::Endpoint,
    at: SocketAddr,
    node: &str,
) -> Result<Channel, String> {
    let conn = transport::connect(endpoint, at, node).await.map_err(|e| e.to_string())?;
    let opened = async {
        let mut ch = Channel::open(conn.clone(), node, 64 << 20).await.map_err(|e| e.to_string())?;
        ch.sender
            .send(&codec::hello(isowall_net::tls::CONTROLLER, Role::Controller))
            .await
            .map_err(|e| e.to_string())?;
        Ok(ch)
    };
    match opened.await {
        Ok(ch) => Ok(ch),
        // Where the node's close overtakes the channel's opening or the Hello, the send sees
        // only the connection lost: the node's close reason, where it gave one, says why.
        Err(lost) => {
            let reason = closed(&conn, Duration::from_secs(1)).await;
            Err(if reason.starts_with('(') { lost } else { reason })
        }
    }
}

// ---- 1: identities ------------------------------------------------------------------------------

#[test]
fn names_equal_without_regard_to_case_are_refused_and_no_node_certificate_is_the_controller() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let config = wall_config(dir.path(), "names", &ports, 16, 12, 2, 5000, "keys");
    let good = text(&config);
    // (a) check-config and keygen refuse `Controller` and `NODE0` beside `node0`, writing nothing.
    for (from, to, says) in [
        ("name = \"node1\"", "name = \"Controller\"", "node name 'Controller' is reserved"),
        (
            "name = \"node1\"",
            "name = \"NODE0\"",
            "duplicate node name 'NODE0' (the same as 'node0' without regard to case)",
        ),
    ] {
        let bad = dir.path().join("bad.toml");
        std::fs::write(&bad, good.replacen(from, to, 1).replace("keys", "bad-keys")).unwrap();
        let out = run_in(dir.path(), "isowall", &["check-config", bad.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&out.stderr).into_owned() + &String::from_utf8_lossy(&out.stdout);
        assert!(!out.status.success() && err.contains(says), "check-config accepted `{to}`:\n{err}");
        let out = run_in(dir.path(), "isowall", &["keygen", "--config", bad.to_str().unwrap()]);
        assert!(!out.status.success(), "keygen accepted `{to}`");
        assert!(!dir.path().join("bad-keys/ca.pem").exists(), "keygen wrote a CA for `{to}`");
        eprintln!("`{to}`: refused by check-config and keygen");
    }
    // (b) Certificates the wall CA signed for such names, on a running wall.
    keygen(dir.path(), &config);
    let keys = dir.path().join("keys");
    let forged = dir.path().join("forged");
    forge(&keys, "names", "Controller", &forged, "controller");
    forge(&keys, "names", "NODE1", &forged, "node1");
    let Some(_daemons) = nodes(dir.path(), &config, 1) else { return };
    let rt = runtime();
    let reason = rt.block_on(async {
        let endpoint = transport::client(&Identity::load(&forged, "controller").unwrap()).unwrap();
        // The node may refuse it before the Hello is sent (its identity is checked first): then
        // the refusal is the error of the handshake, or the close reason.
        let ch = match hello_as_controller(&endpoint, addr(ports[0]), "node0").await {
            Ok(ch) => ch,
            Err(refused) => return refused,
        };
        let first = tokio::time::timeout(Duration::from_secs(5), async {
            let mut r = ch.receiver;
            r.recv().await
        })
        .await;
        assert!(
            !matches!(first, Ok(Ok(Some(_)))),
            "node0 answered a certificate named `Controller`: {first:?}"
        );
        closed(&ch.connection, Duration::from_secs(5)).await
    });
    eprintln!("a certificate named `Controller` as the controller: closed with \"{reason}\"");
    assert!(reason.contains("node `Controller`'s certificate is not the controller's"), "{reason}");
    // (c) `NODE1` serving on node1's address: the controller does not take it for node1.
    let fake = rt.spawn(fake_node(forged.clone(), "node1".into(), ports[1], vec![], Act::Honest));
    let out = run_in(dir.path(), "isowall", &["snapshot", config.to_str().unwrap(), "--out", "s.png"]);
    fake.abort();
    let err = String::from_utf8_lossy(&out.stderr);
    eprintln!("{err}");
    assert!(err.contains("its certificate is node `NODE1`'s, not node `node1`'s"), "{err}");
    // The real controller certificate still drives node0 (the wall starts with the node it has).
    assert!(out.status.success(), "snapshot with node0 failed:\n{err}");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("wrote") && stdout.contains("of 4 tiles"), "{stdout}");
}

// ---- 2: identity before take-over ----------------------------------------------------------------

#[test]
fn a_node_certificate_or_a_silent_controller_never_disturbs_the_running_session() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let config = wall_config(dir.path(), "takeover", &ports, 16, 12, 2, 5000, "keys");
    keygen(dir.path(), &config);
    let Some(_daemons) = nodes(dir.path(), &config, 4) else { return };
    let keys = dir.path().join("keys");
    let (mut orbit, out, err) =
        spawn_isowall(dir.path(), "orbit", &["orbit", config.to_str().unwrap(), "--frames", "100000"]);
    // Every node up (they come up in any order: the last one says 4/4).
    assert!(wait_for(&err, "up (4/4)", Duration::from_secs(60)).is_some(), "{}", text(&err));
    let rt = runtime();
    let started = Instant::now();
    let (attempts, reasons, silent) = rt.block_on(async {
        let node = transport::client(&Identity::load(&keys, "node1").unwrap()).unwrap();
        let controller = transport::client(&Identity::load(&keys, "controller").unwrap()).unwrap();
        // A controller's connection that never opens its stream: it must not take over either.
        let silent = transport::connect(&controller, addr(ports[0]), "node0").await.unwrap();
        let mut reasons = std::collections::BTreeSet::new();
        let mut attempts = 0;
        // An attacker with node1's certificate retrying against node0 for 10 s.
        while started.elapsed() < Duration::from_secs(10) {
            attempts += 1;
            match hello_as_controller(&node, addr(ports[0]), "node0").await {
                Ok(ch) => reasons.insert(closed(&ch.connection, Duration::from_secs(5)).await),
                Err(e) => reasons.insert(e),
            };
        }
        (attempts, reasons, closed(&silent, Duration::from_secs(1)).await)
    });
    // The orbit runs on a moment past the attack's last connection before it is stopped, so that
    // what that connection did to it has reached its log.
    std::thread::sleep(Duration::from_millis(500));
    let _ = orbit.0.kill();
    let _ = orbit.0.wait();
    let stderr = text(&err);
    let downs = stderr.matches(" is down").count();
    let stragglers = stderr.matches("swap released without").count();
    eprintln!(
        "{attempts} attempts with node1's certificate in {:.1} s; closed with {reasons:?}; the silent controller connection: \"{silent}\"; the orbit reported {downs} downs and {stragglers} released swaps with stragglers; stdout:\n{}",
        started.elapsed().as_secs_f64(),
        text(&out)
    );
    assert!(attempts >= 10, "only {attempts} attempts");
    // Each attempt is refused with the reason (or, when the daemon's close overtakes the client's
    // own sends, seen only as the connection lost or reset), and once its first few handshakes
    // have failed, before its handshake (the limit per source address).
    let refused = "node `node1`'s certificate is not the controller's";
    assert!(reasons.iter().any(|r| r.contains(refused)), "{reasons:?}");
    let raced = |r: &String| r.ends_with("connection lost") || r.ends_with("reset by peer)");
    let limited = |r: &String| r.contains("the server refused to accept a new connection");
    assert!(reasons.iter().all(|r| r.contains(refused) || raced(r) || limited(r)), "{reasons:?}");
    assert!(silent.contains("no stream and Hello within 5 s"), "{silent}");
    assert_eq!(downs, 0, "the running controller lost a node:\n{stderr}");
    assert_eq!(stragglers, 0, "a swap went without a node:\n{stderr}");
}

/// When the orbit recorded each frame (`--record-frames DIR`: a line `ID UNIX_MS ...` per swap in
/// `frames`), Unix ms.
fn recorded_ms(frames: &Path) -> Vec<u128> {
    text(frames).lines().filter_map(|l| l.split_whitespace().nth(1)?.parse::<u128>().ok()).collect()
}

/// Frames the orbit recorded between `from` and `to`, per second.
fn fps_between(frames: &Path, from: std::time::SystemTime, to: std::time::SystemTime) -> f64 {
    let ms = |t: std::time::SystemTime| t.duration_since(std::time::UNIX_EPOCH).unwrap().as_millis();
    let (a, b) = (ms(from), ms(to));
    let n = recorded_ms(frames).into_iter().filter(|t| (a..b).contains(t)).count();
    n as f64 / (b - a) as f64 * 1e3
}

#[test]
fn a_reconnect_flood_is_refused_before_its_handshakes_and_the_wall_keeps_its_frame_rate() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let config = wall_config(dir.path(), "flood", &ports, 16, 12, 2, 5000, "keys");
    keygen(dir.path(), &config);
    let Some(_daemons) = nodes(dir.path(), &config, 4) else { return };
    let keys = dir.path().join("keys");
    let record = dir.path().join("frames");
    let (mut orbit, _out, err) = spawn_isowall(
        dir.path(),
        "orbit",
        &[
            "orbit",
            config.to_str().unwrap(),
            "--frames",
            "100000",
            "--record-frames",
            record.to_str().unwrap(),
        ],
    );
    assert!(wait_for(&err, "up (4/4)", Duration::from_secs(60)).is_some(), "{}", text(&err));
    let frames = record.join("frames.txt");
    wait_until("the orbit recorded its first frame", Duration::from_secs(60), || {
        if recorded_ms(&frames).is_empty() {
            Err(text(&err))
        } else {
            Ok(())
        }
    });
    // The wall's frame rate settles before the baseline is measured.
    std::thread::sleep(Duration::from_secs(2));
    let window = Duration::from_secs(5);
    let before = std::time::SystemTime::now();
    std::thread::sleep(window);
    let flood_start = std::time::SystemTime::now();
    // An attacker holding node1's certificate reconnects to node0 about 450 times a second
    // from 8 tasks, each connection closed as soon as it is up.
    const RATE: u64 = 450;
    const TASKS: u64 = 8;
    let rt = runtime();
    let (attempts, refused_before, handshakes) = rt.block_on(async {
        let node = transport::client(&Identity::load(&keys, "node1").unwrap()).unwrap();
        let until = tokio::time::Instant::now() + window;
        let tasks: Vec<_> = (0..TASKS)
            .map(|_| {
                let node = node.clone();
                let at = addr(ports[0]);
                tokio::spawn(async move {
                    let (mut attempts, mut refused, mut handshakes) = (0u64, 0u64, 0u64);
                    let mut tick = tokio::time::interval(Duration::from_micros(TASKS * 1_000_000 / RATE));
                    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
                    while tokio::time::Instant::now() < until {
                        tick.tick().await;
                        attempts += 1;
                        match node.connect(at, "node0").unwrap().await {
                            Ok(c) => {
                                handshakes += 1;
                                c.close(0u32.into(), b"again");
                            }
                            Err(quinn::ConnectionError::ConnectionClosed(c))
                                if c.error_code == quinn::TransportErrorCode::CONNECTION_REFUSED =>
                            {
                                refused += 1
                            }
                            Err(_) => {}
                        }
                    }
                    (attempts, refused, handshakes)
                })
            })
            .collect();
        let mut sum = (0, 0, 0);
        for t in tasks {
            let (a, r, h) = t.await.unwrap();
            sum = (sum.0 + a, sum.1 + r, sum.2 + h);
        }
        sum
    });
    let flood_end = std::time::SystemTime::now();
    // A frame recorded after the flood: every one recorded during it is in the file.
    let end_ms = flood_end.duration_since(std::time::UNIX_EPOCH).unwrap().as_millis();
    wait_until("a frame recorded after the flood", Duration::from_secs(30), || {
        if recorded_ms(&frames).iter().any(|&t| t >= end_ms) {
            Ok(())
        } else {
            Err(text(&err))
        }
    });
    let _ = orbit.0.kill();
    let _ = orbit.0.wait();
    let fps_before = fps_between(&frames, before, flood_start);
    let fps_during = fps_between(&frames, flood_start, flood_end);
    let stderr = text(&err);
    let downs = stderr.matches(" is down").count();
    eprintln!(
        "reconnect flood with node1's certificate: {attempts} attempts in {:.1} s ({:.0}/s), {refused_before} refused before their handshake, {handshakes} handshakes completed; the wall's frame rate {fps_before:.1} fps before, {fps_during:.1} fps during; {downs} nodes reported down",
        flood_end.duration_since(flood_start).unwrap().as_secs_f64(),
        attempts as f64 / flood_end.duration_since(flood_start).unwrap().as_secs_f64(),
    );
    assert!(attempts >= RATE, "only {attempts} attempts");
    assert!(fps_before > 0.0, "no frames recorded before the flood:\n{stderr}");
    // The limit (8 at once, then 4 a second per source) lets a few handshakes through.
    assert!(handshakes <= 8 + 4 * (window.as_secs() + 1), "{handshakes} handshakes completed");
    assert!(refused_before >= attempts / 2, "{refused_before} of {attempts} refused before their handshake");
    assert!(fps_during >= 0.5 * fps_before, "{fps_before:.1} fps before, {fps_during:.1} during the flood");
    assert_eq!(downs, 0, "the running controller lost a node:\n{stderr}");
}

// ---- 5: bincode limits ---------------------------------------------------------------------------

/// A brick map whose body is exactly `len` bytes (one holder's name fills it).
fn bricks_of_len(len: usize) -> Message {
    let with = |n: usize| Message::Bricks { from_frame: 1, holders: vec![Some("n".repeat(n)), None] };
    let base = codec::encode(&with(0)).unwrap().len();
    (0..=8)
        .filter_map(|widen| len.checked_sub(base + widen))
        .map(with)
        .find(|m| codec::encode(m).unwrap().len() == len)
        .unwrap_or_else(|| panic!("no brick map of {len} bytes"))
}

#[test]
fn valid_messages_around_the_old_limits_reach_the_daemon() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let config = wall_config(dir.path(), "limits", &ports, 16, 12, 2, 5000, "keys");
    keygen(dir.path(), &config);
    let Some(_daemons) = nodes(dir.path(), &config, 1) else { return };
    let keys = dir.path().join("keys");
    let rt = runtime();
    let passed = rt.block_on(async {
        let endpoint = transport::client(&Identity::load(&keys, "controller").unwrap()).unwrap();
        let mut ch = hello_as_controller(&endpoint, addr(ports[0]), "node0").await.unwrap();
        let first = ch.receiver.recv().await.unwrap().unwrap();
        assert!(matches!(first, Message::Hello { .. }), "{first:?}");
        let mut passed = 0;
        for edge in [4096usize, 16_384, 65_536, 262_144] {
            for len in edge - 4..=edge + 4 {
                let m = bricks_of_len(len);
                ch.sender.send(&m).await.unwrap();
                // The daemon ignores a brick map in screen space; the Ping proves it decoded it.
                let id = len as u64;
                ch.sender.send(&Message::Ping { id, t0_us: 0 }).await.unwrap();
                let answer = tokio::time::timeout(Duration::from_secs(10), async {
                    loop {
                        match ch.receiver.recv().await {
                            Ok(Some(Message::Pong { id: got, .. })) if got == id => return Ok(()),
                            Ok(Some(_)) => continue,
                            Ok(None) => return Err("stream ended".to_string()),
                            Err(e) => return Err(e.to_string()),
                        }
                    }
                })
                .await;
                match answer {
                    Ok(Ok(())) => passed += 1,
                    other => {
                        let why = closed(&ch.connection, Duration::from_secs(1)).await;
                        panic!(
                            "a valid {len}-byte brick map closed the connection: {other:?}; reason \"{why}\""
                        );
                    }
                }
            }
        }
        passed
    });
    eprintln!("{passed} valid messages of 4092..=262148 bytes around the powers of 4 decoded by the daemon");
    assert_eq!(passed, 4 * 9);
}

// ---- 8: limits -------------------------------------------------------------------------------------

#[test]
fn connections_streams_and_flow_control_are_bounded_per_peer() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let config = wall_config(dir.path(), "bounded", &ports, 16, 12, 2, 5000, "keys");
    keygen(dir.path(), &config);
    let Some(daemons) = nodes(dir.path(), &config, 1) else { return };
    let pid = daemons[0].child.id();
    let keys = dir.path().join("keys");
    let rt = runtime();
    rt.block_on(async {
        let endpoint = transport::client(&Identity::load(&keys, "controller").unwrap()).unwrap();
        // (a) Connections per identity: three controller connections that send nothing. The one
        // the daemon counts third is refused at once, with the reason; the two it counts wait for
        // their Hello and are closed at its timeout (5 s). Which is third is the order in which
        // the daemon finishes their handshakes, each in a task of its own, not the order in which
        // the client's did: so any one of them.
        let mut conns = Vec::new();
        for _ in 0..3 {
            conns.push(transport::connect(&endpoint, addr(ports[0]), "node0").await.unwrap());
        }
        let t = Instant::now();
        let ends: Vec<_> = conns
            .iter()
            .map(|c| {
                let c = c.clone();
                tokio::spawn(async move { (closed(&c, Duration::from_secs(8)).await, t.elapsed()) })
            })
            .collect();
        let mut refused = Vec::new();
        let mut timed_out = Vec::new();
        for end in ends {
            let (reason, after) = end.await.unwrap();
            eprintln!("controller connection closed after {:.2} s: \"{reason}\"", after.as_secs_f64());
            if reason.contains("controller already has 2 connections open") {
                refused.push(after);
            } else {
                assert!(reason.contains("no stream and Hello within 5 s"), "{reason}");
                timed_out.push(after);
            }
        }
        assert_eq!((refused.len(), timed_out.len()), (1, 2), "one refused, two timed out");
        assert!(refused[0] < Duration::from_secs(4), "the refusal waited for the Hello timeout: {refused:?}");
        // (b) Streams and flow control: a peer that opens every stream it may and fills each. The
        // daemon reads none of them (it uses one bidirectional stream), so what it buffers is
        // what the limits let in.
        let rss_before = rss_kib(pid);
        let ch = hello_as_controller(&endpoint, addr(ports[0]), "node0").await.unwrap();
        let mut opened = 0;
        let mut writers = Vec::new();
        for _ in 0..100 {
            match tokio::time::timeout(Duration::from_millis(300), ch.connection.open_uni()).await {
                Ok(Ok(mut s)) => {
                    opened += 1;
                    writers.push(tokio::spawn(async move {
                        let chunk = vec![0x5au8; 64 << 10];
                        let mut sent = 0usize;
                        while sent < (32 << 20) {
                            match tokio::time::timeout(Duration::from_secs(2), s.write_all(&chunk)).await {
                                Ok(Ok(())) => sent += chunk.len(),
                                _ => break,
                            }
                        }
                        sent
                    }));
                }
                _ => break,
            }
        }
        let mut accepted = 0;
        for w in writers {
            accepted += w.await.unwrap();
        }
        let rss_after = rss_kib(pid);
        eprintln!(
            "streams opened: {opened}; bytes the daemon let in: {:.1} MiB; daemon RSS {:.1} -> {:.1} MiB",
            accepted as f64 / (1 << 20) as f64,
            rss_before as f64 / 1024.0,
            rss_after as f64 / 1024.0
        );
        assert!(opened <= transport::MAX_UNI_STREAMS as usize, "{opened} streams opened");
        assert!(
            accepted <= (transport::CONNECTION_FLOW_LIMIT as usize) + (1 << 20),
            "{accepted} bytes let in"
        );
        assert!(rss_after < rss_before + 48 * 1024, "RSS {rss_before} -> {rss_after} KiB");
        ch.connection.close(0u32.into(), b"done");
    });
    let mut d = daemons;
    assert!(d[0].child.try_wait().unwrap().is_none(), "node0 exited:\n{}", d[0].log_text());
}

/// How a node played by the test misbehaves.
#[derive(Clone)]
enum Act {
    /// Speaks the protocol as a daemon does.
    Honest,
    /// Answers a snapshot with its own tiles and this one too (another node's), in red.
    ForeignTile(String, u32, u32),
    /// Says goodbye with this reason after its first presented frame.
    Bye(String),
    /// Lies with its own certificate while it answers every frame: before each Ready this many
    /// BrickFailed for bricks it was never asked to load (their reason full of terminal escapes),
    /// StepLate for its frame and Surface claims past its tiles' pixels (or with more hits at
    /// level 0 than hits); its Presented times 46 days late every other frame, its
    /// Pongs 46 days off after the first two, and from frame `unasked_from` on a Presented and a
    /// Pong nobody asked for after each Presented.
    Flood { per_frame: usize, unasked_from: u64 },
}

/// 46 days in microseconds: the lie of the flood.
const DAYS_46_US: i64 = 46 * 86_400 * 1_000_000;

/// A node played by the test on `port` with `keys/NAME.*` ([`FakeNode`]; its tiles blue), doing
/// what `act` says besides.
async fn fake_node(keys: PathBuf, name: String, port: u16, tiles: Vec<(String, u32, u32)>, act: Act) {
    let endpoint = fake_node::listen(&keys, &name, addr(port));
    let image = |name: &str, w: u32, h: u32, rgb: [u8; 3]| TileImage {
        name: name.into(),
        width: w,
        height: h,
        frame_id: 1,
        rgb8: rgb.iter().copied().cycle().take((w * h * 3) as usize).collect(),
    };
    while let Some(incoming) = endpoint.accept().await {
        let Ok(conn) = incoming.await else { continue };
        let names = tiles.iter().map(|t| t.0.clone()).collect();
        let Some(mut node) = FakeNode::greet(conn, &name, names).await else { continue };
        let mut pongs = 0;
        'conn: while let Some(out) = node.next().await {
            match out {
                NodeOutput::Send(mut msg) => {
                    if let Act::Flood { .. } = &act {
                        match &mut msg {
                            Message::Presented { frame_id, node_time_us, waiting_from_us }
                                if *frame_id % 2 == 0 =>
                            {
                                *node_time_us += DAYS_46_US;
                                // The time it took the swap up too: it would teach the margin.
                                *waiting_from_us += DAYS_46_US;
                            }
                            Message::Pong { t1_us, .. } => {
                                pongs += 1;
                                if pongs > 2 {
                                    *t1_us += DAYS_46_US;
                                }
                            }
                            _ => {}
                        }
                    }
                    let unasked = match (&act, &msg) {
                        (Act::Flood { unasked_from, .. }, Message::Presented { frame_id, .. })
                            if frame_id >= unasked_from =>
                        {
                            vec![
                                Message::Presented { frame_id: 1 << 40, node_time_us: 0, waiting_from_us: 0 },
                                Message::Pong {
                                    id: 1 << 40,
                                    t0_us: 0,
                                    t1_us: 0,
                                    sent_us: 0,
                                    resident_bytes: 0,
                                },
                            ]
                        }
                        _ => vec![],
                    };
                    for msg in std::iter::once(msg).chain(unasked) {
                        if !node.send(&msg).await {
                            break 'conn;
                        }
                    }
                }
                NodeOutput::Render { state, .. } if matches!(act, Act::Flood { .. }) => {
                    let Act::Flood { per_frame: n, .. } = &act else { unreachable!() };
                    let evil = "\u{1b}[2J\u{1b}[31mowned\r\nisowall: frame 9: all good";
                    for i in 0..*n {
                        let lies = [
                            Message::BrickFailed { brick: i as u64, reason: evil.into() },
                            Message::StepLate {
                                frame_id: state.frame_id,
                                shown_step: state.time_step + 1,
                                waited_us: 1,
                            },
                            Message::Surface { frame_id: state.frame_id, hits: u64::MAX, level0: 0 },
                            Message::Surface { frame_id: state.frame_id, hits: 1, level0: 2 },
                        ];
                        for lie in lies {
                            if !node.send(&lie).await {
                                break 'conn;
                            }
                        }
                    }
                    node.rendered(state.frame_id, fake_node::RENDER_TIME);
                }
                NodeOutput::Present { frame_id, .. } => {
                    node.presented(frame_id);
                    if let Act::Bye(reason) = &act {
                        let _ = node.send(&Message::Bye { reason: reason.clone() }).await;
                    }
                }
                NodeOutput::SnapshotWanted => {
                    let mut shown: Vec<TileImage> =
                        tiles.iter().map(|(n, w, h)| image(n, *w, *h, [0, 0, 255])).collect();
                    if let Act::ForeignTile(n, w, h) = &act {
                        shown.push(image(n, *w, *h, [255, 0, 0]));
                    }
                    let _ = node.send(&Message::Snapshot { tiles: shown }).await;
                }
                other => {
                    if !node.answer(other).await {
                        break;
                    }
                }
            }
        }
    }
}

#[test]
fn a_node_cannot_send_another_nodes_tile_nor_write_to_the_operators_terminal() {
    // No GPU: both nodes are played by the test, which answer at once (a short deadline bounds
    // what a lost message costs).
    let short = |config: &Path| {
        std::fs::write(config, text(config).replace("deadline_ms = 60000", "deadline_ms = 2000")).unwrap()
    };
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "fakes", &ports, 8, 4, 0, 0);
    short(&config);
    keygen(dir.path(), &config);
    let keys = dir.path().join("keys");
    let rt = runtime();
    let t = |i: usize| vec![(format!("t{i}"), 8u32, 4u32)];
    // (a) node1 answers a snapshot with node0's tile t0 (red) beside its own.
    let fakes = [
        rt.spawn(fake_node(keys.clone(), "node0".into(), ports[0], t(0), Act::Honest)),
        rt.spawn(fake_node(
            keys.clone(),
            "node1".into(),
            ports[1],
            t(1),
            Act::ForeignTile("t0".into(), 8, 4),
        )),
    ];
    let out = run_in(dir.path(), "isowall", &["snapshot", config.to_str().unwrap(), "--out", "s.png"]);
    let err = String::from_utf8_lossy(&out.stderr);
    eprintln!("{err}");
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("closing node1") && err.contains("tile `t0`, which is not one of its tiles"),
        "{err}"
    );
    let img = image::open(dir.path().join("s.png")).unwrap().to_rgb8();
    assert_eq!(img.get_pixel(0, 0).0, [0, 0, 255], "tile t0 is not node0's");
    for f in fakes {
        f.abort();
    }
    // (b) node1 says goodbye with terminal escapes and a forged line: printed escaped.
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "fakes2", &ports, 8, 4, 0, 0);
    short(&config);
    let evil = "\u{1b}[2J\u{1b}[31mowned\r\nisowall: frame 9: all good";
    let fakes = [
        rt.spawn(fake_node(keys.clone(), "node0".into(), ports[0], t(0), Act::Honest)),
        rt.spawn(fake_node(keys.clone(), "node1".into(), ports[1], t(1), Act::Bye(evil.into()))),
    ];
    let out = run_in(dir.path(), "isowall", &["orbit", config.to_str().unwrap(), "--frames", "3"]);
    let err = String::from_utf8_lossy(&out.stderr);
    eprintln!("{err}");
    for f in fakes {
        f.abort();
    }
    assert!(err.contains("node node1 is down: said goodbye: \\u{1b}[2J"), "{err}");
    assert!(!err.contains('\u{1b}') && !err.contains('\r'), "raw control characters reached the terminal");
    assert!(!err.lines().any(|l| l.starts_with("isowall: frame 9")), "a node forged a line of its own");
}

#[test]
fn a_node_certificate_flooding_lies_prints_a_few_lines_and_leaves_the_skew_report_sane() {
    // No GPU: both nodes are played by the test; node1 floods the controller with unsolicited
    // messages and forged times while `isowall orbit` runs.
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "liar", &ports, 8, 4, 0, 0);
    std::fs::write(&config, text(&config).replace("deadline_ms = 60000", "deadline_ms = 2000")).unwrap();
    keygen(dir.path(), &config);
    let keys = dir.path().join("keys");
    let rt = runtime();
    let t = |i: usize| vec![(format!("t{i}"), 8u32, 4u32)];
    let per_frame = 300;
    let frames: u64 = 100;
    let fakes = [
        rt.spawn(fake_node(keys.clone(), "node0".into(), ports[0], t(0), Act::Honest)),
        rt.spawn(fake_node(
            keys.clone(),
            "node1".into(),
            ports[1],
            t(1),
            Act::Flood { per_frame, unasked_from: frames - 10 },
        )),
    ];
    let start = Instant::now();
    let out =
        run_in(dir.path(), "isowall", &["orbit", config.to_str().unwrap(), "--frames", &frames.to_string()]);
    let elapsed = start.elapsed();
    for f in fakes {
        f.abort();
    }
    let err = String::from_utf8_lossy(&out.stderr);
    let report = String::from_utf8_lossy(&out.stdout);
    let lines = err.lines().count();
    let shown: String = err.lines().take(30).collect::<Vec<_>>().join("\n");
    eprintln!("{shown}\n... {lines} lines on stderr in {:.1} s\n{report}", elapsed.as_secs_f64());
    assert!(out.status.success(), "orbit failed: {shown}");
    // The liar's lines: at most 5 per 10 s (the model's PeerLog), whatever it sends (it sent
    // about 4 x {per_frame} x {frames} = 120,000 messages to be printed); a few lines of the wall's own.
    let windows = elapsed.as_secs() / 10 + 1;
    let bound = 20 + 5 * windows as usize;
    assert!(lines <= bound, "{lines} lines on stderr (at most {bound}): {shown}");
    assert!(!err.contains('\u{1b}') && !err.contains('\r'), "raw control characters reached the terminal");
    assert!(!err.lines().any(|l| l.starts_with("isowall: frame 9")), "a node forged a line of its own");
    assert!(!err.contains("is down"), "the liar was ignored, not dropped: {shown}");
    // Its Surface claims (more surface pixels than its 32, more at level 0 than surface) never
    // reach the report: no frame has a brick cache's line.
    assert!(!report.contains("level 0 (brick cache)"), "{report}");
    // The skew report: the forged times (46 days) kept out; the honest ones measured.
    let skew_line = report.lines().find(|l| l.starts_with("swap skew")).expect("a swap skew line");
    let max_ms: f64 = skew_line
        .split("max ")
        .nth(1)
        .and_then(|r| r.split(" ms").next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no max in `{skew_line}`"));
    assert!(max_ms < 2000.0, "the swap skew reported is {max_ms} ms, over the deadline: {skew_line}");
    let counted = report.lines().find(|l| l.trim_start().starts_with("node1:") && l.contains("ignored"));
    let counted = counted.unwrap_or_else(|| panic!("node1's ignored messages are not counted: {report}"));
    assert!(
        !report.lines().any(|l| l.trim_start().starts_with("node0:") && l.contains("ignored")),
        "{report}"
    );
    eprintln!("counted: {counted}");
}

#[test]
fn a_second_controller_is_refused_with_the_reason_and_the_first_keeps_its_nodes() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "two", &ports, 16, 12, 0, 1);
    keygen(dir.path(), &config);
    let Some(daemons) = nodes(dir.path(), &config, 2) else { return };
    let cfg = config.to_str().unwrap();
    // The first controller: 250 frames paced at 10 a second, so it drives the nodes for 25 s or
    // more whatever the machine's load.
    let (mut first, first_out, first_err) =
        spawn_isowall(dir.path(), "first", &["orbit", cfg, "--frames", "250", "--fps", "10"]);
    assert!(wait_for(&first_err, "up (2/2)", Duration::from_secs(60)).is_some(), "{}", text(&first_err));
    // The second, while the first drives: refused at every node, it tries again for 10 s (what
    // lets a controller restarted after a crash in once its old connection's idle timeout, 5 s,
    // has ended it) and exits with the reason.
    let started = Instant::now();
    let second = run_in(dir.path(), "isowall", &["orbit", cfg, "--frames", "5"]);
    let second_err = String::from_utf8_lossy(&second.stderr).into_owned();
    eprintln!("second controller, after {:.1} s:\n{second_err}", started.elapsed().as_secs_f64());
    assert!(
        first.0.try_wait().unwrap().is_none(),
        "the first ended before the second gave up: the test proves nothing"
    );
    assert!(!second.status.success(), "the second controller drove the wall:\n{second_err}");
    for node in ["node0", "node1"] {
        assert!(
            second_err.contains(&format!("{node} is driven by another controller (from 127.0.0.1:")),
            "{node}'s refusal does not say why:\n{second_err}"
        );
    }
    assert!(second_err.contains("stop it first"), "{second_err}");
    // The first finishes its frames undisturbed: no node down, none taken from it.
    let status = first.0.wait().unwrap();
    let (out, err) = (text(&first_out), text(&first_err));
    eprintln!("first controller:\n{out}{err}");
    assert!(status.success(), "the first controller failed:\n{err}");
    assert!(out.contains("frames: 250 "), "{out}");
    assert!(!err.contains("is down") && !err.contains("is back"), "the first lost a node:\n{err}");
    let logs: Vec<String> = daemons.iter().map(|d| d.log_text()).collect();
    assert!(logs.iter().all(|l| l.contains("refused a second controller")), "{}", logs.join("\n---\n"));
    // Once the first has left, a new controller takes the nodes at once.
    let started = Instant::now();
    let third = run_in(dir.path(), "isowall", &["orbit", cfg, "--frames", "5"]);
    eprintln!("third controller: 5 frames done {:.2} s after its start", started.elapsed().as_secs_f64());
    let third_err = String::from_utf8_lossy(&third.stderr);
    assert!(third.status.success(), "after the first left, a new controller was refused:\n{third_err}");
    assert!(String::from_utf8_lossy(&third.stdout).contains("frames: 5 "), "{third_err}");
}

#[test]
fn a_controller_that_says_bye_is_closed_by_the_node_and_leaves_nothing_held() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(1);
    let config = wall_config(dir.path(), "bye", &ports, 16, 12, 2, 5000, "keys");
    keygen(dir.path(), &config);
    let Some(_daemons) = nodes(dir.path(), &config, 1) else { return };
    let keys = dir.path().join("keys");
    runtime().block_on(async {
        let endpoint = transport::client(&Identity::load(&keys, "controller").unwrap()).unwrap();
        // Each controller says Bye and never closes its side, as when the network loses its
        // close: the node closes at once, so the next is seated, and none counts against the
        // controller's connections, though all of them stay open here.
        let mut left = Vec::new();
        for i in 0..4 {
            let mut ch = hello_as_controller(&endpoint, addr(ports[0]), "node0")
                .await
                .unwrap_or_else(|e| panic!("controller {i} was not served: {e}"));
            let first = tokio::time::timeout(Duration::from_secs(5), ch.receiver.recv()).await;
            let Ok(Ok(Some(hello))) = first else {
                panic!("controller {i}: no Hello from the node: {first:?}")
            };
            codec::check_hello(&hello, Role::Daemon).unwrap();
            let t = Instant::now();
            ch.sender.send(&Message::Bye { reason: "leaving".into() }).await.unwrap();
            let reason = closed(&ch.connection, Duration::from_secs(2)).await;
            eprintln!(
                "controller {i}: closed by the node {:.3} s after its Bye: \"{reason}\"",
                t.elapsed().as_secs_f64()
            );
            assert_eq!(reason, "the controller said goodbye", "controller {i}");
            left.push(ch);
        }
    });
}

/// The console's status, from its address in `out` (`isowall console` prints it); `None` before
/// it serves one (until the wall's first frame it answers 503).
fn console_status(out: &Path) -> Option<serde_json::Value> {
    let base =
        text(out).lines().find_map(|l| l.strip_prefix("isowall console: serving "))?.trim().to_string();
    let agent = ureq::Agent::new_with_config(
        ureq::config::Config::builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(20)))
            .build(),
    );
    let mut r = agent.get(format!("{base}api/status")).call().ok()?;
    if r.status() != 200 {
        return None;
    }
    serde_json::from_slice(&r.body_mut().read_to_vec().ok()?).ok()
}

fn console_post(out: &Path, path: &str, body: &str) -> (u16, String) {
    let base = text(out)
        .lines()
        .find_map(|l| l.strip_prefix("isowall console: serving "))
        .unwrap()
        .trim()
        .to_string();
    let agent = ureq::Agent::new_with_config(
        ureq::config::Config::builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(30)))
            .build(),
    );
    let mut r =
        agent.post(format!("{base}{path}")).header("Content-Type", "application/json").send(body).unwrap();
    (r.status().as_u16(), String::from_utf8_lossy(&r.body_mut().read_to_vec().unwrap()).into_owned())
}

#[test]
fn only_the_controller_holding_a_node_restarts_it_and_it_exits_for_its_supervisor() {
    // The unit restarts a daemon that exits with anything but 0, which is how a Restart ends it.
    let unit =
        std::fs::read_to_string(isowall_e2e::repo_root().join("wall-configs/systemd/isowalld.service"))
            .unwrap();
    assert!(
        unit.lines().any(|l| l.trim() == "Restart=on-failure"),
        "the unit does not restart a failed node"
    );
    assert!(!unit.contains("RestartPreventExitStatus"), "the unit would not restart a restarting node");
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "restart", &ports, 16, 12, 0, 1);
    keygen(dir.path(), &config);
    let Some(mut daemons) = nodes(dir.path(), &config, 2) else { return };
    let cfg = config.to_str().unwrap();
    // The seated controller: a console driving nodes it did not start (as on a real wall).
    let (_console, out, err) =
        spawn_isowall(dir.path(), "console", &["console", cfg, "--listen", "127.0.0.1:0"]);
    let give_up = Instant::now() + Duration::from_secs(90);
    loop {
        let up = console_status(&out)
            .is_some_and(|s| s["nodes"].as_array().unwrap().iter().all(|n| n["state"] == "up"));
        if up {
            break;
        }
        assert!(Instant::now() < give_up, "the console never had both nodes up:\n{}", text(&err));
        std::thread::sleep(Duration::from_millis(200));
    }
    // Its version and GPU, as node0 told them (in a message of its own, after its Hello: a node
    // is up a moment before they are known).
    let s = wait_until("node0's version in the console's status", Duration::from_secs(30), || {
        let s = console_status(&out);
        match s {
            Some(s) if s["nodes"][0]["version"].is_string() => Ok(s),
            _ => Err(format!("the status: {s:?}\n{}", text(&err))),
        }
    });
    assert_eq!(s["nodes"][0]["version"].as_str(), Some(env!("CARGO_PKG_VERSION")), "{}", s["nodes"][0]);
    assert!(s["nodes"][0]["adapter"].as_str().is_some_and(|a| !a.is_empty()), "{}", s["nodes"][0]);
    assert!(s["nodes"][0]["backend"].as_str().is_some_and(|b| !b.is_empty()), "{}", s["nodes"][0]);

    // Another peer with the controller's own certificate, while the console holds the node: it
    // is refused before any message of its counts, so its Restart restarts nothing.
    let rt = runtime();
    let intruder = rt.block_on(async {
        let identity = Identity::load(&dir.path().join("keys"), isowall_net::tls::CONTROLLER).unwrap();
        let endpoint = transport::client(&identity).unwrap();
        match hello_as_controller(&endpoint, addr(ports[0]), "node0").await {
            Err(reason) => reason,
            Ok(mut ch) => {
                let _ = ch.sender.send(&Message::Restart { reason: "intruder".into() }).await;
                closed(&ch.connection, Duration::from_secs(5)).await
            }
        }
    });
    assert!(intruder.contains("node0 is driven by another controller"), "{intruder}");
    assert!(daemons[0].child.try_wait().unwrap().is_none(), "the intruder's Restart ended node0");

    // The console's restart: node0 exits with the restart status, for its supervisor. It is the
    // one restart node0 obeys: had the intruder's counted, node0 would be gone before it (the
    // console's restart refused) or its log would name two.
    let (status, body) = console_post(&out, "api/nodes/node0/restart", r#"{"reason": "test"}"#);
    assert_eq!(status, 200, "{body}");
    assert!(body.contains("told to restart over its connection"), "{body}");
    let give_up = Instant::now() + Duration::from_secs(20);
    let code = loop {
        if let Some(st) = daemons[0].child.try_wait().unwrap() {
            break st.code();
        }
        assert!(Instant::now() < give_up, "node0 did not exit:\n{}", daemons[0].log_text());
        std::thread::sleep(Duration::from_millis(50));
    };
    let log = daemons[0].log_text();
    assert_eq!(code, Some(isowall_model::messages::RESTART_EXIT_CODE), "{log}");
    let restarts: Vec<&str> = log.lines().filter(|l| l.contains("asked this node to restart")).collect();
    assert!(
        restarts.len() == 1 && restarts[0].contains("test") && !restarts[0].contains("intruder"),
        "node0 did not restart once, at the console's request:\n{log}"
    );
    assert!(daemons[1].child.try_wait().unwrap().is_none(), "node1 was not asked");
    // Started again (as systemd does): the console has it back.
    daemons[0] = Daemon::start(dir.path(), &config, "node0", &[]);
    assert!(daemons[0].wait_ready(Duration::from_secs(60)), "{}", daemons[0].log_text());
    let give_up = Instant::now() + Duration::from_secs(40);
    while !console_status(&out)
        .is_some_and(|s| s["nodes"][0]["state"] == "up" && s["nodes"][0]["version"].is_string())
    {
        assert!(Instant::now() < give_up, "node0 did not rejoin:\n{}", text(&err));
        std::thread::sleep(Duration::from_millis(200));
    }
}

// ---- 9: a wall starts without a dead node ------------------------------------------------------

#[test]
fn a_wall_starts_with_the_nodes_it_has_and_a_late_node_joins() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let config = wall_config(dir.path(), "late", &ports, 16, 12, 2, 5000, "keys");
    keygen(dir.path(), &config);
    let Some(mut daemons) = nodes(dir.path(), &config, 3) else { return };
    let t0 = Instant::now();
    let (mut orbit, _out, err) =
        spawn_isowall(dir.path(), "orbit", &["orbit", config.to_str().unwrap(), "--frames", "100000"]);
    let started = wait_for(&err, "starting without node node3", Duration::from_secs(60));
    assert!(started.is_some(), "the wall did not start without node3:\n{}", text(&err));
    let up_at = t0.elapsed();
    daemons.push(Daemon::start(dir.path(), &config, "node3", &[]));
    assert!(daemons[3].wait_ready(Duration::from_secs(120)), "node3:\n{}", daemons[3].log_text());
    let ready_at = t0.elapsed();
    let back = wait_for(&err, "node node3 is back", Duration::from_secs(30));
    let _ = orbit.0.kill();
    let _ = orbit.0.wait();
    let stderr = text(&err);
    eprintln!(
        "started without node3 after {:.2} s; node3 ready {:.2} s later, rejoined {:.2} s after that\n{stderr}",
        up_at.as_secs_f64(),
        (ready_at - up_at).as_secs_f64(),
        back.map_or(f64::NAN, |b| b.as_secs_f64())
    );
    assert!(back.is_some(), "node3 never joined:\n{stderr}");
    assert!(!stderr.contains("cannot reach 1 of 4"), "{stderr}");
}

#[test]
fn isowall_up_starts_without_a_node_it_cannot_reach() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let config = wall_config(dir.path(), "upwithout", &ports, 16, 12, 2, 5000, "keys");
    // node3 lives at an address nothing answers (TEST-NET-1): `up` starts no daemon for it.
    let s = text(&config).replace(&format!("127.0.0.1:{}", ports[3]), "192.0.2.1:7401");
    std::fs::write(&config, s).unwrap();
    keygen(dir.path(), &config);
    let t = Instant::now();
    let out = run_in(dir.path(), "isowall", &["up", config.to_str().unwrap(), "--frames", "5"]);
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    if !out.status.success() && stderr.contains("no Vulkan adapter") && !in_ci() {
        eprintln!("skipping: no Vulkan adapter");
        return;
    }
    eprintln!(
        "`isowall up` with node3 unreachable: exit {} after {:.1} s\n{stdout}\n{stderr}",
        out.status,
        t.elapsed().as_secs_f64()
    );
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("starting without node node3 (192.0.2.1:7401)"), "{stderr}");
    assert!(stdout.contains("frames: 5"), "{stdout}");
}

/// Kills node1 of a running 2x2 wall (object space or screen space): how long until the
/// controller reports it down; at most 3 deadlines (and a little for the processes).
fn a_killed_node_is_down_within_three_deadlines(object: bool) {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let deadline_ms = 1000u64;
    let config = wall_config(dir.path(), "death", &ports, 40, 30, 2, deadline_ms, "keys");
    if object {
        set_object_mode(&config);
    }
    let space = if object { "object space" } else { "screen space" };
    keygen(dir.path(), &config);
    let Some(mut daemons) = nodes(dir.path(), &config, 4) else { return };
    let (mut orbit, _out, err) =
        spawn_isowall(dir.path(), "orbit", &["orbit", config.to_str().unwrap(), "--frames", "100000"]);
    assert!(wait_for(&err, "up (4/4)", Duration::from_secs(60)).is_some(), "{}", text(&err));
    // Frames with all four nodes for a while, so that node1 dies in the middle of a running wall.
    std::thread::sleep(Duration::from_secs(2));
    daemons[1].child.kill().unwrap();
    let down = wait_for(&err, "node node1 is down", Duration::from_secs(20));
    let _ = orbit.0.kill();
    let _ = orbit.0.wait();
    let stderr = text(&err);
    let down = down.unwrap_or_else(|| panic!("node1 was never reported down:\n{stderr}"));
    eprintln!(
        "{space}: node1 killed, reported down {:.2} s later (deadline {deadline_ms} ms)",
        down.as_secs_f64()
    );
    let line = stderr.lines().find(|l| l.contains("node node1 is down")).unwrap_or_default().to_string();
    eprintln!("{line}");
    assert!(down <= Duration::from_millis(3 * deadline_ms + 300), "down after {down:?}:\n{stderr}");
}

#[test]
fn object_space_a_killed_node_is_down_within_three_deadlines() {
    a_killed_node_is_down_within_three_deadlines(true);
}

#[test]
fn screen_space_a_killed_node_is_down_within_three_deadlines() {
    a_killed_node_is_down_within_three_deadlines(false);
}
