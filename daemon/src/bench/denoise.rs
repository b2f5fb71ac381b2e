//! `isowalld bench denoise`: the edge-aware filter's speed against its accuracy, judged by the
//! independent estimate of DESIGN.md "AO" (`isowall-truth`), not by a converged render of ours.
//!
//! Per scene: a camera (for a scan that `--known` has, the known answers' camera at `--size`;
//! otherwise the framing `bench suite` uses), the default AO settings (radius 8 voxels of the
//! largest spacing, Sobol directions), and `--pixels` hit pixels chosen by a seeded hash of their
//! index among the primary hits. The estimate at those pixels' pixel-centre rays (its own camera
//! ray, field, march and `--truth-directions`^2 stratified directions) is the reference. Then, for
//! each sample count, one frame of that many samples (as `bench suite`'s samples axis renders it),
//! raw and denoised, `--repeats` times with different frame indices: the occlusion RMSE, p99 of
//! |error| and bias over every (pixel, repeat) where the GPU's hit is the estimate's (depths within
//! 0.05 voxel), and the median frame time (submit to done; the filter included) and process CPU
//! time (on a CPU driver the frame's cost whatever else runs). The goal check
//! compares denoised 4 spp with raw 32 spp.

use super::chart::{Chart, Marker, Panel, Series};
use super::stats::{median, process_cpu_ms, sample_list, scene_spec};
use crate::args;
use crate::render::load_volume;
use anyhow::{bail, Context, Result};
use clap::Args;
use glam::DVec3;
use isowall_model::cli_args;
use isowall_model::{Camera, Denoise, RenderSettings, View};
use isowall_render::denoise::{filter_with, Input, Stops};
use isowall_render::gpu::GpuRenderer;
use isowall_render::sampling::hash;
use isowall_truth::{parallel_map, Field, KnownAnswers, KnownCamera, KnownCase, Truth};
use isowall_volume::Volume;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The CSV header of `denoise.csv`.
pub const HEADER: &str =
    "scene,spp,denoise,ms_per_frame,occlusion_rmse,occlusion_p99,occlusion_bias,pixels,cpu_ms_per_frame";

#[derive(Args)]
pub struct DenoiseArgs {
    /// Scenes as VOLUME[@ISO], comma-separated (VOLUME as for `render --volume`)
    #[arg(
        long,
        default_value = "../shared/data/ct-cranium.nrrd@300,../shared/data/mri-brainsmall.nrrd@40,procedural:engine"
    )]
    pub scenes: String,
    /// Image size
    #[arg(long, default_value = "512x512", value_parser = args::size)]
    pub size: (u32, u32),
    /// Hit pixels compared per scene (chosen by a hash of their index and --seed)
    #[arg(long, value_parser = args::truth_pixels, default_value_t = 300)]
    pub pixels: usize,
    /// Seed of the pixels' choice
    #[arg(long, default_value_t = 1)]
    pub seed: u32,
    /// AO samples per pixel of the one frame measured, comma-separated
    #[arg(long, default_value = "1,2,4,8,16,32")]
    pub samples: String,
    /// Frames per configuration, each with its own frame index: the time is their median, the
    /// errors pool their pixels
    #[arg(long, value_parser = cli_args::repeats, default_value_t = 3)]
    pub repeats: usize,
    /// Directions of the estimate per pixel: M x M jittered strata (its standard error per pixel is
    /// at most sqrt(A (1 - A)) / M, printed per scene)
    #[arg(long, value_parser = args::truth_directions, default_value_t = 48)]
    pub truth_directions: u32,
    /// The outside answers of the scans: their cameras are used for the scans they name, and the
    /// estimate is compared with them at their 128x128 pixels (a sanity line); skipped if absent
    #[arg(long, default_value = "../shared/conventions/ao-known-answers.json")]
    pub known: PathBuf,
    /// Write denoise.csv and chart.svg (RMSE and p99 against frame ms, raw and denoised) here
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Also filter every raw frame on the CPU (the filter's twin) with these edge stops, each
    /// SIGMA_PLANE:SIGMA_OCCLUSION:NORMAL_SQUARINGS, comma-separated (the renderer's are
    /// 1:2:5): a row each (denoise `cpu SP:SO:NS`, no time), the same frames' error under other
    /// stops, for tuning them against the estimate
    #[arg(long, value_name = "LIST", value_parser = stops_list)]
    pub stops: Option<StopsList>,
}

/// `--stops`: edge stops to try on the CPU.
#[derive(Clone, Debug, PartialEq)]
pub struct StopsList(pub Vec<Stops>);

