//! The stability suite (DESIGN.md "Stability cases"; the expected behaviour of every case, and what
//! was observed, is written down in docs/stability.md).
//!
//! Every case renders with both the GPU renderer and the exact CPU reference, each in four
//! variants: AO ours (exact) with IBL `bent`, ours (exact) with IBL `rays`, ours stepped (the
//! half-voxel march variant) with `bent`, and the 2008 seed with `rays`, 16 AO samples, lit by the
//! built-in sky. Every AOV of every render (colour, depth, normal, hit, occlusion, bent normal,
//! IBL) is scanned: no NaN or Inf, misses zero in every AOV but colour (the background), hits with
//! a unit normal and bent normal and A in [0, 1]. Then the case's own expected behaviour is
//! asserted.

mod common;

use common::{ao_at_gpu_hits, hit_position, plate_scene, sampled};

use glam::DVec3;
use isowall_model::{AoMethod, AoRadius, Aov, Camera, IblMethod, RenderSettings, View};
use isowall_render::environment::Environment;
use isowall_render::gpu::{GpuEnvironment, GpuRenderer};
use isowall_render::reference;
use isowall_render::Frame;
use isowall_volume::procedural::Procedural;
use isowall_volume::{Volume, VolumeError, VolumeSource};

/// The GPU renderer with the sky uploaded, and the sky for the reference.
struct Ctx {
    gpu: GpuRenderer,
    sky: Environment,
    gpu_sky: GpuEnvironment,
}

