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
//! - **Shading** uses `N` flipped to face the viewer (`N_s` below), the light of the settings in
//!   the camera frame, [`shade`] with its ambient term replaced by the ambient/IBL term `E`, and
//!   the exposure: colour = exposure * (albedo * direct + albedo * E). Pixels without a hit hold
//!   the background colour and zero in every other AOV.
//! - **Single-sample axes** (dims 1): the box is flat on that axis and the field is constant along
//!   it; a ray through such a box meets it in one point (or runs inside the plane).
//!
//! # Ambient occlusion (DESIGN.md "AO"), `AoMethod::Ours`, exact
//!
//! With `ao.samples = N > 0`, every hit `p` casts N rays from the surface ([`AoSurface`]):
//! from `o = p + eps * Ng` (`eps = ao.offset_voxels * min spacing`, 0.01 voxel), Ng the trilinear
//! field's own gradient in p's cell turned towards where the primary ray came from (a cap's face
//! normal), in the directions `w_i = cosine_direction(N, ao_point(ao.sequence, i, pixel_key(px,
//! py, ao.frame, ao.seed)))` of [`crate::sampling`] (px, py: the pixel in the *full* image), N the
//! central-difference normal as it is, *not* turned towards the viewer (Ng where its gradient
//! vanished). Ray i is occluded (`V_i = 1`) when the exact trilinear field reaches `f >= iso` at
//! some `t` in `[0, R]`, `R` the AO radius
//! ([`AoSettings::radius_world`](isowall_model::AoSettings::radius_world)) or the box exit when
//! unbounded; `t = 0` is included, so an origin inside the object is occluded. A direction under
//! p's tangent plane (`w . Ng <= 0`, [`under_tangent_plane`]) is occluded without marching: from
//! p itself it enters the object at once (the integral's value at eps -> 0), where marched from o
//! it could escape over a curved surface. Outside the box
//! the field is empty, so a ray that leaves the box is open (and one whose origin lies outside the
//! box is tested from where it enters it, if it does). Exact: the ray walks the cells like a
//! primary ray and each segment's cubic is tested for `max >= iso` (its ends and the roots of its
//! derivative), no step, no up-crossing needed. `A = (1/N) sum V_i`; the bent normal is the
//! normalized sum of the unoccluded `w_i`, and N when none is (`N_s` when AO is off).
//!
//! # `AoMethod::Seed`: the 2008 baseline, ported faithfully with its flaws (not our method)
//!
//! See [`seed_ambient`]. Directions from [`crate::sampling::seed_directions`] (all on one
//! diagonal of the disk, the ones outside it skipped but counted), lifted around `N_s`; a fixed
//! march in texture space; no origin offset; occluded on a strict `vpold < iso < vp` pair.
//!
//! # IBL (DESIGN.md "IBL"): the ambient term `E` (for albedo 1, before exposure)
//!
//! - `IblMethod::None`: `E = ambient * (1 - A)` (the light's constant ambient). With AO off
//!   (`A = 0`) this is exactly the renderer's colour before AO existed.
//! - `Seed`: `E = L_env(bent) * (1 - A)`, the raw environment at the bent normal.
//! - `Bent`: `E = irradiance(sh9, bent) * (1 - A)` ([`Environment::irradiance`]; SH9 projected
//!   once per frame).
//! - `Rays`: `E = (1/N) sum (1 - V_i) L_env(w_i)`: every escaping AO ray looks the environment
//!   up in its own direction; the cosine weighting is in the sample density, so this is an
//!   unbiased estimate of `(1/pi) ∫ L_env V cos`. For the seed AO method, its non-skipped
//!   directions likewise, divided by its N (skipped samples count as 0).
//!   With AO off (`samples = 0`) there are no rays: `E` falls back to `irradiance(sh9, N_s)`.
//!
//! Without an environment (`None`) an IBL method lights with the uniform environment
//! `Environment::constant(ambient)`, so it degrades to the constant ambient instead of failing.
//!
//! `fetches` counts trilinear field evaluations: one per cell a ray visits (its eight corner
//! reads), primary or AO, six per hit for the gradient and one per step of the seed AO march.

use crate::environment::Environment;
use crate::frame::Frame;
use crate::sampling::{ao_point, cosine_direction, pixel_key, seed_directions, seed_lift};
use glam::DVec3;
use isowall_model::camera::Basis;
use isowall_model::render_state::shade;
use isowall_model::{AoMethod, IblMethod, RenderSettings, View};
use isowall_volume::Volume;
use std::borrow::Cow;
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

/// Renders the rectangle of `view` with the exact reference method, without an environment (an IBL
/// method other than `None` then lights with the constant ambient, see the module documentation).
pub fn render(volume: &Volume, view: &View, settings: &RenderSettings) -> Frame {
    render_with_env(volume, view, settings, None)
}

