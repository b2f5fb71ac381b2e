//! `isowalld bench stream`: a volume through the brick cache as a viewer meets it. Opens the
//! volume (a store's metadata and min/max only), draws the first picture from what is resident,
//! refines the still view to level 0 with capped uploads a frame, orbits (each frame's bricks at
//! the level their pixel footprint asks, uploads capped), stops and refines to level 0 again.
//! Prints the times, uploads per frame, the pool's hit rate, the passes and the peak memory, and
//! ends with one line `stream: first X s, converged Y s after stop, peak gpu G' MB, peak host H' MB`.

use super::stats::median;
use crate::args;
use crate::bricked::{budgets_from_flags, BrickedOnGpu, BrickedVolume};
use anyhow::Result;
use clap::Args;
use isowall_model::cli_args;
use isowall_model::{Camera, RenderSettings, View};
use isowall_render::gpu::GpuRenderer;
use isowall_volume::io::VolumeLimit;
use std::time::Instant;

#[derive(Args)]
pub struct StreamArgs {
    /// The volume (as for `render --volume`; an OME-Zarr store is read brick by brick)
    #[arg(long, value_name = "PATH|procedural:NAME[:N]")]
    pub volume: Option<String>,
    /// Iso value [default: as `render` chooses it]
    #[arg(long, value_name = "V", allow_negative_numbers = true)]
    pub iso: Option<f64>,
    /// Image size
    #[arg(long, default_value = "512x512", value_parser = args::size)]
    pub size: (u32, u32),
    /// The brick pool's GPU memory, MiB
    #[arg(long = "gpu-budget-mb", value_name = "MIB")]
    pub gpu_budget_mb: u64,
    /// Decoded bricks held in memory, MiB [default: twice --gpu-budget-mb]
    #[arg(long = "host-budget-mb", value_name = "MIB")]
    pub host_budget_mb: Option<u64>,
    /// The most MiB uploaded into the pool a frame (at least one brick), so that moving frames
    /// keep their rate [default: 1/16 of the GPU budget]
    #[arg(long = "upload-mb-per-frame", value_name = "MIB")]
    pub upload_mb_per_frame: Option<f64>,
    /// AO samples per pixel per frame
    #[arg(long = "ao-samples", value_parser = cli_args::ao_samples, default_value_t = 0)]
    pub ao_samples: u32,
    /// Orbit frames between the two still views
    #[arg(long, default_value_t = 24)]
    pub frames: u32,
    /// Degrees the camera turns a frame while orbiting
    #[arg(long, value_parser = cli_args::degrees, default_value_t = 3.0, allow_negative_numbers = true)]
    pub degrees: f64,
}

/// The process's peak resident memory (VmHWM), bytes; 0 where /proc does not say.
fn peak_rss() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            let line = s.lines().find(|l| l.starts_with("VmHWM:"))?.to_string();
            line.split_whitespace().nth(1)?.parse::<u64>().ok()
        })
        .map_or(0, |kb| kb * 1024)
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / 1048576.0
}

