//! Object space (DESIGN.md "Distribution"): the volume cut into one brick per node, each with a
//! halo, all computed from the same inputs by every node (deterministic, no I/O).
//!
//! - **Split**: a k-d split of the block grid (blocks of [`Occupancy::block`] cells, the volume
//!   crate's `BlockMinMax`). A box of blocks that must hold k bricks is cut along its longest axis
//!   in world units (among the axes at least two blocks long; the lowest axis on a tie) at the block
//!   plane that best gives the first half floor(k/2)/k of the box's *occupied* blocks (blocks whose
//!   max reaches the iso value: where the object is, so where rendering costs), the plane nearest the
//!   middle on a tie; without occupied blocks, by block count. The halves are split recursively;
//!   bricks are numbered left (lower) half first, and brick i goes to the wall's i-th node.
//! - **Ownership**: a brick owns the closed box of its samples; neighbours share the cut plane's
//!   samples. A primary ray's march step belongs to the brick that owns its starting point (half-open
//!   at the cut, see [`Brick::owned_planes`]), so exactly one brick finds each hit.
//! - **Halo**: the samples a brick reads beyond its box, per axis: `ceil((R + eps + step) / s) + 2`
//!   voxels of that axis' spacing s, with R the AO radius, `eps` how far off the surface the AO
//!   rays start (DESIGN.md "AO": `o = p + eps * Ng`, eps = 0.01 of the smallest spacing) and `step`
//!   the primary march step (the step that crosses the cut reads up to one step beyond it, and a
//!   hit found there casts its AO rays from there), plus 2 for the gradient stencil (central
//!   differences one voxel away, whose trilinear cell reaches one more sample; Ng reads only p's
//!   own cell, inside that). Then normals and AO near a cut read exactly the
//!   samples a single-node render reads. An unbounded radius has no halo: object space refuses it
//!   ([`BrickError::UnboundedRadius`]), and so the 2008 `seed` AO method, which marches 0.9 of the box.

use crate::camera::{Rect, View};
use crate::render_state::{AoMethod, RenderSettings};
use glam::DVec3;

/// Samples beyond the AO reach that a brick reads: the gradient stencil (1 voxel) and the
/// trilinear cell it falls in (1 more).
pub const GRADIENT_STENCIL: usize = 2;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BrickError {
    #[error("object space needs a bounded AO radius (the halo is as wide as the radius); `unbounded` reaches the whole box: give `ao_radius` in world units")]
    UnboundedRadius,
    #[error("object space cannot use the `seed` AO method: it marches 0.9 of the box from each hit, far beyond any halo; use `ours`")]
    SeedMethod,
    #[error("the AO radius {radius} reaches beyond this node's halo ({halo} world units along the thinnest axis); the halo was sized at start from the config's radius: restart the wall with the larger `ao_radius`")]
    BeyondHalo { radius: f64, halo: f64 },
    #[error("cannot cut {blocks} block(s) of the volume into {bricks} bricks: fewer blocks than nodes")]
    TooFewBlocks { blocks: usize, bricks: usize },
    #[error("the occupancy grid has {got} blocks, but {counts:?} need {want}")]
    BadGrid { counts: [usize; 3], want: usize, got: usize },
    #[error("no bricks: an object-space wall needs at least one node")]
    NoBricks,
}

/// Which blocks hold part of the object (max >= iso), x fastest; blocks of `block` cells as the
/// volume crate's `BlockMinMax`.
#[derive(Clone, Debug, PartialEq)]
pub struct Occupancy {
    pub block: usize,
    pub counts: [usize; 3],
    pub occupied: Vec<bool>,
}

impl Occupancy {
    /// From per-block (min, max) at `iso`.
    pub fn from_minmax(block: usize, counts: [usize; 3], minmax: &[[f32; 2]], iso: f64) -> Occupancy {
        Occupancy { block, counts, occupied: minmax.iter().map(|m| m[1] as f64 >= iso).collect() }
    }

