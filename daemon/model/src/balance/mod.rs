//! Load-balanced screen space, the split (sort-first, as Equalizer's load equalizer resizes its
//! areas from the last frames' times): the controller cuts the wall's pixels into work rectangles
//! and gives each node a share of equal expected cost. No I/O and no clock: costs come in as
//! numbers (milliseconds or voxel fetches, one unit for the whole wall), the split goes out.
//!
//! - Every tile is cut into [`Balancer::bands`] bands of whole rows; a work rectangle is a run of
//!   bands of one tile, the tile's full width ([`WorkRect`]). Each band has a cost estimate.
//! - A node reports the cost of each rectangle it rendered ([`Balancer::observe`]); the cost is
//!   spread over the rectangle's bands in proportion to their estimates (evenly while they have
//!   none), and each estimate moves towards it by the smoothing weight.
//! - The cut ([`cut`]): the target is the wall's cost over the nodes that take part. A node keeps
//!   its own tiles' bands, in order, while they bring it closer to the target; the bands it does
//!   not keep go, in order, to the nodes below the target, the one with the most room first,
//!   each filled with a contiguous run before the next. So a node renders its own pixels where it
//!   can (no transfer), and the rectangles that travel are few and long.
//! - Hysteresis ([`Balancer::next_split`]): the split in use is kept while its predicted slowest
//!   node over the mean is within [`Balancer::hysteresis`] of a fresh cut's; after
//!   [`STILL_SETTLE_FRAMES`] of a still view it is kept: the view's rectangles keep their
//!   renderers, so their running sums stay where they are.
//! - Nodes that take part ([`Balancer::set_nodes`]): a node that is down renders nothing, and its
//!   tiles (which nobody shows) are left out.
//! - Nodes held out of the split ([`Balancer::set_held`]): a node whose claims did not hold
//!   ([`claims::Claims`]: it did not deliver the rows it was given, or did not report what they
//!   cost) renders its own tiles, all of them, and nothing else, and the others balance among
//!   themselves.
//! - A node's costs are claims ([`Balancer::observe_claim`]): each is held between the pixels'
//!   own floor and 16 times either side of what the rows were predicted to cost (an honest
//!   restarted row costs up to 16 times a settled one under spending by history).
//! - What a node makes of a split ([`share::NodeShare`]): the rectangles it renders, those it
//!   sends to each tile's owner, and those each peer sends it (the compositor's expectation); and
//!   the split on the wire ([`crate::wire::WireSplit`]: tiles and nodes by their index in the
//!   wall config), checked whole before a node uses it.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::config::WallConfig;

pub mod claims;
pub mod node;
pub mod share;

/// Bands per tile by default: 32 bands of a 1080-row tile are about 34 rows each.
pub const DEFAULT_BANDS: u32 = 32;
/// A new split replaces the one in use only where it predicts a slowest/mean this much lower.
pub const DEFAULT_HYSTERESIS: f64 = 0.02;
/// Frames of a still view after which its split is kept (unless a node leaves): a still wall's
/// rectangles then keep their renderers, and with them the pixels' running sums; the first ones
/// still learn the costs.
pub const STILL_SETTLE_FRAMES: u32 = 8;
/// The weight of the newest cost in each band's estimate.
pub const DEFAULT_SMOOTHING: f64 = 1.0;
/// How far a claimed cost may stand from the rows' predicted cost, either way: an honest row
/// restarted by a move spends up to 16 times the samples of a settled one
/// (`Rule::spending`: `clamp(10 - h, 0.25, 4)` a pixel, 4 / 0.25).
pub const CLAIM_RATIO: f64 = 16.0;

/// Rows `first_row ..first_row + rows` of tile `tile` (its full width), rendered by `renderer`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct WorkRect {
    pub tile: String,
    pub first_row: u32,
    pub rows: u32,
    pub renderer: String,
}

/// A frame's work rectangles, in the order of the tiles and their rows.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Split {
    pub rects: Vec<WorkRect>,
}