/// Renders the rectangle of `view` with the exact reference method, AO and IBL included (module
/// documentation), lit by `env` where the IBL method needs one. Rows are shared among
/// `available_parallelism` threads; the output does not depend on how.
pub fn render_with_env(
    volume: &Volume,
    view: &View,
    settings: &RenderSettings,
    env: Option<&Environment>,
) -> Frame {
    let basis = view.camera.basis();
    let (width, height) = (view.rect.width, view.rect.height);
    let _span = tracing::debug_span!("reference_render", width, height, iso = settings.iso).entered();
    let mut frame = Frame::new(width, height);
    let light = settings.light.world_direction(basis.forward, basis.right, basis.up);
    let lighting = IblLighting::new(settings, env);
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
                                let (px, f) =
                                    shade_pixel(volume, view, &basis, settings, &lighting, light, x, y);
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
            frame.occlusion[i] = px.occlusion;
            frame.bent_normal[i] = px.bent_normal;
            frame.ibl[i] = px.ibl;
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

/// Progressive accumulation (`--frames K`): the mean of `frames` renders with `ao.frame` =
/// `settings.ao.frame`, `+ 1`, ..., `+ K - 1` (wrapping), each with its fresh per-pixel
/// decorrelation. Colour, occlusion and E are averaged; the bent normal is the renormalized mean
/// of the frames' bent normals; depth, normal and hit are those of every frame (they do not depend
/// on the frame index); `fetches` is the total. `frames = 0` counts as 1, and 1 gives exactly
/// [`render_with_env`].
pub fn render_accumulated(
    volume: &Volume,
    view: &View,
    settings: &RenderSettings,
    env: Option<&Environment>,
    frames: u32,
) -> Frame {
    render_accumulated_reporting(volume, view, settings, env, frames, None)
}

/// [`render_accumulated`], calling `on_frame(k)` as each frame is done (k from 1 to `frames`).
pub fn render_accumulated_reporting(
    volume: &Volume,
    view: &View,
    settings: &RenderSettings,
    env: Option<&Environment>,
    frames: u32,
    mut on_frame: Option<&mut dyn FnMut(u32)>,
) -> Frame {
    let k = frames.max(1);
    let mut first = render_with_env(volume, view, settings, env);
    if let Some(report) = on_frame.as_mut() {
        report(1);
    }
    if k == 1 {
        return first;
    }
    let n = first.pixel_count();
    let widen = |v: [f32; 3]| v.map(f64::from);
    let mut color: Vec<[f64; 3]> = first.color.iter().map(|&c| widen(c)).collect();
    let mut occlusion: Vec<f64> = first.occlusion.iter().map(|&a| a as f64).collect();
    let mut ibl: Vec<[f64; 3]> = first.ibl.iter().map(|&e| widen(e)).collect();
    let mut bent: Vec<DVec3> = first.bent_normal.iter().map(|&b| DVec3::from(widen(b))).collect();
    for f in 1..k {
        let mut s = *settings;
        s.ao.frame = settings.ao.frame.wrapping_add(f);
        let next = render_with_env(volume, view, &s, env);
        first.fetches += next.fetches;
        for i in 0..n {
            for c in 0..3 {
                color[i][c] += next.color[i][c] as f64;
                ibl[i][c] += next.ibl[i][c] as f64;
            }
            occlusion[i] += next.occlusion[i] as f64;
            bent[i] += DVec3::from(widen(next.bent_normal[i]));
        }
        if let Some(report) = on_frame.as_mut() {
            report(f + 1);
        }
    }
    let kf = k as f64;
    for i in 0..n {
        first.color[i] = color[i].map(|c| (c / kf) as f32);
        first.ibl[i] = ibl[i].map(|c| (c / kf) as f32);
        first.occlusion[i] = (occlusion[i] / kf) as f32;
        if first.hit[i] {
            // Every frame's bent normal lies in the hemisphere of N, so the sum is not zero;
            // should it be, the first frame's is kept.
            if let Some(b) = bent[i].try_normalize() {
                first.bent_normal[i] = b.to_array().map(|c| c as f32);
            }
        }
    }
    first
}

/// The environment and its SH9 projection an IBL method lights with, prepared once per frame.
pub struct IblLighting<'a> {
    method: IblMethod,
    ambient: [f64; 3],
    /// `None` for `IblMethod::None`.
    env: Option<Cow<'a, Environment>>,
    /// SH9 of `env` (zero where not needed).
    sh: [[f32; 3]; 9],
}

impl<'a> IblLighting<'a> {
    /// Prepares the lighting of `settings.ao.ibl` from `env`, or from the uniform environment of
    /// the light's ambient when `env` is `None`.
    pub fn new(settings: &RenderSettings, env: Option<&'a Environment>) -> IblLighting<'a> {
        let method = settings.ao.ibl;
        let ambient = settings.light.ambient;
        let env = (method != IblMethod::None).then(|| match env {
            Some(e) => Cow::Borrowed(e),
            None => Cow::Owned(Environment::constant(ambient.map(|c| c as f32))),
        });
        let sh = match (&env, method) {
            (Some(e), IblMethod::Bent | IblMethod::Rays) => e.sh9(),
            _ => [[0.0; 3]; 9],
        };
        IblLighting { method, ambient, env, sh }
    }

    /// L_env towards `d` (zero without an environment).
    fn radiance(&self, d: DVec3) -> [f64; 3] {
        self.env.as_ref().map_or([0.0; 3], |e| e.lookup(d).map(f64::from))
    }

    /// Whether the AO rays must look up the environment.
    fn rays(&self) -> bool {
        self.method == IblMethod::Rays
    }

    /// E from A, the bent normal and (for `Rays`) the sum of L_env over the escaping rays of `n`
    /// samples.
    fn irradiance(&self, a: f64, bent: DVec3, ray_sum: [f64; 3], n: u32) -> [f64; 3] {
        let open = 1.0 - a;
        match self.method {
            IblMethod::None => self.ambient.map(|c| c * open),
            IblMethod::Seed => self.radiance(bent).map(|c| c * open),
            IblMethod::Bent => Environment::irradiance(&self.sh, bent).map(|c| c as f64 * open),
            IblMethod::Rays if n == 0 => Environment::irradiance(&self.sh, bent).map(f64::from),
            IblMethod::Rays => ray_sum.map(|c| c / n as f64),
        }
    }
}

/// What AO and IBL give at one surface point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ambient {
    /// A in [0, 1], 0 = open.
    pub occlusion: f64,
    /// Unit bent normal (N where no ray is open, `N_s` where AO is off).
    pub bent_normal: DVec3,
    /// E for albedo 1 before exposure, linear RGB.
    pub irradiance: [f64; 3],
    /// Trilinear fetches the AO rays made.
    pub fetches: u64,
}

