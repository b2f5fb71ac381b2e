//! Temporal reprojection of a tile's running sums, and its CPU twin [`reproject`]: the definition
//! `Kernel::Reproject` (shaders/reproject.wgsl, gpu/reproject.rs) follows.
//!
//! When a frame differs from the previous one only by the camera, the occlusion and IBL terms of a
//! surface point do not change (they are view-independent), so a pixel may start from the sums of
//! the previous frame's pixel that saw the same point instead of from nothing:
//! - the new hit p = eye + depth * dir is projected into the previous frame's camera; the four
//!   previous pixels around the projection (bilinear taps) are the candidates;
//! - a tap counts where it lies in the previous rectangle, had a hit, p lies within
//!   [`Rule::plane_tolerance`] footprints of its tangent plane (footprint = depth * 2 tan(fov_y /
//!   2) / H, the world size of a pixel there: a surface that was hidden behind another, or newly
//!   revealed, lies far from it), the two normals agree (dot >= [`Rule::normal_agreement`]) and
//!   both frames see the same side of the surface;
//! - the carried sums are the counting taps' blended by their bilinear weights, not renormalized
//!   ([`Rule::accepted_share`]): where taps are rejected (next to another surface) the history
//!   keeps only its accepted share, weight included, so fresh samples count more there. Renormalized
//!   to 1, an edge pixel's history kept its whole weight while drifting a little each frame: that
//!   bias was 95% of the engine's squared history error, and dropping the rejected share lowered
//!   the moving error by 16% on the engine and 18% on the MRI (docs/bench/history/orbit-history-lavapipe.md).
//!   Bilinear, not the nearest pixel: with the nearest pixel a history moving less than half a
//!   pixel a frame stays where it is on the screen while the surface moves on (measured with
//!   `isowalld bench orbit`: on the engine at 1 degree a frame the occlusion error grew over the
//!   frames past a restart's). [`Rule::nearest`] takes the one previous pixel the projection
//!   falls in instead, for measurements;
//! - the carried sums are scaled to an age of at most [`Rule::max_age`] frames: each pixel carries
//!   its weight (frames' worth of samples: the AO kernel adds its share of a frame to the w of the
//!   E sum), and the sums are multiplied by `min(1, max_age / weight)`, so that old samples of a
//!   moving view fade and a pixel's estimate follows the surface it shows;
//! - before the cap, a history whose samples stand too far from the new hit is scaled down
//!   ([`Rule::drift`]): each pixel also sums the hit positions its samples were taken
//!   at (weighted as the others, so position sum / weight is where its history stands); at a
//!   distance d of more than the tolerance (in footprints of the new hit) the sums are multiplied
//!   by (tolerance / d)^2. Where taps are rejected a history is carried from one side only and
//!   creeps away from the point it stands for, a little each frame: near a crease or a
//!   silhouette that drift, not noise, was the moving error (docs/bench/history/orbit-drift-lavapipe.md);
//! - every other pixel starts at 0 (its weight restarts);
//! - the frame's AO samples are then spent by history ([`Rule::spending`]): a pixel newly seen or
//!   restarted takes more than the frame's S, one with a long history fewer, each adding its
//!   samples over S frames' worth to its weight. The reprojection writes the number into the
//!   position sum's w; the AO kernel takes it.
//!
//! A tile whose history was reprojected divides its sums by the per-pixel weight (compose and the
//! filter) instead of the uniform frame count; a still camera never reprojects and keeps the
//! uniform path bit for bit.

use crate::denoise::{dot, Rays};
use isowall_model::View;

/// The acceptance and ageing rule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rule {
    /// The most frames' worth of history a pixel keeps.
    pub max_age: f32,
    /// The plane distance accepted, in footprints of the previous pixel.
    pub plane_tolerance: f32,
    /// The least dot product of the two normals accepted.
    pub normal_agreement: f32,
    /// Carry the one previous pixel the projection falls in (weight 1) instead of the four
    /// bilinear taps around it.
    pub nearest: bool,
    /// Carry only the accepted share of the history: the counting taps' sums blended by their
    /// bilinear weights without renormalizing them to 1, so where taps are rejected the history
    /// (weight included) shrinks by the rejected share.
    pub accepted_share: bool,
    /// How far the carried history's samples may stand from the new hit before the history is
    /// scaled down by (tolerance / distance)^2.
    pub drift: DriftTolerance,
    /// How a reprojected frame's AO samples are spent over its pixels.
    pub spending: Spending,
}

