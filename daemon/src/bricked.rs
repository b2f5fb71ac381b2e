//! A volume rendered through the brick cache (DESIGN.md "Large volumes"): an OME-Zarr store read
//! brick by brick, or any other volume loaded whole and cut into a pyramid, within a GPU budget
//! (the pool, `--gpu-budget-mb`) and a host budget (decoded bricks, `--host-budget-mb`).
//!
//! `isowalld render` with a GPU budget renders its still frame with every brick it reads at level
//! 0, in screen regions where the pool cannot hold the whole view's bricks, so what it writes is
//! the whole volume's picture (tests/gpu_bricks.rs in the render crate holds the two equal bit
//! for bit).

use anyhow::{anyhow, bail, Context, Result};
use glam::DVec3;
use isowall_model::{RenderSettings, View};
use isowall_render::gpu::{BrickPool, Converged, GpuRenderer};
use isowall_volume::brick_cache::{BrickSource, HostBrickCache, InCorePyramid, DEFAULT_BRICK_CELLS};
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
        let (box_min, box_max) = (l0.origin, l0.box_max());
        let range = bricks.value_range();
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
    pub converged: Converged,
    pub slots: usize,
    pub uploads: u64,
    pub gpu_bytes: u64,
    pub host_peak_bytes: u64,
}

/// The host cache and the GPU pool of `volume` within `budgets`, the coarsest level resident.
pub fn open_cache(
    gpu: &GpuRenderer,
    volume: &BrickedVolume,
    budgets: Budgets,
) -> Result<(HostBrickCache, BrickPool)> {
    let source = volume.source.as_ref();
    let mut cache =
        HostBrickCache::new(budgets.host, source.layout()).map_err(|e| anyhow!("--host-budget-mb: {e}"))?;
    let pool =
        BrickPool::new(&gpu.ctx, &gpu.perf(), source, &mut cache, budgets.gpu).context("--gpu-budget-mb")?;
    Ok((cache, pool))
}

/// Renders the still frame of `view` with every brick it reads at level 0, in as many passes as
/// the pool needs ([`GpuRenderer::render_converged`]): the whole volume's picture.
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
    let (mut cache, mut pool) = open_cache(gpu, volume, budgets)?;
    let converged = gpu.render_converged(&mut pool, source, &mut cache, view, settings, env, frames)?;
    Ok(BrickedRender {
        converged,
        slots: pool.slots(),
        uploads: pool.stats().uploads,
        gpu_bytes: pool.gpu_bytes(),
        host_peak_bytes: cache.stats().peak_bytes,
    })
}
