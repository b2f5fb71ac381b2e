//! The frame protocol on a simulated network: one `FrameController` and N `NodeMachine`s joined
//! by links with latency, jitter and loss, on a virtual clock, with a seeded PRNG. Every message
//! goes through the codec (frames and a streaming decoder per link). The simulation is the "glue"
//! a real network layer will be: it shows what that glue must do, and the tests hold the protocol
//! to DESIGN.md's "Distribution" and "Faults".
//!
//! Time: the controller's clock is the true time; node i's clock is true time + its offset.

mod support;

use std::collections::{BTreeMap, BinaryHeap};
use std::time::Duration;
use support::{Rng, Scheduled};

use isowall_model::codec::{self, Decoder};
use isowall_model::frame_controller::{ControllerOutput, FrameController, FrameStats};
use isowall_model::messages::{Message, ProtocolError, Role, TileImage};
use isowall_model::node_machine::{NodeMachine, NodeOutput};
use isowall_model::render_state::RenderSettings;
use isowall_model::swap_timing::{MarginSetting, SwapTiming};
use isowall_model::wire::FrameState;
use isowall_model::Camera;

/// Milliseconds, exact to the nanosecond (no float truncation surprises in comparisons).
fn ms(x: f64) -> Duration {
    Duration::from_nanos((x * 1e6).round() as u64)
}

fn us(t: Duration) -> i64 {
    t.as_micros() as i64
}

#[derive(Clone, Copy, Debug)]
struct LinkCfg {
    latency: Duration,
    /// Extra delay, uniform in [0, jitter) (a link stays FIFO, as a QUIC stream is).
    jitter: Duration,
    /// Probability that a message is dropped (never Hello: a connection opens or it does not).
    loss: f64,
}

fn link(latency_ms: f64) -> LinkCfg {
    LinkCfg { latency: ms(latency_ms), jitter: Duration::ZERO, loss: 0.0 }
}

#[derive(Clone, Copy, Debug)]
enum PresentModel {
    /// Shown this long after the Swap arrives.
    After(Duration),
    /// Shown at the next vsync of a genlocked wall (true time multiple of the period).
    Vsync(Duration),
}

#[derive(Clone, Debug)]
struct NodeCfg {
    name: String,
    render: Duration,
    render_jitter: Duration,
    clock_offset_us: i64,
    up: LinkCfg,
    down: LinkCfg,
    present: PresentModel,
}

fn node(name: &str, render_ms: f64) -> NodeCfg {
    NodeCfg {
        name: name.into(),
        render: ms(render_ms),
        render_jitter: Duration::ZERO,
        clock_offset_us: 0,
        up: link(1.0),
        down: link(1.0),
        present: PresentModel::After(ms(1.0)),
    }
}

#[derive(Debug)]
enum Ev {
    ToNode { node: usize, conn: u64, bytes: Vec<u8> },
    ToCtrl { node: usize, conn: u64, bytes: Vec<u8> },
    RenderDone { node: usize, conn: u64, frame_id: u64, took: Duration },
    Shown { node: usize, conn: u64, frame_id: u64, waiting_from: Duration },
    Connect { node: usize },
}

struct SimNode {
    cfg: NodeCfg,
    machine: NodeMachine,
    /// Connection id, 0 when none; messages of an older connection are dropped.
    conn: u64,
    alive: bool,
    ctrl_handshaken: bool,
    up_last: Duration,
    down_last: Duration,
    up_dec: Decoder,
    down_dec: Decoder,
}

#[derive(Debug, Clone)]
struct Rel {
    ready: Vec<String>,
    stragglers: Vec<String>,
    barrier: Duration,
}

struct Sim {
    now: Duration,
    ctrl: FrameController,
    nodes: Vec<SimNode>,
    events: BinaryHeap<Scheduled<Ev>>,
    seq: u64,
    next_conn: u64,
    rng: Rng,
    frame_interval: Duration,
    frames_from: Duration,
    last_begin: Option<Duration>,
    next_frame: u64,
    camera: Camera,
    settings: RenderSettings,
    // Records.
    begins: BTreeMap<u64, Duration>,
    released: BTreeMap<u64, Rel>,
    done: BTreeMap<u64, FrameStats>,
    downs: Vec<(Duration, String, String)>,
    ups: Vec<(Duration, String)>,
    errors: Vec<ProtocolError>,
    /// (frame, node index) -> true time shown.
    shown: BTreeMap<(u64, usize), Duration>,
    snapshots: Vec<(String, Vec<TileImage>)>,
    sent: u64,
    lost: u64,
}

const T0: Duration = Duration::from_secs(10);

