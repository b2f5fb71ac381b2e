//! The exact CPU reference renderer: the oracle the GPU renderer is tested against.
//!
//! Everything is `f64`. A primary ray `eye + t * dir` (`dir` unit, so `t` is the distance along
//! the ray) is clipped to the volume box, then walks the cells of the sample grid that it crosses.
//! Inside one cell the trilinear interpolant restricted to the ray is a cubic polynomial in `t`;
//! its coefficients are computed exactly from the cell's eight corner values, and the first point
//! where `f` crosses up to the iso value is found exactly (monotone pieces between the roots of
//! the derivative, then bisection to full `f64` precision). No step size, so no sheet is too thin.
//!
//! The rules, which the GPU renderer follows too (it only marches with a step and refines):
//!
//! - **Outside the box the field is empty** (below any iso, DESIGN.md "Volume"). A ray from an eye
//!   outside the box that enters it where `f >= iso` hits at the box entry: a *cap*, whose normal
//!   is the outward normal of the face entered. Where the entry lies on an edge or corner (several
//!   slabs give the same entry `t`) the face is that of the lowest axis among them (x, then y, z).
//! - **The hit is the first up-crossing**: the first `t` at which `f` goes from `< iso` to
//!   `>= iso`. A crossing exactly on a cell face (`f < iso` at the end of one cell, `>= iso` at the
//!   start of the next) is a hit at that face.
//! - **Eye inside the box**: the march starts at `t = 0`. When `f(eye) >= iso` the camera is inside
//!   the object; the ray must first leave it (`f < iso`) and the hit is the next up-crossing, so the
//!   inner side of the surface the camera sits behind is never shown (the object is see-through
//!   from inside, like a near clipping plane through it). An eye on the box boundary counts as
//!   inside (the box is closed).
//! - **Normal** `N = -grad f / |grad f|` from [`Volume::gradient`] (central differences, h = one
//!   spacing per axis, stencil clamped to the box), pointing out of the object and not flipped.
//!   Where `|grad f| <= 1e-12 * max|f| / min spacing` (max over the hit cell's corners and the
//!   iso value), the gradient is taken as vanished and `N = -dir` (towards the viewer).
//! - **Shading** uses `N` flipped to face the viewer, the light of the settings in the camera
//!   frame, [`shade`] and the exposure. Pixels without a hit hold the background colour and zero in
//!   every other AOV.
//! - **Single-sample axes** (dims 1): the box is flat on that axis and the field is constant along
//!   it; a ray through such a box meets it in one point (or runs inside the plane).
//!
//! `fetches` counts trilinear field evaluations: one per cell the ray visits (its eight corner
//! reads) and six per hit for the gradient.

use crate::frame::Frame;
use glam::DVec3;
use isowall_volume::Volume;
use isowall_wall::camera::Basis;
use isowall_wall::render_state::shade;
use isowall_wall::{RenderSettings, View};
use std::sync::atomic::{AtomicU32, Ordering};

/// A primary-ray hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance from the eye along the (unit) ray.
    pub t: f64,
    /// World position of the hit, `eye + t * dir`.
    pub position: DVec3,
    /// Outward normal N = -grad f / |grad f| (not flipped towards the viewer); the box face's
    /// outward normal for a cap; `-dir` where the gradient vanishes.
    pub normal: DVec3,
    /// Whether the hit is a cap: the ray entered the box already inside the object.
    pub cap: bool,
}

/// Traces one ray `eye + t * dir` against the isosurface `f = iso` of `volume` (see the module
/// documentation for the rules). `dir` is normalised here, so `t` is always a distance; a zero or
/// non-finite `dir`, a non-finite `eye` or a NaN iso give no hit.
pub fn trace(volume: &Volume, eye: DVec3, dir: DVec3, iso: f64) -> Option<Hit> {
    trace_counted(volume, eye, dir, iso).0
}

