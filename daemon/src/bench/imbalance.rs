//! `isowalld bench imbalance`: how unevenly a wall's nodes share a frame's work in screen space,
//! where each node renders its own tiles and the wall's frame is as slow as its slowest node
//! (centre tiles hold the surface and its AO rays, edge tiles sky). Every tile of a wall config
//! is rendered through the tile path (each tile's resources kept over the frames, continuity by
//! the model's rule, reprojection on as a screen-space node has it): the `first` frame of the
//! start camera (a restart), `--still` frames of the unchanged camera (accumulating), then
//! `--frames` frames of an orbit (`--degrees` a frame about the world's z axis through the
//! target). Per tile its counters (trilinear fetches, hits) and its time (submit to done, the
//! process's CPU ms, and the kernels' GPU timestamps where the adapter has them) are summed per
//! node; per frame each node's share of the wall's work and the ratio of the slowest node to
//! the mean, by fetches and by time, averaged over the still and the orbiting frames.

use super::stats::process_cpu_ms;
use crate::render::{load_wall_volume, object_box, volume_limit};
use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use isowall_model::cli_args;
use isowall_model::config::WallConfig;
use isowall_model::wire::{Continuity, FrameSequence};
use isowall_model::{lowres, Camera, FrameState, RenderSettings, View};
use isowall_render::environment::{EnvSource, Environment};
use isowall_render::gpu::{
    FrameRead, GpuEnvironment, GpuRenderer, GpuVolume, ReadbackRing, TileFrame, TileTarget,
};
use std::path::PathBuf;

#[derive(Args)]
pub struct ImbalanceArgs {
    /// The wall config (TOML): its tiles, nodes, camera, volume and render settings
    #[arg(long, value_name = "FILE")]
    pub config: PathBuf,
    /// Frames of the orbit after the still frames
    #[arg(long, value_parser = cli_args::bench_frames, default_value_t = 8)]
    pub frames: u32,
    /// Degrees the camera turns each orbit frame (about the world's z axis through the target)
    #[arg(long, value_parser = cli_args::degrees, default_value_t = 3.0)]
    pub degrees: f64,
    /// Still frames after the first (the camera unchanged: each accumulates, AO only)
    #[arg(long, value_parser = cli_args::still_frames, default_value_t = 2)]
    pub still: u32,
    /// Render each tile at 1/S of its resolution per axis (the whole wall image scaled): fetches
    /// are counted at that size, a full-resolution frame does about S^2 times as many
    #[arg(long, value_parser = cli_args::scale, default_value_t = 1)]
    pub scale: u32,
    /// AO samples per pixel per frame (default: the config's `[render] ao_samples`)
    #[arg(long, value_parser = cli_args::ao_samples)]
    pub samples: Option<u32>,
    /// Also render every tile as this many bands of rows, each its own view (as a balanced node
    /// renders a work rectangle), and write each band's fetches and pixels per frame to
    /// --bands-out (the load-balancing simulator's costs: 32 bands, the split's)
    #[arg(long, value_name = "N", requires = "bands_out", value_parser = clap::value_parser!(u32).range(1..=256))]
    pub bands: Option<u32>,
    /// Where --bands writes its CSV
    #[arg(long, value_name = "FILE", requires = "bands")]
    pub bands_out: Option<PathBuf>,
}

/// What a frame is, for the averages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// The start camera's first frame: a restart.
    First,
    /// The camera unchanged: accumulating.
    Still,
    /// The camera turned since the frame before.
    Orbit,
}

impl Phase {
    fn label(self, k: u32) -> String {
        match self {
            Phase::First => "first".to_string(),
            Phase::Still => format!("still{k}"),
            Phase::Orbit => format!("orbit{k}"),
        }
    }
}

/// One tile's work in one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Work {
    pub fetches: u64,
    pub hits: u64,
    pub pixels: u64,
    /// Submit to done.
    pub ms: f64,
    /// This process's CPU time over the frame (on a CPU driver, the kernels' threads').
    pub cpu_ms: f64,
    /// The timed passes' GPU ms (timestamp queries); `None` without them.
    pub kernel_ms: Option<f64>,
}