impl Sim {
    fn new(cfgs: Vec<NodeCfg>, deadline: Duration, seed: u64) -> Sim {
        let ctrl = FrameController::new(cfgs.iter().map(|c| c.name.clone()).collect(), deadline);
        let nodes = cfgs
            .into_iter()
            .map(|cfg| SimNode {
                machine: NodeMachine::new(cfg.name.clone(), vec![format!("{}-tile", cfg.name)]),
                cfg,
                conn: 0,
                alive: false,
                ctrl_handshaken: false,
                up_last: Duration::ZERO,
                down_last: Duration::ZERO,
                up_dec: Decoder::new(codec::CONTROLLER_LIMIT),
                down_dec: Decoder::new(codec::DAEMON_LIMIT),
            })
            .collect();
        let camera = Camera {
            eye: glam::DVec3::new(3.0, -7.0, 2.0),
            target: glam::DVec3::ZERO,
            up: glam::DVec3::Z,
            fov_y_deg: 40.0,
        };
        let mut sim = Sim {
            now: T0,
            ctrl,
            nodes,
            events: BinaryHeap::new(),
            seq: 0,
            next_conn: 1,
            rng: Rng(seed | 1),
            frame_interval: ms(20.0),
            frames_from: T0 + ms(50.0),
            last_begin: None,
            next_frame: 1,
            camera,
            settings: RenderSettings::new(0.5),
            begins: BTreeMap::new(),
            released: BTreeMap::new(),
            done: BTreeMap::new(),
            downs: Vec::new(),
            ups: Vec::new(),
            errors: Vec::new(),
            shown: BTreeMap::new(),
            snapshots: Vec::new(),
            sent: 0,
            lost: 0,
        };
        for i in 0..sim.nodes.len() {
            sim.schedule(T0, Ev::Connect { node: i });
        }
        sim
    }

    fn schedule(&mut self, at: Duration, ev: Ev) {
        self.seq += 1;
        self.events.push(Scheduled { at, seq: self.seq, ev });
    }

    fn idx(&self, name: &str) -> usize {
        self.nodes.iter().position(|n| n.cfg.name == name).expect("a sim node")
    }

    fn node_clock(&self, i: usize) -> Duration {
        self.clock_at(i, self.now)
    }

    fn clock_at(&self, i: usize, t: Duration) -> Duration {
        Duration::from_micros((us(t) + self.nodes[i].cfg.clock_offset_us) as u64)
    }

    // ---- links ----

    fn send_down(&mut self, i: usize, msg: &Message) {
        let reliable = matches!(msg, Message::Hello { .. });
        let bytes = codec::frame(msg).expect("encodes");
        self.send_down_bytes(i, bytes, reliable);
    }

    fn send_down_bytes(&mut self, i: usize, bytes: Vec<u8>, reliable: bool) {
        let (conn, cfg) = (self.nodes[i].conn, self.nodes[i].cfg.down);
        self.sent += 1;
        if !reliable && self.rng.unit() < cfg.loss {
            self.lost += 1;
            return;
        }
        let at = (self.now + cfg.latency + self.rng.below(cfg.jitter)).max(self.nodes[i].down_last);
        self.nodes[i].down_last = at;
        self.schedule(at, Ev::ToNode { node: i, conn, bytes });
    }

    fn send_up(&mut self, i: usize, msg: &Message) {
        let reliable = matches!(msg, Message::Hello { .. });
        let bytes = codec::frame(msg).expect("encodes");
        self.send_up_bytes(i, bytes, reliable);
    }

    fn send_up_bytes(&mut self, i: usize, bytes: Vec<u8>, reliable: bool) {
        let (conn, cfg) = (self.nodes[i].conn, self.nodes[i].cfg.up);
        self.sent += 1;
        if !reliable && self.rng.unit() < cfg.loss {
            self.lost += 1;
            return;
        }
        let at = (self.now + cfg.latency + self.rng.below(cfg.jitter)).max(self.nodes[i].up_last);
        self.nodes[i].up_last = at;
        self.schedule(at, Ev::ToCtrl { node: i, conn, bytes });
    }

    // ---- the glue: controller side ----

    fn ctrl_outputs(&mut self, outs: Vec<ControllerOutput>) {
        for o in outs {
            match o {
                ControllerOutput::Send { node, message } => {
                    let i = self.idx(&node);
                    self.send_down(i, &message);
                }
                ControllerOutput::Released { frame_id, ready, stragglers, barrier } => {
                    self.released.insert(frame_id, Rel { ready, stragglers, barrier });
                }
                ControllerOutput::NodeDown { node, reason } => self.downs.push((self.now, node, reason)),
                ControllerOutput::FrameDone { frame_id, stats } => {
                    self.done.insert(frame_id, stats);
                }
                ControllerOutput::Snapshot { node, tiles } => self.snapshots.push((node, tiles)),
                // Honest nodes: nothing of theirs may be ignored or refused.
                ControllerOutput::PeerIgnored { node, what, .. } => {
                    self.errors.push(ProtocolError::new(&node, "PeerIgnored", what))
                }
                // Object space's and a balanced wall's; these nodes never send them.
                ControllerOutput::BrickLoaded { .. }
                | ControllerOutput::BrickFailed { .. }
                | ControllerOutput::PixelsMissing { .. }
                | ControllerOutput::StepLate { .. }
                | ControllerOutput::RectCosts { .. } => {}
            }
        }
    }

