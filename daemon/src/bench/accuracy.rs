//! `isowalld bench accuracy`: speed against accuracy, swept over AO methods, samples, IBL methods
//! and scenes (DESIGN.md "Accuracy and speed"): accuracy.csv, the chart and the summary.

use super::chart::{Chart, Marker, Panel, Series};
use super::stats::{error_stats, median, scene_file, scene_key, scene_spec};
use crate::args;
use crate::render::load_volume;
use anyhow::{Context, Result};
use clap::Args;
use isowall_model::cli_args;
use isowall_model::{AoMethod, Camera, IblMethod, RenderSettings, View};
use isowall_render::environment::Environment;
use isowall_render::gpu::{GpuRenderer, PerfOptions};
use std::time::Instant;

/// The scenes of the speed/accuracy chart (DESIGN.md "Accuracy and speed").
pub const ACCURACY_SCENES: &str = "procedural:engine,procedural:marschner-lobb,procedural:sphere-over-plane,\
                                   ../shared/data/ct-cranium.nrrd@300,../shared/data/mri-brainsmall.nrrd@40";

#[derive(Args)]
pub struct AccuracyArgs {
    /// Scenes as VOLUME[@ISO], comma-separated (VOLUME as for `render --volume`; a relative path
    /// not in the working folder is looked for relative to the checkout this binary was built
    /// from, where the default scenes' `../shared/data` is); files found in neither are skipped,
    /// said once at the start
    #[arg(long, default_value = ACCURACY_SCENES)]
    pub scenes: String,
    /// Image size
    #[arg(long, default_value = "128x128", value_parser = args::size)]
    pub size: (u32, u32),
    /// Timed frames per point (the median is reported; one untimed warm-up before) [default: 3, or
    /// 1 with --quick]
    #[arg(long, value_parser = cli_args::repeats)]
    pub repeats: Option<usize>,
    /// Output directory for accuracy.csv, chart.png, chart.svg and summary.txt (created)
    #[arg(long, default_value = "accuracy")]
    pub out: std::path::PathBuf,
    /// Frames of 256 samples accumulated for the converged reference [default: 16, or 4 with --quick]
    #[arg(long, value_parser = args::accumulated_frames)]
    pub reference_frames: Option<u32>,
    /// A small sweep (samples 4, 16, 64; fewer variants) for smoke tests
    #[arg(long)]
    pub quick: bool,
    /// Time budgets (ms, comma-separated) at which the summary gives each method's error
    #[arg(long, default_value = BUDGETS_MS)]
    pub budgets: String,
    /// Measure nothing: redraw the chart and the summary from an accuracy.csv this command wrote
    #[arg(long, value_name = "FILE")]
    pub from_csv: Option<std::path::PathBuf>,
}

/// One point of the speed/accuracy sweep.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Variant {
    method: AoMethod,
    /// Ours: the exact per-cell test (`true`) or a march of `step` voxels (`false`).
    exact: bool,
    step: f64,
    samples: u32,
    frames: u32,
    ibl: IblMethod,
    /// The primary rays march on the hardware-filtered `texture_3d` copy of the volume
    /// (`PerfOptions::texture`; the refinement still exact from the storage volume).
    texture: bool,
}

/// How a curve of the chart is drawn.
struct Curve {
    label: String,
    color: (u8, u8, u8),
    marker: Marker,
}

impl Variant {
    fn ours(samples: u32) -> Variant {
        Variant {
            method: AoMethod::Ours,
            exact: true,
            step: 0.5,
            samples,
            frames: 1,
            ibl: IblMethod::None,
            texture: false,
        }
    }

    /// Ours, exact, with the primary march on the hardware-filtered texture.
    fn texture(samples: u32) -> Variant {
        Variant { texture: true, ..Variant::ours(samples) }
    }

    fn method_name(&self) -> &'static str {
        match (self.method, self.exact, self.texture) {
            (AoMethod::Seed, _, _) => "seed",
            (AoMethod::Ours, true, false) => "ours",
            (AoMethod::Ours, true, true) => "ours-texture",
            (AoMethod::Ours, false, _) => "ours-stepped",
        }
    }

    fn step_name(&self) -> String {
        match (self.method, self.exact) {
            (AoMethod::Seed, _) => String::new(),
            (AoMethod::Ours, true) => "exact".into(),
            (AoMethod::Ours, false) => format!("{}", self.step),
        }
    }

    fn ibl_name(&self) -> &'static str {
        self.ibl.name()
    }

    /// The chart's curve this point belongs to (every point with the same curve but `samples`);
    /// `None` for IBL points, which are not on the occlusion chart (their AO is ours').
    fn curve(&self) -> Option<Curve> {
        if self.ibl != IblMethod::None {
            return None;
        }
        let (label, color, marker) = match (self.method, self.exact, self.frames) {
            (AoMethod::Seed, _, _) => ("seed (2008)".to_string(), (214, 39, 40), Marker::Triangle),
            (AoMethod::Ours, true, 1) if self.texture => {
                ("ours, texture march".into(), (64, 64, 64), Marker::Circle)
            }
            (AoMethod::Ours, true, 1) => ("ours (exact)".into(), (31, 119, 180), Marker::Circle),
            (AoMethod::Ours, true, k) => {
                let color = match k {
                    2 => (23, 190, 207),
                    4 => (148, 103, 189),
                    _ => (227, 119, 194),
                };
                (format!("ours, {k} frames accumulated"), color, Marker::Circle)
            }
            (AoMethod::Ours, false, _) => {
                let color = match self.step {
                    s if s <= 0.25 => (44, 160, 44),
                    s if s <= 0.5 => (188, 189, 34),
                    s if s <= 1.0 => (255, 127, 14),
                    _ => (140, 86, 75),
                };
                (format!("ours stepped, {} voxel", self.step), color, Marker::Square)
            }
        };
        Some(Curve { label, color, marker })
    }
}

