//! Object space on a simulated network: four nodes of a 2x2 wall, each a `NodeMachine` beside an
//! `ObjectMachine` as `isowalld run` pairs them, joined by links with latency, jitter and loss on a
//! virtual clock with a seeded PRNG; every pixel message goes through the codec. The controller is
//! scripted: a frame state every `period` at most (as `isowall orbit --fps`), the next once the
//! frame is released (every node up composited it, or the barrier's deadline passed), the model's
//! `BrickAssigner` when a node dies. A render takes a fixed time and gives, over each view's
//! rectangle, depth `brick + 1` everywhere (a brick covers its whole covered rectangle), so every
//! composited tile can be checked pixel by pixel against the bricks the frame should hold.
//!
//! The scenarios of DESIGN.md "Faults" in object space: a healthy wall, a silent peer, lossy
//! links, a slow peer, and a dead node whose brick a survivor adopts.

mod support;

use std::collections::{BTreeMap, BTreeSet, BinaryHeap};
use std::path::Path;
use std::time::Duration;
use support::{Rng, Scheduled};

use glam::DVec3;
use isowall_model::adoption::{AdoptionOutput, BrickAssigner};
use isowall_model::bricks;
use isowall_model::codec;
use isowall_model::composite::{Composited, Layer, PeerPixels, PixelForm, TileCanvas};
use isowall_model::config::WallConfig;
use isowall_model::messages::{Message, Role};
use isowall_model::node_machine::{NodeMachine, NodeOutput};
use isowall_model::object_machine::{BrickGeometry, FrameViews, ObjectMachine, ObjectOutput};
use isowall_model::wire::FrameState;
use isowall_model::{Camera, RenderSettings};

fn ms(x: u64) -> Duration {
    Duration::from_millis(x)
}

const DEADLINE_MS: u64 = 200;
/// The compositing deadline: nine tenths of the barrier's.
const COMPOSITE_DEADLINE: Duration = Duration::from_millis(180);

/// A 2x2 wall of 32x24 tiles, node i showing tile i, in object space.
fn config() -> WallConfig {
    let mut s = format!(
        "[wall]\nname = \"sim\"\nmode = \"object\"\ndeadline_ms = {DEADLINE_MS}\n\n\
         [camera]\neye = [60.0, -70.0, 45.0]\ntarget = [23.5, 23.5, 23.5]\nup = [0, 0, 1]\nfov_y = 40.0\n\n\
         [volume]\nsource = \"procedural:torus:48\"\n"
    );
    for i in 0..4u32 {
        s += &format!(
            "\n[[tiles]]\nname = \"t{i}\"\nx = {}\ny = {}\nwidth = 32\nheight = 24\n\n\
             [[nodes]]\nname = \"node{i}\"\naddress = \"127.0.0.1:{}\"\ntiles = [\"t{i}\"]\n",
            (i % 2) * 32,
            (i / 2) * 24,
            7401 + i
        );
    }
    WallConfig::parse(&s, Path::new("sim.toml")).expect("a valid wall")
}

/// The volume box [0, 47]^3 in four bricks, by x and y halves.
fn owned() -> Vec<(DVec3, DVec3)> {
    (0..4)
        .map(|i| {
            let (x, y) = ((i % 2) as f64 * 23.5, (i / 2) as f64 * 23.5);
            (DVec3::new(x, y, 0.0), DVec3::new(x + 23.5, y + 23.5, 47.0))
        })
        .collect()
}

/// Links are QUIC streams: a lost packet is sent again (`loss`: the chance a message needs that,
/// `retransmit` the time it adds); `drop`: the chance a message never arrives (its stream reset,
/// its connection lost).
#[derive(Clone, Copy, Debug)]
struct Link {
    latency: Duration,
    jitter: Duration,
    loss: f64,
    retransmit: Duration,
    drop: f64,
}

#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
enum Ev {
    Begin {
        frame: u64,
    },
    FrameState {
        node: usize,
        state: FrameState,
    },
    RenderDone {
        node: usize,
        frame: u64,
        views: FrameViews,
    },
    Pixels {
        to: usize,
        from: usize,
        bytes: Vec<u8>,
    },
    Timeout {
        node: usize,
    },
    Map {
        node: usize,
        from_frame: u64,
        holders: Vec<Option<String>>,
    },
    LoadBrick {
        node: usize,
        brick: u64,
    },
    LoadDone {
        node: usize,
        brick: u64,
    },
    Kill {
        node: usize,
    },
    Detect {
        node: usize,
    },
    /// The swap barrier's deadline for a frame.
    BarrierDeadline {
        frame: u64,
    },
}

struct Node {
    name: String,
    frame: NodeMachine,
    object: ObjectMachine,
    alive: bool,
    render: Duration,
    /// Never sends pixels (it renders and is ready for the controller).
    silent: bool,
    timeout_at: Option<Duration>,
}

/// One composited frame on one node.
#[derive(Debug, Clone)]
struct Record {
    /// From the frame's begin at the controller.
    after: Duration,
    /// From the node's start of the frame (its views), and from its own render done (the
    /// compositing time it reports).
    since_start: Duration,
    composite: Duration,
    missing: Vec<String>,
    done: Composited,
}

