//! Load-balanced screen space at scale: a wall of `cols` x `rows` tiles of 1920x1080, one node a
//! tile, a scan framed in the middle, and the model's [`Balancer`] cutting each frame from the
//! costs the nodes report.
//!
//! - The cost field: a pixel costs `sky_ns` where the rays miss and `surface_ns` where they hit
//!   (the AO rays); the scan's footprint is an ellipse about the wall's centre, `radius` of the
//!   wall's height tall, whose width turns with the orbit (`cos` of the angle, an elongated
//!   head seen from the side and from the front). A rectangle's cost is the sum over its rows.
//! - Each frame every node renders the split's rectangles it was given, other nodes' first: each
//!   is sent to its tile's owner as soon as it is rendered (`bytes_per_pixel` over `bandwidth`,
//!   one send after another), while the node goes on with the rest. A tile's owner is ready when
//!   its own work is done and its rectangles have arrived; the frame takes as long as the last
//!   owner. The measured costs carry seeded noise; the balancer knows the link's cost of a row.
//! - The ideal: all work over the nodes, plus the split's transfer spread over them.

use std::collections::BTreeMap;

use super::lan::Rng;
use crate::balance::{slowest_over_mean, Balancer, Split, WorkRect};

/// Tile size of the simulated walls.
pub const TILE: (u32, u32) = (1920, 1080);

#[derive(Debug, Clone, Copy)]
pub struct BalanceSpec {
    pub cols: u32,
    pub rows: u32,
    pub frames: u32,
    /// Degrees the scan turns a frame (0: still).
    pub degrees: f64,
    /// Cost of a pixel whose ray misses / hits, nanoseconds.
    pub sky_ns: f64,
    pub surface_ns: f64,
    /// The footprint's half height over the wall's height.
    pub radius: f64,
    /// Bytes a moved pixel takes, and the link's bytes per second.
    pub bytes_per_pixel: f64,
    pub bandwidth: f64,
    /// Relative noise of a measured cost (uniform, +-).
    pub noise: f64,
    pub seed: u64,
}

impl BalanceSpec {
    /// A `cols` x `rows` wall orbiting at 1 degree a frame for 60 frames: sky 2 ns and surface 40
    /// ns a pixel (a centre tile's frame near 60 ms), 3-byte pixels over 10 Gbit/s, 5% noise.
    pub fn new(cols: u32, rows: u32) -> BalanceSpec {
        BalanceSpec {
            cols,
            rows,
            frames: 60,
            degrees: 1.0,
            sky_ns: 2.0,
            surface_ns: 40.0,
            radius: 0.35,
            bytes_per_pixel: 3.0,
            bandwidth: 1.25e9,
            noise: 0.05,
            seed: 1,
        }
    }
}

/// Per frame of a run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BalanceFrame {
    /// The slowest node's work over the mean: every node its own tiles / the split.
    pub unbalanced: f64,
    pub balanced: f64,
    /// The frame's time, ms: every node its own tiles / the split (with its transfer) / ideal.
    pub unbalanced_ms: f64,
    pub balanced_ms: f64,
    pub ideal_ms: f64,
    /// Pixels the split moves between nodes.
    pub moved_pixels: u64,
}

/// The scan's footprint at `angle` degrees: per tile row, the columns [a, b) of the wall it hits.
struct Field {
    spec: BalanceSpec,
    centre: (f64, f64),
    half: (f64, f64),
}

impl Field {
    fn at(spec: BalanceSpec, angle: f64) -> Field {
        let (w, h) = ((spec.cols * TILE.0) as f64, (spec.rows * TILE.1) as f64);
        let ry = spec.radius * h;
        let rx = ry * (0.75 + 0.25 * angle.to_radians().cos().abs());
        Field { spec, centre: (w / 2.0, h / 2.0), half: (rx, ry) }
    }

    /// Nanoseconds to render wall row `y`'s columns [x0, x1).
    fn row_ns(&self, y: u32, x0: u32, x1: u32) -> f64 {
        let dy = (y as f64 + 0.5 - self.centre.1) / self.half.1;
        let hit = if dy.abs() < 1.0 {
            let dx = self.half.0 * (1.0 - dy * dy).sqrt();
            let (a, b) = ((self.centre.0 - dx).max(x0 as f64), (self.centre.0 + dx).min(x1 as f64));
            (b - a).max(0.0)
        } else {
            0.0
        };
        let all = (x1 - x0) as f64;
        self.spec.sky_ns * (all - hit) + self.spec.surface_ns * hit
    }

    /// Milliseconds to render a rectangle of tile `(c, r)`.
    fn rect_ms(&self, (c, r): (u32, u32), first_row: u32, rows: u32) -> f64 {
        let (x0, y0) = (c * TILE.0, r * TILE.1);
        (first_row..first_row + rows).map(|y| self.row_ns(y0 + y, x0, x0 + TILE.0)).sum::<f64>() * 1e-6
    }
}

fn tile_name(c: u32, r: u32) -> String {
    format!("t{c}_{r}")
}

fn node_name(c: u32, r: u32) -> String {
    format!("n{c}_{r}")
}

fn tile_at(name: &str) -> (u32, u32) {
    let (c, r) = name[1..].split_once('_').expect("tile names are t{c}_{r}");
    (c.parse().expect("a column"), r.parse().expect("a row"))
}