/// [`Rule::spending`]: how many AO samples each pixel of a reprojected frame takes, from the
/// history it carries. The frame's nominal samples S (the governor's) stay the unit of weight: a
/// pixel taking n samples adds n / S frames' worth to its history.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Spending {
    /// Every pixel takes S.
    Uniform,
    /// A pixel carrying a history of weight h (frames' worth) takes S * clamp(target - h, least,
    /// most) samples, rounded down after adding a number in [0, 1) drawn per pixel and frame
    /// ([`spend_key`]), and at least one: a pixel newly seen takes `most` frames' worth, one
    /// whose history is `target - least` frames or older `least`. The variance of a history of h
    /// frames' worth falls as 1 / (h + n / S): a sample lowers it most where h is small.
    ByHistory { target: f32, least: f32, most: f32 },
}

impl Spending {
    /// The samples a pixel carrying `weight` frames' worth of history takes in a frame of
    /// `samples` (S), its draw in [0, 1) being `(spend_key(..) >> 8) / 2^24`.
    pub fn samples(self, weight: f32, samples: u32, key: u32) -> u32 {
        match self {
            Spending::Uniform => samples,
            Spending::ByHistory { target, least, most } => {
                let x = (target - weight).clamp(least, most) * samples as f32;
                let u = (key >> 8) as f32 * (1.0 / 16_777_216.0);
                ((x + u).floor() as u32).max(1)
            }
        }
    }

    /// The kernel's code (shaders/reproject.wgsl: `SPENDING_*`).
    pub fn code(self) -> u32 {
        match self {
            Spending::Uniform => 0,
            Spending::ByHistory { .. } => 1,
        }
    }

    /// The most samples a pixel takes in a frame of `samples`.
    pub fn most(self, samples: u32) -> u32 {
        match self {
            Spending::Uniform => samples,
            Spending::ByHistory { most, .. } => ((most * samples as f32).ceil() as u32).max(1),
        }
    }
}

/// The per-pixel, per-frame draw of [`Spending::ByHistory`]'s rounding: the sample pattern's key
/// (full-image pixel, the frame's sample index, the seed) hashed once more, so that it is the same
/// on every node and independent of the pattern.
pub fn spend_key(px: u32, py: u32, frame: u32, seed: u32) -> u32 {
    crate::sampling::hash(crate::sampling::pixel_key(px, py, frame, seed) ^ SPEND_SALT)
}

/// Separates [`spend_key`] from the AO pattern's key (shaders/reproject.wgsl has the same,
/// checked by a test).
pub const SPEND_SALT: u32 = 0x5bd1_e995;

/// [`Rule::drift`]: a distance in footprints of the new hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DriftTolerance {
    /// No drift test.
    Off,
    /// This many footprints.
    Fixed(f32),
    /// This many footprints over the square root of the AO samples a frame: the more samples a
    /// frame brings, the less a drifted history is worth against them (measured best on the
    /// engine: 1 footprint at 4 samples, 0.25-0.5 at 16).
    OverSqrtSamples(f32),
}

impl DriftTolerance {
    /// The tolerance in footprints at `samples` AO samples a frame (infinite: no test).
    pub fn footprints(self, samples: u32) -> f32 {
        match self {
            DriftTolerance::Off => f32::INFINITY,
            DriftTolerance::Fixed(t) => t,
            DriftTolerance::OverSqrtSamples(scale) => scale / (samples.max(1) as f32).sqrt(),
        }
    }
}

/// The rule the renderer uses.
pub const RULE: Rule = Rule {
    max_age: 16.0,
    plane_tolerance: 1.0,
    normal_agreement: 0.9,
    nearest: false,
    accepted_share: true,
    drift: DriftTolerance::OverSqrtSamples(DRIFT_SCALE),
    spending: SPENDING,
};

/// The renderer's spending of a reprojected frame's samples.
/// At 4 samples a frame a pixel newly seen takes 16, one with 9.75 frames' worth of history or
/// more takes 1. The target is the one whose mean over an orbit of 1 degree a frame is about the
/// frame's samples (`isowalld bench orbit`: 3.4 a pixel on the engine, 4.3 on the MRI; 6 and 14
/// are the bench's `spend-target` variants).
pub const SPENDING: Spending = Spending::ByHistory { target: 10.0, least: 0.25, most: 4.0 };

