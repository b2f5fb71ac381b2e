//! A volume rendered through the brick cache (DESIGN.md "Large volumes"): an OME-Zarr store read
//! brick by brick, or any other volume loaded whole and cut into a pyramid, within a GPU budget
//! (the pool, `--gpu-budget-mb`) and a host budget (decoded bricks, `--host-budget-mb`).
//!
//! `isowalld render` with a GPU budget waits for every brick its still frame wants at level 0
//! before it renders, so what it writes is the whole volume's picture (tests/gpu_bricks.rs in the
//! render crate holds the two equal bit for bit).

use crate::progress::Counted;
use anyhow::{anyhow, bail, Context, Result};
use glam::DVec3;
use isowall_model::{RenderSettings, View};
use isowall_render::gpu::{BrickPool, GpuRenderer};
use isowall_render::Frame;
use isowall_volume::brick_cache::{
    wanted_bricks, BrickSource, HostBrickCache, InCorePyramid, ViewFootprint, DEFAULT_BRICK_CELLS,
};
use isowall_volume::io::ome_zarr::{is_zarr, OmeZarr};
use isowall_volume::io::{RawSpec, VolumeLimit};
use isowall_volume::{BlockMinMax, Orientation, VolumeSource};

/// The budgets of a bricked volume, in bytes.
#[derive(Clone, Copy, Debug)]
pub struct Budgets {
    pub gpu: u64,
    pub host: u64,
}

impl Budgets {
    /// From the flags' MiB; the host budget defaults to twice the GPU's (a brick evicted from
    /// the pool is read again from memory, not from the store).
    pub fn from_mb(gpu_mb: u64, host_mb: Option<u64>) -> Result<Budgets> {
        let mb = |v: u64, flag: &str| {
            v.checked_mul(1 << 20)
                .filter(|&b| b > 0)
                .ok_or_else(|| anyhow!("{flag} {v}: 1 MiB or more is needed"))
        };
        let gpu = mb(gpu_mb, "--gpu-budget-mb")?;
        let host = mb(host_mb.unwrap_or(gpu_mb.saturating_mul(2)), "--host-budget-mb")?;
        Ok(Budgets { gpu, host })
    }
}

/// A volume opened for the brick cache, with what a camera needs to frame it.
pub struct BrickedVolume {
    pub source: Box<dyn BrickSource>,
    pub iso: f64,
    pub name: String,
    pub box_min: DVec3,
    pub box_max: DVec3,
    /// The object's box at the iso, at brick resolution (the volume's where unknown).
    pub fit: (DVec3, DVec3),
    pub orientation: Option<Orientation>,
}

impl BrickedVolume {
    /// Opens `spec` at time step `step`: a store's metadata and per-brick min/max only (no
    /// voxel), or any other volume loaded whole within `limit` and cut into a pyramid.
    pub fn open(
        spec: Option<&str>,
        raw: Option<&RawSpec>,
        (iso, iso_from): (Option<f64>, &str),
        step: usize,
        limit: &VolumeLimit,
    ) -> Result<BrickedVolume> {
        let source: VolumeSource = match spec {
            Some(s) => s.parse()?,
            None => VolumeSource::default_engine(),
        };
        let store = match &source {
            VolumeSource::File(p) if is_zarr(p) => Some(p.clone()),
            _ => None,
        };
        let (bricks, orientation): (Box<dyn BrickSource>, _) = match store {
            Some(path) => {
                let store = OmeZarr::open(&path)?;
                let orientation = store.patient_axes().and_then(|p| p.orientation());
                (Box::new(store.into_bricks(step)?), orientation)
            }
            None => {
                let (volume, _) =
                    crate::render::load_volume_step_within(spec, raw, (iso, iso_from), step, limit)?;
                let orientation = volume.orientation();
                (Box::new(InCorePyramid::new(volume, DEFAULT_BRICK_CELLS)?), orientation)
            }
        };
        let layout = bricks.layout();
        let l0 = &layout.levels[0];
        let box_min = l0.origin;
        let last = DVec3::new(l0.dims[0] as f64, l0.dims[1] as f64, l0.dims[2] as f64) - 1.0;
        let box_max = l0.origin + last * l0.spacing;
        let range = bricks.ranges(0).map(|r| {
            r.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), m| (a.min(m[0]), b.max(m[1])))
        });
        let iso = match (iso, range) {
            (Some(v), Some(r)) => {
                source.checked_iso(Some(v), r).map_err(|e| anyhow!("{iso_from} {e} ({source})"))?
            }
            (Some(v), None) => v,
            (None, Some(r)) => {
                let chosen = source.checked_iso(None, r).map_err(|e| anyhow!("{iso_from} {e} ({source})"))?;
                if source.natural_iso().is_none() {
                    tracing::warn!("no {iso_from} given for {source}: using {chosen}, the middle of the data range");
                }
                chosen
            }
            (None, None) => bail!(
                "{source}: the store has no per-brick min/max (another program wrote it), so the data's range is unknown: give {iso_from}"
            ),
        };
        let fit = bricks
            .ranges(0)
            .and_then(|r| {
                let blocks = BlockMinMax { block: layout.cells, counts: l0.counts, minmax: r.to_vec() };
                blocks.object_box(iso, l0.dims, l0.origin, l0.spacing)
            })
            .unwrap_or((box_min, box_max));
        let name = bricks.name().to_string();
        Ok(BrickedVolume { source: bricks, iso, name, box_min, box_max, fit, orientation })
    }
}

