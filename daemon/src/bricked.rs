//! A volume rendered through the brick cache (DESIGN.md "Large volumes"): an OME-Zarr store read
//! brick by brick, or any other volume loaded whole and cut into a pyramid, within a GPU budget
//! (the pool, `--gpu-budget-mb`) and a host budget (decoded bricks, `--host-budget-mb`).
//!
//! `isowalld render` with a GPU budget renders its still frame with every brick it reads at level
//! 0, found by ray-guided rounds (the kernels mark the bricks their rays read; the missing ones
//! are loaded and the frame rendered again), in screen regions where the pool cannot hold the
//! bricks of the whole view's rays, so what it writes is the whole volume's picture
//! (tests/gpu_bricks.rs in the render crate holds the two equal bit for bit).

use anyhow::{anyhow, bail, Context, Result};
use glam::DVec3;
use isowall_model::config::BrickBudgets;
use isowall_model::{RenderSettings, View};
use isowall_render::gpu::{wanted_by_views, BrickPool, Converged, GpuRenderer, Refinement};
use isowall_volume::brick_cache::{
    BrickKey, BrickSource, HostBrickCache, InCorePyramid, DEFAULT_BRICK_CELLS,
};
use isowall_volume::io::ome_zarr::{is_zarr, OmeZarr};
use isowall_volume::io::{RawSpec, VolumeLimit};
use isowall_volume::{Orientation, VolumeSource};

/// The brick cache's budgets from the flags (`--gpu-budget-mb`, `--host-budget-mb`,
/// `--upload-mb-per-frame`): the config's rule ([`BrickBudgets::from_mb`]), its errors naming the flag.
pub fn budgets_from_flags(gpu_mb: u64, host_mb: Option<u64>, upload_mb: Option<f64>) -> Result<BrickBudgets> {
    BrickBudgets::from_mb(gpu_mb, host_mb, upload_mb)
        .map_err(|e| anyhow!("--{} {}", e.field.replace('_', "-"), e.problem))
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
        let info = bricks.level0_info();
        let (box_min, box_max) = (info.box_min(), info.box_max());
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
            .level0_blocks()
            .and_then(|b| b.object_box(iso, info.dims, info.origin, info.spacing))
            .unwrap_or((box_min, box_max));
        let name = bricks.name().to_string();
        Ok(BrickedVolume { source: bricks, iso, name, box_min, box_max, fit, orientation })
    }
}

/// What [`BrickedOnGpu::render_converged`] did besides the frame.
pub struct BrickedRender {
    pub converged: Converged,
    pub slots: usize,
    pub uploads: u64,
    pub gpu_bytes: u64,
    pub host_peak_bytes: u64,
}

/// A bricked volume on the GPU: its host cache and pool within the budgets, the coarsest level
/// resident. The render thread of a wall node refines it each frame for the frame's views
/// ([`BrickedOnGpu::refine`]); `isowalld render` and `bench stream` also finish still frames
/// through it ([`BrickedOnGpu::render_converged`]).
pub struct BrickedOnGpu {
    pub volume: BrickedVolume,
    pub cache: HostBrickCache,
    pub pool: BrickPool,
    pub budgets: BrickBudgets,
    /// A still view's ray-guided refinement, where its footprint's set is larger than the pool.
    pub guide: RayGuide,
}

/// A wall node's still view refined by the bricks its rays read (ray-guided, as
/// [`GpuRenderer::render_converged`]'s rounds, one a frame): entered at the still view's first
/// frame where the bricks its footprint wants (every brick near the iso in the views' cones, to
/// the far side) are more than the pool holds beside its coarsest level; left when the camera
/// moves.
#[derive(Debug, Default)]
pub struct RayGuide {
    /// The still view is refined by what its rays read, not by its footprint.
    pub active: bool,
    /// The frame being rendered marks the bricks its rays read.
    marking: bool,
    /// The level-0 bricks the marked frames have read since the camera stopped (started over
    /// from the last frame's where they outgrow the pool).
    read: std::collections::BTreeSet<BrickKey>,
    /// The last marked frame's rays read more bricks than the pool holds.
    over_pool: bool,
    /// No more marks until the picture changes: the last marked frame read only resident bricks
    /// (level 0 wherever it read the volume), or it read more than the pool holds and the round
    /// after it could load nothing (the pool is full of what the rays read: each marked frame
    /// waits for the GPU, which a still wall need not pay for nothing).
    settled: bool,
}

/// What a marked frame told ([`BrickedOnGpu::after_frame`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GuidedFrame {
    pub read: usize,
    pub missing: usize,
    /// The bricks its rays read are more than the pool holds beside its coarsest level.
    pub over_pool: bool,
}

