//! Bad input against a running wall node:
//! the two daemons of a 2-node wall on loopback get
//! (a) garbage UDP datagrams on their ports (random bytes, QUIC long-header packets that do not
//!     decrypt, truncated ones, short-header ones);
//! (b) controllers with the wall's certificate that, each on its own connection, send a frame
//!     whose length is past the configured limit, a truncated frame and then the stream's end,
//!     bytes that do not decode, a Hello of another protocol version, a Swap for a frame never
//!     sent; and a client without a certificate;
//! (c) 200 such connections, with the daemon's resident memory measured after 20 and after 200.
//! Each bad connection must be closed by the daemon with a reason the client reads (the QUIC
//! application close reason), the certificate-less client must get nothing, the daemons must keep
//! running, their memory must not grow with the connections, and a normal `isowall orbit`
//! must work afterwards. (A peer with another CA's certificate: tests/tests/wall.rs.)

use isowall_e2e::{free_udp_ports, in_ci, run_in, Daemon};
use isowall_model::codec;
use isowall_model::messages::{Message, Role, PROTOCOL_VERSION};
use isowall_net::transport::{self, Channel};
use isowall_net::{Identity, ALPN};
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The wall's message limit: small, so "past the limit" is the configured limit, not the codec's.
const LIMIT: u32 = 65_536;

/// How much the daemon's resident memory may grow from the 20th to the 200th bad connection.
const RSS_GROWTH_LIMIT_KIB: u64 = 8 * 1024;

fn wall_config(dir: &Path, ports: &[u16]) -> PathBuf {
    let mut s = format!(
        "[wall]\nname = \"bad-input\"\ndeadline_ms = 20000\nmessage_limit_bytes = {LIMIT}\n\n\
         [camera]\neye = [60.0, -70.0, 45.0]\ntarget = [23.5, 23.5, 23.5]\nup = [0, 0, 1]\nfov_y = 40.0\n\n\
         [volume]\nsource = \"procedural:torus:32\"\n\n[render]\nao_samples = 0\n\n\
         [certificates]\ndir = \"keys\"\n"
    );
    for (i, port) in ports.iter().enumerate() {
        s += &format!(
            "\n[[tiles]]\nname = \"t{i}\"\nx = {}\ny = 0\nwidth = 16\nheight = 12\n\n\
             [[nodes]]\nname = \"node{i}\"\naddress = \"127.0.0.1:{port}\"\ntiles = [\"t{i}\"]\n",
            16 * i
        );
    }
    let path = dir.join("bad-input.toml");
    std::fs::write(&path, s).unwrap();
    path
}

/// The kinds of bad connection.
#[derive(Clone, Copy, Debug)]
enum Bad {
    /// After the Hello, a frame header whose length is one past the wall's limit.
    Oversized,
    /// After the Hello, a frame without its last two bytes, then the end of the stream.
    Truncated,
    /// After the Hello, a well-framed body that is not a message.
    Undecodable,
    /// A Hello of another protocol version.
    WrongVersion,
    /// After the Hello, a Swap for a frame never sent.
    OutOfOrder,
}

const ALL_BAD: [Bad; 5] =
    [Bad::Oversized, Bad::Truncated, Bad::Undecodable, Bad::WrongVersion, Bad::OutOfOrder];

impl Bad {
    /// What the close reason must say.
    fn expected(self) -> Vec<String> {
        match self {
            Bad::Oversized => {
                vec![format!("a frame of {} bytes is over the limit of {LIMIT} bytes", LIMIT + 1)]
            }
            Bad::Truncated => vec!["the stream ended inside a frame".into()],
            Bad::Undecodable => vec!["malformed message".into()],
            Bad::WrongVersion => vec![
                format!("protocol version {}", PROTOCOL_VERSION + 98),
                format!("this build speaks {PROTOCOL_VERSION}"),
            ],
            Bad::OutOfOrder => vec!["Swap for frame 41, which is not rendered".into()],
        }
    }
}

/// Connection attempts the daemon refused before their handshake (it limits handshakes per
/// source address, and this test spends them from one address).
static REFUSED: AtomicUsize = AtomicUsize::new(0);