impl Work {
    /// The sum of two tiles' work.
    pub fn plus(self, o: Work) -> Work {
        Work {
            fetches: self.fetches + o.fetches,
            hits: self.hits + o.hits,
            pixels: self.pixels + o.pixels,
            ms: self.ms + o.ms,
            cpu_ms: self.cpu_ms + o.cpu_ms,
            kernel_ms: match (self.kernel_ms, o.kernel_ms) {
                (Some(a), Some(b)) => Some(a + b),
                _ => None,
            },
        }
    }
}

/// A measure of work the ratios are taken by.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Measure {
    Fetches,
    Ms,
    CpuMs,
    KernelMs,
}

impl Measure {
    pub const ALL: [Measure; 4] = [Measure::Fetches, Measure::Ms, Measure::CpuMs, Measure::KernelMs];

    pub fn name(self) -> &'static str {
        match self {
            Measure::Fetches => "fetches",
            Measure::Ms => "ms",
            Measure::CpuMs => "cpu_ms",
            Measure::KernelMs => "kernel_ms",
        }
    }

    /// `w`'s amount (NaN where not measured).
    pub fn of(self, w: &Work) -> f64 {
        match self {
            Measure::Fetches => w.fetches as f64,
            Measure::Ms => w.ms,
            Measure::CpuMs => w.cpu_ms,
            Measure::KernelMs => w.kernel_ms.unwrap_or(f64::NAN),
        }
    }
}

/// Per node of `config`, in its order, the sum of its tiles' work (`tiles`: per tile name); a
/// node's tile missing from `tiles` is an error naming both.
pub fn node_sums(config: &WallConfig, tiles: &[(String, Work)]) -> Result<Vec<(String, Work)>> {
    config
        .nodes
        .iter()
        .map(|n| {
            let mut sum: Option<Work> = None;
            for t in &n.tiles {
                let w = tiles
                    .iter()
                    .find(|(name, _)| name == t)
                    .map(|(_, w)| *w)
                    .ok_or_else(|| anyhow!("node '{}': no work measured for its tile '{t}'", n.name))?;
                sum = Some(sum.map_or(w, |s| s.plus(w)));
            }
            Ok((n.name.clone(), sum.unwrap_or_default()))
        })
        .collect()
}

/// Each value's share of their sum (NaN where the sum is not positive).
pub fn shares(values: &[f64]) -> Vec<f64> {
    let total: f64 = values.iter().sum();
    values.iter().map(|v| if total > 0.0 { v / total } else { f64::NAN }).collect()
}

/// The largest value over the mean: 1 for an even split, the node count when one node does all
/// the work; NaN where there are no values, the mean is not positive or a value is not finite.
pub fn slowest_over_mean(values: &[f64]) -> f64 {
    if values.is_empty() || values.iter().any(|v| !v.is_finite()) {
        return f64::NAN;
    }
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    if mean <= 0.0 {
        return f64::NAN;
    }
    values.iter().copied().fold(f64::MIN, f64::max) / mean
}

/// The mean of the finite values (NaN without any).
pub fn mean_finite(values: impl Iterator<Item = f64>) -> f64 {
    let v: Vec<f64> = values.filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// One measured frame: its phase, label and per node work.
struct FrameWork {
    phase: Phase,
    label: String,
    nodes: Vec<(String, Work)>,
}

impl FrameWork {
    fn ratio(&self, m: Measure) -> f64 {
        slowest_over_mean(&self.nodes.iter().map(|(_, w)| m.of(w)).collect::<Vec<_>>())
    }
}

/// A tile's view at the bench's scale, with its resources.
struct BenchTile {
    name: String,
    view: View,
    target: TileTarget,
}

/// What every frame renders with.
#[derive(Clone, Copy)]
struct Scene<'a> {
    gpu: &'a GpuRenderer,
    volume: &'a GpuVolume,
    env: Option<&'a GpuEnvironment>,
    settings: RenderSettings,
}

