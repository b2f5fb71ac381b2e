//! Both renderers' AO against an independent estimate of DESIGN.md "AO" (the crate
//! `isowall-truth`, `daemon/truth/`: its own field, march and directions, f64, nothing shared with
//! the renderers but the loaded voxels), and against the outside answers of `../shared/conventions/ao-known-answers.json`.
//!
//! - The real scans of `../shared/data` (CT at iso 300, MRI at iso 40; skipped with a message
//!   where that folder is absent) at radius 8 (world units) and unbounded, at the 300 pixels of the
//!   known answers: the reference and the GPU, converged, have occlusion RMSE <= 0.01, |bias| <=
//!   0.003 and no pixel off by more than 0.3 against the estimate, and RMSE <= 0.015, |bias| <=
//!   0.004 against the outside answers, the estimate too. The old origin (half a voxel off the
//!   surface) fails them, and so do the renderers and the estimate without DESIGN.md's rule for
//!   directions under the tangent plane (the MRI's bias against the outside answers is then
//!   -0.0066).
//! - A sphere over a plane (the estimate against the analytic form factor too), a terraced scene
//!   (a smooth shape sampled with 1x1x3 spacing) and thin steep plates (one or two samples thick,
//!   1x1x3 spacing), with the same tolerances.
//! - IBL `rays` within 1% mean relative error of the estimate under the sky (`bent` and `seed`
//!   printed beside it).
//! - R2 against Owen-scrambled Sobol: RMSE against the estimate at 1..32 samples per pixel; the
//!   default sequence is the better one.
//!
//! The estimate marches every ray at 0.02 voxel, so it is computed once per scene (shared by the
//! tests of this file) on every core; the renderers render 1x1 rectangles at the chosen pixels.

mod common;

use glam::DVec3;
use isowall_model::{AoRadius, AoSequence, Camera, IblMethod, Rect, RenderSettings, View};
use isowall_render::environment::Environment;
use isowall_render::gpu::GpuRenderer;
use isowall_render::reference;
use isowall_truth as truth;
use isowall_volume::procedural::{sphere_over_plane_geometry, Procedural};
use isowall_volume::{Volume, VolumeSource};
use std::path::PathBuf;
use std::sync::OnceLock;
use truth::{errors, parallel_map, Errors, Field, KnownAnswers, Truth};

/// Directions per pixel of the estimate: M x M strata.
const M: u32 = 32;
/// The renderers' converged setting: samples per frame x frames.
const SAMPLES: u32 = 1024;
const FRAMES: u32 = 2;

fn shared() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared")
}

/// A scene: the volume, iso, camera and the pixels the tests look at.
struct Scene {
    name: &'static str,
    volume: Volume,
    iso: f64,
    view: View,
    pixels: Vec<(u32, u32)>,
    /// Outside answers per pixel (A at radius 8, A unbounded), where the scene has them (None at
    /// a pixel whose known hit is not the estimator's).
    known: Option<Vec<Option<(f64, f64)>>>,
    /// The estimate per pixel (None: the estimator's ray misses).
    truth: Vec<Option<Truth>>,
}

/// The unit ray through the centre of pixel (px, py): the estimator's own.
fn pixel_ray(c: &Camera, size: (u32, u32), px: u32, py: u32) -> DVec3 {
    truth::pixel_ray((c.eye, c.target, c.up), c.fov_y_deg, size, px, py)
}

fn estimate_all(volume: &Volume, iso: f64, view: &View, pixels: &[(u32, u32)]) -> Vec<Option<Truth>> {
    let field = Field::new(volume.dims(), volume.spacing(), volume.origin(), volume.data(), iso);
    let start = std::time::Instant::now();
    let out = parallel_map(pixels, |&(px, py)| {
        let d = pixel_ray(&view.camera, view.full, px, py);
        field.estimate(view.camera.eye, d, (px, py), M, f64::INFINITY)
    });
    eprintln!("estimate of {} pixels: {:.1} s", pixels.len(), start.elapsed().as_secs_f64());
    out
}

