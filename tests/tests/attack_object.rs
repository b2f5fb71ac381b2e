//! Hostile peers in object space, over real processes on loopback: a 2x1 object-space wall of two
//! 480x360 tiles (`node0` shows `t0`, `node1` shows `t1`) driven by `isowall orbit`, and a real QUIC
//! client holding `node1`'s own certificate (what a compromised node has) that
//! (a) sends `node0` LZ4 bombs: messages of 200 rectangles, each the whole tile (1.2 MB decoded
//!     from 5 KB), for the frames around the wall's;
//! (b) sends `node0` pixels for far-future frames (2^40, u64::MAX ...);
//! (c) plays `node1` itself: it answers the controller (Ready at once, every frame) and takes the
//!     peers' connections, but never sends pixels and never reads them (a silent peer);
//! (d) on a wall that filters its composited tiles (`denoise = "on"`: pixels in the shading form),
//!     sends `node0` a shading pixel holding NaN, which would spread through the filter to its
//!     neighbours.
//! and on a balanced screen-space wall (`[wall] balance = true`, the torus in `t0` so that `node1`
//! renders rows of it), where a rectangle is accepted only as the controller's split gives it:
//! (e) `node1` sends `node0` the first row of `t0` with hits, a row the split did not give it;
//! (f) the LZ4 bomb of (a);
//! (g) `node1` played by a client that says every rectangle costs nothing (or reports no costs at
//!     all) and never sends the rows of `t0` the split gives it: the controller holds it out of
//!     the split after each miss, longer each time, so over 200 frames `node0` shows a hole in
//!     at most 2% of them (counted by the attacker itself: the frames whose split gave it rows
//!     of `t0`).
//! Each must leave `node0` serving: its peak resident memory (VmHWM) stays within
//! [`HWM_GROWTH_LIMIT_KIB`] of what it was before the attack, the wall keeps swapping with
//! `node0` ready in at least half the frames, and the refusal (the close reason the attacker reads, or the logs)
//! names the peer. Each test prints its numbers (`cargo test ... -- --nocapture`).

use isowall_e2e::fake_node::{runtime, FakeNode};
use isowall_e2e::{free_udp_ports, run_in, start_nodes, start_nodes_with, Daemon};
use isowall_model::codec;
use isowall_model::composite::{Layer, PeerPixels, PixelForm, PixelRect};
use isowall_model::messages::Message;
use isowall_model::node_machine::NodeOutput;
use isowall_net::transport;
use isowall_net::Identity;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

const TILE: (u32, u32) = (480, 360);
/// Long enough for two nodes rendering at once on a loaded lavapipe machine.
const DEADLINE_MS: u64 = 4000;
/// Frames the orbit drives, at [`FPS`] (10 s when every frame keeps up).
const FRAMES: u64 = 20;
const FPS: u32 = 2;
/// How far into the orbit the attacks start.
const ATTACK_AFTER: Duration = Duration::from_secs(3);
/// How much `node0`'s peak resident memory may grow during an attack (one bomb decoded whole
/// is 200 x 1.2 MB = 242 MB).
const HWM_GROWTH_LIMIT_KIB: u64 = 100 * 1024;

/// How the attacked wall shares its work.
#[derive(Clone, Copy, PartialEq)]
enum Mode {
    Object,
    /// Object space, filtering its composited tiles (pixels in the shading form).
    ObjectFiltered,
    /// Balanced screen space, the torus in `t0`.
    Balanced,
}