/// Renders the window of `view` with the exact reference method. Rows are shared among
/// `available_parallelism` threads; the output does not depend on how.
pub fn render(volume: &Volume, view: &View, settings: &RenderSettings) -> Frame {
    let basis = view.camera.basis();
    let (width, height) = (view.window.width, view.window.height);
    let _span = tracing::debug_span!("reference_render", width, height, iso = settings.iso).entered();
    let mut frame = Frame::new(width, height);
    let light = settings.light.world_direction(basis.forward, basis.right, basis.up);
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).min(height.max(1) as usize);
    let next_row = AtomicU32::new(0);
    let rows: Vec<(u32, Vec<Pixel>, u64)> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                s.spawn(|| {
                    let mut out = Vec::new();
                    loop {
                        let y = next_row.fetch_add(1, Ordering::Relaxed);
                        if y >= height {
                            break out;
                        }
                        let mut fetches = 0;
                        let row = (0..width)
                            .map(|x| {
                                let (px, f) = shade_pixel(volume, view, &basis, settings, light, x, y);
                                fetches += f;
                                px
                            })
                            .collect();
                        out.push((y, row, fetches));
                    }
                })
            })
            .collect();
        workers.into_iter().flat_map(|w| w.join().expect("a reference render thread panicked")).collect()
    });
    let w = width as usize;
    for (y, row, fetches) in rows {
        frame.fetches += fetches;
        for (x, px) in row.into_iter().enumerate() {
            let i = y as usize * w + x;
            frame.color[i] = px.color;
            frame.depth[i] = px.depth;
            frame.normal[i] = px.normal;
            frame.hit[i] = px.hit;
        }
    }
    tracing::debug!(
        pixels = frame.pixel_count(),
        hits = frame.hit_count(),
        fetches = frame.fetches,
        "reference frame rendered"
    );
    frame
}

/// One pixel's AOVs.
struct Pixel {
    color: [f32; 3],
    depth: f32,
    normal: [f32; 3],
    hit: bool,
}

/// Traces and shades the pixel (x, y) of the window; returns it and the fetches made.
fn shade_pixel(
    volume: &Volume,
    view: &View,
    basis: &Basis,
    settings: &RenderSettings,
    light: DVec3,
    x: u32,
    y: u32,
) -> (Pixel, u64) {
    let dir = view.ray_dir(basis, x, y);
    let (hit, fetches) = trace_counted(volume, view.camera.eye, dir, settings.iso);
    let px = match hit {
        None => {
            Pixel { color: settings.background.map(|c| c as f32), depth: 0.0, normal: [0.0; 3], hit: false }
        }
        Some(h) => {
            let v = -dir;
            let n = if h.normal.dot(v) < 0.0 { -h.normal } else { h.normal };
            let c = shade(settings, n, light, v);
            Pixel {
                color: c.map(|c| (c * settings.exposure) as f32),
                depth: h.t as f32,
                normal: h.normal.to_array().map(|c| c as f32),
                hit: true,
            }
        }
    };
    (px, fetches)
}

/// The slab clip of a ray against the closed box: `(t_enter, t_exit, entry axis)`, `None` when
/// the ray misses it or the box lies behind the eye. `t_enter` may be negative (eye inside); the
/// entry axis is `None` only when every component of `dir` is 0 (then the ray is not traced).
fn clip(lo: DVec3, hi: DVec3, eye: DVec3, dir: DVec3) -> Option<(f64, f64, Option<usize>)> {
    let (mut t_enter, mut t_exit, mut axis) = (f64::NEG_INFINITY, f64::INFINITY, None);
    for a in 0..3 {
        if dir[a] == 0.0 {
            if eye[a] < lo[a] || eye[a] > hi[a] {
                return None;
            }
            continue;
        }
        let (t1, t2) = ((lo[a] - eye[a]) / dir[a], (hi[a] - eye[a]) / dir[a]);
        let (near, far) = if t1 <= t2 { (t1, t2) } else { (t2, t1) };
        // Strictly greater: on an edge or corner the lowest axis keeps the entry.
        if near > t_enter {
            t_enter = near;
            axis = Some(a);
        }
        t_exit = t_exit.min(far);
    }
    (t_exit >= t_enter.max(0.0)).then_some((t_enter, t_exit, axis))
}