/// The frames' cameras and phases: the first, `still` unchanged, then `frames` turned by
/// `degrees` each.
fn frame_plan(start: &Camera, still: u32, frames: u32, degrees: f64) -> Vec<(Phase, u32, Camera)> {
    let mut plan = vec![(Phase::First, 0, *start)];
    plan.extend((1..=still).map(|k| (Phase::Still, k, *start)));
    plan.extend((1..=frames).map(|k| (Phase::Orbit, k, start.yawed(k as f64 * degrees))));
    plan
}

/// Renders one tile's frame and waits for its counters: its work.
fn render_tile_frame(
    scene: &Scene,
    tile: &mut BenchTile,
    view: &View,
    frame_id: u64,
    continuity: Continuity,
    ring: &mut ReadbackRing<FrameRead>,
) -> Result<Work> {
    let cpu_before = process_cpu_ms();
    let tf = TileFrame {
        frame_id,
        volume: scene.volume,
        view,
        settings: &scene.settings,
        env: scene.env,
        continuity,
        temporal: true,
        share: None,
    };
    scene.gpu.render_tile(&mut tile.target, &tf, ring).with_context(|| format!("tile {}", tile.name))?;
    let read = loop {
        ring.wait_oldest(&scene.gpu.ctx)?;
        if let Some(r) = ring.take_ready().pop() {
            break r;
        }
    };
    let ms = read.latency.as_secs_f64() * 1e3;
    let (_, out) = FrameRead::decode(read, scene.gpu.ctx.queue.get_timestamp_period())?;
    let timed: Vec<f64> = out.kernel_ms.iter().flatten().copied().collect();
    Ok(Work {
        fetches: out.counters.fetches,
        hits: out.counters.hits,
        pixels: out.counters.pixels,
        ms,
        cpu_ms: match (cpu_before, process_cpu_ms()) {
            (Some(a), Some(b)) => b - a,
            _ => f64::NAN,
        },
        kernel_ms: (!timed.is_empty()).then(|| timed.iter().sum()),
    })
}

/// Renders every frame of `plan` on every tile; per frame, the work per node.
fn measure(
    config: &WallConfig,
    scene: &Scene,
    tiles: &mut [BenchTile],
    plan: &[(Phase, u32, Camera)],
    scale: u32,
) -> Result<Vec<FrameWork>> {
    let mut ring = ReadbackRing::<FrameRead>::new(2);
    let mut sequence = FrameSequence::default();
    let mut frames = Vec::new();
    for (id, (phase, k, camera)) in plan.iter().enumerate() {
        // As a node decides: by the model's rule, from the frame state before.
        let (continuity, accumulate) = sequence.start(FrameState::new(id as u64, camera, &scene.settings, 1));
        // The node's decorrelation index: the AO pattern advanced by the frames of the same image.
        let mut settings = scene.settings;
        settings.ao.frame = settings.ao.frame.wrapping_add(accumulate);
        let this = Scene { settings, ..*scene };
        let mut work = Vec::new();
        for tile in tiles.iter_mut() {
            let view = View { camera: *camera, ..tile.view };
            let w = render_tile_frame(&this, tile, &view, id as u64, continuity, &mut ring)?;
            work.push((tile.name.clone(), w));
        }
        let nodes = node_sums(config, &work)?;
        let f = FrameWork { phase: *phase, label: phase.label(*k), nodes };
        print_frame(&f, scale);
        frames.push(f);
    }
    Ok(frames)
}

fn fmt(v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("{v:.digits$}")
    } else {
        String::new()
    }
}

