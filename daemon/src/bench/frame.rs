//! `isowalld bench frame`: what one frame of a wall tile costs, by the node's own frame path. For
//! a tile (default 1920x1080) in screen space (presented offscreen: the frame stays on the GPU;
//! then a snapshot), in object space (the tile's share, colour and depth, read back each frame)
//! and, with `--paths moving`, in screen space with every frame a restart (a camera that moves:
//! the isosurface kernel runs every frame, no accumulation), per frame: GPU allocations, bytes
//! read back, bytes uploaded, CPU ms outside GPU waits, ms per frame, and GPU ms per kernel
//! (timestamp queries where the adapter has them; otherwise submit to done for the whole frame).
//! `--variants plain` (or `before`) runs the path of the build before the frame stayed on the GPU
//! (every AOV made and read back each frame, composed, accumulated and encoded on the CPU,
//! uploaded again to present) in the same run, for ratios.

use super::stats::{
    baseline_row, csv_records, is_plain, median, print_baseline_heading, sample_list, save_csv, scene_spec,
    PLAIN, PLAIN_ALIAS,
};
use crate::args;
use crate::render::load_volume;
use anyhow::{bail, Context, Result};
use clap::Args;
use isowall_model::cli_args;
use isowall_model::composite::PixelForm;
use isowall_model::wire::Continuity;
use isowall_model::{Camera, RenderSettings, View};
use isowall_render::gpu::{
    FrameRead, GpuRenderer, GpuVolume, ReadbackRing, TileFrame, TileTarget, TrafficCount,
};
use isowall_render::output::srgb8;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// The CSV header of `--save` and `--baseline` files (comment lines start with '#').
pub const HEADER: &str = "scene,size,samples,path,variant,ms_per_frame,cpu_ms,gpu_ms_isosurface,gpu_ms_ao,gpu_ms_compose,gpu_ms_frame,allocations,bytes_read_back,bytes_uploaded";

#[derive(Args)]
pub struct FrameArgs {
    /// Scenes as VOLUME[@ISO], comma-separated (VOLUME as for `render --volume`)
    #[arg(long, default_value = "procedural:engine,../shared/data/ct-cranium.nrrd@300")]
    pub scenes: String,
    /// The tile's size
    #[arg(long, default_value = "1920x1080", value_parser = args::size)]
    pub size: (u32, u32),
    /// AO samples per pixel per frame, comma-separated
    #[arg(long, default_value = "32,256")]
    pub samples: String,
    /// Timed frames per row (medians reported), after one untimed frame that makes the resources
    #[arg(long, value_parser = cli_args::repeats, default_value_t = 3)]
    pub repeats: usize,
    /// Paths measured, comma-separated: `screen` (presented offscreen, accumulating, then a
    /// snapshot), `object` (the share read back every frame), `moving` (presented offscreen, every
    /// frame a restart as when the camera moves: the isosurface kernel runs every frame)
    #[arg(long, default_value = "screen,object")]
    pub paths: String,
    /// `default` (the frame on the GPU) and/or `plain` (or `before`: every AOV read back, the CPU
    /// composes, accumulates, encodes and uploads to present), comma-separated
    #[arg(long, default_value = "default")]
    pub variants: String,
    /// Compare with the rows of this CSV (an earlier `--save`): ratios new / baseline
    #[arg(long, value_name = "FILE")]
    pub baseline: Option<PathBuf>,
    /// Write the rows to this CSV
    #[arg(long, value_name = "FILE")]
    pub save: Option<PathBuf>,
}

/// One measured row.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub scene: String,
    pub size: String,
    pub samples: u32,
    pub path: String,
    pub variant: String,
    pub ms: f64,
    pub cpu_ms: f64,
    /// Isosurface, AO, compose (NaN where not measured).
    pub kernel_ms: [f64; 3],
    /// Submit to done of the whole frame.
    pub gpu_ms: f64,
    pub allocations: f64,
    pub read_back: f64,
    pub uploaded: f64,
}