/// A real scan with its outside answers (None, after a message, where `../shared` is absent).
fn scan(index: usize) -> Option<&'static Scene> {
    static SCANS: [OnceLock<Option<Scene>>; 2] = [OnceLock::new(), OnceLock::new()];
    SCANS[index]
        .get_or_init(|| {
            let path = shared().join("conventions/ao-known-answers.json");
            if !path.exists() {
                eprintln!("skipping: {} is absent (the real scans live beside the checkout)", path.display());
                return None;
            }
            let answers = KnownAnswers::read(&path).expect("known answers parse");
            let case = &answers.cases[index];
            let file = case.volume.trim_start_matches("../shared/");
            let source: VolumeSource = shared().join(file).to_str().unwrap().parse().unwrap();
            let volume = source.load(None).expect("the scan loads");
            let iso = case.iso;
            let cam = &case.camera;
            let camera = Camera {
                eye: DVec3::from_array(cam.eye),
                target: DVec3::from_array(cam.target),
                up: DVec3::from_array(cam.up),
                fov_y_deg: cam.fov_y_deg,
            };
            let view = View::whole(camera, cam.width, cam.height);
            let px = &case.pixels;
            let pixels: Vec<(u32, u32)> = px.iter().map(|p| (p.px, p.py)).collect();
            let known: Vec<(f64, f64)> = px.iter().map(|p| (p.a_r8, p.a_unbounded)).collect();
            let name = if index == 0 { "CT" } else { "MRI" };
            let truth = estimate_all(&volume, iso, &view, &pixels);
            // The estimator's own geometry agrees with the outside renderer's (to 0.01 world
            // units) at all but a few pixels, which the comparisons with the known answers leave
            // out: on the CT, 7 of 300 whose known hits lie 0.02 to 0.14 outside the box's y = 0
            // face, where the estimator (and both renderers) find the cap on that face.
            let mut known: Vec<Option<(f64, f64)>> = known.into_iter().map(Some).collect();
            let mut differ = 0;
            for ((t, p), k) in truth.iter().zip(px).zip(known.iter_mut()) {
                let t = t.as_ref().unwrap_or_else(|| panic!("{name}: the estimate misses a known hit {p:?}"));
                let dp = (t.position - DVec3::from_array(p.pos)).length();
                if dp >= 0.01 {
                    eprintln!(
                        "{name} ({}, {}): hit {:?} vs known {:?}: left out",
                        t.px, t.py, t.position, p.pos
                    );
                    *k = None;
                    differ += 1;
                }
            }
            assert!(differ * 100 <= 3 * pixels.len(), "{name}: {differ} hits differ from the known ones");
            Some(Scene { name, volume, iso, view, pixels, known: Some(known), truth })
        })
        .as_ref()
}

/// Pixels on a grid of stride 6 over a `w` x `w` image.
fn grid(w: u32) -> Vec<(u32, u32)> {
    (0..w / 6).flat_map(|j| (0..w / 6).map(move |i| (3 + 6 * i, 3 + 6 * j))).collect()
}

/// A sphere over a plane (64^3), framed at 96x96 so that plane and sphere both fill it.
fn sphere_plane() -> &'static Scene {
    static S: OnceLock<Scene> = OnceLock::new();
    S.get_or_init(|| {
        let volume = Procedural::SphereOverPlane.generate(Some(64));
        let g = sphere_over_plane_geometry(Some(64));
        let camera = Camera {
            eye: DVec3::new(g.centre.x + 6.0, g.centre.y - 50.0, g.plane_z + 45.0),
            target: DVec3::new(g.centre.x, g.centre.y + 2.0, g.plane_z + 4.0),
            up: DVec3::Z,
            fov_y_deg: 50.0,
        };
        let view = View::whole(camera, 96, 96);
        let pixels = grid(96);
        let truth = estimate_all(&volume, 0.0, &view, &pixels);
        Scene { name: "sphere over plane", volume, iso: 0.0, view, pixels, known: None, truth }
    })
}

/// A synthetic scene at iso 0: `dims` samples at spacing `sp`, sample (i, j, k) = `sample(i, j,
/// k)`, seen at 96x96 from `eye` towards `target` (fov 40), at a stride-6 grid of pixels.
fn sampled_scene(
    name: &'static str,
    (dims, sp): ([usize; 3], DVec3),
    sample: impl Fn(usize, usize, usize) -> f32,
    eye: DVec3,
    target: DVec3,
) -> Scene {
    let mut data = Vec::with_capacity(dims[0] * dims[1] * dims[2]);
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                data.push(sample(i, j, k));
            }
        }
    }
    let volume = Volume::new(name, dims, sp, DVec3::ZERO, data).unwrap();
    let view = View::whole(Camera { eye, target, up: DVec3::Z, fov_y_deg: 40.0 }, 96, 96);
    let pixels = grid(96);
    let truth = estimate_all(&volume, 0.0, &view, &pixels);
    Scene { name, volume, iso: 0.0, view, pixels, known: None, truth }
}

