//! The controller's frame machine: the swap barrier of DESIGN.md ("Distribution", "Faults").
//!
//! Sans-IO, in the manner of `quinn-proto`: [`FrameController`] never touches a socket or a clock.
//! The caller passes the time in (`now`, a [`Duration`] since any fixed epoch of the controller's
//! clock), feeds it what happens ([`FrameController::node_up`], [`FrameController::node_down`],
//! [`FrameController::handle`]), asks it to act ([`FrameController::begin_frame`],
//! [`FrameController::ping`], [`FrameController::request_snapshot`]), calls
//! [`FrameController::handle_timeout`] once `now` reaches [`FrameController::poll_timeout`], and
//! carries out the [`ControllerOutput`]s every call returns, in order.
//!
//! One frame:
//! 1. `begin_frame`: the frame state goes to every node that is up; they are the frame's
//!    participants (a node that comes up later joins at the next frame).
//! 2. Ready replies are collected. When every participant still up is ready, or the deadline
//!    (`begin + deadline`) passes, the swap is released: Swap goes to the ready nodes, and
//!    [`ControllerOutput::Released`] names the ready nodes and the stragglers. The release picks
//!    the frame's present time ([`crate::swap_timing`]: a margin after the release, on the frame
//!    grid when paced); each node's Swap carries it in that node's clock, through the node's
//!    clock offset (from Ping/Pong, see [`crate::clock`]; a node whose offset is not known yet
//!    presents on arrival).
//! 3. Presented replies are collected, each converted to controller time by the node's clock
//!    offset. Each says when the node was ready to wait for the present time: after it, the
//!    swap was late (counted); the delays from the release teach the margin. When every released
//!    node has presented, or the present deadline (after the present time) passes,
//!    [`ControllerOutput::FrameDone`] carries the frame's statistics, the swap skew among them.
//!
//! The next frame may begin as soon as the previous one is released: the Presented replies of
//! up to [`PRESENTING`] released frames are still collected meanwhile (a paced frame may wait for
//! its slot while the next renders; beyond that the oldest is finished with what arrived). A
//! straggler's late Ready, or a late Presented, is counted and otherwise ignored; it is no error.
//!
//! Pings go one node at a time, in turn, spread over the ping interval (randomly spaced, so they
//! meet the frames' bursts at every phase): never a burst that queues behind (or ahead of) the
//! Swaps and biases the clock offsets; [`FrameController::SETTLING_PING_SPEEDUP`] times as often
//! while a node's clock is not fitted yet. What is an error ([`ProtocolError`]: the caller closes
//! that node's connection, then calls `node_down`): a message only the controller sends, a second
//! Hello, Ready for a frame the node was never sent or twice, a Snapshot nobody asked for, a
//! message from an unknown node or one that is not up.
//!
//! A node's word is held to what the controller asked and to what the round trip allows, so a
//! lie costs the liar, never the report nor the operator's terminal:
//! - unsolicited messages are ignored and counted ([`NodeCounters::ignored`]): a Presented for a
//!   frame it was not told to swap, a Pong for no Ping of its connection (or with another t0), a
//!   BrickLoaded or BrickFailed for a brick it was not asked to load
//!   ([`FrameController::load_brick`]), a StepLate for a frame it is not rendering or a second one
//!   for the same frame;
//! - times that cannot be true are refused before they reach the statistics
//!   ([`NodeCounters::refused_times`]): a Pong whose `t1` puts the node's clock offset outside the
//!   current estimate ([`ClockEstimator::admit`]), a Presented whose time, through the offset, is
//!   not between the Swap sent and the Presented received ([`ClockOffset::check_between`]): the
//!   frame counts it presented, with no time;
//! - each of these is told as [`ControllerOutput::PeerIgnored`], at most [`PeerLog::LINES`] per
//!   node per [`PeerLog::INTERVAL`] (the rest counted, and the next line says how many).

use std::collections::{BTreeMap, VecDeque};
use std::time::Duration;

use crate::clock::{ClockEstimator, ClockOffset, ClockSample};
use crate::messages::{printable, Message, ProtocolError, Role, TileImage};
use crate::peer_log::PeerLog;
use crate::swap_timing::SwapTiming;
use crate::wire::{FrameState, WireRectCost};

/// Pings and swaps remembered per node, at most (older ones are forgotten: their answers will be
/// protocol errors, which they are after this many have gone unanswered).
const REMEMBERED: usize = 32;

/// Released frames whose Presented replies are collected at once, at most.
pub const PRESENTING: usize = 4;

/// What the caller must do, in order.
#[allow(clippy::large_enum_variant)] // a Message with a FrameState, see `Message`
#[derive(Debug, Clone, PartialEq)]
pub enum ControllerOutput {
    /// Send `message` on `node`'s connection.
    Send { node: String, message: Message },
    /// The swap of `frame_id` was released (Swap sent to `ready`) `barrier` after it began;
    /// `stragglers` were up and missed the deadline (they get no Swap for it).
    Released { frame_id: u64, ready: Vec<String>, stragglers: Vec<String>, barrier: Duration },
    /// `node` is down (or its connection was replaced); it takes part in no frame until it is up.
    NodeDown { node: String, reason: String },
    /// A frame is finished: every released node presented it, or the present deadline passed.
    FrameDone { frame_id: u64, stats: FrameStats },
    /// A node's answer to [`FrameController::request_snapshot`].
    Snapshot { node: String, tiles: Vec<TileImage> },
    /// object space: `node` loaded `brick` (`crate::adoption::BrickAssigner::loaded`).
    BrickLoaded { node: String, brick: u64, load: Duration, resident_bytes: u64 },
    /// object space: `node` could not load `brick` (`crate::adoption::BrickAssigner::load_failed`).
    BrickFailed { node: String, brick: u64, reason: String },
    /// object space: from `frame_id` on, `node` composites without the pixels of `peers` (they
    /// missed its compositing deadline); empty when they are back. Told when the set changes.
    PixelsMissing { node: String, frame_id: u64, peers: Vec<String> },
    /// `node` did not have frame `frame_id`'s time step `wanted` loaded when the frame came
    /// (the caller logs it; [`NodeFrameStats::step_late`] keeps it with the frame).
    /// `told`: `Some(held_back)` when the node's line budget ([`PeerLog`]) lets a line about it
    /// through (`held_back` lines held back before it), `None` when it is only counted: a node
    /// whose loads lag, or that says so falsely, prints no more than any other peer.
    StepLate { node: String, frame_id: u64, wanted: u32, late: StepLate, told: Option<u64> },
    /// A message of `node` was ignored, or a time of its refused (see the module docs): `what`
    /// says which and why (its text made printable). At most [`PeerLog::LINES`] of these per node
    /// per [`PeerLog::INTERVAL`]; `held_back` more were counted since the last one told.
    PeerIgnored { node: String, what: String, held_back: u64 },
    /// load-balanced screen space: what each rectangle `node` rendered of `frame_id` cost (the
    /// caller's `crate::balance::Balancer` observes them).
    RectCosts { node: String, frame_id: u64, costs: Vec<WireRectCost> },
}

/// One node's part in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeFrameStats {
    pub node: String,
    /// The render time it reported in Ready.
    pub render: Option<Duration>,
    /// When its Ready arrived, since the frame began (`None`: not before the release).
    pub ready_after: Option<Duration>,
    /// When it presented, in controller time (`None`: it did not report in time, or its clock
    /// offset is not known yet).
    pub presented_at: Option<Duration>,
    /// When it presented, by its own clock, as it reported.
    pub presented_node_time_us: Option<i64>,
    /// The present time its Swap carried, by its own clock (`None`: untimed).
    pub present_at_us: Option<i64>,
    /// Its Swap came after the frame's present time: it presented at once.
    pub late_swap: bool,
    /// Whether it went down during the frame.
    pub went_down: bool,
    // object space
    /// Bytes it sent its peers for the frame (object space).
    pub bytes_sent: Option<u64>,
    /// Its compositing time (object space).
    pub composite: Option<Duration>,
    /// The volume bytes it holds: its brick and halo (object space).
    pub resident_bytes: Option<u64>,
    /// The work in its compositing: encoding, decoding, merging (object space).
    pub merge: Option<Duration>,
    /// Its StepLate: the frame's time step was not loaded when the frame came (time-varying
    /// volumes).
    pub step_late: Option<StepLate>,
    /// Its Surface: of its tiles' surface pixels, how many level 0 drew (a bricked volume).
    pub surface: Option<SurfaceLevels>,
}

/// A node's surface pixels in a frame, and how many of them were drawn with level 0 where they
/// lie (a volume read through a brick cache: DESIGN.md "Large volumes"). A claim, checked to be
/// no more than the node's tiles' pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SurfaceLevels {
    pub hits: u64,
    pub level0: u64,
}

impl SurfaceLevels {
    /// The share of surface pixels at level 0 (1 where there is no surface).
    pub fn share(self) -> f64 {
        if self.hits == 0 {
            1.0
        } else {
            self.level0 as f64 / self.hits as f64
        }
    }
}

impl std::ops::Add for SurfaceLevels {
    type Output = SurfaceLevels;
    fn add(self, o: SurfaceLevels) -> SurfaceLevels {
        SurfaceLevels { hits: self.hits.saturating_add(o.hits), level0: self.level0.saturating_add(o.level0) }
    }
}

/// A node's time step that was not loaded when its frame came: it waited `waited` (bounded)
/// and rendered `shown_step`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepLate {
    pub shown_step: u32,
    pub waited: Duration,
}

/// A finished frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameStats {
    pub frame_id: u64,
    /// The time step the frame asked for.
    pub time_step: u32,
    /// The frame's participants, by name.
    pub per_node: Vec<NodeFrameStats>,
    /// max - min of `presented_at` over the nodes that have one (`None` when none has).
    pub swap_skew: Option<Duration>,
    /// max - min of the present times the nodes reported by their own clocks: the true skew
    /// where every node runs on one clock (one machine), meaningless elsewhere.
    pub node_clock_skew: Option<Duration>,
    /// The frame's present time on the controller's clock (`None`: untimed swap).
    pub present_at: Option<Duration>,
    /// The margin from the release to the present time (`None`: untimed swap).
    pub margin: Option<Duration>,
    /// Nodes whose Swap came after the present time.
    pub late_swaps: usize,
    /// From the frame's begin to the release of its swap.
    pub barrier: Duration,
    /// Nodes of the wall that took no part in the frame (down when it began).
    pub missing: Vec<String>,
}

/// Running counts of one node, since the controller was made.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NodeCounters {
    /// Frames it was sent.
    pub frames: u64,
    /// Frames it was ready for in time.
    pub ready: u64,
    /// Frames released without it while it was up.
    pub straggled: u64,
    /// Ready replies that came after their frame was released (ignored).
    pub late_ready: u64,
    /// Presented replies that came after their frame was finished (ignored).
    pub late_presented: u64,
    /// Times it went down.
    pub downs: u64,
    /// Ping/Pong round trips completed.
    pub pongs: u64,
    /// Unsolicited messages ignored (see the module docs).
    pub ignored: u64,
    /// Pong and Presented times refused as impossible (see the module docs).
    pub refused_times: u64,
    /// Swaps that came after their present time.
    pub late_swaps: u64,
}

/// Why a frame cannot begin.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BeginError {
    #[error("frame {0} is still waiting for its swap to be released")]
    InFlight(u64),
    #[error("frame id {given} does not follow the last frame id {last}")]
    NotIncreasing { last: u64, given: u64 },
}