impl Row {
    fn key(&self) -> (String, String, u32, String, String) {
        (self.scene.clone(), self.size.clone(), self.samples, self.path.clone(), self.variant.clone())
    }

    fn csv(&self) -> String {
        let k = |v: f64| if v.is_nan() { String::new() } else { format!("{v:.2}") };
        format!(
            "{},{},{},{},{},{:.2},{:.2},{},{},{},{:.2},{:.1},{:.0},{:.0}",
            self.scene,
            self.size,
            self.samples,
            self.path,
            self.variant,
            self.ms,
            self.cpu_ms,
            k(self.kernel_ms[0]),
            k(self.kernel_ms[1]),
            k(self.kernel_ms[2]),
            self.gpu_ms,
            self.allocations,
            self.read_back,
            self.uploaded
        )
    }
}

/// Parses rows written by [`Row::csv`] under [`HEADER`]; errors name the file and line.
pub fn parse_rows(text: &str, file: &str) -> Result<Vec<Row>> {
    let mut rows = Vec::new();
    for (i, f) in csv_records(text, file, HEADER, 14)? {
        let num = |k: usize| -> Result<f64> {
            if f[k].is_empty() && (7..=9).contains(&k) {
                return Ok(f64::NAN);
            }
            f[k].parse::<f64>()
                .map_err(|_| anyhow::anyhow!("{file}:{i}: field {} '{}' is not a number", k + 1, f[k]))
        };
        rows.push(Row {
            scene: f[0].to_string(),
            size: f[1].to_string(),
            samples: f[2]
                .parse()
                .map_err(|_| anyhow::anyhow!("{file}:{i}: samples '{}' is not a whole number", f[2]))?,
            path: f[3].to_string(),
            variant: f[4].to_string(),
            ms: num(5)?,
            cpu_ms: num(6)?,
            kernel_ms: [num(7)?, num(8)?, num(9)?],
            gpu_ms: num(10)?,
            allocations: num(11)?,
            read_back: num(12)?,
            uploaded: num(13)?,
        });
    }
    Ok(rows)
}

/// What one frame cost.
#[derive(Clone, Copy, Debug, Default)]
struct Sample {
    ms: f64,
    cpu_ms: f64,
    kernel_ms: [f64; 3],
    gpu_ms: f64,
    traffic: TrafficCount,
}

fn traffic_delta(gpu: &GpuRenderer, before: TrafficCount) -> TrafficCount {
    gpu.ctx.traffic.now() - before
}

/// A path `bench frame` measures (`--paths`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Path {
    /// Screen space, presented offscreen, accumulating while the frame state holds.
    Screen,
    /// Object space: the tile's share read back every frame.
    Object,
    /// Screen space with every frame a restart, as while the camera moves.
    Moving,
}

impl Path {
    fn parse(name: &str) -> Result<Path> {
        match name {
            "screen" => Ok(Path::Screen),
            "object" => Ok(Path::Object),
            "moving" => Ok(Path::Moving),
            _ => bail!("--paths: unknown path '{name}' (screen, object, moving)"),
        }
    }
}

/// The frame path of this build: the tile's resources made once, one frame at a time (submit,
/// then wait for its read so that the times are the frame's).
struct Current {
    tile: TileTarget,
    ring: ReadbackRing<FrameRead>,
}