fn ctx() -> Option<Ctx> {
    let gpu = common::gpu()?;
    let sky = Environment::sky();
    let gpu_sky = gpu.upload_environment(&sky).unwrap();
    Some(Ctx { gpu, sky, gpu_sky })
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Variant {
    /// Ours, exact, IBL bent.
    OursBent,
    /// Ours, exact, IBL rays.
    OursRays,
    /// Ours, stepped (half-voxel march), IBL bent.
    SteppedBent,
    /// The 2008 seed, IBL rays.
    SeedRays,
}

const VARIANTS: [Variant; 4] =
    [Variant::OursBent, Variant::OursRays, Variant::SteppedBent, Variant::SeedRays];

impl Variant {
    fn apply(self, base: &RenderSettings) -> RenderSettings {
        let mut s = *base;
        let (method, exact, ibl) = match self {
            Variant::OursBent => (AoMethod::Ours, true, IblMethod::Bent),
            Variant::OursRays => (AoMethod::Ours, true, IblMethod::Rays),
            Variant::SteppedBent => (AoMethod::Ours, false, IblMethod::Bent),
            Variant::SeedRays => (AoMethod::Seed, true, IblMethod::Rays),
        };
        s.ao.method = method;
        s.ao.exact = exact;
        s.ao.ibl = ibl;
        s
    }
}

/// One variant rendered both ways.
struct Pair {
    variant: Variant,
    gpu: Frame,
    reference: Frame,
}

/// The renders of one scene.
struct Renders(Vec<Pair>);

impl Renders {
    fn get(&self, v: Variant) -> &Pair {
        self.0.iter().find(|p| p.variant == v).expect("every variant is rendered")
    }
}

/// Base settings of the suite: 16 AO samples, default radius.
fn settings(iso: f64) -> RenderSettings {
    let mut s = RenderSettings::new(iso);
    s.ao.samples = 16;
    s
}

/// Renders every variant of `base` on both renderers and scans every AOV of each.
fn render_all(c: &Ctx, case: &str, volume: &Volume, view: &View, base: &RenderSettings) -> Renders {
    let gv = c.gpu.upload(volume).unwrap();
    let mut out = Vec::new();
    for variant in VARIANTS {
        let s = variant.apply(base);
        let gpu = c.gpu.render(&gv, view, &s, Some(&c.gpu_sky)).unwrap().frame;
        let reference = reference::render_with_env(volume, view, &s, Some(&c.sky));
        check_frame(&gpu, &s, &format!("{case} {variant:?} GPU"));
        check_frame(&reference, &s, &format!("{case} {variant:?} reference"));
        out.push(Pair { variant, gpu, reference });
    }
    Renders(out)
}

/// No NaN or Inf in any AOV; misses hold zero in every AOV but colour, which is the background;
/// hits have A in [0, 1], unit normal and bent normal, non-negative depth, E and colour.
fn check_frame(f: &Frame, s: &RenderSettings, label: &str) {
    for aov in Aov::ALL {
        let values = f.aov(aov);
        let bad = values.iter().filter(|v| !v.is_finite()).count();
        assert_eq!(bad, 0, "{label}: {bad} non-finite values in AOV {}", aov.name());
    }
    let unit = |v: [f32; 3]| (v.iter().map(|c| (*c as f64).powi(2)).sum::<f64>().sqrt() - 1.0).abs() < 1e-3;
    for i in 0..f.pixel_count() {
        if !f.hit[i] {
            assert_eq!(f.color[i], s.background.map(|c| c as f32), "{label}: pixel {i}");
            assert_eq!(
                (f.depth[i], f.normal[i], f.occlusion[i], f.bent_normal[i], f.ibl[i]),
                (0.0, [0.0; 3], 0.0, [0.0; 3], [0.0; 3]),
                "{label}: a miss must be zero in every AOV (pixel {i})"
            );
            continue;
        }
        assert!((0.0..=1.0).contains(&f.occlusion[i]), "{label}: A = {} at pixel {i}", f.occlusion[i]);
        assert!(unit(f.normal[i]), "{label}: normal {:?} at pixel {i}", f.normal[i]);
        assert!(unit(f.bent_normal[i]), "{label}: bent normal {:?} at pixel {i}", f.bent_normal[i]);
        assert!(f.depth[i] >= 0.0, "{label}: depth {} at pixel {i}", f.depth[i]);
        assert!(
            f.ibl[i].iter().chain(&f.color[i]).all(|&c| c >= 0.0),
            "{label}: E or colour < 0 at pixel {i}"
        );
    }
}

fn framed(v: &Volume, n: u32) -> View {
    View::whole(Camera::framing(v.box_min(), v.box_max(), n, n), n, n)
}

fn mean_occlusion(f: &Frame) -> f64 {
    let hits = f.hit_count().max(1);
    (0..f.pixel_count()).filter(|&i| f.hit[i]).map(|i| f.occlusion[i] as f64).sum::<f64>() / hits as f64
}

/// GPU against reference on the primary hit (DESIGN.md's tolerances: masks agree off the
/// silhouette, median depth error < 0.05 voxel, median normal error < 1 degree).
fn assert_primary_agrees(volume: &Volume, p: &Pair, case: &str) -> common::Agreement {
    let a = common::compare(&p.gpu, &p.reference, volume.spacing().min_element());
    eprintln!("{case}: {a:?}");
    assert_eq!(a.mask_mismatches, 0, "{case}: hit masks differ off the silhouette: {a:?}");
    assert!(a.depth_median < 0.05, "{case}: median depth error {} voxel", a.depth_median);
    assert!(a.normal_median_deg < 1.0, "{case}: median normal error {} deg", a.normal_median_deg);
    a
}

// ---------------------------------------------------------------------------------------------
// Sheets thinner than a step

/// Looking down at the floor from between the floor and the plate (the eye inside the box).
fn under_the_plate(n: u32) -> View {
    let camera = Camera {
        eye: DVec3::new(15.3, 15.6, 6.5),
        target: DVec3::new(15.3, 15.6, 0.0),
        up: DVec3::Y,
        fov_y_deg: 60.0,
    };
    View::whole(camera, n, n)
}

#[test]
fn thin_plate_occludes_with_ours_and_the_seed_misses_it() {
    let Some(c) = ctx() else { return };
    let view = under_the_plate(32);
    let mut per_thickness = Vec::new();
    for thick in [false, true] {
        let volume = plate_scene(thick);
        let r = render_all(&c, &volume.name, &volume, &view, &settings(0.0));
        for p in &r.0 {
            assert_eq!(p.gpu.hit_count(), view.pixel_count(), "{:?}: every pixel sees the floor", p.variant);
            assert_eq!(p.reference.hit_count(), view.pixel_count());
            for i in 0..view.pixel_count() {
                let z = hit_position(&view, &p.gpu, i).z;
                assert!((z - 3.5).abs() < 1e-3, "{:?}: pixel {i} hits z = {z}, not the floor", p.variant);
            }
        }
        let m = |v: Variant| (mean_occlusion(&r.get(v).gpu), mean_occlusion(&r.get(v).reference));
        let (ours, stepped, seed) = (m(Variant::OursBent), m(Variant::SteppedBent), m(Variant::SeedRays));
        eprintln!(
            "{}: mean A (GPU, reference): ours {ours:.4?}, stepped {stepped:.4?}, seed {seed:.4?}",
            volume.name
        );
        // Exact on both sides: the same occlusion (one ray at most, f32 against f64).
        let o = r.get(Variant::OursBent);
        for i in 0..view.pixel_count() {
            assert!(
                (o.gpu.occlusion[i] - o.reference.occlusion[i]).abs() <= 1.0 / 16.0 + 1e-6,
                "{}: ours GPU {} vs reference {} at pixel {i}",
                volume.name,
                o.gpu.occlusion[i],
                o.reference.occlusion[i]
            );
        }
        per_thickness.push((o.gpu.occlusion.clone(), o.reference.occlusion.clone(), ours, stepped, seed));
    }
    let (thin, thick) = (&per_thickness[0], &per_thickness[1]);
    // Ours sees the thin plate exactly as it sees a thick one with the same lower face.
    assert_eq!(thin.0, thick.0, "GPU: exact AO depends on the plate's thickness");
    assert_eq!(thin.1, thick.1, "reference: exact AO depends on the plate's thickness");
    let ours = thin.2 .0;
    assert!(ours > 0.6, "the plate covers most of the floor's sky within R: A = {ours}");
    // The GPU's stepped march (the reference has no stepped variant: it is exact) and the seed
    // (both renderers) step through the thin plate on many rays; the thick one they see (the seed
    // with its own flaws: two thirds of its directions are skipped yet counted).
    assert!(
        thin.3 .0 < thick.3 .0 - 0.08,
        "stepped GPU does not miss the thin plate: {:?} {:?}",
        thin.3,
        thick.3
    );
    assert_eq!(thick.3 .0, thick.2 .0, "stepped GPU on the thick plate");
    assert!(
        thin.4 .0 < thick.4 .0 - 0.08,
        "seed GPU does not miss the thin plate: {:?} {:?}",
        thin.4,
        thick.4
    );
    assert!(thin.4 .1 < thick.4 .1 - 0.08, "seed reference does not miss the thin plate: {:?}", thin.4);
    assert!(thin.4 .0 < 0.5 * ours && thin.4 .1 < 0.5 * ours, "seed {:?} vs ours {ours}", thin.4);
}

#[test]
fn thin_plate_seen_directly_gpu_misses_only_crossings_thinner_than_its_step() {
    let Some(c) = ctx() else { return };
    // Primary rays (not AO): the reference is exact and sees the 0.3-voxel plate from above in
    // every pixel; the GPU's primary march (half-voxel steps, by design) may step over it where the
    // ray spends less than a step inside it. Every pixel where the two differ must be such a pixel.
    let volume = plate_scene(false);
    let camera = Camera {
        eye: DVec3::new(15.5, -20.0, 40.0),
        target: DVec3::new(15.5, 15.5, 8.0),
        up: DVec3::Z,
        fov_y_deg: 40.0,
    };
    let view = View::whole(camera, 32, 32);
    let r = render_all(&c, "plate from above", &volume, &view, &settings(0.0));
    let p = r.get(Variant::OursBent);
    let covered = p.reference.hit_count();
    let (misses, thin) = primary_misses(&volume, &view, 0.0, &p.gpu, &p.reference);
    eprintln!("plate from above: the reference hits {covered} pixels, the GPU misses {misses} ({thin} thin)");
    assert_eq!(misses, thin, "a GPU primary miss where the object is thicker than a step");
    assert!(covered > 600, "{covered}");
}

/// GPU primary hits that differ from the reference's (no hit, or a depth more than 0.05 voxel
/// away): (how many, how many of them where the reference's hit lies in a piece of the object
/// that the ray crosses in less than the GPU's march step, half a voxel). A GPU hit in front of
/// the reference's first hit is never allowed.
fn primary_misses(volume: &Volume, view: &View, iso: f64, g: &Frame, r: &Frame) -> (usize, usize) {
    let voxel = volume.spacing().min_element();
    let step = 0.5 * voxel;
    let b = view.camera.basis();
    let (mut misses, mut thin) = (0, 0);
    for i in 0..r.pixel_count() {
        assert!(
            !g.hit[i] || (r.hit[i] && g.depth[i] as f64 > r.depth[i] as f64 - 0.05 * voxel),
            "pixel {i}: the GPU hits at {} in front of the reference ({}, {})",
            g.depth[i],
            r.hit[i],
            r.depth[i]
        );
        if !r.hit[i] || (g.hit[i] && ((g.depth[i] - r.depth[i]) as f64).abs() <= 0.05 * voxel) {
            continue;
        }
        misses += 1;
        // How long the ray stays in the object after the reference's hit (fine steps, f64).
        let d = view.ray_dir(&b, i as u32 % view.rect.width, i as u32 / view.rect.width);
        let t_hit = r.depth[i] as f64;
        let fine = step / 400.0;
        let mut t = t_hit + fine;
        while t < t_hit + 2.0 * step
            && volume.sample(view.camera.eye + t * d).is_some_and(|f| f >= iso - 1e-9 * (1.0 + iso.abs()))
        {
            t += fine;
        }
        thin += usize::from(t - t_hit < step);
    }
    (misses, thin)
}

// ---------------------------------------------------------------------------------------------
// Grazing views

#[test]
fn grazing_views_of_a_tilted_plane() {
    let Some(c) = ctx() else { return };
    // The object is everything below a tilted plane (linear, so the trilinear field is exact);
    // the eye sits 1.5 units above the plane, looking across it: incidence from ~3 degrees.
    let n = DVec3::new(0.05, 0.03, 1.0);
    let volume = sampled("tilted plane", [48, 48, 16], DVec3::ONE, |p| 6.2 - p.dot(n));
    let height = |x: f64, y: f64| 6.2 - 0.05 * x - 0.03 * y;
    let eye = DVec3::new(-6.0, 20.0, height(-6.0, 20.0) + 1.5);
    let camera =
        Camera { eye, target: DVec3::new(48.0, 26.0, height(48.0, 26.0)), up: DVec3::Z, fov_y_deg: 30.0 };
    let view = View::whole(camera, 48, 32);
    let r = render_all(&c, "grazing", &volume, &view, &settings(0.0));
    let normal = -n.normalize();
    let normal = -normal; // N = -grad f points out of the object: up the plane.
    for p in &r.0 {
        let a = assert_primary_agrees(&volume, p, &format!("grazing {:?}", p.variant));
        assert!(a.both_hit > 300, "{a:?}");
        for (name, f) in [("GPU", &p.gpu), ("reference", &p.reference)] {
            let (mut plane, mut caps) = (0, 0);
            for i in 0..f.pixel_count() {
                if !f.hit[i] {
                    continue;
                }
                // The flat plane has nothing above it: open to every ray, grazing ones included.
                assert_eq!(f.occlusion[i], 0.0, "{:?} {name}: A at pixel {i}", p.variant);
                let nv = DVec3::from(f.normal[i].map(f64::from));
                if nv.x == -1.0 {
                    caps += 1; // the x = 0 face, below the plane
                } else {
                    plane += 1;
                    // Away from the box faces (where the gradient stencil is clamped), N is the
                    // plane's normal.
                    let q = hit_position(&view, f, i);
                    if q.x > 1.0 && q.y > 1.0 && q.x < 46.0 && q.y < 46.0 {
                        assert!(
                            nv.angle_between(normal).to_degrees() < 0.01,
                            "{name}: normal {nv:?} at {q:?}"
                        );
                    }
                }
            }
            assert!(plane > 300 && caps > 20, "{name}: {plane} plane and {caps} cap pixels");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Surfaces cut by the box

#[test]
fn surfaces_cut_by_the_box_are_closed_by_caps() {
    let Some(c) = ctx() else { return };
    // A ball of radius 14 centred 3 voxels below the top face z = 31: the face cuts it.
    let centre = DVec3::new(16.0, 16.0, 28.0);
    let volume = sampled("cut ball", [33, 33, 32], DVec3::ONE, |p| 14.0 - (p - centre).length());
    let camera = Camera { eye: DVec3::new(40.0, -30.0, 70.0), target: centre, up: DVec3::Z, fov_y_deg: 35.0 };
    let view = View::whole(camera, 48, 48);
    let r = render_all(&c, "cut by the box", &volume, &view, &settings(0.0));
    let top = volume.box_max().z;
    for p in &r.0 {
        assert_primary_agrees(&volume, p, &format!("cut {:?}", p.variant));
        for (name, f) in [("GPU", &p.gpu), ("reference", &p.reference)] {
            let mut caps = 0;
            for i in 0..f.pixel_count() {
                let q = hit_position(&view, f, i);
                if !f.hit[i] || (q.z - top).abs() > 1e-3 {
                    continue;
                }
                // On the top face, inside the ball's cross-section: a cap with the face normal, and
                // open (everything above the face is outside the box, empty).
                caps += 1;
                assert_eq!(f.normal[i], [0.0, 0.0, 1.0], "{:?} {name}: cap normal at {q:?}", p.variant);
                assert_eq!(f.occlusion[i], 0.0, "{:?} {name}: cap occlusion at {q:?}", p.variant);
                let rho = (q - centre).truncate().length();
                assert!(rho <= (14.0f64.powi(2) - 9.0).sqrt() + 0.6, "cap at radius {rho}");
            }
            assert!(caps > 100, "{:?} {name}: {caps} cap pixels", p.variant);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Zero-gradient plateaus

#[test]
fn zero_gradient_plateaus_fall_back_to_the_viewer_direction() {
    let Some(c) = ctx() else { return };
    // Stripes along z (1, 0, 1, 0, ...), iso 0.5: the field is periodic with period 2, so at every
    // surface point the central difference (h = 1) is exactly 0: N = -dir by the rule.
    let volume =
        sampled("stripes", [24, 24, 24], DVec3::ONE, |p| if p.z as i64 % 2 == 0 { 1.0 } else { 0.0 });
    let camera = Camera {
        eye: DVec3::new(11.3, 11.7, 12.2),
        target: DVec3::new(14.0, 13.0, 0.0),
        up: DVec3::Y,
        fov_y_deg: 40.0,
    };
    let view = View::whole(camera, 32, 32);
    let r = render_all(&c, "stripes", &volume, &view, &settings(0.5));
    let b = camera.basis();
    for p in &r.0 {
        assert_primary_agrees(&volume, p, &format!("stripes {:?}", p.variant));
        for (name, f) in [("GPU", &p.gpu), ("reference", &p.reference)] {
            assert_eq!(f.hit_count(), view.pixel_count(), "{name}: every ray meets a stripe");
            for i in 0..f.pixel_count() {
                let dir = view.ray_dir(&b, i as u32 % 32, i as u32 / 32);
                let nv = DVec3::from(f.normal[i].map(f64::from));
                assert!(nv.angle_between(-dir).to_degrees() < 0.01, "{name}: N {nv:?} vs -dir {:?}", -dir);
            }
        }
    }

    // A quantized plateau: a ball whose samples are rounded to integers (terraces of constant value,
    // as in 8-bit data). Iso between two levels: an ordinary surface through the mixed cells. Iso
    // exactly at a level: {f >= iso} also holds zero-thickness pieces (the faces, edges and
    // corners of cells where only the samples at the level reach it), which the exact reference
    // sees and a march cannot: GPU misses are allowed there, and only there.
    let centre = DVec3::new(15.5, 16.2, 15.8);
    let volume =
        sampled("terraces", [32, 32, 32], DVec3::ONE, |p| (0.5 * (19.0 - (p - centre).length())).round());
    let view = framed(&volume, 64);
    for iso in [2.5, 3.0] {
        let r = render_all(&c, &format!("terraces iso {iso}"), &volume, &view, &settings(iso));
        let p = r.get(Variant::OursBent);
        let (misses, thin) = primary_misses(&volume, &view, iso, &p.gpu, &p.reference);
        let a = common::compare(&p.gpu, &p.reference, 1.0);
        eprintln!("terraces iso {iso}: {a:?}; {misses} GPU misses, {thin} of them thinner than a step");
        assert!(a.both_hit > 500, "{a:?}");
        assert_eq!(misses, thin, "terraces iso {iso}: a GPU miss where the object is thicker than a step");
        assert!(a.depth_median < 0.05 && a.normal_median_deg < 1.0, "{a:?}");
        if iso == 2.5 {
            assert_primary_agrees(&volume, p, "terraces iso 2.5");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Iso at the data's minimum or maximum

#[test]
fn iso_at_or_beyond_the_data_range() {
    let Some(c) = ctx() else { return };
    // A ball centred on a sample: the maximum is reached at that one sample only.
    let centre = DVec3::new(12.0, 11.0, 13.0);
    let volume = sampled("ball", [25, 23, 27], DVec3::ONE, |p| 9.5 - (p - centre).length());
    let (lo, hi) = volume.value_range();
    let view = framed(&volume, 40);

    // Above the maximum, and at it (the object is a single point): nothing to see.
    for iso in [hi as f64 + 1.0, hi as f64] {
        let r = render_all(&c, &format!("iso {iso}"), &volume, &view, &settings(iso));
        for p in &r.0 {
            assert_eq!(p.gpu.hit_count(), 0, "iso {iso} {:?}: GPU hits", p.variant);
            assert_eq!(p.reference.hit_count(), 0, "iso {iso} {:?}: reference hits", p.variant);
        }
    }

    // At the minimum (and below it) f >= iso everywhere in the box: the whole box is the object and
    // every ray that meets the box hits a cap on the face it enters, with that face's normal, open.
    let b = view.camera.basis();
    let (bmin, bmax) = (volume.box_min(), volume.box_max());
    let covered: Vec<bool> = (0..view.pixel_count())
        .map(|i| {
            let d = view.ray_dir(&b, i as u32 % 40, i as u32 / 40);
            let (t1, t2) = ((bmin - view.camera.eye) / d, (bmax - view.camera.eye) / d);
            t1.min(t2).max_element() <= t1.max(t2).min_element()
        })
        .collect();
    let n_covered = covered.iter().filter(|&&c| c).count();
    assert!(n_covered > 500);
    for iso in [lo as f64, lo as f64 - 1.0] {
        let r = render_all(&c, &format!("iso {iso}"), &volume, &view, &settings(iso));
        for p in &r.0 {
            assert_eq!(p.reference.hit, covered, "iso {iso} {:?}: reference hits != box coverage", p.variant);
            let a = assert_primary_agrees(&volume, p, &format!("iso {iso} {:?}", p.variant));
            assert!(a.both_hit + a.silhouette_mismatches >= n_covered);
            for f in [&p.gpu, &p.reference] {
                for i in (0..f.pixel_count()).filter(|&i| f.hit[i]) {
                    let nv = f.normal[i];
                    assert_eq!(nv.iter().filter(|c| c.abs() == 1.0).count(), 1, "not a face normal: {nv:?}");
                    assert_eq!(f.occlusion[i], 0.0);
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// NaN and Inf voxels

#[test]
fn nan_and_inf_voxels_are_refused_with_a_clear_error() {
    // The policy (daemon/volume): a volume with non-finite voxels cannot be made, so neither
    // renderer can ever see one. The error names the source, the count and the first voxel.
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut data = vec![0.5f32; 4 * 3 * 5];
        data[1 + 4 * (2 + 3 * 3)] = bad; // voxel (1, 2, 3)
        data[3 + 4 * (2 + 3 * 4)] = bad; // voxel (3, 2, 4)
        let e = Volume::new("bad.raw", [4, 3, 5], DVec3::ONE, DVec3::ZERO, data).unwrap_err();
        assert!(matches!(e, VolumeError::NonFinite { count: 2, i: 1, j: 2, k: 3, .. }), "{bad}: {e:?}");
        let msg = e.to_string();
        assert!(msg.contains("bad.raw") && msg.contains("NaN or Inf") && msg.contains("(1, 2, 3)"), "{msg}");
    }
    // Through a reader: the file is named.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nan.raw");
    let mut bytes = Vec::new();
    for i in 0..8 {
        bytes.extend_from_slice(&(if i == 5 { f32::NAN } else { 1.0f32 }).to_le_bytes());
    }
    std::fs::write(&path, bytes).unwrap();
    let spec = isowall_volume::io::RawSpec {
        dims: [2, 2, 2],
        voxel: isowall_volume::io::VoxelType::F32,
        spacing: DVec3::ONE,
        big_endian: false,
        header_bytes: 0,
    };
    let msg = isowall_volume::io::load(&path, Some(&spec)).unwrap_err().to_string();
    assert!(msg.contains("nan.raw") && msg.contains("NaN or Inf") && msg.contains("(1, 0, 1)"), "{msg}");
}

// ---------------------------------------------------------------------------------------------
// 1x1x1 and 2x2x2 volumes (and a single-sample axis)

#[test]
fn tiny_volumes() {
    let Some(c) = ctx() else { return };
    // 1x1x1: the box is a point, which no pixel's ray meets: an empty image, whatever the iso.
    let point = Volume::new("point", [1, 1, 1], DVec3::ONE, DVec3::new(2.0, 3.0, 4.0), vec![1.0]).unwrap();
    let camera = Camera {
        eye: DVec3::new(5.0, -1.0, 6.0),
        target: DVec3::new(2.0, 3.0, 4.0),
        up: DVec3::Z,
        fov_y_deg: 40.0,
    };
    for iso in [0.5, 1.0, 2.0] {
        let r = render_all(&c, "1x1x1", &point, &View::whole(camera, 32, 32), &settings(iso));
        for p in &r.0 {
            assert_eq!((p.gpu.hit_count(), p.reference.hit_count()), (0, 0), "1x1x1 iso {iso}");
        }
    }

    // 2x2x2: one cell holding a curved trilinear patch and caps on its faces.
    let corners = [1.0, -0.6, -0.4, -0.9, -0.3, -0.8, 0.2, 0.7];
    let cell = Volume::new("cell", [2, 2, 2], DVec3::splat(2.0), DVec3::ZERO, corners.to_vec()).unwrap();
    let view = framed(&cell, 48);
    let r = render_all(&c, "2x2x2", &cell, &view, &settings(0.0));
    // Where the patch is seen edge-on the object is thinner than the GPU's half-voxel step along
    // some rays: those pixels, and only those, may be missed by the GPU's primary march.
    let p = r.get(Variant::OursBent);
    let (misses, thin) = primary_misses(&cell, &view, 0.0, &p.gpu, &p.reference);
    let a = common::compare(&p.gpu, &p.reference, 2.0);
    eprintln!("2x2x2: {a:?}; {misses} GPU misses, {thin} of them thinner than a step");
    assert_eq!(misses, thin, "2x2x2: a GPU miss where the object is thicker than a step");
    assert!(a.both_hit > 200 && a.depth_median < 0.05 && a.normal_median_deg < 1.0, "{a:?}");
    let (mean, n) = mean_abs_diff(&p.gpu.occlusion, &p.reference.occlusion, &p.gpu.hit, &p.reference.hit);
    let (hits, off) = ao_at_gpu_hits(&cell, &view, &Variant::OursBent.apply(&settings(0.0)), &p.gpu);
    eprintln!("2x2x2 ours: |A_gpu - A_ref| mean {mean:.4} over {n} pixels; at the GPU's hits {off} of {hits} differ");
    assert!(
        mean < 0.01 && off == 0,
        "2x2x2: mean occlusion difference {mean}, {off} pixels at the GPU's hits"
    );

    // 16x16x1: a flat box (one sample along z). The field is the 2D image; where it is >= iso the
    // plane is seen as a cap, normal the face's (-sign(dir.z) along z), open.
    let flat = sampled("flat", [16, 16, 1], DVec3::ONE, |p| 6.0 - (p - DVec3::new(7.5, 7.0, 0.0)).length());
    let camera = Camera {
        eye: DVec3::new(4.0, -6.0, 14.0),
        target: DVec3::new(7.5, 7.5, 0.0),
        up: DVec3::Z,
        fov_y_deg: 50.0,
    };
    let view = View::whole(camera, 32, 32);
    let r = render_all(&c, "16x16x1", &flat, &view, &settings(0.0));
    for p in &r.0 {
        let a = assert_primary_agrees(&flat, p, &format!("16x16x1 {:?}", p.variant));
        assert!(a.both_hit > 100, "{a:?}");
        for f in [&p.gpu, &p.reference] {
            for i in (0..f.pixel_count()).filter(|&i| f.hit[i]) {
                assert_eq!((f.normal[i], f.occlusion[i]), ([0.0, 0.0, 1.0], 0.0), "16x16x1 pixel {i}");
            }
        }
    }
}

fn mean_abs_diff(a: &[f32], b: &[f32], ha: &[bool], hb: &[bool]) -> (f64, usize) {
    let d: Vec<f64> = (0..a.len()).filter(|&i| ha[i] && hb[i]).map(|i| (a[i] - b[i]).abs() as f64).collect();
    (d.iter().sum::<f64>() / d.len().max(1) as f64, d.len())
}

// ---------------------------------------------------------------------------------------------
// Strongly anisotropic spacing

#[test]
fn anisotropic_spacing_1_1_8() {
    let Some(c) = ctx() else { return };
    // A ball of radius 18 sampled every unit in x and y and every 8 units in z.
    let centre = DVec3::new(23.5, 23.0, 24.0);
    let volume =
        sampled("1:1:8 ball", [48, 48, 7], DVec3::new(1.0, 1.0, 8.0), |p| 18.0 - (p - centre).length());
    let view = framed(&volume, 64);
    let r = render_all(&c, "1:1:8", &volume, &view, &settings(0.0));
    for p in &r.0 {
        let a = assert_primary_agrees(&volume, p, &format!("1:1:8 {:?}", p.variant));
        assert!(a.both_hit > 500, "{a:?}");
        let (mean, n) = mean_abs_diff(&p.gpu.occlusion, &p.reference.occlusion, &p.gpu.hit, &p.reference.hit);
        eprintln!("1:1:8 {:?}: |A_gpu - A_ref| mean {mean:.4} over {n} pixels", p.variant);
        let max_mean = if p.variant == Variant::SteppedBent { 0.02 } else { 0.005 };
        assert!(mean < max_mean, "1:1:8 {:?}: mean occlusion difference {mean}", p.variant);
    }
    let s = Variant::OursBent.apply(&settings(0.0));
    let (n, off) = ao_at_gpu_hits(&volume, &view, &s, &r.get(Variant::OursBent).gpu);
    eprintln!("1:1:8: reference AO at the GPU's hits: {off} of {n} pixels differ by more than 1 ray");
    assert!(off * 200 <= n, "1:1:8: {off} of {n} pixels");
}

// ---------------------------------------------------------------------------------------------
// A camera inside the volume, or inside the object

#[test]
fn camera_inside_the_volume_and_inside_the_object() {
    let Some(c) = ctx() else { return };
    // Inside the volume, outside the object: the torus's hole, looking at its inner rim.
    let (torus, iso) =
        (VolumeSource::Procedural { kind: Procedural::Torus, size: Some(48) }.load(None).unwrap(), 0.0);
    let mid = 0.5 * (torus.box_min() + torus.box_max());
    let camera = Camera { eye: mid, target: mid + DVec3::new(1.0, 0.3, -0.2), up: DVec3::Z, fov_y_deg: 70.0 };
    assert!(torus.sample(mid).unwrap() < iso, "the eye is outside the object");
    let view = View::whole(camera, 40, 40);
    let r = render_all(&c, "inside the volume", &torus, &view, &settings(iso));
    for p in &r.0 {
        let a = assert_primary_agrees(&torus, p, &format!("inside the volume {:?}", p.variant));
        assert!(a.both_hit > 500, "{a:?}");
    }

    // Inside the object: two balls; the eye at the centre of A looks at B. The first up-crossing
    // rule: a ray must leave A first (A's inner side is never shown); the hits are all on B.
    let (ca, cb) = (DVec3::new(12.0, 16.0, 16.0), DVec3::new(26.0, 17.0, 15.5));
    let balls = sampled("two balls", [36, 32, 32], DVec3::ONE, |p| {
        (7.0 - (p - ca).length()).max(6.0 - (p - cb).length())
    });
    let camera = Camera { eye: ca, target: cb, up: DVec3::Z, fov_y_deg: 70.0 };
    let view = View::whole(camera, 40, 40);
    let r = render_all(&c, "inside the object", &balls, &view, &settings(0.0));
    for p in &r.0 {
        let a = assert_primary_agrees(&balls, p, &format!("inside the object {:?}", p.variant));
        assert!(a.both_hit > 300 && a.both_hit < 1400, "{a:?}");
        for (name, f) in [("GPU", &p.gpu), ("reference", &p.reference)] {
            for i in (0..f.pixel_count()).filter(|&i| f.hit[i]) {
                let d = (hit_position(&view, f, i) - cb).length();
                assert!((d - 6.0).abs() < 0.3, "{:?} {name}: pixel {i} hits {d} from B's centre", p.variant);
            }
        }
    }
    // A lone ball with the eye inside: nothing is seen.
    let lone = sampled("lone ball", [32, 32, 32], DVec3::ONE, |p| 7.0 - (p - ca).length());
    let r = render_all(&c, "inside a lone ball", &lone, &view, &settings(0.0));
    for p in &r.0 {
        assert_eq!((p.gpu.hit_count(), p.reference.hit_count()), (0, 0), "{:?}", p.variant);
    }
}

// ---------------------------------------------------------------------------------------------
// A huge AO radius

#[test]
fn ao_radius_beyond_the_volume_is_the_same_as_unbounded() {
    let Some(c) = ctx() else { return };
    let (volume, iso) = (
        VolumeSource::Procedural { kind: Procedural::SphereOverPlane, size: Some(40) }.load(None).unwrap(),
        0.0,
    );
    let view = framed(&volume, 40);
    let diag = (volume.box_max() - volume.box_min()).length();
    let mut base = settings(iso);
    base.ao.radius = AoRadius::World(10.0 * diag);
    let huge = render_all(&c, "R = 10 x diagonal", &volume, &view, &base);
    base.ao.radius = AoRadius::Unbounded;
    let unbounded = render_all(&c, "unbounded", &volume, &view, &base);
    base.ao.radius = AoRadius::Default;
    let default = render_all(&c, "default R", &volume, &view, &base);
    for v in VARIANTS {
        let (h, u) = (huge.get(v), unbounded.get(v));
        assert_eq!(h.gpu.occlusion, u.gpu.occlusion, "{v:?}: GPU");
        assert_eq!(h.reference.occlusion, u.reference.occlusion, "{v:?}: reference");
        assert_eq!(h.gpu.ibl, u.gpu.ibl, "{v:?}: GPU E");
        let (a_u, a_d) = (mean_occlusion(&u.reference), mean_occlusion(&default.get(v).reference));
        eprintln!("{v:?}: mean A unbounded {a_u:.4}, default R {a_d:.4}");
        if v != Variant::SeedRays {
            // The radius matters at all (the seed has no radius).
            assert!(a_u > a_d + 0.01, "{v:?}: {a_u} vs {a_d}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// One sample

#[test]
fn one_sample() {
    let Some(c) = ctx() else { return };
    let (volume, iso) =
        (VolumeSource::Procedural { kind: Procedural::Engine, size: Some(48) }.load(None).unwrap(), 0.0);
    let view = framed(&volume, 48);
    let mut base = settings(iso);
    base.ao.samples = 1;
    let r = render_all(&c, "1 sample", &volume, &view, &base);
    let b = view.camera.basis();
    for p in &r.0 {
        for (name, f) in [("GPU", &p.gpu), ("reference", &p.reference)] {
            let mut occluded = 0;
            for i in (0..f.pixel_count()).filter(|&i| f.hit[i]) {
                let a = f.occlusion[i];
                assert!(a == 0.0 || a == 1.0, "{:?} {name}: A = {a} with one sample", p.variant);
                occluded += usize::from(a == 1.0);
                if a == 1.0 {
                    // No open ray: the bent normal is the hemisphere's axis (N as it is for
                    // ours, N_s for the seed), and the rays' E is 0.
                    let dir = view.ray_dir(&b, i as u32 % 48, i as u32 / 48);
                    let nv = DVec3::from(f.normal[i].map(f64::from));
                    let ns = if nv.dot(-dir) < 0.0 { -nv } else { nv };
                    let axis = if p.variant == Variant::SeedRays { ns } else { nv };
                    let bent = DVec3::from(f.bent_normal[i].map(f64::from));
                    assert!(
                        bent.distance(axis) < 1e-4,
                        "{:?} {name}: bent {bent:?} vs axis {axis:?}",
                        p.variant
                    );
                    if p.variant == Variant::OursRays {
                        assert_eq!(f.ibl[i], [0.0; 3]);
                    }
                }
            }
            match p.variant {
                // The seed's only direction (u = v = -1) lies outside the disk: skipped, open.
                Variant::SeedRays => assert_eq!(occluded, 0, "{name}: the seed with one sample"),
                _ => assert!(occluded > 20, "{:?} {name}: only {occluded} occluded pixels", p.variant),
            }
        }
        if matches!(p.variant, Variant::OursBent | Variant::OursRays) {
            let same = (0..p.gpu.pixel_count())
                .filter(|&i| p.gpu.hit[i] && p.reference.hit[i])
                .filter(|&i| p.gpu.occlusion[i] == p.reference.occlusion[i])
                .count();
            let both = (0..p.gpu.pixel_count()).filter(|&i| p.gpu.hit[i] && p.reference.hit[i]).count();
            let (n, off) = ao_at_gpu_hits(&volume, &view, &p.variant.apply(&base), &p.gpu);
            eprintln!(
                "1 sample {:?}: A agrees on {same} of {both} pixels; at the GPU's own hits on {} of {n}",
                p.variant,
                n - off
            );
            // The same direction per pixel: A differs only where the primary hits differ (the
            // engine has fins one voxel thick, seen at grazing angles).
            assert!(same * 100 >= both * 97, "{:?}: A agrees on {same} of {both} pixels", p.variant);
            assert!(off * 200 <= n, "{:?}: A differs at {off} of the GPU's {n} hits", p.variant);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// No NaN or Inf anywhere

#[test]
fn no_aov_is_ever_non_finite_on_the_procedural_volumes() {
    let Some(c) = ctx() else { return };
    // Every built-in volume, at its natural iso and at iso values near its range ends; each
    // render_all scans every AOV of both renderers.
    for kind in Procedural::ALL {
        let volume = VolumeSource::Procedural { kind, size: Some(32) }.load(None).unwrap();
        let (lo, hi) = volume.value_range();
        let view = framed(&volume, 32);
        for iso in
            [kind.natural_iso(), lo as f64 + 1e-3 * (hi - lo) as f64, hi as f64 - 1e-3 * (hi - lo) as f64]
        {
            let r = render_all(&c, &format!("{} iso {iso}", kind.name()), &volume, &view, &settings(iso));
            assert_eq!(r.0.len(), VARIANTS.len());
        }
    }
}
