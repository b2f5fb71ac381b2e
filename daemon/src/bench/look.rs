//! `isowalld bench look`: whether the default look shows shape. AO exists to show shape, so in the
//! default AO render a surface point in a crease must look darker than an open one lit the same
//! way. Per scene and IBL method this renders the default settings (AO on, converged), bins the
//! surface pixels by N.L (the key light's cosine on the normal facing the viewer) and compares, in
//! each bin, the mean luminance of occluded pixels (A >= [`OCCLUDED`]) with the open ones
//! (A <= [`OPEN`]): the darkness is 1 - occluded / open, averaged over the bins (each weighted by
//! the smaller of its two counts), both of linear luminance and of the luminance shown (sRGB).
//! `--before` measures the look the defaults had before this rule chose them, in the same run;
//! `--out DIR` writes each render as a PNG.

use super::stats::{scene_file, scene_spec};
use crate::args;
use crate::render::{load_volume, IblArg};
use anyhow::{anyhow, Result};
use clap::Args;
use isowall_model::cli_args;
use isowall_model::render_state::linear_to_srgb;
use isowall_model::{AoRadius, Camera, IblMethod, RenderSettings, View};
use isowall_render::environment::Environment;
use isowall_render::gpu::GpuRenderer;
use isowall_render::{output, Frame};
use std::path::PathBuf;

/// Occlusion at or above which a pixel counts as occluded.
pub const OCCLUDED: f32 = 0.3;
/// Occlusion at or below which a pixel counts as open.
pub const OPEN: f32 = 0.05;
/// N.L bins over [0, 1] (back-lit pixels go to the first).
const BINS: usize = 10;
/// Pixels a bin needs on each side to count.
const MIN_PER_SIDE: usize = 8;
/// The darkness the default look must reach (printed beside each result).
pub const GOAL: f64 = 0.30;

#[derive(Args)]
pub struct LookArgs {
    /// Scenes as VOLUME[@ISO], comma-separated (VOLUME as for `render --volume`; relative paths not
    /// in the working folder are looked for relative to the checkout)
    #[arg(
        long,
        default_value = "procedural:engine,../shared/data/ct-cranium.nrrd@300,../shared/data/mri-brainsmall.nrrd@40"
    )]
    pub scenes: String,
    /// Image size
    #[arg(long, default_value = "256x256", value_parser = args::size)]
    pub size: (u32, u32),
    /// AO samples per pixel per frame
    #[arg(long, value_parser = cli_args::ao_samples, default_value_t = 32)]
    pub samples: u32,
    /// Frames accumulated (samples x frames rays per pixel: the occlusion must be near converged
    /// for the bins to hold the pixels they should)
    #[arg(long, value_parser = args::accumulated_frames, default_value_t = 8)]
    pub frames: u32,
    /// IBL methods to measure, comma-separated
    #[arg(long, value_enum, value_delimiter = ',', default_value = "none,bent")]
    pub ibl: Vec<IblArg>,
    /// Also measure the look before these defaults (key light 0.9, ambient 0.15, AO radius 8
    /// voxels, exposure 1 or 0.6 with IBL), in the same run
    #[arg(long)]
    pub before: bool,
    /// Override the AO radius (world units, `unbounded`, or `Nvox` for N voxels of the largest
    /// spacing), to compare candidates
    #[arg(long, value_name = "R")]
    pub ao_radius: Option<String>,
    /// Override the key light's radiance (grey)
    #[arg(long, value_parser = cli_args::non_negative, value_name = "K")]
    pub key: Option<f64>,
    /// Override the constant ambient light (grey)
    #[arg(long, value_parser = cli_args::non_negative, value_name = "A")]
    pub ambient: Option<f64>,
    /// Override the exposure
    #[arg(long, value_parser = cli_args::non_negative, value_name = "X")]
    pub exposure: Option<f64>,
    /// Turn the default camera (`isowalld render`'s) by this many degrees about the world's up axis through its target
    #[arg(long, value_parser = cli_args::degrees, value_name = "DEG", default_value_t = 0.0, allow_negative_numbers = true)]
    pub yaw: f64,
    /// Write each render as DIR/look-SCENE-IBL[-before].png
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
}