    /// Closes node i's connection (either side noticed): the controller takes it down.
    fn close(&mut self, i: usize, reason: &str) {
        if self.nodes[i].conn == 0 {
            return;
        }
        self.nodes[i].conn = 0;
        self.nodes[i].machine.reset();
        let name = self.nodes[i].cfg.name.clone();
        let outs = self.ctrl.node_down(self.now, &name, reason);
        self.ctrl_outputs(outs);
    }

    fn at_ctrl(&mut self, i: usize, bytes: &[u8]) {
        self.nodes[i].up_dec.push(bytes);
        loop {
            let msg = match self.nodes[i].up_dec.next() {
                Ok(Some(m)) => m,
                Ok(None) => return,
                Err(e) => {
                    let reason = format!("codec: {e}");
                    return self.close(i, &reason);
                }
            };
            let name = self.nodes[i].cfg.name.clone();
            if !self.nodes[i].ctrl_handshaken {
                match codec::check_hello(&msg, Role::Daemon) {
                    Ok(n) if n == name => {
                        self.nodes[i].ctrl_handshaken = true;
                        self.ups.push((self.now, name.clone()));
                        let outs = self.ctrl.node_up(self.now, &name).expect("a wall node");
                        self.ctrl_outputs(outs);
                    }
                    other => panic!("handshake of {name}: {other:?}"),
                }
                continue;
            }
            match self.ctrl.handle(self.now, &name, msg) {
                Ok(outs) => self.ctrl_outputs(outs),
                Err(e) => {
                    self.errors.push(e.clone());
                    return self.close(i, &e.to_string());
                }
            }
        }
    }

    // ---- the glue: daemon side ----

    fn node_outputs(&mut self, i: usize, outs: Vec<NodeOutput>) {
        let conn = self.nodes[i].conn;
        for o in outs {
            match o {
                NodeOutput::Render { state, .. } => {
                    let cfg = &self.nodes[i].cfg;
                    let (render, jitter) = (cfg.render, cfg.render_jitter);
                    let took = render + self.rng.below(jitter);
                    self.schedule(
                        self.now + took,
                        Ev::RenderDone { node: i, conn, frame_id: state.frame_id, took },
                    );
                }
                NodeOutput::Send(m) => self.send_up(i, &m),
                NodeOutput::Present { frame_id, at } => {
                    // The present time in true time (node clock - offset), if the Swap has one.
                    let offset = self.nodes[i].cfg.clock_offset_us;
                    let target = at.map(|t| Duration::from_micros((us(t) - offset).max(0) as u64));
                    let (ready, shown) = match self.nodes[i].cfg.present {
                        PresentModel::After(d) => {
                            let ready = self.now + d;
                            (ready, target.map_or(ready, |t| t.max(ready)))
                        }
                        PresentModel::Vsync(p) => {
                            let from = target.map_or(self.now, |t| t.max(self.now));
                            let k = from.as_nanos() / p.as_nanos() + 1;
                            (self.now, Duration::from_nanos((k * p.as_nanos()) as u64))
                        }
                    };
                    let waiting_from = self.clock_at(i, ready);
                    self.schedule(shown, Ev::Shown { node: i, conn, frame_id, waiting_from });
                }
                NodeOutput::LateSwap { .. } => {}
                NodeOutput::SnapshotWanted | NodeOutput::ThumbnailWanted { .. } => {
                    let tiles = self.nodes[i]
                        .machine
                        .tiles()
                        .iter()
                        .map(|t| TileImage {
                            name: t.clone(),
                            width: 4,
                            height: 2,
                            frame_id: self.nodes[i].machine.last_presented().unwrap_or(0),
                            rgb8: vec![i as u8; 24],
                        })
                        .collect();
                    self.send_up(i, &Message::Snapshot { tiles });
                }
                NodeOutput::Closed { reason } => self.close(i, &format!("controller said bye: {reason}")),
                // Object space's, a balanced wall's, and the operator's; this controller never
                // sends them.
                NodeOutput::Bricks { .. }
                | NodeOutput::LoadBrick { .. }
                | NodeOutput::Split { .. }
                | NodeOutput::Restart { .. }
                | NodeOutput::Identify { .. } => {}
            }
        }
    }

    fn at_node(&mut self, i: usize, bytes: &[u8]) {
        self.nodes[i].down_dec.push(bytes);
        loop {
            let msg = match self.nodes[i].down_dec.next() {
                Ok(Some(m)) => m,
                Ok(None) => return,
                Err(e) => {
                    let reason = format!("closed by the daemon: codec: {e}");
                    return self.close(i, &reason);
                }
            };
            let clock = self.node_clock(i);
            match self.nodes[i].machine.handle(clock, msg) {
                Ok(outs) => self.node_outputs(i, outs),
                Err(e) => {
                    self.errors.push(e.clone());
                    let reason = format!("closed by the daemon: {e}");
                    return self.close(i, &reason);
                }
            }
        }
    }

