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
//!
//! Where the reprojected history's error goes, in the same run:
//! - `raw32` (`raw` followed by `--compare-samples`): every frame restarts at that many samples, the
//!   error a history of that many samples would have without bias;
//! - ablations of the reprojection rule (`reprojected/...`): the nearest previous pixel instead of
//!   the bilinear taps, the plane test off, the normal test off, both off (the same-side test stays),
//!   the accepted taps' blend renormalized to 1 (the rule before `accepted_share`: a history at an
//!   edge keeps its whole weight),
//!   a history cap of 8, 32 and 64 frames instead of 16 (32 and 64 differ only in an orbit of
//!   more than 33 frames), the drift test off and at other tolerances (`Rule::drift`: 1 and 3
//!   footprints over the square root of the samples a frame instead of 2), the frame's samples
//!   spent uniformly (`uniform`: every pixel takes `--samples`) instead of by history, and by
//!   history with another target (`spend-target6`, `spend-target14`; `Rule::spending`);
//! - per variant, the mean AO samples a pixel with a hit took a frame (`spp`): a reprojected frame
//!   spends the frame's samples by history, so its total is not exactly `--samples`;
//! - the reprojected orbit repeated `--repeats` times with disjoint sample patterns (each repeat's
//!   `settings.ao.frame` offset by [`REPEAT_STRIDE`]), its error per frame split into RMS bias and
//!   RMS std over the repeats ([`history::split`] says how); and where the bias sits: the RMS
//!   bias against the reference blurred over the same surface ([`history::blurred`]), and the
//!   split over pixels with a neighbour on another surface ([`on_edge`]) and over the rest;
//! - per reprojected variant, the pixels of frames `--from-frame`.. grouped by their history's
//!   weight (frames' worth of samples: 1-2, 2-4, 4-8, 8-16, 16+), each group's share and RMSE.
//!
//! Every variant's mean RMSE is printed over frames 1.. and over `--from-frame`.. (the first
//! frames of a history are short by construction).

mod history;

use super::stats::{error_stats, median, scene_spec};
use crate::args;
use crate::render::load_volume;
use anyhow::{bail, Context, Result};
use clap::Args;
use history::{blurred, split, Buckets, Split, BLUR_SIGMAS};
use isowall_model::cli_args;
use isowall_model::{Camera, Denoise, FrameState, RenderSettings, View};
use isowall_render::gpu::{FrameRead, GpuRenderer, GpuVolume, ReadbackRing, TileFrame, TileSums, TileTarget};
use isowall_render::reproject::{DriftTolerance, Rule, Spending, RULE, SPENDING};
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
    #[arg(long, value_parser = cli_args::ao_samples, default_value_t = 4)]
    pub samples: u32,
    /// Frames of the orbit
    #[arg(long, value_parser = cli_args::bench_frames, default_value_t = 30)]
    pub frames: u32,
    /// Degrees the camera turns each frame
    #[arg(long, value_parser = cli_args::degrees, default_value_t = 1.0)]
    pub degrees: f64,
    /// The converged reference of each frame: this many frames of 32 samples accumulated on the
    /// GPU (8: 256 samples per pixel)
    #[arg(long, value_parser = args::accumulated_frames, default_value_t = 8)]
    pub reference_frames: u32,
    /// Write every frame's numbers to this CSV
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// AO samples a frame of the `raw` comparison variant (its name: raw followed by this)
    #[arg(long, value_parser = cli_args::ao_samples, default_value_t = 32)]
    pub compare_samples: u32,
    /// The first frame of the second means (and of the history buckets)
    #[arg(long, value_parser = cli_args::still_frames, default_value_t = 8)]
    pub from_frame: u32,
    /// Runs of the reprojected orbit with disjoint sample patterns, for its bias and std (0 or 1: none)
    #[arg(long, value_parser = args::repeats_u32, default_value_t = 4)]
    pub repeats: u32,
    /// Write the reprojected orbit's bias and std per frame to this CSV
    #[arg(long, value_name = "FILE")]
    pub split_out: Option<PathBuf>,
    /// Write the error per history bucket to this CSV
    #[arg(long, value_name = "FILE")]
    pub buckets_out: Option<PathBuf>,
}