/// How much darker occluded surface pixels look than open ones at the same N.L.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Darkness {
    /// 1 - occluded / open of linear luminance (Rec. 709 weights), averaged over the bins.
    pub linear: f64,
    /// The same of the luminance shown: each channel through the sRGB transfer first.
    pub shown: f64,
    /// Pixels counted on each side over the bins used.
    pub open: usize,
    pub occluded: usize,
    /// Bins with enough pixels on both sides.
    pub bins: usize,
}

/// Rec. 709 luminance weights.
fn luminance(c: [f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

/// The darkness of `frame` (every AOV of `view`'s rectangle, rendered with `settings`), or `None`
/// where no bin has [`MIN_PER_SIDE`] pixels on both sides.
pub fn darkness(frame: &Frame, view: &View, settings: &RenderSettings) -> Option<Darkness> {
    let basis = view.camera.basis();
    let light = settings.light.world_direction(basis.forward, basis.right, basis.up);
    // Per bin and side (0 open, 1 occluded): count, linear sum, shown sum.
    let mut sums = [[(0usize, 0.0f64, 0.0f64); 2]; BINS];
    for y in 0..frame.height {
        for x in 0..frame.width {
            let i = (y * frame.width + x) as usize;
            if !frame.hit[i] {
                continue;
            }
            let a = frame.occlusion[i];
            let side = if a <= OPEN {
                0
            } else if a >= OCCLUDED {
                1
            } else {
                continue;
            };
            let d = view.ray_dir(&basis, x, y);
            let n = glam::DVec3::from(frame.normal[i].map(f64::from));
            let n = if n.dot(d) > 0.0 { -n } else { n };
            let ndl = n.dot(light).clamp(0.0, 1.0);
            let bin = ((ndl * BINS as f64) as usize).min(BINS - 1);
            let c = frame.color[i].map(f64::from);
            let s = &mut sums[bin][side];
            s.0 += 1;
            s.1 += luminance(c);
            s.2 += luminance(c.map(linear_to_srgb));
        }
    }
    let (mut weight, mut linear, mut shown, mut open, mut occluded, mut bins) = (0.0, 0.0, 0.0, 0, 0, 0);
    for [o, c] in sums {
        if o.0 < MIN_PER_SIDE || c.0 < MIN_PER_SIDE || o.1 <= 0.0 || o.2 <= 0.0 {
            continue;
        }
        let w = o.0.min(c.0) as f64;
        linear += w * (1.0 - (c.1 / c.0 as f64) / (o.1 / o.0 as f64));
        shown += w * (1.0 - (c.2 / c.0 as f64) / (o.2 / o.0 as f64));
        weight += w;
        open += o.0;
        occluded += c.0;
        bins += 1;
    }
    (bins > 0).then(|| Darkness { linear: linear / weight, shown: shown / weight, open, occluded, bins })
}

/// The look the defaults had before: key light 0.9, ambient 0.15 (0.17 blue), AO radius 8 voxels
/// of the largest spacing, exposure 1 (0.6 with an IBL method).
fn earlier_look(s: &mut RenderSettings, largest_spacing: f64) {
    s.light.color = [0.9; 3];
    s.light.ambient = [0.15, 0.15, 0.17];
    s.ao.radius = AoRadius::World(8.0 * largest_spacing);
    s.exposure = if s.ibl_needs_environment() { 0.6 } else { 1.0 };
}

fn radius(arg: &str, largest_spacing: f64) -> Result<AoRadius> {
    if arg == "unbounded" {
        return Ok(AoRadius::Unbounded);
    }
    let (num, voxels) = match arg.strip_suffix("vox") {
        Some(n) => (n, true),
        None => (arg, false),
    };
    let r: f64 = num.parse().map_err(|_| anyhow!("--ao-radius '{arg}': a number, Nvox or unbounded"))?;
    if !(r.is_finite() && r > 0.0) {
        return Err(anyhow!("--ao-radius '{arg}' must be > 0"));
    }
    Ok(AoRadius::World(if voxels { r * largest_spacing } else { r }))
}

pub fn run(a: &LookArgs) -> Result<()> {
    let gpu = GpuRenderer::new()?;
    let (w, h) = a.size;
    let sky = gpu.upload_environment(&Environment::sky())?;
    let methods: Vec<IblMethod> = a.ibl.iter().map(|&i| i.into()).collect();
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).map_err(|e| anyhow!("--out {}: {e}", dir.display()))?;
    }
    println!(
        "# isowalld bench look: {w}x{h}, {} x {} AO samples, adapter '{}'; darkness = 1 - occluded/open \
         luminance at the same N.L (occluded A >= {OCCLUDED}, open A <= {OPEN}), goal >= {GOAL}",
        a.frames,
        a.samples,
        gpu.adapter_name()
    );
    println!("scene,look,ibl,radius,key,ambient,exposure,darkness_linear,darkness_shown,open_px,occluded_px,bins,hit_px,mean_a,mean_shown,clipped");
    let mut worst: Option<f64> = None;
    let mut unmeasured = Vec::new();
    for scene in a.scenes.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (spec, iso) = scene_spec(scene)?;
        let file = scene_file(spec).map_err(|e| anyhow!("{e}"))?;
        let (volume, iso) = load_volume(Some(&file), None, iso)?;
        let gv = gpu.upload(&volume)?;
        // The default camera of `isowalld render`: the surface's box, the orientation's side.
        let fit = crate::render::object_box(&volume, iso);
        let camera = Camera::framing_view(fit, None, volume.orientation(), w, h).yawed(a.yaw);
        let view = View::whole(camera, w, h);
        let spacing = volume.spacing().max_element();
        let key = super::stats::scene_key(spec);
        for &method in &methods {
            for before in [false, true].into_iter().filter(|&b| !b || a.before) {
                let mut s = RenderSettings::new(iso);
                s.ao.samples = a.samples;
                s.ao.ibl = method;
                if before {
                    earlier_look(&mut s, spacing);
                } else {
                    if let Some(r) = &a.ao_radius {
                        s.ao.radius = radius(r, spacing)?;
                    }
                    if let Some(k) = a.key {
                        s.light.color = [k; 3];
                    }
                    if let Some(am) = a.ambient {
                        s.light.ambient = [am; 3];
                    }
                    if let Some(x) = a.exposure {
                        s.exposure = x;
                    }
                }
                let env = (method != IblMethod::None).then_some(&sky);
                let frame = gpu.render_accumulated(&gv, &view, &s, env, a.frames)?.frame;
                let look = if before { "before" } else { "default" };
                let hits = frame.hit_count();
                let mean_a = frame
                    .occlusion
                    .iter()
                    .zip(&frame.hit)
                    .filter(|(_, &h)| h)
                    .map(|(&o, _)| o as f64)
                    .sum::<f64>()
                    / hits.max(1) as f64;
                let (shown_sum, clipped) = frame.color.iter().zip(&frame.hit).filter(|(_, &h)| h).fold(
                    (0.0, 0usize),
                    |(sum, n), (c, _)| {
                        let c = c.map(f64::from);
                        (sum + luminance(c.map(linear_to_srgb)), n + usize::from(c.iter().any(|&x| x >= 1.0)))
                    },
                );
                let mean_shown = shown_sum / hits.max(1) as f64;
                let clipped = clipped as f64 / hits.max(1) as f64;
                let r = match s.ao.radius_world(volume.spacing()) {
                    Some(r) => format!("{r:.2}"),
                    None => "unbounded".into(),
                };
                let d = darkness(&frame, &view, &s);
                let (lin, shown, o, c, b) = match d {
                    Some(d) => {
                        (format!("{:.3}", d.linear), format!("{:.3}", d.shown), d.open, d.occluded, d.bins)
                    }
                    None => ("-".into(), "-".into(), 0, 0, 0),
                };
                println!(
                    "{key},{look},{},{r},{:.2},{:.2},{:.2},{lin},{shown},{o},{c},{b},{hits},{mean_a:.4},{mean_shown:.3},{clipped:.3}",
                    method.name(),
                    s.light.color[1],
                    s.light.ambient[1],
                    s.exposure
                );
                match (before, d) {
                    (false, Some(d)) => worst = Some(worst.map_or(d.linear, |w: f64| w.min(d.linear))),
                    (false, None) => unmeasured.push(format!("{key} ({})", method.name())),
                    (true, _) => {}
                }
                if let Some(dir) = &a.out {
                    let suffix = if before { "-before" } else { "" };
                    let path = dir.join(format!("look-{key}-{}{suffix}.png", method.name()));
                    output::write_png(&frame, &path)?;
                }
            }
        }
    }
    let skipped = if unmeasured.is_empty() {
        String::new()
    } else {
        format!("; no pixels to compare in {}", unmeasured.join(", "))
    };
    match worst {
        Some(w) => println!(
            "look: darkness {w:.3} at worst over the scenes with the defaults ({}){skipped}",
            if w >= GOAL { "meets the goal" } else { "below the goal" }
        ),
        None => println!("look: nothing measured{skipped}"),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    /// A frame whose every pixel is a hit facing the camera, with the given occlusion and colour.
    fn frame_of(pixels: &[(f32, f32)], view: &View) -> Frame {
        let mut f = Frame::new(view.rect.width, view.rect.height);
        let basis = view.camera.basis();
        for (i, &(a, grey)) in pixels.iter().enumerate() {
            f.hit[i] = true;
            f.occlusion[i] = a;
            f.color[i] = [grey; 3];
            f.normal[i] = (-basis.forward).as_vec3().to_array();
        }
        f
    }

    fn view() -> View {
        let cam =
            Camera { eye: DVec3::new(0.0, -10.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 1.0 };
        View::whole(cam, 8, 4)
    }

    #[test]
    fn occluded_pixels_half_as_bright_are_half_as_dark_in_linear_light() {
        let v = view();
        let mut px = vec![(0.0, 0.6); 16];
        px.extend(vec![(0.5, 0.3); 16]);
        let d = darkness(&frame_of(&px, &v), &v, &RenderSettings::new(0.0)).unwrap();
        assert!((d.linear - 0.5).abs() < 1e-6, "{d:?}");
        // Shown through sRGB, half the light looks less than half as dark.
        assert!(d.shown < d.linear && d.shown > 0.2, "{d:?}");
        assert_eq!((d.open, d.occluded, d.bins), (16, 16, 1));
    }

    #[test]
    fn pixels_between_the_thresholds_and_thin_bins_do_not_count() {
        let v = view();
        // Only mid occlusion: nothing to compare.
        let d = darkness(&frame_of(&vec![(0.2, 0.5); 32], &v), &v, &RenderSettings::new(0.0));
        assert_eq!(d, None);
        // Too few occluded pixels.
        let mut px = vec![(0.0, 0.6); 24];
        px.extend(vec![(0.9, 0.1); MIN_PER_SIDE - 1]);
        assert_eq!(darkness(&frame_of(&px, &v), &v, &RenderSettings::new(0.0)), None);
    }

    #[test]
    fn radius_arguments() {
        assert_eq!(radius("unbounded", 1.5).unwrap(), AoRadius::Unbounded);
        assert_eq!(radius("12", 1.5).unwrap(), AoRadius::World(12.0));
        assert_eq!(radius("16vox", 1.5).unwrap(), AoRadius::World(24.0));
        assert!(radius("-1", 1.5).is_err() && radius("big", 1.5).is_err());
    }
}