    /// (Re)starts node i: a new daemon process with a new connection.
    fn connect(&mut self, i: usize) {
        let conn = self.next_conn;
        self.next_conn += 1;
        let n = &mut self.nodes[i];
        n.conn = conn;
        n.alive = true;
        n.ctrl_handshaken = false;
        n.machine = NodeMachine::new(n.cfg.name.clone(), vec![format!("{}-tile", n.cfg.name)]);
        n.up_dec = Decoder::new(codec::CONTROLLER_LIMIT);
        n.down_dec = Decoder::new(codec::DAEMON_LIMIT);
        let hello = n.machine.hello();
        self.send_up(i, &hello);
        self.send_down(i, &codec::hello("controller", Role::Controller));
    }

    fn dispatch(&mut self, ev: Ev) {
        match ev {
            Ev::Connect { node } => self.connect(node),
            Ev::ToCtrl { node, conn, bytes } => {
                if self.nodes[node].conn == conn && conn != 0 {
                    self.at_ctrl(node, &bytes);
                }
            }
            Ev::ToNode { node, conn, bytes } => {
                if self.nodes[node].conn == conn && conn != 0 && self.nodes[node].alive {
                    self.at_node(node, &bytes);
                }
            }
            Ev::RenderDone { node, conn, frame_id, took } => {
                if self.nodes[node].conn == conn && self.nodes[node].alive {
                    let clock = self.node_clock(node);
                    let outs = self.nodes[node].machine.render_done(clock, frame_id, took);
                    self.node_outputs(node, outs);
                }
            }
            Ev::Shown { node, conn, frame_id, waiting_from } => {
                if self.nodes[node].conn == conn && self.nodes[node].alive {
                    self.shown.insert((frame_id, node), self.now);
                    let clock = self.node_clock(node);
                    let outs = self.nodes[node].machine.presented(clock, frame_id, waiting_from);
                    self.node_outputs(node, outs);
                }
            }
        }
    }

    fn maybe_begin(&mut self) {
        if self.now < self.frames_from || self.ctrl.in_flight().is_some() {
            return;
        }
        if let Some(last) = self.last_begin {
            if self.now < last + self.frame_interval {
                return;
            }
        }
        let id = self.next_frame;
        self.next_frame += 1;
        self.last_begin = Some(self.now);
        self.begins.insert(id, self.now);
        let state = FrameState::new(id, &self.camera, &self.settings, 1);
        let outs = self.ctrl.begin_frame(self.now, state).expect("no frame in flight");
        self.ctrl_outputs(outs);
    }

    fn next_begin(&self) -> Option<Duration> {
        if self.ctrl.in_flight().is_some() {
            return None;
        }
        Some(match self.last_begin {
            None => self.frames_from,
            Some(l) => (l + self.frame_interval).max(self.frames_from),
        })
    }

    /// Runs until `end` (true time).
    fn run_until(&mut self, end: Duration) {
        loop {
            self.maybe_begin();
            let t = [self.events.peek().map(|e| e.at), self.ctrl.poll_timeout(), self.next_begin()]
                .into_iter()
                .flatten()
                .min();
            let Some(t) = t.filter(|&t| t <= end) else {
                self.now = end;
                return;
            };
            self.now = self.now.max(t);
            if self.ctrl.poll_timeout().is_some_and(|to| to <= self.now) {
                let outs = self.ctrl.handle_timeout(self.now);
                self.ctrl_outputs(outs);
            }
            while self.events.peek().is_some_and(|e| e.at <= self.now) {
                let ev = self.events.pop().expect("peeked").ev;
                self.dispatch(ev);
            }
        }
    }

    fn run_for(&mut self, d: Duration) {
        let end = self.now + d;
        self.run_until(end);
    }

    /// Frames begun in [from, to).
    fn frames_between(&self, from: Duration, to: Duration) -> Vec<u64> {
        self.begins.iter().filter(|(_, &t)| t >= from && t < to).map(|(&id, _)| id).collect()
    }
}

fn names(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| s.to_string()).collect()
}

