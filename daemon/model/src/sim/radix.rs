//! Sort-last compositing schedules on the same [`Lan`]: radix-k (Peterka et al., IceT), of which
//! direct-send is the one-round case (`k = N`) and binary swap the all-twos case, run as a
//! discrete-event simulation over the brick footprints of a real split and camera, without pixels.
//!
//! Each node starts with its brick's footprint (its covered rectangle of the whole image, every
//! pixel a hit, as the object-space simulation renders). Round r with factor k groups the nodes
//! whose indices differ only in digit r (mixed radix over the factors), splits the group's region
//! into k parts (halving the longer side, lower half first; in a wall's one-round direct-send the
//! parts are the tiles, in node order), and each member sends every other member the part of its
//! image in that member's part, keeping its own. What a node holds after a round is the bounding
//! rectangle of what it kept and received, inside its part (IceT's bounding-box sparsity). A
//! message is [`MESSAGE_BYTES`] plus, unless empty, [`RECT_BYTES`] and 7 bytes per pixel; a
//! message goes to every group member each round, empty or not, as Isowall's direct-send does.
//! After the last round, in a wall, the node whose part is another node's tile sends it there.
//!
//! A node enters round r once it has merged all of round r - 1's messages; it encodes and sends
//! its k - 1 messages, then merges each incoming message of round r as it arrives (one
//! compositing thread, [`PixelCost`]), so rounds overlap across nodes as the network allows.

use std::time::Duration;

use super::lan::{Events, Lan, LanCounts, LanModel};
use super::object::PixelCost;
use crate::composite::BYTES_PER_PIXEL;
use crate::Rect;

/// A message's bytes besides its rectangles (frame id, sender, count; as `PeerPixels`).
pub const MESSAGE_BYTES: u64 = 32;
/// A rectangle's bytes besides its pixels (tile, position, size, encoding; as `PixelRect`).
pub const RECT_BYTES: u64 = 48;

/// A rectangle of the image, half-open, in its pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PixelBox {
    pub x0: i64,
    pub y0: i64,
    pub x1: i64,
    pub y1: i64,
}

impl PixelBox {
    pub fn of(w: Rect) -> PixelBox {
        let (x, y) = (i64::from(w.x), i64::from(w.y));
        PixelBox { x0: x, y0: y, x1: x + i64::from(w.width), y1: y + i64::from(w.height) }
    }

    pub fn is_empty(&self) -> bool {
        self.x1 <= self.x0 || self.y1 <= self.y0
    }

    pub fn area(&self) -> u64 {
        if self.is_empty() {
            0
        } else {
            ((self.x1 - self.x0) * (self.y1 - self.y0)) as u64
        }
    }

    pub fn meet(&self, o: &PixelBox) -> PixelBox {
        PixelBox {
            x0: self.x0.max(o.x0),
            y0: self.y0.max(o.y0),
            x1: self.x1.min(o.x1),
            y1: self.y1.min(o.y1),
        }
    }

    /// The bounding box of both (an empty one adds nothing).
    pub fn hull(&self, o: &PixelBox) -> PixelBox {
        match (self.is_empty(), o.is_empty()) {
            (true, _) => *o,
            (_, true) => *self,
            _ => PixelBox {
                x0: self.x0.min(o.x0),
                y0: self.y0.min(o.y0),
                x1: self.x1.max(o.x1),
                y1: self.y1.max(o.y1),
            },
        }
    }

    /// `k` (a power of two) parts by halving the longer side, lower half first.
    pub fn split(&self, k: usize) -> Vec<PixelBox> {
        if k <= 1 {
            return vec![*self];
        }
        let (a, b) = if self.x1 - self.x0 >= self.y1 - self.y0 {
            let m = (self.x0 + self.x1) / 2;
            (PixelBox { x1: m, ..*self }, PixelBox { x0: m, ..*self })
        } else {
            let m = (self.y0 + self.y1) / 2;
            (PixelBox { y1: m, ..*self }, PixelBox { y0: m, ..*self })
        };
        let mut out = a.split(k / 2);
        out.extend(b.split(k - k / 2));
        out
    }
}