/// A frame's rows: per node its work and shares; then its ratios.
fn print_frame(f: &FrameWork, scale: u32) {
    let fetch_shares = shares(&f.nodes.iter().map(|(_, w)| w.fetches as f64).collect::<Vec<_>>());
    let ms_shares = shares(&f.nodes.iter().map(|(_, w)| w.ms).collect::<Vec<_>>());
    for (i, (node, w)) in f.nodes.iter().enumerate() {
        println!(
            "{},{node},{:.1},{},{},{},{:.1},{},{},{:.3},{:.3}",
            f.label,
            w.hits as f64 * 100.0 / w.pixels.max(1) as f64,
            w.fetches,
            w.fetches * u64::from(scale) * u64::from(scale),
            fmt(w.fetches as f64 / w.pixels.max(1) as f64, 1),
            w.ms,
            fmt(w.cpu_ms, 1),
            fmt(w.kernel_ms.unwrap_or(f64::NAN), 1),
            fetch_shares[i],
            ms_shares[i]
        );
    }
}

/// Per phase and measure, the mean of the frames' ratios.
fn phase_ratio(frames: &[FrameWork], phase: Phase, m: Measure) -> f64 {
    mean_finite(frames.iter().filter(|f| f.phase == phase).map(|f| f.ratio(m)))
}

/// Per node, its mean work and share over the frames of `phase`.
fn print_phase_nodes(frames: &[FrameWork], phase: Phase, name: &str) {
    let of_phase: Vec<&FrameWork> = frames.iter().filter(|f| f.phase == phase).collect();
    let Some(first) = of_phase.first() else { return };
    let mean_of = |i: usize, m: Measure| mean_finite(of_phase.iter().map(|f| m.of(&f.nodes[i].1)));
    let fetches: Vec<f64> = (0..first.nodes.len()).map(|i| mean_of(i, Measure::Fetches)).collect();
    let ms: Vec<f64> = (0..first.nodes.len()).map(|i| mean_of(i, Measure::Ms)).collect();
    let (fs, ms_s) = (shares(&fetches), shares(&ms));
    for (i, (node, _)) in first.nodes.iter().enumerate() {
        println!("{name},{node},{:.0},{:.1},{:.3},{:.3}", fetches[i], ms[i], fs[i], ms_s[i]);
    }
}

fn print_summary(frames: &[FrameWork]) {
    println!("# per frame: the slowest node over the mean, by each measure");
    println!(
        "frame,{}",
        Measure::ALL.iter().map(|m| format!("slowest_over_mean_{}", m.name())).collect::<Vec<_>>().join(",")
    );
    for f in frames {
        let r: Vec<String> = Measure::ALL.iter().map(|&m| fmt(f.ratio(m), 3)).collect();
        println!("{},{}", f.label, r.join(","));
    }
    println!("# per node, mean over the still and over the orbiting frames");
    println!("phase,node,fetches,ms,share_fetches,share_ms");
    print_phase_nodes(frames, Phase::Still, "still");
    print_phase_nodes(frames, Phase::Orbit, "orbiting");
    println!("# mean of the frames' slowest/mean");
    println!("phase,{}", Measure::ALL.map(Measure::name).join(","));
    for (phase, name) in [(Phase::First, "first"), (Phase::Still, "still"), (Phase::Orbit, "orbiting")] {
        let r: Vec<String> = Measure::ALL.iter().map(|&m| fmt(phase_ratio(frames, phase, m), 3)).collect();
        println!("{name},{}", r.join(","));
    }
    // "n/a" where a phase has no frames (`--still 0`, `--frames 0`).
    let r = |phase, m| match fmt(phase_ratio(frames, phase, m), 2) {
        s if s.is_empty() => "n/a".to_string(),
        s => s,
    };
    println!(
        "imbalance: slowest/mean {} still, {} orbiting (by fetches); {} still, {} orbiting (by ms)",
        r(Phase::Still, Measure::Fetches),
        r(Phase::Orbit, Measure::Fetches),
        r(Phase::Still, Measure::Ms),
        r(Phase::Orbit, Measure::Ms)
    );
}

/// The wall camera of `config` for the loaded volume: as the controller fills it (the object's
/// box at the iso framed in the whole wall image, unless the config names an eye).
fn wall_camera(config: &WallConfig, volume: &isowall_volume::Volume, iso: f64) -> Camera {
    config.camera_framing((volume.box_min(), volume.box_max()), object_box(volume, iso), volume.orientation())
}