#[test]
fn all_fast_nodes_release_every_frame_without_stragglers() {
    // Exact: no jitter. Barrier = latency (FrameState) + the slowest render + latency (Ready).
    let cfgs = vec![node("a", 8.0), node("b", 9.0), node("c", 10.0), node("d", 11.0)];
    let mut sim = Sim::new(cfgs, ms(50.0), 1);
    sim.run_for(ms(2050.0));
    assert!(sim.released.len() >= 95, "{} frames", sim.released.len());
    for (id, r) in &sim.released {
        assert_eq!(r.ready, names(&["a", "b", "c", "d"]), "frame {id}");
        assert!(r.stragglers.is_empty());
        assert_eq!(r.barrier, ms(13.0), "frame {id}");
    }
    // Every released frame but the last is done, every node presented, with its render time.
    let last = *sim.released.keys().last().unwrap();
    for id in sim.released.keys().filter(|&&id| id != last) {
        let s = &sim.done[id];
        assert!(s.per_node.iter().all(|n| n.presented_at.is_some()), "frame {id}: {s:?}");
        assert_eq!(s.per_node[3].render, Some(ms(11.0)));
        assert_eq!(s.per_node[3].ready_after, Some(ms(13.0)));
        assert!(s.swap_skew.unwrap() <= ms(0.01), "equal latencies, equal clocks: {:?}", s.swap_skew);
    }
    assert!(sim.errors.is_empty() && sim.downs.is_empty());

    // With jitter: renders 10 ms + [0, 3) ms, links 1 ms + [0, 0.5) ms each way.
    let mut cfgs = vec![node("a", 10.0), node("b", 10.0), node("c", 10.0), node("d", 10.0)];
    for c in &mut cfgs {
        c.render_jitter = ms(3.0);
        c.up.jitter = ms(0.5);
        c.down.jitter = ms(0.5);
    }
    let mut sim = Sim::new(cfgs, ms(50.0), 2);
    sim.run_for(ms(2050.0));
    let (mut lo, mut hi, mut sum) = (Duration::MAX, Duration::ZERO, Duration::ZERO);
    for r in sim.released.values() {
        assert_eq!(r.ready.len(), 4);
        assert!(r.stragglers.is_empty());
        // At least 1 + 10 + 1 ms; at most 1.5 + 13 + 1.5 ms.
        assert!(r.barrier >= ms(12.0) && r.barrier < ms(16.0), "{:?}", r.barrier);
        lo = lo.min(r.barrier);
        hi = hi.max(r.barrier);
        sum += r.barrier;
    }
    let n = sim.released.len() as u32;
    eprintln!("all fast, jittered: {n} frames, barrier min {lo:?} mean {:?} max {hi:?}", sum / n);
}

#[test]
fn a_slow_node_is_reported_each_frame_and_the_others_go_on() {
    let cfgs = vec![node("a", 10.0), node("b", 10.0), node("c", 10.0), node("slow", 80.0)];
    let mut sim = Sim::new(cfgs, ms(30.0), 3);
    sim.frame_interval = ms(1.0); // the next frame begins right after the release
    sim.run_for(ms(1050.0));
    assert!(sim.released.len() >= 30, "{}", sim.released.len());
    for (id, r) in &sim.released {
        assert_eq!(r.ready, names(&["a", "b", "c"]), "frame {id}");
        assert_eq!(r.stragglers, names(&["slow"]), "frame {id}");
        assert_eq!(r.barrier, ms(30.0));
    }
    let c = sim.ctrl.counters("slow").unwrap();
    assert_eq!(c.straggled, sim.released.len() as u64);
    assert!(c.late_ready > 5, "its late Ready replies are counted: {c:?}");
    assert_eq!(c.ready, 0);
    let slow = &sim.nodes[3].machine;
    assert!(slow.counters().skipped > 0, "it renders only the latest frame state: {:?}", slow.counters());
    assert!(sim.errors.is_empty(), "{:?}", sim.errors);
    eprintln!("slow node: {} frames released at the 30 ms deadline; slow: {c:?}", sim.released.len());
}

#[test]
fn a_dead_node_is_reported_excluded_and_the_wall_goes_on() {
    let cfgs = vec![node("a", 10.0), node("b", 10.0), node("c", 10.0)];
    let mut sim = Sim::new(cfgs, ms(40.0), 4);
    sim.run_until(T0 + ms(500.0));
    // b stops answering (hung): straggler at every deadline, until its connection times out.
    sim.nodes[1].alive = false;
    sim.run_until(T0 + ms(1000.0));
    let hung = sim.frames_between(T0 + ms(505.0), T0 + ms(1000.0));
    assert!(hung.len() >= 8, "{hung:?}");
    for id in &hung[..hung.len() - 1] {
        let r = &sim.released[id];
        assert_eq!(r.stragglers, names(&["b"]), "frame {id}");
        assert_eq!(r.ready, names(&["a", "c"]));
        assert_eq!(r.barrier, ms(40.0));
    }
    // The idle timeout of its connection: down.
    sim.close(1, "idle timeout");
    assert_eq!(sim.downs.len(), 1);
    assert_eq!((sim.downs[0].1.as_str(), sim.downs[0].2.as_str()), ("b", "idle timeout"));
    sim.run_until(T0 + ms(1500.0));
    let after = sim.frames_between(T0 + ms(1001.0), T0 + ms(1500.0));
    assert!(after.len() >= 15);
    for id in &after[..after.len() - 1] {
        let r = &sim.released[id];
        assert_eq!(r.ready, names(&["a", "c"]));
        assert!(r.stragglers.is_empty());
        assert_eq!(r.barrier, ms(12.0), "fast again");
        assert_eq!(sim.done[id].missing, names(&["b"]));
    }
    assert!(sim.errors.is_empty());
}