/// `SP:SO:NS,...` as edge stops.
fn stops_list(s: &str) -> Result<StopsList, String> {
    s.split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| {
            let parts: Vec<&str> = t.split(':').collect();
            let bad = || format!("`{t}`: want SIGMA_PLANE:SIGMA_OCCLUSION:NORMAL_SQUARINGS, e.g. 1:2:5");
            let [sp, so, ns] = parts[..] else { return Err(bad()) };
            let sigma_plane: f32 = sp.parse().map_err(|_| bad())?;
            let sigma_occlusion: f32 = so.parse().map_err(|_| bad())?;
            let normal_squarings: u32 = ns.parse().map_err(|_| bad())?;
            if !(sigma_plane > 0.0
                && sigma_occlusion > 0.0
                && sigma_plane.is_finite()
                && sigma_occlusion.is_finite())
                || normal_squarings > 16
            {
                return Err(format!(
                    "`{t}`: the sigmas must be positive and finite, the squarings at most 16"
                ));
            }
            Ok(Stops { sigma_plane, sigma_occlusion, normal_squarings })
        })
        .collect::<Result<Vec<_>, _>>()
        .and_then(|v| if v.is_empty() { Err("no stops given".to_string()) } else { Ok(StopsList(v)) })
}

/// One measured configuration of one scene.
#[derive(Clone, Debug)]
struct Row {
    scene: String,
    spp: u32,
    denoise: bool,
    /// The CPU twin's stops that filtered the raw frames (`--stops`); `None`: the GPU's frame,
    /// raw or denoised as `denoise` says.
    stops: Option<Stops>,
    ms: f64,
    /// Median process CPU per frame (`stats::process_cpu_ms`): on a CPU driver the frame's cost
    /// whatever else the machine runs; NaN where it cannot be read.
    cpu_ms: f64,
    rmse: f64,
    p99: f64,
    bias: f64,
    pixels: usize,
}

impl Row {
    fn csv(&self) -> String {
        format!(
            "{},{},{},{:.2},{:.5},{:.5},{:+.5},{},{:.0}",
            self.scene,
            self.spp,
            match (self.stops, self.denoise) {
                (Some(st), _) =>
                    format!("cpu {}:{}:{}", st.sigma_plane, st.sigma_occlusion, st.normal_squarings),
                (None, true) => "on".into(),
                (None, false) => "off".into(),
            },
            self.ms,
            self.rmse,
            self.p99,
            self.bias,
            self.pixels,
            self.cpu_ms
        )
    }
}

/// The camera of a known-answers case.
fn known_camera(c: &KnownCamera) -> Camera {
    let v = DVec3::from_array;
    Camera { eye: v(c.eye), target: v(c.target), up: v(c.up), fov_y_deg: c.fov_y_deg }
}

/// The estimate at `pixels` of `camera` at `size`, marched up to `t_max`, printing progress.
fn estimate(
    field: &Field,
    camera: &Camera,
    size: (u32, u32),
    pixels: &[(u32, u32)],
    m: u32,
    t_max: f64,
    what: &str,
) -> Vec<Option<Truth>> {
    let start = Instant::now();
    let mut out = Vec::with_capacity(pixels.len());
    let chunk = pixels.len().div_ceil(10).max(1);
    for part in pixels.chunks(chunk) {
        out.extend(parallel_map(part, |&(px, py)| {
            let d = isowall_truth::pixel_ray(
                (camera.eye, camera.target, camera.up),
                camera.fov_y_deg,
                size,
                px,
                py,
            );
            field.estimate(camera.eye, d, (px, py), m, t_max)
        }));
        eprint!(
            "\r# {what}: estimate {}/{} pixels, {:.0} s",
            out.len(),
            pixels.len(),
            start.elapsed().as_secs_f64()
        );
    }
    eprintln!();
    out
}

/// `n` hit pixels of `hit` (a `width`-wide image), chosen by a hash of their index and `seed`.
fn choose_pixels(hit: &[bool], width: u32, n: usize, seed: u32) -> Vec<(u32, u32)> {
    let mut idx: Vec<(u32, usize)> =
        (0..hit.len()).filter(|&i| hit[i]).map(|i| (hash(i as u32 ^ hash(seed)), i)).collect();
    idx.sort_unstable();
    idx.truncate(n);
    idx.sort_unstable_by_key(|&(_, i)| i);
    idx.into_iter().map(|(_, i)| (i as u32 % width, i as u32 / width)).collect()
}