/// The renderer's drift tolerance times the square root of the AO samples a frame: 1 footprint
/// at 4 samples (docs/bench/history/orbit-drift-lavapipe.md).
pub const DRIFT_SCALE: f32 = 2.0;

/// A frame's geometry over its (low) rectangle: per pixel, rows top to bottom.
pub struct Geometry<'a> {
    /// The rectangle and its camera.
    pub view: &'a View,
    pub hit: &'a [bool],
    /// Distance along the pixel's ray.
    pub depth: &'a [f32],
    /// N (outward).
    pub normal: &'a [[f32; 3]],
}

/// A camera in f32 as the kernel holds it.
struct Camera32 {
    eye: [f32; 3],
    rays: Rays,
}

impl Camera32 {
    fn new(view: &View) -> Camera32 {
        let e = view.camera.eye;
        Camera32 { eye: [e.x as f32, e.y as f32, e.z as f32], rays: Rays::new(view) }
    }

    /// The hit of rectangle pixel `i` of `g`, and its ray.
    fn point(&self, g: &Geometry, i: usize) -> ([f32; 3], [f32; 3]) {
        let w = g.view.rect.width as usize;
        let d = self.rays.dir(g.view.rect.x + (i % w) as u32, g.view.rect.y + (i / w) as u32);
        (std::array::from_fn(|c| self.eye[c] + g.depth[i] * d[c]), d)
    }
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|c| a[c] - b[c])
}

/// Where world point `p` falls in `cam`'s full image, in pixels (pixel (i, j) covers
/// [i, i + 1) x [j, j + 1)); `None` behind the camera.
fn position(cam: &Camera32, p: [f32; 3]) -> Option<(f32, f32)> {
    let r = &cam.rays;
    let d = sub(p, cam.eye);
    let z = dot(d, r.forward);
    if !(z > 0.0) {
        return None;
    }
    let (w, h) = r.full;
    let sx = dot(d, r.right) / z;
    let sy = dot(d, r.up) / z;
    Some(((sx / (r.tan_half * w / h) + 1.0) * 0.5 * w, (1.0 - sy / r.tan_half) * 0.5 * h))
}

/// The index in `prev`'s rectangle of full-image pixel `q`, where it is inside.
fn index_in(prev: &Geometry, q: (i64, i64)) -> Option<usize> {
    let r = prev.view.rect;
    let (x, y) = (q.0 - r.x as i64, q.1 - r.y as i64);
    (x >= 0 && y >= 0 && x < r.width as i64 && y < r.height as i64).then(|| (x + y * r.width as i64) as usize)
}

/// Per pixel of `next`, the previous pixels whose sums it carries over under `rule`, with their
/// bilinear weights (not normalized): of the four previous pixels around the projection of its
/// hit, those inside the previous rectangle that saw the same surface (a hit, the point within
/// the plane tolerance, the normals agreeing, the same side seen). Empty: the pixel restarts.
pub fn sources(prev: &Geometry, next: &Geometry, rule: &Rule) -> Vec<Vec<(usize, f32)>> {
    let (pc, nc) = (Camera32::new(prev.view), Camera32::new(next.view));
    let pixel_size = 2.0 * pc.rays.tan_half / pc.rays.full.1;
    (0..next.hit.len())
        .map(|i| {
            let mut taps = Vec::new();
            if !next.hit[i] {
                return taps;
            }
            let (p, dir) = nc.point(next, i);
            let Some((u, v)) = position(&pc, p) else { return taps };
            let n = next.normal[i];
            // Nearest: the taps' base is the pixel the projection falls in, at weight 1.
            let (fx, fy) = if rule.nearest { (u.floor(), v.floor()) } else { (u - 0.5, v - 0.5) };
            let (bx, by) = (fx.floor(), fy.floor());
            let (tx, ty) = (fx - bx, fy - by);
            for k in 0..4 {
                let (ox, oy) = (k & 1, k >> 1);
                let w = if ox == 1 { tx } else { 1.0 - tx } * if oy == 1 { ty } else { 1.0 - ty };
                let Some(j) = index_in(prev, (bx as i64 + ox, by as i64 + oy)) else { continue };
                if !(w > 0.0) || !prev.hit[j] {
                    continue;
                }
                let (q, qdir) = pc.point(prev, j);
                let nq = prev.normal[j];
                let footprint = prev.depth[j] * pixel_size;
                let plane = dot(nq, sub(p, q)).abs();
                let agree = dot(n, nq) >= rule.normal_agreement;
                let same_side = (dot(n, dir) < 0.0) == (dot(nq, qdir) < 0.0);
                if plane <= rule.plane_tolerance * footprint && agree && same_side {
                    taps.push((j, w));
                }
            }
            taps
        })
        .collect()
}