/// The sweep: methods x samples at the default (exact) test, accumulated frames, march steps x a
/// couple of sample counts, IBL methods x a couple of sample counts, and ours with the primary
/// march on the filtered texture x samples (last: the kernels are compiled for it once a pass).
/// Not the cartesian product.
fn accuracy_sweep(quick: bool) -> Vec<Variant> {
    // Ours also at 1 and 2 samples, so that the time at which ours reaches the seed's error can be
    // interpolated rather than bounded (the seed needs 4: below that its disk rejects every sample).
    let low: &[u32] = if quick { &[] } else { &[1, 2] };
    let samples: &[u32] = if quick { &[4, 16, 64] } else { &[4, 8, 16, 32, 64, 128, 256] };
    let (frames, max_rays): (&[u32], u32) = if quick { (&[2], 32) } else { (&[2, 4, 8], 512) };
    let steps: &[f64] = if quick { &[0.5, 2.0] } else { &[0.25, 0.5, 1.0, 2.0] };
    let few: &[u32] = if quick { &[16] } else { &[16, 64] };
    let mut v = Vec::new();
    for &n in samples {
        v.push(Variant { method: AoMethod::Seed, ..Variant::ours(n) });
    }
    v.extend(low.iter().chain(samples).map(|&n| Variant::ours(n)));
    for &k in frames {
        for &n in samples.iter().filter(|&&n| n * k <= max_rays) {
            v.push(Variant { frames: k, ..Variant::ours(n) });
        }
    }
    for &step in steps {
        for &n in few {
            v.push(Variant { exact: false, step, ..Variant::ours(n) });
        }
    }
    for ibl in [IblMethod::Seed, IblMethod::Bent, IblMethod::Rays] {
        for &n in few {
            v.push(Variant { ibl, ..Variant::ours(n) });
        }
    }
    v.extend(samples.iter().map(|&n| Variant::texture(n)));
    v
}

/// One measured point.
#[derive(Clone, Debug)]
struct AccuracyRow {
    scene: String,
    variant: Variant,
    ms: f64,
    fetches_per_pixel: f64,
    occlusion_rmse: f64,
    occlusion_p99: f64,
    color_rmse: f64,
}

/// RMSE of linear RGB over pixels where `hit` holds (all three channels).
fn color_rmse(a: &[[f32; 3]], b: &[[f32; 3]], hit: &[bool]) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for i in (0..a.len()).filter(|&i| hit[i]) {
        for c in 0..3 {
            let d = a[i][c] as f64 - b[i][c] as f64;
            sum += d * d;
        }
        n += 3;
    }
    if n == 0 {
        0.0
    } else {
        (sum / n as f64).sqrt()
    }
}

/// A panel title: a readable name, the dimensions and the iso value.
fn scene_title(key: &str, dims: [usize; 3], iso: f64) -> String {
    let name = match key {
        "engine" => "engine-like",
        "marschner-lobb" => "Marschner-Lobb",
        "sphere-over-plane" => "sphere over plane",
        "ct-cranium" => "CT cranium",
        "mri-brainsmall" => "MRI head",
        other => other,
    };
    format!("{name} {}x{}x{}, iso {iso}", dims[0], dims[1], dims[2])
}

/// `y` at `x` along a curve of points sorted by x, interpolated linearly in log-log; `None` outside
/// the curve's x range (no extrapolation).
fn interp_loglog(curve: &[(f64, f64)], x: f64) -> Option<f64> {
    let first = curve.first()?;
    let last = curve.last()?;
    if x < first.0 || x > last.0 {
        return None;
    }
    for w in curve.windows(2) {
        let ((x0, y0), (x1, y1)) = (w[0], w[1]);
        if x >= x0 && x <= x1 {
            if x1 <= x0 {
                return Some(y0.min(y1));
            }
            let t = (x.ln() - x0.ln()) / (x1.ln() - x0.ln());
            return Some((y0.ln() + t * (y1.ln() - y0.ln())).exp());
        }
    }
    Some(first.1) // a single point at exactly x
}

/// When a curve (sorted by time) first reaches an error.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Reach {
    /// At this time, interpolated in log-log between the two points around the crossing.
    At(f64),
    /// Already at the curve's fastest point, at this time (the true time may be lower).
    AtMost(f64),
    /// Never, within the curve.
    Never,
}

fn time_to_reach(curve: &[(f64, f64)], y: f64) -> Reach {
    match curve.iter().position(|p| p.1 <= y) {
        None => Reach::Never,
        Some(0) => Reach::AtMost(curve[0].0),
        Some(i) => {
            let ((t0, e0), (t1, e1)) = (curve[i - 1], curve[i]);
            if e0 <= e1 || t1 <= t0 {
                return Reach::At(t1);
            }
            let u = (y.ln() - e0.ln()) / (e1.ln() - e0.ln());
            Reach::At((t0.ln() + u * (t1.ln() - t0.ln())).exp())
        }
    }
}

/// The (ms, occlusion RMSE) curve of the points of `scene` matching `pred`: their Pareto front
/// (a point slower and no more accurate than another is left out, as a user would never pick it;
/// this also keeps timing noise from folding the curve back), sorted by time, error falling.
fn curve_of(rows: &[AccuracyRow], scene: &str, pred: impl Fn(&Variant) -> bool) -> Vec<(f64, f64)> {
    let points: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| r.scene == scene && pred(&r.variant))
        .map(|r| (r.ms, r.occlusion_rmse))
        .filter(|&(t, e)| t > 0.0 && e > 0.0)
        .collect();
    super::chart::pareto_front(&points)
}

