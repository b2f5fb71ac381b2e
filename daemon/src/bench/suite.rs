//! `isowalld bench suite`: a fixed set of scenes, sizes and AO sample counts, each with ms per frame,
//! trilinear fetches per pixel and its error; `--save FILE` writes the rows as CSV, `--baseline
//! FILE` compares them with a CSV an earlier build saved, as ratios (new / baseline) rather than
//! absolute times, so the comparison survives a different machine load as far as a ratio can.
//!
//! Error of a row (against a converged reference rendered in the same run: ours, exact, f32 voxels,
//! `--reference-frames` x 256 samples accumulated): the occlusion RMSE over the reference's hit
//! pixels, the share of pixels whose hit differs from the reference's, and the median normal error
//! in degrees over pixels both hit.

use super::stats::{
    baseline_row, csv_records, error_stats, is_plain, median, print_baseline_heading, process_cpu_ms,
    sample_list, save_csv, scene_spec,
};
use crate::args;
use crate::render::load_volume;
use anyhow::{Context, Result};
use clap::Args;
use isowall_model::cli_args;
use isowall_model::{AoSequence, Camera, Denoise, RenderSettings, View};
use isowall_render::gpu::{GpuRenderer, GpuVolume, PerfOptions};
use isowall_render::Frame;
use isowall_volume::VoxelFormat;
use std::path::PathBuf;

/// The CSV header of `--save` and `--baseline` files (comment lines start with '#').
pub const HEADER: &str =
    "scene,size,samples,variant,ms_per_frame,fetches_per_pixel,occlusion_rmse,hit_mismatch_percent,normal_error_deg";

#[derive(Args)]
pub struct SuiteArgs {
    /// Scenes as VOLUME[@ISO], comma-separated (VOLUME as for `render --volume`)
    #[arg(long, default_value = "procedural:engine,../shared/data/ct-cranium.nrrd@300")]
    pub scenes: String,
    /// Image sizes, comma-separated
    #[arg(long, default_value = "512x512")]
    pub sizes: String,
    /// AO samples per pixel per frame, comma-separated
    #[arg(long, default_value = "32,256")]
    pub samples: String,
    /// Timed frames per row (the median is reported; one untimed warm-up before)
    #[arg(long, value_parser = cli_args::repeats, default_value_t = 3)]
    pub repeats: usize,
    /// Frames of 256 samples accumulated for the converged reference of each scene and size
    #[arg(long, value_parser = args::accumulated_frames, default_value_t = 4)]
    pub reference_frames: u32,
    /// Compare with the rows of this CSV (an earlier `--save`): ratios new / baseline
    #[arg(long, value_name = "FILE")]
    pub baseline: Option<PathBuf>,
    /// Write the rows to this CSV (e.g. docs/bench/baseline-lavapipe.csv)
    #[arg(long, value_name = "FILE")]
    pub save: Option<PathBuf>,
    /// Renderer variants measured per row, comma-separated: `default`, `plain` (the options of the
    /// build before the performance work; also called `before`), or changes joined by '+': block=N,
    /// ao=N, coarse=N, exit=on|off, wg=XxY, format=r32f|r16f|r16|r8, texture (the primary march
    /// on a hardware-filtered 3D texture), and the AO settings eps=V
    /// (origin off the surface, voxels; 0.5 the old one), seq=r2|sobol (e.g. `ao=2+coarse=16`,
    /// `eps=0.5+seq=r2`), and denoise=on|off (the spatial filter of occlusion and IBL, e.g.
    /// `default,denoise=on`)
    #[arg(long, default_value = "default")]
    pub variants: String,
}

/// One measured row.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub scene: String,
    pub size: String,
    pub samples: u32,
    pub variant: String,
    pub ms: f64,
    pub fetches_per_pixel: f64,
    pub occlusion_rmse: f64,
    pub hit_mismatch_percent: f64,
    pub normal_error_deg: f64,
}

impl Row {
    fn key(&self) -> (String, String, u32, String) {
        (self.scene.clone(), self.size.clone(), self.samples, self.variant.clone())
    }

    fn csv(&self) -> String {
        format!(
            "{},{},{},{},{:.2},{:.2},{:.5},{:.3},{:.4}",
            self.scene,
            self.size,
            self.samples,
            self.variant,
            self.ms,
            self.fetches_per_pixel,
            self.occlusion_rmse,
            self.hit_mismatch_percent,
            self.normal_error_deg
        )
    }
}