/// The factor a history of `weight` frames is scaled by under `rule`: `min(1, max_age / weight)`.
pub fn keep(weight: f32, rule: &Rule) -> f32 {
    if weight > rule.max_age {
        rule.max_age / weight
    } else {
        1.0
    }
}

/// A rectangle's running sums, per pixel: bent + A, E rgb + weight, position (xyz) + the samples
/// a reprojected frame takes there.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Sums {
    pub ao: Vec<[f32; 4]>,
    pub ibl: Vec<[f32; 4]>,
    pub pos: Vec<[f32; 4]>,
}

/// The factor a history whose samples stand `distance` footprints from the new hit is scaled by
/// at a tolerance of `tolerance` footprints: `min(1, (tolerance / distance)^2)`.
pub fn drift_keep(distance: f32, tolerance: f32) -> f32 {
    if distance > tolerance {
        let r = tolerance / distance;
        r * r
    } else {
        1.0
    }
}

/// The frame a reprojection prepares: its nominal AO samples a pixel (S), its index in the sample
/// sequence and its seed (`FrameParams`' `ao_samples`, `frame`, `seed`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pattern {
    pub samples: u32,
    pub frame: u32,
    pub seed: u32,
}

/// The CPU twin of `Kernel::Reproject`: `next`'s running sums carried from `prev`'s under
/// `rule`, before the AO kernel adds the new frame `pattern`. The position sum's w is the number of
/// AO samples the pixel takes in that frame ([`Rule::spending`]; 0 where it has no hit).
pub fn reproject(prev: &Geometry, prev_sums: &Sums, next: &Geometry, rule: &Rule, pattern: Pattern) -> Sums {
    let samples = pattern.samples;
    let tolerance = rule.drift.footprints(samples);
    let width = next.view.rect.width as usize;
    let nc = Camera32::new(next.view);
    let pixel_size = 2.0 * nc.rays.tan_half / nc.rays.full.1;
    let mut out = Sums::default();
    for (i, taps) in sources(prev, next, rule).into_iter().enumerate() {
        let (mut wsum, mut ao, mut ibl, mut pos) = (0.0f32, [0.0f32; 4], [0.0f32; 4], [0.0f32; 4]);
        for (j, w) in taps {
            wsum += w;
            for c in 0..4 {
                ao[c] += w * prev_sums.ao[j][c];
                ibl[c] += w * prev_sums.ibl[j][c];
                pos[c] += w * prev_sums.pos[j][c];
            }
        }
        if wsum > 0.0 {
            let norm = if rule.accepted_share { 1.0 } else { wsum };
            let mut k = 1.0 / norm;
            if ibl[3] * k > 0.0 {
                let (p, _) = nc.point(next, i);
                let centre: [f32; 3] = std::array::from_fn(|c| pos[c] / ibl[3]);
                let d = sub(centre, p);
                k *= drift_keep(dot(d, d).sqrt() / (next.depth[i] * pixel_size), tolerance);
            }
            k *= keep(ibl[3] * k, rule);
            ao = ao.map(|x| x * k);
            ibl = ibl.map(|x| x * k);
            pos = pos.map(|x| x * k);
        }
        pos[3] = 0.0;
        if next.hit[i] {
            let (px, py) = (next.view.rect.x + (i % width) as u32, next.view.rect.y + (i / width) as u32);
            let key = spend_key(px, py, pattern.frame, pattern.seed);
            pos[3] = rule.spending.samples(ibl[3], samples, key) as f32;
        }
        out.ao.push(ao);
        out.ibl.push(ibl);
        out.pos.push(pos);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;
    use isowall_model::Camera;

    /// The plane z = 0 seen from above by `view`'s camera: per pixel of a w x h image, hit, depth, normal.
    fn plane(view: &View) -> (Vec<bool>, Vec<f32>, Vec<[f32; 3]>) {
        let b = view.camera.basis();
        let (w, h) = (view.rect.width, view.rect.height);
        let mut out = (Vec::new(), Vec::new(), Vec::new());
        for y in 0..h {
            for x in 0..w {
                let d = view.ray_dir(&b, x, y);
                let t = -view.camera.eye.z / d.z;
                let hit = t > 0.0;
                out.0.push(hit);
                out.1.push(if hit { t as f32 } else { f32::INFINITY });
                out.2.push([0.0, 0.0, 1.0]);
            }
        }
        out
    }

    fn view(eye: DVec3) -> View {
        let cam = Camera { eye, target: eye - DVec3::new(0.0, 0.0, 2.0), up: DVec3::Y, fov_y_deg: 40.0 };
        View::whole(cam, 32, 24)
    }

    #[test]
    fn a_still_camera_carries_every_hit_from_itself_and_a_shift_carries_the_overlap() {
        let a = view(DVec3::new(0.0, 0.0, 2.0));
        let (hit, depth, normal) = plane(&a);
        let ga = Geometry { view: &a, hit: &hit, depth: &depth, normal: &normal };
        let same = sources(&ga, &ga, &RULE);
        for (i, taps) in same.iter().enumerate() {
            // The projection is the pixel's own centre: its own tap takes (almost) all the weight.
            let wsum: f32 = taps.iter().map(|t| t.1).sum();
            let own = taps.iter().find(|t| t.0 == i).map_or(0.0, |t| t.1);
            assert!(hit[i] && own > 0.99 * wsum, "pixel {i}: {taps:?}");
        }
        // Moved right by about five pixels: the points seen before come from their old pixels;
        // those newly seen at the right start over.
        let b = view(DVec3::new(0.3, 0.0, 2.0));
        let (hb, db, nb) = plane(&b);
        let gb = Geometry { view: &b, hit: &hb, depth: &db, normal: &nb };
        let moved = sources(&ga, &gb, &RULE);
        let carried = moved.iter().filter(|s| !s.is_empty()).count();
        let hits = hb.iter().filter(|&&h| h).count();
        assert!(carried > hits / 2 && carried < hits, "{carried} of {hits}");
        // Moved away entirely: nothing is carried.
        let far = view(DVec3::new(50.0, 0.0, 2.0));
        let (hf, df, nf) = plane(&far);
        let gf = Geometry { view: &far, hit: &hf, depth: &df, normal: &nf };
        assert!(sources(&ga, &gf, &RULE).iter().all(|s| s.is_empty()));
    }

    #[test]
    fn the_nearest_rule_carries_the_one_pixel_the_projection_falls_in() {
        let a = view(DVec3::new(0.0, 0.0, 2.0));
        let (hit, depth, normal) = plane(&a);
        let ga = Geometry { view: &a, hit: &hit, depth: &depth, normal: &normal };
        let nearest = Rule { nearest: true, ..RULE };
        // A still camera: every pixel carries itself alone.
        for (i, taps) in sources(&ga, &ga, &nearest).iter().enumerate() {
            assert_eq!(taps, &vec![(i, 1.0)], "pixel {i}");
        }
        // Moved a third of a pixel sideways: bilinear blends two columns, nearest keeps one.
        let pixel = 2.0 * 2.0 * (20.0f64).to_radians().tan() / 24.0;
        let b = view(DVec3::new(pixel / 3.0, 0.0, 2.0));
        let (hb, db, nb) = plane(&b);
        let gb = Geometry { view: &b, hit: &hb, depth: &db, normal: &nb };
        let centre = 12 * 32 + 16;
        assert_eq!(sources(&ga, &gb, &nearest)[centre].len(), 1);
        assert!(sources(&ga, &gb, &RULE)[centre].len() >= 2);
    }

    #[test]
    fn a_history_that_drifted_off_its_point_is_scaled_down_by_the_squared_ratio() {
        // The renderer's tolerance: 1 footprint at 4 samples a frame, half at 16.
        assert_eq!(RULE.drift.footprints(4), 1.0);
        assert_eq!(RULE.drift.footprints(16), 0.5);
        assert_eq!(DriftTolerance::Fixed(0.3).footprints(16), 0.3);
        assert_eq!(DriftTolerance::Off.footprints(4), f32::INFINITY);
        assert_eq!(drift_keep(0.5, 1.0), 1.0);
        assert_eq!(drift_keep(2.0, 1.0), 0.25);
        assert_eq!(drift_keep(1e9, DriftTolerance::Off.footprints(4)), 1.0);
        // A still camera carries each pixel from itself: a history of weight 4 whose samples
        // stand where the pixel's hit is keeps its weight; one standing two footprints beside it
        // (along the plane) keeps a quarter.
        let a = view(DVec3::new(0.0, 0.0, 2.0));
        let (hit, depth, normal) = plane(&a);
        let g = Geometry { view: &a, hit: &hit, depth: &depth, normal: &normal };
        let cam = Camera32::new(&a);
        let footprint = |i: usize| depth[i] * 2.0 * cam.rays.tan_half / cam.rays.full.1;
        let sums = |offset: f32| {
            let pos = (0..hit.len())
                .map(|i| {
                    let (p, _) = cam.point(&g, i);
                    [4.0 * (p[0] + offset * footprint(i)), 4.0 * p[1], 4.0 * p[2], 0.0]
                })
                .collect();
            Sums {
                ao: vec![[0.0, 0.0, 4.0, 2.0]; hit.len()],
                ibl: vec![[1.0, 1.0, 1.0, 4.0]; hit.len()],
                pos,
            }
        };
        let centre = 12 * 32 + 16;
        for (offset, want) in [(0.0, 4.0), (2.0 * RULE.drift.footprints(4), 1.0)] {
            let out = reproject(&g, &sums(offset), &g, &RULE, Pattern { samples: 4, frame: 0, seed: 0 });
            let weight = out.ibl[centre][3];
            assert!((weight - want).abs() < 1e-3 * want, "offset {offset}: weight {weight}");
            // Every sum is scaled alike: the occlusion estimate (A / weight) is unchanged.
            assert!((out.ao[centre][3] / weight - 0.5).abs() < 1e-5);
        }
    }

    #[test]
    fn samples_are_spent_by_history_unbiased_and_within_their_bounds() {
        let s = 4;
        assert_eq!(Spending::Uniform.samples(0.0, s, 123), 4);
        assert_eq!(Spending::Uniform.most(s), 4);
        let by = Spending::ByHistory { target: 6.0, least: 0.25, most: 4.0 };
        assert_eq!(by.most(s), 16);
        // A draw of 0 rounds down, the largest draw up: the mean over draws is the fraction.
        for (weight, want) in [(0.0, 16.0), (3.0, 12.0), (5.5, 2.0), (5.9, 1.0), (16.0, 1.0)] {
            let keys = (0..4096u32).map(|k| spend_key(k % 64, k / 64, 7, 1));
            let taken: Vec<u32> = keys.map(|k| by.samples(weight, s, k)).collect();
            let mean = taken.iter().sum::<u32>() as f64 / taken.len() as f64;
            assert!((mean - want).abs() < 0.05 * want, "weight {weight}: mean {mean}, want {want}");
            assert!(taken.iter().all(|&n| n >= 1 && n <= by.most(s)), "weight {weight}");
        }
        // Between two integers, both are taken: 5.5 frames' worth leaves 0.5 * 4 = 2 exactly; 5.75
        // leaves 1 (the least, 0.25 frames' worth); 5.2 leaves 3.2, so 3 or 4.
        let draws: std::collections::BTreeSet<u32> =
            (0..256).map(|k| by.samples(5.2, s, spend_key(k, 0, 0, 0))).collect();
        assert_eq!(draws.into_iter().collect::<Vec<_>>(), vec![3, 4]);
        // The draw is the pixel's and the frame's: another frame draws afresh.
        let a: Vec<u32> = (0..64).map(|k| by.samples(5.2, s, spend_key(k, 0, 0, 0))).collect();
        let b: Vec<u32> = (0..64).map(|k| by.samples(5.2, s, spend_key(k, 0, 1, 0))).collect();
        assert_ne!(a, b);
    }

    #[test]
    fn history_is_capped_at_the_maximum_age() {
        assert_eq!(keep(4.0, &RULE), 1.0);
        assert_eq!(keep(RULE.max_age, &RULE), 1.0);
        assert_eq!(keep(4.0 * RULE.max_age, &RULE), 0.25);
    }
}