impl Current {
    fn frame(
        &mut self,
        gpu: &GpuRenderer,
        gv: &GpuVolume,
        view: &View,
        s: &RenderSettings,
        k: u32,
        path: Path,
    ) -> Result<Sample> {
        let before = gpu.ctx.traffic.now();
        let start = Instant::now();
        let mut f = *s;
        f.ao.frame = s.ao.frame.wrapping_add(k);
        let share = path == Path::Object;
        let tf = TileFrame {
            frame_id: k as u64,
            volume: gv,
            view,
            settings: &f,
            env: None,
            // The same image accumulates; the moving path stands in for a camera that moves every
            // frame with reprojection off: every frame starts over.
            continuity: if k > 0 && path != Path::Moving { Continuity::Same } else { Continuity::Changed },
            temporal: false,
            share: share.then_some(PixelForm::Colour),
        };
        gpu.render_tile(&mut self.tile, &tf, &mut self.ring)?;
        let mut waited = Duration::ZERO;
        let read = loop {
            waited += self.ring.wait_oldest(&gpu.ctx)?;
            if let Some(r) = self.ring.take_ready().pop() {
                break r;
            }
        };
        let latency = read.latency;
        let (_, out) = FrameRead::decode(read, gpu.ctx.queue.get_timestamp_period())?;
        let ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(Sample {
            ms,
            cpu_ms: ms - waited.as_secs_f64() * 1e3,
            kernel_ms: out.kernel_ms.map(|k| k.unwrap_or(f64::NAN)),
            gpu_ms: latency.as_secs_f64() * 1e3,
            traffic: traffic_delta(gpu, before),
        })
    }

    /// A snapshot of the last frame.
    fn snapshot(&mut self, gpu: &GpuRenderer, frame_id: u64) -> Result<Sample> {
        let before = gpu.ctx.traffic.now();
        let start = Instant::now();
        gpu.read_tile_image(&self.tile, frame_id, &mut self.ring)?;
        let mut waited = Duration::ZERO;
        let read = loop {
            waited += self.ring.wait_oldest(&gpu.ctx)?;
            if let Some(r) = self.ring.take_ready().pop() {
                break r;
            }
        };
        let latency = read.latency;
        let (_, out) = FrameRead::decode(read, gpu.ctx.queue.get_timestamp_period())?;
        if out.rgb8.is_none_or(|p| p.is_empty()) {
            bail!("the snapshot read no image");
        }
        let ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(Sample {
            ms,
            cpu_ms: ms - waited.as_secs_f64() * 1e3,
            kernel_ms: [f64::NAN; 3],
            gpu_ms: latency.as_secs_f64() * 1e3,
            traffic: traffic_delta(gpu, before),
        })
    }
}

/// The frame path before the frame stayed on the GPU, as the render thread ran it: every AOV made
/// and read back (`GpuRenderer::render`), colour summed and averaged on the CPU, encoded to 8-bit
/// sRGB, upsampled nowhere (scale 1), and in screen space uploaded to a texture to present.
struct Before {
    sum: Vec<[f32; 3]>,
    frames: u32,
    texture: Option<wgpu::Texture>,
}

impl Before {
    fn frame(
        &mut self,
        gpu: &GpuRenderer,
        gv: &GpuVolume,
        view: &View,
        s: &RenderSettings,
        k: u32,
        present: bool,
    ) -> Result<Sample> {
        let before = gpu.ctx.traffic.now();
        let start = Instant::now();
        let mut f = *s;
        f.ao.frame = s.ao.frame.wrapping_add(k);
        let r = gpu.render(gv, view, &f, None)?;
        let mut frame = r.frame;
        if k == 0 || self.sum.len() != frame.color.len() {
            self.sum = vec![[0.0; 3]; frame.color.len()];
            self.frames = 0;
        }
        self.frames += 1;
        let n = self.frames as f32;
        for (acc, c) in self.sum.iter_mut().zip(frame.color.iter_mut()) {
            for i in 0..3 {
                acc[i] += c[i];
                c[i] = acc[i] / n;
            }
        }
        let depth: Vec<f32> =
            frame.depth.iter().zip(&frame.hit).map(|(&d, &h)| if h { d } else { f32::INFINITY }).collect();
        let rgb = srgb8(&frame);
        std::hint::black_box(&depth);
        if present {
            let (w, h) = (frame.width, frame.height);
            let texture = self.texture.get_or_insert_with(|| {
                gpu.ctx.create_texture(&wgpu::TextureDescriptor {
                    label: Some("before: staged tile"),
                    size: wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
                    mip_level_count: 1,
                    sample_count: 1,
                    dimension: wgpu::TextureDimension::D2,
                    format: wgpu::TextureFormat::Rgba8Unorm,
                    usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                    view_formats: &[],
                })
            });
            let mut rgba = vec![255u8; 4 * rgb.len() / 3];
            for (d, c) in rgba.chunks_exact_mut(4).zip(rgb.chunks_exact(3)) {
                d[..3].copy_from_slice(c);
            }
            gpu.ctx.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                &rgba,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * w),
                    rows_per_image: Some(h),
                },
                wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
            );
            gpu.ctx.queue.submit([]);
        }
        let ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(Sample {
            ms,
            cpu_ms: ms - r.wait_time.as_secs_f64() * 1e3,
            kernel_ms: [f64::NAN; 3],
            gpu_ms: r.gpu_time.as_secs_f64() * 1e3,
            traffic: traffic_delta(gpu, before),
        })
    }
}