/// The CSV header of `--split-out`.
pub const SPLIT_HEADER: &str =
    "scene,frame,rmse,rms_bias,rms_std,pixels,bias_vs_blur0.5,bias_vs_blur1,bias_vs_blur1.5,bias_vs_blur2,\
     edge_pixels,edge_rms_bias,edge_rms_std,interior_rms_bias,interior_rms_std";

/// The CSV header of `--buckets-out`.
pub const BUCKETS_HEADER: &str = "scene,variant,history_frames,pixel_fraction,rmse";

/// The offset of a repeat's sample patterns (`settings.ao.frame`): more frames than an orbit has,
/// fewer than the references' offset.
const REPEAT_STRIDE: u32 = 10_000;

/// The CSV header of `--out`.
pub const HEADER: &str = "scene,variant,frame,ms,occlusion_rmse,occlusion_p99,flicker,spp";

/// A way of rendering the orbit.
#[derive(Clone, Debug)]
struct Variant {
    name: String,
    samples: u32,
    temporal: bool,
    denoise: bool,
    rule: Rule,
}

impl Variant {
    fn new(name: &str, samples: u32, temporal: bool, denoise: bool) -> Variant {
        Variant { name: name.to_string(), samples, temporal, denoise, rule: RULE }
    }

    /// `reprojected` under another rule.
    fn ablation(name: &str, samples: u32, rule: Rule) -> Variant {
        Variant { rule, ..Variant::new(&format!("reprojected/{name}"), samples, true, false) }
    }
}

/// The renderer's spending by history ([`SPENDING`]) with another target.
fn spend_target(target: f32) -> Spending {
    match SPENDING {
        Spending::ByHistory { least, most, .. } => Spending::ByHistory { target, least, most },
        Spending::Uniform => Spending::Uniform,
    }
}

/// A plane tolerance and normal agreement no tap fails.
const UNTESTED_PLANE: f32 = 1e30;
const UNTESTED_NORMAL: f32 = -2.0;

/// The variants at `samples` a frame: today's four, raw at `compare` samples, the rule's ablations.
fn variants(samples: u32, compare: u32) -> Vec<Variant> {
    let mut v = vec![
        Variant::new("raw", samples, false, false),
        Variant::new("reprojected", samples, true, false),
        Variant::new("denoised", samples, false, true),
        Variant::new("reprojected+denoised", samples, true, true),
        Variant::new(&format!("raw{compare}"), compare, false, false),
    ];
    let ablations = [
        ("nearest", Rule { nearest: true, ..RULE }),
        ("no-plane-test", Rule { plane_tolerance: UNTESTED_PLANE, ..RULE }),
        ("no-normal-test", Rule { normal_agreement: UNTESTED_NORMAL, ..RULE }),
        ("no-rejection", Rule { plane_tolerance: UNTESTED_PLANE, normal_agreement: UNTESTED_NORMAL, ..RULE }),
        ("renormalized", Rule { accepted_share: false, ..RULE }),
        ("cap8", Rule { max_age: 8.0, ..RULE }),
        ("cap32", Rule { max_age: 32.0, ..RULE }),
        ("cap64", Rule { max_age: 64.0, ..RULE }),
        ("no-drift-test", Rule { drift: DriftTolerance::Off, ..RULE }),
        ("drift-scale1", Rule { drift: DriftTolerance::OverSqrtSamples(1.0), ..RULE }),
        ("drift-scale3", Rule { drift: DriftTolerance::OverSqrtSamples(3.0), ..RULE }),
        ("uniform", Rule { spending: Spending::Uniform, ..RULE }),
        ("spend-target6", Rule { spending: spend_target(6.0), ..RULE }),
        ("spend-target14", Rule { spending: spend_target(14.0), ..RULE }),
    ];
    v.extend(ablations.into_iter().map(|(name, rule)| Variant::ablation(name, samples, rule)));
    v
}

/// `view` with its camera turned by `deg` degrees about the world's z axis through its target.
fn orbit(view: &View, deg: f64) -> View {
    View { camera: view.camera.yawed(deg), ..*view }
}

/// One frame's hits as the flicker needs them: per pixel, hit and distance along the ray.
struct Seen {
    view: View,
    hit: Vec<bool>,
    depth: Vec<f32>,
    /// N (outward); empty where not needed.
    normal: Vec<[f32; 3]>,
}

