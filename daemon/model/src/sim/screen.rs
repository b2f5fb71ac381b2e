//! Screen space at scale: one [`FrameController`] and N [`NodeMachine`]s on a [`Lan`], every
//! message through the codec. The controller is endpoint N. Node i's clock runs at its own rate
//! (seeded, up to `drift_ppm` parts per million fast or slow) from its own offset (seeded, up to
//! `clock_spread` either way), learned by the controller from Ping/Pong as on a real wall. A
//! render takes `render` plus up to `render_jitter`. A node's presenting thread is ready
//! `present_after` its Swap arrives (the wake-up); it shows the frame then, or at the Swap's
//! present time if that is later (the timed swap: `timing`, `frame_rate`), within up to
//! `present_jitter` of a precise wait. The true swap skew is how far apart the nodes showed a
//! frame in true time; the measured one is the controller's own.

use std::collections::BTreeMap;
use std::time::Duration;

use super::lan::{Events, Lan, LanCounts, LanModel};
use crate::codec::{self, Decoder};
use crate::frame_controller::{ControllerOutput, FrameController};
use crate::messages::{Message, Role};
use crate::node_machine::{NodeMachine, NodeOutput};
use crate::render_state::RenderSettings;
use crate::swap_timing::{MarginSetting, SwapTiming};
use crate::wire::FrameState;
use crate::Camera;

/// A screen-space run.
#[derive(Debug, Clone)]
pub struct ScreenSpec {
    pub nodes: usize,
    pub lan: LanModel,
    pub render: Duration,
    pub render_jitter: Duration,
    /// The swap barrier's deadline.
    pub deadline: Duration,
    /// Frames to run.
    pub frames: u64,
    /// A frame begins this long after the previous one at the earliest (and once it is released).
    pub frame_interval: Duration,
    pub present_after: Duration,
    /// Node clocks are off by up to this much either way.
    pub clock_spread: Duration,
    /// Node clocks run fast or slow by up to this many parts per million.
    pub drift_ppm: f64,
    /// The swap margin (`MarginSetting::Off`: nodes show a frame when its Swap arrives).
    pub timing: MarginSetting,
    /// Paced at this many frames a second (`None`: unpaced).
    pub frame_rate: Option<f64>,
    /// A precise wait ends up to this late.
    pub present_jitter: Duration,
    /// Frames begin after this much time of pings (the clock estimates' first samples).
    pub warm_up: Duration,
    /// The controller pings each node this often.
    pub ping_interval: Duration,
    pub seed: u64,
}

impl ScreenSpec {
    /// `nodes` nodes on a 10 GbE LAN, 10 ms renders with up to 1 ms of jitter, a 100 ms deadline,
    /// 60 frames at most 60 a second.
    pub fn new(nodes: usize, seed: u64) -> ScreenSpec {
        ScreenSpec {
            nodes,
            lan: LanModel::ten_gbe(),
            render: Duration::from_millis(10),
            render_jitter: Duration::from_millis(1),
            deadline: Duration::from_millis(100),
            frames: 60,
            frame_interval: Duration::from_micros(16_667),
            present_after: Duration::from_micros(100),
            clock_spread: Duration::from_millis(20),
            drift_ppm: 0.0,
            timing: MarginSetting::Off,
            frame_rate: None,
            present_jitter: Duration::ZERO,
            warm_up: Duration::from_millis(100),
            ping_interval: Duration::from_millis(50),
            seed,
        }
    }
}

/// One frame as the controller saw it, and the truth beside it.
#[derive(Debug, Clone, PartialEq)]
pub struct ScreenFrame {
    pub frame_id: u64,
    /// From its begin to the release of its swap.
    pub barrier: Duration,
    pub ready: usize,
    pub stragglers: usize,
    /// The controller's measure (`FrameStats::swap_skew`).
    pub swap_skew: Option<Duration>,
    /// max - min of the true times the nodes showed it.
    pub true_skew: Option<Duration>,
    /// Nodes whose Swap came after the present time.
    pub late_swaps: usize,
    /// The margin from the release to the present time (`None`: untimed).
    pub margin: Option<Duration>,
    /// The earliest true time a node showed it.
    pub shown_at: Option<Duration>,
}

