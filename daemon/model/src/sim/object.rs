//! Object space at scale: N [`ObjectMachine`]s on a [`Lan`], direct-send compositing of a wall of
//! N tiles, node i showing tile i and rendering brick i of a 512^3 volume split by
//! [`bricks::split`], the wall camera framing the volume ([`WallConfig::camera_for`]). The
//! controller is endpoint N and only sends the frame states (the next frame begins once every
//! node composited the last).
//!
//! The machines run on tiles of 1920/`divisor` x 1080/`divisor` pixels so that a 256-node wall fits
//! in memory; every pixel message is sized for 1080p tiles on the network: its real encoded length
//! (`codec::encode_pixels`, raw rectangles) plus `divisor^2 - 1` times its rectangles' pixel bytes.
//! A render gives, over each view's rectangle, a hit at depth `brick + 1` in every pixel (a brick
//! covers its whole covered rectangle: the most a brick sends).
//!
//! The cost model, per 1080p pixel, on one compositing thread per node: encoding what is sent
//! `encode_ns`, then each peer's message, once it has arrived, decoding and merging it
//! `merge_ns`; the node's own layers are merged after its sends are encoded. The compositing time
//! is the machine's own report (`Message::Composited::composite_us`): from its render done to its
//! tile composited.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use glam::DVec3;

use super::lan::{Events, Lan, LanCounts, LanModel};
use super::SimError;
use crate::bricks::{self, Occupancy};
use crate::codec;
use crate::composite::{PixelForm, TileCanvas, BYTES_PER_PIXEL};
use crate::config::WallConfig;
use crate::messages::Message;
use crate::object_machine::{BrickGeometry, FrameViews, ObjectMachine, ObjectOutput};
use crate::{Camera, Rect, View};

/// The volume the walls render: 512^3 samples, unit spacing.
pub const VOLUME_DIMS: [usize; 3] = [512, 512, 512];
/// A 1080p tile.
pub const TILE: (u32, u32) = (1920, 1080);

/// A per-pixel cost of compositing work.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelCost {
    /// Copying a pixel (depth f32, sRGB8) into a message.
    pub encode_ns: f64,
    /// Decoding a received pixel and keeping the nearer of it and the tile's.
    pub merge_ns: f64,
}

impl PixelCost {
    /// 1 ns to copy 7 bytes out, 2 ns to read 7 bytes in, compare a depth and write 7 bytes: one
    /// core streaming about 10 GB/s.
    pub const fn memory_bound() -> PixelCost {
        PixelCost { encode_ns: 1.0, merge_ns: 2.0 }
    }

    pub fn encode(&self, pixels: u64) -> Duration {
        Duration::from_nanos((pixels as f64 * self.encode_ns).round() as u64)
    }

    pub fn merge(&self, pixels: u64) -> Duration {
        Duration::from_nanos((pixels as f64 * self.merge_ns).round() as u64)
    }
}

/// A wall of `nodes` tiles in a square grid, in object space, and the bricks of its volume.
#[derive(Debug, Clone)]
pub struct ObjectWall {
    pub config: WallConfig,
    pub camera: Camera,
    /// Brick i's owned box (world), rendered by node i.
    pub owned: Vec<(DVec3, DVec3)>,
    pub divisor: u32,
    pub side: usize,
}

impl ObjectWall {
    /// `nodes` must be a square; 1920 and 1080 must divide by `divisor`.
    pub fn new(nodes: usize, divisor: u32) -> Result<ObjectWall, SimError> {
        let side = (nodes as f64).sqrt().round() as usize;
        if side * side != nodes || nodes == 0 {
            return Err(SimError::NotSquare { nodes });
        }
        if divisor == 0 || !TILE.0.is_multiple_of(divisor) || !TILE.1.is_multiple_of(divisor) {
            return Err(SimError::Divisor { divisor });
        }
        let (tw, th) = (TILE.0 / divisor, TILE.1 / divisor);
        let mut s = String::from(
            "[wall]\nname = \"scale\"\nmode = \"object\"\ncompress = false\ndeadline_ms = 60000\n\n\
             [volume]\nsource = \"procedural:sphere:64\"\n",
        );
        for i in 0..nodes {
            let (x, y) = ((i % side) as u32 * tw, (i / side) as u32 * th);
            s += &format!(
                "\n[[tiles]]\nname = \"t{i}\"\nx = {x}\ny = {y}\nwidth = {tw}\nheight = {th}\n\n\
                 [[nodes]]\nname = \"node{i}\"\naddress = \"10.0.{}.{}:7400\"\ntiles = [\"t{i}\"]\n",
                i / 200,
                i % 200 + 1,
            );
        }
        let config =
            WallConfig::parse(&s, Path::new("scale.toml")).map_err(|e| SimError::Config(e.to_string()))?;
        let owned = brick_boxes(nodes)?;
        let hi = DVec3::from_array(VOLUME_DIMS.map(|d| (d - 1) as f64));
        let camera = config.camera_for(DVec3::ZERO, hi);
        Ok(ObjectWall { config, camera, owned, divisor, side })
    }

