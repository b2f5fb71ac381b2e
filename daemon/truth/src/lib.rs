//! An independent estimate of DESIGN.md "AO" (and of the IBL integral), the judge of the AO tests
//! (`daemon/render/tests/ao_truth.rs`) and of `isowalld bench denoise`.
//!
//! Written apart from both renderers on purpose: this crate depends on glam alone and nothing here
//! calls `isowall_render` (not its
//! sampling, not the reference's cell walk or cubic, not the volume crate's trilinear field or
//! gradient). It takes the voxels, dims, spacing and origin of a loaded volume and does the rest
//! itself, brute force, in f64:
//!
//! - the field: its own trilinear interpolation of the samples inside the box, empty outside;
//! - primary hit: a uniform march of `STEP_VOXELS` (0.02 of the smallest spacing) from the box
//!   entry (a cap where the entry is already inside the object), then bisection to 1e-12;
//! - N: its own central differences (h = one spacing per axis, stencil clamped to the box), as it
//!   is; Ng: its own analytic gradient of the trilinear cell holding p, turned towards the eye
//!   (a cap: the face's outward normal); N = Ng where the central difference vanishes;
//! - AO: a direction with w . Ng <= 0 (under p's tangent plane) is occluded at distance 0, unmarched
//!   (DESIGN.md: from p itself it enters the object at once); every other one is a ray from
//!   o = p + 0.01 * (smallest spacing) * Ng, marched uniformly at `STEP_VOXELS` (no
//!   block skipping, no cell bounds), occluded where the field reaches iso within R; directions
//!   from its own set: jittered-stratified points of the unit square (a splitmix64 stream seeded
//!   per pixel, fixed) mapped by the polar (not the concentric) map, cosine-weighted about N in its
//!   own orthonormal basis. One march serves every radius: the first occluding distance is kept.
//! - the camera: its own pixel-centre ray ([`pixel_ray`]), from DESIGN.md "Camera".

pub mod known;

use glam::DVec3;
use std::f64::consts::PI;

pub use known::{KnownAnswers, KnownCamera, KnownCase, KnownPixel};

/// The march step, in voxels of the smallest spacing, for primary and AO rays alike.
pub const STEP_VOXELS: f64 = 0.02;
/// eps of DESIGN.md "AO", in voxels of the smallest spacing.
pub const EPS_VOXELS: f64 = 0.01;

/// The scalar field of a volume, read once from its samples.
pub struct Field {
    dims: [usize; 3],
    spacing: DVec3,
    origin: DVec3,
    data: Vec<f32>,
    iso: f64,
}

/// What the estimator finds at one pixel.
#[derive(Clone, Debug)]
pub struct Truth {
    pub px: u32,
    pub py: u32,
    /// Distance from the eye to the hit.
    pub depth: f64,
    pub position: DVec3,
    /// N as it is (the hemisphere's axis).
    pub normal: DVec3,
    /// The first distance at which each direction's ray reaches the object (`INFINITY`: never
    /// within the box; 0 for a direction under p's tangent plane), in direction order.
    pub first_hits: Vec<f64>,
    /// The directions, unit, cosine-distributed about N.
    pub directions: Vec<DVec3>,
}

impl Truth {
    /// A for radius `r` (world units; `None`: unbounded).
    pub fn occlusion(&self, r: Option<f64>) -> f64 {
        let occluded = self.first_hits.iter().filter(|&&t| t.is_finite() && r.is_none_or(|r| t <= r)).count();
        occluded as f64 / self.first_hits.len() as f64
    }

    /// E = (1/pi) integral of L V cos for radius `r`, for a radiance `l` per direction.
    pub fn irradiance(&self, r: Option<f64>, l: impl Fn(DVec3) -> [f64; 3]) -> [f64; 3] {
        let mut e = [0.0; 3];
        for (t, w) in self.first_hits.iter().zip(&self.directions) {
            let open = !t.is_finite() || r.is_some_and(|r| *t > r);
            if open {
                let c = l(*w);
                (0..3).for_each(|k| e[k] += c[k]);
            }
        }
        e.map(|c| c / self.first_hits.len() as f64)
    }
}