/// The bytes of one message carrying `pixels` in one rectangle.
pub fn message_bytes(pixels: u64) -> u64 {
    MESSAGE_BYTES + if pixels > 0 { RECT_BYTES + pixels * BYTES_PER_PIXEL as u64 } else { 0 }
}

/// What to composite: the image, each node's footprint, and for a wall each node's tile.
#[derive(Debug, Clone)]
pub struct Scene {
    pub image: PixelBox,
    pub footprints: Vec<PixelBox>,
    /// Node i shows `tiles[i]` (a wall); empty: the image stays where it was composited.
    pub tiles: Vec<PixelBox>,
}

/// One node's compositing of one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RadixNode {
    pub sent_bytes: u64,
    pub received_bytes: u64,
    pub sent_messages: u64,
    pub merged_pixels: u64,
    /// From the start (every render done at once) to its part (its tile, in a wall) composited.
    pub done: Duration,
}

#[derive(Debug, Clone, PartialEq)]
pub struct RadixReport {
    pub factors: Vec<usize>,
    pub nodes: Vec<RadixNode>,
    pub lan: LanCounts,
}

impl RadixReport {
    /// (mean, max) of `f` over the nodes.
    pub fn mean_max(&self, f: impl Fn(&RadixNode) -> f64) -> (f64, f64) {
        let v: Vec<f64> = self.nodes.iter().map(f).collect();
        (v.iter().sum::<f64>() / v.len().max(1) as f64, v.iter().copied().fold(0.0, f64::max))
    }
}

/// Factors of `n` (a power of two) for radix-k with rounds of `k` (the last round smaller).
pub fn factors(n: usize, k: usize) -> Vec<usize> {
    let (mut left, mut out) = (n, Vec::new());
    while left > 1 {
        let f = k.min(left);
        out.push(f);
        left /= f;
    }
    out
}

#[derive(Debug)]
enum Ev {
    Arrive { to: usize, round: usize, pixels: u64 },
    Merged { node: usize, round: usize },
    Final { to: usize, pixels: u64 },
}

/// The schedule's geometry, round by round: what each node sends whom, and at the end where its
/// part goes.
#[derive(Debug, Clone)]
struct Plan {
    /// `sends[round][node]`: (to, pixels).
    sends: Vec<Vec<Vec<(usize, u64)>>>,
    /// After the last round: (to, pixels) where the node's part is another node's tile.
    last: Vec<Option<(usize, u64)>>,
}

fn plan(scene: &Scene, factors: &[usize]) -> Plan {
    let n = scene.footprints.len();
    let wall_direct = factors.len() == 1 && !scene.tiles.is_empty();
    let mut active: Vec<PixelBox> = scene.footprints.iter().map(|f| f.meet(&scene.image)).collect();
    let mut region = vec![scene.image; n];
    let mut sends = Vec::with_capacity(factors.len());
    let mut stride = 1;
    for &k in factors {
        let mut round = vec![Vec::new(); n];
        let mut next_active = vec![PixelBox::default(); n];
        let mut next_region = vec![PixelBox::default(); n];
        for node in 0..n {
            let digit = node / stride % k;
            let base = node - digit * stride;
            let parts = if wall_direct { scene.tiles.clone() } else { region[node].split(k) };
            let mine = parts[digit];
            let mut keep = active[node].meet(&mine);
            for j in (0..k).filter(|&j| j != digit) {
                let other = base + j * stride;
                round[node].push((other, active[node].meet(&parts[j]).area()));
                keep = keep.hull(&active[other].meet(&mine));
            }
            next_active[node] = keep;
            next_region[node] = mine;
        }
        sends.push(round);
        active = next_active;
        region = next_region;
        stride *= k;
    }
    let last = (0..n)
        .map(|node| {
            let owner = scene.tiles.iter().position(|t| *t == region[node])?;
            (owner != node).then(|| (owner, active[node].area()))
        })
        .collect();
    Plan { sends, last }
}