    /// Each brick's covered rectangle of the whole wall image (`bricks::covered_rect`), in this
    /// wall's pixels.
    pub fn footprints(&self) -> Vec<Option<Rect>> {
        let (w, h) = self.config.wall_size();
        let view = View { camera: self.camera, full: (w, h), rect: Rect { x: 0, y: 0, width: w, height: h } };
        self.owned.iter().map(|&(lo, hi)| bricks::covered_rect(&view, lo, hi)).collect()
    }
}

/// The owned boxes of `n` bricks of the 512^3 volume, split by sample count.
pub fn brick_boxes(n: usize) -> Result<Vec<(DVec3, DVec3)>, SimError> {
    let block = 8;
    let counts = VOLUME_DIMS.map(|d| d / block);
    let occ = Occupancy { block, counts, occupied: vec![false; counts.iter().product()] };
    let bricks =
        bricks::split(&occ, VOLUME_DIMS, DVec3::ONE, n).map_err(|e| SimError::Config(e.to_string()))?;
    Ok(bricks.iter().map(|b| b.owned_box(DVec3::ZERO, DVec3::ONE)).collect())
}

/// An object-space run.
#[derive(Debug, Clone)]
pub struct ObjectSpec {
    pub nodes: usize,
    pub divisor: u32,
    pub lan: LanModel,
    pub cost: PixelCost,
    pub render: Duration,
    pub frames: u64,
    pub seed: u64,
}

impl ObjectSpec {
    /// `nodes` on 10 GbE, memory-bound compositing, 10 ms renders, 3 frames.
    pub fn new(nodes: usize, divisor: u32, seed: u64) -> ObjectSpec {
        ObjectSpec {
            nodes,
            divisor,
            lan: LanModel::ten_gbe(),
            cost: PixelCost::memory_bound(),
            render: Duration::from_millis(10),
            frames: 3,
            seed,
        }
    }
}

/// One node's share of one frame, sized for 1080p tiles.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct NodeShare {
    pub sent_bytes: u64,
    pub received_bytes: u64,
    pub sent_messages: u64,
    /// Pixels it merged from its peers.
    pub merged_pixels: u64,
    /// Its compositing time (its report to the controller).
    pub composite: Duration,
    /// Peers it went without.
    pub missing: usize,
}

/// A finished object-space run.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectReport {
    pub nodes: usize,
    pub divisor: u32,
    /// Per frame, per node.
    pub frames: Vec<Vec<NodeShare>>,
    pub lan: LanCounts,
    pub errors: Vec<String>,
}

impl ObjectReport {
    /// Over every frame and node: (mean, max) of `f`.
    pub fn mean_max(&self, f: impl Fn(&NodeShare) -> f64) -> (f64, f64) {
        let all: Vec<f64> = self.frames.iter().flatten().map(f).collect();
        let max = all.iter().copied().fold(0.0, f64::max);
        (all.iter().sum::<f64>() / all.len().max(1) as f64, max)
    }
}

#[derive(Debug)]
enum Ev {
    Begin { frame: u64 },
    FrameState { node: usize, frame: u64 },
    RenderDone { node: usize, frame: u64, views: FrameViews },
    Arrived { to: usize, from: usize, bytes: Vec<u8>, pixels: u64 },
    Merged { to: usize, from: usize, bytes: Vec<u8> },
    Timeout { node: usize },
}