impl Split {
    /// The rectangles `node` renders.
    pub fn of<'a>(&'a self, node: &'a str) -> impl Iterator<Item = &'a WorkRect> + 'a {
        self.rects.iter().filter(move |r| r.renderer == node)
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BalanceError {
    #[error("bands per tile must be at least 1")]
    NoBands,
    #[error("hysteresis {0} and smoothing {1}: each must be finite, hysteresis >= 0, smoothing in (0, 1]")]
    Weights(f64, f64),
    #[error("tile `{0}` appears twice")]
    DuplicateTile(String),
}

/// One tile's bands and their estimates.
#[derive(Debug, Clone)]
struct Bands {
    tile: String,
    owner: String,
    height: u32,
    cost: Vec<f64>,
    /// Whether any rectangle of the tile has been measured.
    measured: bool,
}

impl Bands {
    /// Band `k`'s rows.
    fn rows(&self, k: usize) -> (u32, u32) {
        let (n, h) = (self.cost.len() as u64, u64::from(self.height));
        let at = |k: u64| (k * h / n) as u32;
        (at(k as u64), at(k as u64 + 1))
    }

    /// The bands a rectangle covers (those whose rows it holds most of).
    fn covered(&self, first_row: u32, rows: u32) -> std::ops::Range<usize> {
        let end = first_row.saturating_add(rows);
        let inside = |k: usize| {
            let (a, b) = self.rows(k);
            let mid = (a + b) / 2;
            mid >= first_row && mid < end
        };
        let start = (0..self.cost.len()).find(|&k| inside(k)).unwrap_or(self.cost.len());
        let stop = (start..self.cost.len()).find(|&k| !inside(k)).unwrap_or(self.cost.len());
        start..stop
    }
}

/// The split's state (module docs).
#[derive(Debug, Clone)]
pub struct Balancer {
    tiles: Vec<Bands>,
    /// What moving one row of a tile to its owner costs its renderer, in the costs' unit.
    transfer_per_row: f64,
    hysteresis: f64,
    smoothing: f64,
    nodes: BTreeSet<String>,
    /// Nodes held out of the split (module docs).
    held: BTreeSet<String>,
    split: Split,
    /// Frames of the same image so far.
    still_frames: u32,
}

impl Balancer {
    /// `tiles`: (tile, its owner, its height in rows), in the wall's order. Until costs are
    /// observed, every node renders its own tiles.
    pub fn new(
        tiles: Vec<(String, String, u32)>,
        bands: u32,
        hysteresis: f64,
        smoothing: f64,
    ) -> Result<Balancer, BalanceError> {
        if bands == 0 {
            return Err(BalanceError::NoBands);
        }
        let weights_ok = hysteresis.is_finite() && hysteresis >= 0.0 && smoothing > 0.0 && smoothing <= 1.0;
        if !weights_ok {
            return Err(BalanceError::Weights(hysteresis, smoothing));
        }
        let mut seen = BTreeSet::new();
        let mut out = Vec::with_capacity(tiles.len());
        for (tile, owner, height) in tiles {
            if !seen.insert(tile.clone()) {
                return Err(BalanceError::DuplicateTile(tile));
            }
            let n = bands.min(height.max(1)) as usize;
            out.push(Bands { tile, owner, height, cost: vec![0.0; n], measured: false });
        }
        let nodes = out.iter().map(|t| t.owner.clone()).collect();
        let mut b = Balancer {
            tiles: out,
            transfer_per_row: 0.0,
            hysteresis,
            smoothing,
            nodes,
            held: BTreeSet::new(),
            split: Split::default(),
            still_frames: 0,
        };
        b.split = b.own_tiles();
        Ok(b)
    }

    /// The wall's tiles and owners, with the default bands and weights.
    pub fn for_wall(config: &WallConfig) -> Balancer {
        let tiles = config
            .tiles
            .iter()
            .filter_map(|t| config.node_of_tile(&t.name).map(|n| (t.name.clone(), n.name.clone(), t.height)))
            .collect();
        Balancer::new(tiles, DEFAULT_BANDS, DEFAULT_HYSTERESIS, DEFAULT_SMOOTHING)
            .expect("the defaults are valid and a wall's tile names are unique")
    }