/// Every tile of `config` with its view of `camera` at 1/`scale` resolution and its resources
/// (with the filter's guard band where `s` denoises, as a node makes them).
fn bench_tiles(
    gpu: &GpuRenderer,
    config: &WallConfig,
    camera: Camera,
    scale: u32,
    s: &RenderSettings,
) -> Result<Vec<BenchTile>> {
    let guard = if s.denoise.is_on() { isowall_render::denoise::reach() } else { 0 };
    config
        .tiles
        .iter()
        .map(|t| {
            let view = config
                .tile_view(camera, &t.name)
                .ok_or_else(|| anyhow!("{}: no tile '{}'", config.path.display(), t.name))?;
            let view = lowres::scaled_view(&view, scale);
            let target = TileTarget::with_guard(gpu, &t.name, &view, 1, guard)
                .with_context(|| format!("tile {}", t.name))?;
            Ok(BenchTile { name: t.name.clone(), view, target })
        })
        .collect()
}

pub fn run(a: &ImbalanceArgs) -> Result<()> {
    if a.scale == 0 {
        bail!("--scale 0: at least 1");
    }
    let config = WallConfig::load(&a.config).map_err(|e| anyhow!("{e}"))?;
    let limit = volume_limit(config.volume.max_bytes.map(|b| (b, "[volume] max_bytes")), true)?;
    let (volume, iso) = load_wall_volume(&config, &limit)?;
    let mut settings = config.render_settings(iso);
    if let Some(n) = a.samples {
        settings.ao.samples = n;
    }
    let gpu = GpuRenderer::new()?;
    let gv = gpu.upload(&volume)?;
    let env = if settings.ibl_needs_environment() {
        let src: EnvSource =
            config.env_source().parse().with_context(|| format!("{}: [render] env", a.config.display()))?;
        let env = Environment::from_source(&src).context("cannot load the environment")?;
        Some(gpu.upload_environment(&env)?)
    } else {
        None
    };
    let camera = wall_camera(&config, &volume, iso);
    let mut tiles = bench_tiles(&gpu, &config, camera, a.scale, &settings)?;
    print_header(a, &config, &gpu, &volume.name, iso, &settings, &tiles);
    let scene = Scene { gpu: &gpu, volume: &gv, env: env.as_ref(), settings };
    let plan = frame_plan(&camera, a.still, a.frames, a.degrees);
    let frames = measure(&config, &scene, &mut tiles, &plan, a.scale)?;
    print_summary(&frames);
    if let (Some(n), Some(out)) = (a.bands, &a.bands_out) {
        let mut bands = band_tiles(&gpu, &tiles, n, &settings)?;
        let csv = measure_bands(&config, &scene, &mut bands, &plan, a.scale)?;
        std::fs::write(out, csv).with_context(|| format!("writing {}", out.display()))?;
        println!("# bands: {n} a tile, each its own view; per frame and band in {}", out.display());
    }
    Ok(())
}

/// The CSV header of --bands-out: per frame, tile and band, the full-resolution tile's size, the
/// band's pixels and fetches at full resolution (the counts at the bench's scale times scale^2).
pub const BANDS_HEADER: &str = "frame,tile,node,width,height,band,pixels_full,fetches_full";

/// Each tile's `n` bands of rows of its view (band k: rows `k * h / n` up to the next), each with
/// its own resources, as a node that renders it as a work rectangle makes them.
fn band_tiles(
    gpu: &GpuRenderer,
    tiles: &[BenchTile],
    n: u32,
    s: &RenderSettings,
) -> Result<Vec<Vec<BenchTile>>> {
    let guard = if s.denoise.is_on() { isowall_render::denoise::reach() } else { 0 };
    tiles
        .iter()
        .map(|t| {
            let h = t.view.rect.height;
            (0..n)
                .filter_map(|k| {
                    let (a, b) = (k * h / n, (k + 1) * h / n);
                    (b > a).then_some((k, a, b))
                })
                .map(|(k, a, b)| {
                    let rect = isowall_model::Rect { y: t.view.rect.y + a, height: b - a, ..t.view.rect };
                    let view = View { rect, ..t.view };
                    let name = format!("{}/{k}", t.name);
                    let target = TileTarget::with_guard(gpu, &name, &view, 1, guard)
                        .with_context(|| format!("tile {} band {k}", t.name))?;
                    Ok(BenchTile { name, view, target })
                })
                .collect()
        })
        .collect()
}