/// Connects with the wall's certificate; a connection refused before its handshake is tried again
/// a quarter of a second later, as the controller does, for at most 20 s.
async fn connect_with_the_walls_certificate(
    endpoint: &quinn::Endpoint,
    addr: SocketAddr,
) -> quinn::Connection {
    let give_up = Instant::now() + Duration::from_secs(20);
    loop {
        match transport::connect(endpoint, addr, "node0").await {
            Ok(conn) => return conn,
            Err(e) if e.to_string().contains("refused") && Instant::now() < give_up => {
                REFUSED.fetch_add(1, Ordering::Relaxed);
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
            Err(e) => panic!("connect with the wall's certificate: {e}"),
        }
    }
}

/// Plays one bad controller on its own connection; returns the daemon's close reason.
async fn bad_controller(endpoint: &quinn::Endpoint, addr: SocketAddr, bad: Bad) -> String {
    let conn = connect_with_the_walls_certificate(endpoint, addr).await;
    let Channel { connection, mut sender, mut receiver } =
        Channel::open(conn, "node0", 1 << 20).await.expect("open the channel");
    let hello = codec::hello(isowall_net::tls::CONTROLLER, Role::Controller);
    match bad {
        Bad::WrongVersion => {
            let old = Message::Hello {
                version: PROTOCOL_VERSION + 98,
                name: isowall_net::tls::CONTROLLER.into(),
                role: Role::Controller,
            };
            sender.send(&old).await.unwrap();
        }
        Bad::Oversized => {
            sender.send(&hello).await.unwrap();
            let mut bytes = (LIMIT + 1).to_le_bytes().to_vec();
            bytes.extend([0u8; 64]);
            sender.send_raw(&bytes).await.unwrap();
        }
        Bad::Truncated => {
            sender.send(&hello).await.unwrap();
            let f = codec::frame(&Message::Ping { id: 1, t0_us: 123_456_789 }).unwrap();
            sender.send_raw(&f[..f.len() - 2]).await.unwrap();
            sender.finish().unwrap();
        }
        Bad::Undecodable => {
            sender.send(&hello).await.unwrap();
            sender.send_raw(&[5, 0, 0, 0, 200, 1, 2, 3, 4]).await.unwrap();
        }
        Bad::OutOfOrder => {
            sender.send(&hello).await.unwrap();
            sender.send(&Message::Swap { frame_id: 41, present_at_us: None }).await.unwrap();
        }
    }
    // The daemon greets first, whatever comes next.
    let first = tokio::time::timeout(Duration::from_secs(10), receiver.recv()).await;
    if let Ok(Ok(Some(m))) = &first {
        assert!(matches!(m, Message::Hello { .. }), "{bad:?}: the daemon said {m:?} first");
    }
    let closed = tokio::time::timeout(Duration::from_secs(10), connection.closed())
        .await
        .unwrap_or_else(|_| panic!("{bad:?}: the daemon did not close the connection within 10 s"));
    match closed {
        quinn::ConnectionError::ApplicationClosed(c) => String::from_utf8_lossy(&c.reason).into_owned(),
        other => panic!("{bad:?}: the connection ended without an application reason: {other}"),
    }
}

/// A client that trusts the wall CA but presents no certificate: it must not get to say or hear
/// anything. Returns how it failed.
async fn certificate_less_client(keys: &Path, addr: SocketAddr) -> String {
    use rustls::pki_types::{pem::PemObject, CertificateDer};
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut roots = rustls::RootCertStore::empty();
    roots.add(CertificateDer::from_pem_file(keys.join("ca.pem")).unwrap()).unwrap();
    let mut tls = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth();
    tls.alpn_protocols = vec![ALPN.to_vec()];
    let quic = quinn::crypto::rustls::QuicClientConfig::try_from(tls).unwrap();
    let mut endpoint = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
    endpoint.set_default_client_config(quinn::ClientConfig::new(Arc::new(quic)));
    let attempt = async {
        let conn =
            endpoint.connect(addr, "node0").map_err(|e| e.to_string())?.await.map_err(|e| e.to_string())?;
        // TLS 1.3: the client may finish its handshake before the daemon checks its certificate.
        let why = |e: String| conn.close_reason().map_or(e, |r| r.to_string());
        let Channel { mut sender, mut receiver, .. } =
            Channel::open(conn.clone(), "node0", 1 << 20).await.map_err(|e| why(e.to_string()))?;
        sender.send(&codec::hello("intruder", Role::Controller)).await.map_err(|e| why(e.to_string()))?;
        match receiver.recv().await {
            Ok(m) => Err(format!("the daemon answered a client without a certificate: {m:?}")),
            Err(e) => Ok(why(e.to_string())),
        }
    };
    let r = tokio::time::timeout(Duration::from_secs(10), attempt).await.expect("the refusal took over 10 s");
    endpoint.close(0u32.into(), b"");
    match r {
        Ok(how) => how,
        Err(e) if e.starts_with("the daemon answered") => panic!("{e}"),
        Err(e) => e,
    }
}

/// Garbage datagrams to `addr`: random bytes, QUIC long-header packets (version 1, Initial, with
/// random payloads that do not decrypt), truncated ones, short-header ones, an unknown version.
fn garbage_datagrams(addr: SocketAddr, seed: u64) -> usize {
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut s = seed;
    let mut rnd = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    let mut sent = 0;
    for i in 0..600 {
        let mut p: Vec<u8> = Vec::new();
        match i % 5 {
            0 => p.extend((0..1 + rnd() % 1400).map(|_| rnd() as u8)),
            1 | 2 => {
                // Initial: 0b1100_0000 | reserved/pn bits, version 1, DCID, SCID, token, length.
                p.push(0xc0 | (rnd() as u8 & 0x0f));
                p.extend(1u32.to_be_bytes());
                p.push(8);
                p.extend((0..8).map(|_| rnd() as u8));
                p.push(8);
                p.extend((0..8).map(|_| rnd() as u8));
                p.push(0); // no token
                p.extend([0x44, 0xd0]); // length 1232 (varint)
                while p.len() < 1252 {
                    p.push(rnd() as u8);
                }
                if i % 5 == 2 {
                    p.truncate(1 + (rnd() % 60) as usize); // cut inside the header
                }
            }
            3 => {
                p.push(0x40 | (rnd() as u8 & 0x3f));
                p.extend((0..20 + rnd() % 100).map(|_| rnd() as u8));
            }
            _ => {
                p.push(0xc0);
                p.extend(0x1a2a_3a4au32.to_be_bytes()); // a version nobody speaks
                p.push(8);
                p.extend((0..8).map(|_| rnd() as u8));
                p.push(0);
                p.resize(1200, 0);
            }
        }
        if sock.send_to(&p, addr).is_ok() {
            sent += 1;
        }
    }
    sent
}

/// The resident set of a process in KiB (`VmRSS` of /proc/PID/status).
fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("/proc/PID/status");
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).expect("VmRSS");
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