fn wall_config(dir: &Path, ports: &[u16], mode: Mode) -> PathBuf {
    let (w, h) = TILE;
    let render =
        if mode == Mode::ObjectFiltered { "ao_samples = 1\ndenoise = \"on\"" } else { "ao_samples = 0" };
    let (space, target) = match mode {
        Mode::Balanced => ("balance = true", "[70.0, 23.5, 23.5]"),
        _ => ("mode = \"object\"", "[23.5, 23.5, 23.5]"),
    };
    let mut s = format!(
        "[wall]\nname = \"attack-object\"\n{space}\ndeadline_ms = {DEADLINE_MS}\n\n\
         [camera]\neye = [60.0, -70.0, 45.0]\ntarget = {target}\nup = [0, 0, 1]\nfov_y = 40.0\n\n\
         [volume]\nsource = \"procedural:torus:48\"\n\n[render]\n{render}\n\n\
         [certificates]\ndir = \"keys\"\n"
    );
    for (i, port) in ports.iter().enumerate() {
        s += &format!(
            "\n[[tiles]]\nname = \"t{i}\"\nx = {}\ny = 0\nwidth = {w}\nheight = {h}\n\n\
             [[nodes]]\nname = \"node{i}\"\naddress = \"127.0.0.1:{port}\"\ntiles = [\"t{i}\"]\n",
            i as u32 * w
        );
    }
    let path = dir.join("attack-object.toml");
    std::fs::write(&path, s).unwrap();
    path
}

/// A field of /proc/PID/status in KiB (`VmRSS`, `VmHWM`).
fn status_kib(pid: u32, key: &str) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("/proc/PID/status");
    let line = status.lines().find(|l| l.starts_with(key)).unwrap_or_else(|| panic!("no {key}"));
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

/// The wall under attack: its directory, config and node0's address.
struct Wall {
    dir: tempfile::TempDir,
    config: PathBuf,
    node0: SocketAddr,
    node1: SocketAddr,
}

fn wall() -> Option<Wall> {
    wall_with(Mode::Object)
}

/// The wall, sharing its work by `mode`.
fn wall_with(mode: Mode) -> Option<Wall> {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(2);
    let config = wall_config(dir.path(), &ports, mode);
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let addr = |p: u16| SocketAddr::from(([127, 0, 0, 1], p));
    Some(Wall { config, node0: addr(ports[0]), node1: addr(ports[1]), dir })
}

/// What an orbit said: frames released, seconds, and the frames `node0` was ready for.
struct OrbitRun {
    frames: u64,
    seconds: f64,
    node0_ready: u64,
    stdout: String,
    stderr: String,
}

impl OrbitRun {
    /// `node0`'s frames scaled to 20 s.
    fn node0_per_20s(&self) -> f64 {
        self.node0_ready as f64 * 20.0 / self.seconds.max(1e-9)
    }
}

/// `isowall orbit` of [`FRAMES`] at [`FPS`] on its own thread.
fn orbit(w: &Wall) -> std::thread::JoinHandle<OrbitRun> {
    let (dir, config) = (w.dir.path().to_path_buf(), w.config.clone());
    std::thread::spawn(move || {
        let out = run_in(
            &dir,
            "isowall",
            &[
                "orbit",
                config.to_str().unwrap(),
                "--frames",
                &FRAMES.to_string(),
                "--fps",
                &FPS.to_string(),
                "--degrees-per-frame",
                "2",
            ],
        );
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        );
        let line = stdout.lines().find(|l| l.starts_with("frames: ")).unwrap_or_default();
        let mut words = line.split_whitespace();
        let frames = words.nth(1).and_then(|n| n.parse().ok()).unwrap_or(0);
        let seconds = words.nth(1).and_then(|n| n.parse().ok()).unwrap_or(f64::INFINITY);
        let stragglers = stdout
            .lines()
            .find(|l| l.starts_with("stragglers"))
            .map_or(0, |l| l.matches("node0@").count() as u64);
        OrbitRun { frames, seconds, node0_ready: frames.saturating_sub(stragglers), stdout, stderr }
    })
}

/// A client endpoint presenting `node1`'s own certificate.
fn node1_identity(w: &Wall) -> Identity {
    Identity::load(&w.dir.path().join("keys"), "node1").expect("node1's certificate")
}