/// Parses rows written by [`Row::csv`] under [`HEADER`]; errors name the file and line.
pub fn parse_rows(text: &str, file: &str) -> Result<Vec<Row>> {
    let mut rows = Vec::new();
    for (i, f) in csv_records(text, file, HEADER, 9)? {
        let num = |k: usize, name: &str| -> Result<f64> {
            f[k].parse::<f64>().map_err(|_| anyhow::anyhow!("{file}:{i}: {name} '{}' is not a number", f[k]))
        };
        rows.push(Row {
            scene: f[0].to_string(),
            size: f[1].to_string(),
            samples: f[2]
                .parse()
                .map_err(|_| anyhow::anyhow!("{file}:{i}: samples '{}' is not a whole number", f[2]))?,
            variant: f[3].to_string(),
            ms: num(4, "ms_per_frame")?,
            fetches_per_pixel: num(5, "fetches_per_pixel")?,
            occlusion_rmse: num(6, "occlusion_rmse")?,
            hit_mismatch_percent: num(7, "hit_mismatch_percent")?,
            normal_error_deg: num(8, "normal_error_deg")?,
        });
    }
    Ok(rows)
}

/// One line of the comparison: a row against the baseline row with the same scene, size, samples
/// and variant (`None` where the baseline has none; a variant not in the baseline is compared with
/// the baseline's `default` row of the same scene, size and samples).
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    pub row: Row,
    pub base_variant: Option<String>,
    pub ms_ratio: f64,
    pub fetch_ratio: f64,
    pub rmse_ratio: f64,
}

pub fn compare(rows: &[Row], baseline: &[Row]) -> Vec<Comparison> {
    let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { f64::NAN };
    rows.iter()
        .map(|r| {
            let default = (r.scene.clone(), r.size.clone(), r.samples, "default".to_string());
            let b = baseline_row(baseline, Row::key, &r.key(), &default);
            match b {
                Some(b) => Comparison {
                    row: r.clone(),
                    base_variant: Some(b.variant.clone()),
                    ms_ratio: ratio(r.ms, b.ms),
                    fetch_ratio: ratio(r.fetches_per_pixel, b.fetches_per_pixel),
                    rmse_ratio: ratio(r.occlusion_rmse, b.occlusion_rmse),
                },
                None => Comparison {
                    row: r.clone(),
                    base_variant: None,
                    ms_ratio: f64::NAN,
                    fetch_ratio: f64::NAN,
                    rmse_ratio: f64::NAN,
                },
            }
        })
        .collect()
}

/// Hit mismatch (percent of pixels) and median normal error (degrees, over pixels both hit).
fn primary_error(f: &Frame, reference: &Frame) -> (f64, f64) {
    let n = f.pixel_count();
    let mismatch = (0..n).filter(|&i| f.hit[i] != reference.hit[i]).count();
    let angles: Vec<f64> = (0..n)
        .filter(|&i| f.hit[i] && reference.hit[i])
        .map(|i| {
            let a = glam::DVec3::from_array(f.normal[i].map(f64::from));
            let b = glam::DVec3::from_array(reference.normal[i].map(f64::from));
            a.dot(b).clamp(-1.0, 1.0).acos().to_degrees()
        })
        .collect();
    let angle = if angles.is_empty() { 0.0 } else { median(angles) };
    (mismatch as f64 * 100.0 / n.max(1) as f64, angle)
}

/// The renderer's performance options a variant name stands for: `default` (this build's), `plain`
/// (or `before`: the build before the performance work), or changes of the default joined by '+':
/// `block=N` (cells per block edge, primary rays), `ao=N` (AO rays' block, 0: the primary one),
/// `coarse=N` (AO rays' coarse block, 0 none), `exit=on|off` (the block min early exit of AO rays),
/// `wg=XxY` (workgroup shape), `format=r32f|r16f|r16|r8` (the voxels stored packed in that format
/// on the GPU and read by kernels compiled for it: its speed and its error), `texture` (the primary
/// march samples a hardware-filtered `texture_3d` copy of the volume, refinement exact from the
/// storage volume); e.g. `ao=2+coarse=16`, `texture+format=r16f`.
pub fn variant_options(name: &str) -> Result<PerfOptions> {
    let bad = |what: &str| anyhow::anyhow!("variant '{name}': {what}");
    let mut o = PerfOptions::default();
    for part in name.split('+') {
        match part.split_once('=') {
            None if part == "default" => {}
            None if is_plain(part) => o = PerfOptions::PLAIN,
            None if part == "texture" => o.texture = true,
            Some(("block", v)) => o.block = v.parse().map_err(|_| bad("block is not a whole number"))?,
            Some(("ao", v)) => o.ao_block = v.parse().map_err(|_| bad("ao is not a whole number"))?,
            Some(("coarse", v)) => o.coarse = v.parse().map_err(|_| bad("coarse is not a whole number"))?,
            Some(("exit", "on")) => o.block_min_exit = true,
            Some(("exit", "off")) => o.block_min_exit = false,
            Some(("format", v)) => o.format = v.parse::<VoxelFormat>().map_err(|e| bad(&e))?,
            Some(("wg", v)) => {
                o.workgroup = args::size(v).map_err(|e| bad(&format!("wg: {e}")))?;
            }
            _ => {
                return Err(bad(&format!(
                    "unknown part '{part}' (default, plain, texture, block=N, ao=N, coarse=N, exit=on|off, wg=XxY, format=r32f|r16f|r16|r8)"
                )))
            }
        }
    }
    o.validate().map_err(|e| bad(&e))?;
    Ok(o)
}