/// RMSE, p99 of |error| and mean of `got - want`.
fn error_of(d: &[f64]) -> (f64, f64, f64) {
    if d.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    let n = d.len() as f64;
    let rmse = (d.iter().map(|x| x * x).sum::<f64>() / n).sqrt();
    let mut a: Vec<f64> = d.iter().map(|x| x.abs()).collect();
    a.sort_by(f64::total_cmp);
    (rmse, a[(a.len() - 1) * 99 / 100], d.iter().sum::<f64>() / n)
}

pub fn run(a: &DenoiseArgs) -> Result<()> {
    let samples = sample_list(&a.samples)?;
    if a.pixels == 0 || a.truth_directions == 0 {
        bail!("--pixels and --truth-directions must be at least 1");
    }
    let known = match KnownAnswers::read(&a.known) {
        Ok(k) => k.cases,
        Err(e) => {
            println!("# no known answers ({e}): every scene is framed as bench suite frames it");
            Vec::new()
        }
    };
    let gpu = GpuRenderer::new()?;
    let (w, h) = a.size;
    let m = a.truth_directions;
    let header = format!(
        "# isowalld bench denoise: {w}x{h}, {} pixels per scene (seed {}), median of {} frames, adapter '{}'; \
         reference: the independent estimate (isowall-truth), {m}x{m} directions per pixel",
        a.pixels,
        a.seed,
        a.repeats.max(1),
        gpu.adapter_name()
    );
    println!("{header}");
    let mut rows: Vec<Row> = Vec::new();
    let mut goals = Vec::new();
    for scene in a.scenes.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (spec, iso) = scene_spec(scene)?;
        let (volume, iso) = load_volume(Some(spec), None, iso)?;
        let file = Path::new(spec).file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
        let case = known.iter().find(|c| c.file_name() == file);
        let camera = match case {
            Some(c) => known_camera(&c.camera),
            None => Camera::framing(volume.box_min(), volume.box_max(), w, h),
        };
        let view = View::whole(camera, w, h);
        let name = volume.name.clone();
        let base = RenderSettings::new(iso);
        let radius = base.ao.radius_world(volume.spacing()).unwrap_or(f64::INFINITY);
        println!(
            "# {name}: iso {iso}, AO radius {radius} (8 voxels of the largest spacing), camera {}",
            if case.is_some() { "of the known answers" } else { "framing the box (as bench suite)" }
        );
        let gv = gpu.upload(&volume)?;
        let primary = gpu.render(&gv, &view, &base, None)?.frame;
        let pixels = choose_pixels(&primary.hit, w, a.pixels, a.seed);
        let field = field_of(&volume, iso);
        let truth = estimate(&field, &camera, (w, h), &pixels, m, radius, &name);
        // Where the GPU's hit is the estimate's.
        let voxel = volume.spacing().min_element();
        let mut kept: Vec<(usize, f64)> = Vec::new();
        for (&(px, py), t) in pixels.iter().zip(&truth) {
            let i = (px + py * w) as usize;
            if let Some(t) = t {
                if (t.depth - primary.depth[i] as f64).abs() < 0.05 * voxel {
                    kept.push((i, t.occlusion(Some(radius))));
                }
            }
        }
        let std_err = (kept.iter().map(|(_, a)| a * (1.0 - a)).sum::<f64>() / kept.len().max(1) as f64)
            .sqrt()
            / m as f64;
        let mean_a = kept.iter().map(|(_, a)| a).sum::<f64>() / kept.len().max(1) as f64;
        println!(
            "# {name}: {} of {} pixels compared (the rest: the GPU's hit is not the estimate's); mean A {mean_a:.4}; \
             the estimate's standard error <= {std_err:.4} (RMS over the pixels, binomial bound)",
            kept.len(),
            pixels.len()
        );
        if kept.is_empty() {
            bail!("{name}: no pixel where the GPU's hit is the estimate's");
        }
        if let Some(c) = case {
            known_sanity(&field, c, m.min(32), &name);
        }
        println!("{HEADER}");
        for &n in &samples {
            for den in [false, true] {
                let mut s = base;
                s.ao.samples = n;
                s.denoise = if den { Denoise::On } else { Denoise::Off };
                gpu.render(&gv, &view, &s, None)?; // warm-up
                let (mut times, mut cpu, mut d) = (Vec::new(), Vec::new(), Vec::new());
                let mut raw_frames = Vec::new();
                for r in 0..a.repeats.max(1) {
                    s.ao.frame = r as u32;
                    let cpu0 = process_cpu_ms();
                    let out = gpu.render(&gv, &view, &s, None)?;
                    cpu.push(match (cpu0, process_cpu_ms()) {
                        (Some(c0), Some(c1)) => c1 - c0,
                        _ => f64::NAN,
                    });
                    times.push(out.gpu_time.as_secs_f64() * 1e3);
                    d.extend(kept.iter().map(|&(i, want)| out.frame.occlusion[i] as f64 - want));
                    if !den && a.stops.is_some() {
                        raw_frames.push(out.frame);
                    }
                }
                let (rmse, p99, bias) = error_of(&d);
                let row = Row {
                    scene: name.clone(),
                    spp: n,
                    denoise: den,
                    stops: None,
                    ms: median(times),
                    cpu_ms: median(cpu),
                    rmse,
                    p99,
                    bias,
                    pixels: kept.len(),
                };
                println!("{}", row.csv());
                rows.push(row.clone());
                for stops in a.stops.iter().flat_map(|l| &l.0).filter(|_| !den) {
                    let mut d = Vec::new();
                    for f in &raw_frames {
                        let input = Input {
                            view: &view,
                            hit: &f.hit,
                            depth: &f.depth,
                            normal: &f.normal,
                            occlusion: &f.occlusion,
                            ibl: &f.ibl,
                            samples: u64::from(n),
                            pixel_samples: None,
                        };
                        let (occlusion, _) = filter_with(&input, stops);
                        d.extend(kept.iter().map(|&(i, want)| occlusion[i] as f64 - want));
                    }
                    let (rmse, p99, bias) = error_of(&d);
                    // The raw row's frames, filtered on the CPU: no time.
                    let filtered = Row {
                        denoise: true,
                        stops: Some(*stops),
                        ms: f64::NAN,
                        cpu_ms: f64::NAN,
                        rmse,
                        p99,
                        bias,
                        ..row.clone()
                    };
                    println!("{}", filtered.csv());
                    rows.push(filtered);
                }
            }
        }
        let find = |spp: u32, den: bool| {
            rows.iter().find(|r| r.scene == name && r.spp == spp && r.denoise == den && r.stops.is_none())
        };
        if let (Some(d4), Some(r32)) = (find(4, true), find(32, false)) {
            goals.push(goal_line(&name, d4, r32));
            for c in rows.iter().filter(|r| r.scene == name && r.spp == 4 && r.stops.is_some()) {
                goals.push(goal_line(&name, c, r32));
            }
        }
    }
    if !goals.is_empty() {
        println!("# goal: denoised 4 spp reaches raw 32 spp's RMSE in <= 1/3 of its time, p99 <= 1.5x raw 32 spp's");
        for g in &goals {
            println!("{g}");
        }
    }
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        super::stats::save_csv(&dir.join("denoise.csv"), &header, HEADER, rows.iter().map(Row::csv))?;
        let chart = chart(&rows, &header);
        let path = dir.join("chart.svg");
        super::chart::write_svg(&chart, &path, super::chart::default_size(&chart))?;
        println!("# saved {}", path.display());
    }
    Ok(())
}

