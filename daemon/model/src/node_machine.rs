//! The daemon's side of the frame protocol: [`NodeMachine`], sans-IO like
//! [`crate::frame_controller::FrameController`]. `now` is the daemon's own clock (a [`Duration`] since any
//! fixed epoch); the controller learns its offset from Ping/Pong.
//!
//! The caller sends [`NodeMachine::hello`] when the connection opens, passes every message to
//! [`NodeMachine::handle`], and carries out the [`NodeOutput`]s:
//! - `Render { state, accumulate_frame, continuity }`: render `state` (one at a time: the node's
//!   space makes it a [`crate::render_plan::RenderPlan`], what to render), then call
//!   [`NodeMachine::render_done`], which sends Ready. `accumulate_frame` counts frames with the
//!   same image (only the frame id changed): 0 after any change, then 1, 2, ... so progressive AO
//!   can use `settings.ao.frame + accumulate_frame` as its decorrelation index and average in.
//! - `Present { frame_id, at }`: the Swap came: present that frame at `at` of the daemon's clock
//!   (at once when `None` or past; asleep until shortly before it, then a precise wait, on the
//!   thread that presents), then call [`NodeMachine::presented`] with the time it was shown and
//!   the time that thread was ready to wait, which sends Presented (and says whether the swap was
//!   late: `LateSwap`, for the node's log).
//! - `Send(message)`: send it to the controller; a Pong's `sent_us` stamped with the daemon's
//!   clock as it leaves (the machine sets it to the Ping's arrival, `now` of its `handle`: the
//!   caller passes the moment the Ping arrived, not when it got round to it).
//! - `SnapshotWanted`: send `Message::Snapshot` with the tiles' last presented frames.
//! - `ThumbnailWanted { divisor }`: the same, each tile downscaled by `divisor`.
//! - `Closed { reason }`: the controller said goodbye; close the connection.
//!
//! A FrameState that arrives while a frame renders is queued; a newer one replaces it (only the
//! latest is worth rendering). A rendered frame still waiting for its Swap when a new FrameState
//! comes is dropped: the controller released that frame without this node (it was a straggler).

use std::collections::VecDeque;
use std::time::Duration;

use crate::codec::check_hello;
use crate::messages::{
    Message, ProtocolError, Role, MAX_RESTART_REASON_CHARS, MAX_SWAP_WAIT, MAX_THUMBNAIL_DIVISOR,
    PROTOCOL_VERSION,
};
use crate::wire::{Continuity, FrameSequence, FrameSpec, FrameState};

/// What the daemon's caller must do, in order.
#[derive(Debug, Clone, PartialEq)]
pub enum NodeOutput {
    /// Render this frame, then call [`NodeMachine::render_done`]. `continuity` is how it relates
    /// to the frame started before it ([`FrameState::continuity`]): what the renderer's frame plan
    /// follows.
    Render { state: FrameState, accumulate_frame: u32, continuity: Continuity },
    /// Send this to the controller.
    Send(Message),
    /// Present this rendered frame at `at` of the daemon's clock (`None`: now), then call
    /// [`NodeMachine::presented`].
    Present { frame_id: u64, at: Option<Duration> },
    /// The Swap of `frame_id` came `late_by` after its present time: it was presented at once
    /// (counted in [`NodeMachineCounters::late_swaps`]; the caller logs it).
    LateSwap { frame_id: u64, late_by: Duration },
    /// Answer with `Message::Snapshot` of the tiles' last presented frames.
    SnapshotWanted,
    /// Answer with `Message::Snapshot` of them downscaled by `divisor` (`TileImage::downscaled`).
    ThumbnailWanted { divisor: u32 },
    /// The controller said Bye: close the connection.
    Closed { reason: String },
    // object space (`crate::adoption`)
    /// Render, send and composite frames from `from_frame` on by this brick map (validate it
    /// with `BrickMap::from_wire`).
    Bricks { from_frame: u64, holders: Vec<Option<String>> },
    /// Load this brick beside the node's own, then send `BrickLoaded` (or `BrickFailed`).
    LoadBrick { brick: u64 },
    // load-balanced screen space (`crate::balance`)
    /// Render, send and place frames from `from_frame` on by this split (validate it with
    /// `crate::balance::share::split_from_wire`).
    Split { from_frame: u64, split: crate::wire::WireSplit },
    /// The controller (the one holding the node's seat: no other gets this far) asked the node
    /// to restart: log `reason`, close the connection and exit with
    /// [`crate::messages::RESTART_EXIT_CODE`] for its supervisor to start it again.
    Restart { reason: String },
    /// Show (`on`) or stop showing the node's and each tile's name on its tiles, from the next
    /// frame on.
    Identify { on: bool },
}