/// The AO settings a variant changes besides the performance options: `eps=V` (the AO rays' start
/// off the surface in voxels; `eps=0.5` is the old origin, half a voxel out) and `seq=r2|sobol`
/// (the 2D set of the directions). Returns them and the variant name without them (for
/// [`variant_options`]; `default` where nothing is left).
pub fn variant_ao(name: &str) -> Result<(String, Option<f64>, Option<AoSequence>)> {
    let bad = |what: &str| anyhow::anyhow!("variant '{name}': {what}");
    let (mut rest, mut eps, mut seq) = (Vec::new(), None, None);
    for part in name.split('+') {
        match part.split_once('=') {
            Some(("eps", v)) => match v.parse::<f64>() {
                Ok(e) if e.is_finite() && e >= 0.0 => eps = Some(e),
                _ => return Err(bad("eps is not a number >= 0")),
            },
            Some(("seq", "r2")) => seq = Some(AoSequence::R2),
            Some(("seq", "sobol")) => seq = Some(AoSequence::Sobol),
            Some(("seq", _)) => return Err(bad("seq is r2 or sobol")),
            _ => rest.push(part),
        }
    }
    let rest = if rest.is_empty() { "default".to_string() } else { rest.join("+") };
    Ok((rest, eps, seq))
}

/// The filter a variant asks for: `denoise=on|off` (the edge-aware spatial filter of the
/// occlusion and IBL terms, timed with the frame), and the variant name without it (`default`
/// where nothing is left).
pub fn variant_denoise(name: &str) -> Result<(String, Denoise)> {
    let mut rest = Vec::new();
    let mut denoise = Denoise::Off;
    for part in name.split('+') {
        match part.split_once('=') {
            Some(("denoise", "on")) => denoise = Denoise::On,
            Some(("denoise", "off")) => denoise = Denoise::Off,
            Some(("denoise", _)) => return Err(anyhow::anyhow!("variant '{name}': denoise is on or off")),
            _ => rest.push(part),
        }
    }
    let rest = if rest.is_empty() { "default".to_string() } else { rest.join("+") };
    Ok((rest, denoise))
}

/// A measured variant: its name, performance options, AO origin offset and sequence, and filter.
type Variant = (String, PerfOptions, Option<f64>, Option<AoSequence>, Denoise);

