//! `isowalld bench orbit`: a moving camera through the wall's tile path. The camera orbits the
//! scene (about the world's z axis through the framing target, `--degrees` a frame) for
//! `--frames` frames, each frame a camera change (the wall's moving frames: no accumulation), in
//! four variants: `raw` (every frame restarts: today's moving wall), `reprojected` (temporal
//! reprojection of each pixel's history), `denoised` (the spatial filter) and
//! `reprojected+denoised`. Per frame against a converged render of that frame's camera
//! (`render_accumulated`, `--reference-frames` x 32 samples): the occlusion RMSE and the 99th
//! percentile of |error| over pixels both hit; the frame's ms (render and the counters' read); and
//! flicker, the mean |A_t(x) - A_{t-1}(x)| over surface points x seen in both frames (x's previous
//! pixel found by projecting its hit into the previous camera and accepted only where the
//! previous depth there agrees within 1%: the occlusion is view-independent, so the truth changes
//! by nothing; the converged references' own flicker is printed as the floor).

use super::stats::{error_stats, median, scene_spec};
use crate::args;
use crate::render::load_volume;
use anyhow::{bail, Result};
use clap::Args;
use isowall_model::{Camera, Denoise, FrameState, RenderSettings, View};
use isowall_render::gpu::{FrameRead, GpuRenderer, GpuVolume, ReadbackRing, TileFrame, TileSums, TileTarget};
use isowall_render::Frame;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct OrbitArgs {
    /// Scenes as VOLUME[@ISO], comma-separated (VOLUME as for `render --volume`)
    #[arg(long, default_value = "procedural:engine,../shared/data/ct-cranium.nrrd@300")]
    pub scenes: String,
    /// Image size (one tile showing the whole image)
    #[arg(long, default_value = "256x256", value_parser = args::size)]
    pub size: (u32, u32),
    /// AO samples per pixel per frame
    #[arg(long, default_value_t = 4)]
    pub samples: u32,
    /// Frames of the orbit
    #[arg(long, default_value_t = 30)]
    pub frames: u32,
    /// Degrees the camera turns each frame
    #[arg(long, default_value_t = 1.0)]
    pub degrees: f64,
    /// The converged reference of each frame: this many frames of 32 samples accumulated on the
    /// GPU (8: 256 samples per pixel)
    #[arg(long, default_value_t = 8)]
    pub reference_frames: u32,
    /// Write every frame's numbers to this CSV
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
}

/// The CSV header of `--out`.
pub const HEADER: &str = "scene,variant,frame,ms,occlusion_rmse,occlusion_p99,flicker";

/// The variants: (name, temporal reprojection, denoise).
const VARIANTS: [(&str, bool, bool); 4] = [
    ("raw", false, false),
    ("reprojected", true, false),
    ("denoised", false, true),
    ("reprojected+denoised", true, true),
];

/// `view` with its camera turned by `deg` degrees about the world's z axis through its target.
fn orbit(view: &View, deg: f64) -> View {
    View { camera: view.camera.yawed(deg), ..*view }
}

/// One frame's hits as the flicker needs them: per pixel, hit and distance along the ray.
struct Seen {
    view: View,
    hit: Vec<bool>,
    depth: Vec<f32>,
}

/// Per pixel of `next`, the pixel of `prev` that saw the same surface point (the projection of its
/// hit into `prev`'s camera, nearest pixel, its depth within 1% of the point's distance).
fn matches(prev: &Seen, next: &Seen) -> Vec<Option<usize>> {
    let (pb, nb) = (prev.view.camera.basis(), next.view.camera.basis());
    let (w, h) = (prev.view.full.0 as f64, prev.view.full.1 as f64);
    let nw = next.view.rect.width;
    (0..next.hit.len())
        .map(|i| {
            if !next.hit[i] {
                return None;
            }
            let (x, y) = (i as u32 % nw, i as u32 / nw);
            let p = next.view.camera.eye + next.depth[i] as f64 * next.view.ray_dir(&nb, x, y);
            let d = p - prev.view.camera.eye;
            let z = d.dot(pb.forward);
            if z <= 0.0 {
                return None;
            }
            let sx = d.dot(pb.right) / z / (pb.tan_half_fov * w / h);
            let sy = d.dot(pb.up) / z / pb.tan_half_fov;
            let (u, v) = ((sx + 1.0) * 0.5 * w, (1.0 - sy) * 0.5 * h);
            if !(u >= 0.0 && v >= 0.0 && u < w && v < h) {
                return None;
            }
            let j = u as usize + v as usize * w as usize;
            let dist = d.length();
            (prev.hit[j] && (prev.depth[j] as f64 - dist).abs() <= 0.01 * dist).then_some(j)
        })
        .collect()
}