#[test]
fn a_restarted_node_rejoins_at_the_next_frame() {
    let mut cfgs = vec![node("a", 10.0), node("b", 10.0), node("c", 10.0)];
    cfgs[1].clock_offset_us = 50_000;
    let mut sim = Sim::new(cfgs, ms(40.0), 5);
    sim.run_until(T0 + ms(500.0));
    // b crashes (connection reset) and restarts 300 ms later with another clock.
    sim.nodes[1].alive = false;
    sim.close(1, "connection reset");
    sim.run_until(T0 + ms(800.0) + ms(3.0)); // mid-frame
    sim.nodes[1].cfg.clock_offset_us = -20_000;
    sim.connect(1);
    sim.run_until(T0 + ms(1300.0));
    let (up_at, who) = sim.ups.last().unwrap().clone();
    assert_eq!(who, "b");
    assert_eq!(up_at, T0 + ms(804.0), "its Hello arrives 1 ms after it connects");
    let in_flight_at_up = *sim.begins.iter().rfind(|(_, &t)| t <= up_at).unwrap().0;
    for (id, r) in sim.released.range(in_flight_at_up - 5..) {
        let begun = sim.begins[id];
        let b_in = r.ready.contains(&"b".to_string()) || r.stragglers.contains(&"b".to_string());
        if begun < up_at {
            assert!(!b_in, "frame {id} began before b was up: {r:?}");
            assert!(sim.done.get(id).is_none_or(|s| s.missing == names(&["b"])));
        } else {
            assert_eq!(r.ready, names(&["a", "b", "c"]), "frame {id} began after b was up");
            assert!(r.stragglers.is_empty());
        }
    }
    // Its new clock was learned on the new connection.
    let off = sim.ctrl.clock_offset("b").unwrap();
    assert!((off.offset_us + 20_000).abs() <= off.error_us, "{off:?}");
    assert_eq!(sim.downs.len(), 1);
    assert!(sim.errors.is_empty());
}

#[test]
fn clock_offsets_are_estimated_within_the_round_trip_bound() {
    // Offsets of +-50 ms; links 1 ms plus asymmetric jitter: up to 4 ms towards the controller,
    // 0.3 ms towards the node.
    let offsets = [50_000i64, -50_000, 3_000, -17_000];
    let cfgs: Vec<NodeCfg> = offsets
        .iter()
        .enumerate()
        .map(|(i, &o)| {
            let mut c = node(&format!("n{i}"), 10.0);
            c.clock_offset_us = o;
            c.up.jitter = ms(4.0);
            c.down.jitter = ms(0.3);
            c
        })
        .collect();
    let mut sim = Sim::new(cfgs, ms(50.0), 6);
    sim.ctrl.set_ping_interval(Some(ms(100.0)));
    sim.run_for(ms(3000.0));
    let mut worst = 0;
    for (i, &truth) in offsets.iter().enumerate() {
        let est = sim.ctrl.clock_offset(&format!("n{i}")).unwrap();
        let err = (est.offset_us - truth).abs();
        eprintln!(
            "n{i}: true offset {truth} us, estimated {} us (error {err} us, bound {} us, rtt {} us, {} samples)",
            est.offset_us, est.error_us, est.rtt_us, est.samples
        );
        assert!(err <= est.error_us, "n{i}: {est:?}");
        assert!(est.error_us <= 1_500, "the min-RTT sample is close to the 2 ms floor: {est:?}");
        worst = worst.max(err);
    }
    assert!(worst <= 500, "jitter is filtered out: worst error {worst} us");
}