struct Sim {
    spec: ObjectSpec,
    wall: ObjectWall,
    machines: Vec<ObjectMachine>,
    names: Vec<String>,
    index: BTreeMap<String, usize>,
    cpu_free: Vec<Duration>,
    timeout_at: Vec<Option<Duration>>,
    events: Events<Ev>,
    lan: Lan,
    shares: BTreeMap<u64, Vec<NodeShare>>,
    composited: BTreeMap<u64, usize>,
    errors: Vec<String>,
}

impl Sim {
    fn new(spec: ObjectSpec) -> Result<Sim, SimError> {
        let wall = ObjectWall::new(spec.nodes, spec.divisor)?;
        let names: Vec<String> = wall.config.nodes.iter().map(|n| n.name.clone()).collect();
        let own_bytes = (VOLUME_DIMS.iter().product::<usize>() * 4 / spec.nodes) as u64;
        let machines = (0..spec.nodes)
            .map(|i| {
                let geometry = BrickGeometry {
                    owned: wall.owned.clone(),
                    own: i,
                    own_bytes,
                    spacing: DVec3::ONE,
                    halo: [10; 3],
                };
                ObjectMachine::new(&wall.config, &names[i], geometry, None)
            })
            .collect();
        Ok(Sim {
            index: names.iter().cloned().enumerate().map(|(i, n)| (n, i)).collect(),
            machines,
            names,
            cpu_free: vec![Duration::ZERO; spec.nodes],
            timeout_at: vec![None; spec.nodes],
            events: Events::default(),
            lan: Lan::new(spec.lan, spec.nodes + 1, spec.seed),
            shares: BTreeMap::new(),
            composited: BTreeMap::new(),
            errors: Vec::new(),
            wall,
            spec,
        })
    }

    fn scale(&self) -> u64 {
        u64::from(self.spec.divisor).pow(2)
    }

    fn share(&mut self, frame: u64, node: usize) -> &mut NodeShare {
        let n = self.spec.nodes;
        &mut self.shares.entry(frame).or_insert_with(|| vec![NodeShare::default(); n])[node]
    }

    fn run(&mut self) {
        self.events.push(Duration::from_millis(1), Ev::Begin { frame: 1 });
        while let Some((now, ev)) = self.events.pop() {
            self.step(now, ev);
        }
    }

    fn step(&mut self, now: Duration, ev: Ev) {
        let node = match &ev {
            Ev::Begin { frame } => {
                let state_bytes = 400; // a FrameState message, about
                for n in 0..self.spec.nodes {
                    let at = self.lan.send(now, self.spec.nodes, n, state_bytes);
                    self.events.push(at, Ev::FrameState { node: n, frame: *frame });
                }
                return;
            }
            Ev::FrameState { node, .. } | Ev::RenderDone { node, .. } | Ev::Timeout { node } => *node,
            Ev::Arrived { to, .. } | Ev::Merged { to, .. } => *to,
        };
        self.node_event(now, node, ev);
        let next = self.machines[node].poll_timeout();
        if let Some(at) = next.filter(|_| next != self.timeout_at[node]) {
            self.timeout_at[node] = next;
            self.events.push(at.max(now), Ev::Timeout { node });
        }
    }