/// Renders every frame of `plan` on every band of every tile (as [`measure`] does the tiles):
/// the --bands-out CSV.
fn measure_bands(
    config: &WallConfig,
    scene: &Scene,
    bands: &mut [Vec<BenchTile>],
    plan: &[(Phase, u32, Camera)],
    scale: u32,
) -> Result<String> {
    let mut ring = ReadbackRing::<FrameRead>::new(2);
    let mut sequence = FrameSequence::default();
    let mut csv = format!("{BANDS_HEADER}\n");
    let s2 = u64::from(scale) * u64::from(scale);
    for (id, (phase, k, camera)) in plan.iter().enumerate() {
        let (continuity, accumulate) = sequence.start(FrameState::new(id as u64, camera, &scene.settings, 1));
        let mut settings = scene.settings;
        settings.ao.frame = settings.ao.frame.wrapping_add(accumulate);
        let this = Scene { settings, ..*scene };
        for (tile, tile_bands) in config.tiles.iter().zip(bands.iter_mut()) {
            let node = config.node_of_tile(&tile.name).map(|n| n.name.as_str()).unwrap_or("");
            for (b, band) in tile_bands.iter_mut().enumerate() {
                let view = View { camera: *camera, ..band.view };
                let w = render_tile_frame(&this, band, &view, id as u64, continuity, &mut ring)?;
                csv.push_str(&format!(
                    "{},{},{node},{},{},{b},{},{}\n",
                    phase.label(*k),
                    tile.name,
                    tile.width,
                    tile.height,
                    w.pixels * s2,
                    w.fetches * s2
                ));
            }
        }
        eprintln!("bands: frame {} done", phase.label(*k));
    }
    Ok(csv)
}

