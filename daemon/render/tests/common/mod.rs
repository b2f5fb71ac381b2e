//! Shared by the GPU integration tests.
#![allow(dead_code)]

use glam::DVec3;
use isowall_model::wire::Continuity;
use isowall_model::{FrameState, RenderSettings, View};
use isowall_render::environment::Environment;
use isowall_render::gpu::{GpuError, GpuRenderer};
use isowall_render::reference::{self, IblLighting};
use isowall_render::Frame;
use isowall_volume::Volume;

/// How a node relates a frame of `view` and `settings` to the frame before it (`None`: none): the
/// model's rule on the frame states, as `NodeMachine` applies it (the sample index `ao.frame` is
/// the node's own, advanced per accumulated frame, not part of the frame state).
pub fn continuity(
    previous: Option<(&View, &RenderSettings)>,
    view: &View,
    settings: &RenderSettings,
) -> Continuity {
    let state = |v: &View, s: &RenderSettings| {
        let mut s = *s;
        s.ao.frame = 0;
        FrameState::new(0, &v.camera, &s, 1)
    };
    state(view, settings).continuity(previous.map(|(v, s)| state(v, s)).as_ref())
}

/// The GPU renderer, or `None` (after a message) where no Vulkan adapter exists. Under `CI=true`
/// a missing adapter fails the test loudly instead: GPU tests never skip silently in CI.
pub fn gpu() -> Option<GpuRenderer> {
    match GpuRenderer::new() {
        Ok(g) => Some(g),
        // Only a missing adapter may skip, and never in CI; any other failure is a failure.
        Err(e @ GpuError::NoAdapter(_)) if std::env::var("CI").as_deref() != Ok("true") => {
            eprintln!("skipping GPU test: {e}");
            None
        }
        Err(e) => panic!("GPU set-up failed: {e}"),
    }
}

/// Agreement of a GPU frame with a reference frame.
#[derive(Debug)]
pub struct Agreement {
    /// Pixels whose hit flag differs, not counting silhouette pixels.
    pub mask_mismatches: usize,
    /// Pixels that differ on the silhouette (a reference pixel with a neighbour of the other kind).
    pub silhouette_mismatches: usize,
    pub both_hit: usize,
    /// Depth error in voxels (of the smallest spacing) over pixels both hit: median, max.
    pub depth_median: f64,
    pub depth_p99: f64,
    /// Normal error in degrees over pixels both hit: median, 99th percentile.
    pub normal_median_deg: f64,
    pub normal_p99_deg: f64,
}

fn quantile(mut v: Vec<f64>, q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

pub fn compare(gpu: &Frame, reference: &Frame, voxel: f64) -> Agreement {
    assert_eq!((gpu.width, gpu.height), (reference.width, reference.height));
    let (w, h) = (reference.width as i64, reference.height as i64);
    let at = |x: i64, y: i64| reference.hit[(y * w + x) as usize];
    let silhouette = |x: i64, y: i64| {
        let c = at(x, y);
        (-1..=1).any(|dy| {
            (-1..=1).any(|dx| {
                let (nx, ny) = (x + dx, y + dy);
                nx >= 0 && ny >= 0 && nx < w && ny < h && at(nx, ny) != c
            })
        })
    };
    let (mut mask_mismatches, mut silhouette_mismatches) = (0, 0);
    let (mut depth, mut normal) = (Vec::new(), Vec::new());
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            match (gpu.hit[i], reference.hit[i]) {
                (a, b) if a != b => {
                    if silhouette(x, y) {
                        silhouette_mismatches += 1
                    } else {
                        mask_mismatches += 1
                    }
                }
                (true, true) => {
                    depth.push((gpu.depth[i] as f64 - reference.depth[i] as f64).abs() / voxel);
                    let (a, b) = (gpu.normal[i], reference.normal[i]);
                    let dot: f64 = (0..3).map(|c| a[c] as f64 * b[c] as f64).sum();
                    let na: f64 = a.iter().map(|c| (*c as f64).powi(2)).sum::<f64>().sqrt();
                    let nb: f64 = b.iter().map(|c| (*c as f64).powi(2)).sum::<f64>().sqrt();
                    normal.push((dot / (na * nb)).clamp(-1.0, 1.0).acos().to_degrees());
                }
                _ => {}
            }
        }
    }
    Agreement {
        mask_mismatches,
        silhouette_mismatches,
        both_hit: depth.len(),
        depth_median: quantile(depth.clone(), 0.5),
        depth_p99: quantile(depth, 0.99),
        normal_median_deg: quantile(normal.clone(), 0.5),
        normal_p99_deg: quantile(normal, 0.99),
    }
}