pub fn run(a: &StreamArgs) -> Result<()> {
    let budgets = budgets_from_flags(a.gpu_budget_mb, a.host_budget_mb, a.upload_mb_per_frame)?;
    let (w, h) = a.size;
    let gpu = GpuRenderer::new()?;
    gpu.prepare_bricked()?;
    let baseline = peak_rss();
    println!(
        "stream: GPU '{}', {w}x{h}, budgets: gpu {} MiB, host {} MiB; process baseline {:.1} MiB (GPU open, kernels compiled)",
        gpu.adapter_name(),
        mib(budgets.gpu),
        mib(budgets.host),
        mib(baseline)
    );

    // Open: the store's metadata and per-brick min/max; the pool with the coarsest level.
    let opened = Instant::now();
    let volume =
        BrickedVolume::open(a.volume.as_deref(), None, (a.iso, "--iso"), 0, &VolumeLimit::default())?;
    let mut b = BrickedOnGpu::new(&gpu, volume, budgets)?;
    let layout = b.volume.source.layout().clone();
    let t_open = opened.elapsed().as_secs_f64();
    let cap = budgets.upload_per_frame;
    let l0 = &layout.levels[0];
    println!(
        "stream: {} {}x{}x{} in {} levels, bricks of {} cells ({:.2} MiB), {} at level 0; a pool of {} slots; uploads capped at {:.1} MiB a frame",
        b.volume.name,
        l0.dims[0],
        l0.dims[1],
        l0.dims[2],
        layout.levels.len(),
        layout.cells,
        mib(layout.brick_bytes()),
        layout.bricks(0),
        b.pool.slots(),
        mib(cap)
    );
    let mut settings = RenderSettings::new(b.volume.iso);
    settings.ao.samples = a.ao_samples;
    let camera = Camera::framing_view(b.volume.fit, None, b.volume.orientation, w, h);
    let mut view = View::whole(camera, w, h);

    // One frame: a capped round of uploads for what the view wants, then the picture.
    let frame = |b: &mut BrickedOnGpu, view: &View, still: bool| -> Result<_> {
        let r = b.refine(&gpu, std::slice::from_ref(view), &settings, still)?;
        let rendered = gpu.render_accumulated(b.pool.volume(), view, &settings, None, 1)?;
        Ok((r, rendered.gpu_time.as_secs_f64() * 1e3))
    };

    let (first, first_ms) = frame(&mut b, &view, false)?;
    let t_first = opened.elapsed().as_secs_f64();
    println!(
        "stream: first picture {t_first:.2} s after opening (the store and the pool {t_open:.2} s, the frame {first_ms:.0} ms on the GPU; {} bricks uploaded, {} of the moving view's {} resident)",
        first.uploaded, first.resident, first.wanted
    );

    // Finish the still view at level 0: ray-guided rounds, uploads uncapped (the camera is still),
    // in passes where the rays' bricks outgrow the pool.
    let converge = |b: &mut BrickedOnGpu, view: &View, what: &str| -> Result<f64> {
        let start = Instant::now();
        let c = b.render_converged(&gpu, view, &settings, None, 1)?.converged;
        let t = start.elapsed().as_secs_f64();
        println!(
            "stream: {what}: level 0 everywhere the rays read in {t:.2} s ({:.2} s of it rendering, {:.2} s loading bricks): {} ray-guided rounds in {} pass(es), at most {} bricks read in one",
            c.gpu_time.as_secs_f64(),
            c.loading.as_secs_f64(),
            c.rounds,
            c.passes,
            c.most_wanted
        );
        Ok(t)
    };
    converge(&mut b, &view, "still at the start")?;

    // Orbit: each frame's bricks at the level its footprint asks, uploads capped.
    let before = b.pool.stats();
    let mut uploads = Vec::new();
    let mut ms = Vec::new();
    let mut resident_share = Vec::new();
    for _ in 0..a.frames {
        view.camera = view.camera.yawed(a.degrees);
        let (r, t) = frame(&mut b, &view, false)?;
        uploads.push(mib(r.upload_bytes));
        ms.push(t);
        resident_share.push(r.resident as f64 / r.wanted.max(1) as f64);
    }
    let after = b.pool.stats();
    let touched = (after.hits - before.hits) + (after.uploads - before.uploads);
    println!(
        "stream: orbit of {} frames at {} degrees: uploads a frame median {:.2} MiB, most {:.2} MiB; GPU ms a frame median {:.1}; the moving views' bricks resident median {:.0}%; pool hit rate {:.1}%",
        a.frames,
        a.degrees,
        median(uploads.clone()),
        uploads.iter().copied().fold(0.0, f64::max),
        median(ms.clone()),
        100.0 * median(resident_share.clone()),
        100.0 * (after.hits - before.hits) as f64 / touched.max(1) as f64
    );

    let t_stop = converge(&mut b, &view, "stopped")?;
    let hc = b.cache.stats();
    let peak_host = peak_rss();
    println!(
        "stream: pool {:.1} MiB ({} uploads, {} evictions); host cache peak {:.1} MiB ({} reads, {} hits, {} evictions); process peak {:.1} MiB, {:.1} MiB over the baseline",
        mib(b.pool.gpu_bytes()),
        after.uploads,
        b.pool.stats().evictions,
        mib(hc.peak_bytes),
        hc.misses,
        hc.hits,
        hc.evictions,
        mib(peak_host),
        mib(peak_host.saturating_sub(baseline))
    );
    println!(
        "stream: first {t_first:.2} s, converged {t_stop:.2} s after stop, peak gpu {:.1} MB, peak host {:.1} MB",
        b.pool.gpu_bytes() as f64 / 1e6,
        peak_host as f64 / 1e6
    );
    Ok(())
}