fn field_of(volume: &Volume, iso: f64) -> Field {
    Field::new(volume.dims(), volume.spacing(), volume.origin(), volume.data(), iso)
}

fn goal_line(name: &str, d4: &Row, r32: &Row) -> String {
    let time = d4.ms / r32.ms;
    let p99 = d4.p99 / r32.p99;
    let cpu = d4.cpu_ms / r32.cpu_ms;
    let met = d4.rmse <= r32.rmse && time <= 1.0 / 3.0 && p99 <= 1.5;
    let what = match d4.stops {
        Some(st) => format!(
            "4 spp filtered on the CPU with stops {}:{}:{} (no time)",
            st.sigma_plane, st.sigma_occlusion, st.normal_squarings
        ),
        None => "denoised 4 spp".into(),
    };
    format!(
        "{name}: {what} RMSE {:.4} vs raw 32 spp {:.4} (ratio {:.2}), time ratio {time:.3} (process CPU {cpu:.3}), p99 {:.4} vs {:.4} (ratio {p99:.2}): {}",
        d4.rmse,
        r32.rmse,
        d4.rmse / r32.rmse,
        d4.p99,
        r32.p99,
        if met { "met" } else { "not met" }
    )
}

/// The estimate against the known answers at their own camera and pixels, radius 8 (where the
/// estimate's hit is the known one, within 0.01).
fn known_sanity(field: &Field, c: &KnownCase, m: u32, name: &str) {
    let size = (c.camera.width, c.camera.height);
    let pixels: Vec<(u32, u32)> = c.pixels.iter().map(|p| (p.px, p.py)).collect();
    let truth =
        estimate(field, &known_camera(&c.camera), size, &pixels, m, 8.0, &format!("{name} known answers"));
    let d: Vec<f64> = truth
        .iter()
        .zip(&c.pixels)
        .filter_map(|(t, p)| {
            let t = t.as_ref()?;
            ((t.position - DVec3::from_array(p.pos)).length() < 0.01).then(|| t.occlusion(Some(8.0)) - p.a_r8)
        })
        .collect();
    let (rmse, _, bias) = error_of(&d);
    println!(
        "# {name}: sanity, the estimate ({m}x{m} directions) vs the known answers at radius 8 ({}x{}, {} of {} pixels with the same hit): RMSE {rmse:.4}, bias {bias:+.4}",
        size.0,
        size.1,
        d.len(),
        c.pixels.len()
    );
}