struct Sim {
    now: Duration,
    events: BinaryHeap<Scheduled<Ev>>,
    seq: u64,
    rng: Rng,
    config: WallConfig,
    camera: Camera,
    nodes: Vec<Node>,
    link: Link,
    period: Duration,
    frames: u64,
    begins: BTreeMap<u64, Duration>,
    released: BTreeSet<u64>,
    /// Nodes the controller knows are down.
    down: BTreeSet<usize>,
    /// (node, frame) -> when the node started it.
    started: BTreeMap<(usize, u64), Duration>,
    /// (node, frame) -> its composited frame.
    records: BTreeMap<(usize, u64), Record>,
    /// Connections closed: (node, peer, reason).
    closed: Vec<(usize, String, String)>,
    /// Peers to send to on a new connection: (node, peer).
    reconnected: Vec<(usize, String)>,
    assigner: BrickAssigner,
    /// (time, what) of the adoption.
    adoption: Vec<(Duration, AdoptionOutput)>,
    load_time: Duration,
    sent: u64,
    /// Messages sent again, messages that never arrived.
    lost: u64,
    dropped: u64,
}

impl Sim {
    fn new(frames: u64, period: Duration, link: Link, seed: u64) -> Sim {
        let config = config();
        let camera = config.camera_for(DVec3::ZERO, DVec3::splat(47.0));
        let names: Vec<String> = config.nodes.iter().map(|n| n.name.clone()).collect();
        let nodes = names
            .iter()
            .enumerate()
            .map(|(i, name)| {
                let geometry = BrickGeometry {
                    owned: owned(),
                    own: i,
                    own_bytes: 1000,
                    spacing: DVec3::ONE,
                    halo: [3; 3],
                };
                let mut frame = NodeMachine::new(name.clone(), vec![format!("t{i}")]);
                frame.handle(Duration::ZERO, codec::hello("controller", Role::Controller)).unwrap();
                Node {
                    name: name.clone(),
                    frame,
                    object: ObjectMachine::new(&config, name, geometry, None),
                    alive: true,
                    render: ms(10),
                    silent: false,
                    timeout_at: None,
                }
            })
            .collect();
        let mut sim = Sim {
            now: Duration::ZERO,
            events: BinaryHeap::new(),
            seq: 0,
            rng: Rng(seed),
            camera,
            nodes,
            link,
            period,
            frames,
            begins: BTreeMap::new(),
            started: BTreeMap::new(),
            released: BTreeSet::new(),
            down: BTreeSet::new(),
            records: BTreeMap::new(),
            closed: Vec::new(),
            reconnected: Vec::new(),
            assigner: BrickAssigner::new(names),
            adoption: Vec::new(),
            load_time: ms(300),
            sent: 0,
            lost: 0,
            dropped: 0,
            config,
        };
        sim.at(ms(100), Ev::Begin { frame: 1 });
        sim
    }

    fn at(&mut self, at: Duration, ev: Ev) {
        self.seq += 1;
        self.events.push(Scheduled { at, seq: self.seq, ev });
    }

    fn after(&mut self, d: Duration, ev: Ev) {
        self.at(self.now + d, ev);
    }

    fn delay(&mut self) -> Duration {
        self.link.latency + self.link.jitter.mul_f64(self.rng.unit())
    }

    fn run(&mut self) {
        while let Some(s) = self.events.pop() {
            self.now = s.at;
            self.step(s.ev);
        }
    }

    fn step(&mut self, ev: Ev) {
        match ev {
            Ev::Begin { frame } => {
                self.begins.insert(frame, self.now);
                if self.assigner.take_changed() {
                    let map = self.assigner.map(frame);
                    let alive: Vec<usize> = (0..self.nodes.len()).filter(|&n| self.nodes[n].alive).collect();
                    for n in alive {
                        let ev =
                            Ev::Map { node: n, from_frame: map.from_frame, holders: map.holders.clone() };
                        self.after(self.link.latency, ev);
                    }
                }
                let settings = RenderSettings::new(0.0);
                let state = FrameState::new(frame, &self.camera, &settings, 1);
                for n in 0..self.nodes.len() {
                    let d = self.link.latency;
                    self.after(d, Ev::FrameState { node: n, state });
                }
                self.after(ms(DEADLINE_MS), Ev::BarrierDeadline { frame });
            }
            Ev::BarrierDeadline { frame } => self.release(frame),
            Ev::Kill { node } => self.nodes[node].alive = false,
            Ev::Detect { node } => {
                self.down.insert(node);
                let name = self.nodes[node].name.clone();
                let out = self.assigner.node_down(self.now, &name);
                self.adoption(out);
            }
            ev => {
                let node = match &ev {
                    Ev::FrameState { node, .. }
                    | Ev::RenderDone { node, .. }
                    | Ev::Timeout { node }
                    | Ev::Map { node, .. }
                    | Ev::LoadBrick { node, .. }
                    | Ev::LoadDone { node, .. } => *node,
                    Ev::Pixels { to, .. } => *to,
                    _ => unreachable!(),
                };
                if !self.nodes[node].alive {
                    return;
                }
                self.node_event(node, ev);
                // The node's next compositing deadline.
                let next = self.nodes[node].object.poll_timeout();
                if let Some(at) = next.filter(|_| next != self.nodes[node].timeout_at) {
                    self.nodes[node].timeout_at = next;
                    self.at(at.max(self.now), Ev::Timeout { node });
                }
            }
        }
    }