/// Sends one pixels message on a new stream; `false` when the connection is gone.
async fn send_pixels(conn: &quinn::Connection, msg: &PeerPixels) -> bool {
    let bytes = codec::encode_pixels(msg).unwrap();
    let Ok(mut s) = conn.open_uni().await else { return false };
    if s.write_all(&bytes).await.is_err() {
        return false;
    }
    s.finish().is_ok()
}

/// The application close reason of a closed connection.
fn reason(e: &quinn::ConnectionError) -> String {
    match e {
        quinn::ConnectionError::ApplicationClosed(c) => String::from_utf8_lossy(&c.reason).into_owned(),
        other => other.to_string(),
    }
}

/// Connects to `node0` as `node1` and, until `stop`, sends the messages of `round(k)` for
/// k = 0, 1, ... every `every`, reconnecting when the daemon closes the connection. Returns the
/// close reasons and the messages sent.
async fn attack(
    w: &Wall,
    every: Duration,
    stop: Arc<AtomicBool>,
    round: impl Fn(u64) -> Vec<PeerPixels>,
) -> (Vec<String>, u64) {
    let endpoint = transport::client(&node1_identity(w)).unwrap();
    let (mut reasons, mut k, mut sent) = (Vec::new(), 0u64, 0u64);
    while !stop.load(Ordering::Relaxed) {
        let conn = match transport::connect(&endpoint, w.node0, "node0").await {
            Ok(c) => c,
            Err(e) => {
                reasons.push(format!("cannot connect: {e}"));
                // The attack's own pace: tried again a round later.
                tokio::time::sleep(every).await;
                continue;
            }
        };
        while !stop.load(Ordering::Relaxed) {
            let mut open = true;
            for msg in round(k) {
                // A daemon that does not read its streams gives no stream credit: a send that
                // waits longer than a round ends the connection (reconnect).
                open = tokio::time::timeout(every * 4, send_pixels(&conn, &msg)).await.unwrap_or(false);
                if !open || stop.load(Ordering::Relaxed) {
                    break;
                }
                sent += 1;
            }
            k += 1;
            let closed = tokio::time::timeout(every, conn.closed()).await;
            if let Ok(e) = closed {
                reasons.push(reason(&e));
                // Not a connection flood (a limit of its own): the next connection a round later.
                tokio::time::sleep(every).await;
                break;
            }
            if !open {
                break;
            }
        }
    }
    (reasons, sent)
}

/// Sends `rects` as `node1`'s pixels, every half second, for each of the eight frame ids around
/// the wall's (the orbit's clock, from the attack's start, [`ATTACK_AFTER`] into the orbit): live
/// frames, the ones a peer's pixels are for. Pixels for frames already shown are dropped unread,
/// and those far ahead refused as such.
async fn around_the_wall(w: &Wall, stop: Arc<AtomicBool>, rects: Vec<PixelRect>) -> (Vec<String>, u64) {
    let start = Instant::now();
    attack(w, Duration::from_millis(500), stop, move |_| {
        let shown = (start.elapsed() + ATTACK_AFTER).as_secs_f64() * f64::from(FPS);
        let wall_frame = 1 + shown as u64;
        (wall_frame.saturating_sub(4)..wall_frame + 4)
            .map(|id| PeerPixels { frame_id: id, node: "node1".into(), rects: rects.clone() })
            .collect()
    })
    .await
}

/// Starts both real nodes; `None` (skip) without a Vulkan adapter outside CI.
fn start_both(w: &Wall) -> Option<Vec<Daemon>> {
    start_nodes_with(w.dir.path(), &w.config, 2, |_| Vec::new(), None)
}