#[derive(Debug, Default)]
struct NodeState {
    up: bool,
    clock: ClockEstimator,
    /// Outstanding pings: (id, t0_us).
    pings: VecDeque<(u64, i64)>,
    /// First and last frame ids sent on this connection.
    first_sent: Option<u64>,
    last_sent: Option<u64>,
    last_ready: Option<u64>,
    /// Frames it was told to swap and has not reported presented.
    swapped: VecDeque<u64>,
    /// The downscale divisors of the snapshots it was asked for and owes, oldest first (1: a
    /// full snapshot); it answers them in order.
    snapshots_owed: VecDeque<u32>,
    counters: NodeCounters,
    /// object space: the peers whose pixels its last Composited went without.
    missing: Vec<String>,
    /// Since when the controller has asked it something (a Ping, a frame) and heard nothing back.
    waiting_since: Option<Duration>,
    /// The tiles it shows, (name, width, height), once [`FrameController::set_node_tiles`] says.
    tiles: Option<Vec<(String, u32, u32)>>,
    /// Its process's resident memory, from its last Pong on this connection.
    resident_bytes: Option<u64>,
    /// Its clock estimate is a fitted line (see [`ClockEstimator::estimate`]).
    clock_fitted: bool,
    /// object space: the bricks it was asked to load and has not answered for.
    loads_owed: std::collections::BTreeSet<u64>,
    /// Its version and GPU, from its last NodeInfo (kept while it is down: the last known).
    info: Option<crate::messages::NodeInfo>,
    /// Whether it sent its NodeInfo on this connection (once per connection).
    info_told: bool,
    /// load-balanced screen space: the last frame it reported costs for (once a frame).
    costs_told: Option<u64>,
}

impl NodeState {
    /// Whether the node is rendering `frame_id` (sent it, not yet Ready for it): what it may
    /// report on before its Ready; else why not.
    fn rendering(&self, frame_id: u64) -> Result<(), String> {
        let sent =
            matches!((self.first_sent, self.last_sent), (Some(a), Some(b)) if (a..=b).contains(&frame_id));
        if !sent || self.last_ready.is_some_and(|r| frame_id <= r) {
            return Err(format!(
                "which it is not rendering (sent {:?}..={:?}, ready {:?})",
                self.first_sent, self.last_sent, self.last_ready
            ));
        }
        Ok(())
    }
}

impl NodeState {
    /// Forgets everything of the previous connection (a restarted daemon has a new clock too).
    fn reset_connection(&mut self) {
        self.clock.clear();
        self.clock_fitted = false;
        self.pings.clear();
        self.first_sent = None;
        self.last_sent = None;
        self.last_ready = None;
        self.swapped.clear();
        self.snapshots_owed.clear();
        self.missing.clear();
        self.waiting_since = None;
        self.resident_bytes = None;
        self.loads_owed.clear();
        self.info_told = false;
        self.costs_told = None;
    }
}

#[derive(Debug, Default, Clone)]
struct Part {
    render: Option<Duration>,
    ready_after: Option<Duration>,
    released: bool,
    presented: bool,
    presented_at: Option<Duration>,
    presented_node_time_us: Option<i64>,
    /// The present time its Swap carried, by its clock.
    present_at_us: Option<i64>,
    late_swap: bool,
    down: bool,
    // object space
    bytes_sent: Option<u64>,
    composite: Option<Duration>,
    resident_bytes: Option<u64>,
    merge: Option<Duration>,
    step_late: Option<StepLate>,
    surface: Option<SurfaceLevels>,
}

#[derive(Debug)]
struct Frame {
    id: u64,
    time_step: u32,
    begin: Duration,
    /// Set at the release.
    released_at: Option<Duration>,
    /// The present time, on the controller's clock (timed swaps).
    present_at: Option<Duration>,
    parts: BTreeMap<String, Part>,
    missing: Vec<String>,
}

impl Frame {
    fn all_ready(&self) -> bool {
        self.parts.values().all(|p| p.down || p.ready_after.is_some())
    }

    fn all_presented(&self) -> bool {
        self.parts.values().all(|p| p.down || !p.released || p.presented)
    }

    /// When its Presented replies are overdue: `deadline` after its present time (or release).
    fn present_deadline(&self, deadline: Duration) -> Duration {
        self.present_at.or(self.released_at).unwrap_or(self.begin) + deadline
    }
}

fn micros(t: Duration) -> i64 {
    i64::try_from(t.as_micros()).unwrap_or(i64::MAX)
}

/// The controller's frame machine (see the module docs).
#[derive(Debug)]
pub struct FrameController {
    nodes: BTreeMap<String, NodeState>,
    deadline: Duration,
    present_deadline: Duration,
    ping_interval: Option<Duration>,
    next_ping_at: Option<Duration>,
    next_ping_id: u64,
    /// A node silent this long is down (see [`FrameController::set_silence_limit`]).
    silence_limit: Option<Duration>,
    last_frame_id: Option<u64>,
    /// Begun, not released.
    collecting: Option<Frame>,
    /// Released, not finished, oldest first (at most [`PRESENTING`]).
    presenting: VecDeque<Frame>,
    /// The present times of released frames.
    timing: SwapTiming,
    /// The next node to ping, in turn (by name).
    ping_cursor: Option<String>,
    /// Dithers the pings' spacing (xorshift; a fixed seed: the machine stays deterministic).
    ping_dither: u64,
    /// The lines the nodes' ignored messages may make the operator read.
    peer_log: PeerLog,
}

impl FrameController {
    /// Pings every up node this often by default (see [`FrameController::set_ping_interval`]).
    pub const DEFAULT_PING_INTERVAL: Duration = Duration::from_millis(500);

    /// While a node's clock estimate is not a fitted line yet, pings go this many times as often.
    pub const SETTLING_PING_SPEEDUP: u32 = 5;

    /// A controller for the wall's `nodes` (all down until [`FrameController::node_up`]); a frame's
    /// swap is released at the latest `deadline` after it began, and it is finished at the latest
    /// `deadline` after its release.
    pub fn new(nodes: Vec<String>, deadline: Duration) -> Self {
        FrameController {
            nodes: nodes.into_iter().map(|n| (n, NodeState::default())).collect(),
            deadline,
            present_deadline: deadline,
            ping_interval: Some(Self::DEFAULT_PING_INTERVAL),
            next_ping_at: None,
            next_ping_id: 1,
            silence_limit: None,
            last_frame_id: None,
            collecting: None,
            presenting: VecDeque::new(),
            timing: SwapTiming::new(Default::default(), None),
            ping_cursor: None,
            ping_dither: 0x2545_f491_4f6c_dd1d,
            peer_log: PeerLog::default(),
        }
    }

    // ---- getters ----

    /// The frame whose swap is not released yet (a new frame cannot begin while there is one).
    pub fn in_flight(&self) -> Option<u64> {
        self.collecting.as_ref().map(|f| f.id)
    }

    /// The oldest released frame still collecting Presented replies.
    pub fn presenting(&self) -> Option<u64> {
        self.presenting.front().map(|f| f.id)
    }

    /// The present times of released frames: the margin setting, the frame rate, the margin.
    pub fn swap_timing(&self) -> &SwapTiming {
        &self.timing
    }

    /// When the next frame should begin, on a paced wall: a period before the last released
    /// frame's present time, so that at most one frame waits for its slot while the next renders
    /// (it has up to two periods to make the slot after). `None`: now (unpaced, or no frame's
    /// present time is that far ahead).
    pub fn next_begin_at(&self, now: Duration) -> Option<Duration> {
        let period = self.timing.period()?;
        let last = self.presenting.back().and_then(|f| f.present_at)?;
        Some(last.saturating_sub(period)).filter(|&t| t > now)
    }

    /// Times the swaps from the next release on (see [`crate::swap_timing`]).
    pub fn set_swap_timing(&mut self, timing: SwapTiming) {
        self.timing = timing;
    }

    /// The node's clock offset (node clock - controller clock), once a Pong has arrived on its
    /// current connection.
    pub fn clock_offset(&self, node: &str) -> Option<ClockOffset> {
        self.nodes.get(node)?.clock.estimate()
    }

    /// The node's process resident memory as its last Pong on its current connection said.
    pub fn resident_bytes(&self, node: &str) -> Option<u64> {
        self.nodes.get(node)?.resident_bytes
    }

    /// The version and GPU `node` last told (its texts made printable and bounded on receipt).
    pub fn node_info(&self, node: &str) -> Option<&crate::messages::NodeInfo> {
        self.nodes.get(node)?.info.as_ref()
    }

    pub fn is_up(&self, node: &str) -> bool {
        self.nodes.get(node).is_some_and(|n| n.up)
    }

    /// The wall's nodes, in name order.
    pub fn nodes(&self) -> impl Iterator<Item = &str> {
        self.nodes.keys().map(String::as_str)
    }

    pub fn up_nodes(&self) -> Vec<String> {
        self.nodes.iter().filter(|(_, n)| n.up).map(|(k, _)| k.clone()).collect()
    }

    pub fn counters(&self, node: &str) -> Option<NodeCounters> {
        self.nodes.get(node).map(|n| n.counters)
    }

    pub fn deadline(&self) -> Duration {
        self.deadline
    }

    // ---- settings ----

    pub fn set_deadline(&mut self, deadline: Duration) {
        self.deadline = deadline;
    }

    /// How long after its release a frame waits for Presented replies (default: the deadline).
    pub fn set_present_deadline(&mut self, d: Duration) {
        self.present_deadline = d;
    }

    /// Ping every up node this often from [`FrameController::handle_timeout`]; `None`: only when
    /// [`FrameController::ping`] is called (and once at each node's `node_up`).
    pub fn set_ping_interval(&mut self, interval: Option<Duration>) {
        self.ping_interval = interval;
        if interval.is_none() {
            self.next_ping_at = None;
        }
    }

    /// A node that has sent nothing for `limit` since it was asked something (a Ping, which goes
    /// every ping interval, or a frame) is down: [`FrameController::handle_timeout`] reports it
    /// ([`ControllerOutput::NodeDown`]) without waiting for the transport's idle timeout. `limit`
    /// must be well over the ping interval; `None` (the default): only the transport says.
    pub fn set_silence_limit(&mut self, limit: Option<Duration>) {
        self.silence_limit = limit;
    }

    /// The tiles `node` shows, (name, width, height): a Snapshot from it may carry only these.
    pub fn set_node_tiles(&mut self, node: &str, tiles: Vec<(String, u32, u32)>) {
        if let Some(st) = self.nodes.get_mut(node) {
            st.tiles = Some(tiles);
        }
    }

    // ---- connections ----

    /// `node`'s connection is open and its Hello checked ([`crate::codec::check_hello`]). It takes
    /// part from the next frame that begins. Returns a first Ping to it (clock sync). If the node
    /// was up already, its old connection is taken down first (what that releases comes first).
    pub fn node_up(&mut self, now: Duration, node: &str) -> Result<Vec<ControllerOutput>, ProtocolError> {
        let Some(st) = self.nodes.get(node) else {
            return Err(ProtocolError::new(node, "Hello", "not a node of this wall"));
        };
        let mut out = Vec::new();
        if st.up {
            out = self.node_down(now, node, "replaced by a new connection");
        }
        let st = self.nodes.get_mut(node).expect("checked above");
        st.reset_connection();
        st.up = true;
        // The turns resume soon: a node just up is pinged at the settling pace.
        if let Some(every) = self.ping_interval {
            let n = u32::try_from(self.nodes.len().max(1)).unwrap_or(u32::MAX);
            let soon = now + every / Self::SETTLING_PING_SPEEDUP / n;
            self.next_ping_at = Some(self.next_ping_at.map_or(soon, |t| t.min(soon)));
        }
        out.push(self.ping_one(now, node));
        Ok(out)
    }