/// The error a method achieves within a time budget: interpolated (log-log) along its curve (its
/// non-dominated points), the curve's lowest error past its last point; `Err` with the reason
/// where the budget lies outside the times measured (below the fastest or above the slowest point).
fn error_at_budget(
    rows: &[AccuracyRow],
    scene: &str,
    pred: impl Fn(&Variant) -> bool,
    budget: f64,
) -> Result<f64, String> {
    let front = curve_of(rows, scene, &pred);
    let slowest = rows
        .iter()
        .filter(|r| r.scene == scene && pred(&r.variant))
        .map(|r| r.ms)
        .fold(f64::NEG_INFINITY, f64::max);
    match (front.first(), front.last()) {
        (Some(f), _) if budget < f.0 => Err(format!("n/a (fastest {:.0} ms)", f.0)),
        _ if budget > slowest => Err(format!("n/a (slowest {slowest:.0} ms)")),
        (Some(_), Some(l)) if budget >= l.0 => Ok(l.1),
        (Some(_), Some(_)) => interp_loglog(&front, budget).ok_or_else(|| "n/a".to_string()),
        _ => Err("n/a (no points)".into()),
    }
}

fn is_ours(v: &Variant) -> bool {
    *v == Variant::ours(v.samples)
}

fn is_seed(v: &Variant) -> bool {
    v.method == AoMethod::Seed && v.frames == 1 && v.ibl == IblMethod::None
}

/// The default time budgets of the summary's table (ms).
pub const BUDGETS_MS: &str = "10,30,100";

/// Speed-ups of ours over the seed, with whether each is only a lower bound.
#[derive(Default)]
struct Speedups(Vec<(f64, bool)>);

impl Speedups {
    /// How much sooner ours (curve) reaches `err`, which the seed reaches at `t_seed`; as text.
    fn add(&mut self, ours: &[(f64, f64)], err: f64, t_seed: f64) -> String {
        match time_to_reach(ours, err) {
            Reach::At(t) => {
                self.0.push((t_seed / t, false));
                format!("ours reaches it at {t:.1} ms, {:.1}x sooner", t_seed / t)
            }
            Reach::AtMost(t) => {
                self.0.push((t_seed / t, true));
                format!(
                    "ours is below it at its fastest point ({t:.1} ms): at least {:.1}x sooner",
                    t_seed / t
                )
            }
            Reach::Never => "ours never reaches it".into(),
        }
    }

    fn range(&self) -> Option<String> {
        let lo = self.0.iter().map(|s| s.0).fold(f64::INFINITY, f64::min);
        let hi = self.0.iter().map(|s| s.0).fold(0.0, f64::max);
        let bound = if self.0.iter().any(|s| s.1) { " (some only lower bounds)" } else { "" };
        (!self.0.is_empty()).then(|| format!("{lo:.1}x to {hi:.1}x sooner{bound}"))
    }
}

/// Smallest, largest and geometric mean of positive ratios.
fn ratio_stats(r: &[f64]) -> Option<(f64, f64, f64)> {
    if r.is_empty() {
        return None;
    }
    let (lo, hi) = r.iter().fold((f64::INFINITY, 0.0f64), |(l, h), &x| (l.min(x), h.max(x)));
    Some((lo, hi, (r.iter().map(|x| x.ln()).sum::<f64>() / r.len() as f64).exp()))
}

/// The summary: occlusion RMSE of ours and seed at the time budgets, the error ratio at equal
/// time, how much sooner ours reaches the seed's error, and the IBL methods' colour error.
fn accuracy_summary(rows: &[AccuracyRow], scenes: &[(String, String, f64)], budgets: &[f64]) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let _ = writeln!(
        o,
        "Occlusion RMSE within a time budget: log-log interpolation along each method's curve (its\n\
         non-dominated points; past the last one, its lowest error); n/a outside the times measured:\n"
    );
    let heads: Vec<String> = budgets.iter().map(|b| format!("{b} ms")).collect();
    let _ = writeln!(o, "| scene | method | {} | primary only |", heads.join(" | "));
    let _ = writeln!(o, "|---|---|{}---|", "---|".repeat(budgets.len()));
    for (key, _, primary_ms) in scenes {
        for (name, pred) in [("ours", is_ours as fn(&Variant) -> bool), ("seed", is_seed)] {
            let cells: Vec<String> = budgets
                .iter()
                .map(|&b| error_at_budget(rows, key, pred, b).map_or_else(|e| e, |v| format!("{v:.4}")))
                .collect();
            let _ = writeln!(o, "| {key} | {name} | {} | {primary_ms:.1} ms |", cells.join(" | "));
        }
    }
    let _ = writeln!(o, "\nOurs against the seed (occlusion RMSE):\n");
    let (mut all_ratios, mut vs_256) = (Vec::new(), Speedups::default());
    for (key, _, _) in scenes {
        let ours = curve_of(rows, key, is_ours);
        let seed: Vec<&AccuracyRow> =
            rows.iter().filter(|r| r.scene == *key && is_seed(&r.variant)).collect();
        let ratios: Vec<f64> = seed
            .iter()
            .filter_map(|r| error_at_budget(rows, key, is_ours, r.ms).ok().map(|eo| r.occlusion_rmse / eo))
            .collect();
        all_ratios.extend(&ratios);
        let ratio_text = match ratio_stats(&ratios) {
            None => "no common time range".to_string(),
            Some((lo, hi, gm)) => {
                format!(
                    "{lo:.1}x to {hi:.1}x lower (geometric mean {gm:.1}x, at {} seed points)",
                    ratios.len()
                )
            }
        };
        let mut text = format!("- {key}: at equal time ours' error is {ratio_text}");
        if let Some(most) = seed.iter().max_by_key(|r| r.variant.samples) {
            let reach = vs_256.add(&ours, most.occlusion_rmse, most.ms);
            let _ = write!(
                text,
                "; the seed's error at {} samples ({:.4}, {:.0} ms): {reach}",
                most.variant.samples, most.occlusion_rmse, most.ms
            );
        }
        let _ = writeln!(o, "{text}.");
    }
    if let Some((lo, hi, gm)) = ratio_stats(&all_ratios) {
        let _ = writeln!(
            o,
            "- All scenes: at equal time ours' error is {lo:.1}x to {hi:.1}x lower (geometric mean {gm:.1}x)."
        );
    }
    if let Some(r) = vs_256.range() {
        let _ = writeln!(o, "- All scenes: ours reaches the error of the seed at its most samples {r}.");
    }
    texture_march_summary(&mut o, rows, scenes);
    let _ = writeln!(o, "\nIBL: colour RMSE (linear, hit pixels) against the converged `rays` reference:\n");
    let ibl_rows: Vec<&AccuracyRow> = rows.iter().filter(|r| r.variant.ibl != IblMethod::None).collect();
    let mut counts: Vec<u32> = ibl_rows.iter().map(|r| r.variant.samples).collect();
    counts.sort_unstable();
    counts.dedup();
    let header: Vec<String> = counts.iter().map(|n| format!("{n} samples")).collect();
    let _ = writeln!(o, "| scene | ibl | {} |", header.join(" | "));
    let _ = writeln!(o, "|---|---|{}", "---|".repeat(counts.len()));
    for (key, _, _) in scenes {
        for ibl in [IblMethod::Seed, IblMethod::Bent, IblMethod::Rays] {
            let cells: Vec<String> = counts
                .iter()
                .map(|&n| {
                    ibl_rows
                        .iter()
                        .find(|r| r.scene == *key && r.variant.ibl == ibl && r.variant.samples == n)
                        .map_or("".into(), |r| format!("{:.4} ({:.0} ms)", r.color_rmse, r.ms))
                })
                .collect();
            let name = Variant { ibl, ..Variant::ours(1) }.ibl_name();
            let _ = writeln!(o, "| {key} | {name} | {} |", cells.join(" | "));
        }
    }
    o
}

