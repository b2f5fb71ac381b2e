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
use super::SimError;
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

/// A tile of a simulated wall.
#[derive(Debug, Clone, PartialEq)]
pub struct SimTile {
    pub name: String,
    pub owner: String,
    pub width: u32,
    pub height: u32,
}

/// A frame's costs: per tile (in the wall's order), per band of [`crate::balance::DEFAULT_BANDS`]
/// (band k: rows `k * height / bands` up to the next), milliseconds.
pub type FrameCosts = Vec<Vec<f64>>;

/// A measured frame's label (`first`, `still1`, `orbit1`, ...) and its costs.
pub type LabelledCosts = (String, FrameCosts);

/// How a run moves pixels and measures.
#[derive(Debug, Clone, Copy)]
pub struct Transfer {
    /// Bytes a moved pixel takes, and the link's bytes per second.
    pub bytes_per_pixel: f64,
    pub bandwidth: f64,
    /// Relative noise of a measured cost (uniform, +-).
    pub noise: f64,
    pub seed: u64,
}

/// The scan's footprint at `angle` degrees: an ellipse about the wall's centre.
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

    /// Per tile of [`grid`], per band, milliseconds.
    fn costs(&self) -> FrameCosts {
        let bands = crate::balance::DEFAULT_BANDS;
        let mut out = Vec::new();
        for r in 0..self.spec.rows {
            for c in 0..self.spec.cols {
                let (x0, y0) = (c * TILE.0, r * TILE.1);
                let band = |k: u32| {
                    let (a, b) = (k * TILE.1 / bands, (k + 1) * TILE.1 / bands);
                    (a..b).map(|y| self.row_ns(y0 + y, x0, x0 + TILE.0)).sum::<f64>() * 1e-6
                };
                out.push((0..bands).map(band).collect());
            }
        }
        out
    }
}

/// The `cols` x `rows` grid of 1080p tiles, tile `t{c}_{r}` on node `n{c}_{r}`, row by row.
pub fn grid(cols: u32, rows: u32) -> Vec<SimTile> {
    (0..rows)
        .flat_map(|r| {
            (0..cols).map(move |c| SimTile {
                name: format!("t{c}_{r}"),
                owner: format!("n{c}_{r}"),
                width: TILE.0,
                height: TILE.1,
            })
        })
        .collect()
}

/// The bands a rectangle of tile `t` covers (whole bands: the split cuts at their edges).
fn bands_of(t: &SimTile, bands: usize, first_row: u32, rows: u32) -> std::ops::Range<usize> {
    let row_of = |k: usize| (k as u64 * u64::from(t.height) / bands as u64) as u32;
    let start = (0..bands).find(|&k| row_of(k) >= first_row).unwrap_or(bands);
    let end = (start..bands).find(|&k| row_of(k) >= first_row + rows).unwrap_or(bands);
    start..end
}

/// One frame of `split`: per node its work (ms), the frame's ms with the transfers, and the
/// pixels moved.
fn frame_of(
    tiles: &[SimTile],
    costs: &FrameCosts,
    split: &Split,
    transfer: &Transfer,
) -> (BTreeMap<String, f64>, f64, u64) {
    let tile =
        |name: &str| tiles.iter().position(|t| t.name == name).expect("the split's tiles are the wall's");
    let rect_ms = |r: &WorkRect| {
        let i = tile(&r.tile);
        costs[i][bands_of(&tiles[i], costs[i].len(), r.first_row, r.rows)].iter().sum::<f64>()
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
        let (foreign, own): (Vec<&WorkRect>, Vec<&WorkRect>) =
            mine.partition(|r| tiles[tile(&r.tile)].owner != node);
        for r in foreign {
            at += rect_ms(r);
            let pixels = u64::from(tiles[tile(&r.tile)].width) * u64::from(r.rows);
            moved += pixels;
            link_free =
                link_free.max(at) + pixels as f64 * transfer.bytes_per_pixel / transfer.bandwidth * 1e3;
            let e = ready.entry(tiles[tile(&r.tile)].owner.clone()).or_insert(0.0);
            *e = e.max(link_free);
        }
        for r in own {
            at += rect_ms(r);
        }
        work.insert(node.to_string(), at);
        let e = ready.entry(node.to_string()).or_insert(0.0);
        *e = e.max(at);
    }
    let frame_ms = ready.values().copied().fold(0.0, f64::max);
    (work, frame_ms, moved)
}

