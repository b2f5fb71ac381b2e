//! Attacks on the operator console (`isowall console`), made as a client on loopback would make
//! them: the real `isowall console` process, real HTTP and WebSocket clients, and nodes played by
//! the test (no GPU: a QUIC server with the node's certificate that speaks the protocol through the
//! model's `NodeMachine`, renders nothing and answers at once). One test per kind of attack; each
//! says what the console must do, fails when it does not, and prints what the attacker achieved
//! (`--nocapture`).
//!
//! - pictures: clients looping full snapshots while a node never answers one, clients that leave,
//!   thumbnails at a new width each time: the frames go on, the nodes are asked 4 times a second
//!   at most, a request whose client left is dropped;
//! - connections: a crowd of half-sent requests does not hold a newcomer out;
//! - origins: a page of another site (its `Origin`, or `Sec-Fetch-Site`) is refused on every API
//!   route, the WebSocket included, while curl-like clients and the console's own page are not;
//!   a token is never taken from a URL;
//! - the operator lock: while one client holds it, every other client's change (every POST
//!   route) is refused with 423 naming the holder and changes nothing; reads stay open; it lapses
//!   when idle;
//! - restart, logs, bookmarks, node info: a restart reaches only a node of the wall (told over its
//!   connection, its reason bounded and escaped), a log path names a node or nothing, bookmark
//!   names and a malformed bookmarks file are refused without touching the file, and what a node
//!   says of itself is bounded and escaped.

use isowall_e2e::fake_node::{self, runtime, FakeNode};
use isowall_e2e::{bin, free_udp_ports, run_in, wait_until, wall_config_2x1};
use isowall_model::messages::{Message, NodeInfo, TileImage};
use isowall_model::node_machine::NodeOutput;
use serde_json::Value;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// What a node played by the test does and counts.
#[derive(Default)]
struct NodeCtl {
    /// Answers no snapshot or thumbnail request while set.
    silent: AtomicBool,
    /// Snapshot and thumbnail requests received.
    asked: AtomicU64,
    /// The reasons of the Restarts received (each closes the connection, as the daemon's exit).
    restarts: std::sync::Mutex<Vec<String>>,
    /// Connections the node greeted.
    connections: AtomicU64,
}

/// A node played by the test on `port` with `keys/NAME.*`: its tile `(name, w, h)` blue.
async fn fake_node(keys: PathBuf, name: String, port: u16, tile: (String, u32, u32), ctl: Arc<NodeCtl>) {
    let endpoint = fake_node::listen(&keys, &name, format!("127.0.0.1:{port}").parse().unwrap());
    let (tname, w, h) = tile;
    let image = TileImage {
        name: tname.clone(),
        width: w,
        height: h,
        frame_id: 1,
        rgb8: [0u8, 0, 255].iter().copied().cycle().take((w * h * 3) as usize).collect(),
    };
    while let Some(incoming) = endpoint.accept().await {
        let Ok(conn) = incoming.await else { continue };
        let Some(mut node) = FakeNode::greet(conn, &name, vec![tname.clone()]).await else { continue };
        ctl.connections.fetch_add(1, Ordering::Relaxed);
        // What it says of itself: markup and a terminal escape, for the console to show as text.
        let info = NodeInfo {
            version: "0.0.0-fake".into(),
            adapter: format!("fake <script>alert('{name}')</script>\u{1b}[31m"),
            backend: "Vulkan".into(),
            driver: "none".into(),
            driver_info: "played by the test".into(),
            present: "SCHED_FIFO 10".into(),
        };
        if !node.send(&Message::NodeInfo(info)).await {
            continue;
        }
        while let Some(out) = node.next().await {
            let open = match out {
                NodeOutput::SnapshotWanted | NodeOutput::ThumbnailWanted { .. } => {
                    ctl.asked.fetch_add(1, Ordering::Relaxed);
                    let divisor = match out {
                        NodeOutput::ThumbnailWanted { divisor } => divisor,
                        _ => 1,
                    };
                    ctl.silent.load(Ordering::Relaxed)
                        || node.send(&Message::Snapshot { tiles: vec![image.downscaled(divisor)] }).await
                }
                NodeOutput::Restart { reason } => {
                    ctl.restarts.lock().unwrap().push(reason);
                    node.connection.close(75u32.into(), b"restarting");
                    false
                }
                other => node.answer(other).await,
            };
            if !open {
                break;
            }
        }
    }
}

/// A running `isowall console` on loopback, killed when dropped.
struct Console {
    child: Child,
    base: String,
    addr: SocketAddr,
    dir: PathBuf,
    /// `Authorization: Bearer T` where the console has a token.
    bearer: Option<String>,
}

impl Drop for Console {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

struct Reply {
    status: u16,
    body: Vec<u8>,
}

impl Reply {
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&self.body)))
    }
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

fn agent(timeout: Duration) -> ureq::Agent {
    ureq::Agent::new_with_config(
        ureq::config::Config::builder().http_status_as_error(false).timeout_global(Some(timeout)).build(),
    )
}