/// A hit as the AO rays see it (DESIGN.md "AO").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AoSurface {
    /// The hit point p on the surface.
    pub position: DVec3,
    /// N, the hemisphere's axis: the central-difference normal as it is (not turned towards the
    /// viewer), or `geometric` where that gradient vanished (N is then the viewer fallback).
    pub normal: DVec3,
    /// Ng: the trilinear field's own gradient in p's cell, `-grad / |grad|`, turned to the side the
    /// primary ray came from (`-dir` where it vanishes); for a cap, the face's outward normal.
    pub geometric: DVec3,
    /// N turned towards the viewer, as shading uses it (and the `seed` baseline).
    pub facing: DVec3,
}

impl AoSurface {
    /// The AO view of a primary hit at `position` with the normal of the `normal` AOV (DESIGN.md
    /// "Normal": `-dir` where the gradient vanished), reached along the unit `dir`; `cap`: the hit
    /// is on a box face (its normal the face's). The GPU's AO kernel applies the same rules to its
    /// own hits (shaders/ao.wgsl).
    pub fn new(volume: &Volume, position: DVec3, normal: DVec3, dir: DVec3, cap: bool) -> AoSurface {
        let facing = if normal.dot(-dir) < 0.0 { -normal } else { normal };
        let geometric = if cap { normal } else { geometric_normal(volume, position, dir) };
        // The shading normal's fallback for a vanished gradient is exactly -dir.
        let normal = if !cap && normal == -dir { geometric } else { normal };
        AoSurface { position, normal, geometric, facing }
    }

    /// [`AoSurface::new`] for a hit of [`trace`].
    pub fn of_hit(volume: &Volume, hit: &Hit, dir: DVec3) -> AoSurface {
        AoSurface::new(volume, hit.position, hit.normal, dir.normalize(), hit.cap)
    }
}

/// Ng at a surface point `p` reached along `dir`: `-g / |g|` with g the trilinear field's own
/// gradient in p's cell ([`Volume::cell_gradient`]), turned so that `Ng . dir <= 0` (towards where
/// the ray came from); `-dir` where g vanishes or is not finite.
pub fn geometric_normal(volume: &Volume, p: DVec3, dir: DVec3) -> DVec3 {
    let g = volume.cell_gradient(p);
    let len = g.length();
    if !(len.is_finite() && len > 0.0) {
        return -dir;
    }
    let n = -g / len;
    if n.dot(dir) > 0.0 {
        -n
    } else {
        n
    }
}

/// The origin of the AO rays (ours) of a surface point `p` with geometric normal `ng`:
/// `p + eps * ng`, eps = `ao.offset_voxels` (0.01) of the smallest spacing.
pub fn ao_origin(volume: &Volume, settings: &RenderSettings, p: DVec3, ng: DVec3) -> DVec3 {
    p + settings.ao.offset_voxels * volume.spacing().min_element() * ng
}

/// DESIGN.md "AO": a direction `w` under the tangent plane of a surface point with geometric
/// normal `ng` (`w . ng <= 0`) is occluded, without marching (inside p's cell the trilinear field
/// rises along it). The GPU's twin is `under_tangent_plane` in shaders/ao.wgsl.
pub fn under_tangent_plane(w: DVec3, ng: DVec3) -> bool {
    w.dot(ng) <= 0.0
}

/// AO, bent normal and E at the surface point `surface`, seen through pixel `(px, py)` of the full
/// image (module documentation; `settings.ao.method` picks ours or the seed baseline).
pub fn ambient_at(
    volume: &Volume,
    settings: &RenderSettings,
    lighting: &IblLighting,
    surface: &AoSurface,
    (px, py): (u32, u32),
) -> Ambient {
    let ao = &settings.ao;
    let n = ao.samples;
    if n == 0 || ao.method == AoMethod::Seed {
        return seed_ambient(volume, settings, lighting, surface.position, surface.facing);
    }
    let key = pixel_key(px, py, ao.frame, ao.seed);
    let axis = surface.normal;
    let o = ao_origin(volume, settings, surface.position, surface.geometric);
    let radius = ao.radius_world(volume.spacing());
    let (mut tally, mut fetches) = (Tally::default(), 0);
    for i in 0..n {
        let (u, v) = ao_point(ao.sequence, i, key);
        let w = cosine_direction(axis, u, v);
        let (hit, f) = if under_tangent_plane(w, surface.geometric) {
            (true, 0)
        } else {
            ao_ray_counted(volume, o, w, settings.iso, radius)
        };
        fetches += f;
        tally.add(hit, w, lighting);
    }
    tally.ambient(n, axis, lighting, fetches)
}