/// A smooth shape (two overlapping balls and a slab, with creases where they meet) sampled at
/// spacing 1x1x3: the trilinear field is piecewise linear in z over 3 units, so the surface has
/// terraces, the case thick slices give real scans.
fn terraced() -> &'static Scene {
    static S: OnceLock<Scene> = OnceLock::new();
    S.get_or_init(|| {
        let sp = DVec3::new(1.0, 1.0, 3.0);
        let f = |p: DVec3| {
            let a = 13.0 - (p - DVec3::new(18.0, 20.0, 24.0)).length();
            let b = 10.0 - (p - DVec3::new(31.0, 27.0, 28.0)).length();
            let slab = 9.0 - p.z;
            a.max(b).max(slab)
        };
        sampled_scene(
            "terraced 1x1x3",
            ([48, 48, 16], sp),
            |i, j, k| f(sp * DVec3::new(i as f64, j as f64, k as f64)) as f32,
            DVec3::new(70.0, -40.0, 75.0),
            DVec3::new(24.0, 24.0, 18.0),
        )
    })
}

/// Thin steep plates at spacing 1x1x3 on a floor: four plates across y, one or two samples thick
/// in x (alternately), each leaning by one sample in x per sample in z (a terrace of 3 world units
/// a step, about 72 degrees from the floor), with narrow gaps between them: creases, thin sheets
/// and directions under the tangent plane at every plate's curved rim.
fn thin_plates() -> &'static Scene {
    static S: OnceLock<Scene> = OnceLock::new();
    S.get_or_init(|| {
        let inside = |i: usize, j: usize, k: usize| {
            let plate = (0..4).any(|p| {
                let (x0, thick) = (4 + 9 * p + k, 1 + p % 2);
                (x0..x0 + thick).contains(&i) && (4..44).contains(&j) && k <= 11
            });
            k == 0 || plate
        };
        sampled_scene(
            "thin plates 1x1x3",
            ([48, 48, 16], DVec3::new(1.0, 1.0, 3.0)),
            |i, j, k| if inside(i, j, k) { 2.0 } else { -1.0 },
            DVec3::new(75.0, -35.0, 70.0),
            DVec3::new(26.0, 24.0, 12.0),
        )
    })
}

fn settings(iso: f64, radius: Option<f64>, samples: u32) -> RenderSettings {
    let mut s = RenderSettings::new(iso);
    s.ao.samples = samples;
    s.ao.radius = radius.map_or(AoRadius::Unbounded, AoRadius::World);
    s
}

/// What a renderer gives at one pixel: hit depth, A, E.
#[derive(Clone, Copy)]
struct Got {
    depth: f64,
    occlusion: f64,
    ibl: [f64; 3],
}

fn one_pixel(view: &View, (px, py): (u32, u32)) -> View {
    View { rect: Rect { x: px, y: py, width: 1, height: 1 }, ..*view }
}

fn reference_at(
    scene: &Scene,
    s: &RenderSettings,
    env: Option<&Environment>,
    frames: u32,
) -> Vec<Option<Got>> {
    parallel_map(&scene.pixels, |&p| {
        let f = reference::render_accumulated(&scene.volume, &one_pixel(&scene.view, p), s, env, frames);
        f.hit[0].then(|| Got {
            depth: f.depth[0] as f64,
            occlusion: f.occlusion[0] as f64,
            ibl: f.ibl[0].map(f64::from),
        })
    })
}

fn gpu_at(
    gpu: &GpuRenderer,
    scene: &Scene,
    s: &RenderSettings,
    env: Option<&Environment>,
) -> Vec<Option<Got>> {
    let volume = gpu.upload(&scene.volume).unwrap();
    let genv = env.map(|e| gpu.upload_environment(e).unwrap());
    scene
        .pixels
        .iter()
        .map(|&p| {
            let f = gpu
                .render_accumulated(&volume, &one_pixel(&scene.view, p), s, genv.as_ref(), FRAMES)
                .unwrap()
                .frame;
            f.hit[0].then(|| Got {
                depth: f.depth[0] as f64,
                occlusion: f.occlusion[0] as f64,
                ibl: f.ibl[0].map(f64::from),
            })
        })
        .collect()
}