#[test]
fn swap_skew_is_measured_in_controller_time() {
    // A genlocked wall: every node shows a frame at the next vsync of one true clock, so frames
    // swapped together are shown at the same true time, while the nodes' clocks differ by 100 ms.
    let offsets = [50_000i64, -50_000, 20_000, 0];
    let mk = |present: PresentModel, lat: [f64; 4]| -> Vec<NodeCfg> {
        (0..4)
            .map(|i| {
                let mut c = node(&format!("n{i}"), 5.0);
                c.clock_offset_us = offsets[i];
                // Symmetric links: an asymmetric path biases an offset by half the difference,
                // which no round trip can see (it stays within the error bound).
                c.down = link(lat[i]);
                c.up = link(lat[i]);
                c.up.jitter = ms(0.5);
                c.down.jitter = ms(0.2);
                c.present = present;
                c
            })
            .collect()
    };
    // (worst |measured - true|, max measured skew where the true skew is 0, frames, frames whose
    // swaps straddled a vsync)
    let check = |sim: &Sim| -> (Duration, Duration, usize, usize) {
        let (mut worst_err, mut max_skew, mut n, mut straddled) = (Duration::ZERO, Duration::ZERO, 0, 0);
        let err_bound: i64 = (0..4).map(|i| sim.ctrl.clock_offset(&format!("n{i}")).unwrap().error_us).sum();
        for (id, s) in &sim.done {
            let Some(skew) = s.swap_skew else { continue };
            let shown: Vec<Duration> = (0..4).filter_map(|i| sim.shown.get(&(*id, i)).copied()).collect();
            if shown.len() < 4 || s.per_node.iter().any(|p| p.presented_at.is_none()) {
                continue;
            }
            let truth = *shown.iter().max().unwrap() - *shown.iter().min().unwrap();
            let err = skew.abs_diff(truth);
            assert!(us(err) <= err_bound, "frame {id}: skew {skew:?}, true {truth:?}");
            // Raw node times differ by the clock offsets: 100 ms.
            let raw: Vec<i64> = s.per_node.iter().filter_map(|p| p.presented_node_time_us).collect();
            assert!(raw.iter().max().unwrap() - raw.iter().min().unwrap() > 90_000);
            worst_err = worst_err.max(err);
            if truth.is_zero() {
                max_skew = max_skew.max(skew);
            } else if truth > ms(10.0) {
                straddled += 1;
            } else {
                max_skew = max_skew.max(skew);
            }
            n += 1;
        }
        (worst_err, max_skew, n, straddled)
    };
    let untimed = || SwapTiming::new(MarginSetting::Off, None);
    let mut sim = Sim::new(mk(PresentModel::Vsync(ms(1000.0 / 60.0)), [1.0; 4]), ms(50.0), 7);
    sim.ctrl.set_swap_timing(untimed());
    sim.ctrl.set_ping_interval(Some(ms(100.0)));
    sim.run_for(ms(3000.0));
    let (err, skew, n, straddled) = check(&sim);
    assert!(n > 50, "{n}");
    assert!(skew <= ms(1.0), "same true vsync: measured skew at most {skew:?}");
    assert!(straddled < n / 10);
    eprintln!(
        "genlocked: {n} frames, measured skew <= {skew:?} where the true skew is 0, worst error vs the true \
         skew {err:?}, {straddled} frames whose swaps straddled a vsync (true skew one period, measured too)"
    );

    // Swaps that arrive 4 ms apart, shown at once: the skew is measured as 4 ms.
    let mut sim = Sim::new(mk(PresentModel::After(Duration::ZERO), [1.0, 1.0, 5.0, 1.0]), ms(50.0), 8);
    sim.ctrl.set_swap_timing(untimed());
    sim.ctrl.set_ping_interval(Some(ms(100.0)));
    sim.run_for(ms(3000.0));
    let (err, skew, n, _) = check(&sim);
    assert!(n > 50);
    assert!(skew >= ms(3.5) && skew <= ms(5.0), "{skew:?}");
    eprintln!("one slow link: {n} frames, measured skew up to {skew:?}, worst error vs true skew {err:?}");

    // The same link with the timed swap (the default): every node shows the frame at one time,
    // the margin learned from the slow link's deliveries; only the first frames, before the
    // margin has learned it, are late.
    let mut sim = Sim::new(mk(PresentModel::After(Duration::ZERO), [1.0, 1.0, 5.0, 1.0]), ms(50.0), 8);
    sim.ctrl.set_ping_interval(Some(ms(100.0)));
    sim.run_for(ms(3000.0));
    let (err, skew, n, _) = check(&sim);
    assert!(n > 50);
    let late: Vec<u64> = sim.done.iter().filter(|(_, s)| s.late_swaps > 0).map(|(id, _)| *id).collect();
    assert!(late.iter().all(|&id| id <= 3), "late swaps in frames {late:?}");
    let settled: Vec<Duration> = sim
        .done
        .iter()
        .filter(|(id, _)| **id > 3)
        .filter_map(|(id, _)| {
            let shown: Vec<Duration> = (0..4).filter_map(|i| sim.shown.get(&(*id, i)).copied()).collect();
            (shown.len() == 4).then(|| *shown.iter().max().unwrap() - *shown.iter().min().unwrap())
        })
        .collect();
    let worst_true = settled.iter().max().copied().unwrap_or_default();
    // The true skew is what the clock offsets' errors leave: within their bounds.
    let bound: i64 = (0..4).map(|i| sim.ctrl.clock_offset(&format!("n{i}")).unwrap().error_us).sum();
    assert!(us(worst_true) <= bound, "true skew up to {worst_true:?}, clock bounds {bound} us");
    let margin = sim.ctrl.swap_timing().margin();
    assert!(margin >= ms(4.0) && margin <= ms(8.0), "margin {margin:?}");
    eprintln!(
        "one slow link, timed swap: {n} frames, true skew up to {worst_true:?} (bounds {bound} us), measured \
         up to {skew:?}, worst error {err:?}, margin {margin:?}, late swaps in frames {late:?}"
    );
}