impl Seen {
    /// Whether pixel `q` saw the surface pixel `i` saw, as the reprojection accepts a tap: both
    /// hits, q's point within a footprint of i's tangent plane, the normals within [`RULE`]'s
    /// agreement.
    fn same_surface(&self) -> impl Fn(usize, usize) -> bool + '_ {
        let b = self.view.camera.basis();
        let w = self.view.rect.width;
        let pixel = 2.0 * b.tan_half_fov / self.view.full.1 as f64;
        let points: Vec<glam::DVec3> = (0..self.hit.len())
            .map(|i| {
                let dir = self.view.ray_dir(&b, i as u32 % w, i as u32 / w);
                self.view.camera.eye + self.depth[i] as f64 * dir
            })
            .collect();
        move |i, q| {
            let (n, m) = (self.normal[i], self.normal[q]);
            let n = glam::DVec3::new(n[0] as f64, n[1] as f64, n[2] as f64);
            let m = glam::DVec3::new(m[0] as f64, m[1] as f64, m[2] as f64);
            let plane = n.dot(points[q] - points[i]).abs();
            self.hit[i]
                && self.hit[q]
                && plane <= (RULE.plane_tolerance as f64) * pixel * self.depth[i] as f64
                && n.dot(m) >= RULE.normal_agreement as f64
        }
    }
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

/// The mean AO samples a pixel with a hit took in the frame whose sums are `sums` (read with their
/// positions where a reprojection may have spent them by history), the frame's being `samples`.
fn samples_taken(sums: &TileSums, samples: u32) -> f64 {
    let hits = sums.color.iter().enumerate().filter(|(_, c)| c[3] >= 0.5);
    let taken: Vec<f64> = hits
        .map(|(i, _)| match sums.pos.get(i) {
            Some(p) if p[3] > 0.0 => f64::from(p[3]),
            _ => f64::from(samples),
        })
        .collect();
    mean(&taken)
}

/// Per pixel, the weight of a tile's history (frames' worth of samples).
fn history_weight(sums: &TileSums) -> Vec<f32> {
    sums.ibl.iter().map(|e| e[3]).collect()
}

/// What a frame showed: per pixel, the occlusion (NaN without a hit) and the history's weight.
struct Shown {
    occlusion: Vec<f32>,
    weight: Vec<f32>,
}

/// A variant's numbers over the orbit.
struct Row {
    ms: Vec<f64>,
    /// The mean AO samples a pixel with a hit took in the frame.
    spp: Vec<f64>,
    rmse: Vec<f64>,
    p99: Vec<f64>,
    flicker: Vec<f64>,
    shown: Vec<Shown>,
}

fn mean(v: &[f64]) -> f64 {
    let v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// A scene's orbit: its volume on the GPU, the frames' views, their references (what each saw,
/// the converged occlusion).
struct Orbit<'a> {
    gpu: &'a GpuRenderer,
    gv: &'a GpuVolume,
    views: &'a [View],
    refs: &'a [(Seen, Vec<f32>)],
}

/// Renders the orbit as `v` says from settings `s` (sample patterns from `s.ao.frame`).
fn run_variant(o: &Orbit, s: &RenderSettings, v: &Variant) -> Result<Row> {
    let Orbit { gpu, gv, views, refs } = *o;
    let mut s = *s;
    s.ao.samples = v.samples;
    s.denoise = if v.denoise { Denoise::On } else { Denoise::Off };
    let temporal = v.temporal;
    let mut tile = TileTarget::new(gpu, "orbit", &views[0], 1)?;
    tile.set_reproject_rule(v.rule);
    let mut ring = ReadbackRing::<FrameRead>::new(2);
    let mut row = Row {
        ms: Vec::new(),
        spp: Vec::new(),
        rmse: Vec::new(),
        p99: Vec::new(),
        flicker: Vec::new(),
        shown: Vec::new(),
    };
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
        // A temporal tile's position sums hold, in w, the samples each pixel took on a reprojected
        // frame (0 on a frame that restarted: the frame's samples everywhere).
        let sums =
            if temporal { gpu.read_tile_sums_with_positions(&tile)? } else { gpu.read_tile_sums(&tile)? };
        row.spp.push(samples_taken(&sums, v.samples));
        let a = shown_occlusion(&sums, tile.frames());
        let (seen, truth) = &refs[k];
        let both: Vec<bool> = (0..a.len()).map(|i| seen.hit[i] && a[i].is_finite()).collect();
        let (rmse, p99) = error_stats(&a, truth, &both);
        row.rmse.push(rmse);
        row.p99.push(p99);
        if let Some(prev) = &last {
            row.flicker.push(flicker(&refs[k - 1].0, seen, prev, &a));
        }
        row.shown.push(Shown { occlusion: a.clone(), weight: history_weight(&sums) });
        last = Some(a);
    }
    Ok(row)
}