/// The renderer's A against the estimate at the pixels where both hit the same point (depths
/// within 0.05 voxel: AO is compared, not geometry); the pixels left out are counted and few.
fn against_truth(scene: &Scene, got: &[Option<Got>], radius: Option<f64>, label: &str) -> Errors {
    let voxel = scene.volume.spacing().min_element();
    let (mut g, mut w, mut left_out) = (Vec::new(), Vec::new(), 0);
    for (t, r) in scene.truth.iter().zip(got) {
        match (t, r) {
            (Some(t), Some(r)) if (t.depth - r.depth).abs() < 0.05 * voxel => {
                g.push(r.occlusion);
                w.push(t.occlusion(radius));
            }
            (None, None) => {}
            _ => left_out += 1,
        }
    }
    let e = errors(&g, &w);
    eprintln!("{} {label} vs estimate: {e} ({left_out} pixels left out: the hits differ)", scene.name);
    assert!(g.len() >= 100, "{} {label}: only {} pixels compared", scene.name, g.len());
    assert!(left_out * 50 <= g.len(), "{} {label}: {left_out} pixels whose hits differ", scene.name);
    e
}

fn assert_converged(e: &Errors, what: &str) {
    assert!(e.rmse <= 0.01 && e.bias.abs() <= 0.003 && e.off_03 == 0, "{what}: {e}");
}

/// Radius 8 and unbounded, as the known answers have them.
const RADII: [(Option<f64>, &str); 2] = [(Some(8.0), "r8"), (None, "unbounded")];

/// Against the known answers (the outside renderer's, DESIGN.md "AO"): RMSE and |bias| within
/// these, for the estimate and both renderers. Without the rule for directions under the tangent
/// plane the MRI's bias was -0.0066 (rays from 0.01 voxel out that dip under the plane escape
/// over its curved surface).
const KNOWN_RMSE: f64 = 0.015;
const KNOWN_BIAS: f64 = 0.004;

/// Checks scan `index`: both renderers at both radii against the estimate and the known answers.
/// The GPU on the CT at an unbounded radius (1024 samples of rays up to the box) is the case that
/// found lavapipe's loop budget (`AoDispatches` in daemon/render/src/gpu/ao.rs): in one dispatch
/// its later rays came back open (RMSE 0.030, bias -0.0069, max 0.178 against the estimate).
fn check_scan(index: usize) {
    let Some(scene) = scan(index) else { return };
    let gpu = common::gpu();
    let known = scene.known.as_ref().unwrap();
    for (k, &(radius, rname)) in RADII.iter().enumerate() {
        // The pixels with a known answer whose hit is the estimator's.
        let keep: Vec<usize> = (0..known.len()).filter(|&i| known[i].is_some()).collect();
        let want_known: Vec<f64> =
            keep.iter().map(|&i| known[i].map(|a| if k == 0 { a.0 } else { a.1 }).unwrap()).collect();
        let truth: Vec<f64> =
            keep.iter().map(|&i| scene.truth[i].as_ref().unwrap().occlusion(radius)).collect();
        let e = errors(&truth, &want_known);
        eprintln!("{} {rname}: estimate vs known answers: {e}", scene.name);
        assert!(
            e.rmse <= KNOWN_RMSE && e.bias.abs() <= KNOWN_BIAS,
            "{} {rname}: the estimate vs known: {e}",
            scene.name
        );
        let s = settings(scene.iso, radius, SAMPLES);
        let mut renders = vec![("reference", reference_at(scene, &s, None, FRAMES))];
        if let Some(g) = &gpu {
            renders.push(("gpu", gpu_at(g, scene, &s, None)));
        }
        for (label, got) in &renders {
            let e = against_truth(scene, got, radius, &format!("{label} {rname}"));
            assert_converged(&e, &format!("{} {label} {rname}", scene.name));
            // Where the renderer's hit is the estimator's too (the GPU's march may step over a
            // sliver the outside renderer hit).
            let voxel = scene.volume.spacing().min_element();
            let same: Vec<usize> = (0..keep.len())
                .filter(|&j| {
                    let (g, t) = (got[keep[j]], scene.truth[keep[j]].as_ref().unwrap());
                    g.is_some_and(|g| (g.depth - t.depth).abs() < 0.05 * voxel)
                })
                .collect();
            let a: Vec<f64> = same.iter().map(|&j| got[keep[j]].unwrap().occlusion).collect();
            let want: Vec<f64> = same.iter().map(|&j| want_known[j]).collect();
            let e = errors(&a, &want);
            eprintln!("{} {label} {rname} vs known answers: {e}", scene.name);
            assert!(
                e.rmse <= KNOWN_RMSE && e.bias.abs() <= KNOWN_BIAS,
                "{} {label} {rname} vs known: {e}",
                scene.name
            );
        }
    }
}