/// Runs the orbit while `attack` runs (from the orbit's start to its end); prints and checks
/// what each attack must leave: node0's memory, frames, the refusal naming `node1`.
fn under_attack<F, Fut>(what: &str, w: &Wall, node0: &mut Daemon, run_attack: F) -> (OrbitRun, Vec<String>)
where
    F: FnOnce(Arc<AtomicBool>) -> Fut + Send,
    Fut: std::future::Future<Output = (Vec<String>, u64)>,
{
    let pid = node0.child.id();
    let stop = Arc::new(AtomicBool::new(false));
    let orbit = orbit(w);
    // The wall's first frames before the attack, so the baseline includes a rendering node. A
    // fixed time on the orbit's paced clock: `around_the_wall` counts the wall's frames from it.
    std::thread::sleep(ATTACK_AFTER);
    let (rss0, hwm0) = (status_kib(pid, "VmRSS:"), status_kib(pid, "VmHWM:"));
    let started = Instant::now();
    let (run, (reasons, sent)) = std::thread::scope(|s| {
        let flag = stop.clone();
        let attack = s.spawn(move || {
            let runtime = runtime();
            runtime.block_on(run_attack(flag))
        });
        let run = orbit.join().unwrap();
        stop.store(true, Ordering::Relaxed);
        (run, attack.join().unwrap())
    });
    if let Some(status) = node0.child.try_wait().unwrap() {
        panic!("{what}: node0 exited ({status}):\n{}", node0.log_text());
    }
    let (rss1, hwm1) = (status_kib(pid, "VmRSS:"), status_kib(pid, "VmHWM:"));
    eprintln!(
        "{what}: node0 VmRSS {rss0} -> {rss1} KiB, VmHWM {hwm0} -> {hwm1} KiB ({:+} KiB); {sent} messages in {:.1} s, \
         {} connections closed; orbit: {} frames in {:.1} s, node0 ready in {} ({:.1} per 20 s)",
        hwm1 as i64 - hwm0 as i64,
        started.elapsed().as_secs_f64(),
        reasons.len(),
        run.frames,
        run.seconds,
        run.node0_ready,
        run.node0_per_20s(),
    );
    for r in reasons.iter().take(3) {
        eprintln!("{what}: closed: {r}");
    }
    assert_eq!(run.frames, FRAMES, "{what}: the orbit did not finish:\n{}\n{}", run.stdout, run.stderr);
    assert!(
        hwm1 <= hwm0 + HWM_GROWTH_LIMIT_KIB,
        "{what}: node0's peak memory grew by {} KiB (limit {HWM_GROWTH_LIMIT_KIB} KiB)",
        hwm1 - hwm0
    );
    assert!(
        run.node0_ready * 2 >= FRAMES,
        "{what}: node0 was ready in only {} of {FRAMES} frames:\n{}\n{}\n{}",
        run.node0_ready,
        run.stdout,
        run.stderr,
        node0.log_text()
    );
    (run, reasons)
}

/// A refusal names the attacker's certificate and says why.
fn assert_named(what: &str, reasons: &[String], why: &[&str], log: &str) {
    let named = reasons.iter().find(|r| r.contains("node1") && why.iter().any(|w| r.contains(w)));
    assert!(
        named.is_some(),
        "{what}: no close reason names node1 and says one of {why:?}: {reasons:?}\nnode0's log:\n{log}"
    );
}

#[test]
fn an_lz4_bomb_of_200_rectangles_is_refused_before_it_is_decompressed() {
    let Some(w) = wall() else { return };
    let Some(mut daemons) = start_both(&w) else { return };
    let (tw, th) = TILE;
    // The whole tile, no hits: 1.2 MB decoded (480x360 pixels of 7 bytes, depth f32 and sRGB8)
    // from a few KB.
    let rect = Layer::empty(0, 0, tw, th, PixelForm::Colour).encode("t0", true);
    eprintln!("one bomb rectangle: {} B on the wire, {} B decoded", rect.payload.len(), tw * th * 7);
    let rects: Vec<_> = (0..200).map(|_| rect.clone()).collect();
    let (run, reasons) =
        under_attack("LZ4 bomb", &w, &mut daemons[0], |stop| around_the_wall(&w, stop, rects.clone()));
    let log = daemons[0].log_text();
    assert_named("LZ4 bomb", &reasons, &["rectangles"], &log);
    assert!(run.stderr.lines().all(|l| !l.contains("node node1 is down")), "{}", run.stderr);
}