/// [`trace`] plus the number of trilinear fetches it made.
fn trace_counted(volume: &Volume, eye: DVec3, dir: DVec3, iso: f64) -> (Option<Hit>, u64) {
    let dir = dir.normalize_or_zero();
    if dir == DVec3::ZERO || !dir.is_finite() || !eye.is_finite() || iso.is_nan() {
        return (None, 0);
    }
    let (lo, hi) = (volume.box_min(), volume.box_max());
    let Some((t_enter, t_end, entry_axis)) = clip(lo, hi, eye, dir) else {
        return (None, 0);
    };
    let outside = t_enter > 0.0;
    let t_start = t_enter.max(0.0);

    let dims = volume.dims();
    let spacing = volume.spacing();
    let du = dir / spacing;
    // Voxel coordinates of the start point; the entry face's coordinate is snapped onto the face.
    let mut start = eye + t_start * dir;
    if let (true, Some(a)) = (outside, entry_axis) {
        start[a] = if dir[a] > 0.0 { lo[a] } else { hi[a] };
    }
    let u_start = volume.to_voxel(start);
    let u_at = |t: f64| u_start + (t - t_start) * du;

    // 3D DDA over the interior cell planes: next plane index and its t per axis.
    let mut plane = [0f64; 3];
    let mut next = [f64::INFINITY; 3];
    let mut step = [0f64; 3];
    for a in 0..3 {
        if dims[a] > 1 && du[a] != 0.0 {
            step[a] = du[a].signum();
            plane[a] = if du[a] > 0.0 { u_start[a].floor() + 1.0 } else { u_start[a].ceil() - 1.0 };
            next[a] = t_start + (plane[a] - u_start[a]) / du[a];
        }
    }

    let mut fetches = 0u64;
    // Whether f >= iso at the last point looked at: outside the box f is empty (below); an eye
    // inside the box takes the state of the field at the eye (inside the object or not).
    let mut above: Option<bool> = if outside { Some(false) } else { None };
    let mut t0 = t_start;
    loop {
        let t1 = next[0].min(next[1]).min(next[2]).min(t_end).max(t0);
        fetches += 1;
        let cell = Cell::along(volume, u_at(0.5 * (t0 + t1)), u_at(t0), du);
        let g = cell.cubic(iso);
        let was_above = *above.get_or_insert(eval(&g, 0.0) >= 0.0);
        match first_up_crossing(&g, t1 - t0, was_above) {
            Crossing::At(s) => {
                let t = (t0 + s).min(t1);
                let cap = outside && t == t_start;
                let mut position = eye + t * dir;
                let normal = if cap {
                    let a = entry_axis.expect("an eye outside the box enters it through a face");
                    position[a] = start[a];
                    let mut n = DVec3::ZERO;
                    n[a] = if dir[a] > 0.0 { -1.0 } else { 1.0 };
                    n
                } else {
                    fetches += 6;
                    let grad = volume.gradient(position);
                    let scale = cell.max_abs().max(iso.abs()) / spacing.min_element();
                    let len = grad.length();
                    if len.is_finite() && len > 0.0 && len > 1e-12 * scale {
                        -grad / len
                    } else {
                        -dir
                    }
                };
                return (Some(Hit { t, position, normal, cap }), fetches);
            }
            Crossing::None { above_at_end } => above = Some(above_at_end),
        }
        if t1 >= t_end {
            return (None, fetches);
        }
        for a in 0..3 {
            if next[a] <= t1 {
                plane[a] += step[a];
                next[a] = t_start + (plane[a] - u_start[a]) / du[a];
            }
        }
        t0 = t1;
    }
}

/// The trilinear interpolant of one cell along a ray segment, in local voxel coordinates.
struct Cell {
    /// Corner values, index `dx + 2 * dy + 4 * dz`.
    c: [f64; 8],
    /// Local coordinates at the segment start (0..1 inside the cell) and their rates per unit t.
    x0: DVec3,
    dx: DVec3,
}

impl Cell {
    /// The cell containing voxel position `u_mid` (clamped to the grid), for a segment starting at
    /// voxel position `u0` and moving `du` per unit t. An axis with a single sample is constant.
    fn along(volume: &Volume, u_mid: DVec3, u0: DVec3, du: DVec3) -> Cell {
        let dims = volume.dims();
        let mut base = [0usize; 3];
        let mut off = [0usize; 3];
        let (mut x0, mut dx) = (DVec3::ZERO, DVec3::ZERO);
        for a in 0..3 {
            let n = dims[a];
            if n == 1 {
                continue;
            }
            let m = u_mid[a];
            let i = if m.is_nan() || m <= 0.0 { 0 } else { (m.floor() as usize).min(n - 2) };
            base[a] = i;
            off[a] = 1;
            x0[a] = u0[a] - i as f64;
            dx[a] = du[a];
        }
        let c = std::array::from_fn(|k| {
            let (i, j, l) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
            volume.at(base[0] + i * off[0], base[1] + j * off[1], base[2] + l * off[2]) as f64
        });
        Cell { c, x0, dx }
    }

    /// The largest corner magnitude.
    fn max_abs(&self) -> f64 {
        self.c.iter().fold(0.0, |m, v| m.max(v.abs()))
    }