    fn node_event(&mut self, now: Duration, n: usize, ev: Ev) {
        match ev {
            Ev::FrameState { frame, .. } => {
                self.machines[n].announce(frame);
                let (views, out) = self.machines[n].views(now, frame, self.wall.camera, [0; 3]);
                self.outputs(now, n, out);
                self.events.push(now + self.spec.render, Ev::RenderDone { node: n, frame, views });
            }
            Ev::RenderDone { frame, views, .. } => {
                let mut own_pixels = 0u64;
                let canvases: Vec<TileCanvas> = views
                    .views
                    .iter()
                    .zip(&views.bricks)
                    .map(|((tile, v), &b)| {
                        let px = v.rect.width as usize * v.rect.height as usize;
                        if self.wall.config.node_of_tile(tile).is_some_and(|o| o.name == self.names[n]) {
                            own_pixels += px as u64;
                        }
                        TileCanvas {
                            name: tile.clone(),
                            width: v.rect.width,
                            height: v.rect.height,
                            form: PixelForm::Colour,
                            depth: vec![b as f32 + 1.0; px],
                            rgb8: vec![(b % 251) as u8; px * 3],
                            shading: Vec::new(),
                        }
                    })
                    .collect();
                let out = self.machines[n].local_done(now, frame, self.spec.render, canvases);
                let mut cpu = now.max(self.cpu_free[n]);
                let mut rest = Vec::new();
                for o in out {
                    let ObjectOutput::SendPixels { peer, frame_id, bytes } = o else {
                        rest.push(o);
                        continue;
                    };
                    let pixels = match codec::decode_pixels(&bytes) {
                        Ok(p) => {
                            p.rects.iter().map(|r| u64::from(r.width) * u64::from(r.height)).sum::<u64>()
                        }
                        Err(e) => {
                            self.errors.push(format!("{}: its own pixels do not decode: {e}", self.names[n]));
                            continue;
                        }
                    };
                    let full_pixels = pixels * self.scale();
                    let wire = bytes.len() as u64 + (full_pixels - pixels) * BYTES_PER_PIXEL as u64;
                    cpu += self.spec.cost.encode(full_pixels);
                    let to = self.index[&peer];
                    let at = self.lan.send(cpu, n, to, wire as usize);
                    let s = self.share(frame_id, n);
                    s.sent_bytes += wire;
                    s.sent_messages += 1;
                    self.share(frame_id, to).received_bytes += wire;
                    self.events.push(at, Ev::Arrived { to, from: n, bytes, pixels: full_pixels });
                }
                self.cpu_free[n] = cpu + self.spec.cost.merge(own_pixels * self.scale());
                self.outputs(now, n, rest);
            }
            Ev::Arrived { from, bytes, pixels, .. } => {
                let end = now.max(self.cpu_free[n]) + self.spec.cost.merge(pixels);
                self.cpu_free[n] = end;
                self.events.push(end, Ev::Merged { to: n, from, bytes });
            }
            Ev::Merged { from, bytes, .. } => match codec::decode_pixels(&bytes) {
                Ok(pixels) => {
                    let f = pixels.frame_id;
                    let merged: u64 =
                        pixels.rects.iter().map(|r| u64::from(r.width) * u64::from(r.height)).sum();
                    let scale = self.scale();
                    self.share(f, n).merged_pixels += merged * scale;
                    let cert = self.names[from].clone();
                    let out = self.machines[n].peer(now, &cert, from as u64, pixels);
                    self.outputs(now, n, out);
                }
                Err(e) => {
                    self.errors.push(format!("{}: pixels from {} do not decode: {e}", self.names[n], from))
                }
            },
            Ev::Timeout { .. } => {
                self.timeout_at[n] = None;
                let out = self.machines[n].handle_timeout(now);
                self.outputs(now, n, out);
            }
            Ev::Begin { .. } => {}
        }
    }

    fn outputs(&mut self, now: Duration, n: usize, out: Vec<ObjectOutput>) {
        for o in out {
            match o {
                ObjectOutput::Composited(c) => {
                    let report = self.machines[n].report(now, &c);
                    let Message::Composited { composite_us, missing, .. } = report else { continue };
                    let s = self.share(c.frame_id, n);
                    s.composite = Duration::from_micros(composite_us);
                    s.missing = missing.len();
                    let done = self.composited.entry(c.frame_id).or_default();
                    *done += 1;
                    if *done == self.spec.nodes && c.frame_id < self.spec.frames {
                        self.events.push(now + Duration::from_millis(1), Ev::Begin { frame: c.frame_id + 1 });
                    }
                }
                ObjectOutput::ClosePeer { peer, reason, .. } | ObjectOutput::Dropped { peer, reason } => {
                    self.errors.push(format!("{} closed {peer}: {reason}", self.names[n]))
                }
                // The simulated links have no connections to renew.
                ObjectOutput::Reconnect { .. } => {}
                other => self.errors.push(format!("{}: unexpected {other:?}", self.names[n])),
            }
        }
    }
}

/// Runs `spec`: every frame rendered, sent and composited by every node.
pub fn run_object(spec: &ObjectSpec) -> Result<ObjectReport, SimError> {
    let mut sim = Sim::new(spec.clone())?;
    sim.run();
    Ok(ObjectReport {
        nodes: spec.nodes,
        divisor: spec.divisor,
        frames: sim.shares.into_values().collect(),
        lan: sim.lan.counts(),
        errors: sim.errors,
    })
}