/// The CSVs of a run, each from its header.
struct Tables {
    frames: String,
    split: String,
    buckets: String,
}

pub fn run(a: &OrbitArgs) -> Result<()> {
    check(a)?;
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
    println!("# per variant: mean over frames 1.. of the occlusion RMSE and p99 |error| against each frame's reference, mean flicker, median ms; rmse_from: the mean RMSE over frames {}..", a.from_frame);
    println!("# spp_from: the mean AO samples a pixel with a hit took a frame over frames {}.. (the reprojected variants spend them by history)", a.from_frame);
    println!("scene,variant,rmse,p99,flicker,ms,rmse_from,spp_from");
    let mut t = Tables {
        frames: format!("{HEADER}\n"),
        split: format!("{SPLIT_HEADER}\n"),
        buckets: format!("{BUCKETS_HEADER}\n"),
    };
    for scene in a.scenes.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        run_scene(&gpu, a, scene, &mut t)?;
    }
    for (path, text) in [(&a.out, &t.frames), (&a.split_out, &t.split), (&a.buckets_out, &t.buckets)] {
        if let Some(path) = path {
            std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
            println!("# saved {}", path.display());
        }
    }
    Ok(())
}

/// The arguments' limits.
fn check(a: &OrbitArgs) -> Result<()> {
    if a.frames < 2 {
        bail!("--frames {}: at least 2 (flicker compares consecutive frames)", a.frames);
    }
    if a.frames >= REPEAT_STRIDE {
        bail!(
            "--frames {}: fewer than {REPEAT_STRIDE} (the repeats' sample patterns would overlap)",
            a.frames
        );
    }
    if a.from_frame == 0 || a.from_frame >= a.frames {
        bail!("--from-frame {}: from 1 to --frames - 1 ({})", a.from_frame, a.frames - 1);
    }
    if a.repeats > 99 {
        bail!("--repeats {}: at most 99 (their patterns must stay clear of the references')", a.repeats);
    }
    Ok(())
}

/// Each frame's converged reference under settings `s`: what it saw and its occlusion (NaN
/// without a hit), from `frames` frames of 32 samples with patterns disjoint from the measured ones.
fn references(
    gpu: &GpuRenderer,
    gv: &GpuVolume,
    views: &[View],
    s: &RenderSettings,
    frames: u32,
) -> Result<Vec<(Seen, Vec<f32>)>> {
    let mut r = *s;
    r.ao.samples = 32;
    r.ao.frame = 1_000_000; // disjoint from the measured frames' patterns
    let mut refs = Vec::new();
    for v in views {
        let f: Frame = gpu.render_accumulated(gv, v, &r, None, frames.max(1))?.frame;
        let occlusion: Vec<f32> =
            (0..f.pixel_count()).map(|i| if f.hit[i] { f.occlusion[i] } else { f32::NAN }).collect();
        refs.push((Seen { view: *v, hit: f.hit, depth: f.depth, normal: f.normal }, occlusion));
    }
    Ok(refs)
}