/// A finished run.
#[derive(Debug, Clone, PartialEq)]
pub struct ScreenReport {
    pub nodes: usize,
    pub frames: Vec<ScreenFrame>,
    pub lan: LanCounts,
    /// Protocol errors (none on a healthy run).
    pub errors: Vec<String>,
}

#[derive(Debug)]
enum Ev {
    ToNode { node: usize, bytes: Vec<u8> },
    ToCtrl { node: usize, bytes: Vec<u8> },
    RenderDone { node: usize, frame_id: u64, took: Duration },
    Shown { node: usize, frame_id: u64, waiting_from: Duration },
}

struct SimNode {
    machine: NodeMachine,
    name: String,
    offset_us: i64,
    /// Its clock's rate error, parts per million.
    drift_ppm: f64,
    up_dec: Decoder,
    down_dec: Decoder,
}

struct Sim {
    spec: ScreenSpec,
    now: Duration,
    ctrl: FrameController,
    nodes: Vec<SimNode>,
    index: BTreeMap<String, usize>,
    events: Events<Ev>,
    lan: Lan,
    last_begin: Option<Duration>,
    next_frame: u64,
    camera: Camera,
    settings: RenderSettings,
    released: BTreeMap<u64, (Duration, usize, usize)>,
    done: BTreeMap<u64, (Option<Duration>, usize, Option<Duration>)>,
    shown: BTreeMap<u64, Vec<Duration>>,
    errors: Vec<String>,
}

impl Sim {
    fn new(spec: ScreenSpec) -> Sim {
        let names: Vec<String> = (0..spec.nodes).map(|i| format!("node{i:04}")).collect();
        let mut ctrl = FrameController::new(names.clone(), spec.deadline);
        ctrl.set_ping_interval(Some(spec.ping_interval));
        ctrl.set_present_deadline(spec.deadline);
        ctrl.set_swap_timing(SwapTiming::new(spec.timing, spec.frame_rate));
        let mut lan = Lan::new(spec.lan, spec.nodes + 1, spec.seed);
        let spread = spec.clock_spread.as_micros() as f64;
        let nodes = names
            .iter()
            .map(|name| {
                let mut machine = NodeMachine::new(name.clone(), vec![format!("{name}-tile")]);
                machine.handle(Duration::ZERO, codec::hello("controller", Role::Controller)).expect("hello");
                SimNode {
                    machine,
                    name: name.clone(),
                    offset_us: ((lan.rng().unit() * 2.0 - 1.0) * spread) as i64,
                    drift_ppm: (lan.rng().unit() * 2.0 - 1.0) * spec.drift_ppm,
                    up_dec: Decoder::new(codec::CONTROLLER_LIMIT),
                    down_dec: Decoder::new(codec::DAEMON_LIMIT),
                }
            })
            .collect();
        // What the frames show does not matter here, only their size.
        let camera = Camera::framing(glam::DVec3::ZERO, glam::DVec3::ONE, 1920, 1080);
        Sim {
            index: names.iter().cloned().enumerate().map(|(i, n)| (n, i)).collect(),
            spec,
            now: Duration::ZERO,
            ctrl,
            nodes,
            events: Events::default(),
            lan,
            last_begin: None,
            next_frame: 1,
            camera,
            settings: RenderSettings::new(0.5),
            released: BTreeMap::new(),
            done: BTreeMap::new(),
            shown: BTreeMap::new(),
            errors: Vec::new(),
        }
    }

    fn controller(&self) -> usize {
        self.spec.nodes
    }

    /// Node `i`'s clock at true time `t`: its rate and offset (and a second, so it is never
    /// negative).
    fn clock_at(&self, i: usize, t: Duration) -> Duration {
        let n = &self.nodes[i];
        let true_us = t.as_secs_f64() * 1e6;
        let us = true_us * (1.0 + n.drift_ppm * 1e-6) + (n.offset_us + 1_000_000) as f64;
        Duration::from_micros(us.max(0.0).round() as u64)
    }