/// Composites `scene` by radix-k with `factors` (their product is the node count; each a power
/// of two) on `lan`, all renders done at time zero.
pub fn run_radix(scene: &Scene, factors: &[usize], lan: LanModel, cost: PixelCost, seed: u64) -> RadixReport {
    let n = scene.footprints.len();
    debug_assert_eq!(factors.iter().product::<usize>(), n);
    let plan = plan(scene, factors);
    let mut sim = RadixSim {
        plan: &plan,
        factors,
        net: Lan::new(lan, n, seed),
        events: Events::default(),
        out: vec![RadixNode::default(); n],
        cpu_free: vec![Duration::ZERO; n],
        round: vec![0; n],
        got: vec![0; n],
        early: vec![Vec::new(); n],
        cost,
        // In a wall a node is done when its own tile is; a node whose last part is another's
        // tile gets its own from elsewhere.
        shows_own: (0..n).map(|i| plan.last.iter().all(|l| l.is_none_or(|(to, _)| to != i))).collect(),
    };
    for node in 0..n {
        sim.enter(node, 0, Duration::ZERO);
    }
    while let Some((now, ev)) = sim.events.pop() {
        match ev {
            Ev::Arrive { to, round, pixels } => {
                if sim.round[to] == round {
                    sim.merge(to, round, pixels, now);
                } else {
                    sim.early[to].push((round, pixels, now));
                }
            }
            Ev::Merged { node, round } => {
                sim.got[node] += 1;
                if sim.got[node] + 1 == factors[round] {
                    sim.enter(node, round + 1, now);
                }
            }
            Ev::Final { to, pixels } => {
                let end = now.max(sim.cpu_free[to]) + cost.merge(pixels);
                sim.cpu_free[to] = end;
                sim.out[to].merged_pixels += pixels;
                sim.out[to].done = sim.out[to].done.max(end);
            }
        }
    }
    RadixReport { factors: factors.to_vec(), nodes: sim.out, lan: sim.net.counts() }
}

struct RadixSim<'a> {
    plan: &'a Plan,
    factors: &'a [usize],
    net: Lan,
    events: Events<Ev>,
    out: Vec<RadixNode>,
    cpu_free: Vec<Duration>,
    round: Vec<usize>,
    got: Vec<usize>,
    /// Arrivals for rounds a node has not entered yet: (round, pixels, arrived at).
    early: Vec<Vec<(usize, u64, Duration)>>,
    cost: PixelCost,
    shows_own: Vec<bool>,
}

impl RadixSim<'_> {
    fn send(&mut self, from: usize, to: usize, pixels: u64, cpu: &mut Duration) -> Duration {
        let bytes = message_bytes(pixels);
        *cpu += self.cost.encode(pixels);
        self.out[from].sent_bytes += bytes;
        self.out[from].sent_messages += 1;
        self.out[to].received_bytes += bytes;
        self.net.send(*cpu, from, to, bytes as usize)
    }

    fn merge(&mut self, node: usize, round: usize, pixels: u64, at: Duration) {
        let end = at.max(self.cpu_free[node]) + self.cost.merge(pixels);
        self.cpu_free[node] = end;
        self.out[node].merged_pixels += pixels;
        self.events.push(end, Ev::Merged { node, round });
    }

    /// `node` enters `round` at `now`: sends its messages, then merges what came early.
    fn enter(&mut self, node: usize, round: usize, now: Duration) {
        self.round[node] = round;
        self.got[node] = 0;
        let mut cpu = now.max(self.cpu_free[node]);
        if round == self.factors.len() {
            if self.shows_own[node] {
                self.out[node].done = self.out[node].done.max(cpu);
            }
            if let Some((to, pixels)) = self.plan.last[node] {
                let at = self.send(node, to, pixels, &mut cpu);
                self.events.push(at, Ev::Final { to, pixels });
            }
            self.cpu_free[node] = cpu;
            return;
        }
        for &(to, pixels) in &self.plan.sends[round][node] {
            let at = self.send(node, to, pixels, &mut cpu);
            self.events.push(at, Ev::Arrive { to, round, pixels });
        }
        self.cpu_free[node] = cpu;
        if self.factors[round] == 1 {
            return self.enter(node, round + 1, now);
        }
        for (r, pixels, at) in std::mem::take(&mut self.early[node]) {
            if r == round {
                self.merge(node, round, pixels, at);
            } else {
                self.early[node].push((r, pixels, at));
            }
        }
    }
}