/// Running counts of a daemon.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NodeMachineCounters {
    pub rendered: u64,
    pub presented: u64,
    /// Queued frame states replaced by newer ones before they were rendered.
    pub skipped: u64,
    /// Rendered frames dropped because a newer frame came before their Swap.
    pub dropped: u64,
    /// Swaps whose present time had passed when the presenting thread took them up.
    pub late_swaps: u64,
}

/// The daemon's frame machine (see the module docs).
#[derive(Debug)]
pub struct NodeMachine {
    name: String,
    tiles: Vec<String>,
    hello_done: bool,
    last_frame_id: Option<u64>,
    /// The frame being rendered.
    rendering: Option<u64>,
    /// The latest frame state received while rendering.
    queued: Option<FrameState>,
    /// Rendered, Ready sent, waiting for Swap.
    rendered: Option<u64>,
    /// Present told, `presented` not yet called: (frame, present time).
    presenting: VecDeque<(u64, Option<Duration>)>,
    /// The frames started, for `accumulate_frame` and `continuity`.
    started: FrameSequence,
    last_presented: Option<u64>,
    counters: NodeMachineCounters,
    /// The daemon process's resident memory as last told by its runtime, sent with each Pong.
    resident_bytes: u64,
}

const PEER: &str = "controller";

fn micros(t: Duration) -> i64 {
    i64::try_from(t.as_micros()).unwrap_or(i64::MAX)
}

impl NodeMachine {
    /// A daemon called `name` (its name in the wall config) showing `tiles`.
    pub fn new(name: impl Into<String>, tiles: Vec<String>) -> Self {
        NodeMachine {
            name: name.into(),
            tiles,
            hello_done: false,
            last_frame_id: None,
            rendering: None,
            queued: None,
            rendered: None,
            presenting: VecDeque::new(),
            started: FrameSequence::default(),
            last_presented: None,
            counters: NodeMachineCounters::default(),
            resident_bytes: 0,
        }
    }