impl Field {
    pub fn new(dims: [usize; 3], spacing: DVec3, origin: DVec3, data: &[f32], iso: f64) -> Field {
        assert_eq!(data.len(), dims[0] * dims[1] * dims[2]);
        assert!(dims.iter().all(|&n| n >= 2), "the estimator wants at least 2 samples per axis");
        Field { dims, spacing, origin, data: data.to_vec(), iso }
    }

    fn lo(&self) -> DVec3 {
        self.origin
    }

    fn hi(&self) -> DVec3 {
        self.origin + self.spacing * DVec3::new(self.n(0) - 1.0, self.n(1) - 1.0, self.n(2) - 1.0)
    }

    fn n(&self, a: usize) -> f64 {
        self.dims[a] as f64
    }

    fn voxel(&self, i: usize, j: usize, k: usize) -> f64 {
        self.data[i + self.dims[0] * (j + self.dims[1] * k)] as f64
    }

    /// Cell index and local coordinates of a world point (clamped into the grid).
    fn locate(&self, p: DVec3) -> ([usize; 3], DVec3) {
        let g = (p - self.origin) / self.spacing;
        let mut cell = [0usize; 3];
        let mut local = DVec3::ZERO;
        for a in 0..3 {
            let top = self.n(a) - 1.0;
            let x = g[a].clamp(0.0, top);
            let c = (x.floor()).min(top - 1.0);
            cell[a] = c as usize;
            local[a] = x - c;
        }
        (cell, local)
    }

    fn corners(&self, c: [usize; 3]) -> [f64; 8] {
        std::array::from_fn(|m| self.voxel(c[0] + (m & 1), c[1] + ((m >> 1) & 1), c[2] + ((m >> 2) & 1)))
    }

    /// The trilinear field at p, position clamped to the box.
    fn clamped(&self, p: DVec3) -> f64 {
        let (c, l) = self.locate(p);
        let v = self.corners(c);
        let (x, y, z) = (l.x, l.y, l.z);
        let a = v[0] * (1.0 - x) + v[1] * x;
        let b = v[2] * (1.0 - x) + v[3] * x;
        let d = v[4] * (1.0 - x) + v[5] * x;
        let e = v[6] * (1.0 - x) + v[7] * x;
        let lower = a * (1.0 - y) + b * y;
        let upper = d * (1.0 - y) + e * y;
        lower * (1.0 - z) + upper * z
    }

    /// f(p) - iso inside the closed box, -infinity (empty) outside.
    fn excess(&self, p: DVec3) -> f64 {
        let (lo, hi) = (self.lo(), self.hi());
        if (0..3).any(|a| p[a] < lo[a] || p[a] > hi[a]) {
            return f64::NEG_INFINITY;
        }
        self.clamped(p) - self.iso
    }

    /// Central differences, h = one spacing per axis, stencil clamped to the box.
    fn central_gradient(&self, p: DVec3) -> DVec3 {
        let mut g = DVec3::ZERO;
        for a in 0..3 {
            let mut e = DVec3::ZERO;
            e[a] = self.spacing[a];
            g[a] = (self.clamped(p + e) - self.clamped(p - e)) / (2.0 * self.spacing[a]);
        }
        g
    }

    /// The gradient of the trilinear cell holding p.
    fn cell_gradient(&self, p: DVec3) -> DVec3 {
        let (c, l) = self.locate(p);
        let v = self.corners(c);
        let (x, y, z) = (l.x, l.y, l.z);
        let bl = |a: f64, b: f64, c: f64, d: f64, s: f64, t: f64| {
            (a * (1.0 - s) + b * s) * (1.0 - t) + (c * (1.0 - s) + d * s) * t
        };
        let gx = bl(v[1] - v[0], v[3] - v[2], v[5] - v[4], v[7] - v[6], y, z);
        let gy = bl(v[2] - v[0], v[3] - v[1], v[6] - v[4], v[7] - v[5], x, z);
        let gz = bl(v[4] - v[0], v[5] - v[1], v[6] - v[2], v[7] - v[3], x, y);
        DVec3::new(gx, gy, gz) / self.spacing
    }