/// What the AO rays of one point found: how many were occluded, the sum of the open directions,
/// and the sum of L_env over them (when the lighting estimates by rays). Shared by ours and the
/// seed method.
#[derive(Default)]
struct Tally {
    occluded: u32,
    open_sum: DVec3,
    ray_sum: [f64; 3],
}

impl Tally {
    fn add(&mut self, occluded: bool, w: DVec3, lighting: &IblLighting) {
        if occluded {
            self.occluded += 1;
        } else {
            self.open_sum += w;
            if lighting.rays() {
                let l = lighting.radiance(w);
                (0..3).for_each(|c| self.ray_sum[c] += l[c]);
            }
        }
    }

    /// A = occluded / n (n counts skipped samples too); bent normal = the normalized open sum, or
    /// `axis` (the hemisphere's) when no ray was open; E from the lighting.
    fn ambient(&self, n: u32, axis: DVec3, lighting: &IblLighting, fetches: u64) -> Ambient {
        let occlusion = self.occluded as f64 / n as f64;
        let bent_normal = self.open_sum.try_normalize().unwrap_or(axis);
        let irradiance = lighting.irradiance(occlusion, bent_normal, self.ray_sum, n);
        Ambient { occlusion, bent_normal, irradiance, fetches }
    }
}

/// The 2008 RTPara AO shader, ported faithfully as the **baseline**, with its flaws (DESIGN.md):
/// this is *not* our method. For a hit `p` with viewer-facing normal `n_s` and `n_samples` = N:
///
/// - Position in the report's normalized volume space (3D texture coordinates of the box):
///   `q = (p - box_min) / (box_max - box_min)` per axis (a flat axis divides by 1 and keeps q = 0;
///   it takes no part in the range test below).
/// - Directions from [`seed_directions`]`(N)` (u = v: all on one diagonal of the disk), lifted
///   around `n_s` with [`seed_lift`]; the ones outside the disk are skipped but still counted in N.
/// - No origin offset. Each direction `w` (a *world* unit vector used as a texture-space one, as
///   the shader adds `t * dir` to the texture coordinate) is marched at `q_k = q + t_k w`,
///   `t_k = 0.01 k`, k = 1..=90 (t = 0.01 .. 0.9), whatever the voxel size; the field is the
///   trilinear interpolant at the world point `box_min + q_k (box_max - box_min)`. `vpold` starts
///   as the field at `p` (about iso); the ray is occluded at the first step with
///   `vpold < iso < vp` (strict). A step outside `[0, 1]^3` reads empty (`-inf`): no crossing,
///   and as the box is convex the ray cannot come back, so the march ends there.
/// - A = occluded / N; bent normal = normalized sum of the non-skipped unoccluded directions
///   (`n_s` when none).
pub fn seed_ambient(
    volume: &Volume,
    settings: &RenderSettings,
    lighting: &IblLighting,
    p: DVec3,
    n_s: DVec3,
) -> Ambient {
    let n = settings.ao.samples;
    if n == 0 {
        // AO off (either method): A = 0, bent normal N_s.
        let irradiance = lighting.irradiance(0.0, n_s, [0.0; 3], 0);
        return Ambient { occlusion: 0.0, bent_normal: n_s, irradiance, fetches: 0 };
    }
    let (tally, fetches) = seed_march(volume, settings.iso, p, n_s, n, lighting);
    tally.ambient(n, n_s, lighting, fetches)
}

/// The seed march of [`seed_ambient`]: what its rays found, and the fetches.
fn seed_march(
    volume: &Volume,
    iso: f64,
    p: DVec3,
    n_s: DVec3,
    n: u32,
    lighting: &IblLighting,
) -> (Tally, u64) {
    let (lo, hi) = (volume.box_min(), volume.box_max());
    let extent = hi - lo;
    let flat = extent.cmple(DVec3::ZERO);
    let q = (p - lo) / DVec3::select(flat, DVec3::ONE, extent);
    let q = DVec3::select(flat, DVec3::ZERO, q);
    let start = volume.sample_clamped(p);
    let (mut tally, mut fetches) = (Tally::default(), 1u64);
    for d in seed_directions(n).flatten() {
        let w = seed_lift(n_s, d);
        let mut vpold = start;
        let mut hit = false;
        for k in 1..=90 {
            let qt = q + (k as f64 * 0.01) * w;
            let inside = (0..3).all(|a| flat.test(a) || (0.0..=1.0).contains(&qt[a]));
            if !inside {
                break;
            }
            fetches += 1;
            let vp = volume.trilinear_voxel(volume.to_voxel(lo + qt * extent));
            if vpold < iso && iso < vp {
                hit = true;
                break;
            }
            vpold = vp;
        }
        tally.add(hit, w, lighting);
    }
    (tally, fetches)
}

