//! `isowalld render`: one headless frame to a file.

use crate::args;
use crate::bricked::{budgets_from_flags, BrickedOnGpu, BrickedVolume};
use crate::progress::Counted;
use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, ValueEnum};
use glam::DVec3;
use isowall_model::config::BrickBudgets;
use isowall_model::render_state::DEFAULT_EXPOSURE;
use isowall_model::{
    AoMethod, AoRadius, AoSequence, Aov, Camera, Denoise, IblMethod, RenderSettings, Shading, View,
    ViewPreset, WallConfig,
};
use isowall_render::environment::{EnvSource, Environment};
use isowall_render::gpu::GpuRenderer;
use isowall_render::{output, reference, Frame};
use isowall_volume::io::{RawSpec, VolumeLimit};
use isowall_volume::{BlockMinMax, Volume, VolumeSource};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Default)]
pub enum RendererKind {
    /// The wgpu compute ray-caster (Vulkan; lavapipe where there is no GPU).
    #[default]
    Gpu,
    /// The exact CPU reference renderer (f64, cubic root per cell): slow, the oracle for tests.
    Reference,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ShadingArg {
    Lambert,
    BlinnPhong,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum AovArg {
    Color,
    Depth,
    Normal,
    Hit,
    Occlusion,
    BentNormal,
    Ibl,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum AoMethodArg {
    /// Cosine-weighted directions (`--ao-sequence`), decorrelated per pixel and frame, from the surface, every cell tested exactly
    Ours,
    /// The 2008 RTPara shader, ported faithfully as the baseline (biased; not our method)
    Seed,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum AoSequenceArg {
    /// The R2 sequence, shifted per pixel and frame
    R2,
    /// Sobol with hash-based Owen scrambling, seeded per pixel and frame (the default)
    Sobol,
}

impl From<AoSequenceArg> for AoSequence {
    fn from(a: AoSequenceArg) -> AoSequence {
        match a {
            AoSequenceArg::R2 => AoSequence::R2,
            AoSequenceArg::Sobol => AoSequence::Sobol,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum IblArg {
    /// Constant ambient light times 1 - A
    None,
    /// The raw environment at the bent normal times 1 - A (the 2008 method)
    Seed,
    /// The environment's diffuse irradiance (SH9) at the bent normal times 1 - A
    Bent,
    /// Every escaping AO ray looks up the environment (unbiased)
    Rays,
}

impl From<IblArg> for IblMethod {
    fn from(i: IblArg) -> Self {
        match i {
            IblArg::None => IblMethod::None,
            IblArg::Seed => IblMethod::Seed,
            IblArg::Bent => IblMethod::Bent,
            IblArg::Rays => IblMethod::Rays,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum DenoiseArg {
    /// The running sums as they are
    Off,
    /// The edge-aware spatial filter of the occlusion and IBL terms
    On,
}

impl From<DenoiseArg> for Denoise {
    fn from(d: DenoiseArg) -> Denoise {
        match d {
            DenoiseArg::Off => Denoise::Off,
            DenoiseArg::On => Denoise::On,
        }
    }
}

/// `--view NAME`, one of [`ViewPreset::names`].
fn view_preset(s: &str) -> Result<ViewPreset, String> {
    s.parse().map_err(|e: isowall_model::UnknownView| e.to_string())
}

/// `--ao-radius R|unbounded`.
fn ao_radius(s: &str) -> Result<AoRadius, String> {
    if s == "unbounded" {
        return Ok(AoRadius::Unbounded);
    }
    match s.parse::<f64>() {
        Ok(r) if r.is_finite() && r > 0.0 => Ok(AoRadius::World(r)),
        _ => Err(format!("'{s}' is neither a positive number (world units) nor 'unbounded'")),
    }
}

impl From<AovArg> for Aov {
    fn from(a: AovArg) -> Aov {
        match a {
            AovArg::Color => Aov::Color,
            AovArg::Depth => Aov::Depth,
            AovArg::Normal => Aov::Normal,
            AovArg::Hit => Aov::Hit,
            AovArg::Occlusion => Aov::Occlusion,
            AovArg::BentNormal => Aov::BentNormal,
            AovArg::Ibl => Aov::Ibl,
        }
    }
}

#[derive(Args, Debug, Default, Clone)]
pub struct RenderArgs {
    /// Volume: a file (.nrrd .nhdr .mhd .mha .nii .nii.gz, a DICOM folder or one file of the series,
    /// an OME-Zarr store, or raw with --dims/--type/--spacing) or
    /// procedural:NAME[:N] with NAME one of sphere, sphere-over-plane, torus, marschner-lobb, gyroid,
    /// engine and N the largest dimension [default: procedural:engine, 256x256x118]
    #[arg(long, value_name = "PATH|procedural:NAME[:N]")]
    pub volume: Option<String>,
    /// DICOM: the SeriesInstanceUID to read where the folder holds several (the error without it
    /// lists them)
    #[arg(long, value_name = "UID")]
    pub series: Option<String>,
    /// Time-varying volumes (a `step_*.nrrd` glob, a 4-D NIfTI or NRRD): the time step to render,
    /// from 0 [default: 0]
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub step: usize,
    /// Iso value in the data's own units (Hounsfield for CT) [default: the procedural volume's own;
    /// for files the middle of the data range, with a warning]
    #[arg(long, value_name = "V", allow_negative_numbers = true)]
    pub iso: Option<f64>,
    /// Image size in pixels [default: 800x600]
    #[arg(long, value_name = "WxH", value_parser = args::size)]
    pub size: Option<(u32, u32)>,
    /// Camera position (world units) [default: a view that frames the surface at the iso (the
    /// blocks that reach it; the volume's box where none does): with --view from that side, for
    /// a scan with a patient orientation from the anterior, else a three-quarter view from the
    /// front-right (-y, +x) and above]
    #[arg(long, value_name = "X,Y,Z", value_parser = args::vec3, allow_hyphen_values = true)]
    pub eye: Option<DVec3>,
    /// Look at the volume from a side of the patient, framed: anterior (the face, superior up),
    /// posterior, left, right (superior up), superior, inferior (anterior up). Where the file has no
    /// orientation (NRRD space, NIfTI qform/sform, DICOM ImageOrientationPatient) the world axes
    /// are read as LPS: anterior looks from -y, posterior +y, left +x, right -x, superior +z,
    /// inferior -z. Not with --eye; --target, --up, --fov-y still apply
    #[arg(long, value_name = "NAME", value_parser = view_preset, conflicts_with = "eye")]
    pub view: Option<ViewPreset>,
    /// Point the camera looks at [default: the centre of what is framed; with --eye the centre of
    /// the volume]
    #[arg(long, value_name = "X,Y,Z", value_parser = args::vec3, allow_hyphen_values = true)]
    pub target: Option<DVec3>,
    /// Camera up direction [default: 0,0,1 (world up is +z)]
    #[arg(long, value_name = "X,Y,Z", value_parser = args::vec3, allow_hyphen_values = true)]
    pub up: Option<DVec3>,
    /// Vertical field of view in degrees [default: 35]
    #[arg(long = "fov-y", value_name = "DEG")]
    pub fov_y: Option<f64>,
    /// Direct-light shading model [default: blinn-phong]
    #[arg(long, value_enum)]
    pub shading: Option<ShadingArg>,
    /// Output variable: color (8-bit sRGB PNG) or depth, normal, hit, occlusion (A, 0 = open),
    /// bent-normal, ibl (E for albedo 1, before exposure) as PFM, 0 where there is no hit
    /// [default: color]
    #[arg(long, value_enum)]
    pub aov: Option<AovArg>,
    /// Output file [default: isowall.png for color, isowall-AOV.pfm otherwise]
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// Which renderer [default: gpu]
    #[arg(long, value_enum)]
    pub renderer: Option<RendererKind>,
    /// The most bytes the volume may take as float32 (4 a voxel), checked from the file's header
    /// before it is read [default: 2 GiB, and for the GPU renderer at most the GPU's largest
    /// storage binding]
    #[arg(long, value_name = "BYTES")]
    pub max_volume_bytes: Option<u64>,
    #[command(flatten)]
    pub raw: args::RawVolumeArgs,
    /// Render through the brick cache (DESIGN.md "Large volumes") with a pool of this many MiB of
    /// GPU memory: an OME-Zarr store is read brick by brick (never whole, so it may be larger
    /// than memory), any other volume is loaded whole and cut into a pyramid. Every pixel is
    /// rendered with the bricks it reads resident at level 0 (ray-guided rounds: each frame
    /// marks the bricks its rays read, the missing ones are loaded and the frame rendered
    /// again), so the picture is the whole volume's picture; where the pool cannot hold the
    /// bricks of the whole view's rays, the picture is finished in passes over screen regions
    /// [default: off: the volume is uploaded whole]
    #[arg(long = "gpu-budget-mb", value_name = "MIB")]
    pub gpu_budget_mb: Option<u64>,
    /// With --gpu-budget-mb: the most MiB of decoded bricks held in memory (least recently used
    /// evicted first) [default: twice --gpu-budget-mb]
    #[arg(long = "host-budget-mb", value_name = "MIB", requires = "gpu_budget_mb")]
    pub host_budget_mb: Option<u64>,
    /// Ambient-occlusion rays per pixel per frame, 0..=1024; 0 turns AO off [default: 0]
    #[arg(long = "ao-samples", value_name = "N", value_parser = clap::value_parser!(u32).range(0..=1024))]
    pub ao_samples: Option<u32>,
    /// AO radius in world units, or `unbounded` (to the volume's box) [default: 8 voxels of the
    /// largest spacing]
    #[arg(long = "ao-radius", value_name = "R|unbounded", value_parser = ao_radius)]
    pub ao_radius: Option<AoRadius>,
    /// AO method [default: ours]
    #[arg(long = "ao-method", value_enum)]
    pub ao_method: Option<AoMethodArg>,
    /// The 2D point set of ours' AO directions [default: sobol]
    #[arg(long = "ao-sequence", value_enum)]
    pub ao_sequence: Option<AoSequenceArg>,
    /// Ambient/image-based lighting [default: none]
    #[arg(long, value_enum)]
    pub ibl: Option<IblArg>,
    /// Environment for IBL: `sky` (built-in procedural HDR sky), FILE.hdr (equirectangular), or a
    /// directory with six faces px nx py ny pz nz (.png or .hdr) [default: sky]
    #[arg(long, value_name = "sky|FILE.hdr|DIR")]
    pub env: Option<String>,
    /// Frames to accumulate, each with a fresh decorrelation of the AO pattern [default: 1]
    #[arg(long, value_name = "K")]
    pub frames: Option<u32>,
    /// Seed mixed into every pixel's sample pattern (renders are reproducible) [default: 0]
    #[arg(long, value_name = "S")]
    pub seed: Option<u32>,
    /// Exposure: linear colour is multiplied by it before the sRGB transfer [default: 0.6]
    #[arg(long, value_name = "X")]
    pub exposure: Option<f64>,
    /// The edge-aware spatial filter (a-trous, guided by depth, normal and the occlusion
    /// estimate's variance) of the occlusion and IBL terms; it needs AO samples [default: off]
    #[arg(long, value_enum)]
    pub denoise: Option<DenoiseArg>,
}

impl RenderArgs {}

/// Loads the volume named by `--volume` (or the default) and the iso value to use, within the
/// default [`VolumeLimit`].
pub fn load_volume(spec: Option<&str>, raw: Option<&RawSpec>, iso: Option<f64>) -> Result<(Volume, f64)> {
    load_volume_within(spec, raw, (iso, "--iso"), &VolumeLimit::default())
}

/// The most a node's volume may take: `configured` (`--max-volume-bytes`, `[volume] max_bytes`;
/// else the default) and, for the GPU renderer, the adapter's largest storage binding, the
/// tighter of the two. Asking the adapter opens no device.
pub fn volume_limit(configured: Option<(u64, &str)>, gpu: bool) -> Result<VolumeLimit> {
    let mut limit = match configured {
        Some((bytes, source)) => VolumeLimit::new(bytes, source),
        None => VolumeLimit::default(),
    };
    if gpu {
        let (adapter, bytes) = isowall_render::gpu::adapter_storage_limit()?;
        limit =
            limit.min(VolumeLimit::new(bytes, format!("the largest storage binding of the GPU '{adapter}'")));
    }
    Ok(limit)
}

/// [`load_volume`] within `limit`, checked from the file's header before any voxel is read. `iso`
/// is the value given, if any, and where it was given (`--iso`, `[volume] iso`), for messages: a
/// value outside the data's range is refused ([`isowall_volume::check_iso`]).
pub fn load_volume_within(
    spec: Option<&str>,
    raw: Option<&RawSpec>,
    iso: (Option<f64>, &str),
    limit: &VolumeLimit,
) -> Result<(Volume, f64)> {
    load_volume_step_within(spec, raw, iso, 0, limit)
}

/// The whole volume of a wall config (`[volume]`: source, raw layout, iso) within `limit`, as a
/// screen-space node loads it; errors name the config.
pub fn load_wall_volume(config: &WallConfig, limit: &VolumeLimit) -> Result<(Volume, f64)> {
    let raw = config.raw_spec().map_err(|e| anyhow!("{}: {e}", config.path.display()))?;
    let iso_from = wall_iso_from(config);
    load_volume_within(Some(&config.volume_source()), raw.as_ref(), (config.volume.iso, &iso_from), limit)
}

/// Where a wall's iso comes from, as its errors name it (the config file's `[volume] iso`).
pub fn wall_iso_from(config: &WallConfig) -> String {
    format!("{}: [volume] iso", config.path.display())
}

/// [`load_volume_within`] of time step `step`.
pub fn load_volume_step_within(
    spec: Option<&str>,
    raw: Option<&RawSpec>,
    (iso, iso_from): (Option<f64>, &str),
    step: usize,
    limit: &VolumeLimit,
) -> Result<(Volume, f64)> {
    let source: VolumeSource = match spec {
        Some(s) => s.parse()?,
        None => VolumeSource::default_engine(),
    };
    let start = Instant::now();
    tracing::info!(volume = %source, step, "loading volume");
    let bar = crate::progress::spinner(format!("loading volume {source}"));
    let volume =
        source.load_step_within(raw, step, limit).with_context(|| format!("cannot load volume {source}"));
    bar.finish_and_clear();
    let volume = volume?;
    let (lo, hi) = volume.value_range();
    let d = volume.dims();
    tracing::info!(
        volume = %source, dims = ?d, spacing = ?volume.spacing().to_array(), range = ?(lo, hi),
        ms = start.elapsed().as_secs_f64() * 1e3, "volume ready"
    );
    let chosen = source.checked_iso(iso, (lo, hi)).map_err(|e| anyhow!("{iso_from} {e} ({source})"))?;
    if iso.or(source.natural_iso()).is_none() {
        tracing::warn!(
            "no {iso_from} given for {source}: using {chosen}, the middle of the data range [{lo}, {hi}]"
        );
    }
    Ok((volume, chosen))
}

pub fn run(a: &RenderArgs) -> Result<()> {
    // Where the image goes, checked before anything is loaded or rendered.
    let aov: Aov = a.aov.map(Aov::from).unwrap_or_default();
    let out = a.out.clone().unwrap_or_else(|| match aov {
        Aov::Color => PathBuf::from("isowall.png"),
        other => PathBuf::from(format!("isowall-{}.pfm", other.name())),
    });
    output::check_aov_path(aov, &out).context("--out")?;
    if let Some(folder) = out.parent().filter(|p| !p.as_os_str().is_empty() && !p.is_dir()) {
        bail!("--out {}: the folder {} does not exist", out.display(), folder.display());
    }
    let raw = a.raw.spec()?;
    let spec = match (&a.volume, &a.series) {
        (v, None) => v.clone(),
        (Some(v), Some(uid)) => Some(v.parse::<VolumeSource>()?.with_series(Some(uid))?.to_string()),
        (None, Some(_)) => bail!("--series needs --volume (a DICOM folder or one file of it)"),
    };
    let gpu = a.renderer.unwrap_or_default() == RendererKind::Gpu;
    let budgets = match a.gpu_budget_mb {
        Some(_) if !gpu => {
            bail!("--gpu-budget-mb is the GPU renderer's (the reference renderer reads the volume whole)")
        }
        Some(mb) => Some(budgets_from_flags(mb, a.host_budget_mb, None)?),
        None => None,
    };
    // Held whole, the volume must fit one storage binding; bricked, only the default limit on
    // what is loaded whole applies (a store is never loaded whole).
    let limit =
        volume_limit(a.max_volume_bytes.map(|b| (b, "--max-volume-bytes")), gpu && budgets.is_none())?;
    let loaded = match budgets {
        Some(budgets) => Loaded::Bricked(
            BrickedVolume::open(spec.as_deref(), raw.as_ref(), (a.iso, "--iso"), a.step, &limit)?,
            budgets,
        ),
        None => {
            let (volume, iso) =
                load_volume_step_within(spec.as_deref(), raw.as_ref(), (a.iso, "--iso"), a.step, &limit)?;
            Loaded::Whole(volume, iso)
        }
    };
    let (iso, name, (box_min, box_max), orientation, fit) = match &loaded {
        Loaded::Whole(v, iso) => {
            (*iso, v.name.clone(), (v.box_min(), v.box_max()), v.orientation(), object_box(v, *iso))
        }
        Loaded::Bricked(b, _) => (b.iso, b.name.clone(), (b.box_min, b.box_max), b.orientation, b.fit),
    };
    let (w, h) = a.size.unwrap_or((800, 600));
    tracing::info!(
        framed = ?(fit.0.to_array(), fit.1.to_array()),
        volume = ?(box_min.to_array(), box_max.to_array()),
        orientation = orientation.map(|o| o.code()).unwrap_or_else(|| "none".into()),
        "the object's box at the iso"
    );
    let framing = Camera::framing_view(fit, a.view, orientation, w, h);
    let centre = 0.5 * (box_min + box_max);
    let camera = match a.eye {
        None => Camera {
            target: a.target.unwrap_or(framing.target),
            up: a.up.unwrap_or(framing.up),
            fov_y_deg: a.fov_y.unwrap_or(framing.fov_y_deg),
            ..framing
        },
        Some(eye) => Camera {
            eye,
            target: a.target.unwrap_or(centre),
            up: a.up.unwrap_or(DVec3::Z),
            fov_y_deg: a.fov_y.unwrap_or(framing.fov_y_deg),
        },
    };
    camera.validate().context("bad camera")?;
    let view = View::whole(camera, w, h);
    let mut settings = RenderSettings::new(iso);
    if let Some(s) = a.shading {
        settings.shading = match s {
            ShadingArg::Lambert => Shading::Lambert,
            ShadingArg::BlinnPhong => Shading::BlinnPhong,
        };
    }
    if let Some(n) = a.ao_samples {
        settings.ao.samples = n;
    }
    if let Some(r) = a.ao_radius {
        settings.ao.radius = r;
    }
    if let Some(m) = a.ao_method {
        settings.ao.method = match m {
            AoMethodArg::Ours => AoMethod::Ours,
            AoMethodArg::Seed => AoMethod::Seed,
        };
    }
    if let Some(q) = a.ao_sequence {
        settings.ao.sequence = q.into();
    }
    if let Some(i) = a.ibl {
        settings.ao.ibl = i.into();
    }
    settings.ao.seed = a.seed.unwrap_or(0);
    settings.denoise = a.denoise.map(Denoise::from).unwrap_or_default();
    if settings.denoise.is_on() && settings.ao.samples == 0 {
        tracing::warn!("--denoise on filters nothing without --ao-samples");
    }
    settings.exposure = match a.exposure {
        Some(x) if x.is_finite() && x >= 0.0 => x,
        Some(x) => bail!("--exposure {x} must be a finite number >= 0"),
        None => DEFAULT_EXPOSURE,
    };
    let frames = a.frames.unwrap_or(1);
    if !(1..=isowall_render::gpu::MAX_FRAMES).contains(&frames) {
        bail!("--frames {frames} is outside 1..={}", isowall_render::gpu::MAX_FRAMES);
    }
    let env: Option<Environment> = if settings.ibl_needs_environment() {
        let src: EnvSource = a.env.as_deref().unwrap_or("sky").parse().context("--env")?;
        Some(Environment::from_source(&src).context("cannot load the environment")?)
    } else {
        if a.env.is_some() {
            tracing::warn!("--env is ignored with --ibl none");
        }
        None
    };

    let start = Instant::now();
    // Bricked volumes are the GPU renderer's only (the reference renderer was refused above).
    let (frame, label): (Frame, String) = match (loaded, a.renderer.unwrap_or_default()) {
        (Loaded::Bricked(bricked, budgets), _) => {
            let gpu = GpuRenderer::new()?;
            let genv = env.as_ref().map(|e| gpu.upload_environment(e)).transpose()?;
            let mut bricked = BrickedOnGpu::new(&gpu, bricked, budgets)?;
            let r = bricked.render_converged(&gpu, &view, &settings, genv.as_ref(), frames)?;
            let c = r.converged;
            (
                c.frame,
                format!(
                    "gpu '{}', {:.1} ms on the GPU; bricks: {} ray-guided round(s) in {} pass(es), at most {} read at level 0 in one, {} uploaded, a pool of {} slots in {:.1} MiB, host cache peak {:.1} MiB",
                    gpu.adapter_name(),
                    c.gpu_time.as_secs_f64() * 1e3,
                    c.rounds,
                    c.passes,
                    c.most_wanted,
                    r.uploads,
                    r.slots,
                    r.gpu_bytes as f64 / 1048576.0,
                    r.host_peak_bytes as f64 / 1048576.0
                ),
            )
        }
        (Loaded::Whole(volume, _), RendererKind::Gpu) => {
            let gpu = GpuRenderer::new()?;
            let gv = gpu.upload(&volume)?;
            let genv = env.as_ref().map(|e| gpu.upload_environment(e)).transpose()?;
            // Frames accumulate only with AO or image-based light: then each is reported.
            let accumulates = settings.ao.samples > 0 || settings.ao.ibl != IblMethod::None;
            let mut progress = (frames > 1 && accumulates).then(|| Counted::frames(frames, &volume.name));
            let mut report = progress.as_mut().map(|p| move |k: u32| p.done(k));
            let on_frame = report.as_mut().map(|r| r as &mut dyn FnMut(u32));
            let r =
                gpu.render_accumulated_reporting(&gv, &view, &settings, genv.as_ref(), frames, on_frame)?;
            drop(progress);
            (
                r.frame,
                format!("gpu '{}', {:.1} ms on the GPU", gpu.adapter_name(), r.gpu_time.as_secs_f64() * 1e3),
            )
        }
        (Loaded::Whole(volume, _), RendererKind::Reference) => {
            let mut progress = (frames > 1).then(|| Counted::frames(frames, &volume.name));
            let mut report = progress.as_mut().map(|p| move |k: u32| p.done(k));
            let on_frame = report.as_mut().map(|r| r as &mut dyn FnMut(u32));
            let mut frame = reference::render_accumulated_reporting(
                &volume,
                &view,
                &settings,
                env.as_ref(),
                frames,
                on_frame,
            );
            drop(progress);
            if settings.denoise.is_on() {
                denoise_reference(&mut frame, &view, &settings, frames);
            }
            (frame, "reference".to_string())
        }
    };
    output::write_aov(&frame, aov, &out).with_context(|| format!("cannot write {}", out.display()))?;
    if frame.hit_count() == 0 {
        // The data reaches the iso (checked above), so the surface exists: it is out of the
        // view, or thinner than a pixel of it (a sheet edge-on, a far or tiny object).
        eprintln!(
            "isowalld: warning: no pixel of the {w}x{h} picture hit the surface at iso {iso}: it is out of \
             the view or thinner than a pixel here (try a larger --size, a closer --eye, or the default camera)"
        );
    }
    let hits = frame.hit_count() as f64 / frame.pixel_count() as f64 * 100.0;
    println!(
        "wrote {} ({} {w}x{h}, {}, iso {iso}; {label}, {:.0} ms in all; {:.1} trilinear fetches/pixel, {hits:.1}% of pixels hit)",
        out.display(),
        aov.name(),
        name,
        start.elapsed().as_secs_f64() * 1e3,
        frame.fetches_per_pixel(),
    );
    Ok(())
}

/// The volume `render` draws: held whole (with its iso), or through the brick cache (with its
/// budgets).
enum Loaded {
    Whole(Volume, f64),
    Bricked(BrickedVolume, BrickBudgets),
}

/// The box a default camera frames: the object's at `iso` at block resolution
/// ([`BlockMinMax::object_box`]), or the volume's where no block reaches `iso`.
pub fn object_box(volume: &Volume, iso: f64) -> (DVec3, DVec3) {
    BlockMinMax::new(volume, BlockMinMax::DEFAULT_BLOCK)
        .object_box(iso, volume.dims(), volume.origin(), volume.spacing())
        .unwrap_or((volume.box_min(), volume.box_max()))
}

/// The filter's CPU twin on a reference frame: occlusion and IBL filtered, the colour's IBL part
/// replaced (colour = exposure (direct + albedo E), so the new E enters by its difference).
fn denoise_reference(frame: &mut Frame, view: &View, s: &RenderSettings, frames: u32) {
    let samples = s.ao.samples as u64 * frames as u64;
    let (occlusion, ibl) = isowall_render::denoise::filter(&isowall_render::denoise::Input {
        view,
        hit: &frame.hit,
        depth: &frame.depth,
        normal: &frame.normal,
        occlusion: &frame.occlusion,
        ibl: &frame.ibl,
        samples,
        pixel_samples: None,
    });
    for (i, new) in ibl.iter().enumerate() {
        if frame.hit[i] {
            let old = frame.ibl[i];
            for (c, colour) in frame.color[i].iter_mut().enumerate() {
                *colour += (s.exposure * s.material.albedo[c]) as f32 * (new[c] - old[c]);
            }
        }
    }
    frame.occlusion = occlusion;
    frame.ibl = ibl;
}