#[test]
fn a_shading_pixel_of_nan_is_refused_before_it_reaches_the_filter() {
    let Some(w) = wall_with(Mode::ObjectFiltered) else { return };
    let Some(mut daemons) = start_both(&w) else { return };
    // One pixel near the image's centre (t0's right edge), where both bricks' footprints lie
    // whatever the orbit's angle (the cut runs through the torus's middle), with a hit and NaN in
    // its AO sum: decoded, it would pass the footprint checks.
    let mut l = Layer::empty(470, 180, 1, 1, PixelForm::Shading);
    l.depth[0] = 50.0;
    l.shading[0] =
        [[0.5, 0.5, 0.5, 1.0], [0.0, 0.0, 1.0, 50.0], [0.0, 0.0, 1.0, f32::NAN], [0.5, 0.5, 0.5, 1.0]];
    let rects = vec![l.encode("t0", false)];
    let (_run, reasons) =
        under_attack("NaN shading", &w, &mut daemons[0], |stop| around_the_wall(&w, stop, rects.clone()));
    let log = daemons[0].log_text();
    assert_named("NaN shading", &reasons, &["NaN"], &log);
}

#[test]
fn far_future_frame_ids_are_refused_and_not_kept_pending() {
    let Some(w) = wall() else { return };
    let Some(mut daemons) = start_both(&w) else { return };
    let ids = [1u64 << 40, u64::MAX, u64::MAX - 1, 1 << 20, 1 << 50, u64::MAX / 2, 1 << 33, 1 << 62, 1 << 41];
    let (_run, reasons) = under_attack("far-future frames", &w, &mut daemons[0], |stop| {
        let w = &w;
        async move {
            attack(w, Duration::from_millis(100), stop, move |k| {
                let frame_id = ids[k as usize % ids.len()] - (k / ids.len() as u64);
                vec![PeerPixels { frame_id, node: "node1".into(), rects: Vec::new() }]
            })
            .await
        }
    });
    let log = daemons[0].log_text();
    assert_named("far-future frames", &reasons, &["ahead"], &log);
}

/// What a fake `node1` says of its work on a balanced wall.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Lie {
    /// Nothing: object space, no costs.
    None,
    /// Every rectangle the split gives it cost 0.
    FreeRows,
    /// No costs at all.
    NoCosts,
}

/// Plays `node1` for the controller (Ready at once for every frame) and takes its peers'
/// connections without ever reading them or sending pixels, until `stop`. On a balanced wall it
/// reports its rectangles' costs as `lie` says, and counts in `holes` the frames whose split gave
/// it rows of `t0` (which it never sends).
async fn silent_node(identity: Identity, addr: SocketAddr, stop: Arc<AtomicBool>) {
    fake_node1(identity, addr, stop, Lie::None, Arc::new(std::sync::atomic::AtomicU64::new(0))).await
}