/// Runs the orbit of the synthetic scan (module docs) on a `cols` x `rows` grid.
pub fn run_balance(spec: &BalanceSpec) -> Vec<BalanceFrame> {
    let tiles = grid(spec.cols, spec.rows);
    let frames: Vec<FrameCosts> =
        (0..spec.frames).map(|k| Field::at(*spec, k as f64 * spec.degrees).costs()).collect();
    let transfer = Transfer {
        bytes_per_pixel: spec.bytes_per_pixel,
        bandwidth: spec.bandwidth,
        noise: spec.noise,
        seed: spec.seed,
    };
    run_balance_on(&tiles, &frames, &transfer, spec.degrees == 0.0)
}

/// Runs the split over `frames` of costs of `tiles` ([`crate::balance::DEFAULT_BANDS`] bands a
/// tile): each frame the balancer's split is rendered, the nodes report each rectangle's cost
/// (with noise), the next split follows. `still`: every frame after the first shows the same
/// image.
pub fn run_balance_on(
    tiles: &[SimTile],
    frames: &[FrameCosts],
    transfer: &Transfer,
    still: bool,
) -> Vec<BalanceFrame> {
    let owned = tiles.iter().map(|t| (t.name.clone(), t.owner.clone(), t.height)).collect();
    let mut balancer = Balancer::new(
        owned,
        crate::balance::DEFAULT_BANDS,
        crate::balance::DEFAULT_HYSTERESIS,
        crate::balance::DEFAULT_SMOOTHING,
    )
    .expect("the defaults and distinct tile names are valid");
    let width = tiles.iter().map(|t| t.width).max().unwrap_or(0);
    balancer.set_transfer_per_row(f64::from(width) * transfer.bytes_per_pixel / transfer.bandwidth * 1e3);
    let own = balancer.own_tiles();
    let nodes = tiles.iter().map(|t| &t.owner).collect::<std::collections::BTreeSet<_>>().len() as f64;
    let mut rng = Rng(transfer.seed);
    let mut out = Vec::with_capacity(frames.len());
    for (k, costs) in frames.iter().enumerate() {
        let split = balancer.next_split(k > 0 && still).clone();
        let (own_work, own_ms, _) = frame_of(tiles, costs, &own, transfer);
        let (work, ms, moved) = frame_of(tiles, costs, &split, transfer);
        let total: f64 = own_work.values().sum();
        let transfer_ms = moved as f64 * transfer.bytes_per_pixel / transfer.bandwidth * 1e3;
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
            let i = tiles.iter().position(|t| t.name == r.tile).expect("the split's tiles are the wall's");
            let ms: f64 = costs[i][bands_of(&tiles[i], costs[i].len(), r.first_row, r.rows)].iter().sum();
            balancer.observe(r, ms * (1.0 + transfer.noise * (2.0 * rng.unit() - 1.0)));
        }
    }
    out
}