    fn at(&self, b: [usize; 3]) -> bool {
        self.occupied[b[0] + self.counts[0] * (b[1] + self.counts[1] * b[2])]
    }
}

/// One brick: the samples it owns (inclusive, per axis) and the blocks they make up.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Brick {
    pub index: usize,
    /// Owned samples `lo[a] ..= hi[a]` (neighbours share the cut plane's samples).
    pub lo: [usize; 3],
    pub hi: [usize; 3],
    /// Occupied blocks in the brick (what the split balances).
    pub occupied_blocks: usize,
    /// Blocks in the brick.
    pub blocks: usize,
}

impl Brick {
    /// The samples the brick holds: its own and the halo, clipped to the volume.
    pub fn data_range(&self, halo: [usize; 3], dims: [usize; 3]) -> ([usize; 3], [usize; 3]) {
        let lo = [0, 1, 2].map(|a| self.lo[a].saturating_sub(halo[a]));
        let hi = [0, 1, 2].map(|a| (self.hi[a] + halo[a]).min(dims[a] - 1));
        (lo, hi)
    }

    /// Samples in the brick and halo.
    pub fn data_samples(&self, halo: [usize; 3], dims: [usize; 3]) -> usize {
        let (lo, hi) = self.data_range(halo, dims);
        (0..3).map(|a| hi[a] + 1 - lo[a]).product()
    }

    /// The world planes bounding what the brick owns: a point q (clamped to the volume box) is the
    /// brick's when `min <= q < max` on every axis. Faces on the volume's own faces are open
    /// (-inf, +inf as +-1e30), so the bricks cover the whole box and never overlap.
    pub fn owned_planes(&self, dims: [usize; 3], origin: DVec3, spacing: DVec3) -> (DVec3, DVec3) {
        let mut min = DVec3::splat(-1e30);
        let mut max = DVec3::splat(1e30);
        for a in 0..3 {
            if self.lo[a] > 0 {
                min[a] = origin[a] + self.lo[a] as f64 * spacing[a];
            }
            if self.hi[a] < dims[a] - 1 {
                max[a] = origin[a] + self.hi[a] as f64 * spacing[a];
            }
        }
        (min, max)
    }

    /// The world box of the owned samples.
    pub fn owned_box(&self, origin: DVec3, spacing: DVec3) -> (DVec3, DVec3) {
        let p = |i: [usize; 3]| origin + spacing * DVec3::new(i[0] as f64, i[1] as f64, i[2] as f64);
        (p(self.lo), p(self.hi))
    }
}

/// Splits a volume of `dims` samples (spacing `spacing`) into `n` bricks balanced by `occ`.
pub fn split(occ: &Occupancy, dims: [usize; 3], spacing: DVec3, n: usize) -> Result<Vec<Brick>, BrickError> {
    if n == 0 {
        return Err(BrickError::NoBricks);
    }
    let want: usize = occ.counts.iter().product();
    if occ.occupied.len() != want || dims.contains(&0) {
        return Err(BrickError::BadGrid { counts: occ.counts, want, got: occ.occupied.len() });
    }
    let total: usize = occ.counts.iter().product();
    if total < n {
        return Err(BrickError::TooFewBlocks { blocks: total, bricks: n });
    }
    let by_count = !occ.occupied.iter().any(|&o| o);
    let mut out = Vec::with_capacity(n);
    split_box(occ, dims, spacing, by_count, [0; 3], occ.counts, n, &mut out)?;
    Ok(out)
}