#[test]
fn ct_converges_to_the_estimate_and_the_known_answers() {
    check_scan(0);
}

#[test]
fn mri_converges_to_the_estimate_and_the_known_answers() {
    check_scan(1);
}

#[test]
fn the_old_origin_half_a_voxel_off_the_surface_fails_the_estimate() {
    let Some(scene) = scan(1) else { return };
    let mut s = settings(scene.iso, Some(8.0), 256);
    s.ao.offset_voxels = 0.5;
    let got = reference_at(scene, &s, None, 1);
    let e = against_truth(scene, &got, Some(8.0), "reference, origin 0.5 voxel off");
    assert!(e.bias < -0.01 && e.rmse > 0.02, "half a voxel off must lose occlusion: {e}");
}

fn check_synthetic(scene: &Scene, radius: Option<f64>, rname: &str) {
    let s = settings(scene.iso, radius, SAMPLES);
    let e =
        against_truth(scene, &reference_at(scene, &s, None, FRAMES), radius, &format!("reference {rname}"));
    assert_converged(&e, &format!("{} reference {rname}", scene.name));
    if let Some(g) = common::gpu() {
        let e = against_truth(scene, &gpu_at(&g, scene, &s, None), radius, &format!("gpu {rname}"));
        assert_converged(&e, &format!("{} gpu {rname}", scene.name));
    }
}

#[test]
fn sphere_over_plane_estimate_is_analytic_and_both_renderers_converge_to_it() {
    let scene = sphere_plane();
    let g = sphere_over_plane_geometry(Some(64));
    let (mut se, mut n, mut top) = (0.0, 0, 0f64);
    for t in scene.truth.iter().flatten() {
        if (t.position.z - g.plane_z).abs() < 1e-6 && (t.normal - DVec3::Z).length() < 1e-9 {
            // A = r^2 (c - o).z / |c - o|^3 at o = p + eps z.
            let o = t.position + truth::EPS_VOXELS * DVec3::Z;
            let c = g.centre - o;
            let exact = g.radius * g.radius * c.z / c.length().powi(3);
            se += (t.occlusion(None) - exact).powi(2);
            top = top.max(exact);
            n += 1;
        }
    }
    let rmse = (se / n as f64).sqrt();
    eprintln!(
        "sphere over plane: estimate vs analytic on {n} plane pixels: RMSE {rmse:.5} (A up to {top:.3})"
    );
    assert!(n >= 40 && top > 0.1, "{n} plane pixels, A up to {top}");
    assert!(rmse < 0.006, "the estimate is off the analytic form factor: {rmse}");
    check_synthetic(scene, None, "unbounded");
}

#[test]
fn terraced_scene_converges_to_the_estimate() {
    let scene = terraced();
    // The default radius: 8 voxels of the largest spacing (24 world units); and unbounded.
    check_synthetic(scene, Some(24.0), "r24");
    check_synthetic(scene, None, "unbounded");
}

#[test]
fn thin_steep_plates_converge_to_the_estimate() {
    let scene = thin_plates();
    // The default radius: 8 voxels of the largest spacing (24 world units); and unbounded.
    check_synthetic(scene, Some(24.0), "r24");
    check_synthetic(scene, None, "unbounded");
}

fn luminance(e: [f64; 3]) -> f64 {
    0.2126 * e[0] + 0.7152 * e[1] + 0.0722 * e[2]
}