    fn step(&self) -> f64 {
        STEP_VOXELS * self.spacing.min_element()
    }

    /// The parameter range of the ray o + t d inside the box, or None.
    fn clip(&self, o: DVec3, d: DVec3) -> Option<(f64, f64, usize)> {
        let (lo, hi) = (self.lo(), self.hi());
        let (mut t0, mut t1, mut axis) = (f64::NEG_INFINITY, f64::INFINITY, 0);
        for a in 0..3 {
            if d[a].abs() < 1e-300 {
                if o[a] < lo[a] || o[a] > hi[a] {
                    return None;
                }
                continue;
            }
            let (ta, tb) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
            let (near, far) = if ta < tb { (ta, tb) } else { (tb, ta) };
            if near > t0 {
                t0 = near;
                axis = a;
            }
            t1 = t1.min(far);
        }
        (t1 >= t0.max(0.0)).then_some((t0, t1, axis))
    }

    /// The first hit of the ray from `eye` along unit `d`: (t, p, N as it is, Ng).
    pub fn primary(&self, eye: DVec3, d: DVec3) -> Option<(f64, DVec3, DVec3, DVec3)> {
        let (t_in, t_out, axis) = self.clip(eye, d)?;
        assert!(t_in > 0.0, "the estimator's cameras are outside the box");
        if self.clamped(eye + t_in * d) >= self.iso {
            // A cap: the face entered, its outward normal for both normals.
            let mut n = DVec3::ZERO;
            n[axis] = -d[axis].signum();
            return Some((t_in, eye + t_in * d, n, n));
        }
        let h = self.step();
        let mut t = t_in;
        while t < t_out {
            let t_next = (t + h).min(t_out);
            if self.clamped(eye + t_next * d) >= self.iso {
                let (mut a, mut b) = (t, t_next);
                while b - a > 1e-12 {
                    let m = 0.5 * (a + b);
                    if self.clamped(eye + m * d) >= self.iso {
                        b = m;
                    } else {
                        a = m;
                    }
                }
                let p = eye + b * d;
                let g = self.cell_gradient(p);
                let ng = if g.length() > 0.0 {
                    let n = -g.normalize();
                    if n.dot(d) > 0.0 {
                        -n
                    } else {
                        n
                    }
                } else {
                    -d
                };
                let c = self.central_gradient(p);
                let n = if c.length() > 1e-12 * self.iso.abs().max(1.0) { -c.normalize() } else { ng };
                return Some((b, p, n, ng));
            }
            t = t_next;
        }
        None
    }

    /// The first distance along unit `w` from `o` where the field reaches iso, up to `t_max`
    /// (INFINITY where it does not within the box or `t_max`).
    pub fn first_occluder(&self, o: DVec3, w: DVec3, t_max: f64) -> f64 {
        let Some((t_in, t_out, _)) = self.clip(o, w) else {
            return f64::INFINITY;
        };
        let end = t_out.min(t_max);
        let h = self.step();
        let mut t = t_in.max(0.0);
        loop {
            if self.excess(o + t * w) >= 0.0 {
                return t;
            }
            if t >= end {
                return f64::INFINITY;
            }
            t = (t + h).min(end);
        }
    }

    /// The estimate at the hit of pixel `(px, py)` seen from `eye` along `d`: `m` x `m` stratified
    /// directions, rays marched up to `t_max` (world units; INFINITY: to the box).
    pub fn estimate(&self, eye: DVec3, d: DVec3, (px, py): (u32, u32), m: u32, t_max: f64) -> Option<Truth> {
        let (depth, p, n, ng) = self.primary(eye, d)?;
        let o = p + EPS_VOXELS * self.spacing.min_element() * ng;
        let directions = cosine_set(n, m, 0x9e37_79b9_7f4a_7c15 ^ ((px as u64) << 32 | py as u64));
        let first_hits = directions
            .iter()
            .map(|&w| if w.dot(ng) <= 0.0 { 0.0 } else { self.first_occluder(o, w, t_max) })
            .collect();
        Some(Truth { px, py, depth, position: p, normal: n, first_hits, directions })
    }
}