    /// The true time node `i`'s clock says `clock`.
    fn true_time(&self, i: usize, clock: Duration) -> Duration {
        let n = &self.nodes[i];
        let us = (clock.as_secs_f64() * 1e6 - (n.offset_us + 1_000_000) as f64) / (1.0 + n.drift_ppm * 1e-6);
        Duration::from_secs_f64(us.max(0.0) / 1e6)
    }

    fn node_clock(&self, i: usize) -> Duration {
        self.clock_at(i, self.now)
    }

    fn send_down(&mut self, i: usize, msg: &Message) {
        let bytes = codec::frame(msg).expect("a message encodes");
        let at = self.lan.send(self.now, self.controller(), i, bytes.len());
        self.events.push(at, Ev::ToNode { node: i, bytes });
    }

    fn send_up(&mut self, i: usize, msg: &Message) {
        let bytes = codec::frame(msg).expect("a message encodes");
        let at = self.lan.send(self.now, i, self.controller(), bytes.len());
        self.events.push(at, Ev::ToCtrl { node: i, bytes });
    }

    fn ctrl_outputs(&mut self, outs: Vec<ControllerOutput>) {
        for o in outs {
            match o {
                ControllerOutput::Send { node, message } => {
                    let i = self.index[&node];
                    self.send_down(i, &message);
                }
                ControllerOutput::Released { frame_id, ready, stragglers, barrier } => {
                    self.released.insert(frame_id, (barrier, ready.len(), stragglers.len()));
                }
                ControllerOutput::FrameDone { frame_id, stats } => {
                    self.done.insert(frame_id, (stats.swap_skew, stats.late_swaps, stats.margin));
                }
                ControllerOutput::NodeDown { node, reason } => {
                    self.errors.push(format!("{node} down: {reason}"))
                }
                // Honest nodes on a virtual LAN: nothing of theirs may be ignored or refused.
                ControllerOutput::PeerIgnored { node, what, .. } => {
                    self.errors.push(format!("{node}: {what}"))
                }
                ControllerOutput::Snapshot { .. }
                | ControllerOutput::BrickLoaded { .. }
                | ControllerOutput::BrickFailed { .. }
                | ControllerOutput::PixelsMissing { .. }
                | ControllerOutput::StepLate { .. }
                | ControllerOutput::RectCosts { .. } => {}
            }
        }
    }

    fn node_outputs(&mut self, i: usize, outs: Vec<NodeOutput>) {
        for o in outs {
            match o {
                NodeOutput::Render { state, .. } => {
                    let took = self.spec.render + self.lan.rng().below(self.spec.render_jitter);
                    self.events
                        .push(self.now + took, Ev::RenderDone { node: i, frame_id: state.frame_id, took });
                }
                NodeOutput::Send(m) => self.send_up(i, &m),
                NodeOutput::Present { frame_id, at } => {
                    let ready = self.now + self.spec.present_after;
                    let waiting_from = self.clock_at(i, ready);
                    let target = at.map_or(ready, |at| self.true_time(i, at).max(ready));
                    let shown = target + self.lan.rng().below(self.spec.present_jitter);
                    self.events.push(shown, Ev::Shown { node: i, frame_id, waiting_from });
                }
                NodeOutput::LateSwap { .. } => {}
                other => self.errors.push(format!("{}: unexpected {other:?}", self.nodes[i].name)),
            }
        }
    }

    fn dispatch(&mut self, ev: Ev) {
        match ev {
            Ev::ToNode { node, bytes } => {
                self.nodes[node].down_dec.push(&bytes);
                while let Ok(Some(msg)) = self.nodes[node].down_dec.next() {
                    let clock = self.node_clock(node);
                    match self.nodes[node].machine.handle(clock, msg) {
                        Ok(outs) => self.node_outputs(node, outs),
                        Err(e) => self.errors.push(e.to_string()),
                    }
                }
            }
            Ev::ToCtrl { node, bytes } => {
                self.nodes[node].up_dec.push(&bytes);
                while let Ok(Some(msg)) = self.nodes[node].up_dec.next() {
                    let name = self.nodes[node].name.clone();
                    match self.ctrl.handle(self.now, &name, msg) {
                        Ok(outs) => self.ctrl_outputs(outs),
                        Err(e) => self.errors.push(e.to_string()),
                    }
                }
            }
            Ev::RenderDone { node, frame_id, took } => {
                let clock = self.node_clock(node);
                let outs = self.nodes[node].machine.render_done(clock, frame_id, took);
                self.node_outputs(node, outs);
            }
            Ev::Shown { node, frame_id, waiting_from } => {
                self.shown.entry(frame_id).or_default().push(self.now);
                let clock = self.node_clock(node);
                let outs = self.nodes[node].machine.presented(clock, frame_id, waiting_from);
                self.node_outputs(node, outs);
            }
        }
    }

