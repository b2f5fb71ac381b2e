//! `isowalld bench`: renderer benchmarks. Times are medians of repeated frames measured in one run;
//! hardware-free counts (trilinear fetches per pixel) sit beside them.

mod accuracy;
pub(crate) mod chart;
mod denoise;
mod frame;
mod imbalance;
mod look;
mod orbit;
mod stats;
mod stream;
mod suite;

use crate::args;
use crate::render::load_volume;
use accuracy::AccuracyArgs;
use anyhow::Result;
use clap::{Args, Subcommand};
use isowall_model::cli_args;
use isowall_model::{AoMethod, Camera, RenderSettings, View};
use isowall_render::gpu::GpuRenderer;
use stats::{error_stats, median, sample_list, scene_spec};

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Primary rays only (first hit, normal, direct shading): ms per frame and trilinear fetches per
    /// pixel with and without empty-space skipping, each with its error against the exact CPU
    /// reference renderer (median depth error over pixels both hit, and the share of pixels whose
    /// hit differs or whose depth is off by more than 0.05 voxel).
    Primary(PrimaryArgs),
    /// Ambient occlusion: ms per frame, trilinear fetches per pixel and the error of the occlusion
    /// AOV against a converged reference, for each AO method and sample count.
    Ao(AoArgs),
    /// Speed against accuracy: sweeps AO methods (seed; ours; ours accumulated over 2/4/8 frames;
    /// ours stepped at 0.25-2 voxels), samples per frame and IBL methods over several scenes, and
    /// writes accuracy.csv (frame time, fetches per pixel, error against a converged reference per
    /// point), chart.png and chart.svg (occlusion RMSE against time, log-log, one panel per scene,
    /// Pareto front dashed) into --out; prints the error at fixed time budgets.
    Accuracy(AccuracyArgs),
    /// A fixed set of scenes, sizes and sample counts: ms per frame, fetches per pixel and error
    /// per row; `--save FILE` writes them, `--baseline FILE` compares with an earlier build's
    /// file as ratios (docs/bench/baseline-lavapipe.csv).
    Suite(suite::SuiteArgs),
    /// One frame of a wall tile (default 1920x1080) by the node's frame path, in screen space
    /// (presented offscreen, then a snapshot) and object space (the share read back): per frame GPU
    /// allocations, bytes read back and uploaded, CPU ms outside GPU waits, ms per frame and GPU ms
    /// per kernel; `--variants plain` (or `before`) measures the earlier path in the same run;
    /// `--save` and `--baseline` as `bench suite` has them.
    Frame(frame::FrameArgs),
    /// The AO filter (`--denoise on`) judged by the independent estimate of DESIGN.md "AO"
    /// (isowall-truth), on the CT, the MRI and the engine: for 1..32 samples in one frame, raw and
    /// denoised, the occlusion RMSE, p99 of |error| and bias at chosen hit pixels, and the median
    /// ms per frame; then the goal check (denoised 4 spp against raw 32 spp: its RMSE in at most a
    /// third of the time, p99 at most 1.5x). `--out DIR` writes denoise.csv and chart.svg.
    Denoise(denoise::DenoiseArgs),
    /// A moving camera through the wall's tile path: a `--frames` orbit of `--degrees` a frame,
    /// every frame a camera change, in four variants (raw: each frame restarts, as a moving wall
    /// did before; reprojected: each pixel's history carried over; denoised; reprojected and
    /// denoised). Per variant: the occlusion RMSE and p99 |error| against a converged render of
    /// each frame's camera, flicker (mean change of the occlusion of a surface point between
    /// consecutive frames; the converged references' own is the floor) and the median ms per
    /// frame; `--out` writes every frame's numbers as CSV. Where the history's error goes: raw at
    /// `--compare-samples`, the reprojection rule's ablations (nearest pixel, rejection tests off,
    /// history caps, drift tolerances), means from `--from-frame`, the reprojected error split into bias and std
    /// over `--repeats` runs (`--split-out`) and by history length (`--buckets-out`).
    Orbit(orbit::OrbitArgs),
    /// Whether the default look shows shape: per scene and IBL method, how much darker surface
    /// pixels in creases (A >= 0.3) look than open ones (A <= 0.05) at the same N.L, in linear
    /// light and as shown (sRGB); `--before` the earlier defaults in the same run, `--out DIR` the
    /// pictures. Ends with one line `look: darkness X at worst ...`.
    Look(look::LookArgs),
    /// How unevenly a wall's nodes share a frame in screen space (a wall is as slow as its slowest
    /// node): every tile of `--config`'s wall rendered through the tile path, still and orbiting;
    /// per frame and node the trilinear fetches, ms (submit to done), CPU ms and share of the
    /// wall's work, the slowest node over the mean per frame and averaged. `--scale S` renders
    /// each tile at 1/S resolution per axis (fetches then about 1/S^2 of a full frame's). Ends
    /// with one line `imbalance: slowest/mean X still, Y orbiting (by fetches); ...`.
    Imbalance(imbalance::ImbalanceArgs),
    /// A volume through the brick cache (`render --gpu-budget-mb`) as a viewer meets it: opens
    /// it, draws the first picture from what is resident, refines the still view to level 0 with
    /// capped uploads a frame, orbits (each frame's bricks at the level their pixel footprint
    /// asks), stops and refines again. Prints the time to the first picture and to level 0 after
    /// the stop, uploads per frame, the pool's hit rate, passes and peak memory; ends with one line
    /// `stream: first X s, converged Y s after stop, peak gpu G' MB, peak host H' MB`.
    Stream(stream::StreamArgs),
}