/// The primary march on the filtered texture against the storage march, ours exact at the same
/// samples: each scene's frame-time ratios and occlusion RMSE of both (nothing where no texture
/// point was measured).
fn texture_march_summary(o: &mut String, rows: &[AccuracyRow], scenes: &[(String, String, f64)]) {
    use std::fmt::Write;
    let pairs = |key: &str| -> Vec<(&AccuracyRow, &AccuracyRow)> {
        rows.iter()
            .filter(|t| t.scene == key && t.variant == Variant::texture(t.variant.samples))
            .filter_map(|t| {
                rows.iter()
                    .find(|r| r.scene == key && r.variant == Variant::ours(t.variant.samples))
                    .map(|r| (r, t))
            })
            .collect()
    };
    if scenes.iter().all(|(key, _, _)| pairs(key).is_empty()) {
        return;
    }
    let _ = writeln!(
        o,
        "\nThe primary march on the hardware-filtered texture (`ours-texture`) against the storage march\n\
         (`ours`), both exact AO at the same samples: frame time ratio texture / storage (smallest, median,\n\
         largest over the sample counts) and occlusion RMSE of each, at the fewest and the most samples:\n"
    );
    let _ = writeln!(o, "| scene | ms ratio | RMSE, fewest samples | RMSE, most samples |");
    let _ = writeln!(o, "|---|---|---|---|");
    for (key, _, _) in scenes {
        let p = pairs(key);
        let (Some(first), Some(last)) = (p.first(), p.last()) else { continue };
        let ratios: Vec<f64> = p.iter().map(|(r, t)| t.ms / r.ms).collect();
        let Some((lo, hi, _)) = ratio_stats(&ratios) else { continue };
        let rmse = |(r, t): &(&AccuracyRow, &AccuracyRow)| {
            format!("{:.4} / {:.4} ({} spp)", r.occlusion_rmse, t.occlusion_rmse, r.variant.samples)
        };
        let _ = writeln!(
            o,
            "| {key} | {lo:.2} / {:.2} / {hi:.2} | {} | {} |",
            median(ratios),
            rmse(first),
            rmse(last)
        );
    }
}