fn alive(d: &mut Daemon, name: &str) {
    if let Some(status) = d.child.try_wait().unwrap() {
        panic!("{name} exited ({status}):\n{}", d.log_text());
    }
}

#[test]
fn bad_input_closes_that_connection_with_a_reason_and_the_wall_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config(dir.path(), &ports);
    let cfg = config.to_str().unwrap();
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", cfg]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let t0 = Instant::now();
    let mut daemons: Vec<Daemon> =
        (0..2).map(|i| Daemon::start(dir.path(), &config, &format!("node{i}"), &[])).collect();
    for (i, d) in daemons.iter_mut().enumerate() {
        if !d.wait_ready(Duration::from_secs(120)) {
            let log = d.log_text();
            if log.contains("no Vulkan adapter") && !in_ci() {
                eprintln!("skipping: no Vulkan adapter (install mesa-vulkan-drivers)");
                return;
            }
            panic!("node{i} did not start:\n{log}");
        }
    }
    eprintln!("daemons ready in {:.1} s", t0.elapsed().as_secs_f64());
    let addrs: Vec<SocketAddr> = ports.iter().map(|p| SocketAddr::from(([127, 0, 0, 1], *p))).collect();
    let pid = daemons[0].child.id();

    // (a) Garbage datagrams to every listening port.
    for (i, &addr) in addrs.iter().enumerate() {
        let n = garbage_datagrams(addr, 0x5eed_0000 + i as u64);
        eprintln!("sent {n} garbage datagrams to node{i} ({addr})");
    }
    // A moment for a daemon the garbage crashed to be gone; the connections and the orbit below
    // show that they still serve.
    std::thread::sleep(Duration::from_millis(300));
    alive(&mut daemons[0], "node0");
    alive(&mut daemons[1], "node1");

    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let keys = dir.path().join("keys");
    let identity = Identity::load(&keys, isowall_net::tls::CONTROLLER).unwrap();
    let (rss_start, rss_20, rss_200, elapsed) = runtime.block_on(async {
        let endpoint = transport::client(&identity).unwrap();
        let rss_start = rss_kib(pid);

        // (b) Each kind once, each on its own connection, each closed with its reason.
        for bad in ALL_BAD {
            let reason = bad_controller(&endpoint, addrs[0], bad).await;
            eprintln!("{bad:?}: closed with \"{reason}\"");
            for want in bad.expected() {
                assert!(reason.contains(&want), "{bad:?}: the reason \"{reason}\" does not say \"{want}\"");
            }
        }
        let how = certificate_less_client(&keys, addrs[0]).await;
        eprintln!("no certificate: refused ({how})");

        // (c) Memory: 200 bad connections in all (every kind in turn, and certificate-less ones).
        let start = Instant::now();
        let mut rss_20 = 0;
        for i in ALL_BAD.len() + 1..200 {
            if i % 6 == 5 {
                certificate_less_client(&keys, addrs[0]).await;
            } else {
                let bad = ALL_BAD[i % 6];
                let reason = bad_controller(&endpoint, addrs[0], bad).await;
                assert!(reason.contains(&bad.expected()[0]), "{bad:?} (connection {i}): \"{reason}\"");
            }
            if i + 1 == 20 {
                // The same pause before both readings, for the daemon to let go of the last
                // connection: the two readings compare like with like.
                tokio::time::sleep(Duration::from_millis(200)).await;
                rss_20 = rss_kib(pid);
            }
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
        let rss_200 = rss_kib(pid);
        endpoint.wait_idle().await;
        (rss_start, rss_20, rss_200, start.elapsed())
    });
    eprintln!(
        "node0 VmRSS: {rss_start} KiB before, {rss_20} KiB after 20 bad connections, {rss_200} KiB after 200 \
         ({:+} KiB; the last 194 connections in {:.1} s; {} attempts refused before their handshake and \
         tried again)",
        rss_200 as i64 - rss_20 as i64,
        elapsed.as_secs_f64(),
        REFUSED.load(Ordering::Relaxed)
    );
    alive(&mut daemons[0], "node0");
    alive(&mut daemons[1], "node1");
    assert!(
        rss_200 <= rss_20 + RSS_GROWTH_LIMIT_KIB,
        "node0's memory grew by {} KiB from 20 to 200 bad connections (limit {RSS_GROWTH_LIMIT_KIB} KiB)",
        rss_200 - rss_20
    );

    // The wall still works: a normal controller drives both nodes.
    let t1 = Instant::now();
    let out = run_in(dir.path(), "isowall", &["orbit", cfg, "--frames", "2"]);
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(
        out.status.success(),
        "orbit after the bad input failed:\n{stdout}\n{stderr}\n{}",
        daemons[0].log_text()
    );
    assert!(stdout.contains("frames: 2"), "{stdout}");
    eprintln!("orbit of 2 frames after the bad input: ok in {:.1} s", t1.elapsed().as_secs_f64());

    let log = daemons[0].log_text();
    assert!(!log.contains("panicked"), "node0 panicked:\n{log}");
    assert!(log.contains("refused a connection"), "node0 did not log the certificate-less client:\n{log}");
    for d in &daemons {
        assert!(!d.log_text().contains("panicked"));
    }
}