/// The world position of pixel i's hit.
pub fn hit_position(view: &View, f: &Frame, i: usize) -> DVec3 {
    let b = view.camera.basis();
    let (x, y) = (i as u32 % view.rect.width, i as u32 / view.rect.width);
    view.camera.eye + f.depth[i] as f64 * view.ray_dir(&b, x, y)
}

/// The AO kernel alone: the reference's AO at the GPU's own hits (its hit point and normal, the
/// same pixel's directions); returns (hit pixels, pixels differing by more than one ray).
pub fn ao_at_gpu_hits(volume: &Volume, view: &View, s: &RenderSettings, g: &Frame) -> (usize, usize) {
    let b = view.camera.basis();
    let lighting = IblLighting::new(s, None);
    let one_ray = 1.0 / s.ao.samples.max(1) as f64 + 1e-6;
    let (mut n, mut off) = (0, 0);
    for i in 0..g.pixel_count() {
        if !g.hit[i] {
            continue;
        }
        let (x, y) = (i as u32 % view.rect.width, i as u32 / view.rect.width);
        let dir = view.ray_dir(&b, x, y);
        let nv = DVec3::from(g.normal[i].map(f64::from));
        let p = hit_position(view, g, i);
        let surface = reference::AoSurface::new(volume, p, nv, dir, is_cap(volume, p, nv));
        let a = reference::ambient_at(volume, s, &lighting, &surface, (view.rect.x + x, view.rect.y + y));
        n += 1;
        off += usize::from((a.occlusion - g.occlusion[i] as f64).abs() > one_ray);
    }
    (n, off)
}

/// Whether a GPU hit is a cap, by the AO kernel's rule: its normal is a box face's outward normal
/// and it lies on that face (within 1e-3 voxel).
pub fn is_cap(volume: &Volume, p: DVec3, n: DVec3) -> bool {
    let (lo, hi, tol) = (volume.box_min(), volume.box_max(), 1e-3 * volume.spacing());
    (0..3).any(|a| {
        let axis = n[a].abs() == 1.0 && (0..3).all(|b| b == a || n[b] == 0.0);
        axis && ((n[a] < 0.0 && (p[a] - lo[a]).abs() <= tol[a])
            || (n[a] > 0.0 && (p[a] - hi[a]).abs() <= tol[a]))
    })
}

/// A floor (f >= 0 below z = 3.5) under a plate over the whole box whose lower face is at
/// z = 7.85: thin, samples -0.85, 0.15, -0.85 at z = 7, 8, 9 (f = 0.15 - |z - 8|, z in
/// [7.85, 8.15], 0.3 voxel thick); thick, 0.15 at z = 8, 9, 10 (the same lower face, 2.3 voxels
/// thick). 32 x 32 x 64, spacing 1 (the box is tall so that the seed's texture-space steps are
/// 0.63 voxel along z).
pub fn plate_scene(thick: bool) -> Volume {
    let top = if thick { 10.0 } else { 8.0 };
    sampled(if thick { "thick plate" } else { "thin plate" }, [32, 32, 64], DVec3::ONE, |p| {
        let plate = 0.15 - (8.0 - p.z).max(p.z - top).max(0.0);
        plate.max(3.5 - p.z)
    })
}