pub fn run(a: &AccuracyArgs) -> Result<()> {
    let started = Instant::now();
    let budgets: Vec<f64> = a
        .budgets
        .split(',')
        .map(|b| match b.trim().parse::<f64>() {
            Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
            _ => Err(anyhow::anyhow!("--budgets: '{b}' is not a positive number of ms")),
        })
        .collect::<Result<_>>()?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("cannot create {}", a.out.display()))?;
    if let Some(csv) = &a.from_csv {
        let text = std::fs::read_to_string(csv).with_context(|| format!("cannot read {}", csv.display()))?;
        let run = AccuracyRun::from_csv(&text).with_context(|| format!("{}", csv.display()))?;
        return accuracy_report(&run, &a.out, &budgets, None);
    }
    // Every scene's file, found before anything is measured: what is missing is said once, now.
    let mut measured: Vec<(String, Option<f64>)> = Vec::new(); // file, iso
    let mut skipped = Vec::new();
    let mut why = Vec::new();
    for scene in a.scenes.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (spec, iso) = scene_spec(scene)?;
        match scene_file(spec) {
            Ok(file) => measured.push((file, iso)),
            Err(e) => {
                skipped.push(scene.to_string());
                why.push(e);
            }
        }
    }
    if !skipped.is_empty() {
        eprintln!(
            "isowalld bench accuracy: skipping {} of {} scenes, their files are not here: {}",
            skipped.len(),
            skipped.len() + measured.len(),
            why.join("; ")
        );
    }
    if measured.is_empty() {
        anyhow::bail!("no scene to measure (skipped: {})", skipped.join(", "));
    }
    let mut gpu = GpuRenderer::new()?;
    let (w, h) = a.size;
    let repeats = a.repeats.unwrap_or(if a.quick { 1 } else { 3 }).max(1);
    let ref_frames = a.reference_frames.unwrap_or(if a.quick { 4 } else { 16 });
    if !(1..=isowall_render::gpu::MAX_FRAMES).contains(&ref_frames) {
        anyhow::bail!("--reference-frames {ref_frames} is outside 1..={}", isowall_render::gpu::MAX_FRAMES);
    }
    const REF_SAMPLES: u32 = 256;
    let sky = Environment::sky();
    let genv = gpu.upload_environment(&sky)?;
    let sweep = accuracy_sweep(a.quick);
    let adapter = gpu.adapter_name().to_string();
    println!(
        "# isowalld bench accuracy: {w}x{h}, {} points per scene, median of {repeats} frames, adapter '{adapter}'; reference: GPU, ours exact, {ref_frames} frames x {REF_SAMPLES} samples",
        sweep.len()
    );
    println!(
        "scene,method,samples,frames,step,ibl,ms,fetches_per_pixel,occlusion_rmse,occlusion_p99,color_rmse"
    );

    let mut rows: Vec<AccuracyRow> = Vec::new();
    let mut scenes: Vec<(String, String, f64)> = Vec::new(); // key, panel title, primary-only ms
    for (spec, iso) in &measured {
        let (volume, iso) = load_volume(Some(spec), None, *iso)?;
        let key = scene_key(spec);
        let gv = gpu.upload(&volume)?;
        // The volume again with its filtered texture copy, for the texture march's points; the
        // kernels are compiled for it while those points run, the default ones otherwise.
        let perf_for = |texture: bool| PerfOptions { texture, ..PerfOptions::default() };
        gpu.set_perf(perf_for(true))?;
        let gv_texture = gpu.upload(&volume)?;
        gpu.set_perf(perf_for(false))?;
        let mut texture_on = false;
        let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
        let settings_for = |v: &Variant| {
            let mut s = RenderSettings::new(iso);
            s.ao.method = v.method;
            s.ao.exact = v.exact;
            s.ao.step_voxels = v.step;
            s.ao.samples = v.samples;
            s.ao.ibl = v.ibl;
            s
        };
        let env_for = |v: &Variant| (v.ibl != IblMethod::None).then_some(&genv);

        // Converged references: ours exact, many frames, pattern indices disjoint from the sweep's.
        let ref_start = Instant::now();
        let mut rs = settings_for(&Variant::ours(REF_SAMPLES));
        rs.ao.frame = 1_000_000;
        let reference = gpu.render_accumulated(&gv, &view, &rs, None, ref_frames)?.frame;
        let rays = Variant { ibl: IblMethod::Rays, ..Variant::ours(REF_SAMPLES) };
        let mut rr = settings_for(&rays);
        rr.ao.frame = 1_000_000;
        let reference_rays = gpu.render_accumulated(&gv, &view, &rr, Some(&genv), ref_frames)?.frame;
        tracing::info!(scene = %key, s = ref_start.elapsed().as_secs_f64(), "references rendered");

        let plain = RenderSettings::new(iso);

        // Warm-up, then `repeats` passes over the whole sweep: each point's timed frames are spread
        // over the scene's run, so a burst of load from elsewhere on the machine hits one of them,
        // not all (the median drops it).
        let mut acc = vec![(Vec::new(), 0.0, 0.0, 0.0, 0.0); sweep.len()]; // times, occ, p99, colour, fetches
        let mut primary_times = Vec::new();
        for pass in 0..=repeats {
            let timed = pass > 0;
            if texture_on {
                // The first frame of freshly compiled kernels is not timed.
                gpu.set_perf(perf_for(false))?;
                texture_on = false;
                gpu.render(&gv, &view, &plain, None)?;
            }
            let r = gpu.render(&gv, &view, &plain, None)?;
            if timed {
                primary_times.push(r.gpu_time.as_secs_f64() * 1e3);
            }
            for (v, acc) in sweep.iter().zip(&mut acc) {
                let mut s = settings_for(v);
                // The warm-up has a pattern of its own; each timed pass a fresh one.
                s.ao.frame = if timed { (pass as u32 - 1) * v.frames } else { 500_000 };
                let volume = if v.texture { &gv_texture } else { &gv };
                if v.texture != texture_on {
                    gpu.set_perf(perf_for(v.texture))?;
                    texture_on = v.texture;
                    gpu.render_accumulated(volume, &view, &s, env_for(v), v.frames)?;
                }
                let out = gpu.render_accumulated(volume, &view, &s, env_for(v), v.frames)?;
                if !timed {
                    continue;
                }
                let color_ref = if v.ibl == IblMethod::None { &reference } else { &reference_rays };
                let (e, p) = error_stats(&out.frame.occlusion, &reference.occlusion, &reference.hit);
                let n = repeats as f64;
                acc.0.push(out.gpu_time.as_secs_f64() * 1e3);
                acc.1 += e / n;
                acc.2 += p / n;
                acc.3 += color_rmse(&out.frame.color, &color_ref.color, &reference.hit) / n;
                acc.4 += out.frame.fetches_per_pixel() / n;
            }
        }
        scenes.push((key.clone(), scene_title(&key, volume.dims(), iso), median(primary_times)));
        for (v, (times, occ, p99, col, fetches)) in sweep.iter().zip(acc) {
            let row = AccuracyRow {
                scene: key.clone(),
                variant: *v,
                ms: median(times),
                fetches_per_pixel: fetches,
                occlusion_rmse: occ,
                occlusion_p99: p99,
                color_rmse: col,
            };
            println!("{}", csv_row(&row));
            rows.push(row);
        }
    }

    // Does the GPU honour `exact`? (Until the exact per-cell kernel exists it marches 0.5 voxel.)
    let exact_note = {
        let fetch = |pred: &dyn Fn(&Variant) -> bool| {
            rows.iter().find(|r| pred(&r.variant) && r.variant.samples == 16).map(|r| r.fetches_per_pixel)
        };
        let exact = fetch(&|v| is_ours(v));
        let stepped = fetch(&|v| v.method == AoMethod::Ours && !v.exact && v.step == 0.5 && v.frames == 1);
        match (exact, stepped) {
            (Some(e), Some(s)) if (e - s).abs() < 1e-9 => Some(
                "the GPU kernel ignored ao.exact in this run (same fetches as the 0.5-voxel march): \
                 'ours' and the reference are the 0.5-voxel march here"
                    .to_string(),
            ),
            _ => None,
        }
    };
    let run = AccuracyRun {
        size: (w, h),
        adapter,
        repeats,
        ref_frames,
        ref_samples: REF_SAMPLES,
        scenes,
        skipped,
        note: exact_note,
        rows,
    };
    let csv_path = a.out.join("accuracy.csv");
    std::fs::write(&csv_path, run.to_csv())
        .with_context(|| format!("cannot write {}", csv_path.display()))?;
    accuracy_report(&run, &a.out, &budgets, Some(started.elapsed().as_secs_f64()))
}