/// Measured costs (`isowalld bench imbalance --bands 32 --bands-out FILE`): the wall's tiles and,
/// per frame (its label), each band's cost in milliseconds at `ns_per_fetch` a trilinear fetch
/// and `ns_per_pixel` a pixel (the work a pixel costs whether or not its ray hits).
pub fn measured_costs(
    csv: &str,
    ns_per_fetch: f64,
    ns_per_pixel: f64,
) -> Result<(Vec<SimTile>, Vec<LabelledCosts>), SimError> {
    let bad = |line: usize, why: &str| SimError::Config(format!("bands CSV line {}: {why}", line + 1));
    let mut lines = csv.lines().enumerate();
    match lines.next() {
        Some((_, h)) if h.trim() == "frame,tile,node,width,height,band,pixels_full,fetches_full" => {}
        _ => return Err(bad(0, "not the header of `bench imbalance --bands-out`")),
    }
    let mut tiles: Vec<SimTile> = Vec::new();
    let mut frames: Vec<LabelledCosts> = Vec::new();
    for (n, line) in lines.filter(|(_, l)| !l.trim().is_empty()) {
        let f: Vec<&str> = line.split(',').collect();
        let [frame, tile, node, width, height, band, pixels, fetches] = f[..] else {
            return Err(bad(n, "not 8 fields"));
        };
        let num = |v: &str, what: &str| v.trim().parse::<u64>().map_err(|_| bad(n, &format!("{what} `{v}`")));
        let (width, height) = (num(width, "width")? as u32, num(height, "height")? as u32);
        let band = num(band, "band")? as usize;
        let ms = (num(fetches, "fetches")? as f64 * ns_per_fetch
            + num(pixels, "pixels")? as f64 * ns_per_pixel)
            * 1e-6;
        let t = match tiles.iter().position(|t| t.name == tile) {
            Some(t) => t,
            None => {
                tiles.push(SimTile { name: tile.into(), owner: node.into(), width, height });
                tiles.len() - 1
            }
        };
        if frames.last().is_none_or(|(label, _)| label != frame) {
            frames.push((frame.to_string(), Vec::new()));
        }
        let costs = &mut frames.last_mut().expect("pushed").1;
        costs.resize(costs.len().max(t + 1), Vec::new());
        if band != costs[t].len() {
            return Err(bad(n, &format!("band {band} of tile {tile} out of order")));
        }
        costs[t].push(ms);
    }
    let bands = crate::balance::DEFAULT_BANDS as usize;
    for (label, costs) in &frames {
        if costs.len() != tiles.len() || costs.iter().any(|c| c.len() != bands) {
            return Err(SimError::Config(format!("bands CSV frame {label}: every tile needs {bands} bands")));
        }
    }
    Ok((tiles, frames))
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
        let costs = f.costs();
        assert_eq!((costs.len(), costs[0].len()), (4, crate::balance::DEFAULT_BANDS as usize));
        // Tile t0_0's bottom band (near the centre) costs more than its top one.
        assert!(costs[0][31] > 2.0 * costs[0][0], "{:?}", costs[0]);
    }

    #[test]
    fn measured_costs_are_read_per_frame_tile_and_band_and_refused_when_malformed() {
        let mut csv = String::from("frame,tile,node,width,height,band,pixels_full,fetches_full\n");
        for frame in ["orbit1", "orbit2"] {
            for (tile, node) in [("a", "n0"), ("b", "n1")] {
                for band in 0..32 {
                    csv += &format!("{frame},{tile},{node},64,64,{band},128,1000\n");
                }
            }
        }
        let (tiles, frames) = measured_costs(&csv, 1.0, 2.0).unwrap();
        assert_eq!(tiles[1], SimTile { name: "b".into(), owner: "n1".into(), width: 64, height: 64 });
        assert_eq!(frames.len(), 2);
        assert_eq!(frames[1].0, "orbit2");
        assert!((frames[0].1[1][31] - (1000.0 + 256.0) * 1e-6).abs() < 1e-12);
        assert!(measured_costs("x,y\n", 1.0, 1.0).is_err());
        let short: String = csv.lines().take(10).collect::<Vec<_>>().join("\n");
        assert!(measured_costs(&short, 1.0, 1.0).is_err(), "a tile with 9 bands");
        let garbled = csv.replace("orbit2,b,n1,64,64,3,128,1000", "orbit2,b,n1,64,64,3,lots,1000");
        let e = measured_costs(&garbled, 1.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("pixels `lots`"), "{e}");
    }

    #[test]
    fn every_node_its_own_tiles_moves_nothing_and_is_as_slow_as_the_busiest() {
        let tiles = grid(2, 2);
        let costs = Field::at(BalanceSpec::new(2, 2), 0.0).costs();
        let b = Balancer::new(
            tiles.iter().map(|t| (t.name.clone(), t.owner.clone(), t.height)).collect(),
            32,
            0.05,
            0.5,
        )
        .unwrap();
        let transfer = Transfer { bytes_per_pixel: 3.0, bandwidth: 1e9, noise: 0.0, seed: 1 };
        let (work, ms, moved) = frame_of(&tiles, &costs, &b.own_tiles(), &transfer);
        assert_eq!(moved, 0);
        assert_eq!(ms, work.values().copied().fold(0.0, f64::max));
        assert_eq!(bands_of(&tiles[0], 32, 0, 1080), 0..32);
        assert_eq!(bands_of(&tiles[0], 32, 33, 101), 1..4);
    }
}