impl BrickedOnGpu {
    pub fn new(gpu: &GpuRenderer, volume: BrickedVolume, budgets: BrickBudgets) -> Result<BrickedOnGpu> {
        let source = volume.source.as_ref();
        let mut cache = HostBrickCache::new(budgets.host, source.layout())
            .map_err(|e| anyhow!("the host budget (--host-budget-mb, [volume] host_budget_mb): {e}"))?;
        let pool = BrickPool::new(&gpu.ctx, &gpu.perf(), source, &mut cache, budgets.gpu)
            .context("the GPU budget (--gpu-budget-mb, [volume] gpu_budget_mb)")?;
        Ok(BrickedOnGpu { volume, cache, pool, budgets, guide: RayGuide::default() })
    }

    /// One frame's round of uploads, at most the budget's uploads a frame: the bricks `views`
    /// want (level 0 where `still`, else each brick's footprint level), nearest first. A still
    /// view whose footprint wants more bricks than the pool holds is refined by what its rays
    /// read instead ([`RayGuide`]): this frame then marks them, and [`BrickedOnGpu::after_frame`]
    /// reads the marks once it is rendered.
    pub fn refine(
        &mut self,
        gpu: &GpuRenderer,
        views: &[View],
        settings: &RenderSettings,
        still: bool,
    ) -> Result<Refinement> {
        let source = self.volume.source.as_ref();
        let cap = self.budgets.upload_per_frame;
        if !still {
            self.guide = RayGuide::default();
        }
        let wanted = if still && self.guide.active {
            // Nearest first, so that capped rounds fill the front of the view first.
            let eye = views.first().map_or(DVec3::ZERO, |v| v.camera.eye);
            let layout = self.pool.layout();
            let distance = |k: &BrickKey| {
                let (lo, hi) = layout.brick_box(*k);
                (0.5 * (lo + hi)).distance_squared(eye)
            };
            let mut read: Vec<BrickKey> = self.guide.read.iter().copied().collect();
            read.sort_by(|a, b| distance(a).total_cmp(&distance(b)));
            read
        } else {
            let wanted = wanted_by_views(source, views, settings, &gpu.perf(), still);
            // Known before any upload: this round still loads the footprint's nearest, and
            // marks what the rays read for the next.
            self.guide.active = still && wanted.len() > self.pool.free_slots();
            wanted
        };
        let r = self.pool.refine(&gpu.ctx, source, &mut self.cache, &wanted, cap)?;
        if self.guide.over_pool && r.uploaded == 0 {
            self.guide.settled = true;
        }
        self.guide.marking = still && self.guide.active && !self.guide.settled;
        if self.guide.marking {
            self.pool.clear_marks(&gpu.ctx);
        }
        Ok(r)
    }

    /// After a frame for which [`BrickedOnGpu::refine`] turned the marks on: reads the bricks its
    /// rays read (waiting for the GPU) and keeps them for the next frame's round; `None` where
    /// the frame marked nothing.
    pub fn after_frame(&mut self, gpu: &GpuRenderer, iso: f64) -> Result<Option<GuidedFrame>> {
        if !std::mem::take(&mut self.guide.marking) {
            return Ok(None);
        }
        let marked = self.pool.read_marks(&gpu.ctx, iso as f32);
        self.pool.stop_marking();
        let marked = marked?;
        let missing = marked.iter().filter(|k| !self.pool.holds(**k)).count();
        let free = self.pool.free_slots();
        let g = &mut self.guide;
        g.settled = missing == 0;
        g.over_pool = marked.len() > free;
        g.read.extend(marked.iter().copied());
        if g.read.len() > free {
            g.read = marked.iter().copied().collect();
        }
        Ok(Some(GuidedFrame { read: marked.len(), missing, over_pool: g.over_pool }))
    }

    /// The GPU budget the still view that left `over` wanted bricks out needs, in MiB.
    pub fn needed_mib(&self, over: usize) -> u64 {
        (self.pool.gpu_bytes() + over as u64 * self.pool.layout().brick_bytes()).div_ceil(1 << 20)
    }

    /// Renders the still frame of `view` with every brick it reads at level 0, in as many passes
    /// as the pool needs ([`GpuRenderer::render_converged`]): the whole volume's picture.
    pub fn render_converged(
        &mut self,
        gpu: &GpuRenderer,
        view: &View,
        settings: &RenderSettings,
        env: Option<&isowall_render::gpu::GpuEnvironment>,
        frames: u32,
    ) -> Result<BrickedRender> {
        let source = self.volume.source.as_ref();
        let converged =
            gpu.render_converged(&mut self.pool, source, &mut self.cache, view, settings, env, frames)?;
        Ok(BrickedRender {
            converged,
            slots: self.pool.slots(),
            uploads: self.pool.stats().uploads,
            gpu_bytes: self.pool.gpu_bytes(),
            host_peak_bytes: self.cache.stats().peak_bytes,
        })
    }
}