/// Everything a sweep measured: enough to redraw the chart and the summary (`--from-csv`).
struct AccuracyRun {
    size: (u32, u32),
    adapter: String,
    repeats: usize,
    ref_frames: u32,
    ref_samples: u32,
    /// Short name, panel title and primary-only ms of each scene measured.
    scenes: Vec<(String, String, f64)>,
    skipped: Vec<String>,
    note: Option<String>,
    rows: Vec<AccuracyRow>,
}

const ACCURACY_COLUMNS: &str =
    "scene,method,samples,frames,step,ibl,ms,fetches_per_pixel,occlusion_rmse,occlusion_p99,color_rmse";

impl AccuracyRun {
    fn to_csv(&self) -> String {
        let (w, h) = self.size;
        let mut csv = format!(
            "# isowalld bench accuracy, {w}x{h}, adapter '{}', {} scene(s){}\n\
             # ms: median of {} frame(s) of GPU submit-to-done wall time (Rendered::gpu_time), readback excluded, no GPU \
             timestamp queries; one frame per pass over the sweep, after a warm-up pass\n\
             # frames: frames accumulated in one render (ms is for all of them); samples: AO rays per pixel per frame\n\
             # method: seed (2008), ours (exact per-cell test), ours-stepped (a march of `step` voxels), ours-texture (ours, \
             with the primary rays' march on the hardware-filtered texture_3d copy of the volume, refined exactly from the storage volume)\n\
             # step: 'exact' (ours: exact per-cell test), march step in voxels (ours-stepped), empty (seed: its fixed 0.01 of the texture)\n\
             # reference: GPU, ours exact, {} frames x {} samples accumulated (disjoint pattern); \
             IBL points' color_rmse against the same with --ibl rays and the built-in sky (exposure 0.6)\n\
             # occlusion_rmse, occlusion_p99: RMSE and 99th percentile of |A - A_ref| over hit pixels; color_rmse: linear RGB \
             after exposure, over hit pixels; each the mean over the repeats\n",
            self.adapter,
            self.scenes.len(),
            if self.skipped.is_empty() {
                String::new()
            } else {
                format!(" (skipped, not found: {})", self.skipped.join(", "))
            },
            self.repeats,
            self.ref_frames,
            self.ref_samples,
        );
        if let Some(n) = &self.note {
            csv.push_str(&format!("# note: {n}\n"));
        }
        // Machine-readable lines, for `--from-csv`.
        csv.push_str(&format!(
            "# run: size={w}x{h}; repeats={}; reference_frames={}; reference_samples={}; adapter={}\n",
            self.repeats, self.ref_frames, self.ref_samples, self.adapter
        ));
        for (key, title, primary) in &self.scenes {
            csv.push_str(&format!("# scene: {key}; {title}; primary_only_ms={primary:.3}\n"));
        }
        csv.push_str(ACCURACY_COLUMNS);
        csv.push('\n');
        for r in &self.rows {
            csv.push_str(&csv_row(r));
            csv.push('\n');
        }
        csv
    }