    pub fn hysteresis(&self) -> f64 {
        self.hysteresis
    }

    /// What sending one row of a tile to its owner costs the node that rendered it, in the costs'
    /// unit (0 by default; e.g. a row's bytes over the link's rate, as time): a band is given
    /// away only where it still pays.
    pub fn set_transfer_per_row(&mut self, cost: f64) {
        if cost.is_finite() && cost >= 0.0 {
            self.transfer_per_row = cost;
        }
    }

    /// The split in use.
    pub fn split(&self) -> &Split {
        &self.split
    }

    /// Every node rendering its own tiles (the unbalanced wall).
    pub fn own_tiles(&self) -> Split {
        let rects = self
            .tiles
            .iter()
            .filter(|t| self.nodes.contains(&t.owner))
            .map(|t| WorkRect {
                tile: t.tile.clone(),
                first_row: 0,
                rows: t.height,
                renderer: t.owner.clone(),
            })
            .collect();
        Split { rects }
    }

    /// The nodes that take part from now on (a node that is down: none of its tiles are shown,
    /// and it renders nothing). The next split leaves the others out at once.
    pub fn set_nodes(&mut self, nodes: impl IntoIterator<Item = String>) {
        self.nodes = nodes.into_iter().collect();
    }

    /// The nodes held out of the split from now on (module docs): each renders its own tiles
    /// and nothing else. The next split follows at once.
    pub fn set_held(&mut self, held: impl IntoIterator<Item = String>) {
        self.held = held.into_iter().collect();
    }

    /// The nodes held out of the split.
    pub fn held(&self) -> &BTreeSet<String> {
        &self.held
    }

    /// The cost `rect`'s renderer claims, held to what it can be: at least `floor` (what the
    /// rectangle's pixels cost whatever their rays do) and, once the tile has been measured,
    /// within [`CLAIM_RATIO`] of the rows' predicted cost either way. Returns the cost observed,
    /// `None` where it is not a number or the rectangle is not of this wall.
    pub fn observe_claim(&mut self, rect: &WorkRect, claimed: f64, floor: f64) -> Option<f64> {
        let t = self.tiles.iter().find(|t| t.tile == rect.tile)?;
        let range = t.covered(rect.first_row, rect.rows);
        if range.is_empty() || claimed.is_nan() || !(floor.is_finite() && floor >= 0.0) {
            return None;
        }
        let predicted: f64 = t.cost[range].iter().sum();
        let (lo, hi) = if t.measured && predicted > 0.0 {
            (floor.max(predicted / CLAIM_RATIO), (predicted * CLAIM_RATIO).max(floor))
        } else {
            (floor, f64::MAX)
        };
        let cost = claimed.clamp(lo, hi);
        self.observe(rect, cost);
        Some(cost)
    }

    /// A rectangle of the split in use took `cost` to render (module docs). Rectangles of tiles
    /// the wall lacks, and costs that are not finite or negative, are ignored.
    pub fn observe(&mut self, rect: &WorkRect, cost: f64) {
        if !cost.is_finite() || cost < 0.0 {
            return;
        }
        let alpha = self.smoothing;
        let Some(t) = self.tiles.iter_mut().find(|t| t.tile == rect.tile) else { return };
        let range = t.covered(rect.first_row, rect.rows);
        if range.is_empty() {
            return;
        }
        let predicted: f64 = t.cost[range.clone()].iter().sum();
        let n = range.len() as f64;
        // The first measure of a tile replaces its empty estimates outright.
        let alpha = if t.measured { alpha } else { 1.0 };
        for k in range {
            let share = if predicted > 0.0 { t.cost[k] / predicted } else { 1.0 / n };
            t.cost[k] = (1.0 - alpha) * t.cost[k] + alpha * cost * share;
        }
        t.measured = true;
    }