    /// The swap of `frame` is released: the next frame begins, `period` after this one at the
    /// earliest.
    fn release(&mut self, frame: u64) {
        if !self.released.insert(frame) || frame >= self.frames {
            return;
        }
        let at = self.now.max(self.begins[&frame] + self.period);
        self.at(at, Ev::Begin { frame: frame + 1 });
    }

    fn adoption(&mut self, out: Vec<AdoptionOutput>) {
        for o in out {
            if let AdoptionOutput::Load { node, brick } = &o {
                let n = self.nodes.iter().position(|x| &x.name == node).unwrap();
                self.after(self.link.latency, Ev::LoadBrick { node: n, brick: *brick as u64 });
            }
            self.adoption.push((self.now, o));
        }
    }

    fn node_event(&mut self, n: usize, ev: Ev) {
        let now = self.now;
        match ev {
            Ev::FrameState { state, .. } => {
                self.nodes[n].object.announce(state.frame_id);
                let out = self.nodes[n].frame.handle(now, Message::FrameState(state)).unwrap();
                self.frame_outputs(n, out);
            }
            Ev::RenderDone { frame, views, .. } => {
                let rendered = views
                    .views
                    .iter()
                    .zip(&views.bricks)
                    .map(|((tile, v), &b)| {
                        let px = (v.rect.width * v.rect.height) as usize;
                        TileCanvas {
                            name: tile.clone(),
                            width: v.rect.width,
                            height: v.rect.height,
                            form: PixelForm::Colour,
                            depth: vec![b as f32 + 1.0; px],
                            rgb8: vec![b as u8 * 40; px * 3],
                            shading: Vec::new(),
                        }
                    })
                    .collect();
                let render = self.nodes[n].render;
                let out = self.nodes[n].object.local_done(now, frame, render, rendered);
                self.object_outputs(n, out);
            }
            Ev::Pixels { from, bytes, .. } => {
                let pixels = codec::decode_pixels(&bytes).expect("the codec's own bytes");
                let cert = self.nodes[from].name.clone();
                let out = self.nodes[n].object.peer(now, &cert, from as u64, pixels);
                self.object_outputs(n, out);
            }
            Ev::Timeout { .. } => {
                self.nodes[n].timeout_at = None;
                let out = self.nodes[n].object.handle_timeout(now);
                self.object_outputs(n, out);
            }
            Ev::Map { from_frame, holders, .. } => {
                let (_, out) = self.nodes[n].object.set_map(now, from_frame, holders).expect("a valid map");
                self.object_outputs(n, out);
            }
            Ev::LoadBrick { brick, .. } => {
                let out = self.nodes[n].object.load(brick);
                self.object_outputs(n, out);
            }
            Ev::LoadDone { brick, .. } => {
                let msg = self.nodes[n].object.load_done(brick, Ok(1000), self.load_time);
                let Message::BrickLoaded { brick, load_us, .. } = msg else { panic!("{msg:?}") };
                let name = self.nodes[n].name.clone();
                let out = self.assigner.loaded(now, &name, brick as usize, Duration::from_micros(load_us));
                self.adoption(out);
            }
            _ => unreachable!(),
        }
    }

    fn frame_outputs(&mut self, n: usize, out: Vec<NodeOutput>) {
        for o in out {
            if let NodeOutput::Render { state, .. } = o {
                self.started.insert((n, state.frame_id), self.now);
                let (views, out) = self.nodes[n].object.views(self.now, state.frame_id, self.camera, [0; 3]);
                let render = self.nodes[n].render;
                self.after(render, Ev::RenderDone { node: n, frame: state.frame_id, views });
                self.object_outputs(n, out);
            }
        }
    }

    fn object_outputs(&mut self, n: usize, out: Vec<ObjectOutput>) {
        for o in out {
            match o {
                ObjectOutput::SendPixels { peer, bytes, .. } => {
                    if self.nodes[n].silent {
                        continue;
                    }
                    self.sent += 1;
                    if self.rng.unit() < self.link.drop {
                        self.dropped += 1;
                        continue;
                    }
                    let mut d = self.delay();
                    if self.rng.unit() < self.link.loss {
                        self.lost += 1;
                        d += self.link.retransmit;
                    }
                    let to = self.nodes.iter().position(|x| x.name == peer).unwrap();
                    self.after(d, Ev::Pixels { to, from: n, bytes });
                }
                ObjectOutput::Composited(c) => {
                    let report = self.nodes[n].object.report(self.now, &c);
                    let Message::Composited { composite_us, missing, .. } = report else {
                        panic!("{report:?}")
                    };
                    assert_eq!(missing, c.missing);
                    let begin = self.begins[&c.frame_id];
                    let started = self.started[&(n, c.frame_id)];
                    let rec = Record {
                        after: self.now - begin,
                        since_start: self.now - started,
                        composite: Duration::from_micros(composite_us),
                        missing: c.missing.clone(),
                        done: c.clone(),
                    };
                    self.records.insert((n, c.frame_id), rec);
                    let all = (0..self.nodes.len())
                        .filter(|m| !self.down.contains(m))
                        .all(|m| self.records.contains_key(&(m, c.frame_id)));
                    if all {
                        self.release(c.frame_id);
                    }
                    let render = self.nodes[n].render;
                    let out = self.nodes[n].frame.render_done(self.now, c.frame_id, render);
                    self.frame_outputs(n, out);
                }
                ObjectOutput::ClosePeer { peer, reason, .. } | ObjectOutput::Dropped { peer, reason } => {
                    self.closed.push((n, peer, reason))
                }
                ObjectOutput::Reconnect { peer } => self.reconnected.push((n, peer)),
                ObjectOutput::Load { brick, .. } => {
                    let d = self.load_time;
                    self.after(d, Ev::LoadDone { node: n, brick });
                }
                ObjectOutput::Send(m) => panic!("unexpected {m:?}"),
            }
        }
    }