    /// Reads back what `to_csv` wrote.
    fn from_csv(text: &str) -> Result<AccuracyRun> {
        let mut run = AccuracyRun {
            size: (0, 0),
            adapter: String::new(),
            repeats: 0,
            ref_frames: 0,
            ref_samples: 0,
            scenes: Vec::new(),
            skipped: Vec::new(),
            note: None,
            rows: Vec::new(),
        };
        let bad = |n: usize, what: &str| anyhow::anyhow!("line {}: {what}", n + 1);
        for (n, line) in text.lines().enumerate() {
            if let Some(rest) = line.strip_prefix("# run: ") {
                for kv in rest.split("; ") {
                    let (k, v) = kv.split_once('=').ok_or_else(|| bad(n, "expected key=value"))?;
                    match k {
                        "size" => run.size = args::size(v).map_err(|e| bad(n, &e))?,
                        "repeats" => run.repeats = v.parse().map_err(|_| bad(n, "repeats"))?,
                        "reference_frames" => run.ref_frames = v.parse().map_err(|_| bad(n, "frames"))?,
                        "reference_samples" => run.ref_samples = v.parse().map_err(|_| bad(n, "samples"))?,
                        "adapter" => run.adapter = v.to_string(),
                        _ => {}
                    }
                }
            } else if let Some(rest) = line.strip_prefix("# scene: ") {
                let parts: Vec<&str> = rest.split("; ").collect();
                let [key, title, primary] = parts[..] else {
                    return Err(bad(n, "expected KEY; TITLE; primary"));
                };
                let primary =
                    primary.trim_start_matches("primary_only_ms=").parse().map_err(|_| bad(n, "ms"))?;
                run.scenes.push((key.to_string(), title.to_string(), primary));
            } else if let Some(rest) = line.strip_prefix("# note: ") {
                run.note = Some(rest.to_string());
            } else if line.starts_with('#') || line == ACCURACY_COLUMNS || line.trim().is_empty() {
                continue;
            } else {
                let f: Vec<&str> = line.split(',').collect();
                if f.len() != 11 {
                    return Err(bad(n, "expected 11 columns"));
                }
                let num = |i: usize| {
                    f[i].parse::<f64>().map_err(|_| bad(n, &format!("'{}' is not a number", f[i])))
                };
                let (method, exact, texture) = match f[1] {
                    "seed" => (AoMethod::Seed, true, false),
                    "ours" => (AoMethod::Ours, true, false),
                    "ours-texture" => (AoMethod::Ours, true, true),
                    "ours-stepped" => (AoMethod::Ours, false, false),
                    m => return Err(bad(n, &format!("unknown method '{m}'"))),
                };
                let ibl = match f[5] {
                    "none" => IblMethod::None,
                    "seed" => IblMethod::Seed,
                    "bent" => IblMethod::Bent,
                    "rays" => IblMethod::Rays,
                    i => return Err(bad(n, &format!("unknown ibl '{i}'"))),
                };
                let variant = Variant {
                    method,
                    exact,
                    step: if exact { 0.5 } else { num(4)? },
                    samples: num(2)? as u32,
                    frames: num(3)? as u32,
                    ibl,
                    texture,
                };
                run.rows.push(AccuracyRow {
                    scene: f[0].to_string(),
                    variant,
                    ms: num(6)?,
                    fetches_per_pixel: num(7)?,
                    occlusion_rmse: num(8)?,
                    occlusion_p99: num(9)?,
                    color_rmse: num(10)?,
                });
            }
        }
        if run.size.0 == 0 || run.scenes.is_empty() {
            anyhow::bail!("no '# run:' or '# scene:' line: not written by `isowalld bench accuracy`");
        }
        Ok(run)
    }
}

/// Writes chart.png, chart.svg and summary.txt for a run into `out`, and prints the summary.
fn accuracy_report(
    run: &AccuracyRun,
    out: &std::path::Path,
    budgets: &[f64],
    secs: Option<f64>,
) -> Result<()> {
    let (w, h) = run.size;
    let chart = accuracy_chart(run);
    let size = super::chart::default_size(&chart);
    super::chart::write_png(&chart, &out.join("chart.png"), size)?;
    super::chart::write_svg(&chart, &out.join("chart.svg"), size)?;
    let mut summary = format!(
        "isowalld bench accuracy: {w}x{h}, adapter '{}', median of {} frame(s), reference {} x {} samples (ours exact, GPU)\n",
        run.adapter, run.repeats, run.ref_frames, run.ref_samples
    );
    if let Some(n) = &run.note {
        summary.push_str(&format!("Note: {n}.\n"));
    }
    summary.push('\n');
    summary.push_str(&accuracy_summary(&run.rows, &run.scenes, budgets));
    if let Some(secs) = secs {
        summary.push_str(&format!("\n{} points in {secs:.0} s.\n", run.rows.len()));
    }
    let path = out.join("summary.txt");
    std::fs::write(&path, &summary).with_context(|| format!("cannot write {}", path.display()))?;
    println!("\n{summary}");
    println!("wrote {} (chart.png, chart.svg, summary.txt)", out.display());
    Ok(())
}

fn csv_row(r: &AccuracyRow) -> String {
    let v = &r.variant;
    format!(
        "{},{},{},{},{},{},{:.3},{:.1},{:.5},{:.5},{:.5}",
        r.scene,
        v.method_name(),
        v.samples,
        v.frames,
        v.step_name(),
        v.ibl_name(),
        r.ms,
        r.fetches_per_pixel,
        r.occlusion_rmse,
        r.occlusion_p99,
        r.color_rmse
    )
}