    /// `node`'s connection closed (or timed out, or the caller closed it after a protocol error).
    /// It leaves the frames in flight; a frame that only waited on it is released or finished now.
    /// Returns nothing for a node that is not up.
    pub fn node_down(&mut self, now: Duration, node: &str, reason: &str) -> Vec<ControllerOutput> {
        let Some(st) = self.nodes.get_mut(node) else { return Vec::new() };
        if !st.up {
            return Vec::new();
        }
        st.up = false;
        st.counters.downs += 1;
        st.reset_connection();
        let mut out = vec![ControllerOutput::NodeDown { node: node.to_string(), reason: reason.to_string() }];
        for f in &mut self.presenting {
            if let Some(p) = f.parts.get_mut(node) {
                p.down = true;
            }
        }
        self.finish_presented(&mut out);
        if let Some(f) = &mut self.collecting {
            if let Some(p) = f.parts.get_mut(node) {
                p.down = true;
            }
            if f.all_ready() {
                self.release(now, &mut out);
            }
        }
        out
    }

    // ---- frames ----

    /// Begins frame `state.frame_id` (ids must increase): sends `state` to every up node. With no
    /// node up, the frame is released and finished at once.
    pub fn begin_frame(
        &mut self,
        now: Duration,
        state: FrameState,
    ) -> Result<Vec<ControllerOutput>, BeginError> {
        if let Some(f) = &self.collecting {
            return Err(BeginError::InFlight(f.id));
        }
        let id = state.frame_id;
        if let Some(last) = self.last_frame_id {
            if id <= last {
                return Err(BeginError::NotIncreasing { last, given: id });
            }
        }
        self.last_frame_id = Some(id);
        let mut out = Vec::new();
        let mut parts = BTreeMap::new();
        let mut missing = Vec::new();
        for (name, st) in &mut self.nodes {
            if !st.up {
                missing.push(name.clone());
                continue;
            }
            st.first_sent.get_or_insert(id);
            st.last_sent = Some(id);
            st.waiting_since.get_or_insert(now);
            st.counters.frames += 1;
            parts.insert(name.clone(), Part::default());
            out.push(ControllerOutput::Send { node: name.clone(), message: Message::FrameState(state) });
        }
        self.collecting = Some(Frame {
            id,
            time_step: state.time_step,
            begin: now,
            released_at: None,
            present_at: None,
            parts,
            missing,
        });
        if self.collecting.as_ref().is_some_and(Frame::all_ready) {
            self.release(now, &mut out);
        }
        Ok(out)
    }

    /// Releases the collecting frame: picks its present time, sends Swap to the ready nodes (the
    /// time in each one's clock), reports; finishes the oldest presenting frame first when
    /// [`PRESENTING`] are, and the new one at once if nobody was ready.
    fn release(&mut self, now: Duration, out: &mut Vec<ControllerOutput>) {
        let Some(mut f) = self.collecting.take() else { return };
        if self.presenting.len() >= PRESENTING {
            if let Some(oldest) = self.presenting.pop_front() {
                self.finish(oldest, out);
            }
        }
        let present_at = if f.parts.values().any(|p| !p.down && p.ready_after.is_some()) {
            self.timing.present_at(now)
        } else {
            None
        };
        let (mut ready, mut stragglers) = (Vec::new(), Vec::new());
        for (name, p) in &mut f.parts {
            if p.down {
                continue;
            }
            let st = self.nodes.get_mut(name).expect("participants are nodes");
            if p.ready_after.is_some() {
                p.released = true;
                st.swapped.push_back(f.id);
                if st.swapped.len() > REMEMBERED {
                    st.swapped.pop_front();
                }
                // In the node's clock; a node whose offset is not known yet presents on arrival.
                p.present_at_us = present_at.and_then(|t| Some(st.clock.estimate()?.to_daemon(micros(t))));
                out.push(ControllerOutput::Send {
                    node: name.clone(),
                    message: Message::Swap { frame_id: f.id, present_at_us: p.present_at_us },
                });
                ready.push(name.clone());
            } else {
                st.counters.straggled += 1;
                stragglers.push(name.clone());
            }
        }
        let barrier = now.saturating_sub(f.begin);
        f.released_at = Some(now);
        f.present_at = present_at;
        out.push(ControllerOutput::Released { frame_id: f.id, ready, stragglers, barrier });
        self.presenting.push_back(f);
        self.finish_presented(out);
    }

    /// Finishes, oldest first, the presenting frames every released node has presented.
    fn finish_presented(&mut self, out: &mut Vec<ControllerOutput>) {
        while let Some(i) = self.presenting.iter().position(Frame::all_presented) {
            // Frames before it are finished first, with what arrived: frames finish in order.
            for f in self.presenting.drain(..=i).collect::<Vec<_>>() {
                self.finish(f, out);
            }
        }
    }

    /// Finishes a released frame with what arrived.
    fn finish(&mut self, f: Frame, out: &mut Vec<ControllerOutput>) {
        let released_at = f.released_at.unwrap_or(f.begin);
        let margin = f.present_at.map(|t| t.saturating_sub(released_at));
        let per_node: Vec<NodeFrameStats> = f
            .parts
            .into_iter()
            .map(|(node, p)| NodeFrameStats {
                node,
                render: p.render,
                ready_after: p.ready_after,
                presented_at: p.presented_at,
                presented_node_time_us: p.presented_node_time_us,
                present_at_us: p.present_at_us,
                late_swap: p.late_swap,
                went_down: p.down,
                bytes_sent: p.bytes_sent,
                composite: p.composite,
                resident_bytes: p.resident_bytes,
                merge: p.merge,
                step_late: p.step_late,
                surface: p.surface,
            })
            .collect();
        let spread = |v: Vec<i64>| -> Option<Duration> {
            let (lo, hi) = (v.iter().min()?, v.iter().max()?);
            Some(Duration::from_micros(u64::try_from(hi.saturating_sub(*lo)).unwrap_or(u64::MAX)))
        };
        let times = per_node.iter().filter_map(|s| s.presented_at);
        let swap_skew = match (times.clone().min(), times.max()) {
            (Some(lo), Some(hi)) => Some(hi - lo),
            _ => None,
        };
        let node_clock_skew = spread(per_node.iter().filter_map(|s| s.presented_node_time_us).collect());
        let late_swaps = per_node.iter().filter(|s| s.late_swap).count();
        self.timing.frame_done();
        out.push(ControllerOutput::FrameDone {
            frame_id: f.id,
            stats: FrameStats {
                frame_id: f.id,
                time_step: f.time_step,
                per_node,
                swap_skew,
                node_clock_skew,
                present_at: f.present_at,
                margin,
                late_swaps,
                barrier: released_at.saturating_sub(f.begin),
                missing: f.missing,
            },
        });
    }

    // ---- timers ----

    /// When [`FrameController::handle_timeout`] must be called next: the release deadline of the
    /// frame in flight, the present deadline of the presenting one, or the next ping.
    pub fn poll_timeout(&self) -> Option<Duration> {
        let collect = self.collecting.as_ref().map(|f| f.begin + self.deadline);
        let present = self.presenting.iter().map(|f| f.present_deadline(self.present_deadline)).min();
        let silent = self.silence_limit.and_then(|limit| {
            self.nodes.values().filter(|n| n.up).filter_map(|n| n.waiting_since).min().map(|t| t + limit)
        });
        [collect, present, self.next_ping_at, silent].into_iter().flatten().min()
    }

    /// Acts on every timer that is due at `now`: releases the swap to the ready nodes (naming the
    /// stragglers), finishes a frame whose Presented replies are overdue, pings.
    pub fn handle_timeout(&mut self, now: Duration) -> Vec<ControllerOutput> {
        let mut out = Vec::new();
        if let Some(limit) = self.silence_limit {
            let silent: Vec<(String, Duration)> = self
                .nodes
                .iter()
                .filter(|(_, n)| n.up)
                .filter_map(|(name, n)| Some((name.clone(), n.waiting_since?)))
                .filter(|(_, since)| now >= *since + limit)
                .collect();
            for (node, since) in silent {
                let reason = format!(
                    "silent for {} ms (limit {} ms): no answer to frames or pings",
                    now.saturating_sub(since).as_millis(),
                    limit.as_millis()
                );
                out.extend(self.node_down(now, &node, &reason));
            }
        }
        while self.presenting.front().is_some_and(|f| now >= f.present_deadline(self.present_deadline)) {
            let f = self.presenting.pop_front().expect("checked");
            self.finish(f, &mut out);
        }
        if let Some(f) = &self.collecting {
            if now >= f.begin + self.deadline {
                self.release(now, &mut out);
            }
        }
        if let (Some(at), Some(every)) = (self.next_ping_at, self.ping_interval) {
            if now >= at {
                // One node, the next in turn: each up node once an interval, spread over it.
                let up = self.up_nodes();
                let next = self
                    .ping_cursor
                    .as_ref()
                    .and_then(|c| up.iter().find(|n| *n > c))
                    .or(up.first())
                    .cloned();
                if let Some(node) = next {
                    out.push(self.ping_one(now, &node));
                    self.ping_cursor = Some(node);
                }
                // Spaced a random 0.5 to 1.5 slots apart: a ping interval that is a multiple of
                // the frame period would otherwise meet every frame's bursts at the same phase.
                self.ping_dither ^= self.ping_dither << 13;
                self.ping_dither ^= self.ping_dither >> 7;
                self.ping_dither ^= self.ping_dither << 17;
                // Five times as often while a node's clock is not fitted yet (a node just up).
                let settling = self.nodes.values().any(|n| n.up && !n.clock_fitted);
                let every = if settling { every / Self::SETTLING_PING_SPEEDUP } else { every };
                let slot = every / u32::try_from(up.len().max(1)).unwrap_or(u32::MAX);
                let slot = slot.mul_f64(0.5 + (self.ping_dither >> 11) as f64 / (1u64 << 53) as f64);
                let mut next = at + slot;
                if next <= now {
                    next = now + slot;
                }
                self.next_ping_at = Some(next);
            }
        }
        out
    }

    // ---- clocks and snapshots ----

    fn ping_one(&mut self, now: Duration, node: &str) -> ControllerOutput {
        let id = self.next_ping_id;
        self.next_ping_id += 1;
        let t0_us = micros(now);
        let st = self.nodes.get_mut(node).expect("a node");
        st.waiting_since.get_or_insert(now);
        st.pings.push_back((id, t0_us));
        if st.pings.len() > REMEMBERED {
            st.pings.pop_front();
        }
        ControllerOutput::Send { node: node.to_string(), message: Message::Ping { id, t0_us } }
    }

    /// Pings every up node now (clock sync; the Pongs go through [`FrameController::handle`]).
    pub fn ping(&mut self, now: Duration) -> Vec<ControllerOutput> {
        let up = self.up_nodes();
        up.iter().map(|n| self.ping_one(now, n)).collect()
    }

    /// Asks every up node for its tiles' last presented frames; each answer comes out of
    /// [`FrameController::handle`] as [`ControllerOutput::Snapshot`].
    pub fn request_snapshot(&mut self, _now: Duration) -> Vec<ControllerOutput> {
        let mut out = Vec::new();
        for (name, st) in &mut self.nodes {
            if st.up && !st.snapshots_owed.contains(&1) {
                st.snapshots_owed.push_back(1);
                out.push(ControllerOutput::Send { node: name.clone(), message: Message::SnapshotRequest });
            }
        }
        out
    }

    /// [`FrameController::request_snapshot`] with every tile downscaled by `divisor` at the
    /// nodes (1..=[`crate::messages::MAX_THUMBNAIL_DIVISOR`]): a live thumbnail. A node that still
    /// owes the answer to an earlier request at the same divisor is not asked again (that answer
    /// will do), so a slow node's late answer is never one too many. Each answer is checked
    /// against the divisor of the request it answers (a node answers in order).
    pub fn request_thumbnail(&mut self, _now: Duration, divisor: u32) -> Vec<ControllerOutput> {
        let mut out = Vec::new();
        for (name, st) in &mut self.nodes {
            if st.up && !st.snapshots_owed.contains(&divisor) {
                st.snapshots_owed.push_back(divisor);
                out.push(ControllerOutput::Send {
                    node: name.clone(),
                    message: Message::ThumbnailRequest { divisor },
                });
            }
        }
        out
    }