    /// The predicted cost of each taking part node under `split` (its rectangles' work, and the
    /// transfer of those of other nodes' tiles).
    pub fn loads(&self, split: &Split) -> BTreeMap<String, f64> {
        let mut loads: BTreeMap<String, f64> = self.nodes.iter().map(|n| (n.clone(), 0.0)).collect();
        for r in &split.rects {
            let Some(t) = self.tiles.iter().find(|t| t.tile == r.tile) else { continue };
            let mut c: f64 = t.cost[t.covered(r.first_row, r.rows)].iter().sum();
            if r.renderer != t.owner {
                c += self.transfer_per_row * f64::from(r.rows);
            }
            *loads.entry(r.renderer.clone()).or_default() += c;
        }
        loads
    }

    /// The split for the next frame: a fresh [`cut`] where the one in use names a node that no
    /// longer takes part, shows a tile nobody shows or leaves out one of a node that is back,
    /// or predicts a slowest/mean more than
    /// [`Balancer::hysteresis`] above the fresh cut's; else the one in use, and always, unless
    /// stale, after [`STILL_SETTLE_FRAMES`] frames of the same image (`still`: the frame shows
    /// the same image as the one before).
    pub fn next_split(&mut self, still: bool) -> &Split {
        self.still_frames = if still { self.still_frames.saturating_add(1) } else { 0 };
        let margin = if self.still_frames > STILL_SETTLE_FRAMES { f64::INFINITY } else { self.hysteresis };
        let fresh = cut(&self.tiles, &self.nodes, &self.held, self.transfer_per_row);
        let stale = self.split.rects.iter().any(|r| {
            !self.nodes.contains(&r.renderer)
                || self.tiles.iter().any(|t| {
                    t.tile == r.tile
                        && (!self.nodes.contains(&t.owner)
                            || (t.owner != r.renderer
                                && (self.held.contains(&r.renderer) || self.held.contains(&t.owner))))
                })
        }) || self
            .tiles
            .iter()
            .any(|t| self.nodes.contains(&t.owner) && !self.split.rects.iter().any(|r| r.tile == t.tile));
        let worse =
            slowest_over_mean(&self.loads(&self.split)) > slowest_over_mean(&self.loads(&fresh)) + margin;
        if stale || worse {
            self.split = fresh;
        }
        &self.split
    }
}

/// The slowest node's cost over the mean (1 where nothing costs anything).
pub fn slowest_over_mean(loads: &BTreeMap<String, f64>) -> f64 {
    let n = loads.len().max(1) as f64;
    let mean = loads.values().sum::<f64>() / n;
    let max = loads.values().copied().fold(0.0, f64::max);
    if mean > 0.0 {
        max / mean
    } else {
        1.0
    }
}

/// The cut (module docs): each node keeps its own tiles' bands while they bring it closer to
/// the target; the rest go to the nodes below it, most room first. The target is the wall's
/// cost over the nodes, with the transfer of the rows a first cut at that target moves. Held
/// nodes keep their own tiles whole and take nothing: the target is the others' cost over them.
fn cut(tiles: &[Bands], nodes: &BTreeSet<String>, held: &BTreeSet<String>, transfer_per_row: f64) -> Split {
    let shown: Vec<&Bands> = tiles.iter().filter(|t| nodes.contains(&t.owner)).collect();
    let total: f64 = shown.iter().filter(|t| !held.contains(&t.owner)).flat_map(|t| t.cost.iter()).sum();
    let n = nodes.iter().filter(|n| !held.contains(*n)).count().max(1) as f64;
    let first = cut_at(&shown, nodes, held, total / n, transfer_per_row);
    if transfer_per_row == 0.0 {
        return first;
    }
    let moved: u32 = first
        .rects
        .iter()
        .filter(|r| shown.iter().any(|t| t.tile == r.tile && t.owner != r.renderer))
        .map(|r| r.rows)
        .sum();
    cut_at(&shown, nodes, held, (total + transfer_per_row * f64::from(moved)) / n, transfer_per_row)
}

/// [`cut`] at a given target.
fn cut_at(
    shown: &[&Bands],
    nodes: &BTreeSet<String>,
    held: &BTreeSet<String>,
    target: f64,
    transfer_per_row: f64,
) -> Split {
    // Per band: who renders it.
    let mut renderer: Vec<Vec<&str>> = shown.iter().map(|t| vec![t.owner.as_str(); t.cost.len()]).collect();
    let mut load: BTreeMap<&str, f64> = nodes.iter().map(|n| (n.as_str(), 0.0)).collect();
    let mut given: Vec<(usize, usize)> = Vec::new();
    for node in nodes {
        let mut kept = 0.0;
        for (i, t) in shown.iter().enumerate().filter(|(_, t)| &t.owner == node) {
            for (k, &c) in t.cost.iter().enumerate() {
                if kept + c / 2.0 <= target || kept == 0.0 || held.contains(node) {
                    kept += c;
                } else {
                    given.push((i, k));
                }
            }
        }
        load.insert(node.as_str(), kept);
    }
    // Receivers by room, most first (names break ties, so the cut is the same on every run).
    let mut receivers: Vec<(&str, f64)> = load
        .iter()
        .filter(|(&n, &l)| l < target && !held.contains(n))
        .map(|(&n, &l)| (n, target - l))
        .collect();
    receivers.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(b.0)));
    let mut r = 0;
    for (i, k) in given {
        let (a, b) = shown[i].rows(k);
        let c = shown[i].cost[k] + transfer_per_row * f64::from(b - a);
        while r + 1 < receivers.len() && receivers[r].1 < c / 2.0 {
            r += 1;
        }
        // No node below the target: the band stays with its owner.
        if let Some(slot) = receivers.get_mut(r) {
            renderer[i][k] = slot.0;
            slot.1 -= c;
        }
    }
    // Runs of one renderer in a tile are one rectangle.
    let mut rects = Vec::new();
    for (i, t) in shown.iter().enumerate() {
        let mut k = 0;
        while k < t.cost.len() {
            let who = renderer[i][k];
            let start = k;
            while k < t.cost.len() && renderer[i][k] == who {
                k += 1;
            }
            let (first, _) = t.rows(start);
            let (_, end) = t.rows(k - 1);
            rects.push(WorkRect {
                tile: t.tile.clone(),
                first_row: first,
                rows: end - first,
                renderer: who.to_string(),
            });
        }
    }
    Split { rects }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A row of `n` tiles of 100 rows, tile i owned by node i.
    fn wall(n: usize, bands: u32) -> Balancer {
        let tiles = (0..n).map(|i| (format!("t{i}"), format!("n{i}"), 100)).collect();
        Balancer::new(tiles, bands, DEFAULT_HYSTERESIS, DEFAULT_SMOOTHING).unwrap()
    }

    fn ratio(b: &Balancer) -> f64 {
        slowest_over_mean(&b.loads(b.split()))
    }

    #[test]
    fn before_any_cost_each_node_renders_its_own_tiles() {
        let b = wall(3, 10);
        assert_eq!(b.split().rects.len(), 3);
        for (i, r) in b.split().rects.iter().enumerate() {
            assert_eq!(
                (r.tile.as_str(), r.first_row, r.rows, r.renderer.as_str()),
                (&*format!("t{i}"), 0, 100, &*format!("n{i}"))
            );
        }
    }

    #[test]
    fn a_busy_tile_is_shared_with_idle_nodes_to_equal_cost() {
        let mut b = wall(4, 20);
        // Tile 0 holds the scan: 10 units a band; the others sky, 0.5 a band.
        let costs = [200.0, 10.0, 10.0, 10.0];
        for (i, c) in costs.iter().enumerate() {
            let r = b.split().rects[i].clone();
            b.observe(&r, *c);
        }
        assert!((ratio(&b) - 200.0 / (230.0 / 4.0)).abs() < 1e-9, "unbalanced: {}", ratio(&b));
        b.next_split(false);
        let loads = b.loads(b.split());
        assert!(ratio(&b) < 1.15, "balanced: {loads:?}");
        // The busy tile's rows are covered once, by rectangles of whole bands, and n0 keeps the top.
        let t0: Vec<&WorkRect> = b.split().rects.iter().filter(|r| r.tile == "t0").collect();
        assert_eq!(t0[0].renderer, "n0");
        assert_eq!(t0[0].first_row, 0);
        let mut row = 0;
        for r in &t0 {
            assert_eq!(r.first_row, row);
            row += r.rows;
        }
        assert_eq!(row, 100);
        assert!(t0.len() >= 4, "{t0:?}");
        // The others keep their own tiles whole.
        for i in 1..4 {
            let own: Vec<&WorkRect> = b.split().rects.iter().filter(|r| r.tile == format!("t{i}")).collect();
            assert_eq!((own.len(), own[0].renderer.clone()), (1, format!("n{i}")));
        }
    }

    #[test]
    fn a_still_wall_keeps_its_split_and_a_moved_load_changes_it() {
        let mut b = wall(4, 20);
        let measure = |b: &mut Balancer, per_tile: [f64; 4]| {
            // Each rectangle's true cost: its share of its tile's rows of the tile's cost.
            let rects = b.split().rects.clone();
            for r in rects {
                let i: usize = r.tile[1..].parse().unwrap();
                b.observe(&r, per_tile[i] * r.rows as f64 / 100.0);
            }
        };
        measure(&mut b, [200.0, 10.0, 10.0, 10.0]);
        let first = b.next_split(false).clone();
        for _ in 0..10 {
            measure(&mut b, [200.0, 10.0, 10.0, 10.0]);
            assert_eq!(b.next_split(true), &first, "a still view keeps its rectangles");
        }
        // The scan moves to tile 3.
        for _ in 0..6 {
            measure(&mut b, [10.0, 10.0, 10.0, 200.0]);
            b.next_split(false);
        }
        assert_ne!(b.split(), &first);
        assert!(ratio(&b) < 1.15, "{:?}", b.loads(b.split()));
        assert!(b.split().of("n3").any(|r| r.tile == "t3" && r.first_row == 0));
    }

    #[test]
    fn a_node_that_is_down_renders_nothing_and_its_tiles_are_left_out() {
        let mut b = wall(4, 20);
        for (i, c) in [200.0, 10.0, 10.0, 10.0].iter().enumerate() {
            let r = b.split().rects[i].clone();
            b.observe(&r, *c);
        }
        b.next_split(false);
        assert!(b.split().of("n2").next().is_some());
        b.set_nodes(["n0", "n1", "n3"].map(String::from));
        b.next_split(false);
        assert!(b.split().of("n2").next().is_none());
        assert!(b.split().rects.iter().all(|r| r.tile != "t2"));
        assert!(ratio(&b) < 1.15, "{:?}", b.loads(b.split()));
    }

    #[test]
    fn a_held_node_renders_its_own_tiles_whole_and_the_others_balance_among_themselves() {
        let mut b = wall(4, 20);
        for (i, c) in [200.0, 10.0, 10.0, 10.0].iter().enumerate() {
            let r = b.split().rects[i].clone();
            b.observe(&r, *c);
        }
        b.next_split(false);
        assert!(b.split().of("n1").any(|r| r.tile == "t0"), "n1 takes rows of t0");
        b.set_held(["n1".to_string()]);
        b.next_split(false);
        let n1: Vec<&WorkRect> = b.split().of("n1").collect();
        assert_eq!(n1.len(), 1);
        assert_eq!((n1[0].tile.as_str(), n1[0].first_row, n1[0].rows), ("t1", 0, 100));
        assert!(b.split().rects.iter().filter(|r| r.tile == "t1").all(|r| r.renderer == "n1"));
        let loads = b.loads(b.split());
        let others: BTreeMap<String, f64> = loads.into_iter().filter(|(n, _)| n != "n1").collect();
        assert!(slowest_over_mean(&others) < 1.15, "{others:?}");
        // Readmitted, it takes part again.
        b.set_held([]);
        b.next_split(false);
        assert!(b.split().of("n1").any(|r| r.tile == "t0"));
    }

    #[test]
    fn a_claimed_cost_is_held_to_the_pixels_floor_and_to_its_prediction() {
        let mut b = wall(2, 10);
        let r0 = b.split().rects[0].clone();
        // Unmeasured: the floor only.
        assert_eq!(b.clone().observe_claim(&r0, 1e6, 300.0), Some(1e6));
        assert_eq!(b.observe_claim(&r0, 0.0, 300.0), Some(300.0));
        // Measured (300): within 16x of the prediction either way.
        assert_eq!(b.observe_claim(&r0, 1e6, 300.0), Some(4800.0));
        assert_eq!(b.observe_claim(&r0, 1.0, 30.0), Some(300.0));
        assert_eq!(b.observe_claim(&r0, f64::INFINITY, 30.0), Some(4800.0));
        assert_eq!(b.observe_claim(&r0, f64::NAN, 30.0), None);
        assert_eq!(b.observe_claim(&WorkRect { tile: "zz".into(), ..r0.clone() }, 5.0, 1.0), None);
        // The floor stands under a prediction that has fallen below it.
        assert_eq!(b.observe_claim(&r0, 0.0, 1e6), Some(1e6));
    }

    #[test]
    fn bad_weights_and_names_are_refused_and_bad_costs_ignored() {
        let t = || vec![("a".to_string(), "n".to_string(), 10)];
        assert_eq!(Balancer::new(t(), 0, 0.1, 0.5).unwrap_err(), BalanceError::NoBands);
        assert!(matches!(Balancer::new(t(), 4, f64::NAN, 0.5), Err(BalanceError::Weights(..))));
        assert!(matches!(Balancer::new(t(), 4, 0.1, 0.0), Err(BalanceError::Weights(..))));
        let two = vec![("a".to_string(), "n".to_string(), 10), ("a".to_string(), "m".to_string(), 10)];
        assert_eq!(Balancer::new(two, 4, 0.1, 0.5).unwrap_err(), BalanceError::DuplicateTile("a".into()));
        let mut b = Balancer::new(t(), 4, 0.1, 0.5).unwrap();
        let r = b.split().rects[0].clone();
        b.observe(&r, f64::NAN);
        b.observe(&r, -1.0);
        b.observe(&WorkRect { tile: "zz".into(), ..r.clone() }, 5.0);
        assert_eq!(b.loads(b.split())["n"], 0.0);
        // A tile shorter than its bands has one band a row.
        let mut short = Balancer::new(vec![("a".into(), "n".into(), 3)], 32, 0.1, 0.5).unwrap();
        short.observe(&short.split().rects[0].clone(), 3.0);
        assert_eq!(short.loads(short.split())["n"], 3.0);
    }

    #[test]
    fn a_wall_config_gives_each_node_its_own_tiles_first() {
        let toml = "[wall]\nname = \"w\"\n[camera]\neye = [0, -10, 0]\ntarget = [0, 0, 0]\nup = [0, 0, 1]\n\
                    [volume]\nsource = \"procedural:engine\"\n\
                    [[tiles]]\nname = \"a\"\nx = 0\ny = 0\nwidth = 64\nheight = 48\n\
                    [[tiles]]\nname = \"b\"\nx = 64\ny = 0\nwidth = 64\nheight = 48\n\
                    [[nodes]]\nname = \"n0\"\naddress = \"127.0.0.1:7000\"\ntiles = [\"a\"]\n\
                    [[nodes]]\nname = \"n1\"\naddress = \"127.0.0.1:7001\"\ntiles = [\"b\"]\n";
        let config = WallConfig::parse(toml, std::path::Path::new("w.toml")).unwrap();
        let b = Balancer::for_wall(&config);
        let rects: Vec<(&str, u32, &str)> =
            b.split().rects.iter().map(|r| (r.tile.as_str(), r.rows, r.renderer.as_str())).collect();
        assert_eq!(rects, [("a", 48, "n0"), ("b", 48, "n1")]);
        assert_eq!(b.hysteresis(), DEFAULT_HYSTERESIS);
    }
}