    /// Whether node n's composited tile of `frame` holds exactly the bricks `bricks`: per pixel the
    /// nearest (lowest-numbered) brick whose covered rectangle holds it.
    fn exact(&self, n: usize, frame: u64, bricks: &[usize]) -> bool {
        let Some(r) = self.records.get(&(n, frame)) else { return false };
        let tile = self.config.tile(&format!("t{n}")).unwrap();
        let view = self.config.tile_view(self.camera, &tile.name).unwrap();
        let canvas = &r.done.tiles[0];
        let owned = owned();
        (0..tile.height).all(|y| {
            (0..tile.width).all(|x| {
                let (wx, wy) = (tile.x + x, tile.y + y);
                let want = bricks
                    .iter()
                    .filter(|&&b| {
                        bricks::covered_rect(&view, owned[b].0, owned[b].1).is_some_and(|w| {
                            wx >= w.x && wx < w.x + w.width && wy >= w.y && wy < w.y + w.height
                        })
                    })
                    .map(|&b| b as f32 + 1.0)
                    .fold(f32::INFINITY, f32::min);
                canvas.depth[(y * tile.width + x) as usize] == want
            })
        })
    }

    fn frames_of(&self, n: usize) -> Vec<(u64, &Record)> {
        self.records.iter().filter(|((m, _), _)| *m == n).map(|((_, f), r)| (*f, r)).collect()
    }
}

fn lan() -> Link {
    Link { latency: ms(1), jitter: Duration::ZERO, loss: 0.0, retransmit: Duration::ZERO, drop: 0.0 }
}

const ALL: [usize; 4] = [0, 1, 2, 3];

#[test]
fn a_healthy_wall_composites_every_frame_exactly_without_waiting_for_a_deadline() {
    let mut sim = Sim::new(30, ms(50), lan(), 1);
    sim.run();
    assert!(sim.closed.is_empty(), "{:?}", sim.closed);
    for n in ALL {
        let frames = sim.frames_of(n);
        assert_eq!(frames.len(), 30, "node{n}");
        for (f, r) in frames {
            assert!(r.missing.is_empty(), "node{n} frame {f}: {:?}", r.missing);
            // Render (10 ms) plus a link each way: no deadline waited for.
            assert!(r.after <= ms(13), "node{n} frame {f} after {:?}", r.after);
            assert_eq!(r.composite, ms(1), "node{n} frame {f}: the peers' pixels are a link away");
            assert!(sim.exact(n, f, &ALL), "node{n} frame {f} is not the four bricks' image");
        }
    }
}

#[test]
fn a_silent_peer_costs_one_deadline_is_named_and_the_wall_goes_on() {
    let mut sim = Sim::new(30, ms(50), lan(), 2);
    sim.nodes[1].silent = true;
    sim.run();
    for n in [0, 2, 3] {
        let frames = sim.frames_of(n);
        assert_eq!(frames.len(), 30, "node{n} composited {} of 30 frames", frames.len());
        let waited: Vec<u64> = frames.iter().filter(|(_, r)| r.composite > ms(5)).map(|(f, _)| *f).collect();
        // The first frame waits for the deadline (then node1 is not waited for: it sent nothing).
        assert_eq!(waited, vec![1], "node{n}: frames that waited");
        let (_, first) = frames[0];
        assert_eq!(first.since_start, COMPOSITE_DEADLINE, "node{n}");
        for (f, r) in &frames {
            assert_eq!(r.missing, vec!["node1".to_string()], "node{n} frame {f}");
            assert!(sim.exact(n, *f, &[0, 2, 3]), "node{n} frame {f}: not the other three bricks");
        }
    }
    // node1 composites its own tile: it gets every other node's pixels.
    assert!(sim.frames_of(1).iter().all(|(_, r)| r.missing.is_empty()), "{:?}", sim.frames_of(1));
    assert!(sim.closed.is_empty(), "{:?}", sim.closed);
}

#[test]
fn lossy_links_lose_frames_by_the_deadline_and_never_stall() {
    let link = Link { latency: ms(1), jitter: ms(2), loss: 0.05, retransmit: ms(30), drop: 0.01 };
    let mut sim = Sim::new(200, ms(50), link, 3);
    sim.run();
    assert!(sim.lost > 0 && sim.dropped > 0, "no message was lost");
    let (mut complete, mut total, mut worst) = (0, 0, Duration::ZERO);
    for n in ALL {
        let frames = sim.frames_of(n);
        // A frame that waits for its deadline skips the frame states that come meanwhile.
        let floor = 200 - 4 * sim.dropped as usize;
        assert!(frames.len() >= floor, "node{n} composited {} of 200 frames", frames.len());
        for (f, r) in frames {
            total += 1;
            worst = worst.max(r.after);
            // Never past its deadline.
            assert!(r.since_start <= COMPOSITE_DEADLINE, "node{n} frame {f} after {:?}", r.since_start);
            if r.missing.is_empty() {
                complete += 1;
                assert!(sim.exact(n, f, &ALL), "node{n} frame {f} complete but not exact");
            }
        }
    }
    eprintln!(
        "lossy links: {} of {} pixel messages sent again (+30 ms), {} never arrived; {complete} of {total} \
         frames composited complete; slowest frame {:?} after its begin",
        sim.lost, sim.sent, sim.dropped, worst
    );
    // A message that never arrives costs its frame, and the next one when the peer, not waited
    // for, sends its pixels after that frame is done.
    assert!(
        total - complete <= 2 * sim.dropped as usize,
        "{complete} of {total} complete, {} dropped",
        sim.dropped
    );
}