    // ---- messages ----

    /// A message from `node` (whose Hello was handled by the caller before `node_up`). On
    /// `Err`, close that node's connection with the error as the reason and call `node_down`.
    pub fn handle(
        &mut self,
        now: Duration,
        node: &str,
        msg: Message,
    ) -> Result<Vec<ControllerOutput>, ProtocolError> {
        let kind = msg.kind();
        let err = |problem: String| ProtocolError::new(node, kind, problem);
        let Some(st) = self.nodes.get(node) else {
            return Err(err("not a node of this wall".into()));
        };
        if !st.up {
            return Err(err("the node is not up (no Hello, or its connection is closed)".into()));
        }
        self.nodes.get_mut(node).expect("checked").waiting_since = None;
        // Who sends what is `Message::sender`'s one list.
        if msg.sender() == Some(Role::Controller) {
            return Err(err("only the controller sends this".into()));
        }
        match msg {
            Message::Hello { .. } => Err(err("a second Hello: the handshake is done".into())),
            Message::BrickLoaded { brick, load_us, resident_bytes } => {
                if !self.nodes.get_mut(node).expect("checked").loads_owed.remove(&brick) {
                    return Ok(self.ignore(
                        now,
                        node,
                        format!("BrickLoaded for brick {brick}, which it was not asked to load"),
                    ));
                }
                Ok(vec![ControllerOutput::BrickLoaded {
                    node: node.to_string(),
                    brick,
                    load: Duration::from_micros(load_us),
                    resident_bytes,
                }])
            }
            Message::BrickFailed { brick, reason } => {
                if !self.nodes.get_mut(node).expect("checked").loads_owed.remove(&brick) {
                    return Ok(self.ignore(
                        now,
                        node,
                        format!(
                            "BrickFailed for brick {brick}, which it was not asked to load ({})",
                            printable(&reason)
                        ),
                    ));
                }
                Ok(vec![ControllerOutput::BrickFailed {
                    node: node.to_string(),
                    brick,
                    reason: printable(&reason),
                }])
            }
            Message::Ready { frame_id, render_us } => self.handle_ready(now, node, frame_id, render_us),
            Message::Presented { frame_id, node_time_us, waiting_from_us } => {
                self.handle_presented(now, node, frame_id, node_time_us, waiting_from_us)
            }
            Message::Pong { id, t0_us, t1_us, sent_us, resident_bytes } => {
                self.handle_pong(now, node, id, t0_us, (t1_us, sent_us), resident_bytes)
            }
            Message::Snapshot { tiles } => {
                let st = self.nodes.get_mut(node).expect("checked");
                let Some(divisor) = st.snapshots_owed.pop_front() else {
                    return Err(err("a Snapshot nobody asked for".into()));
                };
                for (i, t) in tiles.iter().enumerate() {
                    t.validate().map_err(err)?;
                    if tiles[..i].iter().any(|u| u.name == t.name) {
                        return Err(err(format!("tile `{}` twice in one Snapshot", printable(&t.name))));
                    }
                    // A thumbnail's tiles are its own over the divisor asked for.
                    let shown = st.tiles.as_ref().map(|own| {
                        own.iter().any(|(name, w, h)| {
                            *name == t.name
                                && (w.div_ceil(divisor), h.div_ceil(divisor)) == (t.width, t.height)
                        })
                    });
                    if shown == Some(false) {
                        return Err(err(format!(
                            "a {}x{} tile `{}`, which is not one of its tiles over {divisor}",
                            t.width,
                            t.height,
                            printable(&t.name)
                        )));
                    }
                }
                Ok(vec![ControllerOutput::Snapshot { node: node.to_string(), tiles }])
            }
            Message::Bye { reason } => {
                Ok(self.node_down(now, node, &format!("said goodbye: {}", printable(&reason))))
            }
            Message::StepLate { frame_id, shown_step, waited_us } => {
                let st = self.nodes.get(node).expect("checked");
                if let Err(why) = st.rendering(frame_id) {
                    return Ok(self.ignore(now, node, format!("StepLate for frame {frame_id}, {why}")));
                }
                let frame = self.collecting.as_mut().filter(|f| f.id == frame_id);
                let part = frame.and_then(|f| Some(f.time_step).zip(f.parts.get_mut(node)));
                if part.as_ref().is_some_and(|(_, p)| p.step_late.is_some()) {
                    return Ok(self.ignore(now, node, format!("a second StepLate for frame {frame_id}")));
                }
                if let Some((wanted, p)) = part {
                    let waited = Duration::from_micros(waited_us);
                    p.step_late = Some(StepLate { shown_step, waited });
                    let told = self.peer_log.allow(now, node);
                    return Ok(vec![ControllerOutput::StepLate {
                        told,
                        node: node.to_string(),
                        frame_id,
                        wanted,
                        late: StepLate { shown_step, waited },
                    }]);
                }
                Ok(Vec::new())
            }
            Message::Composited { frame_id, bytes_sent, composite_us, merge_us, resident_bytes, missing } => {
                let st = self.nodes.get(node).expect("checked");
                if let Err(why) = st.rendering(frame_id) {
                    return Err(err(format!("Composited for frame {frame_id}, {why}")));
                }
                let part =
                    self.collecting.as_mut().filter(|f| f.id == frame_id).and_then(|f| f.parts.get_mut(node));
                if let Some(p) = part {
                    p.bytes_sent = Some(bytes_sent);
                    p.composite = Some(Duration::from_micros(composite_us));
                    p.resident_bytes = Some(resident_bytes);
                    p.merge = Some(Duration::from_micros(merge_us));
                }
                // Names only the wall's other nodes, each once (it is printed).
                let unique: std::collections::BTreeSet<&String> = missing.iter().collect();
                if let Some(n) = missing.iter().find(|n| n.as_str() == node || !self.nodes.contains_key(*n)) {
                    return Err(err(format!(
                        "Composited names `{}` as missing, not another node of the wall",
                        n.escape_debug()
                    )));
                }
                if unique.len() != missing.len() {
                    return Err(err("Composited names a missing node twice".into()));
                }
                let st = self.nodes.get_mut(node).expect("checked");
                if st.missing == missing {
                    return Ok(Vec::new());
                }
                st.missing = missing.clone();
                Ok(vec![ControllerOutput::PixelsMissing { node: node.to_string(), frame_id, peers: missing }])
            }
            Message::Surface { frame_id, hits, level0 } => {
                let st = self.nodes.get(node).expect("checked");
                if let Err(why) = st.rendering(frame_id) {
                    return Ok(self.ignore(now, node, format!("Surface for frame {frame_id}, {why}")));
                }
                // A claim: no more hits than its tiles have pixels, no more at level 0 than hits.
                let pixels: u64 =
                    st.tiles.iter().flatten().map(|(_, w, h)| u64::from(*w) * u64::from(*h)).sum();
                if level0 > hits || (st.tiles.is_some() && hits > pixels) {
                    let what = format!(
                        "Surface for frame {frame_id}: {level0} of {hits} hits at level 0, on tiles of {pixels} pixels"
                    );
                    return Ok(self.ignore(now, node, what));
                }
                let part =
                    self.collecting.as_mut().filter(|f| f.id == frame_id).and_then(|f| f.parts.get_mut(node));
                if let Some(p) = part {
                    if p.surface.is_some() {
                        return Ok(self.ignore(now, node, format!("a second Surface for frame {frame_id}")));
                    }
                    p.surface = Some(SurfaceLevels { hits, level0 });
                }
                Ok(Vec::new())
            }
            Message::RectCosts { frame_id, costs } => {
                let st = self.nodes.get(node).expect("checked");
                if let Err(why) = st.rendering(frame_id) {
                    return Err(err(format!("RectCosts for frame {frame_id}, {why}")));
                }
                // No more entries than the split can give rectangles (where the wall's tiles are
                // known): each of the wall's tiles is cut in at most MAX_RECTS_PER_TILE.
                let tiles: usize = self.nodes.values().filter_map(|n| n.tiles.as_ref()).map(Vec::len).sum();
                let most = tiles.saturating_mul(crate::balance::share::MAX_RECTS_PER_TILE);
                if tiles > 0 && costs.len() > most {
                    return Err(err(format!(
                        "RectCosts for frame {frame_id} with {} entries; a split gives at most {most} rectangles",
                        costs.len()
                    )));
                }
                // Once a frame, in order: a node's reports cannot pile up.
                if let Some(told) = st.costs_told.filter(|&t| frame_id <= t) {
                    return Err(err(format!(
                        "RectCosts for frame {frame_id} after its costs for frame {told}: once a frame, in order"
                    )));
                }
                self.nodes.get_mut(node).expect("checked").costs_told = Some(frame_id);
                Ok(vec![ControllerOutput::RectCosts { node: node.to_string(), frame_id, costs }])
            }
            Message::NodeInfo(info) => {
                info.validate().map_err(err)?;
                let st = self.nodes.get_mut(node).expect("checked");
                if std::mem::replace(&mut st.info_told, true) {
                    return Ok(self.ignore(now, node, "a second NodeInfo on one connection".into()));
                }
                st.info = Some(info.printable());
                Ok(Vec::new())
            }
            // What only the controller sends, refused above.
            _ => Err(err("only the controller sends this".into())),
        }
    }

    fn handle_ready(
        &mut self,
        now: Duration,
        node: &str,
        id: u64,
        render_us: u64,
    ) -> Result<Vec<ControllerOutput>, ProtocolError> {
        let st = self.nodes.get_mut(node).expect("checked");
        let err = |problem: String| Err(ProtocolError::new(node, "Ready", problem));
        match (st.first_sent, st.last_sent) {
            (Some(first), Some(last)) if (first..=last).contains(&id) => {}
            _ => return err(format!("Ready for frame {id}, which was never sent to it")),
        }
        if let Some(last_ready) = st.last_ready {
            if id <= last_ready {
                return err(format!("Ready for frame {id} after Ready for frame {last_ready}"));
            }
        }
        st.last_ready = Some(id);
        let mut out = Vec::new();
        let part = self.collecting.as_mut().filter(|f| f.id == id).and_then(|f| {
            let begin = f.begin;
            f.parts.get_mut(node).map(|p| (p, begin))
        });
        match part {
            Some((p, begin)) if !p.down => {
                p.ready_after = Some(now.saturating_sub(begin));
                p.render = Some(Duration::from_micros(render_us));
                st.counters.ready += 1;
                if self.collecting.as_ref().is_some_and(Frame::all_ready) {
                    self.release(now, &mut out);
                }
            }
            _ => st.counters.late_ready += 1,
        }
        Ok(out)
    }