impl Console {
    /// `isowall console CONFIG --listen 127.0.0.1:0 EXTRA...` under `ulimit -n FDS`, once it serves
    /// and has released a frame.
    fn start(dir: &Path, config: &Path, extra: &[&str], fds: u32) -> Console {
        let err = std::fs::File::create(dir.join("console.err")).unwrap();
        let mut child = Command::new("sh")
            .arg("-c")
            .arg(format!("ulimit -n {fds} && exec \"$0\" \"$@\""))
            .arg(bin("isowall"))
            .arg("console")
            .arg(config)
            .args(["--listen", "127.0.0.1:0"])
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(err)
            .spawn()
            .expect("start isowall console");
        let stdout = child.stdout.take().unwrap();
        let rx = isowall_e2e::console_urls(stdout);
        let log = || std::fs::read_to_string(dir.join("console.err")).unwrap_or_default();
        let base =
            rx.recv_timeout(Duration::from_secs(60)).unwrap_or_else(|_| panic!("no console:\n{}", log()));
        let addr = base.trim_start_matches("http://").parse().unwrap();
        let bearer = extra.iter().position(|a| *a == "--token").map(|i| format!("Bearer {}", extra[i + 1]));
        let con = Console { child, base, addr, dir: dir.to_path_buf(), bearer };
        let give_up = Instant::now() + Duration::from_secs(60);
        while con.released() < 3 {
            assert!(Instant::now() < give_up, "no frame:\n{}", log());
            std::thread::sleep(Duration::from_millis(100));
        }
        con
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.join("console.err")).unwrap_or_default()
    }

    fn get(&self, a: &ureq::Agent, path: &str, headers: &[(&str, &str)]) -> Result<Reply, ureq::Error> {
        let mut req = a.get(format!("{}{path}", self.base));
        for (k, v) in headers {
            req = req.header(*k, *v);
        }
        let mut r = req.call()?;
        Ok(Reply { status: r.status().as_u16(), body: r.body_mut().read_to_vec()? })
    }

    /// `POST PATH` with a JSON body and `headers` (the token added where the console has one).
    fn post(&self, a: &ureq::Agent, path: &str, body: &str, headers: &[(&str, &str)]) -> Reply {
        let mut req = a.post(format!("{}{path}", self.base)).header("Content-Type", "application/json");
        if let Some(b) = &self.bearer {
            req = req.header("Authorization", b.as_str());
        }
        for (k, v) in headers {
            req = req.header(*k, *v);
        }
        let mut r = req.send(body).expect("the console answers");
        Reply { status: r.status().as_u16(), body: r.body_mut().read_to_vec().expect("a body") }
    }

    fn status(&self) -> Value {
        let r = self.get(&agent(Duration::from_secs(20)), "/api/status", &[]).expect("the status");
        assert_eq!(r.status, 200, "{}", r.text());
        r.json()
    }

    /// Swaps released since the wall came up.
    fn released(&self) -> u64 {
        let auth: Vec<(&str, &str)> = self.bearer.iter().map(|b| ("Authorization", b.as_str())).collect();
        match self.get(&agent(Duration::from_secs(20)), "/api/status", &auth) {
            Ok(r) if r.status == 200 => r.json()["frame"]["released"].as_u64().unwrap_or(0),
            _ => 0,
        }
    }

    /// Swaps a second over `span`.
    fn swap_rate(&self, span: Duration) -> f64 {
        let (a, t) = (self.released(), Instant::now());
        std::thread::sleep(span);
        (self.released() - a) as f64 / t.elapsed().as_secs_f64()
    }
}

/// A 2x1 wall of 64x48 tiles whose two nodes are played by the test; its console started.
struct FakeWall {
    dir: tempfile::TempDir,
    _rt: tokio::runtime::Runtime,
    nodes: [Arc<NodeCtl>; 2],
    con: Console,
}

fn fake_wall(extra: &[&str], fds: u32) -> FakeWall {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config_2x1(dir.path(), "console-attack", &ports, 64, 48, 0, 1);
    // A short deadline: a lost message costs little.
    let text = std::fs::read_to_string(&config).unwrap();
    std::fs::write(&config, text.replace("deadline_ms = 60000", "deadline_ms = 2000")).unwrap();
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let rt = runtime();
    let nodes = [Arc::new(NodeCtl::default()), Arc::new(NodeCtl::default())];
    for (i, ctl) in nodes.iter().enumerate() {
        let keys = dir.path().join("keys");
        rt.spawn(fake_node(keys, format!("node{i}"), ports[i], (format!("t{i}"), 64, 48), ctl.clone()));
    }
    let con = Console::start(dir.path(), &config, extra, fds);
    FakeWall { dir, _rt: rt, nodes, con }
}