async fn fake_node1(
    identity: Identity,
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    lie: Lie,
    holes: Arc<std::sync::atomic::AtomicU64>,
) {
    let endpoint = transport::server(addr, &identity).expect("listen as node1");
    let mut held = Vec::new();
    while !stop.load(Ordering::Relaxed) {
        let Ok(Some(incoming)) = tokio::time::timeout(Duration::from_millis(200), endpoint.accept()).await
        else {
            continue;
        };
        let Ok(conn) = incoming.await else { continue };
        if !isowall_net::tls::peer_is(&conn, isowall_net::tls::CONTROLLER) {
            // A peer's pixel connection: kept open, never read.
            held.push(conn);
            continue;
        }
        let stop = stop.clone();
        let holes = holes.clone();
        tokio::spawn(async move {
            // The splits it was sent: (from frame, rectangles).
            let mut splits: Vec<(u64, Vec<isowall_model::wire::WireWorkRect>)> = Vec::new();
            let Some(mut node) = FakeNode::greet(conn, "node1", vec!["t1".into()]).await else { return };
            while let Some(o) = node.next().await {
                if stop.load(Ordering::Relaxed) {
                    return;
                }
                let open = match o {
                    NodeOutput::Render { state, .. } => {
                        let id = state.frame_id;
                        let split = splits.iter().rev().find(|(from, _)| *from <= id);
                        let mine: Vec<_> = split
                            .map(|(_, r)| r.iter().filter(|r| r.renderer == 1).collect())
                            .unwrap_or_default();
                        if mine.iter().any(|r| r.tile == 0) {
                            holes.fetch_add(1, Ordering::Relaxed);
                        }
                        if lie == Lie::FreeRows && !mine.is_empty() {
                            let costs = mine
                                .iter()
                                .map(|r| isowall_model::wire::WireRectCost {
                                    tile: r.tile,
                                    first_row: r.first_row,
                                    rows: r.rows,
                                    cost: 0,
                                })
                                .collect();
                            if !node.send(&Message::RectCosts { frame_id: id, costs }).await {
                                return;
                            }
                        }
                        node.rendered(id, Duration::from_millis(1));
                        true
                    }
                    NodeOutput::SnapshotWanted | NodeOutput::ThumbnailWanted { .. } => {
                        node.send(&Message::Snapshot { tiles: vec![] }).await
                    }
                    NodeOutput::LoadBrick { brick } => {
                        let reason = "a silent test peer".to_string();
                        node.send(&Message::BrickFailed { brick, reason }).await
                    }
                    NodeOutput::Split { from_frame, split } => {
                        splits.push((from_frame, split.rects));
                        true
                    }
                    NodeOutput::Restart { .. } => return,
                    // Sent as the machine says, presented at once whatever the present time.
                    other => node.answer(other).await,
                };
                if !open {
                    return;
                }
            }
        });
    }
    drop(held);
}

#[test]
fn a_silent_peer_does_not_freeze_the_wall() {
    let Some(w) = wall() else { return };
    let runtime = runtime();
    let stop = Arc::new(AtomicBool::new(false));
    let fake = runtime.spawn(silent_node(node1_identity(&w), w.node1, stop.clone()));
    let Some(mut nodes) = start_nodes(w.dir.path(), &w.config, 1) else { return };
    let mut node0 = nodes.remove(0);
    let (run, _) = under_attack("silent peer", &w, &mut node0, |_| async { (Vec::new(), 0) });
    stop.store(true, Ordering::Relaxed);
    let _ = runtime.block_on(fake);
    // node0 says which peer's pixels it went on without, and so does the controller.
    let log = node0.log_text();
    assert!(log.contains("node1") && log.contains("deadline"), "node0's log does not name node1:\n{log}");
    assert!(
        run.stderr.contains("node1") && run.stderr.contains("pixels"),
        "the controller does not name node1's missing pixels:\n{}",
        run.stderr
    );
}

#[test]
fn on_a_balanced_wall_rows_the_split_did_not_give_a_node_are_refused() {
    let Some(w) = wall_with(Mode::Balanced) else { return };
    let Some(mut daemons) = start_both(&w) else { return };
    let (tw, _) = TILE;
    // t0's first row, every pixel a hit: node0 keeps its tile's first rows (the split gives away
    // its last ones), so these are node0's own, and no more bytes than node1's share.
    let mut l = Layer::empty(0, 0, tw, 1, PixelForm::Colour);
    l.depth.iter_mut().for_each(|d| *d = 1.0);
    l.rgb8.iter_mut().for_each(|c| *c = 255);
    let rects = vec![l.encode("t0", true)];
    let (run, reasons) =
        under_attack("rows not given", &w, &mut daemons[0], |stop| around_the_wall(&w, stop, rects.clone()));
    let log = daemons[0].log_text();
    assert_named(
        "rows not given",
        &reasons,
        &["outside what the frame gives it", "bytes", "rectangles"],
        &log,
    );
    assert!(run.stderr.lines().all(|l| !l.contains("node node1 is down")), "{}", run.stderr);
    // The wall balanced: node1 rendered rows of t0 and sent them.
    assert!(run.stdout.contains("balance (bytes of rectangles"), "{}", run.stdout);
}