fn row(scene: &str, size: (u32, u32), samples: u32, path: &str, variant: &str, samples_of: &[Sample]) -> Row {
    let m = |f: &dyn Fn(&Sample) -> f64| median(samples_of.iter().map(f).collect());
    let mk = |k: usize| {
        let v: Vec<f64> = samples_of.iter().map(|s| s.kernel_ms[k]).filter(|v| !v.is_nan()).collect();
        if v.is_empty() {
            f64::NAN
        } else {
            median(v)
        }
    };
    Row {
        scene: scene.to_string(),
        size: format!("{}x{}", size.0, size.1),
        samples,
        path: path.to_string(),
        variant: variant.to_string(),
        ms: m(&|s| s.ms),
        cpu_ms: m(&|s| s.cpu_ms),
        kernel_ms: [mk(0), mk(1), mk(2)],
        gpu_ms: m(&|s| s.gpu_ms),
        allocations: m(&|s| s.traffic.allocations as f64),
        read_back: m(&|s| s.traffic.read_back as f64),
        uploaded: m(&|s| s.traffic.uploaded as f64),
    }
}

pub fn run(a: &FrameArgs) -> Result<()> {
    let baseline = match &a.baseline {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("reading the baseline {}", p.display()))?;
            Some(parse_rows(&text, &p.display().to_string())?)
        }
        None => None,
    };
    let list = |s: &str| -> Vec<String> {
        s.split(',').map(str::trim).filter(|v| !v.is_empty()).map(String::from).collect()
    };
    let paths = list(&a.paths);
    let variants = list(&a.variants);
    let kinds = paths.iter().map(|p| Path::parse(p)).collect::<Result<Vec<Path>>>()?;
    for v in &variants {
        if v != "default" && !is_plain(v) {
            bail!("--variants: unknown variant '{v}' (default, plain)");
        }
    }
    let gpu = GpuRenderer::new()?;
    let timestamps = gpu.ctx.device.features().contains(wgpu::Features::TIMESTAMP_QUERY);
    let samples = sample_list(&a.samples)?;
    let (w, h) = a.size;
    let header = format!(
        "# isowalld bench frame: {w}x{h} tile, median of {} frames after 1 untimed, adapter '{}'; GPU ms per kernel from {}",
        a.repeats.max(1),
        gpu.adapter_name(),
        if timestamps { "timestamp queries" } else { "nothing (no timestamp queries: see gpu_ms_frame, submit to done)" }
    );
    println!("{header}");
    println!("{HEADER}");
    let mut rows = Vec::new();
    for scene in list(&a.scenes) {
        let (spec, iso) = scene_spec(&scene)?;
        let (volume, iso) = load_volume(Some(spec), None, iso)?;
        let gv = gpu.upload(&volume)?;
        let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
        for &n in &samples {
            let mut s = RenderSettings::new(iso);
            s.ao.samples = n;
            for (path, &kind) in paths.iter().zip(&kinds) {
                for variant in &variants {
                    let mut timed = Vec::new();
                    let repeats = a.repeats.max(1) as u32;
                    let mut snapshot = None;
                    if variant == "default" {
                        let mut c = Current {
                            tile: TileTarget::new(&gpu, &volume.name, &view, 1)?,
                            ring: ReadbackRing::new(3),
                        };
                        for k in 0..=repeats {
                            let sample = c.frame(&gpu, &gv, &view, &s, k, kind)?;
                            if k > 0 {
                                timed.push(sample);
                            }
                        }
                        if kind == Path::Screen {
                            snapshot = Some(c.snapshot(&gpu, repeats as u64)?);
                        }
                    } else {
                        // The earlier path rendered the primary hits every frame, so its moving frame
                        // is its screen frame without the running colour sum carried over.
                        let mut b = Before { sum: Vec::new(), frames: 0, texture: None };
                        for k in 0..=repeats {
                            let restart = if kind == Path::Moving { 0 } else { k };
                            let sample = b.frame(&gpu, &gv, &view, &s, restart, kind != Path::Object)?;
                            if k > 0 {
                                timed.push(sample);
                            }
                        }
                    }
                    let r = row(&volume.name, a.size, n, path, variant, &timed);
                    println!("{}", r.csv());
                    rows.push(r);
                    if let Some(snap) = snapshot {
                        let r = row(&volume.name, a.size, n, "snapshot", variant, &[snap]);
                        println!("{}", r.csv());
                        rows.push(r);
                    }
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
            "scene,size,samples,path,variant,baseline_variant,ms_ratio,cpu_ms_ratio,allocations_ratio,read_back_ratio,uploaded_ratio",
        );
        for r in &rows {
            // The same row of the baseline, else its `plain` row (a build without this path),
            // which a baseline made before that name calls `before`.
            let key = r.key();
            let plain = |name: &str| (key.0.clone(), key.1.clone(), key.2, key.3.clone(), name.to_string());
            let b = baseline_row(&base, Row::key, &key, &plain(PLAIN))
                .or_else(|| baseline_row(&base, Row::key, &key, &plain(PLAIN_ALIAS)));
            let ratio = |x: f64, y: f64| {
                if y == 0.0 {
                    if x == 0.0 {
                        "1.000".to_string()
                    } else {
                        "inf".to_string()
                    }
                } else {
                    format!("{:.3}", x / y)
                }
            };
            match b {
                Some(b) => println!(
                    "{},{},{},{},{},{},{},{},{},{},{}",
                    r.scene,
                    r.size,
                    r.samples,
                    r.path,
                    r.variant,
                    b.variant,
                    ratio(r.ms, b.ms),
                    ratio(r.cpu_ms, b.cpu_ms),
                    ratio(r.allocations, b.allocations),
                    ratio(r.read_back, b.read_back),
                    ratio(r.uploaded, b.uploaded)
                ),
                None => println!("{},{},{},{},{},none,,,,,", r.scene, r.size, r.samples, r.path, r.variant),
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_survive_save_and_parse_and_bad_files_are_named() {
        let r = Row {
            scene: "engine".into(),
            size: "1920x1080".into(),
            samples: 32,
            path: "screen".into(),
            variant: "default".into(),
            ms: 12.5,
            cpu_ms: 0.25,
            kernel_ms: [1.5, f64::NAN, 0.75],
            gpu_ms: 12.0,
            allocations: 0.0,
            read_back: 64.0,
            uploaded: 544.0,
        };
        let text = format!("# comment\n{HEADER}\n{}\n", r.csv());
        let back = parse_rows(&text, "f.csv").unwrap();
        assert_eq!(back.len(), 1);
        assert_eq!(back[0].key(), r.key());
        assert_eq!(back[0].read_back, 64.0);
        assert!(back[0].kernel_ms[1].is_nan() && back[0].kernel_ms[2] == 0.75);
        let e = parse_rows(&format!("{HEADER}\nengine,1,2\n"), "f.csv").unwrap_err().to_string();
        assert!(e.contains("f.csv:2"), "{e}");
        assert!(parse_rows("scene,x\n", "g.csv").unwrap_err().to_string().contains("g.csv:1"));
    }
}