#[derive(Args)]
pub struct AoArgs {
    /// Scenes as VOLUME[@ISO], comma-separated (VOLUME as for `render --volume`)
    #[arg(long, default_value = "procedural:engine,../shared/data/ct-cranium.nrrd@300")]
    pub scenes: String,
    /// Image size
    #[arg(long, default_value = "512x512", value_parser = args::size)]
    pub size: (u32, u32),
    /// AO samples per pixel per frame, comma-separated
    #[arg(long, default_value = "8,32,64,128,256")]
    pub samples: String,
    /// Frames per configuration (the median is reported)
    #[arg(long, value_parser = cli_args::repeats, default_value_t = 3)]
    pub repeats: usize,
    /// The converged reference: ours with this many frames of 256 samples accumulated on the GPU
    /// (the exact CPU renderer agrees with the GPU's AO to within a ray or two per pixel, and is too
    /// slow at this size)
    #[arg(long, value_parser = args::accumulated_frames, default_value_t = 16)]
    pub reference_frames: u32,
}

#[derive(Args)]
pub struct PrimaryArgs {
    /// Scenes as VOLUME[@ISO], comma-separated (VOLUME as for `render --volume`)
    #[arg(long, default_value = "procedural:engine,../shared/data/ct-cranium.nrrd@300")]
    pub scenes: String,
    /// Image size
    #[arg(long, default_value = "512x512", value_parser = args::size)]
    pub size: (u32, u32),
    /// Frames per configuration (the median is reported)
    #[arg(long, value_parser = cli_args::repeats, default_value_t = 7)]
    pub repeats: usize,
}

pub fn run(cmd: &BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Primary(a) => primary(a),
        BenchCommand::Ao(a) => ao(a),
        BenchCommand::Accuracy(a) => accuracy::run(a),
        BenchCommand::Suite(a) => suite::run(a),
        BenchCommand::Frame(a) => frame::run(a),
        BenchCommand::Denoise(a) => denoise::run(a),
        BenchCommand::Orbit(a) => orbit::run(a),
        BenchCommand::Look(a) => look::run(a),
        BenchCommand::Imbalance(a) => imbalance::run(a),
        BenchCommand::Stream(a) => stream::run(a),
    }
}