#[test]
fn a_slow_peer_within_the_deadline_is_waited_for() {
    let mut sim = Sim::new(20, ms(200), lan(), 4);
    sim.nodes[3].render = ms(120);
    sim.run();
    for n in [0, 1, 2] {
        for (f, r) in sim.frames_of(n) {
            assert!(r.missing.is_empty(), "node{n} frame {f}: {:?}", r.missing);
            // node3's pixels come 110 ms after this node's own render (and a link).
            assert_eq!(r.composite, ms(111), "node{n} frame {f}");
            assert!(sim.exact(n, f, &ALL));
        }
    }
}

#[test]
fn a_dead_nodes_brick_is_adopted_and_frames_never_wait_for_the_dead() {
    let mut sim = Sim::new(40, ms(50), lan(), 5);
    // node2 dies just after frame 10 begins; the controller notices 3 deadlines later.
    let kill = ms(100) + ms(50) * 9 + ms(5);
    sim.at(kill, Ev::Kill { node: 2 });
    sim.at(kill + ms(3 * DEADLINE_MS), Ev::Detect { node: 2 });
    sim.run();
    let adopted = sim.adoption.iter().find_map(|(t, o)| match o {
        AdoptionOutput::Adopted { node, brick: 2, .. } => Some((*t, node.clone())),
        _ => None,
    });
    let (at, adopter) = adopted.expect("brick 2 adopted");
    let from = sim.begins.iter().find(|(_, &b)| b > at).map(|(f, _)| *f).expect("a frame after the adoption");
    let adopter = sim.nodes.iter().position(|n| n.name == adopter).unwrap();
    assert_ne!(adopter, 2);
    for n in [0, 1, 3] {
        let frames = sim.frames_of(n);
        assert_eq!(frames.len(), 40, "node{n}: every frame composited");
        for (f, r) in frames {
            if f < 10 {
                assert!(r.missing.is_empty() && sim.exact(n, f, &ALL), "node{n} frame {f} before the death");
            } else if f >= from {
                assert!(r.missing.is_empty(), "node{n} frame {f}: {:?}", r.missing);
                assert!(sim.exact(n, f, &ALL), "node{n} frame {f}: the adopted brick is not in its place");
            } else {
                // Without brick 2; a deadline at most once (then node2 is not waited for, and from
                // the map on it is not expected).
                assert!(sim.exact(n, f, &[0, 1, 3]), "node{n} frame {f} without brick 2");
                assert!(r.since_start <= COMPOSITE_DEADLINE, "node{n} frame {f} after {:?}", r.since_start);
            }
        }
        let waited: Vec<u64> =
            sim.frames_of(n).iter().filter(|(_, r)| r.composite > ms(5)).map(|(f, _)| *f).collect();
        assert!(waited.len() <= 1, "node{n} waited for a deadline in frames {waited:?}");
    }
    let named: BTreeSet<String> = sim.records.values().flat_map(|r| r.missing.clone()).collect();
    assert_eq!(named, BTreeSet::from(["node2".to_string()]));
    assert!(sim.closed.is_empty(), "{:?}", sim.closed);
    assert!(sim.reconnected.is_empty(), "nobody came back: {:?}", sim.reconnected);
}

/// A node that holds bricks again after a map without it is a new process (restarted): its
/// peers send to it on a new connection, since one to the process before may not have timed out
/// and would lose what is sent on it. Once, when it comes back; not for itself.
#[test]
fn a_node_back_from_the_dead_is_sent_to_on_a_new_connection() {
    let config = config();
    let geometry =
        |own| BrickGeometry { owned: owned(), own, own_bytes: 1000, spacing: DVec3::ONE, halo: [3; 3] };
    let map = |names: [&str; 4]| names.iter().map(|n| Some(n.to_string())).collect::<Vec<_>>();
    let reconnects = |out: &[ObjectOutput]| -> Vec<String> {
        out.iter()
            .filter_map(|o| match o {
                ObjectOutput::Reconnect { peer } => Some(peer.clone()),
                _ => None,
            })
            .collect()
    };
    let mut m = ObjectMachine::new(&config, "node0", geometry(0), None);
    // node1 dies: node3 renders its brick.
    let (_, out) = m.set_map(ms(0), 5, map(["node0", "node3", "node2", "node3"])).unwrap();
    assert!(reconnects(&out).is_empty(), "{out:?}");
    // node1 is back from frame 9.
    let (_, out) = m.set_map(ms(10), 9, map(["node0", "node1", "node2", "node3"])).unwrap();
    assert_eq!(reconnects(&out), ["node1"]);
    let (_, out) = m.set_map(ms(20), 12, map(["node0", "node1", "node2", "node3"])).unwrap();
    assert!(reconnects(&out).is_empty(), "the same nodes again: {out:?}");
    // The node that came back does not reconnect to itself, nor to peers that never left.
    let mut back = ObjectMachine::new(&config, "node1", geometry(1), None);
    let (_, out) = back.set_map(ms(10), 9, map(["node0", "node1", "node2", "node3"])).unwrap();
    assert!(reconnects(&out).is_empty(), "{out:?}");
}