#[allow(clippy::too_many_arguments)]
fn split_box(
    occ: &Occupancy,
    dims: [usize; 3],
    spacing: DVec3,
    by_count: bool,
    b0: [usize; 3],
    b1: [usize; 3],
    k: usize,
    out: &mut Vec<Brick>,
) -> Result<(), BrickError> {
    let weight = |b: [usize; 3]| usize::from(by_count || occ.at(b));
    let blocks: usize = (0..3).map(|a| b1[a] - b0[a]).product();
    if k == 1 {
        let mut occupied = 0;
        for z in b0[2]..b1[2] {
            for y in b0[1]..b1[1] {
                for x in b0[0]..b1[0] {
                    occupied += usize::from(occ.at([x, y, z]));
                }
            }
        }
        let last = dims.map(|n| n.max(1) - 1);
        out.push(Brick {
            index: out.len(),
            lo: [0, 1, 2].map(|a| (b0[a] * occ.block).min(last[a])),
            hi: [0, 1, 2].map(|a| (b1[a] * occ.block).min(last[a])),
            occupied_blocks: occupied,
            blocks,
        });
        return Ok(());
    }
    if blocks < k {
        return Err(BrickError::TooFewBlocks { blocks, bricks: k });
    }
    // The longest axis (world units) that can be cut.
    let extent = |a: usize| {
        let lo = (b0[a] * occ.block).min(dims[a] - 1);
        let hi = (b1[a] * occ.block).min(dims[a] - 1);
        (hi - lo) as f64 * spacing[a]
    };
    let axis = (0..3)
        .filter(|&a| b1[a] - b0[a] >= 2)
        .fold(None, |best: Option<usize>, a| match best {
            Some(b) if extent(b) >= extent(a) => Some(b),
            _ => Some(a),
        })
        .ok_or(BrickError::TooFewBlocks { blocks, bricks: k })?;
    // Weight of each layer of blocks along the axis.
    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
    let layers: Vec<usize> = (b0[axis]..b1[axis])
        .map(|l| {
            let mut w = 0;
            for p in b0[u]..b1[u] {
                for q in b0[v]..b1[v] {
                    let mut b = [0; 3];
                    b[axis] = l;
                    b[u] = p;
                    b[v] = q;
                    w += weight(b);
                }
            }
            w
        })
        .collect();
    let total: usize = layers.iter().sum();
    let k_left = k / 2;
    let cross = blocks / (b1[axis] - b0[axis]);
    let len = b1[axis] - b0[axis];
    let mid2 = len; // twice the middle, in layers
    let mut best: Option<(usize, usize, usize)> = None; // (imbalance, distance from middle, cut)
    let mut left = 0usize;
    for c in 1..len {
        left += layers[c - 1];
        // Each side needs at least as many blocks as bricks.
        if c * cross < k_left || (len - c) * cross < k - k_left {
            continue;
        }
        let imbalance = (left * k).abs_diff(total * k_left);
        let dist = (2 * c).abs_diff(mid2);
        let cand = (imbalance, dist, c);
        if best.is_none_or(|b| (cand.0, cand.1) < (b.0, b.1)) {
            best = Some(cand);
        }
    }
    let (_, _, c) = best.ok_or(BrickError::TooFewBlocks { blocks, bricks: k })?;
    let mut left_hi = b1;
    left_hi[axis] = b0[axis] + c;
    let mut right_lo = b0;
    right_lo[axis] = b0[axis] + c;
    split_box(occ, dims, spacing, by_count, b0, left_hi, k_left, out)?;
    split_box(occ, dims, spacing, by_count, right_lo, b1, k - k_left, out)
}