fn ao(a: &AoArgs) -> Result<()> {
    let gpu = GpuRenderer::new()?;
    let (w, h) = a.size;
    let samples = sample_list(&a.samples)?;
    println!(
        "# isowalld bench ao: {w}x{h}, median of {} frames, adapter '{}'; reference: ours, {} frames x 256 samples",
        a.repeats.max(1),
        gpu.adapter_name(),
        a.reference_frames
    );
    println!("scene,method,samples,ms_per_frame,fetches_per_pixel,occlusion_rmse,occlusion_p99");
    for scene in a.scenes.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (spec, iso) = scene_spec(scene)?;
        let (volume, iso) = load_volume(Some(spec), None, iso)?;
        let gv = gpu.upload(&volume)?;
        let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
        let mut s = RenderSettings::new(iso);
        s.ao.samples = 256;
        s.ao.frame = 1_000_000; // disjoint from the measured frames' patterns
        let reference = gpu.render_accumulated(&gv, &view, &s, None, a.reference_frames)?.frame;
        let primary_only = gpu.render(&gv, &view, &RenderSettings::new(iso), None)?;
        for method in [AoMethod::Seed, AoMethod::Ours] {
            for &n in &samples {
                let mut s = RenderSettings::new(iso);
                s.ao.samples = n;
                s.ao.method = method;
                gpu.render(&gv, &view, &s, None)?; // warm-up
                let mut times = Vec::new();
                let mut last = None;
                for r in 0..a.repeats.max(1) {
                    s.ao.frame = r as u32;
                    let out = gpu.render(&gv, &view, &s, None)?;
                    times.push(out.gpu_time.as_secs_f64() * 1e3);
                    last = Some(out.frame);
                }
                let f = last.expect("at least one repeat");
                let (rmse, p99) = error_stats(&f.occlusion, &reference.occlusion, &reference.hit);
                println!(
                    "{},{},{n},{:.2},{:.1},{rmse:.4},{p99:.4}",
                    volume.name,
                    match method {
                        AoMethod::Ours => "ours",
                        AoMethod::Seed => "seed",
                    },
                    median(times),
                    f.fetches_per_pixel(),
                );
            }
        }
        println!(
            "{},primary-only,0,{:.2},{:.1},,",
            volume.name,
            primary_only.gpu_time.as_secs_f64() * 1e3,
            primary_only.frame.fetches_per_pixel()
        );
    }
    Ok(())
}

fn primary(a: &PrimaryArgs) -> Result<()> {
    let gpu = GpuRenderer::new()?;
    let (w, h) = a.size;
    println!(
        "# isowalld bench primary: {w}x{h}, median of {} frames, adapter '{}'",
        a.repeats.max(1),
        gpu.adapter_name()
    );
    println!(
        "scene,iso,empty_space_skipping,ms_per_frame,fetches_per_pixel,hit_pixels,median_depth_error_voxels,pixels_off_reference_percent"
    );
    for scene in a.scenes.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (spec, iso) = match scene.rsplit_once('@') {
            Some((s, i)) => (
                s,
                Some(i.parse::<f64>().map_err(|_| anyhow::anyhow!("{scene}: iso '{i}' is not a number"))?),
            ),
            None => (scene, None),
        };
        let (volume, iso) = load_volume(Some(spec), None, iso)?;
        let gv = gpu.upload(&volume)?;
        let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
        let mut frames = Vec::new();
        for ess in [false, true] {
            let mut s = RenderSettings::new(iso);
            s.empty_space_skipping = ess;
            gpu.render(&gv, &view, &s, None)?; // warm-up
            let mut times = Vec::new();
            let mut last = None;
            for _ in 0..a.repeats.max(1) {
                let r = gpu.render(&gv, &view, &s, None)?;
                times.push(r.gpu_time.as_secs_f64() * 1e3);
                last = Some(r.frame);
            }
            let frame = last.expect("at least one repeat");
            frames.push((ess, median(times), frame));
        }
        let reference = isowall_render::reference::render(&volume, &view, &RenderSettings::new(iso));
        let voxel = volume.spacing().min_element();
        for (ess, ms, f) in &frames {
            let mut depth_err: Vec<f64> = (0..f.pixel_count())
                .filter(|&i| f.hit[i] && reference.hit[i])
                .map(|i| (f.depth[i] as f64 - reference.depth[i] as f64).abs() / voxel)
                .collect();
            let off = (0..f.pixel_count())
                .filter(|&i| {
                    f.hit[i] != reference.hit[i]
                        || (f.hit[i] && (f.depth[i] as f64 - reference.depth[i] as f64).abs() > 0.05 * voxel)
                })
                .count();
            let median_err = if depth_err.is_empty() { 0.0 } else { median(std::mem::take(&mut depth_err)) };
            println!(
                "{},{iso},{},{ms:.2},{:.2},{},{median_err:.2e},{:.3}",
                volume.name,
                if *ess { "on" } else { "off" },
                f.fetches_per_pixel(),
                f.hit_count(),
                off as f64 * 100.0 / f.pixel_count() as f64
            );
        }
    }
    Ok(())
}