/// Whether the AO ray `origin + t * dir` is occluded: the exact trilinear field reaches
/// `f >= iso` for some `t` in `[0, radius]` (`None`: to the box exit), outside the box empty.
/// `dir` is normalised here; a zero or non-finite ray or a NaN iso is open.
pub fn ao_ray_occluded(volume: &Volume, origin: DVec3, dir: DVec3, iso: f64, radius: Option<f64>) -> bool {
    ao_ray_counted(volume, origin, dir, iso, radius).0
}

/// [`ao_ray_occluded`] plus the fetches it made.
fn ao_ray_counted(volume: &Volume, o: DVec3, dir: DVec3, iso: f64, radius: Option<f64>) -> (bool, u64) {
    let dir = dir.normalize_or_zero();
    if dir == DVec3::ZERO || !dir.is_finite() || !o.is_finite() || iso.is_nan() {
        return (false, 0);
    }
    let Some((t_enter, t_exit, _)) = clip(volume.box_min(), volume.box_max(), o, dir) else {
        return (false, 0);
    };
    let t_start = t_enter.max(0.0);
    let t_end = radius.map_or(t_exit, |r| t_exit.min(r));
    if t_end.is_nan() || t_end < t_start {
        return (false, 0);
    }
    let u_start = volume.to_voxel(o + t_start * dir);
    let mut fetches = 0;
    for (t0, t1, cell) in CellWalk::new(volume, u_start, dir / volume.spacing(), t_start, t_end) {
        fetches += 1;
        // Every corner below iso: the trilinear blend is below it everywhere in the cell.
        if cell.max() < iso {
            continue;
        }
        if reaches(&cell.cubic(iso), t1 - t0) {
            return (true, fetches);
        }
    }
    (false, fetches)
}

/// One pixel's AOVs.
struct Pixel {
    color: [f32; 3],
    depth: f32,
    normal: [f32; 3],
    hit: bool,
    occlusion: f32,
    bent_normal: [f32; 3],
    ibl: [f32; 3],
}