pub fn run(a: &SuiteArgs) -> Result<()> {
    let baseline = match &a.baseline {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("reading the baseline {}", p.display()))?;
            Some(parse_rows(&text, &p.display().to_string())?)
        }
        None => None,
    };
    let variants: Vec<Variant> = a
        .variants
        .split(',')
        .map(str::trim)
        .filter(|v| !v.is_empty())
        .map(|v| {
            let (rest, denoise) = variant_denoise(v)?;
            let (perf, eps, seq) = variant_ao(&rest)?;
            Ok((v.to_string(), variant_options(&perf)?, eps, seq, denoise))
        })
        .collect::<Result<_>>()?;
    let mut gpu = GpuRenderer::new()?;
    let sizes: Vec<(u32, u32)> = a
        .sizes
        .split(',')
        .map(|s| args::size(s.trim()).map_err(|e| anyhow::anyhow!("--sizes: {e}")))
        .collect::<Result<_>>()?;
    let samples = sample_list(&a.samples)?;
    let header = format!(
        "# isowalld bench suite: median of {} frames, adapter '{}'; reference: ours, exact, {} frames x 256 samples",
        a.repeats.max(1),
        gpu.adapter_name(),
        a.reference_frames
    );
    println!("{header}");
    println!("{HEADER}");
    let mut rows = Vec::new();
    for scene in a.scenes.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (spec, iso) = scene_spec(scene)?;
        let (volume, iso) = load_volume(Some(spec), None, iso)?;
        gpu.set_perf(PerfOptions::default())?;
        let gv = gpu.upload(&volume)?;
        // The volume as each variant's block levels and voxel format need it.
        // Keyed by (block, AO block, coarse, format, texture).
        type UploadKey = (u32, u32, u32, VoxelFormat, bool);
        let mut uploads: Vec<(UploadKey, GpuVolume)> = Vec::new();
        for (variant, o, _, _, _) in &variants {
            let key = (o.block, o.ao_block, o.coarse, o.format, o.texture);
            if !uploads.iter().any(|(k, _)| *k == key) {
                gpu.set_perf(*o)?;
                let gv = gpu.upload(&volume)?;
                println!(
                    "# resident on the GPU, {} as {variant}: voxels {} bytes ({} per voxel, {}), block min/max {} bytes, march texture {} bytes",
                    volume.name,
                    gv.voxel_bytes,
                    o.format.bytes(),
                    o.format.name(),
                    gv.minmax_bytes,
                    if gv.march.enabled { gv.march.bytes } else { 0 }
                );
                uploads.push((key, gv));
            }
        }
        for &(w, h) in &sizes {
            let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
            gpu.set_perf(PerfOptions::default())?;
            let mut s = RenderSettings::new(iso);
            s.ao.samples = 256;
            s.ao.frame = 1_000_000; // disjoint from the measured frames' patterns
            let reference = gpu.render_accumulated(&gv, &view, &s, None, a.reference_frames.max(1))?.frame;
            for &n in &samples {
                for (variant, o, eps, seq, denoise) in &variants {
                    gpu.set_perf(*o)?;
                    let key = (o.block, o.ao_block, o.coarse, o.format, o.texture);
                    let gv = &uploads.iter().find(|(k, _)| *k == key).expect("uploaded").1;
                    let mut s = RenderSettings::new(iso);
                    s.ao.samples = n;
                    if let Some(e) = eps {
                        s.ao.offset_voxels = *e;
                    }
                    if let Some(q) = seq {
                        s.ao.sequence = *q;
                    }
                    s.denoise = *denoise;
                    gpu.render(gv, &view, &s, None)?; // warm-up
                    let mut times = Vec::new();
                    let mut cpu = Vec::new();
                    let mut last = None;
                    for r in 0..a.repeats.max(1) {
                        s.ao.frame = r as u32;
                        let cpu0 = process_cpu_ms();
                        let out = gpu.render(gv, &view, &s, None)?;
                        if let (Some(c0), Some(c1)) = (cpu0, process_cpu_ms()) {
                            cpu.push(c1 - c0);
                        }
                        times.push(out.gpu_time.as_secs_f64() * 1e3);
                        last = Some(out.frame);
                    }
                    let f = last.expect("at least one repeat");
                    let (rmse, _) = error_stats(&f.occlusion, &reference.occlusion, &reference.hit);
                    let (mismatch, angle) = primary_error(&f, &reference);
                    let row = Row {
                        scene: volume.name.clone(),
                        size: format!("{w}x{h}"),
                        samples: n,
                        variant: variant.to_string(),
                        ms: median(times),
                        fetches_per_pixel: f.fetches_per_pixel(),
                        occlusion_rmse: rmse,
                        hit_mismatch_percent: mismatch,
                        normal_error_deg: angle,
                    };
                    println!("{}", row.csv());
                    let measured = cpu.len();
                    if measured > 0 {
                        // On a CPU driver the frame's own cost, whatever else the machine runs.
                        println!(
                            "# cpu {},{w}x{h},{n},{variant}: {:.0} ms of process CPU per frame (median of {measured})",
                            volume.name,
                            median(cpu),
                        );
                    }
                    rows.push(row);
                }
            }
        }
    }
    if let Some(p) = &a.save {
        save_csv(p, &header, HEADER, rows.iter().map(Row::csv))?;
    }
    if let (Some(base), Some(p)) = (baseline, &a.baseline) {
        print_baseline_heading(
            p,
            "scene,size,samples,variant,baseline_variant,ms_ratio,fetch_ratio,occlusion_rmse_ratio",
        );
        for c in compare(&rows, &base) {
            let r = &c.row;
            println!(
                "{},{},{},{},{},{:.3},{:.3},{:.3}",
                r.scene,
                r.size,
                r.samples,
                r.variant,
                c.base_variant.as_deref().unwrap_or("none"),
                c.ms_ratio,
                c.fetch_ratio,
                c.rmse_ratio
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(variant: &str, ms: f64, fetches: f64, rmse: f64) -> Row {
        Row {
            scene: "procedural:engine:256".into(),
            size: "512x512".into(),
            samples: 32,
            variant: variant.into(),
            ms,
            fetches_per_pixel: fetches,
            occlusion_rmse: rmse,
            hit_mismatch_percent: 0.0,
            normal_error_deg: 0.0,
        }
    }

    #[test]
    fn variant_names_change_the_default() {
        assert_eq!(variant_options("default").unwrap(), PerfOptions::default());
        assert_eq!(variant_options("plain").unwrap(), PerfOptions::PLAIN);
        assert_eq!(variant_options("before").unwrap(), PerfOptions::PLAIN);
        assert_eq!(variant_options("format=r16").unwrap().format, VoxelFormat::R16);
        let o = variant_options("block=4+ao=2+coarse=8+exit=off+wg=16x4+format=r8").unwrap();
        assert_eq!(
            o,
            PerfOptions {
                block: 4,
                ao_block: 2,
                coarse: 8,
                block_min_exit: false,
                workgroup: (16, 4),
                format: VoxelFormat::R8,
                texture: false,
            }
        );
        assert_eq!(variant_options("before+wg=4x4").unwrap().workgroup, (4, 4));
        let t = variant_options("texture+format=r16f").unwrap();
        assert!(t.texture && t.format == VoxelFormat::R16F && !variant_options("default").unwrap().texture);
        for bad in ["fast", "block=x", "wg=0x8", "wg=32x32", "exit=maybe", "format=r4"] {
            assert!(variant_options(bad).is_err(), "{bad}");
        }
        assert_eq!(
            variant_ao("eps=0.5+seq=r2").unwrap(),
            ("default".into(), Some(0.5), Some(AoSequence::R2))
        );
        assert_eq!(variant_ao("ao=2+seq=sobol").unwrap(), ("ao=2".into(), None, Some(AoSequence::Sobol)));
        for bad in ["eps=-1", "eps=x", "seq=halton"] {
            assert!(variant_ao(bad).is_err(), "{bad}");
        }
        assert_eq!(variant_denoise("denoise=on").unwrap(), ("default".into(), Denoise::On));
        assert_eq!(variant_denoise("ao=2+denoise=on").unwrap(), ("ao=2".into(), Denoise::On));
        assert_eq!(variant_denoise("ao=2").unwrap(), ("ao=2".into(), Denoise::Off));
        assert!(variant_denoise("denoise=yes").is_err());
    }

    #[test]
    fn rows_survive_save_and_parse() {
        let rows = vec![row("default", 700.0, 53.8, 0.0271), row("r16", 650.5, 50.25, 0.02715)];
        let mut text = format!("# comment\n{HEADER}\n");
        for r in &rows {
            text.push_str(&r.csv());
            text.push('\n');
        }
        assert_eq!(parse_rows(&text, "x.csv").unwrap(), rows);
    }

    #[test]
    fn bad_files_name_the_line() {
        let e = parse_rows("scene,nope\n", "b.csv").unwrap_err().to_string();
        assert!(e.contains("b.csv:1"), "{e}");
        let e = parse_rows(&format!("{HEADER}\na,b,1,d,x,1,1,1,1\n"), "c.csv").unwrap_err().to_string();
        assert!(e.contains("c.csv:2") && e.contains("ms_per_frame"), "{e}");
        assert!(parse_rows("# only a comment\n", "d.csv").is_err());
    }

    #[test]
    fn comparison_is_a_ratio_and_falls_back_to_default() {
        let base = vec![row("default", 800.0, 60.0, 0.02)];
        let new = vec![row("default", 400.0, 30.0, 0.02), row("r16", 200.0, 30.0, 0.03), {
            let mut r = row("default", 1.0, 1.0, 1.0);
            r.samples = 256;
            r
        }];
        let c = compare(&new, &base);
        assert_eq!(c[0].base_variant.as_deref(), Some("default"));
        assert!((c[0].ms_ratio - 0.5).abs() < 1e-12 && (c[0].fetch_ratio - 0.5).abs() < 1e-12);
        assert!((c[0].rmse_ratio - 1.0).abs() < 1e-12);
        assert_eq!(c[1].base_variant.as_deref(), Some("default"));
        assert!((c[1].ms_ratio - 0.25).abs() < 1e-12 && (c[1].rmse_ratio - 1.5).abs() < 1e-12);
        assert_eq!(c[2].base_variant, None);
        assert!(c[2].ms_ratio.is_nan());
    }
}