/// A peer's second message for a frame is dropped with a reason naming the peer, its connection
/// left open (a second connection with the same certificate may carry it); pixels that came
/// early and break the rules once their frame starts close the connection that carried them,
/// not a newer one of the same certificate.
#[test]
fn a_duplicate_is_dropped_and_an_early_refusal_closes_the_link_that_carried_it() {
    let config = config();
    let geometry =
        BrickGeometry { owned: owned(), own: 0, own_bytes: 1000, spacing: DVec3::ONE, halo: [3; 3] };
    let mut m = ObjectMachine::new(&config, "node0", geometry, None);
    let camera = config.camera_for(DVec3::ZERO, DVec3::splat(47.0));
    let rect = |x| {
        let mut l = Layer::empty(x, 0, 2, 2, PixelForm::Colour);
        l.depth.fill(1.0);
        l.rgb8.fill(9);
        l.encode("t0", false)
    };
    let pixels = |frame_id, rects| PeerPixels { frame_id, node: "node1".into(), rects };
    let closes = |out: &[ObjectOutput]| out.iter().any(|o| matches!(o, ObjectOutput::ClosePeer { .. }));
    // Frame 1 from node1 on link 1, then again on link 2.
    let first = m.peer(ms(0), "node1", 1, pixels(1, vec![]));
    assert!(!closes(&first), "{first:?}");
    let again = m.peer(ms(1), "node1", 2, pixels(1, vec![]));
    assert!(
        matches!(&again[..], [ObjectOutput::Dropped { peer, reason }] if peer == "node1" && reason.contains("twice")),
        "{again:?}"
    );
    // Frame 2's pixels come early on link 2 with more rectangles than node1's one brick may
    // cover of tile t0; node1 then reconnects (link 3). When frame 2 starts, link 2 is closed.
    let early = m.peer(ms(2), "node1", 2, pixels(2, vec![rect(0), rect(2)]));
    assert!(early.is_empty(), "{early:?}");
    let newer = m.peer(ms(3), "node1", 3, pixels(3, vec![]));
    assert!(!closes(&newer), "{newer:?}");
    let (_, out) = m.views(ms(4), 2, camera, [0; 3]);
    assert!(
        matches!(&out[..], [ObjectOutput::ClosePeer { peer, link: 2, reason }] if peer == "node1" && reason.contains("rectangles")),
        "{out:?}"
    );
}

/// A node told to refuse adoptions (a time-varying volume's) answers a `LoadBrick` of another
/// brick with `BrickFailed` and the reason, loads nothing, and still answers for its own brick.
#[test]
fn a_node_that_refuses_adoptions_answers_brick_failed_and_loads_nothing() {
    let config = config();
    let geometry =
        || BrickGeometry { owned: owned(), own: 0, own_bytes: 1000, spacing: DVec3::ONE, halo: [3; 3] };
    let mut m = ObjectMachine::new(&config, "node0", geometry(), None);
    assert!(
        matches!(&m.load(1)[..], [ObjectOutput::Load { brick: 1, index: 1 }]),
        "without the refusal the brick is loaded"
    );
    let mut m = ObjectMachine::new(&config, "node0", geometry(), None);
    m.refuse_adoptions("steps: not adopted".into());
    let out = m.load(1);
    assert!(
        matches!(&out[..], [ObjectOutput::Send(Message::BrickFailed { brick: 1, reason })] if reason == "steps: not adopted"),
        "{out:?}"
    );
    let own = m.load(0);
    assert!(matches!(&own[..], [ObjectOutput::Send(Message::BrickLoaded { brick: 0, .. })]), "{own:?}");
}