fn print_header(
    a: &ImbalanceArgs,
    config: &WallConfig,
    gpu: &GpuRenderer,
    volume: &str,
    iso: f64,
    s: &RenderSettings,
    tiles: &[BenchTile],
) {
    let (w, h) = config.wall_size();
    let (sw, sh) = tiles.first().map(|t| t.view.full).unwrap_or((w, h));
    let timestamps = gpu.ctx.device.features().contains(wgpu::Features::TIMESTAMP_QUERY);
    println!(
        "# isowalld bench imbalance: wall '{}' from {} ({} tiles on {} nodes, {w}x{h} px), volume {volume} at iso {iso}, \
         {} AO samples a frame, adapter '{}'",
        config.wall.name,
        a.config.display(),
        config.tiles.len(),
        config.nodes.len(),
        s.ao.samples,
        gpu.adapter_name()
    );
    println!(
        "# screen space, each node rendering its own tiles one after another; every tile at 1/{} resolution per axis \
         (the wall image {sw}x{sh} px): fetches are counted at that size, a full-resolution frame does about {}x as many \
         (fetches_full); ms: submit to done per tile, summed per node; cpu_ms: this process's CPU time (a CPU driver's \
         kernels run on its threads); kernel_ms: {}",
        a.scale,
        a.scale * a.scale,
        if timestamps {
            "the timed passes' GPU timestamps (on lavapipe they do not bracket the passes: read ms)"
        } else {
            "none (no timestamp queries)"
        }
    );
    println!(
        "# frames: first (the start camera, a restart), still1..{} (unchanged: accumulating), orbit1..{} ({} degrees a \
         frame about z through the target: reprojected)",
        a.still, a.frames, a.degrees
    );
    println!(
        "frame,node,hit_percent,fetches,fetches_full,fetches_per_pixel,ms,cpu_ms,kernel_ms,share_fetches,share_ms"
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn work(fetches: u64, ms: f64) -> Work {
        Work { fetches, hits: 1, pixels: 4, ms, cpu_ms: ms, kernel_ms: None }
    }

    const WALL: &str = "[wall]\nname = \"w\"\n\n[volume]\nsource = \"procedural:sphere:16\"\n\n\
        [[tiles]]\nname = \"a\"\nx = 0\ny = 0\nwidth = 8\nheight = 8\n\n\
        [[tiles]]\nname = \"b\"\nx = 8\ny = 0\nwidth = 8\nheight = 8\n\n\
        [[tiles]]\nname = \"c\"\nx = 16\ny = 0\nwidth = 8\nheight = 8\n\n\
        [[nodes]]\nname = \"n0\"\naddress = \"127.0.0.1:7400\"\ntiles = [\"a\", \"c\"]\n\n\
        [[nodes]]\nname = \"n1\"\naddress = \"127.0.0.1:7401\"\ntiles = [\"b\"]\n";

    #[test]
    fn a_node_sums_its_own_tiles_and_a_missing_tile_is_named() {
        let config = WallConfig::parse(WALL, Path::new("w.toml")).expect("the test wall parses");
        let tiles =
            vec![("a".to_string(), work(10, 1.0)), ("b".into(), work(5, 2.0)), ("c".into(), work(7, 4.0))];
        let nodes = node_sums(&config, &tiles).unwrap();
        assert_eq!(nodes.len(), 2);
        assert_eq!((nodes[0].0.as_str(), nodes[0].1.fetches, nodes[0].1.ms), ("n0", 17, 5.0));
        assert_eq!((nodes[0].1.hits, nodes[0].1.pixels), (2, 8));
        assert_eq!((nodes[1].0.as_str(), nodes[1].1.fetches, nodes[1].1.ms), ("n1", 5, 2.0));
        let e = node_sums(&config, &tiles[..2]).unwrap_err().to_string();
        assert!(e.contains("'n0'") && e.contains("'c'"), "{e}");
    }

    #[test]
    fn slowest_over_mean_is_one_when_even_and_the_node_count_when_one_does_all() {
        assert_eq!(slowest_over_mean(&[3.0, 3.0, 3.0]), 1.0);
        assert_eq!(slowest_over_mean(&[0.0, 8.0, 0.0, 0.0]), 4.0);
        assert!((slowest_over_mean(&[1.0, 2.0, 3.0]) - 1.5).abs() < 1e-12);
        assert!(slowest_over_mean(&[]).is_nan());
        assert!(slowest_over_mean(&[0.0, 0.0]).is_nan());
        assert!(slowest_over_mean(&[1.0, f64::NAN]).is_nan());
        let s = shares(&[1.0, 3.0]);
        assert_eq!(s, vec![0.25, 0.75]);
        assert!(shares(&[0.0, 0.0]).iter().all(|v| v.is_nan()));
        assert_eq!(mean_finite([1.0, f64::NAN, 3.0].into_iter()), 2.0);
        // Timestamps only where every tile has them.
        let t = Work { kernel_ms: Some(1.0), ..work(1, 1.0) };
        assert_eq!(t.plus(t).kernel_ms, Some(2.0));
        assert_eq!(t.plus(work(1, 1.0)).kernel_ms, None);
    }

    #[test]
    fn the_plan_starts_still_then_turns_about_the_target() {
        let start = Camera {
            eye: glam::DVec3::new(10.0, 0.0, 0.0),
            target: glam::DVec3::ZERO,
            up: glam::DVec3::Z,
            fov_y_deg: 30.0,
        };
        let plan = frame_plan(&start, 2, 3, 90.0);
        let phases: Vec<Phase> = plan.iter().map(|p| p.0).collect();
        use Phase::*;
        assert_eq!(phases, vec![First, Still, Still, Orbit, Orbit, Orbit]);
        assert_eq!(plan[2].2, start);
        assert!((plan[3].2.eye - glam::DVec3::new(0.0, 10.0, 0.0)).length() < 1e-9);
        assert_eq!(plan[5].0.label(plan[5].1), "orbit3");
    }
}