    fn handle_presented(
        &mut self,
        now: Duration,
        node: &str,
        id: u64,
        node_time_us: i64,
        waiting_from_us: i64,
    ) -> Result<Vec<ControllerOutput>, ProtocolError> {
        let st = self.nodes.get_mut(node).expect("checked");
        let Some(pos) = st.swapped.iter().position(|&s| s == id) else {
            return Ok(self.ignore(
                now,
                node,
                format!("Presented for frame {id} before (or without) its Swap"),
            ));
        };
        // Frames swapped before it and not reported presented were reported in lost messages, or
        // never will be: forget them.
        st.swapped.drain(..=pos);
        let offset = st.clock.estimate();
        let mut out = Vec::new();
        let frame = self.presenting.iter_mut().find(|f| f.id == id);
        let swapped_at = frame.as_ref().map(|f| f.released_at.unwrap_or(f.begin));
        let part = frame.and_then(|f| f.parts.get_mut(node));
        match part {
            Some(p) if p.released && !p.down && !p.presented => {
                p.presented = true;
                // Between the Swap sent and this Presented received, through the offset.
                let between = |us: i64| {
                    offset.map(|o| o.check_between(us, micros(swapped_at.unwrap_or_default()), micros(now)))
                };
                let checked = between(node_time_us);
                let waited = between(waiting_from_us);
                let refused = match (&checked, &waited) {
                    (Some(Err(why)), _) => {
                        Some(format!("Presented time {node_time_us} us for frame {id} refused: {why}"))
                    }
                    (_, Some(Err(why))) => Some(format!(
                        "Presented waiting time {waiting_from_us} us for frame {id} refused: {why}"
                    )),
                    _ => None,
                };
                if let Some(what) = refused {
                    self.nodes.get_mut(node).expect("checked").counters.refused_times += 1;
                    out.extend(self.ignore_line(now, node, what));
                } else {
                    p.presented_node_time_us = Some(node_time_us);
                    p.presented_at = checked
                        .and_then(Result::ok)
                        .and_then(|us| u64::try_from(us).ok())
                        .map(Duration::from_micros);
                    p.late_swap = p.present_at_us.is_some_and(|t| waiting_from_us > t);
                    // What the margin has to cover: from the release to the node ready to wait.
                    if let (Some(Ok(ready)), Some(released)) = (waited, swapped_at) {
                        let ready = Duration::from_micros(u64::try_from(ready).unwrap_or(0));
                        self.timing.observe(ready.saturating_sub(released));
                    }
                    if p.late_swap {
                        self.nodes.get_mut(node).expect("checked").counters.late_swaps += 1;
                    }
                }
                self.finish_presented(&mut out);
            }
            _ => st.counters.late_presented += 1,
        }
        Ok(out)
    }

    fn handle_pong(
        &mut self,
        now: Duration,
        node: &str,
        id: u64,
        t0_us: i64,
        (t1_us, sent_us): (i64, i64),
        resident_bytes: u64,
    ) -> Result<Vec<ControllerOutput>, ProtocolError> {
        let st = self.nodes.get_mut(node).expect("checked");
        let Some(pos) = st.pings.iter().position(|&(p, _)| p == id) else {
            return Ok(self.ignore(
                now,
                node,
                format!("Pong for Ping {id}, which was not sent to it (or was answered)"),
            ));
        };
        let (_, sent) = st.pings[pos];
        if sent != t0_us {
            let what = format!("Pong for Ping {id} echoes t0 = {t0_us} us, but it was sent at {sent} us");
            return Ok(self.ignore(now, node, what));
        }
        st.pings.remove(pos);
        let held_us = sent_us.saturating_sub(t1_us);
        if let Err(why) = st.clock.admit(ClockSample { t0_us: sent, t1_us, held_us, t2_us: micros(now) }) {
            st.counters.refused_times += 1;
            return Ok(self.ignore_line(now, node, format!("Pong for Ping {id} refused: {why}")));
        }
        st.counters.pongs += 1;
        st.clock_fitted = st.clock.estimate().is_some_and(|e| e.is_fitted());
        // 0: the node's OS does not say.
        st.resident_bytes = (resident_bytes > 0).then_some(resident_bytes);
        Ok(Vec::new())
    }

    /// An unsolicited message of `node`, ignored: counted, and told within the node's line budget.
    fn ignore(&mut self, now: Duration, node: &str, what: String) -> Vec<ControllerOutput> {
        if let Some(st) = self.nodes.get_mut(node) {
            st.counters.ignored += 1;
        }
        self.ignore_line(now, node, format!("ignored {what}"))
    }

    /// The line about something of `node`'s ignored or refused, if its budget lets it through.
    fn ignore_line(&mut self, now: Duration, node: &str, what: String) -> Vec<ControllerOutput> {
        match self.peer_log.allow(now, node) {
            Some(held_back) => {
                vec![ControllerOutput::PeerIgnored {
                    node: node.to_string(),
                    what: printable(&what),
                    held_back,
                }]
            }
            None => Vec::new(),
        }
    }

    /// object space: asks `node` to load `brick` (the message to send); its BrickLoaded or
    /// BrickFailed for that brick is expected from then on, and any other is ignored.
    pub fn load_brick(&mut self, node: &str, brick: u64) -> ControllerOutput {
        if let Some(st) = self.nodes.get_mut(node) {
            st.loads_owed.insert(brick);
        }
        ControllerOutput::Send { node: node.to_string(), message: Message::LoadBrick { brick } }
    }