/// Traces and shades the pixel (x, y) of the rectangle; returns it and the fetches made.
#[allow(clippy::too_many_arguments)]
fn shade_pixel(
    volume: &Volume,
    view: &View,
    basis: &Basis,
    settings: &RenderSettings,
    lighting: &IblLighting,
    light: DVec3,
    x: u32,
    y: u32,
) -> (Pixel, u64) {
    let dir = view.ray_dir(basis, x, y);
    let (hit, mut fetches) = trace_counted(volume, view.camera.eye, dir, settings.iso);
    let px = match hit {
        None => Pixel {
            color: settings.background.map(|c| c as f32),
            depth: 0.0,
            normal: [0.0; 3],
            hit: false,
            occlusion: 0.0,
            bent_normal: [0.0; 3],
            ibl: [0.0; 3],
        },
        Some(h) => {
            let v = -dir;
            let surface = AoSurface::of_hit(volume, &h, dir);
            let n = surface.facing;
            let pixel = (view.rect.x + x, view.rect.y + y);
            let amb = ambient_at(volume, settings, lighting, &surface, pixel);
            fetches += amb.fetches;
            // albedo * (E + light * N.L) + specular: shade() with its ambient replaced by E.
            let mut lit = *settings;
            lit.light.ambient = amb.irradiance;
            let c = shade(&lit, n, light, v);
            Pixel {
                color: c.map(|c| (c * settings.exposure) as f32),
                depth: h.t as f32,
                normal: h.normal.to_array().map(|c| c as f32),
                hit: true,
                occlusion: amb.occlusion as f32,
                bent_normal: amb.bent_normal.to_array().map(|c| c as f32),
                ibl: amb.irradiance.map(|c| c as f32),
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

/// The cells a ray crosses from `t_start` to `t_end`, front to back: `(t0, t1, cell)` per
/// segment, the cell's cubic in `s = t - t0`. The ray is at voxel position `u_start` at
/// `t_start` and moves `du` voxels per unit `t`. Shared by primary and AO rays.
struct CellWalk<'v> {
    volume: &'v Volume,
    u_start: DVec3,
    du: DVec3,
    t_start: f64,
    t_end: f64,
    /// 3D DDA over the interior cell planes: next plane index and its t per axis.
    plane: [f64; 3],
    next: [f64; 3],
    step: [f64; 3],
    t0: f64,
    done: bool,
}

impl<'v> CellWalk<'v> {
    fn new(volume: &'v Volume, u_start: DVec3, du: DVec3, t_start: f64, t_end: f64) -> CellWalk<'v> {
        let dims = volume.dims();
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
        CellWalk { volume, u_start, du, t_start, t_end, plane, next, step, t0: t_start, done: false }
    }

    fn u_at(&self, t: f64) -> DVec3 {
        self.u_start + (t - self.t_start) * self.du
    }
}

impl Iterator for CellWalk<'_> {
    type Item = (f64, f64, Cell);

    fn next(&mut self) -> Option<(f64, f64, Cell)> {
        if self.done {
            return None;
        }
        let t0 = self.t0;
        let t1 = self.next[0].min(self.next[1]).min(self.next[2]).min(self.t_end).max(t0);
        let cell = Cell::along(self.volume, self.u_at(0.5 * (t0 + t1)), self.u_at(t0), self.du);
        if t1 >= self.t_end {
            self.done = true;
        } else {
            for a in 0..3 {
                if self.next[a] <= t1 {
                    self.plane[a] += self.step[a];
                    self.next[a] = self.t_start + (self.plane[a] - self.u_start[a]) / self.du[a];
                }
            }
            self.t0 = t1;
        }
        Some((t0, t1, cell))
    }
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

    let spacing = volume.spacing();
    // Voxel coordinates of the start point; the entry face's coordinate is snapped onto the face.
    let mut start = eye + t_start * dir;
    if let (true, Some(a)) = (outside, entry_axis) {
        start[a] = if dir[a] > 0.0 { lo[a] } else { hi[a] };
    }

    let mut fetches = 0u64;
    // Whether f >= iso at the last point looked at: outside the box f is empty (below); an eye
    // inside the box takes the state of the field at the eye (inside the object or not).
    let mut above: Option<bool> = if outside { Some(false) } else { None };
    for (t0, t1, cell) in CellWalk::new(volume, volume.to_voxel(start), dir / spacing, t_start, t_end) {
        fetches += 1;
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
    }
    (None, fetches)
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

    /// The largest corner value: the trilinear blend inside the cell is never above it.
    fn max(&self) -> f64 {
        self.c.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v))
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

/// Whether g >= 0 somewhere on [0, len] (exact: the maximum of the cubic there is at 0, at len or
/// at a root of g'). A `len` that is not positive tests s = 0 only.
fn reaches(g: &[f64; 4], len: f64) -> bool {
    if eval(g, 0.0) >= 0.0 {
        return true;
    }
    if len.is_nan() || len <= 0.0 {
        return false;
    }
    eval(g, len) >= 0.0
        || quadratic_roots(3.0 * g[3], 2.0 * g[2], g[1])
            .into_iter()
            .any(|r| r > 0.0 && r < len && eval(g, r) >= 0.0)
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
    use isowall_model::{AoRadius, Camera, Rect};

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
    fn render_matches_trace_and_rects_match_the_whole_image() {
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
        let tile = View { rect: Rect { x: 5, y: 7, width: 11, height: 6 }, ..whole };
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
        s.exposure *= 2.0;
        let bright = render(&v, &whole, &s);
        for i in 0..f.pixel_count() {
            let k = if f.hit[i] { 2.0 } else { 1.0 };
            assert!((bright.color[i][0] - k * f.color[i][0]).abs() < 1e-6);
        }
    }

    #[test]
    fn reaches_finds_any_point_at_or_above_iso() {
        // g = 0.01 - (s - 1/2)^2: below at both ends, above around s = 1/2.
        let g = [0.01 - 0.25, 1.0, -1.0, 0.0];
        assert!(reaches(&g, 1.0));
        assert!(!reaches(&g, 0.3));
        assert!(!reaches(&[-0.01 - 0.25, 1.0, -1.0, 0.0], 1.0));
        // At the start only, or at the end only.
        assert!(reaches(&[0.0, -1.0, 0.0, 0.0], 1.0));
        assert!(reaches(&[-1.0, 1.0, 0.0, 0.0], 1.0));
        assert!(!reaches(&[-1.0, 1.0, 0.0, 0.0], 0.999));
        // A zero-length segment looks at s = 0 alone; NaN never reaches.
        assert!(!reaches(&[-1.0, 5.0, 0.0, 0.0], 0.0) && reaches(&[0.0; 4], 0.0));
        assert!(!reaches(&[f64::NAN; 4], 1.0));
    }

    /// DESIGN.md "AO": every direction under p's tangent plane is occluded, none else on a convex
    /// ball (unbounded radius). Marched from o = p + eps Ng, the grazing ones among those
    /// directions escape over the ball's curved surface: without the rule, A would be lower.
    #[test]
    fn directions_under_the_tangent_plane_are_occluded_without_marching() {
        let c = DVec3::splat(15.5);
        let v = field([32, 32, 32], DVec3::ONE, DVec3::ZERO, |p| 10.0 - (p - c).length());
        let dir = DVec3::new(0.1, 0.2, -1.0).normalize();
        let hit = trace(&v, c - 40.0 * dir, dir, 0.0).expect("the ball is hit");
        let mut surface = AoSurface::of_hit(&v, &hit, dir);
        let ng = surface.geometric;
        // An axis tilted 25 degrees from Ng, so that a share of the hemisphere lies under the plane.
        let tangent = ng.any_orthonormal_vector();
        surface.normal = (ng * 25f64.to_radians().cos() + tangent * 25f64.to_radians().sin()).normalize();
        let mut settings = RenderSettings::new(0.0);
        settings.ao.samples = 1024;
        settings.ao.radius = AoRadius::Unbounded;
        let lighting = IblLighting::new(&settings, None);
        let (px, py) = (7, 9);
        let got = ambient_at(&v, &settings, &lighting, &surface, (px, py));
        let key = pixel_key(px, py, settings.ao.frame, settings.ao.seed);
        let o = ao_origin(&v, &settings, surface.position, ng);
        let (mut under, mut escaping_under) = (0, 0);
        for i in 0..settings.ao.samples {
            let (u, w) = ao_point(settings.ao.sequence, i, key);
            let w = cosine_direction(surface.normal, u, w);
            if w.dot(ng) <= 0.0 {
                under += 1;
                escaping_under += usize::from(!ao_ray_occluded(&v, o, w, 0.0, None));
            }
        }
        let n = settings.ao.samples as f64;
        assert!(under >= 10, "{under} of {n} directions under the plane");
        assert!(escaping_under >= 1, "marched, {escaping_under} of {under} escape");
        assert_eq!(got.occlusion, under as f64 / n, "A counts exactly the directions under the plane");
        // Such a direction is never open: the bent normal leans away from under the plane.
        assert!(got.bent_normal.dot(ng) > 0.0);
    }

    #[test]
    fn ao_rays_are_occluded_exactly_within_the_radius() {
        let v = two_slabs();
        // From the gap straight up: f = 0 (iso) exactly at z = 4.5, one unit away.
        let o = DVec3::new(1.5, 1.5, 3.5);
        assert!(!ao_ray_occluded(&v, o, DVec3::Z, 0.0, Some(0.999)));
        assert!(ao_ray_occluded(&v, o, DVec3::Z, 0.0, Some(1.0)));
        assert!(ao_ray_occluded(&v, o, DVec3::Z, 0.0, None));
        assert!(ao_ray_occluded(&v, o, -DVec3::Z, 0.0, Some(1.0)));
        // Along the gap: leaves the box without meeting the object.
        assert!(!ao_ray_occluded(&v, o, DVec3::X, 0.0, None));
        // An origin inside the object is occluded, even with R = 0.
        assert!(ao_ray_occluded(&v, DVec3::new(1.5, 1.5, 1.0), DVec3::X, 0.0, Some(0.0)));
        // An origin outside the box: tested from where the ray enters it (a cap at z = 0).
        let below = DVec3::new(1.5, 1.5, -2.0);
        assert!(!ao_ray_occluded(&v, below, DVec3::Z, 0.0, Some(1.999)));
        assert!(ao_ray_occluded(&v, below, DVec3::Z, 0.0, Some(2.0)));
        assert!(!ao_ray_occluded(&v, below, -DVec3::Z, 0.0, None));
        // Degenerate rays are open.
        assert!(!ao_ray_occluded(&v, o, DVec3::ZERO, 0.0, None));
        assert!(!ao_ray_occluded(&v, o, DVec3::new(f64::NAN, 0.0, 1.0), 0.0, None));
        assert!(!ao_ray_occluded(&v, o, DVec3::Z, f64::NAN, None));

        // A blob thinner than half a voxel (see a_spike_thinner_than_half_a_voxel_is_found): a
        // half-voxel march steps over it, the exact test does not.
        let v = field([9, 9, 9], DVec3::ONE, DVec3::ZERO, |p| if p == DVec3::splat(4.0) { 1.0 } else { 0.0 });
        let (o, w) = (DVec3::new(0.25, 4.02, 3.97), DVec3::X);
        assert!(ao_ray_occluded(&v, o, w, 0.9, None));
        assert!(!ao_ray_occluded(&v, o, w, 0.9, Some(2.5)));
        assert!(!ao_ray_occluded(&v, o + DVec3::new(0.0, 0.3, 0.0), w, 0.9, None));
    }

    /// Viewer-facing normal of pixel i of a whole-image view, from the frame's N.
    fn facing(view: &View, f: &Frame, i: usize) -> DVec3 {
        let b = view.camera.basis();
        let dir = view.ray_dir(&b, i as u32 % view.rect.width, i as u32 / view.rect.width);
        let n = DVec3::from(f.normal[i].map(f64::from));
        if n.dot(-dir) < 0.0 {
            -n
        } else {
            n
        }
    }

    #[test]
    fn ao_off_keeps_the_colour_of_constant_ambient_shading() {
        let c = DVec3::new(7.3, 6.8, 7.9);
        let v = field([16, 15, 17], DVec3::ONE, DVec3::ZERO, |p| 5.5 - (p - c).length());
        let view = small_view(&v, 20, 16);
        let mut s = RenderSettings::new(0.0);
        s.exposure = 1.3;
        let f = render(&v, &view, &s);
        let b = view.camera.basis();
        let light = s.light.world_direction(b.forward, b.right, b.up);
        assert!(f.hit_count() > 20);
        for i in 0..f.pixel_count() {
            if !f.hit[i] {
                assert_eq!((f.occlusion[i], f.bent_normal[i], f.ibl[i]), (0.0, [0.0; 3], [0.0; 3]));
                continue;
            }
            let dir = view.ray_dir(&b, i as u32 % 20, i as u32 / 20);
            let h = trace(&v, view.camera.eye, dir, 0.0).unwrap();
            let n = if h.normal.dot(-dir) < 0.0 { -h.normal } else { h.normal };
            // Exactly the shading of before AO existed: shade() with the constant ambient.
            assert_eq!(f.color[i], shade(&s, n, light, -dir).map(|c| (c * s.exposure) as f32));
            assert_eq!(f.occlusion[i], 0.0);
            assert_eq!(f.bent_normal[i], n.to_array().map(|c| c as f32));
            assert_eq!(f.ibl[i], s.light.ambient.map(|c| c as f32));
        }
    }

    #[test]
    fn occlusion_scales_the_ambient_term_only() {
        // A ball in a bowl-shaped box corner: f = max(ball, floor, wall).
        let c = DVec3::new(6.0, 6.0, 5.0);
        let v = field([14, 14, 14], DVec3::ONE, DVec3::ZERO, |p| {
            (3.0 - (p - c).length()).max(2.0 - p.z).max(2.0 - p.x)
        });
        let view = small_view(&v, 24, 20);
        let mut s = RenderSettings::new(0.0);
        s.exposure = 0.8;
        let off = render(&v, &view, &s);
        s.ao.samples = 32;
        let on = render(&v, &view, &s);
        assert!(on.fetches > off.fetches);
        let mut occluded = 0;
        for i in 0..on.pixel_count() {
            assert_eq!((on.hit[i], on.depth[i], on.normal[i]), (off.hit[i], off.depth[i], off.normal[i]));
            if !on.hit[i] {
                continue;
            }
            let a = on.occlusion[i] as f64;
            assert!((0.0..=1.0).contains(&a));
            occluded += usize::from(a > 0.1);
            for c in 0..3 {
                let want =
                    off.color[i][c] as f64 - s.exposure * s.material.albedo[c] * s.light.ambient[c] * a;
                assert!(
                    (on.color[i][c] as f64 - want).abs() < 1e-5,
                    "pixel {i}: {:?} vs {want}",
                    on.color[i]
                );
                assert!((on.ibl[i][c] as f64 - s.light.ambient[c] * (1.0 - a)).abs() < 1e-6);
            }
            let n = facing(&view, &on, i);
            let bent = DVec3::from(on.bent_normal[i].map(f64::from));
            assert!((bent.length() - 1.0).abs() < 1e-5 && bent.dot(n) > 0.0, "{bent:?} {n:?}");
        }
        assert!(occluded > 10, "the scene has creases: {occluded}");
    }

    #[test]
    fn seed_ao_marches_fixed_texture_steps_and_counts_skipped_samples() {
        // Floor below z = 5 and ceiling above z = 12 (f = max(5 - z, z - 12), linear near both
        // surfaces so the trilinear field crosses 0 exactly there). A point of the floor, N = +z.
        let make = |sz: f64| {
            let s = DVec3::new(1.0, 1.0, sz);
            field([16, 16, 32], s, DVec3::ZERO, |p| (5.0 - p.z / sz).max(p.z / sz - 12.0))
        };
        let v = make(1.0);
        let mut s = RenderSettings::new(0.0);
        s.ao.method = AoMethod::Seed;
        s.ao.samples = 64;
        let lighting = IblLighting::new(&s, None);
        let p = DVec3::new(8.0, 8.0, 5.0);
        let got = seed_ambient(&v, &s, &lighting, p, DVec3::Z);
        // Expected from the geometry: direction (x0, x0, sqrt(1 - 2 x0^2)) with x0 = 4i/N - 3
        // inside the disk; texture steps q + 0.01 k w, k = 1..=90, the box is 15 x 15 x 31; the
        // ceiling is met (f from < 0 to > 0) at the first step with 31 q_z > 12, while in the box.
        let mut want = 0;
        let mut kept = 0;
        for i in 0..64 {
            let x0 = 4.0 * i as f64 / 64.0 - 3.0;
            if 2.0 * x0 * x0 > 1.0 {
                continue;
            }
            kept += 1;
            let w = DVec3::new(x0, x0, (1.0 - 2.0 * x0 * x0).sqrt());
            let q0 = p / DVec3::new(15.0, 15.0, 31.0);
            for k in 1..=90 {
                let q = q0 + 0.01 * k as f64 * w;
                if q.cmplt(DVec3::ZERO).any() || q.cmpgt(DVec3::ONE).any() {
                    break;
                }
                if 31.0 * q.z > 12.0 {
                    want += 1;
                    break;
                }
            }
        }
        assert_eq!(kept, 23);
        assert!(want > 5 && want < kept, "test setup: {want} of {kept}");
        assert_eq!(got.occlusion, want as f64 / 64.0, "skipped samples count in the denominator");
        // Symmetric about x0 = 0 on the diagonal: the open directions sum up along the normal.
        assert!((got.bent_normal - DVec3::Z).length() < 1e-9, "{:?}", got.bent_normal);
        assert!(got.fetches > 0);
        // The march is in texture space: stretching z (the same samples, spacing 2) changes nothing.
        let tall = make(2.0);
        let got2 = seed_ambient(&tall, &s, &lighting, DVec3::new(8.0, 8.0, 10.0), DVec3::Z);
        assert_eq!(got2.occlusion, got.occlusion);
    }

    #[test]
    fn ibl_without_an_environment_lights_with_the_constant_ambient() {
        let c = DVec3::new(7.3, 6.8, 7.9);
        let v = field([16, 15, 17], DVec3::ONE, DVec3::ZERO, |p| 5.5 - (p - c).length());
        let view = small_view(&v, 12, 10);
        let mut s = RenderSettings::new(0.0);
        s.ao.samples = 16;
        let none = render(&v, &view, &s);
        for ibl in [IblMethod::Seed, IblMethod::Bent, IblMethod::Rays] {
            s.ao.ibl = ibl;
            let f = render(&v, &view, &s);
            for i in 0..f.pixel_count() {
                for c in 0..3 {
                    assert!(
                        (f.ibl[i][c] - none.ibl[i][c]).abs() < 2e-3,
                        "{ibl:?} {:?} {:?}",
                        f.ibl[i],
                        none.ibl[i]
                    );
                }
            }
        }
    }
}