/// One frame of `split` over `field`: per node its work (ms), the frame's ms with the
/// transfers, and the pixels moved.
fn frame_of(field: &Field, split: &Split) -> (BTreeMap<String, f64>, f64, u64) {
    let spec = field.spec;
    let owner_of = |r: &WorkRect| {
        let (c, row) = tile_at(&r.tile);
        node_name(c, row)
    };
    let mut work: BTreeMap<String, f64> = BTreeMap::new();
    let mut ready: BTreeMap<String, f64> = BTreeMap::new();
    let mut moved = 0u64;
    // Per renderer: other nodes' rectangles first, each sent once rendered, sends in a queue.
    let renderers: std::collections::BTreeSet<&str> =
        split.rects.iter().map(|r| r.renderer.as_str()).collect();
    for node in renderers {
        let (mut at, mut link_free) = (0.0f64, 0.0f64);
        let mine = split.rects.iter().filter(|r| r.renderer == node);
        let (foreign, own): (Vec<&WorkRect>, Vec<&WorkRect>) = mine.partition(|r| owner_of(r) != node);
        for r in foreign {
            at += field.rect_ms(tile_at(&r.tile), r.first_row, r.rows);
            let pixels = u64::from(TILE.0) * u64::from(r.rows);
            moved += pixels;
            link_free = link_free.max(at) + pixels as f64 * spec.bytes_per_pixel / spec.bandwidth * 1e3;
            let e = ready.entry(owner_of(r)).or_insert(0.0);
            *e = e.max(link_free);
        }
        for r in own {
            at += field.rect_ms(tile_at(&r.tile), r.first_row, r.rows);
        }
        work.insert(node.to_string(), at);
        let e = ready.entry(node.to_string()).or_insert(0.0);
        *e = e.max(at);
    }
    let frame_ms = ready.values().copied().fold(0.0, f64::max);
    (work, frame_ms, moved)
}

/// Runs the orbit (module docs).
pub fn run_balance(spec: &BalanceSpec) -> Vec<BalanceFrame> {
    let tiles = (0..spec.rows)
        .flat_map(|r| (0..spec.cols).map(move |c| (tile_name(c, r), node_name(c, r), TILE.1)))
        .collect();
    let mut balancer = Balancer::new(
        tiles,
        crate::balance::DEFAULT_BANDS,
        crate::balance::DEFAULT_HYSTERESIS,
        crate::balance::DEFAULT_SMOOTHING,
    )
    .expect("the defaults and distinct tile names are valid");
    balancer.set_transfer_per_row(f64::from(TILE.0) * spec.bytes_per_pixel / spec.bandwidth * 1e3);
    let own = balancer.own_tiles();
    let nodes = (spec.cols * spec.rows) as f64;
    let mut rng = Rng(spec.seed);
    let mut out = Vec::with_capacity(spec.frames as usize);
    for k in 0..spec.frames {
        let field = Field::at(*spec, k as f64 * spec.degrees);
        let split = balancer.next_split(k > 0 && spec.degrees == 0.0).clone();
        let (own_work, own_ms, _) = frame_of(&field, &own);
        let (work, ms, moved) = frame_of(&field, &split);
        let total: f64 = own_work.values().sum();
        let transfer_ms = moved as f64 * spec.bytes_per_pixel / spec.bandwidth * 1e3;
        out.push(BalanceFrame {
            unbalanced: slowest_over_mean(&own_work),
            balanced: slowest_over_mean(&work),
            unbalanced_ms: own_ms,
            balanced_ms: ms,
            ideal_ms: (total + transfer_ms) / nodes,
            moved_pixels: moved,
        });
        // The nodes report what each rectangle took.
        for r in &split.rects {
            let measured = field.rect_ms(tile_at(&r.tile), r.first_row, r.rows)
                * (1.0 + spec.noise * (2.0 * rng.unit() - 1.0));
            balancer.observe(r, measured);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_field_costs_more_where_the_scan_is() {
        let spec = BalanceSpec::new(2, 2);
        let f = Field::at(spec, 0.0);
        // The wall's centre row through the middle: hit across the footprint's width.
        let centre = f.row_ns(TILE.1, 0, 2 * TILE.0);
        let top = f.row_ns(0, 0, 2 * TILE.0);
        assert!((top - 2.0 * 3840.0).abs() < 1e-9, "{top}");
        assert!(centre > 5.0 * top, "{centre} {top}");
        assert_eq!(tile_at(&tile_name(3, 12)), (3, 12));
    }

    #[test]
    fn every_node_its_own_tiles_moves_nothing_and_is_as_slow_as_the_busiest() {
        let spec = BalanceSpec::new(2, 2);
        let b = Balancer::new(
            (0..2).flat_map(|r| (0..2).map(move |c| (tile_name(c, r), node_name(c, r), TILE.1))).collect(),
            32,
            0.05,
            0.5,
        )
        .unwrap();
        let f = Field::at(spec, 0.0);
        let (work, ms, moved) = frame_of(&f, &b.own_tiles());
        assert_eq!(moved, 0);
        assert_eq!(ms, work.values().copied().fold(0.0, f64::max));
    }
}