#[test]
fn on_a_balanced_wall_an_lz4_bomb_is_refused_before_it_is_decompressed() {
    let Some(w) = wall_with(Mode::Balanced) else { return };
    let Some(mut daemons) = start_both(&w) else { return };
    let (tw, th) = TILE;
    let rect = Layer::empty(0, 0, tw, th, PixelForm::Colour).encode("t0", true);
    let rects: Vec<_> = (0..200).map(|_| rect.clone()).collect();
    let (_run, reasons) = under_attack("balanced LZ4 bomb", &w, &mut daemons[0], |stop| {
        around_the_wall(&w, stop, rects.clone())
    });
    let log = daemons[0].log_text();
    assert_named("balanced LZ4 bomb", &reasons, &["rectangles", "bytes"], &log);
}

/// (g): a balanced wall's `node1` lies about its work whenever it is let into the split.
fn lying_node_holes(lie: Lie) {
    let what = format!("lying node ({lie:?})");
    let Some(w) = wall_with(Mode::Balanced) else { return };
    let runtime = runtime();
    let stop = Arc::new(AtomicBool::new(false));
    let holes = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let fake = runtime.spawn(fake_node1(node1_identity(&w), w.node1, stop.clone(), lie, holes.clone()));
    let Some(mut nodes) = start_nodes(w.dir.path(), &w.config, 1) else { return };
    let mut node0 = nodes.remove(0);
    const LIE_FRAMES: u64 = 200;
    let out = run_in(
        w.dir.path(),
        "isowall",
        &[
            "orbit",
            w.config.to_str().unwrap(),
            "--frames",
            &LIE_FRAMES.to_string(),
            "--degrees-per-frame",
            "1",
        ],
    );
    stop.store(true, Ordering::Relaxed);
    let _ = runtime.block_on(fake);
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{what}: the orbit failed:\n{stdout}\n{stderr}");
    let held: Vec<&str> = stderr.lines().filter(|l| l.contains("isowall: balance: node node1")).collect();
    let holes = holes.load(Ordering::Relaxed);
    eprintln!(
        "{what}: node0 showed a hole in {holes} of {LIE_FRAMES} frames; node1 held out {} times",
        held.len()
    );
    for l in &held {
        eprintln!("{what}: {l}");
    }
    assert!(!held.is_empty(), "{what}: node1 was never held out of the split:\n{stderr}");
    assert!(held.len() <= 8, "{what}: held out {} times in {LIE_FRAMES} frames: once a hold", held.len());
    assert!(holes >= 1, "{what}: the split never gave node1 rows of t0: the attack did nothing");
    assert!(
        holes * 50 <= LIE_FRAMES,
        "{what}: {holes} of {LIE_FRAMES} frames of node0 had a hole (more than 2%)"
    );
    assert!(node0.child.try_wait().unwrap().is_none(), "{what}: node0 exited:\n{}", node0.log_text());
}

#[test]
fn on_a_balanced_wall_a_node_that_says_its_rows_cost_nothing_takes_no_screen() {
    lying_node_holes(Lie::FreeRows);
}

#[test]
fn on_a_balanced_wall_a_node_that_never_reports_its_costs_takes_no_screen() {
    lying_node_holes(Lie::NoCosts);
}