/// The part of `view`'s rectangle where a box can show: the bounding rectangle of its eight corners
/// projected (pixel centres, the DESIGN.md camera), widened by a pixel for rounding, clipped to the
/// rectangle; the whole rectangle where a corner is at or behind the eye's plane; `None` where the
/// bounding rectangle misses the view's.
pub fn covered_rect(view: &View, box_min: DVec3, box_max: DVec3) -> Option<Rect> {
    let b = view.camera.basis();
    let (w, h) = (view.full.0 as f64, view.full.1 as f64);
    let tan_x = b.tan_half_fov * w / h;
    let (mut x0, mut x1, mut y0, mut y1) =
        (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for i in 0..8 {
        let c = DVec3::new(
            if i & 1 == 0 { box_min.x } else { box_max.x },
            if i & 2 == 0 { box_min.y } else { box_max.y },
            if i & 4 == 0 { box_min.z } else { box_max.z },
        ) - view.camera.eye;
        let z = c.dot(b.forward);
        if z <= 1e-9 * c.length().max(1e-300) {
            return Some(view.rect);
        }
        // sx = ((px + 0.5) / W * 2 - 1) * tan_x  <=>  px = (sx / tan_x + 1) / 2 * W - 0.5
        let px = (c.dot(b.right) / z / tan_x + 1.0) * 0.5 * w - 0.5;
        let py = (1.0 - c.dot(b.up) / z / b.tan_half_fov) * 0.5 * h - 0.5;
        x0 = x0.min(px);
        x1 = x1.max(px);
        y0 = y0.min(py);
        y1 = y1.max(py);
    }
    let win = view.rect;
    let clip = |lo: f64, hi: f64, start: u32, len: u32| -> Option<(u32, u32)> {
        let lo = (lo.floor() - 1.0).max(start as f64);
        let hi = (hi.ceil() + 1.0).min((start + len) as f64 - 1.0);
        (hi >= lo).then(|| (lo as u32, (hi - lo) as u32 + 1))
    };
    let (x, width) = clip(x0, x1, win.x, win.width)?;
    let (y, height) = clip(y0, y1, win.y, win.height)?;
    Some(Rect { x, y, width, height })
}

/// The AO reach a brick's halo must cover for `settings`: R plus eps (the rays' start off the
/// surface), in world units. Errors where object space cannot bound it.
pub fn ao_reach(settings: &RenderSettings, spacing: DVec3) -> Result<f64, BrickError> {
    if settings.ao.method == AoMethod::Seed {
        return Err(BrickError::SeedMethod);
    }
    let r = settings.ao.radius_world(spacing).ok_or(BrickError::UnboundedRadius)?;
    Ok(r + settings.ao.offset_voxels * spacing.min_element())
}

/// The halo (samples per axis) for `settings` on a volume of `spacing` (module notes).
pub fn halo_voxels(settings: &RenderSettings, spacing: DVec3) -> Result<[usize; 3], BrickError> {
    let reach = ao_reach(settings, spacing)?;
    // The hit lies up to one primary step past the owned box (the step that crosses the cut).
    let step = settings.step_voxels * spacing.min_element();
    let w = reach + step;
    Ok([0, 1, 2].map(|a| (w / spacing[a] - 1e-9).ceil().max(0.0) as usize + GRADIENT_STENCIL))
}

/// Checks at run time that a frame's settings stay within the halo the brick was read with.
pub fn check_within_halo(
    settings: &RenderSettings,
    spacing: DVec3,
    halo: [usize; 3],
) -> Result<(), BrickError> {
    let need = halo_voxels(settings, spacing)?;
    if (0..3).any(|a| need[a] > halo[a]) {
        let halo_world =
            (0..3).map(|a| (halo[a] - GRADIENT_STENCIL) as f64 * spacing[a]).fold(f64::INFINITY, f64::min);
        return Err(BrickError::BeyondHalo { radius: ao_reach(settings, spacing)?, halo: halo_world });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render_state::AoRadius;

    fn occ_all(counts: [usize; 3], f: impl Fn([usize; 3]) -> bool) -> Occupancy {
        let mut occupied = Vec::new();
        for z in 0..counts[2] {
            for y in 0..counts[1] {
                for x in 0..counts[0] {
                    occupied.push(f([x, y, z]));
                }
            }
        }
        Occupancy { block: 8, counts, occupied }
    }

    /// Every sample is owned (as a half-open cell range) by exactly one brick.
    fn check_partition(bricks: &[Brick], dims: [usize; 3]) {
        let cells = dims.map(|n| n - 1);
        let mut owner = vec![usize::MAX; cells.iter().product()];
        for b in bricks {
            for z in b.lo[2]..b.hi[2] {
                for y in b.lo[1]..b.hi[1] {
                    for x in b.lo[0]..b.hi[0] {
                        let i = x + cells[0] * (y + cells[1] * z);
                        assert_eq!(owner[i], usize::MAX, "cell ({x},{y},{z}) in two bricks");
                        owner[i] = b.index;
                    }
                }
            }
        }
        assert!(owner.iter().all(|&o| o != usize::MAX), "a cell in no brick");
    }

    #[test]
    fn splits_along_the_longest_axis_balanced_by_occupied_blocks() {
        // 64 x 32 x 32 samples; the object fills only x >= 32: two bricks cut x at 48, not 32.
        let dims = [65, 33, 33];
        let occ = occ_all([8, 4, 4], |b| b[0] >= 4);
        let bricks = split(&occ, dims, DVec3::ONE, 2).unwrap();
        assert_eq!(bricks.len(), 2);
        assert_eq!(bricks[0].hi, [48, 32, 32]);
        assert_eq!(bricks[1].lo, [48, 0, 0]);
        assert_eq!(bricks[0].occupied_blocks, bricks[1].occupied_blocks);
        check_partition(&bricks, dims);
        // By voxel count it would have cut at 32: the occupancy moved the cut.
        let even = split(&occ_all([8, 4, 4], |_| false), dims, DVec3::ONE, 2).unwrap();
        assert_eq!(even[0].hi[0], 32);
    }

    #[test]
    fn four_and_three_bricks_cover_the_volume_once_and_are_deterministic() {
        let dims = [64, 64, 40];
        let occ = occ_all([8, 8, 5], |b| (b[0] + 2 * b[1] + b[2]) % 3 == 0);
        for n in [1, 2, 3, 4, 7] {
            let a = split(&occ, dims, DVec3::new(1.0, 1.0, 1.5), n).unwrap();
            assert_eq!(a.len(), n);
            check_partition(&a, dims);
            assert_eq!(a, split(&occ, dims, DVec3::new(1.0, 1.0, 1.5), n).unwrap());
            let total: usize = a.iter().map(|b| b.occupied_blocks).sum();
            let max = a.iter().map(|b| b.occupied_blocks).max().unwrap();
            // Balanced within a layer of blocks of the ideal share.
            assert!(max as f64 <= total as f64 / n as f64 + 64.0, "{n}: {a:?}");
        }
        // Anisotropic spacing decides the longest axis: z is 39 * 4 = 156 world units long.
        let b = split(&occ, dims, DVec3::new(1.0, 1.0, 4.0), 2).unwrap();
        assert!(b[0].hi[2] < 39 && b[0].hi[0] == 63, "{b:?}");
    }

    #[test]
    fn too_many_bricks_or_a_bad_grid_are_errors() {
        let occ = occ_all([1, 1, 2], |_| true);
        assert_eq!(
            split(&occ, [9, 9, 17], DVec3::ONE, 3),
            Err(BrickError::TooFewBlocks { blocks: 2, bricks: 3 })
        );
        assert!(split(&occ, [9, 9, 17], DVec3::ONE, 2).is_ok());
        let bad = Occupancy { block: 8, counts: [2, 2, 2], occupied: vec![true; 7] };
        assert!(matches!(split(&bad, [17, 17, 17], DVec3::ONE, 2), Err(BrickError::BadGrid { .. })));
        assert_eq!(split(&occ, [9, 9, 17], DVec3::ONE, 0), Err(BrickError::NoBricks));
    }

    #[test]
    fn halo_covers_the_ao_reach_plus_the_stencil_and_refuses_unbounded() {
        let mut s = RenderSettings::new(0.0);
        s.ao.radius = AoRadius::World(6.0);
        // (6 + eps 0.01 + step 0.5) / 1 -> 7, + 2; z spacing 2: ceil(3.255) = 4, + 2.
        assert!((ao_reach(&s, DVec3::new(1.0, 1.0, 2.0)).unwrap() - 6.01).abs() < 1e-12);
        assert_eq!(halo_voxels(&s, DVec3::new(1.0, 1.0, 2.0)).unwrap(), [9, 9, 6]);
        let halo = halo_voxels(&s, DVec3::ONE).unwrap();
        assert!(check_within_halo(&s, DVec3::ONE, halo).is_ok());
        s.ao.radius = AoRadius::World(8.0);
        assert!(matches!(check_within_halo(&s, DVec3::ONE, halo), Err(BrickError::BeyondHalo { .. })));
        s.ao.radius = AoRadius::Unbounded;
        let e = halo_voxels(&s, DVec3::ONE).unwrap_err();
        assert_eq!(e, BrickError::UnboundedRadius);
        assert!(e.to_string().contains("unbounded"));
        s.ao.radius = AoRadius::Default;
        s.ao.method = AoMethod::Seed;
        assert_eq!(halo_voxels(&s, DVec3::ONE), Err(BrickError::SeedMethod));
    }

    #[test]
    fn covered_rect_holds_every_pixel_whose_ray_meets_the_box() {
        use crate::camera::Camera;
        let cam = Camera {
            eye: DVec3::new(60.0, -50.0, 40.0),
            target: DVec3::new(16.0, 16.0, 16.0),
            up: DVec3::Z,
            fov_y_deg: 35.0,
        };
        let full = (96, 64);
        let tile = Rect { x: 48, y: 0, width: 48, height: 64 };
        let view = View { camera: cam, full, rect: tile };
        let (lo, hi) = (DVec3::new(16.0, 0.0, 0.0), DVec3::new(32.0, 32.0, 32.0));
        let r = covered_rect(&view, lo, hi).expect("the box shows in the tile");
        assert!(r.x >= tile.x && r.x + r.width <= tile.x + tile.width && r.width < tile.width);
        let basis = cam.basis();
        let mut inside = 0;
        for py in 0..full.1 {
            for px in tile.x..tile.x + tile.width {
                let d = view.ray_dir_full(&basis, px, py);
                let inv = d.recip();
                let (ta, tb) = ((lo - cam.eye) * inv, (hi - cam.eye) * inv);
                let (t0, t1) = (ta.min(tb).max_element(), ta.max(tb).min_element());
                if t1 >= t0.max(0.0) {
                    inside += 1;
                    let in_rect = px >= r.x && px < r.x + r.width && py >= r.y && py < r.y + r.height;
                    assert!(in_rect, "pixel ({px}, {py}) sees the box outside {r:?}");
                }
            }
        }
        assert!(inside > 100);
        // A box behind the camera's view of this tile misses it; one around the eye covers all.
        let left = View { rect: Rect { x: 0, y: 0, width: 8, height: 8 }, ..view };
        assert_eq!(covered_rect(&left, lo, hi), None);
        assert_eq!(covered_rect(&view, cam.eye - DVec3::ONE, cam.eye + DVec3::ONE), Some(tile));
    }

    #[test]
    fn owned_planes_are_open_on_the_volume_faces_and_shared_at_cuts() {
        let dims = [33, 17, 17];
        let occ = occ_all([4, 2, 2], |_| true);
        let b = split(&occ, dims, DVec3::ONE, 2).unwrap();
        let (min0, max0) = b[0].owned_planes(dims, DVec3::ZERO, DVec3::ONE);
        let (min1, max1) = b[1].owned_planes(dims, DVec3::ZERO, DVec3::ONE);
        assert_eq!(max0.x, 16.0);
        assert_eq!(min1.x, 16.0);
        assert!(min0.x < -1e29 && max1.x > 1e29 && min0.y < -1e29 && max0.z > 1e29);
        assert_eq!(b[0].data_range([3, 3, 3], dims), ([0, 0, 0], [19, 16, 16]));
        assert_eq!(b[1].data_range([3, 3, 3], dims), ([13, 0, 0], [32, 16, 16]));
    }
}