    /// The runtime tells the machine its process's resident memory (the machine reads no OS
    /// state); the next Pong carries it to the controller.
    pub fn set_resident_bytes(&mut self, bytes: u64) {
        self.resident_bytes = bytes;
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn tiles(&self) -> &[String] {
        &self.tiles
    }

    /// The frame being rendered.
    pub fn rendering(&self) -> Option<u64> {
        self.rendering
    }

    /// The rendered frame waiting for its Swap.
    pub fn waiting_for_swap(&self) -> Option<u64> {
        self.rendered
    }

    pub fn last_presented(&self) -> Option<u64> {
        self.last_presented
    }

    pub fn counters(&self) -> NodeMachineCounters {
        self.counters
    }

    /// The first message to send on a new connection.
    pub fn hello(&self) -> Message {
        Message::Hello { version: PROTOCOL_VERSION, name: self.name.clone(), role: Role::Daemon }
    }

    /// The connection closed: forget the frames in flight (a new connection starts over; a render
    /// still running is ignored when it completes). Accumulation restarts too.
    pub fn reset(&mut self) {
        *self = NodeMachine {
            counters: self.counters,
            ..NodeMachine::new(self.name.clone(), self.tiles.clone())
        };
    }

    fn start(&mut self, state: FrameState) -> NodeOutput {
        let (continuity, accumulate_frame) = self.started.start(state);
        self.rendering = Some(state.frame_id);
        NodeOutput::Render { state, accumulate_frame, continuity }
    }

    /// A message from the controller. On `Err`, close the connection with the error as the reason.
    pub fn handle(&mut self, now: Duration, msg: Message) -> Result<Vec<NodeOutput>, ProtocolError> {
        let kind = msg.kind();
        let err = |problem: String| Err(ProtocolError::new(PEER, kind, problem));
        if !self.hello_done {
            return match check_hello(&msg, Role::Controller) {
                Ok(_) => {
                    self.hello_done = true;
                    Ok(Vec::new())
                }
                Err(e) => err(e.to_string()),
            };
        }
        // Who sends what is `Message::sender`'s one list.
        if msg.sender() == Some(Role::Daemon) {
            return err("only a daemon sends this".into());
        }
        match msg {
            Message::Hello { .. } => err("a second Hello: the handshake is done".into()),
            Message::Bricks { from_frame, holders } => Ok(vec![NodeOutput::Bricks { from_frame, holders }]),
            Message::LoadBrick { brick } => Ok(vec![NodeOutput::LoadBrick { brick }]),
            Message::Split { from_frame, split } => Ok(vec![NodeOutput::Split { from_frame, split }]),
            Message::FrameState(state) => {
                if let Some(last) = self.last_frame_id {
                    if state.frame_id <= last {
                        return err(format!("frame {} does not follow frame {last}", state.frame_id));
                    }
                }
                if let Err(e) = FrameSpec::try_from(&state) {
                    return err(format!("frame {}: {e}", state.frame_id));
                }
                self.last_frame_id = Some(state.frame_id);
                if self.rendering.is_some() {
                    if self.queued.replace(state).is_some() {
                        self.counters.skipped += 1;
                    }
                    return Ok(Vec::new());
                }
                if self.rendered.take().is_some() {
                    self.counters.dropped += 1;
                }
                Ok(vec![self.start(state)])
            }
            Message::Swap { frame_id, present_at_us } => {
                if self.rendered != Some(frame_id) {
                    let what = match (self.rendering, self.rendered) {
                        (Some(r), _) if r == frame_id => "it is still rendering".to_string(),
                        (_, Some(w)) => format!("the frame rendered and waiting is {w}"),
                        _ => "no frame is rendered".to_string(),
                    };
                    return err(format!("Swap for frame {frame_id}, which is not rendered: {what}"));
                }
                let at = present_at_us.map(|t| Duration::from_micros(u64::try_from(t).unwrap_or(0)));
                if let Some(t) = at.filter(|&t| t > now + MAX_SWAP_WAIT) {
                    return err(format!(
                        "Swap for frame {frame_id} at {} us of this node's clock, {} ms ahead: more than {} ms",
                        micros(t),
                        t.saturating_sub(now).as_millis(),
                        MAX_SWAP_WAIT.as_millis()
                    ));
                }
                self.rendered = None;
                self.presenting.push_back((frame_id, at));
                Ok(vec![NodeOutput::Present { frame_id, at }])
            }
            // `sent_us` is the arrival too: the caller stamps it again as the Pong leaves.
            Message::Ping { id, t0_us } => Ok(vec![NodeOutput::Send(Message::Pong {
                id,
                t0_us,
                t1_us: micros(now),
                sent_us: micros(now),
                resident_bytes: self.resident_bytes,
            })]),
            Message::SnapshotRequest => Ok(vec![NodeOutput::SnapshotWanted]),
            Message::ThumbnailRequest { divisor } => {
                if !(1..=MAX_THUMBNAIL_DIVISOR).contains(&divisor) {
                    return err(format!("thumbnail divisor {divisor} is not in 1..={MAX_THUMBNAIL_DIVISOR}"));
                }
                Ok(vec![NodeOutput::ThumbnailWanted { divisor }])
            }
            Message::Restart { reason } => {
                let n = reason.chars().count();
                if n > MAX_RESTART_REASON_CHARS {
                    return err(format!(
                        "a Restart reason of {n} characters, more than {MAX_RESTART_REASON_CHARS}"
                    ));
                }
                self.reset();
                Ok(vec![NodeOutput::Restart { reason: crate::messages::printable(&reason) }])
            }
            Message::Identify { on } => Ok(vec![NodeOutput::Identify { on }]),
            Message::Bye { reason } => {
                self.reset();
                Ok(vec![NodeOutput::Closed { reason }])
            }
            // What only a daemon sends, refused above.
            _ => err("only a daemon sends this".into()),
        }
    }

    /// The renderer finished `frame_id` in `render_time`: sends Ready, and starts the queued frame
    /// if one came meanwhile (then the finished one is superseded: the controller has moved on).
    /// A completion for a frame that is not rendering (after a reset) is ignored.
    pub fn render_done(&mut self, now: Duration, frame_id: u64, render_time: Duration) -> Vec<NodeOutput> {
        let _ = now;
        if self.rendering != Some(frame_id) {
            return Vec::new();
        }
        self.rendering = None;
        self.counters.rendered += 1;
        let render_us = u64::try_from(render_time.as_micros()).unwrap_or(u64::MAX);
        let mut out = vec![NodeOutput::Send(Message::Ready { frame_id, render_us })];
        match self.queued.take() {
            Some(next) => {
                self.counters.dropped += 1;
                out.push(self.start(next));
            }
            None => self.rendered = Some(frame_id),
        }
        out
    }

    /// `frame_id` was shown at `now` (the daemon's clock, e.g. the vsync it went out on); the
    /// presenting thread was ready to wait for its present time at `waiting_from`: sends
    /// Presented, and `LateSwap` first when that was after the present time. Ignored for a frame
    /// it was not told to present.
    pub fn presented(&mut self, now: Duration, frame_id: u64, waiting_from: Duration) -> Vec<NodeOutput> {
        let Some(pos) = self.presenting.iter().position(|&(f, _)| f == frame_id) else {
            return Vec::new();
        };
        let (_, at) = self.presenting[pos];
        self.presenting.drain(..=pos);
        self.last_presented = Some(frame_id);
        self.counters.presented += 1;
        let mut out = Vec::new();
        if let Some(at) = at.filter(|&at| waiting_from > at) {
            self.counters.late_swaps += 1;
            out.push(NodeOutput::LateSwap { frame_id, late_by: waiting_from - at });
        }
        out.push(NodeOutput::Send(Message::Presented {
            frame_id,
            node_time_us: micros(now),
            waiting_from_us: micros(waiting_from),
        }));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::codec::hello;
    use crate::render_state::RenderSettings;
    use glam::DVec3;

    fn ms(x: u64) -> Duration {
        Duration::from_millis(x)
    }

    fn state(id: u64, eye_y: f64) -> FrameState {
        let cam =
            Camera { eye: DVec3::new(0.0, eye_y, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 30.0 };
        FrameState::new(id, &cam, &RenderSettings::new(0.5), 1)
    }

    fn machine() -> NodeMachine {
        let mut m = NodeMachine::new("n1", vec!["left".into()]);
        assert!(m.handle(ms(0), hello("controller", Role::Controller)).unwrap().is_empty());
        m
    }

    fn render(out: &[NodeOutput]) -> Option<(u64, u32)> {
        out.iter().find_map(|o| match o {
            NodeOutput::Render { state, accumulate_frame, .. } => Some((state.frame_id, *accumulate_frame)),
            _ => None,
        })
    }

    #[test]
    fn a_frame_renders_waits_presents_and_accumulates_while_unchanged() {
        let mut m = machine();
        assert_eq!(m.hello(), hello("n1", Role::Daemon));
        let mut acc = Vec::new();
        for (id, eye) in [(1, -5.0), (2, -5.0), (3, -5.0), (4, -6.0), (5, -6.0)] {
            let out = m.handle(ms(id * 20), Message::FrameState(state(id, eye))).unwrap();
            let (fid, a) = render(&out).unwrap();
            assert_eq!(fid, id);
            acc.push(a);
            let out = m.render_done(ms(id * 20 + 5), id, ms(5));
            assert_eq!(out, vec![NodeOutput::Send(Message::Ready { frame_id: id, render_us: 5000 })]);
            assert_eq!(m.waiting_for_swap(), Some(id));
            let out = m.handle(ms(id * 20 + 6), Message::Swap { frame_id: id, present_at_us: None }).unwrap();
            assert_eq!(out, vec![NodeOutput::Present { frame_id: id, at: None }]);
            let out = m.presented(ms(id * 20 + 7), id, ms(id * 20 + 6));
            assert_eq!(
                out,
                vec![NodeOutput::Send(Message::Presented {
                    frame_id: id,
                    node_time_us: (id as i64 * 20 + 7) * 1000,
                    waiting_from_us: (id as i64 * 20 + 6) * 1000,
                })]
            );
        }
        assert_eq!(acc, vec![0, 1, 2, 0, 1]);
        assert_eq!(m.last_presented(), Some(5));
    }

    #[test]
    fn a_timed_swap_presents_at_its_time_and_one_come_after_it_is_late() {
        let mut m = machine();
        for (id, swap_at, present_at, waiting_from, late) in
            [(1u64, 25u64, 30u64, 26u64, false), (2, 51, 50, 52, true)]
        {
            m.handle(ms(id * 20), Message::FrameState(state(id, -5.0))).unwrap();
            m.render_done(ms(id * 20 + 2), id, ms(2));
            let t = Some(present_at as i64 * 1000);
            let out = m.handle(ms(swap_at), Message::Swap { frame_id: id, present_at_us: t }).unwrap();
            assert_eq!(out, vec![NodeOutput::Present { frame_id: id, at: Some(ms(present_at)) }]);
            let shown = ms(present_at.max(waiting_from));
            let out = m.presented(shown, id, ms(waiting_from));
            let sent = NodeOutput::Send(Message::Presented {
                frame_id: id,
                node_time_us: micros(shown),
                waiting_from_us: micros(ms(waiting_from)),
            });
            if late {
                let late_by = ms(waiting_from - present_at);
                assert_eq!(out, vec![NodeOutput::LateSwap { frame_id: id, late_by }, sent]);
            } else {
                assert_eq!(out, vec![sent]);
            }
        }
        assert_eq!(m.counters().late_swaps, 1);
        // A present time more than a second ahead is refused: the node never waits that long.
        m.handle(ms(100), Message::FrameState(state(3, -5.0))).unwrap();
        m.render_done(ms(101), 3, ms(1));
        let far = Some(micros(ms(102) + MAX_SWAP_WAIT) + 1);
        let e = m.handle(ms(102), Message::Swap { frame_id: 3, present_at_us: far }).unwrap_err();
        assert!(e.problem.contains("ms ahead: more than 1000 ms"), "{e}");
        // One in the past (or before the clock's zero) is presented at once.
        let out = m.handle(ms(102), Message::Swap { frame_id: 3, present_at_us: Some(-5) }).unwrap();
        assert_eq!(out, vec![NodeOutput::Present { frame_id: 3, at: Some(Duration::ZERO) }]);
    }

    #[test]
    fn frame_states_during_a_render_queue_the_latest() {
        let mut m = machine();
        m.handle(ms(0), Message::FrameState(state(1, -5.0))).unwrap();
        assert!(m.handle(ms(1), Message::FrameState(state(2, -5.0))).unwrap().is_empty());
        assert!(m.handle(ms(2), Message::FrameState(state(3, -5.0))).unwrap().is_empty());
        let out = m.render_done(ms(3), 1, ms(3));
        assert_eq!(out[0], NodeOutput::Send(Message::Ready { frame_id: 1, render_us: 3000 }));
        assert_eq!(render(&out), Some((3, 1)));
        assert_eq!(m.waiting_for_swap(), None, "frame 1 is superseded");
        assert_eq!(m.counters().skipped, 1);
        // A straggler: rendered 3, no Swap came, frame 4 arrives: 3 is dropped, 4 renders.
        m.render_done(ms(4), 3, ms(1));
        assert_eq!(m.waiting_for_swap(), Some(3));
        let out = m.handle(ms(5), Message::FrameState(state(4, -5.0))).unwrap();
        assert_eq!(render(&out), Some((4, 2)));
        assert_eq!(m.counters().dropped, 2);
        // Completions of frames not rendering are ignored.
        assert!(m.render_done(ms(6), 3, ms(1)).is_empty());
        assert!(m.presented(ms(6), 3, ms(6)).is_empty());
    }

    #[test]
    fn ping_is_answered_with_the_local_clock_and_the_resident_memory() {
        let mut m = machine();
        let out = m.handle(ms(1234), Message::Ping { id: 9, t0_us: -7 }).unwrap();
        assert_eq!(
            out,
            vec![NodeOutput::Send(Message::Pong {
                id: 9,
                t0_us: -7,
                t1_us: 1_234_000,
                sent_us: 1_234_000,
                resident_bytes: 0
            })]
        );
        m.set_resident_bytes(300 << 20);
        let out = m.handle(ms(2000), Message::Ping { id: 10, t0_us: 5 }).unwrap();
        assert_eq!(
            out,
            vec![NodeOutput::Send(Message::Pong {
                id: 10,
                t0_us: 5,
                t1_us: 2_000_000,
                sent_us: 2_000_000,
                resident_bytes: 300 << 20
            })]
        );
        assert_eq!(m.handle(ms(0), Message::SnapshotRequest).unwrap(), vec![NodeOutput::SnapshotWanted]);
        assert_eq!(
            m.handle(ms(0), Message::ThumbnailRequest { divisor: 4 }).unwrap(),
            vec![NodeOutput::ThumbnailWanted { divisor: 4 }]
        );
        for divisor in [0, MAX_THUMBNAIL_DIVISOR + 1] {
            let e = m.handle(ms(0), Message::ThumbnailRequest { divisor }).unwrap_err();
            assert!(e.problem.contains(&format!("divisor {divisor} is not in")), "{e}");
        }
    }

    #[test]
    fn violations_are_protocol_errors_naming_the_message() {
        // Before Hello.
        let mut m = NodeMachine::new("n1", vec![]);
        let e = m.handle(ms(0), Message::Swap { frame_id: 1, present_at_us: None }).unwrap_err();
        assert_eq!((e.peer.as_str(), e.message), ("controller", "Swap"));
        assert!(e.problem.contains("must be Hello"), "{e}");
        let e = m
            .handle(
                ms(0),
                Message::Hello { version: PROTOCOL_VERSION + 1, name: "c".into(), role: Role::Controller },
            )
            .unwrap_err();
        assert!(e.problem.contains("version"), "{e}");
        let e = m.handle(ms(0), hello("c", Role::Daemon)).unwrap_err();
        assert!(e.problem.contains("expected a controller"), "{e}");

        let mut m = machine();
        let e = m.handle(ms(0), Message::Swap { frame_id: 1, present_at_us: None }).unwrap_err();
        assert!(e.problem.contains("Swap for frame 1, which is not rendered: no frame is rendered"), "{e}");
        m.handle(ms(0), Message::FrameState(state(5, -5.0))).unwrap();
        let e = m.handle(ms(0), Message::Swap { frame_id: 5, present_at_us: None }).unwrap_err();
        assert!(e.problem.contains("still rendering"), "{e}");
        let e = m.handle(ms(0), Message::FrameState(state(5, -5.0))).unwrap_err();
        assert!(e.problem.contains("does not follow frame 5"), "{e}");
        let mut bad = state(6, -5.0);
        bad.camera.fov_y_deg = 200.0;
        let e = m.handle(ms(0), Message::FrameState(bad)).unwrap_err();
        assert!(e.problem.contains("camera.fov_y_deg"), "{e}");
        for msg in [Message::Ready { frame_id: 5, render_us: 0 }, Message::Snapshot { tiles: vec![] }] {
            let e = m.handle(ms(0), msg).unwrap_err();
            assert!(e.problem.contains("only a daemon"), "{e}");
        }
        let e = m.handle(ms(0), hello("controller", Role::Controller)).unwrap_err();
        assert!(e.problem.contains("second Hello"), "{e}");
        let out = m.handle(ms(0), Message::Bye { reason: "done".into() }).unwrap();
        assert_eq!(out, vec![NodeOutput::Closed { reason: "done".into() }]);
        assert_eq!(m.rendering(), None);
    }

    #[test]
    fn a_restart_is_carried_out_only_after_the_handshake_with_a_bounded_reason() {
        let restart = |r: &str| Message::Restart { reason: r.into() };
        // Before Hello (a peer that was refused the seat never gets here either).
        let mut m = NodeMachine::new("n1", vec![]);
        let e = m.handle(ms(0), restart("x")).unwrap_err();
        assert!(e.problem.contains("must be Hello"), "{e}");
        let mut m = machine();
        m.handle(ms(0), Message::FrameState(state(1, -5.0))).unwrap();
        let out = m.handle(ms(1), restart("operator\nasked")).unwrap();
        assert_eq!(out, vec![NodeOutput::Restart { reason: "operator\\nasked".into() }]);
        assert_eq!(m.rendering(), None, "the frames in flight are forgotten");
        let mut m = machine();
        let long = "r".repeat(MAX_RESTART_REASON_CHARS + 1);
        let e = m.handle(ms(0), restart(&long)).unwrap_err();
        assert!(e.problem.contains("257 characters, more than 256"), "{e}");
        assert_eq!(
            machine().handle(ms(0), Message::Identify { on: true }).unwrap(),
            vec![NodeOutput::Identify { on: true }]
        );
        // A daemon's message on the controller's side is refused.
        let e = machine().handle(ms(0), Message::NodeInfo(Default::default())).unwrap_err();
        assert!(e.problem.contains("only a daemon"), "{e}");
    }
}