/// What [`render_converged`] did besides the frame.
pub struct BrickedRender {
    pub frame: Frame,
    pub gpu_time: std::time::Duration,
    /// Bricks the still frame wanted, the pool's slots, bricks uploaded.
    pub wanted: usize,
    pub slots: usize,
    pub uploads: u64,
    pub gpu_bytes: u64,
    pub host_peak_bytes: u64,
}

/// Renders the still frame of `view` once every brick it wants is resident at level 0: the
/// whole volume's picture. Refused, saying what budget would do, where the still frame's set is
/// larger than the pool (finishing it in passes is not built yet).
pub fn render_converged(
    gpu: &GpuRenderer,
    volume: &BrickedVolume,
    budgets: Budgets,
    view: &View,
    settings: &RenderSettings,
    env: Option<&isowall_render::gpu::GpuEnvironment>,
    frames: u32,
) -> Result<BrickedRender> {
    let source = volume.source.as_ref();
    let layout = source.layout();
    let mut cache =
        HostBrickCache::new(budgets.host, layout).map_err(|e| anyhow!("--host-budget-mb: {e}"))?;
    let mut pool =
        BrickPool::new(&gpu.ctx, &gpu.perf(), source, &mut cache, budgets.gpu).context("--gpu-budget-mb")?;
    let c = &view.camera;
    let pixel_angle = 2.0 * (c.fov_y_deg.to_radians() / 2.0).tan() / f64::from(view.full.1.max(1));
    let wanted =
        wanted_bricks(source, volume.iso as f32, &ViewFootprint { eye: c.eye, pixel_angle, still: true });
    let free = pool.slots() - layout.bricks(layout.coarsest());
    if wanted.len() > free {
        let needed = pool.gpu_bytes() + (wanted.len() - free) as u64 * layout.brick_bytes();
        bail!(
            "{}: the still frame wants {} bricks at level 0 and the pool holds {free} beside the coarsest level: \
             a frame larger than the pool is not finished in passes yet; give --gpu-budget-mb {} or more",
            volume.name,
            wanted.len(),
            needed.div_ceil(1 << 20)
        );
    }
    let mut bar = Counted::of("isowalld render", "brick", wanted.len() as u64, &volume.name);
    let mut done = 0;
    for chunk in wanted.chunks(64) {
        let r = pool.refine(&gpu.ctx, source, &mut cache, &wanted[..done + chunk.len()], u64::MAX)?;
        done += chunk.len();
        bar.done_of(r.resident as u64);
    }
    drop(bar);
    let r = pool.refine(&gpu.ctx, source, &mut cache, &wanted, u64::MAX)?;
    if !r.complete() {
        bail!("{}: {} of {} wanted bricks are resident ({r:?})", volume.name, r.resident, r.wanted);
    }
    gpu.prepare(pool.volume())?;
    let rendered = gpu.render_accumulated(pool.volume(), view, settings, env, frames)?;
    Ok(BrickedRender {
        frame: rendered.frame,
        gpu_time: rendered.gpu_time,
        wanted: wanted.len(),
        slots: pool.slots(),
        uploads: pool.stats().uploads,
        gpu_bytes: pool.gpu_bytes(),
        host_peak_bytes: cache.stats().peak_bytes,
    })
}
