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
//!   a token is never taken from a URL.

use isowall_e2e::{bin, free_udp_ports, run_in, wall_config_2x1};
use isowall_model::messages::{Message, TileImage};
use isowall_model::node_machine::{NodeMachine, NodeOutput};
use isowall_net::transport::{self, Channel};
use isowall_net::Identity;
use serde_json::Value;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap()
}

/// What a node played by the test does and counts.
#[derive(Default)]
struct NodeCtl {
    /// Answers no snapshot or thumbnail request while set.
    silent: AtomicBool,
    /// Snapshot and thumbnail requests received.
    asked: AtomicU64,
}

/// A node played by the test on `port` with `keys/NAME.*`: its tile `(name, w, h)` blue.
async fn fake_node(keys: PathBuf, name: String, port: u16, tile: (String, u32, u32), ctl: Arc<NodeCtl>) {
    let identity = Identity::load(&keys, &name).unwrap();
    let addr: SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let endpoint = transport::server(addr, &identity).unwrap();
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
        let Ok(Channel { mut sender, mut receiver, .. }) = Channel::accept(conn, "controller", 1 << 20).await
        else {
            continue;
        };
        let mut m = NodeMachine::new(name.clone(), vec![tname.clone()]);
        let epoch = Instant::now();
        if sender.send(&m.hello()).await.is_err() {
            continue;
        }
        'conn: while let Ok(Some(msg)) = receiver.recv().await {
            let Ok(out) = m.handle(epoch.elapsed(), msg) else { break };
            let mut queue: std::collections::VecDeque<NodeOutput> = out.into();
            while let Some(out) = queue.pop_front() {
                let answer = match out {
                    NodeOutput::Send(msg) => Some(msg),
                    NodeOutput::Render { state, .. } => {
                        queue.extend(m.render_done(
                            epoch.elapsed(),
                            state.frame_id,
                            Duration::from_micros(50),
                        ));
                        None
                    }
                    NodeOutput::Present { frame_id, .. } => {
                        queue.extend(m.presented(epoch.elapsed(), frame_id, epoch.elapsed()));
                        None
                    }
                    NodeOutput::SnapshotWanted | NodeOutput::ThumbnailWanted { .. } => {
                        ctl.asked.fetch_add(1, Ordering::Relaxed);
                        let divisor = match out {
                            NodeOutput::ThumbnailWanted { divisor } => divisor,
                            _ => 1,
                        };
                        (!ctl.silent.load(Ordering::Relaxed))
                            .then(|| Message::Snapshot { tiles: vec![image.downscaled(divisor)] })
                    }
                    NodeOutput::Closed { .. } => break 'conn,
                    _ => None,
                };
                if let Some(msg) = answer {
                    if sender.send(&msg).await.is_err() {
                        break 'conn;
                    }
                }
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
    _dir: tempfile::TempDir,
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
    FakeWall { _dir: dir, _rt: rt, nodes, con }
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
    // snapshot and leaves; once node1 answers again, a thumbnail comes at once, not after the
    // abandoned request's 5 s give-up.
    std::thread::sleep(Duration::from_millis(1500));
    let _ = con.get(&agent(Duration::from_millis(300)), "/api/snapshot.png", &[]);
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
    std::thread::sleep(Duration::from_secs(7));
    let mut closed = 0;
    for s in &mut held {
        s.set_read_timeout(Some(Duration::from_millis(20))).unwrap();
        let mut b = [0u8; 512];
        // Closed: an end of file or a reset; open: nothing to read yet.
        match s.read(&mut b) {
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            _ => closed += 1,
        }
    }
    eprintln!("{closed} of {} closed after 7.5 s", held.len());
    assert_eq!(closed, held.len(), "half-sent requests still open after 7.5 s");
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
    for path in ["/api/status", "/api/snapshot.png", "/api/snapshot.png?width=32"] {
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
    // Nothing prints the token.
    assert!(!con.log().contains(token), "the console's log holds the token:\n{}", con.log());
}