/// The unit ray through the centre of pixel (px, py) of a `w` x `h` image (py = 0 the top row) of
/// the pinhole camera at `eye` looking at `target` with `up` and a vertical field of view of
/// `fov_y_deg` degrees, from DESIGN.md "Camera" (written here anew).
pub fn pixel_ray(
    (eye, target, up): (DVec3, DVec3, DVec3),
    fov_y_deg: f64,
    (w, h): (u32, u32),
    px: u32,
    py: u32,
) -> DVec3 {
    let f = (target - eye).normalize();
    let r = f.cross(up).normalize();
    let u = r.cross(f);
    let t = (fov_y_deg.to_radians() / 2.0).tan();
    let sx = ((px as f64 + 0.5) / w as f64 * 2.0 - 1.0) * t * w as f64 / h as f64;
    let sy = (1.0 - (py as f64 + 0.5) / h as f64 * 2.0) * t;
    (f + sx * r + sy * u).normalize()
}

/// splitmix64 (Steele, Lea, Flood 2014).
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        (z >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// m x m jittered-stratified cosine-weighted directions about unit `n`: polar map
/// (r = sqrt(u), phi = 2 pi v), lifted with z = sqrt(1 - u).
pub fn cosine_set(n: DVec3, m: u32, seed: u64) -> Vec<DVec3> {
    let mut rng = SplitMix(seed);
    // A basis from the axis least aligned with n.
    let helper = if n.x.abs() <= n.y.abs() && n.x.abs() <= n.z.abs() {
        DVec3::X
    } else if n.y.abs() <= n.z.abs() {
        DVec3::Y
    } else {
        DVec3::Z
    };
    let a = n.cross(helper).normalize();
    let b = n.cross(a);
    let mut out = Vec::with_capacity((m * m) as usize);
    for j in 0..m {
        for i in 0..m {
            let u = (i as f64 + rng.next()) / m as f64;
            let v = (j as f64 + rng.next()) / m as f64;
            let (r, phi) = (u.sqrt(), 2.0 * PI * v);
            out.push(r * phi.cos() * a + r * phi.sin() * b + (1.0 - u).max(0.0).sqrt() * n);
        }
    }
    out
}

/// Runs `f` over `items` on every core (the results in order).
pub fn parallel_map<T: Sync, R: Send>(items: &[T], f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).min(items.len().max(1));
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut out: Vec<(usize, R)> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                s.spawn(|| {
                    let mut mine = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        if i >= items.len() {
                            break mine;
                        }
                        mine.push((i, f(&items[i])));
                    }
                })
            })
            .collect();
        workers.into_iter().flat_map(|w| w.join().expect("an estimator thread panicked")).collect()
    });
    out.sort_by_key(|(i, _)| *i);
    out.into_iter().map(|(_, r)| r).collect()
}

/// Errors of an estimate `got` (one A per pixel) against the truth `want`.
#[derive(Clone, Copy, Debug)]
pub struct Errors {
    pub pixels: usize,
    pub mean_truth: f64,
    pub mean_got: f64,
    pub rmse: f64,
    pub bias: f64,
    pub max: f64,
    /// Pixels off by more than 0.3.
    pub off_03: usize,
}

pub fn errors(got: &[f64], want: &[f64]) -> Errors {
    assert_eq!(got.len(), want.len());
    let n = got.len().max(1) as f64;
    let d: Vec<f64> = got.iter().zip(want).map(|(g, w)| g - w).collect();
    Errors {
        pixels: got.len(),
        mean_truth: want.iter().sum::<f64>() / n,
        mean_got: got.iter().sum::<f64>() / n,
        rmse: (d.iter().map(|x| x * x).sum::<f64>() / n).sqrt(),
        bias: d.iter().sum::<f64>() / n,
        max: d.iter().fold(0.0, |m, x| m.max(x.abs())),
        off_03: d.iter().filter(|x| x.abs() > 0.3).count(),
    }
}

impl std::fmt::Display for Errors {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} px, mean A truth {:.4} got {:.4}, RMSE {:.4}, bias {:+.4}, max {:.3}, off > 0.3: {}",
            self.pixels, self.mean_truth, self.mean_got, self.rmse, self.bias, self.max, self.off_03
        )
    }
}