#[test]
fn one_percent_loss_never_stops_the_wall() {
    let mut cfgs = vec![node("a", 8.0), node("b", 9.0), node("c", 10.0), node("d", 11.0)];
    for c in &mut cfgs {
        c.up.loss = 0.01;
        c.down.loss = 0.01;
        c.up.jitter = ms(0.5);
        c.render_jitter = ms(2.0);
    }
    let mut sim = Sim::new(cfgs, ms(30.0), 9);
    sim.ctrl.set_present_deadline(ms(30.0));
    sim.run_for(ms(40_050.0));
    let begun = sim.begins.len();
    assert!(begun >= 1900, "{begun}");
    assert!(sim.errors.is_empty(), "loss is no protocol error: {:?}", sim.errors);
    assert!(sim.downs.is_empty());
    // Every frame but the last is released and done, ids without gaps.
    let ids: Vec<u64> = sim.begins.keys().copied().collect();
    assert_eq!(ids, (1..=begun as u64).collect::<Vec<_>>());
    for id in &ids[..ids.len() - 2] {
        assert!(sim.released.contains_key(id) && sim.done.contains_key(id), "frame {id}");
    }
    let with_stragglers = sim.released.values().filter(|r| !r.stragglers.is_empty()).count();
    // Frames where a node that was sent Swap did not report Presented (a Swap or a Presented lost).
    let incomplete = sim
        .done
        .values()
        .filter(|s| s.per_node.iter().any(|p| p.ready_after.is_some() && p.presented_at.is_none()))
        .count();
    assert!(with_stragglers > 0 && incomplete > 0, "the deadline paths were taken");
    assert!(with_stragglers < begun / 5);
    eprintln!(
        "1% loss: {begun} frames, {} of {} messages lost, {with_stragglers} released at the deadline with a \
         straggler, {incomplete} finished without every Presented",
        sim.lost, sim.sent
    );
}

#[test]
fn violations_close_only_that_peer_with_a_clear_reason() {
    let cfgs = vec![node("a", 10.0), node("b", 10.0), node("c", 10.0)];
    let mut sim = Sim::new(cfgs, ms(40.0), 10);
    sim.run_until(T0 + ms(300.0));
    // c says Presented for a frame it was never told to swap: ignored (and told), not closed.
    sim.send_up(2, &Message::Presented { frame_id: 999_999, node_time_us: 0, waiting_from_us: 0 });
    sim.run_until(T0 + ms(350.0));
    assert_eq!(sim.errors.len(), 1);
    let e = &sim.errors[0];
    assert_eq!((e.peer.as_str(), e.message), ("c", "PeerIgnored"));
    assert!(e.problem.contains("ignored Presented for frame 999999"), "{e}");
    assert!(sim.downs.is_empty());
    // c says Ready for a frame it was never sent: a protocol violation, closed.
    sim.send_up(2, &Message::Ready { frame_id: 999_999, render_us: 0 });
    sim.run_until(T0 + ms(400.0));
    assert_eq!(sim.errors.len(), 2);
    let e = &sim.errors[1];
    assert_eq!((e.peer.as_str(), e.message), ("c", "Ready"));
    assert_eq!(sim.downs.len(), 1);
    assert_eq!(sim.downs[0].1, "c");
    assert!(sim.downs[0].2.contains("`c` (Ready): Ready for frame 999999"), "{}", sim.downs[0].2);
    // c reconnects; then b sends garbage bytes.
    sim.connect(2);
    sim.run_until(T0 + ms(500.0));
    sim.send_up_bytes(1, vec![3, 0, 0, 0, 0xee, 0xee, 0xee], true);
    sim.run_until(T0 + ms(600.0));
    assert_eq!(sim.downs.len(), 2);
    assert_eq!(sim.downs[1].1, "b");
    assert!(sim.downs[1].2.starts_with("codec: malformed message"), "{}", sim.downs[1].2);
    // An oversized frame from a: refused from its header.
    sim.connect(1);
    sim.run_until(T0 + ms(700.0));
    sim.send_up_bytes(0, (u32::MAX - 1).to_le_bytes().to_vec(), true);
    sim.run_until(T0 + ms(800.0));
    assert_eq!(sim.downs[2].1, "a");
    assert!(sim.downs[2].2.contains("over the limit"), "{}", sim.downs[2].2);
    // The controller sends b a Swap for a frame it has not rendered: b closes.
    sim.send_down(1, &Message::Swap { frame_id: 123_456_789, present_at_us: None });
    sim.run_until(T0 + ms(900.0));
    assert_eq!(sim.downs[3].1, "b");
    assert!(
        sim.downs[3].2.contains("closed by the daemon")
            && sim.downs[3].2.contains("Swap for frame 123456789")
    );
    // Through all of it the others went on.
    let late = sim.frames_between(T0 + ms(810.0), T0 + ms(880.0));
    assert!(late.len() >= 3);
    assert!(late.iter().all(|id| sim.released[id].ready == names(&["c"])), "only c is left up");
    assert!(sim.released.values().all(|r| r.stragglers.is_empty()), "nobody was slow");
}

#[test]
fn snapshots_come_back_from_every_node() {
    let mut sim = Sim::new(vec![node("a", 5.0), node("b", 5.0)], ms(40.0), 11);
    sim.run_until(T0 + ms(200.0));
    let outs = sim.ctrl.request_snapshot(sim.now);
    sim.ctrl_outputs(outs);
    sim.run_until(T0 + ms(210.0));
    assert_eq!(sim.snapshots.len(), 2);
    for (node, tiles) in &sim.snapshots {
        assert_eq!(tiles[0].name, format!("{node}-tile"));
        assert!(tiles[0].frame_id > 0);
    }
    // An unrequested one is a violation.
    sim.send_up(0, &Message::Snapshot { tiles: vec![] });
    sim.run_until(T0 + ms(220.0));
    assert_eq!(sim.errors[0].message, "Snapshot");
}