fn accuracy_chart(run: &AccuracyRun) -> Chart {
    let (rows, (w, h), adapter) = (&run.rows, run.size, &run.adapter);
    let (repeats, ref_frames, ref_samples) = (run.repeats, run.ref_frames, run.ref_samples);
    let panels = run
        .scenes
        .iter()
        .map(|(key, title, _)| {
            let mut series: Vec<Series> = Vec::new();
            for r in rows.iter().filter(|r| r.scene == *key) {
                let Some(c) = r.variant.curve() else { continue };
                let p = (r.ms, r.occlusion_rmse);
                // Sample counts beside the seed's and ours' points.
                let note = if is_seed(&r.variant) || is_ours(&r.variant) {
                    r.variant.samples.to_string()
                } else {
                    String::new()
                };
                match series.iter_mut().find(|s| s.label == c.label) {
                    Some(s) => {
                        s.points.push(p);
                        s.notes.push(note);
                    }
                    None => series.push(Series {
                        label: c.label,
                        notes: vec![note],
                        color: c.color,
                        marker: c.marker,
                        points: vec![p],
                    }),
                }
            }
            Panel { title: title.clone(), series }
        })
        .collect();
    Chart {
        title: format!("Ambient occlusion: error against frame time ({w}x{h}, {adapter})"),
        subtitle: format!(
            "Occlusion RMSE over hit pixels against a converged reference (GPU, ours exact, {ref_frames} frames x {ref_samples} samples).\n\
             Time: median of {repeats} GPU submit-to-done wall times per point. Numbers beside points: AO samples per pixel per frame."
        ),
        x_desc: "ms per frame".into(),
        y_desc: "occlusion RMSE".into(),
        panels,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loglog_interpolation_and_reach() {
        let c = [(10.0, 0.1), (40.0, 0.025), (160.0, 0.01)];
        assert!((interp_loglog(&c, 20.0).unwrap() - 0.05).abs() < 1e-12);
        assert!((interp_loglog(&c, 10.0).unwrap() - 0.1).abs() < 1e-12);
        assert_eq!(interp_loglog(&c, 5.0), None);
        assert_eq!(interp_loglog(&c, 200.0), None);
        assert!(matches!(time_to_reach(&c, 0.05), Reach::At(t) if (t - 20.0).abs() < 1e-9));
        assert_eq!(time_to_reach(&c, 0.2), Reach::AtMost(10.0));
        assert_eq!(time_to_reach(&c, 0.001), Reach::Never);
    }

    #[test]
    fn csv_round_trip_and_budgets() {
        let row = |variant: Variant, ms: f64, e: f64| AccuracyRow {
            scene: "engine".into(),
            variant,
            ms,
            fetches_per_pixel: 10.0,
            occlusion_rmse: e,
            occlusion_p99: 3.0 * e,
            color_rmse: e / 10.0,
        };
        let seed = |n| Variant { method: AoMethod::Seed, ..Variant::ours(n) };
        let run = AccuracyRun {
            size: (64, 48),
            adapter: "test adapter (1.0, 2 bits)".into(),
            repeats: 3,
            ref_frames: 16,
            ref_samples: 256,
            scenes: vec![("engine".into(), "engine-like 256x256x118, iso 0".into(), 5.0)],
            skipped: vec![],
            note: Some("a note".into()),
            rows: vec![
                row(seed(4), 10.0, 0.2),
                row(seed(64), 50.0, 0.19),
                row(Variant::ours(4), 10.0, 0.1),
                row(Variant::ours(16), 20.0, 0.05),
                row(Variant::ours(64), 40.0, 0.025),
                row(Variant { exact: false, step: 0.25, ..Variant::ours(16) }, 30.0, 0.04),
                row(Variant { ibl: IblMethod::Bent, ..Variant::ours(16) }, 22.0, 0.05),
                row(Variant::texture(4), 9.0, 0.1),
                row(Variant::texture(16), 20.0, 0.05),
                row(Variant::texture(64), 44.0, 0.026),
            ],
        };
        let back = AccuracyRun::from_csv(&run.to_csv()).unwrap();
        assert_eq!((back.size, back.repeats, back.ref_frames), ((64, 48), 3, 16));
        assert_eq!(back.adapter, run.adapter);
        assert_eq!(back.scenes, run.scenes);
        assert_eq!(back.note.as_deref(), Some("a note"));
        assert_eq!(back.rows.len(), run.rows.len());
        for (a, b) in back.rows.iter().zip(&run.rows) {
            assert_eq!(
                a.variant,
                Variant { step: if b.variant.exact { 0.5 } else { b.variant.step }, ..b.variant }
            );
            assert!((a.ms - b.ms).abs() < 1e-3 && (a.occlusion_rmse - b.occlusion_rmse).abs() < 1e-5);
        }
        // Budgets: interpolated along each method's curve; n/a outside the times measured.
        let at = |pred: fn(&Variant) -> bool, b| error_at_budget(&run.rows, "engine", pred, b);
        assert!((at(is_ours, 20.0).unwrap() - 0.05).abs() < 1e-12);
        assert!((at(is_ours, 40.0).unwrap() - 0.025).abs() < 1e-12);
        assert!(at(is_ours, 5.0).unwrap_err().contains("fastest 10 ms"));
        assert!(at(is_ours, 100.0).unwrap_err().contains("slowest 40 ms"));
        assert!((at(is_seed, 50.0).unwrap() - 0.19).abs() < 1e-12);
        let summary = accuracy_summary(&run.rows, &run.scenes, &[10.0, 30.0]);
        assert!(summary.contains("| engine | ours | 0.1000 |"), "{summary}");
        // The texture march's points are neither ours' nor on ours' curve; the summary pairs them
        // with ours at the same samples (ratios 0.9, 1.0 and 1.1).
        assert_eq!(back.rows.iter().filter(|r| r.variant.texture).count(), 3);
        assert!(
            summary.contains(
                "| engine | 0.90 / 1.00 / 1.10 | 0.1000 / 0.1000 (4 spp) | 0.0250 / 0.0260 (64 spp) |"
            ),
            "{summary}"
        );
        assert!(AccuracyRun::from_csv("scene,method\n").is_err());
    }

    #[test]
    fn sweep_is_not_the_product_and_names_are_stable() {
        let full = accuracy_sweep(false);
        assert_eq!(full.iter().filter(|v| is_seed(v)).count(), 7);
        assert_eq!(full.iter().filter(|v| is_ours(v)).count(), 9);
        assert!(full.iter().all(|v| v.samples * v.frames <= 512));
        assert_eq!(full.iter().filter(|v| !v.exact).count(), 8);
        assert_eq!(full.iter().filter(|v| v.ibl != IblMethod::None).count(), 6);
        assert_eq!(full.iter().filter(|v| v.texture).count(), 7);
        assert!(full.iter().skip_while(|v| !v.texture).all(|v| v.texture), "texture points last");
        assert_eq!(Variant::texture(16).method_name(), "ours-texture");
        assert!(!is_ours(&Variant::texture(16)));
        assert!(accuracy_sweep(true).len() < full.len() / 2);
        let stepped = Variant { exact: false, step: 0.25, ..Variant::ours(16) };
        assert_eq!((stepped.method_name(), stepped.step_name().as_str()), ("ours-stepped", "0.25"));
        assert_eq!(scene_key("../shared/data/ct-cranium.nrrd"), "ct-cranium");
        assert_eq!(scene_key("procedural:engine:128"), "engine");
    }
}