fn run_scene(gpu: &GpuRenderer, a: &OrbitArgs, scene: &str, t: &mut Tables) -> Result<()> {
    let (spec, iso) = scene_spec(scene)?;
    let (volume, iso) = load_volume(Some(spec), None, iso)?;
    let gv = gpu.upload(&volume)?;
    let (w, h) = a.size;
    let start = View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
    let views: Vec<View> = (0..a.frames).map(|k| orbit(&start, k as f64 * a.degrees)).collect();
    let mut s = RenderSettings::new(iso);
    s.ao.samples = a.samples;
    let refs = references(gpu, &gv, &views, &s, a.reference_frames)?;
    let name = &volume.name;
    let floor: Vec<f64> =
        (1..refs.len()).map(|k| flicker(&refs[k - 1].0, &refs[k].0, &refs[k - 1].1, &refs[k].1)).collect();
    for (k, f) in floor.iter().enumerate() {
        t.frames.push_str(&format!("{name},reference,{},,,,{f:.5},\n", k + 1));
    }
    println!("{name},reference,,,{:.4},,", mean(&floor));
    let o = Orbit { gpu, gv: &gv, views: &views, refs: &refs };
    let from = a.from_frame as usize;
    let mut first_run = None;
    let mut bucket_lines = Vec::new();
    for v in variants(a.samples, a.compare_samples) {
        let row = run_variant(&o, &s, &v)?;
        push_frames(&mut t.frames, name, &v.name, &row);
        println!(
            "{name},{},{:.4},{:.4},{:.4},{:.1},{:.4},{:.2}",
            v.name,
            mean(&row.rmse[1..]),
            mean(&row.p99[1..]),
            mean(&row.flicker),
            median(row.ms.clone()),
            mean(&row.rmse[from..]),
            mean(&row.spp[from..])
        );
        if v.temporal && !v.denoise {
            for b in history_buckets(&row, &refs, from).errors() {
                let line = format!("{name},{},{},{:.4},{:.5}", v.name, b.name, b.fraction, b.rmse);
                t.buckets.push_str(&format!("{line}\n"));
                bucket_lines.push(line);
            }
        }
        if v.name == "reprojected" {
            first_run = Some(row.shown.into_iter().map(|f| f.occlusion).collect::<Vec<_>>());
        }
    }
    println!("# {name}: the reprojected variants' pixels of frames {from}.. by history (frames' worth of samples): share of pixels, RMSE");
    println!("{BUCKETS_HEADER}");
    bucket_lines.iter().for_each(|l| println!("{l}"));
    if let (Some(first), true) = (first_run, a.repeats >= 2) {
        let split = reprojected_split(&o, &s, a, first)?;
        print_split(name, &split, from, a.repeats, &mut t.split);
    }
    Ok(())
}

/// A variant's frames as rows of the `--out` CSV.
fn push_frames(csv: &mut String, scene: &str, variant: &str, row: &Row) {
    for k in 0..row.rmse.len() {
        let fl = if k == 0 { String::new() } else { format!("{:.5}", row.flicker[k - 1]) };
        csv.push_str(&format!(
            "{scene},{variant},{k},{:.2},{:.5},{:.5},{fl},{:.3}\n",
            row.ms[k], row.rmse[k], row.p99[k], row.spp[k]
        ));
    }
}

/// The error of a variant's frames `from`.. by history length.
fn history_buckets(row: &Row, refs: &[(Seen, Vec<f32>)], from: usize) -> Buckets {
    let mut b = Buckets::default();
    for (shown, (_, truth)) in row.shown.iter().zip(refs).skip(from) {
        b.add(&shown.occlusion, truth, &shown.weight);
    }
    b
}

/// Per frame, the reprojected orbit's error split over `--repeats` runs, `first` (its occlusion
/// per frame) the run already made.
fn reprojected_split(
    o: &Orbit,
    s: &RenderSettings,
    a: &OrbitArgs,
    first: Vec<Vec<f32>>,
) -> Result<Vec<FrameSplit>> {
    let v = Variant::new("reprojected", a.samples, true, false);
    let mut runs = vec![first];
    for r in 1..a.repeats {
        let mut sr = *s;
        sr.ao.frame = r * REPEAT_STRIDE;
        runs.push(run_variant(o, &sr, &v)?.shown.into_iter().map(|f| f.occlusion).collect());
    }
    Ok((0..o.views.len())
        .map(|k| {
            let frame: Vec<Vec<f32>> = runs.iter().map(|run| run[k].clone()).collect();
            let ((seen, truth), width) = (&o.refs[k], o.views[k].rect.width as usize);
            let same = seen.same_surface();
            let edge = on_edge(seen.hit.len(), width, &same);
            let only = |want: bool| -> Vec<f32> {
                truth.iter().zip(&edge).map(|(&t, &e)| if e == want { t } else { f32::NAN }).collect()
            };
            FrameSplit {
                split: split(&frame, truth),
                blurred_bias: BLUR_SIGMAS
                    .map(|sigma| split(&frame, &blurred(truth, width, sigma, &same)).rms_bias),
                edge: split(&frame, &only(true)),
                interior: split(&frame, &only(false)),
            }
        })
        .collect())
}