/// A wall that filters its composited tiles: with a guard band of 8 pixels node3 handles its tile
/// t3 (32x24 at (32, 24) of the 64x48 image) as the canvas 40x32 at (24, 16), clipped by the
/// image's right and bottom edges. The views its brick renders cover the guard band; footprints,
/// the rectangles it sends and its own layers are placed in the canvas; the composited tile is the
/// canvas, in the shading form; the stream limit is the canvases' in that form.
#[test]
fn a_guard_band_grows_views_footprints_and_canvases_and_the_shading_form_travels() {
    const GUARD: u32 = 8;
    let config = config();
    // From further away and looking past the volume, so that it lies in t3's quarter of the
    // image and bricks' rectangles start inside t3's canvas rather than at its edges.
    let mut camera = config.camera_for(DVec3::ZERO, DVec3::splat(47.0));
    camera.eye = camera.target + 2.5 * (camera.eye - camera.target);
    let (b, d) = (camera.basis(), (camera.target - camera.eye).length());
    let shift = d * (-0.24 * b.right + 0.18 * b.up);
    (camera.eye, camera.target) = (camera.eye + shift, camera.target + shift);
    let geometry =
        |own| BrickGeometry { owned: owned(), own, own_bytes: 1000, spacing: DVec3::ONE, halo: [3; 3] };
    let rect = |x, y, width, height| isowall_model::Rect { x, y, width, height };
    let mut plain = ObjectMachine::new(&config, "node3", geometry(3), None);
    let mut m = ObjectMachine::new(&config, "node3", geometry(3), Some(GUARD));
    assert_eq!((plain.form(), m.form()), (PixelForm::Colour, PixelForm::Shading));
    assert_eq!(plain.canvas_rect("t3"), Some(rect(32, 24, 32, 24)));
    assert_eq!(m.canvas_rect("t3"), Some(rect(24, 16, 40, 32)));
    assert_eq!(m.canvas_rect("t0"), Some(rect(0, 0, 40, 32)));
    assert_eq!(m.canvas_rect("nope"), None);
    // The stream limit: 4 bricks x (the canvas's pixels in the form + one rectangle's framing).
    assert_eq!(plain.max_pixels_bytes(), 4 * (32 * 24 * 7 + 64 + 2) + 256);
    assert_eq!(m.max_pixels_bytes(), 4 * (40 * 32 * 68 + 64 + 2) + 256);

    // Views: brick 3's covered rectangle of every tile's canvas, each containing the plain one.
    let (views, out) = m.views(ms(0), 1, camera, [0; 3]);
    assert!(out.is_empty(), "{out:?}");
    let (plain_views, _) = plain.views(ms(0), 1, camera, [0; 3]);
    let (lo, hi) = owned()[3];
    let mut beyond = 0;
    for (tile, v) in &views.views {
        let canvas = m.canvas_rect(tile).unwrap();
        let canvas_view = isowall_model::View { rect: canvas, ..config.tile_view(camera, tile).unwrap() };
        assert_eq!(Some(v.rect), bricks::covered_rect(&canvas_view, lo, hi), "tile {tile}");
        let t = config.tile(tile).unwrap().rect();
        let inside = |r: isowall_model::Rect, o: isowall_model::Rect| {
            r.x >= o.x && r.y >= o.y && r.x + r.width <= o.x + o.width && r.y + r.height <= o.y + o.height
        };
        assert!(inside(v.rect, canvas), "tile {tile}: {:?} outside the canvas {canvas:?}", v.rect);
        if !inside(v.rect, t) {
            beyond += 1;
        }
        if let Some((_, p)) = plain_views.views.iter().find(|(n, _)| n == tile) {
            assert!(inside(p.rect, v.rect), "tile {tile}: the guarded view {:?} lacks {:?}", v.rect, p.rect);
        }
    }
    assert!(beyond > 0, "no view reaches into a guard band: {:?}", views.views);

    // Footprints are placed in the canvas: a peer's brick's covered rectangle of t3's canvas,
    // less the canvas's origin (24, 16), is accepted; the same placed from the tile's origin
    // (32, 24) is not.
    let t3_view =
        isowall_model::View { rect: rect(24, 16, 40, 32), ..config.tile_view(camera, "t3").unwrap() };
    let footprint = |b: usize| {
        let (lo, hi) = owned()[b];
        bricks::covered_rect(&t3_view, lo, hi).map(|w| (w.x - 24, w.y - 16, w.width, w.height))
    };
    let layer = |(x, y, w, h): (u32, u32, u32, u32), depth: f32, value: f32| {
        let mut l = Layer::empty(x, y, w, h, PixelForm::Shading);
        l.depth.fill(depth);
        l.shading.fill([[value; 4]; 4]);
        l
    };
    let (mut peers_fp, mut refused) = (Vec::new(), 0);
    for b in 0..3 {
        let peer = format!("node{b}");
        let rects: Vec<_> = footprint(b).map(|f| layer(f, 1.0 + b as f32, b as f32)).into_iter().collect();
        if let Some((x, y, w, h)) = footprint(b).filter(|f| f.0 >= GUARD && f.1 >= GUARD) {
            refused += 1;
            let from_tile = layer((x - GUARD, y - GUARD, w, h), 1.0, 0.0).encode("t3", true);
            let msg = PeerPixels { frame_id: 1, node: peer.clone(), rects: vec![from_tile] };
            let out = m.peer(ms(1), &peer, 1, msg);
            assert!(
                matches!(&out[..], [ObjectOutput::ClosePeer { reason, .. }] if reason.contains("outside what the frame gives it")),
                "{peer}: {out:?}"
            );
        }
        let msg = PeerPixels {
            frame_id: 1,
            node: peer.clone(),
            rects: rects.iter().map(|l| l.encode("t3", true)).collect(),
        };
        let out = m.peer(ms(1), &peer, 1, msg);
        assert!(out.is_empty(), "{peer}: {out:?}");
        peers_fp.extend(rects);
    }
    assert!(!peers_fp.is_empty() && refused > 0, "no peer's brick starts inside t3's canvas");

    // This node's render, in the shading form and nearest of all (depth 0.5), and what it sends.
    let rendered: Vec<TileCanvas> = views
        .views
        .iter()
        .map(|(tile, v)| {
            let mut c = TileCanvas::new(tile, v.rect.width, v.rect.height, PixelForm::Shading);
            c.depth.fill(0.5);
            c.shading.fill([[7.0; 4]; 4]);
            c
        })
        .collect();
    let out = m.local_done(ms(2), 1, ms(1), rendered);
    let mut composited = None;
    let mut sent = 0;
    for o in out {
        match o {
            ObjectOutput::SendPixels { peer, bytes, .. } => {
                let pixels = codec::decode_pixels(&bytes).unwrap();
                for r in &pixels.rects {
                    // Each rectangle is its view less the canvas's origin, in the shading form.
                    let canvas = m.canvas_rect(&r.tile).unwrap();
                    let (_, v) = views.views.iter().find(|(n, _)| *n == r.tile).unwrap();
                    assert_eq!((r.x, r.y), (v.rect.x - canvas.x, v.rect.y - canvas.y), "{peer} {}", r.tile);
                    let l = r.decode("node3", (canvas.width, canvas.height), PixelForm::Shading).unwrap();
                    assert!(l.shading.iter().all(|p| *p == [[7.0; 4]; 4]));
                    sent += 1;
                }
            }
            ObjectOutput::Composited(c) => composited = Some(c),
            o => panic!("{o:?}"),
        }
    }
    assert_eq!(sent, views.views.iter().filter(|(t, _)| t != "t3").count());
    let done = composited.expect("every peer's pixels are in");
    assert!(done.missing.is_empty(), "{:?}", done.missing);
    let [t] = &done.tiles[..] else { panic!("{:?}", done.tiles.len()) };
    assert_eq!((t.name.as_str(), t.width, t.height, t.form), ("t3", 40, 32, PixelForm::Shading));
    // Pixel by pixel: this node's view of t3 (placed from the canvas's origin) is nearest; the
    // peers' footprints elsewhere; no hit (+inf, zeros) where nothing covers.
    let own = views.views.iter().find(|(n, _)| n == "t3").map(|(_, v)| v.rect);
    let covers =
        |r: (u32, u32, u32, u32), x: u32, y: u32| x >= r.0 && y >= r.1 && x < r.0 + r.2 && y < r.1 + r.3;
    for y in 0..32 {
        for x in 0..40 {
            let k = (y * 40 + x) as usize;
            let nearest_peer = peers_fp
                .iter()
                .filter(|l| covers((l.x, l.y, l.width, l.height), x, y))
                .map(|l| (l.depth[0], l.shading[0]))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            let want = match own.filter(|o| covers((o.x - 24, o.y - 16, o.width, o.height), x, y)) {
                Some(_) => Some((0.5, [[7.0; 4]; 4])),
                None => nearest_peer,
            };
            let (depth, shading) = want.unwrap_or((f32::INFINITY, [[0.0; 4]; 4]));
            assert_eq!((t.depth[k], t.shading[k]), (depth, shading), "canvas pixel ({x}, {y})");
        }
    }
}