#[test]
fn pictures_never_stop_the_frames_and_reach_the_nodes_4_times_a_second_at_most() {
    let w = fake_wall(&[], 1024);
    let con = &w.con;
    let before = con.swap_rate(Duration::from_secs(3));
    eprintln!("swaps a second, nobody asking for pictures: {before:.1}");

    // (1) Thumbnails at a new width each time, four clients looping: the nodes are asked 4 times
    // a second at most (before: once for every width, 276 a second in the attacker's run).
    let span = Duration::from_secs(5);
    let asked0 = w.nodes[0].asked.load(Ordering::Relaxed);
    let started = Instant::now();
    let answered = AtomicU64::new(0);
    let statuses = std::sync::Mutex::new(std::collections::BTreeMap::<u16, u64>::new());
    std::thread::scope(|s| {
        for c in 0..4u32 {
            let (answered, statuses) = (&answered, &statuses);
            s.spawn(move || {
                let a = agent(Duration::from_secs(30));
                let mut width = 1 + c * 7;
                while started.elapsed() < span {
                    width = width % 127 + 1;
                    if let Ok(r) = con.get(&a, &format!("/api/snapshot.png?width={width}"), &[]) {
                        *statuses.lock().unwrap().entry(r.status).or_default() += 1;
                        if r.status == 200 {
                            answered.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
            });
        }
    });
    let took = started.elapsed().as_secs_f64();
    let asked = w.nodes[0].asked.load(Ordering::Relaxed) - asked0;
    let answered = answered.load(Ordering::Relaxed);
    eprintln!(
        "thumbnails at new widths: {answered} answered in {took:.1} s ({:?}), node0 asked {asked} times ({:.1} a second)",
        statuses.lock().unwrap(),
        asked as f64 / took
    );
    assert!(answered >= 8, "only {answered} thumbnails answered in {took:.1} s");
    assert!(
        asked as f64 <= 4.0 * took + 3.0,
        "node0 was asked for {asked} pictures in {took:.1} s: more than 4 a second"
    );

    // (2) node1 never answers a picture. Six clients loop full snapshots, three more leave after
    // a second each: the frames go on (before: every snapshot held the frame loop until node1 was
    // given up, 10 s; 0 swaps a second).
    w.nodes[1].silent.store(true, Ordering::Relaxed);
    let released0 = con.released();
    let started = Instant::now();
    let span = Duration::from_secs(6);
    let outcomes = std::sync::Mutex::new(std::collections::BTreeMap::<String, u64>::new());
    std::thread::scope(|s| {
        for _ in 0..6 {
            let outcomes = &outcomes;
            s.spawn(move || {
                let a = agent(Duration::from_secs(30));
                while started.elapsed() < span {
                    let k = match con.get(&a, "/api/snapshot.png", &[]) {
                        Ok(r) => r.status.to_string(),
                        Err(e) => format!("{e}"),
                    };
                    *outcomes.lock().unwrap().entry(k).or_default() += 1;
                }
            });
        }
        for i in 0..3 {
            s.spawn(move || {
                // Half a second apart: they leave at different moments of the loop.
                std::thread::sleep(Duration::from_millis(500 * i));
                let _ = con.get(&agent(Duration::from_secs(1)), "/api/snapshot.png", &[]);
            });
        }
    });
    let took = started.elapsed().as_secs_f64();
    let during = (con.released() - released0) as f64 / took;
    eprintln!(
        "a silent node, 6 clients looping snapshots and 3 leaving: {during:.1} swaps a second over {took:.1} s (before: {before:.1}); answers {:?}",
        outcomes.lock().unwrap()
    );
    assert!(
        during >= 0.25 * before && during >= 2.0,
        "the frames slowed from {before:.1} to {during:.1} swaps a second while snapshots were asked for\n{}",
        con.log()
    );

    // (3) A request whose client left is dropped: with node1 silent, a client asks for a full
    // snapshot and leaves once the nodes were asked for it; once node1 answers again, a thumbnail
    // comes at once, not after the abandoned request's 5 s give-up.
    // node0 tells that the nodes were asked (node1 owes a snapshot already and is not asked again).
    let before_leaving = w.nodes[0].asked.load(Ordering::Relaxed);
    let ask = || {
        let mut s = TcpStream::connect(con.addr).unwrap();
        s.write_all(b"GET /api/snapshot.png HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").unwrap();
        s.set_nonblocking(true).unwrap();
        s
    };
    let (mut leaving, mut answered) = (ask(), String::new());
    wait_until("the nodes asked for the snapshot of a client that leaves", Duration::from_secs(20), || {
        if w.nodes[0].asked.load(Ordering::Relaxed) > before_leaving {
            return Ok(());
        }
        // Answered without the nodes (a full snapshot is served again for a second, and a client
        // has 4 requests waiting at most): asked again.
        let mut b = [0u8; 64];
        if !matches!(leaving.read(&mut b), Err(e) if e.kind() == std::io::ErrorKind::WouldBlock) {
            answered = String::from_utf8_lossy(&b).lines().next().unwrap_or_default().to_string();
            leaving = ask();
        }
        Err(format!("the last answer: {answered:?}\n{}", con.log()))
    });
    drop(leaving);
    // The console sees the connection closed and drops the request; the thumbnail's time below
    // is what tells whether it did.
    std::thread::sleep(Duration::from_millis(700));
    w.nodes[1].silent.store(false, Ordering::Relaxed);
    let t = Instant::now();
    let r = con.get(&agent(Duration::from_secs(30)), "/api/snapshot.png?width=40", &[]).unwrap();
    let waited = t.elapsed();
    eprintln!("a thumbnail after an abandoned snapshot: {} in {waited:?}", r.status);
    assert_eq!(r.status, 200, "{}", r.text());
    assert!(
        waited < Duration::from_millis(2500),
        "a thumbnail waited {waited:?} behind an abandoned snapshot"
    );
}

#[test]
fn half_sent_requests_do_not_hold_other_clients_out() {
    // The console with 1,024 file descriptors (a common default); 1,100 connections that send
    // half a request and wait (before: every other client was held out until they left).
    let w = fake_wall(&[], 1024);
    let con = &w.con;
    let mut held = Vec::new();
    let (t, mut failed) = (Instant::now(), 0);
    for _ in 0..1100 {
        match TcpStream::connect_timeout(&con.addr, Duration::from_secs(5)) {
            Ok(mut s) => {
                let _ = s.write_all(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ");
                held.push(s);
            }
            Err(e) => {
                failed += 1;
                eprintln!("connect {} after {:?}: {e}", held.len() + failed, t.elapsed());
                if failed > 5 {
                    break;
                }
            }
        }
    }
    eprintln!("{} connections in {:?}", held.len(), t.elapsed());
    // A moment for the console to take them in (or not): the newcomer comes after the crowd.
    std::thread::sleep(Duration::from_millis(500));
    let t = Instant::now();
    let r = con.get(&agent(Duration::from_secs(20)), "/api/status", &[]);
    let waited = t.elapsed();
    let ok = matches!(&r, Ok(r) if r.status == 200);
    eprintln!(
        "{} half-sent requests held; a newcomer's status: {} after {waited:?}",
        held.len(),
        match &r {
            Ok(r) => r.status.to_string(),
            Err(e) => e.to_string(),
        }
    );
    assert!(ok && waited < Duration::from_secs(10), "a newcomer was held out {waited:?}: {:?}", r.err());
    // The half-sent ones are closed by the header timeout (5 s) or to make room.
    let (t, n) = (Instant::now(), held.len());
    let mut open: Vec<&mut TcpStream> = held.iter_mut().collect();
    for s in &mut open {
        s.set_nonblocking(true).unwrap();
    }
    wait_until("every half-sent request closed", Duration::from_secs(30), || {
        // Closed: an end of file, a reset or an answer; open: nothing to read yet.
        open.retain_mut(|s| {
            let mut b = [0u8; 512];
            matches!(s.read(&mut b), Err(e) if e.kind() == std::io::ErrorKind::WouldBlock)
        });
        if open.is_empty() {
            Ok(())
        } else {
            Err(format!("{} still open", open.len()))
        }
    });
    eprintln!("all {n} closed {:.1} s after the newcomer's status", t.elapsed().as_secs_f64());
    drop(held);
    assert_eq!(con.get(&agent(Duration::from_secs(20)), "/api/status", &[]).unwrap().status, 200);
}

/// A WebSocket handshake to `path` with `headers`: the status line of the answer and its headers.
fn websocket(addr: SocketAddr, path: &str, headers: &[(&str, &str)]) -> String {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    let mut req = format!(
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n\
         Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
    );
    for (k, v) in headers {
        req += &format!("{k}: {v}\r\n");
    }
    req += "\r\n";
    s.write_all(req.as_bytes()).unwrap();
    let mut head = Vec::new();
    let mut b = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") && s.read(&mut b).unwrap_or(0) == 1 {
        head.push(b[0]);
    }
    String::from_utf8_lossy(&head).into_owned()
}

#[test]
fn a_page_of_another_site_is_refused_and_curl_and_the_page_are_not() {
    let w = fake_wall(&[], 1024);
    let con = &w.con;
    let a = agent(Duration::from_secs(30));
    let own = format!("http://{}", con.addr);
    let evil = [("Origin", "https://evil.example")];
    // Every API route, read or change, refused with the reason; the same from curl (no Origin)
    // or the console's own page answered.
    for path in [
        "/api/status",
        "/api/snapshot.png",
        "/api/snapshot.png?width=32",
        "/api/bookmarks",
        "/api/nodes/node0/log",
    ] {
        let r = con.get(&a, path, &evil).unwrap();
        assert_eq!(r.status, 403, "{path}: {}", r.text());
        assert!(r.json()["error"].as_str().unwrap().contains("`https://evil.example` is not this console's"));
        // An <img> of another page: no Origin, the browser's Sec-Fetch-Site.
        let r = con.get(&a, path, &[("Sec-Fetch-Site", "cross-site")]).unwrap();
        assert_eq!(r.status, 403, "{path} from an <img>: {}", r.text());
        assert_eq!(con.get(&a, path, &[]).unwrap().status, 200, "{path} from curl");
        let page = [("Origin", own.as_str()), ("Sec-Fetch-Site", "same-origin")];
        assert_eq!(con.get(&a, path, &page).unwrap().status, 200, "{path} from the page");
    }
    let post = |origin: Option<&str>| {
        let mut req = a.post(format!("{}/api/render", con.base)).header("Content-Type", "application/json");
        if let Some(o) = origin {
            req = req.header("Origin", o);
        }
        let mut r = req.send("{\"exposure\": 0.8}").unwrap();
        (r.status().as_u16(), r.body_mut().read_to_string().unwrap())
    };
    let (status, body) = post(Some("http://evil.example"));
    assert_eq!(status, 403, "{body}");
    // The operator's changes alike: another site's page restarts, bookmarks, identifies and
    // locks nothing.
    for (path, body) in [
        ("/api/nodes/node0/restart", "{}"),
        ("/api/bookmarks", r#"{"name": "evil"}"#),
        ("/api/bookmarks/recall", r#"{"name": "evil"}"#),
        ("/api/bookmarks/delete", r#"{"name": "evil"}"#),
        ("/api/identify", r#"{"on": true}"#),
        ("/api/lock", "{}"),
        ("/api/lock/release", "{}"),
    ] {
        for headers in [vec![("Origin", "https://evil.example")], vec![("Sec-Fetch-Site", "cross-site")]] {
            let r = con.post(&a, path, body, &headers);
            assert_eq!(r.status, 403, "{path} {headers:?}: {}", r.text());
        }
    }
    let s = settled(con, &a, &[]);
    assert!(s["console"]["lock"].is_null() && s["wall"]["identify"] == false, "{}", s["console"]);
    assert!(w.nodes.iter().all(|n| n.restarts.lock().unwrap().is_empty()), "another site restarted a node");
    assert!(!w.dir.path().join("console-attack.bookmarks.toml").exists());
    assert_eq!(post(Some(&own)).0, 200);
    assert_eq!(post(None).0, 200);
    // The live status over a WebSocket: another site's page refused (before: node addresses,
    // memory, the volume's path and the camera to any page).
    let head = websocket(con.addr, "/api/live?hz=2", &[("Origin", "http://evil.example")]);
    assert!(head.starts_with("HTTP/1.1 403"), "{head}");
    let head = websocket(
        con.addr,
        "/api/live?hz=2",
        &[("Origin", own.as_str()), ("Sec-WebSocket-Protocol", "isowall")],
    );
    assert!(head.starts_with("HTTP/1.1 101"), "{head}");
    assert!(head.to_ascii_lowercase().contains("sec-websocket-protocol: isowall\r\n"), "{head}");
    assert!(websocket(con.addr, "/api/live", &[]).starts_with("HTTP/1.1 101"), "a script's WebSocket");
}

#[test]
fn a_token_is_never_taken_from_a_url_and_the_websocket_sends_it_as_a_subprotocol() {
    let token = "sesame-0123456789abcdef";
    let w = fake_wall(&["--token", token, "--read-only"], 1024);
    let con = &w.con;
    let a = agent(Duration::from_secs(30));
    let bearer = format!("Bearer {token}");
    assert_eq!(con.get(&a, "/api/status", &[("Authorization", bearer.as_str())]).unwrap().status, 200);
    let r = con.get(&a, &format!("/api/status?token={token}"), &[]).unwrap();
    assert_eq!(r.status, 400, "{}", r.text());
    assert!(r.text().contains("token in the URL"), "{}", r.text());
    let r = con
        .get(
            &a,
            &format!("/api/snapshot.png?download=1&token={token}"),
            &[("Authorization", bearer.as_str())],
        )
        .unwrap();
    assert_eq!(r.status, 400, "a token in the URL is refused even beside the header: {}", r.text());
    // The page's WebSocket: `isowall` and the token's bytes in hex as subprotocols.
    let hex: String = token.bytes().map(|b| format!("{b:02x}")).collect();
    let protocols = format!("isowall, isowall-token.{hex}");
    let head = websocket(con.addr, "/api/live", &[("Sec-WebSocket-Protocol", protocols.as_str())]);
    assert!(head.starts_with("HTTP/1.1 101"), "{head}");
    let head = websocket(con.addr, "/api/live", &[("Sec-WebSocket-Protocol", "isowall, isowall-token.00")]);
    assert!(head.starts_with("HTTP/1.1 401"), "{head}");
    let head = websocket(con.addr, &format!("/api/live?token={token}"), &[]);
    assert!(head.starts_with("HTTP/1.1 400"), "{head}");
    // The operator's changes: without the token 401, with it refused by --read-only (403).
    for (path, body) in [
        ("/api/nodes/node0/restart", "{}"),
        ("/api/bookmarks", r#"{"name": "x"}"#),
        ("/api/bookmarks/recall", r#"{"name": "x"}"#),
        ("/api/bookmarks/delete", r#"{"name": "x"}"#),
        ("/api/identify", r#"{"on": true}"#),
        ("/api/lock", "{}"),
        ("/api/lock/release", "{}"),
    ] {
        let r = a.post(format!("{}{path}", con.base)).header("Content-Type", "application/json").send(body);
        assert_eq!(r.unwrap().status().as_u16(), 401, "{path} without the token");
        let r = con.post(&a, path, body, &[]);
        assert_eq!(r.status, 403, "{path} on a read-only console: {}", r.text());
    }
    for path in ["/api/bookmarks", "/api/nodes/node0/log"] {
        assert_eq!(con.get(&a, path, &[]).unwrap().status, 401, "{path} without the token");
        assert_eq!(con.get(&a, path, &[("Authorization", bearer.as_str())]).unwrap().status, 200, "{path}");
    }
    assert!(w.nodes.iter().all(|n| n.restarts.lock().unwrap().is_empty()));
    // Nothing prints the token.
    assert!(!con.log().contains(token), "the console's log holds the token:\n{}", con.log());
}

/// Waits until `done` holds for the status (at most 20 s).
fn wait_status(con: &Console, what: &str, done: impl Fn(&Value) -> bool) -> Value {
    wait_until(what, Duration::from_secs(20), || {
        let s = con.status();
        if done(&s) {
            Ok(s)
        } else {
            Err(s.to_string())
        }
    })
}

/// Asks (as agent `a`, with `headers`) for a change that moves nothing on the wall, the paused
/// orbit's rate, and returns the first status that shows it: the console carries out changes in
/// order, so what any change asked before it did shows there too.
fn settled(con: &Console, a: &ureq::Agent, headers: &[(&str, &str)]) -> Value {
    let rate = con.status()["orbit"]["degrees_per_second"].as_f64().expect("the orbit's rate");
    let next = if rate < 180.0 { rate + 1.0 } else { rate - 1.0 };
    let r = con.post(a, "/api/camera", &format!("{{\"orbit_degrees_per_second\": {next}}}"), headers);
    assert_eq!(r.status, 200, "{}", r.text());
    wait_status(con, "the orbit's new rate in the status", |s| s["orbit"]["degrees_per_second"] == next)
}

#[test]
fn the_operator_lock_refuses_every_other_clients_change_and_reads_stay_open() {
    let w = fake_wall(&["--lock-idle-s", "3"], 1024);
    let con = &w.con;
    let (alice, mallory) = (agent(Duration::from_secs(30)), agent(Duration::from_secs(30)));
    let r = con.post(&alice, "/api/lock", r#"{"holder": "alice"}"#, &[]);
    assert_eq!(r.status, 200, "{}", r.text());
    let id = r.json()["lock_id"].as_str().unwrap().to_string();
    assert_eq!(id.len(), 32);
    let since = r.json()["since_unix_ms"].as_u64().unwrap();
    let before = wait_status(con, "the lock in the status", |s| s["console"]["lock"]["holder"] == "alice");
    // Every change of another client: 423, naming the holder and since when, whatever the id
    // it makes up.
    let changes = [
        ("/api/lock", r#"{"holder": "mallory"}"#),
        ("/api/lock/release", "{}"),
        ("/api/render", r#"{"exposure": 0.25}"#),
        ("/api/camera", r#"{"yaw_deg": 30}"#),
        ("/api/time", r#"{"rate": 2}"#),
        ("/api/bookmarks", r#"{"name": "stolen"}"#),
        ("/api/bookmarks/recall", r#"{"name": "stolen"}"#),
        ("/api/bookmarks/delete", r#"{"name": "stolen"}"#),
        ("/api/nodes/node0/restart", "{}"),
        ("/api/identify", r#"{"on": true}"#),
    ];
    let forged = "0".repeat(32);
    for (path, body) in changes {
        for headers in [vec![], vec![("X-Isowall-Lock", forged.as_str())], vec![("X-Isowall-Lock", "")]] {
            let r = con.post(&mallory, path, body, &headers);
            assert_eq!(r.status, 423, "{path} {headers:?}: {}", r.text());
            let j = r.json();
            assert_eq!(
                (j["holder"].as_str(), j["since_unix_ms"].as_u64()),
                (Some("alice"), Some(since)),
                "{j}"
            );
            assert!(j["error"].as_str().unwrap().contains("locked by `alice`"), "{j}");
        }
    }
    eprintln!("another client's 30 changes while alice holds the lock: all 423");
    // Reads stay open.
    let a = agent(Duration::from_secs(20));
    for path in ["/api/status", "/api/bookmarks", "/api/nodes/node0/log", "/api/snapshot.png?width=32"] {
        assert_eq!(con.get(&a, path, &[]).unwrap().status, 200, "{path}");
    }
    // Nothing changed: the settings, the camera, no restart, no bookmarks file.
    let mine = [("X-Isowall-Lock", id.as_str())];
    let after = settled(con, &alice, &mine);
    assert_eq!((&after["render"], &after["camera"]), (&before["render"], &before["camera"]));
    assert!(w.nodes.iter().all(|n| n.restarts.lock().unwrap().is_empty()));
    assert!(!w.dir.path().join("console-attack.bookmarks.toml").exists());
    assert_eq!(after["wall"]["identify"], false);
    // The holder's own changes go ahead.
    assert_eq!(con.post(&alice, "/api/render", r#"{"exposure": 0.5}"#, &mine).status, 200);
    wait_status(con, "the holder's change", |s| s["render"]["exposure"] == 0.5);
    // Idle for its 3 s: it lapses, and anybody may change the wall again. (A fixed time: the idle
    // time itself, counted from the holder's change above, answered before it starts.)
    std::thread::sleep(Duration::from_millis(3500));
    let r = con.post(&mallory, "/api/render", r#"{"exposure": 0.75}"#, &[]);
    assert_eq!(r.status, 200, "after the lock lapsed: {}", r.text());
    wait_status(con, "the lapsed lock", |s| s["console"]["lock"].is_null());
    // Taken again and released by its holder (only): open again.
    let r = con.post(&mallory, "/api/lock", r#"{"holder": "mallory"}"#, &[]);
    let id2 = r.json()["lock_id"].as_str().unwrap().to_string();
    assert_ne!(id2, id);
    assert_eq!(con.post(&alice, "/api/lock/release", "{}", &mine).status, 423);
    assert_eq!(
        con.post(&mallory, "/api/lock/release", "{}", &[("X-Isowall-Lock", id2.as_str())]).status,
        200
    );
    assert_eq!(con.post(&alice, "/api/render", r#"{"exposure": 1.0}"#, &[]).status, 200);
}

#[test]
fn restarts_logs_bookmarks_and_node_info_refuse_what_is_not_theirs() {
    let w = fake_wall(&[], 1024);
    let con = &w.con;
    let a = agent(Duration::from_secs(30));
    // What a node says of itself: kept as text, escaped, bounded (the page sets it as text).
    let s = wait_status(con, "node info", |s| s["nodes"][0]["version"] == "0.0.0-fake");
    let adapter = s["nodes"][0]["adapter"].as_str().unwrap();
    assert_eq!(adapter, "fake <script>alert('node0')</script>\\u{1b}[31m");
    assert_eq!(
        (s["nodes"][0]["backend"].as_str(), s["nodes"][0]["local_log"].as_bool()),
        (Some("Vulkan"), Some(false))
    );

    // Restart: only a node of the wall, as JSON; told over its connection with the reason
    // escaped and cut, then the node is back.
    for (path, body, status) in [
        ("/api/nodes/node9/restart", "{}", 404),
        ("/api/nodes/..%2Fnode0/restart", "{}", 404),
        ("/api/nodes/node0/restart", r#"{"reason": 5}"#, 422),
        ("/api/nodes/node0/restart", r#"{"why": "x"}"#, 422),
    ] {
        let r = con.post(&a, path, body, &[]);
        assert_eq!(r.status, status, "{path} {body}: {}", r.text());
    }
    let r = a
        .post(format!("{}/api/nodes/node0/restart", con.base))
        .header("Content-Type", "text/plain")
        .send("{}")
        .unwrap();
    assert_eq!(r.status().as_u16(), 415, "a form post cannot restart a node");
    assert!(w.nodes[0].restarts.lock().unwrap().is_empty(), "refused, yet restarted");
    let connections = w.nodes[0].connections.load(Ordering::Relaxed);
    let reason = format!("\u{1b}[2J<b>{}", "r".repeat(400));
    let r =
        con.post(&a, "/api/nodes/node0/restart", &serde_json::json!({ "reason": reason }).to_string(), &[]);
    assert_eq!(r.status, 200, "{}", r.text());
    assert!(
        r.json()["how"].as_str().unwrap().contains("told to restart over its connection"),
        "{}",
        r.text()
    );
    let give_up = Instant::now() + Duration::from_secs(20);
    while w.nodes[0].restarts.lock().unwrap().is_empty() {
        assert!(Instant::now() < give_up, "node0 never got its Restart:\n{}", con.log());
        std::thread::sleep(Duration::from_millis(50));
    }
    let told = w.nodes[0].restarts.lock().unwrap()[0].clone();
    assert!(told.starts_with("\\u{1b}[2J<b>rrr"), "{told}");
    assert!(told.chars().count() <= 310, "{} characters told", told.chars().count());
    assert!(w.nodes[1].restarts.lock().unwrap().is_empty(), "node1 was not asked");
    // The wall reconnects it, as any node that comes back.
    let give_up = Instant::now() + Duration::from_secs(30);
    while w.nodes[0].connections.load(Ordering::Relaxed) <= connections {
        assert!(Instant::now() < give_up, "node0 was not reconnected:\n{}", con.log());
        std::thread::sleep(Duration::from_millis(100));
    }
    wait_status(con, "node0 up again", |s| s["nodes"][0]["state"] == "up");

    // Logs: a node of the wall or nothing; a remote node's stays on its machine.
    for (path, status) in [
        ("/api/nodes/node0/log?lines=0", 400),
        ("/api/nodes/node0/log?lines=100000", 400),
        ("/api/nodes/node0/log?path=/etc/passwd", 400),
        ("/api/nodes/..%2F..%2Fetc%2Fpasswd/log", 404),
        ("/api/nodes/keys%2Fcontroller.key/log", 404),
    ] {
        assert_eq!(con.get(&a, path, &[]).unwrap().status, status, "{path}");
    }
    let log = con.get(&a, "/api/nodes/node1/log", &[]).unwrap().json();
    assert_eq!((log["local"].as_bool(), log["lines"].as_array().map(Vec::len)), (Some(false), Some(0)));
    assert!(log["note"].as_str().unwrap().contains("journalctl"), "{log}");

    // Bookmarks: names checked, unknown ones named, the file beside the config written whole.
    let file = w.dir.path().join("console-attack.bookmarks.toml");
    for name in ["", "../../etc/passwd", "<script>", "a\nb", " lead", &"n".repeat(41), "é"] {
        let body = serde_json::json!({ "name": name }).to_string();
        let r = con.post(&a, "/api/bookmarks", &body, &[]);
        assert_eq!((r.status, r.json()["field"].as_str()), (422, Some("name")), "{name:?}: {}", r.text());
    }
    assert!(!file.exists(), "a refused name wrote the file");
    assert_eq!(con.post(&a, "/api/bookmarks", r#"{"name": "front", "eye": [0, 0, 0]}"#, &[]).status, 422);
    let r = con.post(&a, "/api/bookmarks", r#"{"name": "front"}"#, &[]);
    assert_eq!(r.status, 200, "{}", r.text());
    assert_eq!(r.json()["bookmarks"][0]["name"], "front");
    assert!(std::fs::read_to_string(&file).unwrap().contains("name = \"front\""));
    assert_eq!(con.post(&a, "/api/bookmarks/recall", r#"{"name": "back"}"#, &[]).status, 404);
    assert_eq!(con.post(&a, "/api/bookmarks/delete", r#"{"name": "back"}"#, &[]).status, 404);
    // A malformed file: named at its line, listed as none, never written over.
    let broken = "[[bookmark]]\nname = \"front\"\neye = [1, 2]\n";
    std::fs::write(&file, broken).unwrap();
    let r = con.get(&a, "/api/bookmarks", &[]).unwrap();
    assert_eq!(r.status, 200);
    let error = r.json()["error"].as_str().unwrap().to_string();
    assert!(error.contains("console-attack.bookmarks.toml:3: "), "{error}");
    let r = con.post(&a, "/api/bookmarks", r#"{"name": "other"}"#, &[]);
    assert_eq!(r.status, 409, "{}", r.text());
    assert_eq!(std::fs::read_to_string(&file).unwrap(), broken, "a malformed file was written over");
    // A file too large to be bookmarks is not read whole.
    std::fs::write(&file, vec![b'#'; 1 << 20]).unwrap();
    let error = con.get(&a, "/api/bookmarks", &[]).unwrap().json()["error"].as_str().unwrap().to_string();
    assert!(error.contains("larger than"), "{error}");
    // A FIFO nobody writes, twice: each answer comes at once (nothing waits for a writer, no
    // thread is left blocked); a link out of the folder is not followed.
    std::fs::remove_file(&file).unwrap();
    assert!(std::process::Command::new("mkfifo").arg(&file).status().unwrap().success());
    for _ in 0..2 {
        let asked = Instant::now();
        let r =
            con.get(&agent(Duration::from_secs(10)), "/api/bookmarks", &[]).expect("an answer, not a hang");
        let error = r.json()["error"].as_str().unwrap_or_default().to_string();
        assert!(error.contains("FIFO"), "{error}");
        assert!(asked.elapsed() < Duration::from_secs(5), "{:?} for a FIFO", asked.elapsed());
    }
    std::fs::remove_file(&file).unwrap();
    let outside = w.dir.path().join("outside.toml");
    std::fs::write(
        &outside,
        "[[bookmark]]\nname = \"secret\"\neye = [1, 2, 3]\ntarget = [0, 0, 0]\nup = [0, 0, 1]\nfov_y = 40\n",
    )
    .unwrap();
    std::os::unix::fs::symlink(&outside, &file).unwrap();
    let r = con.get(&a, "/api/bookmarks", &[]).unwrap();
    assert!(!r.text().contains("secret"), "a link was followed: {}", r.text());
    assert!(r.json()["error"].as_str().unwrap_or_default().contains("symbolic link"), "{}", r.text());
    // The console runs on.
    let released = con.released();
    let give_up = Instant::now() + Duration::from_secs(20);
    while con.released() <= released {
        assert!(Instant::now() < give_up, "the frames stopped");
        std::thread::sleep(Duration::from_millis(100));
    }
}