/// IBL on the MRI at radius 8: `rays` within 1% mean relative error (per pixel, luminance) of the
/// estimate's E under a smooth environment; `bent` and `seed` reported beside it. Under the
/// built-in sky (its sun a small bright disk) both estimates carry more noise; reported too.
#[test]
fn ibl_rays_match_the_estimate_and_bent_and_seed_are_reported() {
    let Some(scene) = scan(1) else { return };
    let radius = Some(8.0);
    let gpu = common::gpu();
    let voxel = scene.volume.spacing().min_element();
    for (env, methods) in [
        (common::smooth_environment(), &[IblMethod::Rays, IblMethod::Bent, IblMethod::Seed][..]),
        (Environment::sky(), &[IblMethod::Rays][..]),
    ] {
        let want: Vec<f64> = scene
            .truth
            .iter()
            .map(|t| luminance(t.as_ref().unwrap().irradiance(radius, |w| env.lookup(w).map(f64::from))))
            .collect();
        for &ibl in methods {
            let mut s = settings(scene.iso, radius, SAMPLES);
            s.ao.ibl = ibl;
            let mut renders = vec![("reference", reference_at(scene, &s, Some(&env), FRAMES))];
            if let Some(g) = &gpu {
                renders.push(("gpu", gpu_at(g, scene, &s, Some(&env))));
            }
            for (label, got) in renders {
                // Where the renderer's hit is the estimator's.
                let pairs: Vec<(f64, f64)> = got
                    .iter()
                    .zip(&scene.truth)
                    .zip(&want)
                    .filter_map(|((g, t), &w)| {
                        let (g, t) = (g.as_ref()?, t.as_ref()?);
                        ((g.depth - t.depth).abs() < 0.05 * voxel).then(|| (luminance(g.ibl), w))
                    })
                    .collect();
                let n = pairs.len() as f64;
                let mre = pairs.iter().map(|(g, w)| (g - w).abs() / w).sum::<f64>() / n;
                let bias = pairs.iter().map(|(g, w)| (g - w) / w).sum::<f64>() / n;
                eprintln!(
                    "{} IBL {ibl:?} {label}, {}: mean relative error {:.2}% (mean signed {:+.2}%) over {} pixels",
                    scene.name,
                    env.name,
                    100.0 * mre,
                    100.0 * bias,
                    pairs.len()
                );
                if ibl == IblMethod::Rays && env.name == "smooth" {
                    assert!(pairs.len() >= 290, "{} pixels compared", pairs.len());
                    assert!(mre <= 0.01, "{} {label}: rays {:.2}% off the estimate", scene.name, 100.0 * mre);
                }
            }
        }
    }
}

/// RMSE against the estimate of the reference with `sequence` at `n` samples per pixel, over
/// `frames` independent frames at every pixel of the scan.
fn sequence_rmse(scene: &Scene, sequence: AoSequence, n: u32, frames: u32, radius: Option<f64>) -> f64 {
    let mut s = settings(scene.iso, radius, n);
    s.ao.sequence = sequence;
    let truth: Vec<f64> = scene.truth.iter().map(|t| t.as_ref().unwrap().occlusion(radius)).collect();
    let se: Vec<f64> = parallel_map(&(0..scene.pixels.len()).collect::<Vec<_>>(), |&i| {
        let view = one_pixel(&scene.view, scene.pixels[i]);
        (0..frames)
            .map(|k| {
                let mut sk = s;
                sk.ao.frame = 1000 + k;
                let f = reference::render_with_env(&scene.volume, &view, &sk, None);
                (f.occlusion[0] as f64 - truth[i]).powi(2)
            })
            .sum()
    });
    (se.iter().sum::<f64>() / (frames as usize * se.len()) as f64).sqrt()
}

#[test]
fn sobol_against_r2_per_sample_count_and_the_default_is_the_better() {
    let counts = [1u32, 2, 4, 8, 16, 32];
    let mut wins = [0usize; 2];
    for index in [0, 1] {
        let Some(scene) = scan(index) else { return };
        for (radius, rname) in RADII {
            eprintln!(
                "{} {rname}: spp, RMSE R2, RMSE Sobol (16 frames x {} pixels)",
                scene.name,
                scene.pixels.len()
            );
            for &n in &counts {
                let r2 = sequence_rmse(scene, AoSequence::R2, n, 16, radius);
                let sobol = sequence_rmse(scene, AoSequence::Sobol, n, 16, radius);
                eprintln!("  {n:>3} {r2:.5} {sobol:.5}");
                wins[usize::from(sobol < r2)] += 1;
            }
        }
    }
    let better = if wins[1] >= wins[0] { AoSequence::Sobol } else { AoSequence::R2 };
    eprintln!("wins: R2 {}, Sobol {}", wins[0], wins[1]);
    assert_eq!(RenderSettings::new(0.0).ao.sequence, better, "the default must be the better sequence");
}