/// A frame's plan in object space: the views of `views`, always at scale 1 whatever the frame's
/// (the tiles are composited by full-resolution depth), `seed` AO rendered as `ours` and a radius
/// past the halo bounded by it (warned once), the pixels shared in the wall's form, and the
/// background of misses in 8-bit sRGB.
#[test]
fn object_space_plans_its_bricks_at_scale_one_within_the_halo_and_shares_them() {
    use isowall_model::render_plan::RenderPlan;
    use isowall_model::wire::{Continuity, FrameSpec};
    use isowall_model::{AoMethod, AoRadius};
    let config = config();
    let camera = config.camera_for(DVec3::ZERO, DVec3::splat(47.0));
    let geometry =
        BrickGeometry { owned: owned(), own: 0, own_bytes: 1000, spacing: DVec3::ONE, halo: [3; 3] };
    let mut m = ObjectMachine::new(&config, "node0", geometry.clone(), None);
    let mut settings = RenderSettings::new(0.5);
    settings.ao.method = AoMethod::Seed;
    settings.ao.radius = AoRadius::World(40.0);
    let spec = FrameSpec { frame_id: 1, camera, settings, scale: 3, time_step: 2 };
    let p = m.plan(ms(0), &spec, 5, Continuity::ViewMoved);
    let mut same = ObjectMachine::new(&config, "node0", geometry, None);
    let (views, _) = same.views(ms(0), 1, camera, [0; 3]);
    assert_eq!((p.plan.views.clone(), p.plan.bricks.clone()), (views.views, views.bricks));
    assert!(!p.plan.views.is_empty());
    assert_eq!((p.plan.scale, p.plan.time_step, p.plan.accumulate_frame), (1, 2, 5));
    assert_eq!(p.plan.continuity, Continuity::ViewMoved);
    assert_eq!(p.plan.share, Some(m.form()));
    assert_eq!(p.plan.settings.ao.method, AoMethod::Ours);
    let AoRadius::World(r) = p.plan.settings.ao.radius else { panic!("{:?}", p.plan.settings.ao.radius) };
    assert!(r < 3.0, "the radius {r} is bounded by the 3-voxel halo");
    assert!(p.warning.is_some());
    assert!(
        m.plan(ms(1), &FrameSpec { frame_id: 2, ..spec }, 0, Continuity::Changed).warning.is_none(),
        "warned once"
    );
    // Screen space of the same frame: every own tile at the frame's scale, nothing shared.
    let screen = RenderPlan::screen(&config, &["t0".to_string()], &spec, 5, Continuity::ViewMoved);
    assert_eq!((screen.scale, screen.share, screen.settings), (3, None, settings));
}