/// A volume sampling `f` at the world positions of its samples.
pub fn sampled(name: &str, dims: [usize; 3], spacing: DVec3, f: impl Fn(DVec3) -> f64) -> Volume {
    let mut data = Vec::with_capacity(dims.iter().product());
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                data.push(f(spacing * DVec3::new(i as f64, j as f64, k as f64)) as f32);
            }
        }
    }
    Volume::new(name, dims, spacing, DVec3::ZERO, data).unwrap()
}

/// The scenes of the performance tests: the engine (96^3-ish, default radius) and a sphere over a
/// plane (unbounded radius), framed at 64x64 with 16 AO samples: (name, volume, view, settings).
pub fn perf_scenes() -> Vec<(&'static str, Volume, View, RenderSettings)> {
    use isowall_model::{AoRadius, Camera};
    use isowall_volume::procedural::Procedural;
    [(Procedural::Engine, 96, AoRadius::Default), (Procedural::SphereOverPlane, 48, AoRadius::Unbounded)]
        .into_iter()
        .map(|(kind, n, radius)| {
            let volume = isowall_volume::VolumeSource::Procedural { kind, size: Some(n) }.load(None).unwrap();
            let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), 64, 64), 64, 64);
            let mut s = RenderSettings::new(kind.natural_iso());
            s.ao.samples = 16;
            s.ao.radius = radius;
            (kind.name(), volume, view, s)
        })
        .collect()
}

/// A smooth environment (no sun): brighter above, tinted along x, dim below.
pub fn smooth_environment() -> Environment {
    let (w, h) = (128u32, 64u32);
    let mut texels = Vec::new();
    for row in 0..h {
        for col in 0..w {
            let d =
                Environment::uv_to_direction((col as f64 + 0.5) / w as f64, (row as f64 + 0.5) / h as f64);
            let sky = 0.2 + 0.8 * d.z.max(0.0);
            texels.push([(sky + 0.3 * d.x.max(0.0)) as f32, sky as f32, (sky * 1.3 - 0.1 * d.y) as f32]);
        }
    }
    Environment::new("smooth", w, h, texels).unwrap()
}

/// Root mean square of `a - truth` over the pixels `counted` picks (more than 100 of them).
pub fn rmse(a: &[f32], truth: &[f32], counted: impl Fn(usize) -> bool) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for i in (0..a.len()).filter(|&i| counted(i)) {
        sum += ((a[i] - truth[i]) as f64).powi(2);
        n += 1;
    }
    assert!(n > 100, "only {n} pixels");
    (sum / n as f64).sqrt()
}

/// The sphere over a plane (40^3) framed at `w` x `h`, with 4 AO samples and ambient light only
/// (the colour is albedo * ambient * (1 - A): the occlusion made visible): the scene of the
/// filter's and the reprojection's tests.
pub fn ambient_sphere_scene(w: u32, h: u32) -> (Volume, View, RenderSettings) {
    use isowall_volume::procedural::Procedural;
    let src = isowall_volume::VolumeSource::Procedural { kind: Procedural::SphereOverPlane, size: Some(40) };
    let volume = src.load(None).unwrap();
    let view = View::whole(isowall_model::Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
    let mut s = RenderSettings::new(Procedural::SphereOverPlane.natural_iso());
    s.light.color = [0.0; 3];
    s.light.ambient = [1.0; 3];
    s.ao.samples = 4;
    (volume, view, s)
}

/// Renders `frame` of `tile` and waits for its read (the ring must have no read in flight):
/// its counters, and its image and depth where `frame.share`.
pub fn render_tile_and_read(
    gpu: &GpuRenderer,
    tile: &mut isowall_render::gpu::TileTarget,
    ring: &mut isowall_render::gpu::ReadbackRing<isowall_render::gpu::FrameRead>,
    frame: &isowall_render::gpu::TileFrame,
) -> isowall_render::gpu::TileOutput {
    gpu.render_tile(tile, frame, ring).unwrap();
    ring.wait_oldest(&gpu.ctx).unwrap();
    let mut reads = ring.take_ready();
    assert_eq!(reads.len(), 1);
    isowall_render::gpu::FrameRead::decode(reads.remove(0), gpu.ctx.queue.get_timestamp_period()).unwrap().1
}