    /// Coefficients (ascending powers of s, s = t - segment start) of f(s) - iso.
    fn cubic(&self, iso: f64) -> [f64; 4] {
        // Linear weights of the low and high corner along each axis, as polynomials in s.
        let w = |a: usize| ([1.0 - self.x0[a], -self.dx[a]], [self.x0[a], self.dx[a]]);
        let (wx, wy, wz) = (w(0), w(1), w(2));
        let lin = |p: [f64; 2], lo: f64, hi: f64, q: [f64; 2]| [lo * p[0] + hi * q[0], lo * p[1] + hi * q[1]];
        let mul2 = |p: [f64; 2], q: [f64; 2]| [p[0] * q[0], p[0] * q[1] + p[1] * q[0], p[1] * q[1]];
        let mut quad = [[0f64; 3]; 2];
        for (l, q) in quad.iter_mut().enumerate() {
            // Along x for both y, then along y.
            let e0 = lin(wx.0, self.c[4 * l], self.c[1 + 4 * l], wx.1);
            let e1 = lin(wx.0, self.c[2 + 4 * l], self.c[3 + 4 * l], wx.1);
            let a = mul2(e0, wy.0);
            let b = mul2(e1, wy.1);
            *q = [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
        }
        // Along z.
        let mul3 = |p: [f64; 3], q: [f64; 2]| {
            [p[0] * q[0], p[0] * q[1] + p[1] * q[0], p[1] * q[1] + p[2] * q[0], p[2] * q[1]]
        };
        let a = mul3(quad[0], wz.0);
        let b = mul3(quad[1], wz.1);
        [a[0] + b[0] - iso, a[1] + b[1], a[2] + b[2], a[3] + b[3]]
    }
}

/// The cubic at s (Horner).
fn eval(g: &[f64; 4], s: f64) -> f64 {
    ((g[3] * s + g[2]) * s + g[1]) * s + g[0]
}

/// What a segment gave.
#[derive(Debug, PartialEq)]
enum Crossing {
    /// An up-crossing at local s.
    At(f64),
    /// None; whether g >= 0 at the segment end.
    None { above_at_end: bool },
}

/// The first s in [0, len] where g goes from < 0 to >= 0, given whether g was >= 0 just before
/// s = 0 (`above`). A segment that starts at g >= 0 after a state below is a crossing at s = 0.
fn first_up_crossing(g: &[f64; 4], len: f64, mut above: bool) -> Crossing {
    let v0 = eval(g, 0.0);
    if !above && v0 >= 0.0 {
        return Crossing::At(0.0);
    }
    above = v0 >= 0.0;
    if len.is_nan() || len <= 0.0 {
        return Crossing::None { above_at_end: above };
    }
    // Monotone pieces between the interior roots of g' = g1 + 2 g2 s + 3 g3 s^2.
    let mut ends = [len; 3];
    let mut n = 0;
    for r in quadratic_roots(3.0 * g[3], 2.0 * g[2], g[1]) {
        if r > 0.0 && r < len && (n == 0 || r > ends[n - 1]) {
            ends[n] = r;
            n += 1;
        }
    }
    ends[n] = len;
    let mut lo = 0.0;
    for &hi in &ends[..=n] {
        let v = eval(g, hi);
        if !above && v >= 0.0 {
            return Crossing::At(bisect(g, lo, hi));
        }
        above = v >= 0.0;
        lo = hi;
    }
    Crossing::None { above_at_end: above }
}

/// The smallest s in (lo, hi] with g(s) >= 0 to full f64 precision, given g(lo) < 0 <= g(hi).
fn bisect(g: &[f64; 4], mut lo: f64, mut hi: f64) -> f64 {
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if eval(g, mid) >= 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    hi
}

/// Real roots of a s^2 + b s + c = 0 in ascending order (NaN where absent), computed stably;
/// degenerates to the linear root when a = 0.
fn quadratic_roots(a: f64, b: f64, c: f64) -> [f64; 2] {
    let mut r = [f64::NAN; 2];
    if a == 0.0 {
        if b != 0.0 {
            r[0] = -c / b;
        }
        return r;
    }
    let disc = b * b - 4.0 * a * c;
    if disc.is_nan() || disc < 0.0 {
        return r;
    }
    let q = -0.5 * (b + b.signum() * disc.sqrt());
    r[0] = q / a;
    r[1] = if q != 0.0 { c / q } else { r[0] };
    if r[1] < r[0] {
        r.swap(0, 1);
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use isowall_wall::{Camera, Window};

    /// A volume sampling `f` at the world positions of its samples.
    fn field(dims: [usize; 3], spacing: DVec3, origin: DVec3, f: impl Fn(DVec3) -> f64) -> Volume {
        let mut data = Vec::with_capacity(dims[0] * dims[1] * dims[2]);
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    data.push(f(origin + spacing * DVec3::new(i as f64, j as f64, k as f64)) as f32);
                }
            }
        }
        Volume::new("test", dims, spacing, origin, data).unwrap()
    }

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn a_volume_all_above_iso_is_hit_on_the_entered_face() {
        let v = field([4, 5, 6], DVec3::new(1.0, 2.0, 0.5), DVec3::new(1.0, 2.0, 3.0), |_| 1.0);
        assert_eq!(v.box_max(), DVec3::new(4.0, 10.0, 5.5));
        // Straight at the x = 1 face from 6 units away.
        let h = trace(&v, DVec3::new(-5.0, 4.0, 4.0), DVec3::X, 0.5).unwrap();
        assert!(h.cap && close(h.t, 6.0, 1e-12), "{h:?}");
        assert_eq!(h.normal, -DVec3::X);
        assert_eq!(h.position.x, 1.0);
        // Obliquely down onto the top face z = 5.5.
        let eye = DVec3::new(2.5, 6.0, 20.0);
        let dir = DVec3::new(0.1, -0.2, -1.0).normalize();
        let h = trace(&v, eye, dir, 0.5).unwrap();
        assert!(h.cap && close(h.t, (5.5 - 20.0) / dir.z, 1e-12), "{h:?}");
        assert_eq!(h.normal, DVec3::Z);
        assert_eq!(h.position.z, 5.5);
        // Through the edge x = 1, y = 2 exactly: both slabs give the entry; x (the lowest axis) wins.
        let dir = DVec3::new(1.0, 2.0, 0.0).normalize();
        let h = trace(&v, DVec3::new(0.0, 0.0, 4.0), dir, 0.5).unwrap();
        assert!(h.cap && close(h.t, 5f64.sqrt(), 1e-12), "{h:?}");
        assert_eq!(h.normal, -DVec3::X);
        // An iso above the data: nothing.
        assert!(trace(&v, DVec3::new(-5.0, 4.0, 4.0), DVec3::X, 1.5).is_none());
    }

    #[test]
    fn a_linear_field_is_hit_where_it_reaches_iso() {
        // f = z - 5.3: trilinear interpolation reproduces it exactly (up to the f32 rounding of the
        // voxels, hence tolerances of 1e-6).
        let (s, o) = (DVec3::new(0.7, 1.3, 0.9), DVec3::new(-1.0, -2.0, -0.5));
        let v = field([8, 8, 12], s, o, |p| p.z - 5.3);
        let eye = DVec3::new(0.5, 0.3, -10.0);
        let dir = DVec3::new(0.05, 0.1, 1.0).normalize();
        let h = trace(&v, eye, dir, 0.0).unwrap();
        assert!(!h.cap && close(h.t, 15.3 / dir.z, 1e-6), "{h:?}");
        assert!((h.normal + DVec3::Z).length() < 1e-6, "{h:?}");
        assert!((h.position - (eye + h.t * dir)).length() < 1e-12);
        // From above, the ray enters at the top face z = 9.4 already inside {f >= 0}: a cap.
        let h = trace(&v, DVec3::new(0.5, 0.3, 20.0), -DVec3::Z, 0.0).unwrap();
        assert!(h.cap && close(h.t, 20.0 - 9.4, 1e-6) && h.normal == DVec3::Z, "{h:?}");

        // A generic linear field: depth and normal are analytic (the hit is > 1 voxel from the faces,
        // so the central differences are not clamped).
        let grad = DVec3::new(0.3, -0.5, 0.8);
        let f = |p: DVec3| grad.dot(p) + 0.1;
        let v = field([8, 8, 12], s, o, f);
        let (eye, iso) = (DVec3::new(-6.0, 9.0, -4.0), 1.0);
        let dir = (DVec3::new(1.5, 2.5, 4.5) - eye).normalize();
        let t = (iso - f(eye)) / grad.dot(dir);
        let h = trace(&v, eye, dir, iso).unwrap();
        let p = eye + t * dir;
        assert!(p.cmpgt(o + s).all() && p.cmplt(v.box_max() - s).all(), "test setup: {p:?}");
        assert!(!h.cap && close(h.t, t, 1e-6), "{h:?} want t = {t}");
        assert!((h.normal + grad.normalize()).length() < 1e-6, "{h:?}");
    }

    /// Along z: object, gap, object (f = 1, -1, 1) on a 4x4x8 grid, spacing 1.
    fn two_slabs() -> Volume {
        field([4, 4, 8], DVec3::ONE, DVec3::ZERO, |p| if (3.0..=4.0).contains(&p.z) { -1.0 } else { 1.0 })
    }

    #[test]
    fn a_camera_inside_the_object_sees_the_next_surface_out_of_it() {
        let v = two_slabs();
        // From inside the lower object looking up: leaves it at z = 2.5, hits the upper at z = 4.5.
        let h = trace(&v, DVec3::new(1.5, 1.5, 1.0), DVec3::Z, 0.0).unwrap();
        assert!(!h.cap && close(h.t, 3.5, 1e-12), "{h:?}");
        assert!((h.normal + DVec3::Z).length() < 1e-12, "{h:?}");
        // Looking down from inside the lower object: leaves it, then only the box's end: no hit.
        assert!(trace(&v, DVec3::new(1.5, 1.5, 1.0), -DVec3::Z, 0.0).is_none());
        // Inside the box in the gap: the nearest surface either way.
        let h = trace(&v, DVec3::new(1.5, 1.5, 3.5), DVec3::Z, 0.0).unwrap();
        assert!(close(h.t, 1.0, 1e-12) && (h.normal + DVec3::Z).length() < 1e-12, "{h:?}");
        let h = trace(&v, DVec3::new(1.5, 1.5, 3.5), -DVec3::Z, 0.0).unwrap();
        assert!(close(h.t, 1.0, 1e-12) && (h.normal - DVec3::Z).length() < 1e-12, "{h:?}");
        // From outside below the box: the lower object is a cap at z = 0.
        let h = trace(&v, DVec3::new(1.5, 1.5, -2.0), DVec3::Z, 0.0).unwrap();
        assert!(h.cap && close(h.t, 2.0, 1e-12) && h.normal == -DVec3::Z, "{h:?}");
    }

    #[test]
    fn a_crossing_exactly_on_a_cell_face_is_found() {
        // f = -1, -1, -1, 0, 0, ... along z, iso 0: f reaches iso exactly at the plane z = 3.
        let v = field([3, 3, 6], DVec3::ONE, DVec3::ZERO, |p| if p.z >= 3.0 { 0.0 } else { -1.0 });
        let h = trace(&v, DVec3::new(1.0, 1.0, -1.0), DVec3::Z, 0.0).unwrap();
        assert!(!h.cap && close(h.t, 4.0, 1e-12), "{h:?}");
    }

    #[test]
    fn rays_that_miss_the_box_give_nothing() {
        let v = field([4, 4, 4], DVec3::ONE, DVec3::ZERO, |_| 1.0);
        // Pointing away from the box.
        assert!(trace(&v, DVec3::new(-2.0, 1.0, 1.0), -DVec3::X, 0.0).is_none());
        // Passing beside it.
        assert!(trace(&v, DVec3::new(-2.0, 5.0, 1.0), DVec3::X, 0.0).is_none());
        // Parallel to the y slab but outside it (a direction component of 0).
        assert!(trace(&v, DVec3::new(-2.0, 3.0001, 1.0), DVec3::X, 0.0).is_none());
        // ... and just inside it (on the face y = 3): a hit.
        assert!(trace(&v, DVec3::new(-2.0, 3.0, 1.0), DVec3::X, 0.0).unwrap().cap);
        // Degenerate rays.
        assert!(trace(&v, DVec3::new(-2.0, 1.0, 1.0), DVec3::ZERO, 0.0).is_none());
        assert!(trace(&v, DVec3::new(-2.0, 1.0, 1.0), DVec3::new(f64::NAN, 0.0, 0.0), 0.0).is_none());
        assert!(trace(&v, DVec3::new(-2.0, 1.0, 1.0), DVec3::X, f64::NAN).is_none());
    }

    fn small_view(volume: &Volume, w: u32, h: u32) -> View {
        View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h)
    }

    fn assert_finite(frame: &Frame) {
        assert!(frame.color.iter().flatten().all(|c| c.is_finite()));
        assert!(frame.depth.iter().all(|d| d.is_finite() && *d >= 0.0));
        assert!(frame.normal.iter().flatten().all(|c| c.is_finite()));
    }

    #[test]
    fn tiny_and_flat_volumes_render_without_panicking() {
        // 1x1x1: a single point, hit only by a ray through it (a cap on the face entered).
        let one = Volume::new("one", [1, 1, 1], DVec3::ONE, DVec3::new(1.0, 2.0, 3.0), vec![5.0]).unwrap();
        let h = trace(&one, DVec3::new(1.0, 2.0, -4.0), DVec3::Z, 1.0).unwrap();
        assert!(h.cap && close(h.t, 7.0, 1e-12) && h.normal == -DVec3::Z, "{h:?}");
        assert!(trace(&one, DVec3::new(1.0, 2.0, -4.0), DVec3::Z, 6.0).is_none());
        assert!(trace(&one, DVec3::new(1.0, 2.0, 3.0), DVec3::Z, 1.0).is_none(), "eye inside the object");
        let s = RenderSettings::new(1.0);
        let f = render(&one, &small_view(&one, 9, 7), &s);
        assert_finite(&f);

        // 2x2x2: one corner above iso.
        let mut d = vec![0.0f32; 8];
        d[0] = 1.0;
        let two = Volume::new("two", [2, 2, 2], DVec3::ONE, DVec3::ZERO, d).unwrap();
        let f = render(&two, &small_view(&two, 32, 24), &RenderSettings::new(0.5));
        assert_finite(&f);
        assert!(f.hit_count() > 0 && f.hit_count() < 32 * 24, "{}", f.hit_count());

        // A flat volume (dims 1 along z): a sheet, met in one point by an oblique ray ...
        let flat = field([5, 4, 1], DVec3::ONE, DVec3::ZERO, |p| p.x);
        let h = trace(&flat, DVec3::new(3.0, 1.0, 5.0), DVec3::new(0.1, 0.2, -1.0).normalize(), 2.5).unwrap();
        assert!(h.cap && h.normal == DVec3::Z && h.position.z == 0.0, "{h:?}");
        assert!(
            trace(&flat, DVec3::new(1.0, 1.0, 5.0), DVec3::new(0.1, 0.2, -1.0).normalize(), 2.5).is_none()
        );
        // ... and a ray inside its plane sees a 2D field.
        let h = trace(&flat, DVec3::new(-3.0, 1.5, 0.0), DVec3::X, 2.5).unwrap();
        assert!(!h.cap && close(h.t, 5.5, 1e-12) && (h.normal + DVec3::X).length() < 1e-12, "{h:?}");
        let f = render(&flat, &small_view(&flat, 16, 12), &RenderSettings::new(2.5));
        assert_finite(&f);
    }

    /// A saddle: f = -1, 1, 1, -1 at the (x, y) corners, the same for both z. Along the diagonal
    /// x = y = s, f = -(2s - 1)^2: it touches 0 at the centre.
    fn saddle() -> Volume {
        let d = [-1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0, -1.0];
        Volume::new("saddle", [2, 2, 2], DVec3::ONE, DVec3::ZERO, d.to_vec()).unwrap()
    }

    #[test]
    fn a_tangent_graze_gives_no_nan() {
        let v = saddle();
        let (eye, dir) = (DVec3::new(-1.0, -1.0, 0.5), DVec3::new(1.0, 1.0, 0.0).normalize());
        let r2 = 2f64.sqrt();
        // Exactly tangent: a hit at the touching point or none, never NaN.
        if let Some(h) = trace(&v, eye, dir, 0.0) {
            assert!(close(h.t, 1.5 * r2, 1e-6), "{h:?}");
            assert!(h.normal.is_finite() && (h.normal + dir).length() < 1e-6, "{h:?}");
        }
        // Just below the touch: two close roots, the first is the hit.
        let h = trace(&v, eye, dir, -1e-6).unwrap();
        assert!(close(h.t, r2 * (1.0 + 0.4995), 1e-9), "{h:?}");
        assert!(h.normal.is_finite() && (h.normal + dir).length() < 1e-6, "{h:?}");
        // Just above: no hit.
        assert!(trace(&v, eye, dir, 1e-6).is_none());
        // Entering the saddle's top face at its centre (f = 0 there): a cap with the face normal.
        let h = trace(&v, DVec3::new(0.5, 0.5, 3.0), -DVec3::Z, 0.0).unwrap();
        assert!(h.cap && h.normal == DVec3::Z, "{h:?}");
        let f = render(&v, &small_view(&v, 24, 24), &RenderSettings::new(0.0));
        assert_finite(&f);
    }

    #[test]
    fn a_vanishing_gradient_falls_back_to_the_viewer_direction() {
        // Along z: 2, -1, 1, 0. The surface z = 1.5 has f(0.5) = f(2.5) = 0.5: the central
        // difference with h = 1 is exactly 0 there.
        let v = field([3, 3, 4], DVec3::ONE, DVec3::ZERO, |p| [2.0, -1.0, 1.0, 0.0][p.z as usize]);
        let dir = DVec3::new(0.1, 0.0, 1.0).normalize();
        let h = trace(&v, DVec3::new(1.0, 1.0, 0.75), dir, 0.0).unwrap();
        assert!(!h.cap && close(h.t, 0.75 / dir.z, 1e-12), "{h:?}");
        assert!(v.gradient(h.position).length() < 1e-12);
        assert_eq!(h.normal, -dir);
    }

    #[test]
    fn cubic_pieces_give_the_first_up_crossing() {
        // g = -(s - 1/4)(s - 1/2)(s - 3/4): >= 0 at 0, down at 1/4, up at 1/2, down at 3/4.
        let g = [3.0 / 32.0, -11.0 / 16.0, 1.5, -1.0];
        assert!(close(eval(&g, 0.25), 0.0, 1e-15) && close(eval(&g, 0.5), 0.0, 1e-15));
        assert_eq!(first_up_crossing(&g, 1.0, false), Crossing::At(0.0));
        match first_up_crossing(&g, 1.0, true) {
            Crossing::At(s) => assert!(close(s, 0.5, 1e-14), "{s}"),
            c => panic!("{c:?}"),
        }
        // The segment ends before the up-crossing: the state at its end is below.
        assert_eq!(first_up_crossing(&g, 0.4, true), Crossing::None { above_at_end: false });
        // A double root (tangent from below) and a constant: no NaN anywhere.
        let g = [-0.25, 1.0, -1.0, 0.0]; // -(s - 1/2)^2
        match first_up_crossing(&g, 1.0, false) {
            Crossing::At(s) => assert!(close(s, 0.5, 1e-7), "{s}"),
            Crossing::None { above_at_end } => assert!(!above_at_end),
        }
        assert_eq!(first_up_crossing(&[0.0; 4], 1.0, false), Crossing::At(0.0));
        assert_eq!(
            first_up_crossing(&[-1.0, 0.0, 0.0, 0.0], 0.0, false),
            Crossing::None { above_at_end: false }
        );
        assert_eq!(quadratic_roots(0.0, 0.0, 1.0).map(f64::is_nan), [true, true]);
        assert_eq!(quadratic_roots(1.0, -3.0, 2.0), [1.0, 2.0]);
    }

    #[test]
    fn a_spike_thinner_than_half_a_voxel_is_found() {
        // One voxel at 1 in a zero 9^3 volume, iso 0.9: {f >= 0.9} is a tiny blob around (4, 4, 4).
        let v = field([9, 9, 9], DVec3::ONE, DVec3::ZERO, |p| if p == DVec3::splat(4.0) { 1.0 } else { 0.0 });
        let (eye, dir, iso) = (DVec3::new(0.25, 4.02, 3.97), DVec3::X, 0.9);
        // A march with a half-voxel step from the eye steps over it ...
        let mut t = 0.0;
        while t <= 7.75 {
            assert!(v.sample(eye + t * dir).unwrap() < iso, "t = {t}");
            t += 0.5;
        }
        // ... the exact method does not: f = (x - 3) * (1 - 0.02) * 0.97 in the cell before the voxel.
        let want_x = 3.0 + iso / ((1.0 - (4.02 - 4.0)) * (3.97 - 3.0));
        let h = trace(&v, eye, dir, iso).unwrap();
        assert!(close(h.t, want_x - 0.25, 1e-9), "{h:?} want x = {want_x}");
        assert!(!h.cap && h.normal.x < -0.5, "{h:?}");
    }

    #[test]
    fn render_matches_trace_and_windows_match_the_whole_image() {
        let c = DVec3::new(7.3, 6.8, 7.9);
        let v = field([16, 15, 17], DVec3::ONE, DVec3::ZERO, |p| 5.5 - (p - c).length());
        let whole = small_view(&v, 24, 18);
        let mut s = RenderSettings::new(0.0);
        let f = render(&v, &whole, &s);
        assert!(f.hit_count() > 20 && f.hit_count() < 24 * 18, "{}", f.hit_count());
        assert!(f.fetches > f.pixel_count() as u64);
        let b = whole.camera.basis();
        for y in 0..18 {
            for x in 0..24 {
                let i = y as usize * 24 + x as usize;
                let dir = whole.ray_dir(&b, x, y);
                match trace(&v, whole.camera.eye, dir, 0.0) {
                    None => {
                        assert!(!f.hit[i] && f.depth[i] == 0.0 && f.normal[i] == [0.0; 3]);
                        assert_eq!(f.color[i], s.background.map(|c| c as f32));
                    }
                    Some(h) => {
                        assert!(f.hit[i] && f.depth[i] == h.t as f32);
                        assert_eq!(f.normal[i], h.normal.to_array().map(|c| c as f32));
                        assert!(f.color[i].iter().all(|c| *c > 0.0));
                    }
                }
            }
        }
        let tile = View { window: Window { x: 5, y: 7, width: 11, height: 6 }, ..whole };
        let t = render(&v, &tile, &s);
        for y in 0..6 {
            for x in 0..11 {
                let (i, j) = (y * 11 + x, (y + 7) * 24 + x + 5);
                assert_eq!((t.hit[i], t.depth[i], t.color[i]), (f.hit[j], f.depth[j], f.color[j]));
            }
        }
        // Rendering is deterministic, and exposure scales the colour of hits only.
        let again = render(&v, &whole, &s);
        assert_eq!((again.color, again.depth, again.fetches), (f.color.clone(), f.depth.clone(), f.fetches));
        s.exposure = 2.0;
        let bright = render(&v, &whole, &s);
        for i in 0..f.pixel_count() {
            let k = if f.hit[i] { 2.0 } else { 1.0 };
            assert!((bright.color[i][0] - k * f.color[i][0]).abs() < 1e-6);
        }
    }
}