/// Mean |a_next - a_prev| over the matched pixels.
fn flicker(prev: &Seen, next: &Seen, a_prev: &[f32], a_next: &[f32]) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for (i, m) in matches(prev, next).into_iter().enumerate() {
        if let Some(j) = m {
            if a_next[i].is_finite() && a_prev[j].is_finite() {
                sum += (a_next[i] as f64 - a_prev[j] as f64).abs();
                n += 1;
            }
        }
    }
    if n == 0 {
        f64::NAN
    } else {
        sum / n as f64
    }
}

/// The occlusion a tile's last frame shows, per pixel (NaN without a hit).
fn shown_occlusion(sums: &TileSums, frames: u32) -> Vec<f32> {
    (0..sums.color.len())
        .map(|i| {
            if sums.color[i][3] < 0.5 {
                return f32::NAN;
            }
            match &sums.denoised {
                Some(d) => d[i][3] / frames as f32,
                None => sums.ao[i][3] / sums.ibl[i][3],
            }
        })
        .collect()
}

/// A variant's numbers over the orbit.
struct Row {
    ms: Vec<f64>,
    rmse: Vec<f64>,
    p99: Vec<f64>,
    flicker: Vec<f64>,
}

fn mean(v: &[f64]) -> f64 {
    let v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

#[allow(clippy::too_many_arguments)]
fn run_variant(
    gpu: &GpuRenderer,
    gv: &GpuVolume,
    views: &[View],
    refs: &[(Seen, Vec<f32>)],
    s: &RenderSettings,
    temporal: bool,
    denoise: bool,
) -> Result<Row> {
    let mut s = *s;
    s.denoise = if denoise { Denoise::On } else { Denoise::Off };
    let mut tile = TileTarget::new(gpu, "orbit", &views[0], 1)?;
    let mut ring = ReadbackRing::<FrameRead>::new(2);
    let mut row = Row { ms: Vec::new(), rmse: Vec::new(), p99: Vec::new(), flicker: Vec::new() };
    let mut last: Option<Vec<f32>> = None;
    let mut previous: Option<FrameState> = None;
    for (k, view) in views.iter().enumerate() {
        // As a node decides: by the model's rule, from the frame state before.
        let state = FrameState::new(k as u64, &view.camera, &s, 1);
        let continuity = state.continuity(previous.as_ref());
        previous = Some(state);
        let tf = TileFrame {
            frame_id: k as u64,
            volume: gv,
            view,
            settings: &s,
            env: None,
            continuity,
            temporal,
            share: None,
        };
        let start = Instant::now();
        gpu.render_tile(&mut tile, &tf, &mut ring)?;
        loop {
            ring.wait_oldest(&gpu.ctx)?;
            if !ring.take_ready().is_empty() {
                break;
            }
        }
        row.ms.push(start.elapsed().as_secs_f64() * 1e3);
        let a = shown_occlusion(&gpu.read_tile_sums(&tile)?, tile.frames());
        let (seen, truth) = &refs[k];
        let both: Vec<bool> = (0..a.len()).map(|i| seen.hit[i] && a[i].is_finite()).collect();
        let (rmse, p99) = error_stats(&a, truth, &both);
        row.rmse.push(rmse);
        row.p99.push(p99);
        if let Some(prev) = &last {
            row.flicker.push(flicker(&refs[k - 1].0, seen, prev, &a));
        }
        last = Some(a);
    }
    Ok(row)
}

pub fn run(a: &OrbitArgs) -> Result<()> {
    if a.frames < 2 {
        bail!("--frames {}: at least 2 (flicker compares consecutive frames)", a.frames);
    }
    let gpu = GpuRenderer::new()?;
    let (w, h) = a.size;
    println!(
        "# isowalld bench orbit: {w}x{h}, {} frames of {} degrees, {} AO samples a frame, adapter '{}'; \
         reference: {} frames x 32 samples ({} spp) per frame",
        a.frames,
        a.degrees,
        a.samples,
        gpu.adapter_name(),
        a.reference_frames,
        a.reference_frames * 32
    );
    println!("# per variant: mean over frames 1.. of the occlusion RMSE and p99 |error| against each frame's reference, mean flicker, median ms");
    println!("scene,variant,rmse,p99,flicker,ms");
    let mut csv = format!("{HEADER}\n");
    for scene in a.scenes.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (spec, iso) = scene_spec(scene)?;
        let (volume, iso) = load_volume(Some(spec), None, iso)?;
        let gv = gpu.upload(&volume)?;
        let start = View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
        let views: Vec<View> = (0..a.frames).map(|k| orbit(&start, k as f64 * a.degrees)).collect();
        let mut s = RenderSettings::new(iso);
        s.ao.samples = a.samples;
        let mut r = s;
        r.ao.samples = 32;
        r.ao.frame = 1_000_000; // disjoint from the measured frames' patterns
        let mut refs = Vec::new();
        for v in &views {
            let f: Frame = gpu.render_accumulated(&gv, v, &r, None, a.reference_frames.max(1))?.frame;
            let occlusion: Vec<f32> =
                (0..f.pixel_count()).map(|i| if f.hit[i] { f.occlusion[i] } else { f32::NAN }).collect();
            refs.push((Seen { view: *v, hit: f.hit, depth: f.depth }, occlusion));
        }
        let floor: Vec<f64> = (1..refs.len())
            .map(|k| flicker(&refs[k - 1].0, &refs[k].0, &refs[k - 1].1, &refs[k].1))
            .collect();
        for (k, f) in floor.iter().enumerate() {
            csv.push_str(&format!("{},reference,{},,,,{f:.5}\n", volume.name, k + 1));
        }
        println!("{},reference,,,{:.4},", volume.name, mean(&floor));
        for (name, temporal, denoise) in VARIANTS {
            let row = run_variant(&gpu, &gv, &views, &refs, &s, temporal, denoise)?;
            for k in 0..views.len() {
                let fl = if k == 0 { String::new() } else { format!("{:.5}", row.flicker[k - 1]) };
                csv.push_str(&format!(
                    "{},{name},{k},{:.2},{:.5},{:.5},{fl}\n",
                    volume.name, row.ms[k], row.rmse[k], row.p99[k]
                ));
            }
            println!(
                "{},{name},{:.4},{:.4},{:.4},{:.1}",
                volume.name,
                mean(&row.rmse[1..]),
                mean(&row.p99[1..]),
                mean(&row.flicker),
                median(row.ms.clone())
            );
        }
    }
    if let Some(path) = &a.out {
        std::fs::write(path, csv).map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))?;
        println!("# saved {}", path.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    /// A plane z = 0 under a camera looking down from `eye`.
    fn seen(eye: DVec3) -> Seen {
        let cam = Camera { eye, target: eye - DVec3::new(0.0, 0.0, 1.0), up: DVec3::Y, fov_y_deg: 40.0 };
        let view = View::whole(cam, 16, 12);
        let b = view.camera.basis();
        let depth: Vec<f32> = (0..16 * 12)
            .map(|i| {
                let d = view.ray_dir(&b, i % 16, i / 16);
                (-eye.z / d.z) as f32
            })
            .collect();
        Seen { view, hit: vec![true; 16 * 12], depth }
    }

    #[test]
    fn flicker_follows_points_and_is_zero_for_an_unchanged_signal_on_them() {
        let a = seen(DVec3::new(0.0, 0.0, 2.0));
        let b = seen(DVec3::new(0.2, 0.0, 2.0));
        let m = matches(&a, &b);
        // The camera moved right: a matched pixel's previous pixel lies to its right.
        let matched: Vec<(usize, usize)> =
            m.iter().enumerate().filter_map(|(i, j)| j.map(|j| (i, j))).collect();
        assert!(matched.len() > 100 && matched.len() < 16 * 12, "{}", matched.len());
        assert!(matched.iter().all(|&(i, j)| j % 16 > i % 16 && j / 16 == i / 16));
        // A signal painted on the plane (a function of world x) does not flicker; one painted on
        // the screen does.
        let world = |s: &Seen| -> Vec<f32> {
            let bb = s.view.camera.basis();
            (0..s.hit.len())
                .map(|i| {
                    let p = s.view.camera.eye
                        + s.depth[i] as f64 * s.view.ray_dir(&bb, i as u32 % 16, i as u32 / 16);
                    p.x as f32
                })
                .collect()
        };
        assert!(flicker(&a, &b, &world(&a), &world(&b)) < 0.1);
        let screen: Vec<f32> = (0..16 * 12).map(|i| (i % 16) as f32).collect();
        assert!(flicker(&a, &b, &screen, &screen) > 1.0);
    }
}