    fn next_begin(&self) -> Option<Duration> {
        if self.ctrl.in_flight().is_some() || self.next_frame > self.spec.frames {
            return None;
        }
        let at = match self.last_begin {
            None => self.spec.warm_up,
            Some(l) => (l + self.spec.frame_interval).max(self.now),
        };
        // A paced wall begins no sooner than the frame controller says.
        Some(self.ctrl.next_begin_at(self.now).map_or(at, |t| t.max(at)))
    }

    fn run(&mut self) {
        for i in 0..self.nodes.len() {
            let name = self.nodes[i].name.clone();
            let outs = self.ctrl.node_up(self.now, &name).expect("a wall node");
            self.ctrl_outputs(outs);
        }
        let end_after_last = self.spec.deadline * 3;
        let mut end: Option<Duration> = None;
        loop {
            if self.next_begin().is_some_and(|t| t <= self.now) {
                let id = self.next_frame;
                self.next_frame += 1;
                self.last_begin = Some(self.now);
                let state = FrameState::new(id, &self.camera, &self.settings, 1);
                let outs = self.ctrl.begin_frame(self.now, state).expect("no frame in flight");
                self.ctrl_outputs(outs);
            }
            if end.is_none() && self.next_frame > self.spec.frames && self.ctrl.in_flight().is_none() {
                end = Some(self.now + end_after_last);
            }
            let t = [self.events.next_at(), self.ctrl.poll_timeout(), self.next_begin()]
                .into_iter()
                .flatten()
                .min();
            let Some(t) = t.filter(|&t| end.is_none_or(|e| t <= e)) else { return };
            self.now = self.now.max(t);
            if self.ctrl.poll_timeout().is_some_and(|to| to <= self.now) {
                let outs = self.ctrl.handle_timeout(self.now);
                self.ctrl_outputs(outs);
            }
            while self.events.next_at().is_some_and(|at| at <= self.now) {
                let (_, ev) = self.events.pop().expect("an event is due");
                self.dispatch(ev);
            }
        }
    }
}

/// Runs `spec` to the end: every frame begun, released and finished.
pub fn run_screen(spec: &ScreenSpec) -> ScreenReport {
    let mut sim = Sim::new(spec.clone());
    sim.run();
    let frames = sim
        .released
        .iter()
        .map(|(&frame_id, &(barrier, ready, stragglers))| {
            let shown = sim.shown.get(&frame_id);
            let true_skew = shown.and_then(|s| Some(*s.iter().max()? - *s.iter().min()?));
            let (swap_skew, late_swaps, margin) = sim.done.get(&frame_id).copied().unwrap_or((None, 0, None));
            ScreenFrame {
                frame_id,
                barrier,
                ready,
                stragglers,
                swap_skew,
                true_skew,
                late_swaps,
                margin,
                shown_at: shown.and_then(|s| s.iter().min().copied()),
            }
        })
        .collect();
    ScreenReport { nodes: spec.nodes, frames, lan: sim.lan.counts(), errors: sim.errors }
}

/// The median, 99th percentile and maximum of `v` (zeros when empty).
pub fn percentiles(v: &[Duration]) -> (Duration, Duration, Duration) {
    let mut s = v.to_vec();
    s.sort();
    if s.is_empty() {
        return (Duration::ZERO, Duration::ZERO, Duration::ZERO);
    }
    let at = |q: f64| s[((s.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.99), s[s.len() - 1])
}