/// Per pixel of a `width`-wide image of `n` pixels: whether one of its eight neighbours (in the
/// image) did not see its surface (`same`: a silhouette, a crease, a hit next to none).
fn on_edge(n: usize, width: usize, same: &dyn Fn(usize, usize) -> bool) -> Vec<bool> {
    let (w, h) = (width as i64, (n / width.max(1)) as i64);
    (0..n)
        .map(|i| {
            let (x, y) = (i as i64 % w, i as i64 / w);
            (-1..=1).any(|dy| {
                (-1..=1).any(|dx| {
                    let (qx, qy) = (x + dx, y + dy);
                    qx >= 0 && qy >= 0 && qx < w && qy < h && !same(i, (qx + qy * w) as usize)
                })
            })
        })
        .collect()
}

/// A frame's split; its RMS bias against the reference blurred by each of [`BLUR_SIGMAS`]; the
/// split over the pixels [`on_edge`] and over the others.
struct FrameSplit {
    split: Split,
    blurred_bias: [f64; 4],
    edge: Split,
    interior: Split,
}

/// Prints the split per frame and its means over frames `from`.., and adds it to the CSV.
fn print_split(scene: &str, split: &[FrameSplit], from: usize, repeats: u32, csv: &mut String) {
    println!("# {scene}: the reprojected orbit over {repeats} runs of disjoint patterns, per frame: RMSE, RMS bias (the reference's own noise included), RMS std; the RMS bias against the reference blurred by a Gaussian of 0.5, 1, 1.5, 2 pixels");
    println!("{SPLIT_HEADER}");
    for (k, f) in split.iter().enumerate() {
        let sp = &f.split;
        let blur = f.blurred_bias.map(|b| format!("{b:.5}")).join(",");
        let (e, i) = (&f.edge, &f.interior);
        let line = format!(
            "{scene},{k},{:.5},{:.5},{:.5},{},{blur},{},{:.5},{:.5},{:.5},{:.5}",
            sp.rmse,
            sp.rms_bias,
            sp.rms_std,
            sp.pixels,
            e.pixels,
            e.rms_bias,
            e.rms_std,
            i.rms_bias,
            i.rms_std
        );
        println!("{line}");
        csv.push_str(&format!("{line}\n"));
    }
    let over = |f: &dyn Fn(&FrameSplit) -> f64| mean(&split[from..].iter().map(f).collect::<Vec<_>>());
    let blur: Vec<String> =
        (0..BLUR_SIGMAS.len()).map(|b| format!("{:.5}", over(&|f| f.blurred_bias[b]))).collect();
    println!(
        "{scene},mean {from}..,{:.5},{:.5},{:.5},,{},{:.0},{:.5},{:.5},{:.5},{:.5}",
        over(&|f| f.split.rmse),
        over(&|f| f.split.rms_bias),
        over(&|f| f.split.rms_std),
        blur.join(","),
        over(&|f| f.edge.pixels as f64),
        over(&|f| f.edge.rms_bias),
        over(&|f| f.edge.rms_std),
        over(&|f| f.interior.rms_bias),
        over(&|f| f.interior.rms_std)
    );
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
        Seen { view, hit: vec![true; 16 * 12], depth, normal: Vec::new() }
    }

    #[test]
    fn an_edge_is_where_a_neighbour_saw_another_surface() {
        // 5 x 4 pixels: columns 0-1 one surface, 2-4 another.
        let edge = on_edge(20, 5, &|i, q| (i % 5 < 2) == (q % 5 < 2));
        let cols: Vec<usize> = (0..5).filter(|&x| edge[x + 5]).collect();
        assert_eq!(cols, vec![1, 2]);
        assert!(!on_edge(20, 5, &|_, _| true).iter().any(|&e| e));
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