/// RMSE and p99 against frame ms, a panel per scene and measure, raw and denoised lines.
fn chart(rows: &[Row], header: &str) -> Chart {
    let mut scenes: Vec<&str> = Vec::new();
    for r in rows {
        if !scenes.contains(&r.scene.as_str()) {
            scenes.push(&r.scene);
        }
    }
    let mut panels = Vec::new();
    for (measure, pick) in [("RMSE", (|r: &Row| r.rmse) as fn(&Row) -> f64), ("p99 |error|", |r: &Row| r.p99)]
    {
        for scene in &scenes {
            let series = [
                (false, "raw", (40, 90, 200), Marker::Circle),
                (true, "denoised", (210, 50, 40), Marker::Triangle),
            ]
            .into_iter()
            .map(|(den, label, color, marker)| {
                let mine: Vec<&Row> = rows
                    .iter()
                    .filter(|r| r.scene == *scene && r.denoise == den && r.stops.is_none())
                    .collect();
                Series {
                    label: label.into(),
                    notes: mine.iter().map(|r| r.spp.to_string()).collect(),
                    color,
                    marker,
                    points: mine.iter().map(|r| (r.ms, pick(r))).collect(),
                }
            })
            .collect();
            panels.push(Panel { title: format!("{scene}: occlusion {measure}"), series });
        }
    }
    Chart {
        title: "Denoised and raw AO against the independent estimate".into(),
        subtitle: format!(
            "{}\none frame of 1..32 samples per pixel (the number beside each point)",
            header.trim_start_matches("# ")
        ),
        x_desc: "ms per frame".into(),
        y_desc: "occlusion error".into(),
        panels,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_are_hits_distinct_and_reproducible() {
        let hit: Vec<bool> = (0..64 * 64).map(|i| i % 3 != 0).collect();
        let p = choose_pixels(&hit, 64, 100, 7);
        assert_eq!(p.len(), 100);
        assert!(p.iter().all(|&(x, y)| hit[(x + 64 * y) as usize]));
        let mut q = p.clone();
        q.dedup();
        assert_eq!(q.len(), 100);
        assert_eq!(choose_pixels(&hit, 64, 100, 7), p);
        assert_ne!(choose_pixels(&hit, 64, 100, 8), p);
        assert_eq!(choose_pixels(&hit, 64, 100_000, 7).len(), hit.iter().filter(|&&h| h).count());
    }

    #[test]
    fn stops_lists_parse_and_bad_ones_are_named() {
        let s = stops_list("1:2:5, 0.5:4:3").unwrap().0;
        assert_eq!(
            s,
            vec![
                Stops { sigma_plane: 1.0, sigma_occlusion: 2.0, normal_squarings: 5 },
                Stops { sigma_plane: 0.5, sigma_occlusion: 4.0, normal_squarings: 3 },
            ]
        );
        for bad in ["1:2", "1:x:5", "0:2:5", "1:2:40", ""] {
            let e = stops_list(bad).unwrap_err();
            assert!(e.contains(bad) || e == "no stops given", "{bad}: {e}");
        }
    }

    #[test]
    fn errors_of_a_hand_made_set() {
        let (rmse, p99, bias) = error_of(&[0.1, -0.1, 0.1, -0.1]);
        assert!((rmse - 0.1).abs() < 1e-12 && (p99 - 0.1).abs() < 1e-12 && bias.abs() < 1e-12);
        let d: Vec<f64> = (0..100).map(|i| i as f64 / 100.0).collect();
        assert!((error_of(&d).1 - 0.98).abs() < 1e-12);
        assert!(error_of(&[]).0.is_nan());
    }
}