    /// The interval of each node's line budget for [`ControllerOutput::PeerIgnored`].
    pub fn peer_log_interval(&self) -> Duration {
        self.peer_log.interval()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::render_state::RenderSettings;
    use glam::DVec3;

    fn ms(x: u64) -> Duration {
        Duration::from_millis(x)
    }

    fn state(id: u64) -> FrameState {
        let cam =
            Camera { eye: DVec3::new(0.0, -5.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 30.0 };
        FrameState::new(id, &cam, &RenderSettings::new(0.5), 1)
    }

    fn sends(out: &[ControllerOutput]) -> Vec<(String, &'static str)> {
        out.iter()
            .filter_map(|o| match o {
                ControllerOutput::Send { node, message } => Some((node.clone(), message.kind())),
                _ => None,
            })
            .collect()
    }

    fn released(out: &[ControllerOutput]) -> Option<(Vec<String>, Vec<String>, Duration)> {
        out.iter().find_map(|o| match o {
            ControllerOutput::Released { ready, stragglers, barrier, .. } => {
                Some((ready.clone(), stragglers.clone(), *barrier))
            }
            _ => None,
        })
    }

    fn controller(names: &[&str]) -> FrameController {
        let mut c = FrameController::new(names.iter().map(|s| s.to_string()).collect(), ms(50));
        c.set_ping_interval(None);
        for n in names {
            let out = c.node_up(ms(0), n).unwrap();
            assert_eq!(sends(&out), vec![(n.to_string(), "Ping")]);
        }
        c
    }

    #[test]
    fn node_info_is_kept_once_per_connection_bounded_and_printable() {
        use crate::messages::{NodeInfo, MAX_NODE_INFO_CHARS};
        let mut c = controller(&["a", "b"]);
        assert_eq!(c.node_info("a"), None);
        let info = NodeInfo {
            version: "0.1.0".into(),
            adapter: "llvmpipe\u{1b}[2J".into(),
            backend: "Vulkan".into(),
            driver: "llvmpipe".into(),
            driver_info: "Mesa".into(),
            present: "SCHED_FIFO 10".into(),
        };
        assert!(c.handle(ms(1), "a", Message::NodeInfo(info.clone())).unwrap().is_empty());
        let kept = c.node_info("a").unwrap();
        assert_eq!((kept.version.as_str(), kept.adapter.as_str()), ("0.1.0", "llvmpipe\\u{1b}[2J"));
        // A second one on the same connection is ignored (and told within the node's budget).
        let mut other = info.clone();
        other.version = "9.9.9".into();
        let out = c.handle(ms(2), "a", Message::NodeInfo(other.clone())).unwrap();
        assert_eq!(ignored(&out), vec!["ignored a second NodeInfo on one connection".to_string()]);
        assert_eq!(c.node_info("a").unwrap().version, "0.1.0");
        // A new connection tells it again; kept while the node is down.
        c.node_down(ms(3), "a", "gone");
        assert_eq!(c.node_info("a").unwrap().version, "0.1.0");
        c.node_up(ms(4), "a").unwrap();
        c.handle(ms(5), "a", Message::NodeInfo(other)).unwrap();
        assert_eq!(c.node_info("a").unwrap().version, "9.9.9");
        // Too long: a protocol error, nothing kept.
        let mut long = info;
        long.driver_info = "d".repeat(MAX_NODE_INFO_CHARS + 1);
        let e = c.handle(ms(6), "b", Message::NodeInfo(long)).unwrap_err();
        assert!(e.problem.contains("`driver_info` has 257 characters"), "{e}");
        assert_eq!(c.node_info("b"), None);
        // The controller's own message from a node is refused.
        let e = c.handle(ms(7), "b", Message::Restart { reason: String::new() }).unwrap_err();
        assert!(e.problem.contains("only the controller"), "{e}");
    }

    #[test]
    fn a_thumbnail_asks_each_node_once_until_it_answers() {
        let mut c = controller(&["a", "b"]);
        let out = c.request_thumbnail(ms(1), 8);
        assert_eq!(sends(&out), vec![("a".into(), "ThumbnailRequest"), ("b".into(), "ThumbnailRequest")]);
        assert!(matches!(
            &out[0],
            ControllerOutput::Send { message: Message::ThumbnailRequest { divisor: 8 }, .. }
        ));
        let tile = TileImage { name: "ta".into(), width: 2, height: 1, frame_id: 0, rgb8: vec![0; 6] };
        let out = c.handle(ms(2), "a", Message::Snapshot { tiles: vec![tile.clone()] }).unwrap();
        assert_eq!(out, vec![ControllerOutput::Snapshot { node: "a".into(), tiles: vec![tile.clone()] }]);
        // b still owes its answer: only a is asked again, and b's late answer is no protocol error.
        let out = c.request_thumbnail(ms(3), 8);
        assert_eq!(sends(&out), vec![("a".into(), "ThumbnailRequest")]);
        assert!(c.handle(ms(4), "b", Message::Snapshot { tiles: vec![] }).is_ok());
        assert!(c.handle(ms(5), "b", Message::Snapshot { tiles: vec![] }).is_err(), "one answer per request");
    }

    #[test]
    fn a_thumbnails_tiles_are_the_nodes_own_over_the_divisor_and_answers_come_in_order() {
        let mut c = controller(&["a"]);
        c.set_node_tiles("a", vec![("ta".into(), 5, 3)]);
        let tile = |w: u32, h: u32| TileImage {
            name: "ta".into(),
            width: w,
            height: h,
            frame_id: 0,
            rgb8: vec![0; (w * h * 3) as usize],
        };
        // 5x3 over 2 is 3x2; the full tile answers a thumbnail wrongly, and the reverse.
        c.request_thumbnail(ms(1), 2);
        let e = c.handle(ms(2), "a", Message::Snapshot { tiles: vec![tile(5, 3)] }).unwrap_err();
        assert!(e.to_string().contains("not one of its tiles over 2"), "{e}");
        c.request_snapshot(ms(3));
        assert!(c.handle(ms(4), "a", Message::Snapshot { tiles: vec![tile(3, 2)] }).is_err());
        // A thumbnail, then a full snapshot before the first answer: each answer in its turn.
        let asked = [c.request_thumbnail(ms(5), 2), c.request_snapshot(ms(6))];
        assert_eq!(asked.iter().map(|o| sends(o).len()).sum::<usize>(), 2);
        assert!(c.handle(ms(7), "a", Message::Snapshot { tiles: vec![tile(3, 2)] }).is_ok());
        assert!(c.handle(ms(8), "a", Message::Snapshot { tiles: vec![tile(5, 3)] }).is_ok());
        assert!(c.handle(ms(9), "a", Message::Snapshot { tiles: vec![] }).is_err(), "nobody asked");
    }

    #[test]
    fn a_frame_is_released_when_all_are_ready_and_done_when_all_presented() {
        let mut c = controller(&["a", "b"]);
        let out = c.begin_frame(ms(100), state(1)).unwrap();
        assert_eq!(sends(&out), vec![("a".into(), "FrameState"), ("b".into(), "FrameState")]);
        assert_eq!(c.in_flight(), Some(1));
        assert_eq!(c.poll_timeout(), Some(ms(150)));
        assert!(c.handle(ms(110), "a", Message::Ready { frame_id: 1, render_us: 9000 }).unwrap().is_empty());
        let out = c.handle(ms(120), "b", Message::Ready { frame_id: 1, render_us: 19000 }).unwrap();
        assert_eq!(sends(&out), vec![("a".into(), "Swap"), ("b".into(), "Swap")]);
        assert_eq!(released(&out), Some((vec!["a".into(), "b".into()], vec![], ms(20))));
        assert_eq!(c.in_flight(), None);
        assert_eq!(c.presenting(), Some(1));
        // No clock offsets known (no Pong yet): presented_at stays None.
        c.handle(ms(125), "a", Message::Presented { frame_id: 1, node_time_us: 5, waiting_from_us: 5 })
            .unwrap();
        let out = c
            .handle(ms(126), "b", Message::Presented { frame_id: 1, node_time_us: 6, waiting_from_us: 6 })
            .unwrap();
        let ControllerOutput::FrameDone { frame_id: 1, stats } = &out[0] else { panic!("{out:?}") };
        assert_eq!(stats.barrier, ms(20));
        assert_eq!(stats.swap_skew, None);
        assert_eq!(stats.per_node[1].render, Some(ms(19)));
        assert_eq!(stats.per_node[1].ready_after, Some(ms(20)));
        assert_eq!(stats.per_node[1].presented_node_time_us, Some(6));
        assert_eq!(c.poll_timeout(), None);
    }

    #[test]
    fn a_surface_claim_is_kept_with_its_frame_and_one_past_the_tiles_pixels_is_ignored() {
        let mut c = controller(&["a", "b"]);
        c.set_node_tiles("a", vec![("t0".into(), 4, 3)]);
        c.begin_frame(ms(0), state(1)).unwrap();
        let claim = |hits, level0| Message::Surface { frame_id: 1, hits, level0 };
        // More hits than its 12 pixels, or more at level 0 than hits: a lie, ignored and counted.
        for lie in [claim(13, 0), claim(5, 6)] {
            let out = c.handle(ms(1), "a", lie).unwrap();
            assert!(
                matches!(&out[..], [ControllerOutput::PeerIgnored { what, .. }] if what.contains("hits at level 0")),
                "{out:?}"
            );
        }
        assert!(c.handle(ms(1), "a", claim(12, 9)).unwrap().is_empty());
        let out = c.handle(ms(1), "a", claim(12, 12)).unwrap();
        assert!(
            matches!(&out[..], [ControllerOutput::PeerIgnored { what, .. }] if what.contains("second Surface"))
        );
        for (n, t) in [("a", 2), ("b", 3)] {
            c.handle(ms(t), n, Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        }
        // After its Ready, or for a frame never sent: ignored.
        let out = c.handle(ms(4), "a", claim(1, 1)).unwrap();
        assert!(
            matches!(&out[..], [ControllerOutput::PeerIgnored { what, .. }] if what.contains("not rendering"))
        );
        c.handle(ms(5), "a", Message::Presented { frame_id: 1, node_time_us: 0, waiting_from_us: 0 })
            .unwrap();
        let out = c
            .handle(ms(6), "b", Message::Presented { frame_id: 1, node_time_us: 0, waiting_from_us: 0 })
            .unwrap();
        let ControllerOutput::FrameDone { stats, .. } = &out[0] else { panic!("{out:?}") };
        let kept = stats.per_node[0].surface.unwrap();
        assert_eq!((kept, stats.per_node[1].surface), (SurfaceLevels { hits: 12, level0: 9 }, None));
        assert_eq!(kept.share(), 0.75);
        assert_eq!(c.counters("a").unwrap().ignored, 4);
    }

    #[test]
    fn a_late_time_step_is_told_and_kept_with_the_frame_and_a_stray_one_is_ignored() {
        let mut c = controller(&["a", "b"]);
        c.begin_frame(ms(0), state(1).at_time_step(6)).unwrap();
        let late = Message::StepLate { frame_id: 1, shown_step: 5, waited_us: 40_000 };
        let out = c.handle(ms(1), "a", late.clone()).unwrap();
        let told = StepLate { shown_step: 5, waited: ms(40) };
        assert_eq!(
            out,
            vec![ControllerOutput::StepLate {
                node: "a".into(),
                frame_id: 1,
                wanted: 6,
                late: told,
                told: Some(0)
            }]
        );
        // A second one for the frame is ignored (told once), so are ones after its Ready or for a
        // frame never sent: counted, never kept.
        let out = c.handle(ms(1), "a", late.clone()).unwrap();
        assert!(
            matches!(&out[..], [ControllerOutput::PeerIgnored { what, .. }] if what.contains("second StepLate")),
            "{out:?}"
        );
        c.handle(ms(2), "a", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        c.handle(ms(3), "b", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        let out = c.handle(ms(4), "a", late).unwrap();
        assert!(
            matches!(&out[..], [ControllerOutput::PeerIgnored { what, .. }] if what.contains("not rendering")),
            "{out:?}"
        );
        let never = Message::StepLate { frame_id: 9, shown_step: 0, waited_us: 0 };
        c.handle(ms(4), "b", never).unwrap();
        assert_eq!((c.counters("a").unwrap().ignored, c.counters("b").unwrap().ignored), (2, 1));
        c.handle(ms(5), "a", Message::Presented { frame_id: 1, node_time_us: 0, waiting_from_us: 0 })
            .unwrap();
        let out = c
            .handle(ms(5), "b", Message::Presented { frame_id: 1, node_time_us: 0, waiting_from_us: 0 })
            .unwrap();
        let ControllerOutput::FrameDone { stats, .. } = &out[0] else { panic!("{out:?}") };
        assert_eq!(stats.time_step, 6);
        assert_eq!(stats.per_node[0].step_late, Some(told));
        assert_eq!(stats.per_node[1].step_late, None);
    }

    #[test]
    fn a_balanced_walls_costs_go_to_the_caller_only_for_a_frame_the_node_renders() {
        let mut c = controller(&["a", "b"]);
        c.begin_frame(ms(0), state(1)).unwrap();
        let costs = vec![WireRectCost { tile: 0, first_row: 0, rows: 8, cost: 77 }];
        let msg = |id| Message::RectCosts { frame_id: id, costs: costs.clone() };
        let out = c.handle(ms(5), "a", msg(1)).unwrap();
        assert_eq!(
            out,
            vec![ControllerOutput::RectCosts { node: "a".into(), frame_id: 1, costs: costs.clone() }]
        );
        // A second report of the same frame breaks the protocol: once a frame.
        let e = c.handle(ms(5), "a", msg(1)).unwrap_err().to_string();
        assert!(e.contains("once a frame"), "{e}");
        // For a frame never sent, or after its Ready, RectCosts breaks the protocol.
        assert!(c.handle(ms(6), "b", msg(2)).is_err());
        c.handle(ms(7), "a", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        assert!(c.handle(ms(8), "a", msg(1)).is_err());
    }

    #[test]
    fn object_space_stats_reach_the_frame_and_a_stray_composited_is_an_error() {
        let mut c = controller(&["a", "b"]);
        c.begin_frame(ms(0), state(1)).unwrap();
        let comp = |id| Message::Composited {
            frame_id: id,
            bytes_sent: 1234,
            composite_us: 2500,
            merge_us: 700,
            resident_bytes: 99,
            missing: vec![],
        };
        assert!(c.handle(ms(5), "a", comp(1)).unwrap().is_empty());
        c.handle(ms(6), "a", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        c.handle(ms(7), "b", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        // After its Ready, or for a frame never sent, Composited breaks the protocol.
        assert!(c.handle(ms(8), "a", comp(1)).is_err());
        c.handle(ms(9), "a", Message::Presented { frame_id: 1, node_time_us: 0, waiting_from_us: 0 })
            .unwrap();
        let out = c
            .handle(ms(9), "b", Message::Presented { frame_id: 1, node_time_us: 0, waiting_from_us: 0 })
            .unwrap();
        let ControllerOutput::FrameDone { stats, .. } = &out[0] else { panic!("{out:?}") };
        assert_eq!(stats.per_node[0].bytes_sent, Some(1234));
        assert_eq!(stats.per_node[0].composite, Some(Duration::from_micros(2500)));
        assert_eq!(stats.per_node[0].resident_bytes, Some(99));
        assert_eq!(stats.per_node[0].merge, Some(Duration::from_micros(700)));
        assert_eq!(stats.per_node[1].bytes_sent, None);
        assert!(c.handle(ms(10), "b", comp(7)).is_err());
    }

    #[test]
    fn missing_pixels_are_told_when_they_change_and_name_only_other_nodes() {
        let mut c = controller(&["a", "b", "c"]);
        let comp = |id, missing: &[&str]| Message::Composited {
            frame_id: id,
            bytes_sent: 0,
            composite_us: 0,
            merge_us: 0,
            resident_bytes: 0,
            missing: missing.iter().map(|s| s.to_string()).collect(),
        };
        let mut told = Vec::new();
        for id in 1..=4 {
            c.begin_frame(ms(id * 100), state(id)).unwrap();
            let missing: &[&str] = if id == 2 || id == 3 { &["c"] } else { &[] };
            told.extend(c.handle(ms(id * 100 + 5), "a", comp(id, missing)).unwrap());
            for n in ["a", "b", "c"] {
                c.handle(ms(id * 100 + 6), n, Message::Ready { frame_id: id, render_us: 0 }).unwrap();
            }
            for n in ["a", "b", "c"] {
                c.handle(
                    ms(id * 100 + 7),
                    n,
                    Message::Presented { frame_id: id, node_time_us: 0, waiting_from_us: 0 },
                )
                .unwrap();
            }
        }
        assert_eq!(
            told,
            vec![
                ControllerOutput::PixelsMissing { node: "a".into(), frame_id: 2, peers: vec!["c".into()] },
                ControllerOutput::PixelsMissing { node: "a".into(), frame_id: 4, peers: vec![] },
            ]
        );
        c.begin_frame(ms(500), state(5)).unwrap();
        for bad in [&["a"][..], &["zz"], &["b", "b"]] {
            let e = c.handle(ms(501), "a", comp(5, bad)).unwrap_err();
            assert!(e.to_string().contains("missing"), "{e}");
        }
    }

    #[test]
    fn the_deadline_releases_the_ready_and_names_the_stragglers() {
        let mut c = controller(&["a", "b", "c"]);
        c.begin_frame(ms(0), state(1)).unwrap();
        c.handle(ms(10), "a", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        assert!(c.handle_timeout(ms(49)).is_empty());
        let out = c.handle_timeout(ms(50));
        assert_eq!(released(&out), Some((vec!["a".into()], vec!["b".into(), "c".into()], ms(50))));
        assert_eq!(sends(&out), vec![("a".into(), "Swap")]);
        // A straggler's late Ready is counted, not an error; a second one for the same frame is.
        assert!(c.handle(ms(60), "b", Message::Ready { frame_id: 1, render_us: 0 }).unwrap().is_empty());
        assert_eq!(c.counters("b").unwrap().late_ready, 1);
        assert_eq!(c.counters("b").unwrap().straggled, 1);
        let e = c.handle(ms(61), "b", Message::Ready { frame_id: 1, render_us: 0 }).unwrap_err();
        assert_eq!((e.peer.as_str(), e.message), ("b", "Ready"));
        // The next frame may begin while frame 1 still waits for Presented.
        c.begin_frame(ms(62), state(2)).unwrap();
        assert_eq!(c.presenting(), Some(1));
        let out = c
            .handle(ms(63), "a", Message::Presented { frame_id: 1, node_time_us: 0, waiting_from_us: 0 })
            .unwrap();
        assert!(matches!(&out[0], ControllerOutput::FrameDone { frame_id: 1, .. }));
    }

    #[test]
    fn a_node_going_down_releases_a_frame_that_waited_only_on_it() {
        let mut c = controller(&["a", "b"]);
        c.begin_frame(ms(0), state(1)).unwrap();
        c.handle(ms(10), "a", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        let out = c.node_down(ms(20), "b", "connection lost");
        assert_eq!(out[0], ControllerOutput::NodeDown { node: "b".into(), reason: "connection lost".into() });
        assert_eq!(released(&out), Some((vec!["a".into()], vec![], ms(20))));
        assert!(c.node_down(ms(21), "b", "again").is_empty());
        // Down: not in the next frame, listed as missing.
        let out = c.begin_frame(ms(30), state(2)).unwrap();
        assert_eq!(sends(&out), vec![("a".into(), "FrameState")]);
        // Back up mid-frame: joins at the next one.
        c.node_up(ms(31), "b").unwrap();
        let out = c.handle(ms(32), "a", Message::Ready { frame_id: 2, render_us: 0 }).unwrap();
        assert_eq!(released(&out).unwrap().0, vec!["a".to_string()]);
        let out = c.begin_frame(ms(40), state(3)).unwrap();
        assert_eq!(sends(&out).len(), 2);
        // Presented from frame 2 finishes it, and frame 1 before it (frames finish in order),
        // with what arrived: nothing from `a` for frame 1.
        let out = c
            .handle(ms(41), "a", Message::Presented { frame_id: 2, node_time_us: 0, waiting_from_us: 0 })
            .unwrap();
        let done: Vec<&FrameStats> = out
            .iter()
            .filter_map(|o| match o {
                ControllerOutput::FrameDone { stats, .. } => Some(stats),
                _ => None,
            })
            .collect();
        assert_eq!(done.iter().map(|s| s.frame_id).collect::<Vec<_>>(), vec![1, 2]);
        assert_eq!(done[0].per_node[0].presented_node_time_us, None);
        assert_eq!(done[1].missing, vec!["b".to_string()]);
    }

    #[test]
    fn frames_cannot_overlap_or_go_backwards() {
        let mut c = controller(&["a"]);
        c.begin_frame(ms(0), state(5)).unwrap();
        assert_eq!(c.begin_frame(ms(1), state(6)), Err(BeginError::InFlight(5)));
        c.handle_timeout(ms(50));
        assert_eq!(c.begin_frame(ms(51), state(5)), Err(BeginError::NotIncreasing { last: 5, given: 5 }));
        // With nobody up a frame is released and finished at once.
        let mut c = FrameController::new(vec!["a".into()], ms(50));
        let out = c.begin_frame(ms(0), state(1)).unwrap();
        assert!(matches!(out[0], ControllerOutput::Released { .. }));
        assert!(matches!(out[1], ControllerOutput::FrameDone { .. }));
        assert_eq!(c.in_flight(), None);
    }

    #[test]
    fn protocol_violations_name_the_node_and_the_message() {
        let mut c = controller(&["a", "b"]);
        c.begin_frame(ms(0), state(1)).unwrap();
        let cases: Vec<(&str, Message, &str)> = vec![
            ("a", Message::Ready { frame_id: 2, render_us: 0 }, "never sent"),
            ("a", Message::Swap { frame_id: 1, present_at_us: None }, "only the controller"),
            ("a", Message::FrameState(state(1)), "only the controller"),
            (
                "a",
                Message::Hello { version: 1, name: "a".into(), role: crate::messages::Role::Daemon },
                "second Hello",
            ),
            ("a", Message::Snapshot { tiles: vec![] }, "nobody asked"),
            ("zz", Message::Ready { frame_id: 1, render_us: 0 }, "not a node of this wall"),
        ];
        for (node, msg, what) in cases {
            let kind = msg.kind();
            let e = c.handle(ms(1), node, msg).unwrap_err();
            assert_eq!((e.peer.as_str(), e.message), (node, kind));
            assert!(e.problem.contains(what), "{e}");
            assert!(e.to_string().contains(node) && e.to_string().contains(kind), "{e}");
        }
        c.node_down(ms(2), "b", "x");
        let e = c.handle(ms(3), "b", Message::Ready { frame_id: 1, render_us: 0 }).unwrap_err();
        assert!(e.problem.contains("not up"), "{e}");
        assert!(c.node_up(ms(3), "nobody").is_err());
    }

    /// The `what` of every PeerIgnored in `out`.
    fn ignored(out: &[ControllerOutput]) -> Vec<String> {
        out.iter()
            .filter_map(|o| match o {
                ControllerOutput::PeerIgnored { what, .. } => Some(what.clone()),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn unsolicited_messages_are_ignored_counted_and_told_within_a_budget() {
        let mut c = controller(&["a", "b"]);
        c.begin_frame(ms(0), state(1)).unwrap();
        let evil = "\u{1b}[2J\u{1b}[31mowned\r\nisowall: frame 9: all good";
        let cases: Vec<(Message, &str)> = vec![
            (
                Message::Presented { frame_id: 1, node_time_us: 0, waiting_from_us: 0 },
                "before (or without) its Swap",
            ),
            (Message::Pong { id: 99, t0_us: 0, t1_us: 0, sent_us: 0, resident_bytes: 0 }, "not sent to it"),
            (Message::BrickFailed { brick: 3, reason: evil.into() }, "not asked to load"),
            (Message::BrickLoaded { brick: 3, load_us: 1, resident_bytes: 1 }, "not asked to load"),
        ];
        for (msg, what) in cases {
            let out = c.handle(ms(1), "a", msg).unwrap();
            let lines = ignored(&out);
            assert_eq!(lines.len(), 1, "{out:?}");
            assert!(lines[0].contains(what), "{lines:?}");
            assert!(!lines[0].contains('\u{1b}') && !lines[0].contains('\n'), "{lines:?}");
        }
        // A Pong whose t0 is not the Ping's.
        let out = c.ping(ms(5));
        let Some(ControllerOutput::Send { message: Message::Ping { id, t0_us }, .. }) = out.first() else {
            panic!()
        };
        let out = c
            .handle(
                ms(6),
                "a",
                Message::Pong { id: *id, t0_us: t0_us + 1, t1_us: 0, sent_us: 0, resident_bytes: 0 },
            )
            .unwrap();
        assert!(ignored(&out)[0].contains("echoes"), "{out:?}");
        assert_eq!(c.counters("a").unwrap().ignored, 5);
        assert!(c.is_up("a"), "ignored, not closed");
        // Asked to load brick 3, its BrickFailed is told (once: a second is unsolicited).
        let send = c.load_brick("a", 3);
        assert_eq!(
            send,
            ControllerOutput::Send { node: "a".into(), message: Message::LoadBrick { brick: 3 } }
        );
        let failed = Message::BrickFailed { brick: 3, reason: evil.into() };
        let out = c.handle(ms(7), "a", failed.clone()).unwrap();
        let [ControllerOutput::BrickFailed { brick: 3, reason, .. }] = &out[..] else { panic!("{out:?}") };
        assert!(!reason.contains('\u{1b}'), "{reason}");
        // The budget (5 lines per 10 s) is spent: counted, not told.
        assert_eq!(c.handle(ms(7), "a", failed).unwrap(), vec![]);
        assert_eq!(c.counters("a").unwrap().ignored, 6);
        // A flood: 60,000 unsolicited messages over 6 s of virtual time make at most
        // PeerLog::LINES lines per PeerLog::INTERVAL, the next one saying how many were held back.
        let mut lines = 0;
        let mut held = 0;
        for i in 0..60_000u64 {
            let msg = Message::BrickFailed { brick: i, reason: evil.into() };
            for o in c.handle(ms(10) + Duration::from_micros(i * 100), "a", msg).unwrap() {
                if let ControllerOutput::PeerIgnored { held_back, .. } = o {
                    lines += 1;
                    held += held_back;
                }
            }
        }
        assert_eq!(lines, 0, "the first window's budget (from 1 ms, 10 s long) was spent");
        let out =
            c.handle(ms(10_001), "a", Message::BrickFailed { brick: 1, reason: String::new() }).unwrap();
        let [ControllerOutput::PeerIgnored { held_back, .. }] = &out[..] else { panic!("{out:?}") };
        assert_eq!(*held_back + held, 60_000 + 1, "every line held back is counted");
        assert_eq!(c.counters("a").unwrap().ignored, 5 + 1 + 60_000 + 1);
        // Node b's budget is its own.
        assert_eq!(
            ignored(
                &c.handle(
                    ms(10_002),
                    "b",
                    Message::Pong { id: 7, t0_us: 0, t1_us: 0, sent_us: 0, resident_bytes: 0 }
                )
                .unwrap()
            )
            .len(),
            1
        );
    }

    #[test]
    fn a_step_late_every_frame_is_kept_with_each_frame_and_told_within_the_budget() {
        let mut c = controller(&["a"]);
        let (mut told, mut kept, mut held) = (0, 0, 0);
        // 1,000 frames at 100 a second (10 s of virtual time), each late.
        for id in 1..=1_000u64 {
            let t = ms(id * 10);
            c.begin_frame(t, state(id).at_time_step(6)).unwrap();
            let late = Message::StepLate { frame_id: id, shown_step: 5, waited_us: 1 };
            for o in c.handle(t, "a", late).unwrap() {
                if let ControllerOutput::StepLate { told: t, .. } = o {
                    kept += 1;
                    if let Some(h) = t {
                        told += 1;
                        held += h;
                    }
                }
            }
            c.handle(t, "a", Message::Ready { frame_id: id, render_us: 0 }).unwrap();
            c.handle(t, "a", Message::Presented { frame_id: id, node_time_us: 0, waiting_from_us: 0 })
                .unwrap();
        }
        assert_eq!(kept, 1_000, "every one reaches its frame");
        // Windows start at 10 ms and 10,010 ms: 5 lines in the first, 1 in the second (at 10 s).
        assert_eq!(told, 5, "lines told in 10 s");
        assert_eq!(held, 0);
        let last = Message::StepLate { frame_id: 1_001, shown_step: 5, waited_us: 1 };
        c.begin_frame(ms(10_010), state(1_001).at_time_step(6)).unwrap();
        let out = c.handle(ms(10_010), "a", last).unwrap();
        assert!(matches!(&out[..], [ControllerOutput::StepLate { told: Some(995), .. }]), "{out:?}");
    }

    #[test]
    fn forged_present_and_pong_times_are_refused_before_they_reach_the_skew() {
        let mut c = controller(&["a", "b"]);
        // The node_up pings were id 1 (a) and 2 (b) at t0 = 0; both clocks 10 ms ahead, 1 ms each way.
        c.handle(
            ms(2),
            "a",
            Message::Pong {
                id: 1,
                t0_us: 0,
                t1_us: 1_000 + 10_000,
                sent_us: 1_000 + 10_000,
                resident_bytes: 0,
            },
        )
        .unwrap();
        c.handle(
            ms(2),
            "b",
            Message::Pong {
                id: 2,
                t0_us: 0,
                t1_us: 1_000 + 10_000,
                sent_us: 1_000 + 10_000,
                resident_bytes: 0,
            },
        )
        .unwrap();
        let days_46 = 46 * 86_400 * 1_000_000i64;
        // A Pong 46 days off is refused; the offset stays.
        let out = c.ping(ms(100));
        let Some(ControllerOutput::Send { message: Message::Ping { id, t0_us }, .. }) =
            out.iter().find(|o| matches!(o, ControllerOutput::Send { node, .. } if node == "a"))
        else {
            panic!()
        };
        let forged = Message::Pong {
            id: *id,
            t0_us: *t0_us,
            t1_us: 101_000 + 10_000 + days_46,
            sent_us: 101_000 + 10_000 + days_46,
            resident_bytes: 0,
        };
        let lines = ignored(&c.handle(ms(102), "a", forged).unwrap());
        assert!(lines[0].contains("Pong for Ping") && lines[0].contains("refused"), "{lines:?}");
        assert_eq!(c.clock_offset("a").unwrap().offset_us, 10_000);
        assert_eq!(c.counters("a").unwrap().refused_times, 1);
        // A Presented 46 days late: refused, the frame done with b's time only; a skew of 0.4 ms stays.
        for id in 1..=3u64 {
            let t = 200 * id;
            c.begin_frame(ms(t), state(id)).unwrap();
            c.handle(ms(t + 5), "a", Message::Ready { frame_id: id, render_us: 0 }).unwrap();
            c.handle(ms(t + 5), "b", Message::Ready { frame_id: id, render_us: 0 }).unwrap();
            let present_us = (t as i64 + 10) * 1_000 + 10_000;
            let a_time = if id == 2 { present_us + days_46 } else { present_us };
            let out = c
                .handle(
                    ms(t + 12),
                    "a",
                    Message::Presented { frame_id: id, node_time_us: a_time, waiting_from_us: a_time },
                )
                .unwrap();
            assert_eq!(ignored(&out).len(), usize::from(id == 2), "{out:?}");
            let out = c
                .handle(
                    ms(t + 12),
                    "b",
                    Message::Presented {
                        frame_id: id,
                        node_time_us: present_us + 400,
                        waiting_from_us: present_us + 400,
                    },
                )
                .unwrap();
            let Some(ControllerOutput::FrameDone { stats, .. }) = out.last() else { panic!("{out:?}") };
            if id == 2 {
                assert_eq!(stats.swap_skew, Some(Duration::ZERO), "b's time only");
                assert_eq!(stats.per_node[0].presented_at, None);
                assert_eq!(stats.per_node[0].presented_node_time_us, None);
            } else {
                assert_eq!(stats.swap_skew, Some(Duration::from_micros(400)));
            }
        }
        // Before its Swap was sent (a present time from the past) is refused too.
        c.begin_frame(ms(1_000), state(4)).unwrap();
        c.handle(ms(1_005), "a", Message::Ready { frame_id: 4, render_us: 0 }).unwrap();
        c.handle(ms(1_005), "b", Message::Ready { frame_id: 4, render_us: 0 }).unwrap();
        let out = c
            .handle(
                ms(1_010),
                "a",
                Message::Presented { frame_id: 4, node_time_us: 10_000, waiting_from_us: 10_000 },
            )
            .unwrap();
        assert!(ignored(&out)[0].contains("before the earliest"), "{out:?}");
        assert_eq!(c.counters("a").unwrap().refused_times, 3);
        assert_eq!(c.counters("b").unwrap().refused_times, 0);
    }

    #[test]
    fn pongs_give_offsets_and_presented_times_convert_through_them() {
        let mut c = controller(&["a", "b"]);
        // The node_up pings were id 1 (a) and 2 (b) at t0 = 0; a's clock is 50 ms ahead, b's 30 ms
        // behind, 1 ms each way.
        c.handle(
            ms(2),
            "a",
            Message::Pong {
                id: 1,
                t0_us: 0,
                t1_us: 1_000 + 50_000,
                sent_us: 1_000 + 50_000,
                resident_bytes: 7 << 20,
            },
        )
        .unwrap();
        c.handle(
            ms(2),
            "b",
            Message::Pong {
                id: 2,
                t0_us: 0,
                t1_us: 1_000 - 30_000,
                sent_us: 1_000 - 30_000,
                resident_bytes: 0,
            },
        )
        .unwrap();
        assert_eq!(c.clock_offset("a").unwrap().offset_us, 50_000);
        assert_eq!(c.clock_offset("b").unwrap().offset_us, -30_000);
        assert_eq!(c.clock_offset("a").unwrap().error_us, 1_001);
        // The Pongs carry each node's resident memory (0: not known).
        assert_eq!(c.resident_bytes("a"), Some(7 << 20));
        assert_eq!(c.resident_bytes("b"), None);
        c.begin_frame(ms(100), state(1)).unwrap();
        c.handle(ms(110), "a", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        c.handle(ms(110), "b", Message::Ready { frame_id: 1, render_us: 0 }).unwrap();
        // Both present at controller time 111 ms and 111.4 ms.
        c.handle(
            ms(112),
            "a",
            Message::Presented {
                frame_id: 1,
                node_time_us: 111_000 + 50_000,
                waiting_from_us: 111_000 + 50_000,
            },
        )
        .unwrap();
        let out = c
            .handle(
                ms(112),
                "b",
                Message::Presented {
                    frame_id: 1,
                    node_time_us: 111_400 - 30_000,
                    waiting_from_us: 111_400 - 30_000,
                },
            )
            .unwrap();
        let ControllerOutput::FrameDone { stats, .. } = &out[0] else { panic!() };
        assert_eq!(stats.per_node[0].presented_at, Some(ms(111)));
        assert_eq!(stats.swap_skew, Some(Duration::from_micros(400)));
    }

    #[test]
    fn pings_go_one_node_at_a_time_in_turn_faster_until_the_clocks_are_fitted() {
        let mut c = FrameController::new(vec!["a".into()], ms(50));
        assert_eq!(c.poll_timeout(), None);
        let names = ["a", "b", "c", "d"];
        let mut c2 = FrameController::new(names.iter().map(|n| n.to_string()).collect(), ms(50));
        c.node_up(ms(0), "a").unwrap();
        assert_eq!(c.poll_timeout(), Some(FrameController::DEFAULT_PING_INTERVAL / 5));
        // Four nodes answering every Ping 50 us later, for 20 s.
        let mut pings: Vec<(Duration, String)> = Vec::new();
        let mut fitted_at = None;
        for n in names {
            c2.node_up(ms(0), n).unwrap();
        }
        let mut now = ms(0);
        while now < ms(20_000) {
            now = c2.poll_timeout().unwrap();
            for o in c2.handle_timeout(now) {
                if let ControllerOutput::Send { node, message: Message::Ping { id, t0_us } } = o {
                    pings.push((now, node.clone()));
                    let pong = Message::Pong {
                        id,
                        t0_us,
                        t1_us: t0_us + 50,
                        sent_us: t0_us + 50,
                        resident_bytes: 0,
                    };
                    c2.handle(now + Duration::from_micros(100), &node, pong).unwrap();
                }
            }
            if fitted_at.is_none() && names.iter().all(|n| c2.clock_offset(n).is_some_and(|e| e.is_fitted()))
            {
                fitted_at = Some(now);
            }
        }
        // Never two at once; in turn: a b c d a b ...
        assert!(pings.windows(2).all(|w| w[0].0 < w[1].0));
        for (i, (_, n)) in pings.iter().enumerate() {
            assert_eq!(n, names[i % 4], "ping {i}");
        }
        // Until every clock is fitted (three samples over a second), five times as often.
        let fitted_at = fitted_at.expect("the clocks are fitted");
        assert!(fitted_at <= ms(1_300), "fitted at {fitted_at:?}");
        let early = pings.iter().filter(|(t, _)| *t < fitted_at).count() as f64;
        let late = pings.iter().filter(|(t, _)| *t >= ms(10_000)).count() as f64;
        let (early_rate, late_rate) = (early / fitted_at.as_secs_f64(), late / 10.0);
        assert!((late_rate - 8.0).abs() < 1.0, "settled: {late_rate} pings a second (4 nodes every 500 ms)");
        assert!(early_rate > 3.0 * late_rate, "settling: {early_rate} pings a second");
    }

    /// Plays the wall on a virtual clock: every `step` ms, timers fire; node `a` answers every
    /// Ping and FrameState at once, `b` goes silent at `dies_at`. Returns when `b` was reported
    /// down, and whether `a` ever was.
    fn run_until_down(limit: Option<Duration>, dies_at: u64, until: u64) -> (Option<u64>, bool) {
        let mut c = FrameController::new(vec!["a".into(), "b".into()], ms(100));
        c.set_ping_interval(Some(ms(100)));
        c.set_silence_limit(limit);
        let mut queue: Vec<ControllerOutput> = Vec::new();
        for n in ["a", "b"] {
            queue.extend(c.node_up(ms(0), n).unwrap());
        }
        let (mut b_down, mut a_down) = (None, false);
        let mut next_frame = 1;
        for t in (0..=until).step_by(5) {
            let now = ms(t);
            if c.in_flight().is_none() {
                queue.extend(c.begin_frame(now, state(next_frame)).unwrap());
                next_frame += 1;
            }
            if c.poll_timeout().is_some_and(|at| at <= now) {
                queue.extend(c.handle_timeout(now));
            }
            while !queue.is_empty() {
                for out in std::mem::take(&mut queue) {
                    match out {
                        ControllerOutput::NodeDown { node, reason } => {
                            if node == "b" {
                                assert!(reason.contains("silent for"), "{reason}");
                                b_down.get_or_insert(t);
                            } else {
                                a_down = true;
                            }
                        }
                        ControllerOutput::Send { node, message } if node == "a" || t < dies_at => {
                            let answer = match message {
                                Message::Ping { id, t0_us } => Message::Pong {
                                    id,
                                    t0_us,
                                    t1_us: t0_us,
                                    sent_us: t0_us,
                                    resident_bytes: 1,
                                },
                                Message::FrameState(f) => {
                                    Message::Ready { frame_id: f.frame_id, render_us: 1 }
                                }
                                _ => continue,
                            };
                            queue.extend(c.handle(now, &node, answer).unwrap());
                        }
                        _ => {}
                    }
                }
            }
        }
        (b_down, a_down)
    }

    #[test]
    fn a_silent_node_is_down_within_the_silence_limit_and_an_answering_one_never() {
        // Limit 3 deadlines (300 ms): `b` dies at 1000 ms, down by 1300 ms; `a` stays up.
        let (down, a_down) = run_until_down(Some(ms(300)), 1000, 5000);
        let down = down.expect("the silent node was never reported down");
        assert!((1000..=1300).contains(&down), "down at {down} ms");
        assert!(!a_down, "the node that answers was reported down");
        // Without a limit the machine waits for the transport to say.
        assert_eq!(run_until_down(None, 1000, 5000), (None, false));
    }

    #[test]
    fn a_snapshot_may_carry_only_the_nodes_own_tiles() {
        let mut c = controller(&["a", "b"]);
        c.set_node_tiles("a", vec![("ta".into(), 2, 1)]);
        c.set_node_tiles("b", vec![("tb".into(), 2, 1)]);
        let tile = |name: &str, w: u32| TileImage {
            name: name.into(),
            width: w,
            height: 1,
            frame_id: 0,
            rgb8: vec![0; w as usize * 3],
        };
        for (tiles, why) in [
            (vec![tile("tb", 2)], "not one of its tiles"),
            (vec![tile("ta", 3)], "not one of its tiles"),
            (vec![tile("ta", 2), tile("ta", 2)], "twice"),
        ] {
            c.request_snapshot(ms(1));
            let e = c.handle(ms(2), "a", Message::Snapshot { tiles }).unwrap_err();
            assert!(e.to_string().contains(why) && e.to_string().contains("`a`"), "{e}");
        }
        c.request_snapshot(ms(3));
        let out = c.handle(ms(4), "a", Message::Snapshot { tiles: vec![tile("ta", 2)] }).unwrap();
        assert!(matches!(&out[..], [ControllerOutput::Snapshot { node, .. }] if node == "a"));
    }

    #[test]
    fn a_peers_text_is_printable() {
        assert_eq!(printable("ok: état"), "ok: état");
        assert_eq!(printable("a\x1b[2Jb\nc\r"), "a\\u{1b}[2Jb\\nc\\r");
        assert_eq!(printable(&"x".repeat(1000)).chars().count(), crate::messages::PRINTABLE_CHARS + 3);
    }
}
