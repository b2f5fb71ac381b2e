//! Object space on a wall node (`[wall] mode = "object"`): the I/O around the model's
//! [`ObjectMachine`] (`isowall_model::object_machine`: the views of each frame, the brick maps,
//! compositing with its caps and deadline, and the messages for the controller live there; the
//! geometry in `isowall_model::bricks`, the pixels' rules in `isowall_model::composite`):
//!
//! - set-up ([`load_brick`]): a streaming pass over the volume gives the block min/max of the whole
//!   (one z-slice resident at a time), every node computes the same split from it at the config's
//!   iso, and this node reads only its brick and halo ([`isowall_volume::region`] says how each
//!   format is read). Resident afterwards: the brick and halo as f32 plus the whole volume's block
//!   grid (8 bytes per block); both are logged and the voxel bytes reported to the controller.
//! - each frame ([`ObjectNode`]): the machine's views are rendered; the rectangles it encodes go to
//!   their tiles' owners on the pixel streams of [`isowall_net::pixels`] (one QUIC stream per frame
//!   per peer, node-to-node with mutual TLS, every wait bounded by the wall's deadline); peers'
//!   pixels go to the machine as they arrive, and a peer that breaks its rules has its connection
//!   closed with the machine's reason. When a frame's tiles are composited (everything in, or the
//!   compositing deadline passed: the peers it went without are logged when they change) the
//!   session reports Composited and Ready, and swaps as in screen space.
//! - a frame whose AO radius exceeds the halo (the config's radius sized it) is rendered with the
//!   radius bounded by the halo, and `seed` AO with `ours`, with a warning (the config check refuses
//!   both up front).
//! - a node dies ([`isowall_model::adoption`] has the rules): the controller's brick map gives its
//!   brick to nobody, and pending frames stop waiting for it; the survivor it chose gets
//!   `LoadBrick` and reads that brick and halo with the same partial read as at start-up
//!   ([`read_brick`], from the [`BrickPlan`] kept since start-up) on a blocking task, the render
//!   thread uploads it as a second volume between frames ([`spawn_load`]), and the node answers
//!   `BrickLoaded`. An adopted brick is dropped (its GPU volume freed) at the first frame whose map
//!   gives it to another node. `--adopt-delay-ms` (hidden) delays the read, so tests can watch
//!   frames run while it loads.
//! - a time-varying volume ([`brick_steps`]): the split is made on the first step (its occupancy
//!   at the iso) and kept for every step. The node's brick and halo of each step are read ahead
//!   on a loader thread within `[volume] cache_bytes` (a [`StepCache`] of region reads), one
//!   pass over each step giving the region and the step's block grid of the whole volume (every
//!   node marches the whole box with the step's own empty-space skipping, as the single render
//!   does). The render thread writes the frame's step into the brick's GPU buffers; a step not
//!   loaded in time is waited for within the bound of screen space and reported (`StepLate`)
//!   with the composited frame. A dead node's brick is not adopted: the survivors answer
//!   `BrickFailed` with the reason and the wall composites without it until its node is back.

use crate::pixel_links::PixelLinks;
use crate::render_thread::{BrickData, CanvasJob, JobResult, RenderHandle, StepsOf, TileResult};
use anyhow::{anyhow, Context, Result};
use isowall_model::adoption::AdoptionError;
use isowall_model::bricks::{self, Brick, Occupancy};
use isowall_model::composite::{Composited, PixelForm, TileCanvas};
use isowall_model::config::WallConfig;
use isowall_model::messages::Message;
use isowall_model::object_machine::{BrickGeometry, ObjectMachine, ObjectOutput};
use isowall_model::render_plan::RenderPlan;
use isowall_model::wire::{Continuity, FrameSpec};
use isowall_model::{Camera, RenderSettings};
use isowall_net::pixels::PeerPixelsIn;
use isowall_net::Identity;
use isowall_render::gpu::ObjectSpace;
use isowall_volume::io::{RawSpec, VolumeLimit};
use isowall_volume::region::VolumeStream;
use isowall_volume::steps::StepCache;
use isowall_volume::{BlockMinMax, VolumeInfo, VolumeSource, VoxelRange};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// This node's brick, as set up.
pub struct BrickSetup {
    pub data: BrickData,
    pub halo: [usize; 3],
    pub plan: Arc<BrickPlan>,
}

/// What start-up computed, kept to read any brick later (one adopted from a dead node).
pub struct BrickPlan {
    pub source: VolumeSource,
    pub raw: Option<RawSpec>,
    pub info: VolumeInfo,
    /// The whole volume's block grid (every brick's GPU volume gets it).
    pub blocks: BlockMinMax,
    pub split: Vec<Brick>,
    pub halo: [usize; 3],
    /// What a brick and its halo may hold (`[volume] max_bytes` and the GPU's binding limit).
    pub limit: VolumeLimit,
}

/// Reads brick `index` and its halo: the partial read of start-up, from `stream` (or the plan's
/// source opened again).
pub fn read_brick(plan: &BrickPlan, index: usize, stream: Option<&VolumeStream>) -> Result<BrickData> {
    let start = Instant::now();
    let source = &plan.source;
    let opened;
    let stream = match stream {
        Some(s) => s,
        None => {
            opened =
                source.stream(plan.raw.as_ref()).with_context(|| format!("cannot open volume {source}"))?;
            &opened
        }
    };
    let info = &plan.info;
    let brick = plan.split.get(index).ok_or_else(|| anyhow!("no brick {index} in the split"))?;
    let (lo, hi) = brick.data_range(plan.halo, info.dims);
    let extent = (0..3).map(|a| (hi[a] + 1 - lo[a]).to_string()).collect::<Vec<_>>().join("x");
    let voxels = brick.data_samples(plan.halo, info.dims) as u64;
    plan.limit
        .check(voxels, &format!("brick {index} and its halo ({extent} samples of {source})"))
        .map_err(|e| anyhow!("{e}"))?;
    let region =
        stream.read_region(&VoxelRange { lo, hi }).with_context(|| format!("cannot read volume {source}"))?;
    let (owned_min, owned_max) = brick.owned_planes(info.dims, info.origin, info.spacing);
    tracing::info!(
        volume = %source,
        brick = index,
        bricks = plan.split.len(),
        owned = ?(brick.lo, brick.hi),
        halo = ?plan.halo,
        data = ?(lo, hi),
        occupied_blocks = brick.occupied_blocks,
        resident_volume_bytes = region.resident_bytes(),
        block_grid_bytes = plan.blocks.minmax.len() * 8,
        whole_volume_bytes = info.dims.iter().product::<usize>() * 4,
        partial_reads = stream.partial(),
        ms = start.elapsed().as_secs_f64() * 1e3,
        "object space: brick ready"
    );
    Ok(BrickData {
        index,
        region,
        info: info.clone(),
        blocks: plan.blocks.clone(),
        object: ObjectSpace { data_offset: lo, owned_min, owned_max },
    })
}

/// Reads this node's brick and halo (module notes). `iso` is the config's (or the volume's
/// natural) iso value; `None`: the middle of the data range, from the block grid.
pub fn load_brick(
    config: &WallConfig,
    node: &str,
    raw: Option<&RawSpec>,
    limit: VolumeLimit,
) -> Result<BrickSetup> {
    let start = Instant::now();
    let source: VolumeSource = config.volume_source().parse()?;
    let bricking = Arc::new(crate::progress::Bricking::new(node, &source.to_string()));
    let observer = bricking.clone();
    let stream = source
        .stream(raw)
        .with_context(|| format!("cannot open volume {source}"))?
        .on_progress(move |p| observer.report(p));
    let info = stream.info().clone();
    let blocks = stream
        .block_minmax(BlockMinMax::DEFAULT_BLOCK)
        .with_context(|| format!("cannot read volume {source}"))?;
    let iso = source
        .checked_iso(config.volume.iso, blocks.value_range())
        .map_err(|e| anyhow!("{}: [volume] iso {e} ({source})", config.path.display()))?;
    let occ = Occupancy::from_minmax(blocks.block, blocks.counts, &blocks.minmax, iso);
    let n = config.nodes.len();
    let index = config
        .nodes
        .iter()
        .position(|x| x.name == node)
        .ok_or_else(|| anyhow!("no node '{node}' in the wall config"))?;
    let split = bricks::split(&occ, info.dims, info.spacing, n).map_err(|e| anyhow!("{source}: {e}"))?;
    let settings = config.render_settings(iso);
    let halo = bricks::halo_voxels(&settings, info.spacing).map_err(|e| anyhow!("[render] {e}"))?;
    let plan = Arc::new(BrickPlan { source, raw: raw.cloned(), info, blocks, split, halo, limit });
    let data = read_brick(&plan, index, Some(&stream));
    bricking.finish();
    let data = data?;
    tracing::debug!(ms = start.elapsed().as_secs_f64() * 1e3, "object space: set-up done");
    Ok(BrickSetup { data, halo, plan })
}

/// A time-varying volume (module notes): this node's brick and halo of every step, read ahead
/// by a [`StepCache`] within `cache_bytes`, each step a region read of the step with the step's
/// block grid ([`VolumeSource::step_regions`]). The region is the same for every step, so
/// the volume limit [`read_brick`] checked at start-up holds for all. `None` for a volume
/// without time steps.
pub fn brick_steps(setup: &BrickSetup, cache_bytes: usize) -> Result<Option<StepsOf>> {
    let plan = setup.plan.clone();
    let source = &plan.source;
    let steps = source.time_steps().with_context(|| format!("volume {source}"))?;
    if steps < 2 {
        return Ok(None);
    }
    let index = setup.data.index;
    let brick = plan.split.get(index).ok_or_else(|| anyhow!("no brick {index} in the split"))?;
    let (lo, hi) = brick.data_range(plan.halo, plan.info.dims);
    let range = VoxelRange { lo, hi };
    tracing::info!(volume = %source, steps, cache_bytes, brick = index, "time-varying volume: bricks per step");
    let name = source.to_string();
    // A 4-D file's steps from one stream kept open: a pass inflates it once, not once per step.
    let mut regions = source
        .step_regions(plan.raw.as_ref(), range, plan.blocks.block, plan.info.clone())
        .with_context(|| format!("volume {source}"))?;
    let load = move |k| regions.read(k);
    let cache = StepCache::with_loader(steps, cache_bytes, name, Box::new(load))?;
    Ok(Some(StepsOf::Brick {
        index,
        info: setup.data.info.clone(),
        object: setup.data.object.clone(),
        cache,
    }))
}

/// An adoption's outcome ([`spawn_load`]): the brick, its owned box and bytes, or why not.
pub struct LoadDone {
    pub brick: u64,
    /// The brick's volume bytes, or why not.
    pub result: Result<u64, String>,
    pub took: Duration,
}

/// Loads brick `brick` beside the node's own (module notes): reads it on a blocking task, then
/// has the render thread upload it after the jobs already queued; the outcome goes to `done`.
pub fn spawn_load(
    plan: Arc<BrickPlan>,
    brick: u64,
    index: usize,
    renderer: RenderHandle,
    done: tokio::sync::mpsc::UnboundedSender<LoadDone>,
    delay: Duration,
) {
    tokio::spawn(async move {
        tokio::time::sleep(delay).await;
        // The load time reported leaves out the injected delay.
        let t0 = Instant::now();
        let result = async {
            let p = plan.clone();
            let data = tokio::task::spawn_blocking(move || read_brick(&p, index, None))
                .await
                .map_err(|e| anyhow!("the reading task failed: {e}"))??;
            let bytes = data.region.resident_bytes() as u64;
            renderer.load(data).await?;
            Ok::<_, anyhow::Error>(bytes)
        }
        .await
        .map_err(|e| format!("{e:#}"));
        let _ = done.send(LoadDone { brick, result, took: t0.elapsed() });
    });
}

/// A composited frame: its tiles for the swap and the controller's `Composited`.
pub struct Done {
    pub job: JobResult,
    /// For the controller before Ready: object space's `Composited`; a balanced wall's
    /// `RectCosts` and `Composited`.
    pub reports: Vec<Message>,
    /// Where the wall filters the composited tile: the canvases the render thread filters and
    /// composes into the tiles' images (`job.tiles` is empty until then).
    pub canvas: Option<CanvasJob>,
}

/// The node's object-space side: the model's [`ObjectMachine`] and what it asks for (the pixel
/// streams of [`isowall_net::pixels`], brick reads, the render thread's uploads).
pub struct ObjectNode {
    machine: ObjectMachine,
    plan: Arc<BrickPlan>,
    load_tx: tokio::sync::mpsc::UnboundedSender<LoadDone>,
    /// Fault injection (`--adopt-delay-ms`): a wait before reading an adopted brick.
    pub adopt_delay: Duration,
    /// The pixel streams to and from the peers.
    links: PixelLinks,
    /// The machine's clock.
    epoch: Instant,
    /// A time-varying volume: the frames whose step was late here (the render thread's
    /// report), until they are composited.
    step_late: HashMap<u64, (u32, Duration)>,
    /// Where the wall filters the composited tile (`[render] denoise = "on"`): the guard band
    /// every tile's canvas has (the filter's reach), and each frame's camera and settings until
    /// it is composited.
    filter_guard: Option<u32>,
    cameras: HashMap<u64, (Camera, RenderSettings)>,
}

impl ObjectNode {
    /// The node's object-space state; adoptions' outcomes go to `load_tx` (the session hands them
    /// to [`ObjectNode::load_done`]).
    pub fn new(
        config: &WallConfig,
        name: &str,
        setup: &BrickSetup,
        load_tx: tokio::sync::mpsc::UnboundedSender<LoadDone>,
    ) -> Result<ObjectNode> {
        let plan = &setup.plan;
        let geometry = BrickGeometry {
            owned: plan.split.iter().map(|b| b.owned_box(plan.info.origin, plan.info.spacing)).collect(),
            own: setup.data.index,
            own_bytes: setup.data.region.resident_bytes() as u64,
            spacing: plan.info.spacing,
            halo: setup.halo,
        };
        // Shares travel in shading form and tiles are composited over their canvases; the filter
        // then runs on the GPU of the tile's owner (frames whose settings turn it off are composed
        // unfiltered from the same shares).
        let filter_guard = config.filters_composited().then(isowall_render::denoise::reach);
        let mut machine = ObjectMachine::new(config, name, geometry, filter_guard);
        let steps = plan.source.time_steps().map_err(|e| anyhow!("volume {}: {e}", plan.source))?;
        if steps > 1 {
            machine.refuse_adoptions(format!(
                "{}: a time-varying volume's brick is not adopted (the adopter would have to load it \
                 for every step); the wall composites without it until its node is back",
                plan.source
            ));
        }
        let links = PixelLinks::new(config, machine.receivers())?;
        Ok(ObjectNode {
            machine,
            plan: setup.plan.clone(),
            load_tx,
            adopt_delay: Duration::ZERO,
            links,
            epoch: Instant::now(),
            step_late: HashMap::new(),
            filter_guard,
            cameras: HashMap::new(),
        })
    }

    /// The form this node's pixels travel in (every node of the wall the same).
    pub fn form(&self) -> PixelForm {
        self.machine.form()
    }

    fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    /// The longest pixel stream a peer may send this node.
    pub fn max_pixels_bytes(&self) -> usize {
        self.machine.max_pixels_bytes()
    }

    /// The wall's deadline: each wait for a peer's stream ends there.
    pub fn deadline(&self) -> Duration {
        self.links.deadline()
    }

    /// A new controller session: its frame ids start afresh.
    pub fn reset(&mut self) {
        self.machine.reset();
        self.cameras.clear();
        self.step_late.clear();
    }

    /// Opens the endpoint this node connects to its peers from (inside the async runtime).
    pub fn open_endpoint(&mut self, identity: &Identity) -> Result<()> {
        self.links.open_endpoint(identity)
    }

    /// A frame state arrived from the controller.
    pub fn announce(&mut self, frame_id: u64) {
        self.machine.announce(frame_id);
    }

    /// What this node renders of a frame (the model's [`ObjectMachine::plan`]): its warnings
    /// logged, the adopted bricks it no longer holds dropped from the GPU, early pixels that
    /// broke the rules answered.
    pub fn plan(
        &mut self,
        spec: &FrameSpec,
        accumulate_frame: u32,
        continuity: Continuity,
        renderer: &RenderHandle,
    ) -> RenderPlan {
        let frame_id = spec.frame_id;
        let p = self.machine.plan(self.now(), spec, accumulate_frame, continuity);
        if let Some(w) = &p.warning {
            tracing::warn!(frame_id, "object space: {w}");
        }
        if self.filter_guard.is_some() {
            self.cameras.insert(frame_id, (spec.camera, p.plan.settings));
        }
        for &b in &p.unload {
            tracing::info!(frame_id, brick = b, "object space: dropping adopted brick (its home is back)");
            let _ = renderer.unload(b);
        }
        for b in &p.not_loaded {
            tracing::error!(
                frame_id,
                brick = b,
                "object space: the map gives this node a brick it has not loaded"
            );
        }
        let done = self.execute(p.outputs);
        debug_assert!(done.is_empty(), "a frame starting completes nothing");
        p.plan
    }

    /// Carries out the machine's outputs; returns the composited frames.
    fn execute(&mut self, outputs: Vec<ObjectOutput>) -> Vec<Done> {
        let mut done = Vec::new();
        for out in self.links.execute(outputs) {
            match out {
                ObjectOutput::Composited(c) => {
                    let report = self.machine.report(self.now(), &c);
                    self.links.note_missing(&c);
                    let (job, canvas) = self.finish(c);
                    done.push(Done { job, reports: vec![report], canvas });
                }
                // Only `load` gives these, and handles them there.
                ObjectOutput::Send(_) | ObjectOutput::Load { .. } => {
                    tracing::error!("object space: an adoption's output outside an adoption")
                }
                // The links carried them out.
                ObjectOutput::SendPixels { .. }
                | ObjectOutput::ClosePeer { .. }
                | ObjectOutput::Dropped { .. }
                | ObjectOutput::Reconnect { .. } => {}
            }
        }
        done
    }

    /// The frame's result, and in shading form the canvases to filter and compose first.
    fn finish(&mut self, c: Composited) -> (JobResult, Option<CanvasJob>) {
        let id = c.frame_id;
        let render_time = self.machine.render_time(id);
        // This node's step was late for this frame (older frames are no longer composited).
        let step_late = self.step_late.remove(&id);
        self.step_late.retain(|&f, _| f > id);
        let frame = self.cameras.remove(&id);
        self.cameras.retain(|&f, _| f > id);
        let (tiles, canvas) = match (self.filter_guard, frame) {
            (Some(guard), Some((camera, settings))) => {
                let tiles = c
                    .tiles
                    .into_iter()
                    .filter_map(|t| {
                        let view = self.machine.config().tile_view(camera, &t.name)?;
                        Some((t.name, view, t.shading))
                    })
                    .collect();
                (Vec::new(), Some(CanvasJob { frame_id: id, tiles, settings, guard }))
            }
            // A frame this node did not start (none composites without the node's own render).
            (Some(_), None) => {
                tracing::error!(frame_id = id, "object space: a composited frame without its camera");
                (Vec::new(), None)
            }
            (None, _) => (c.tiles.into_iter().map(TileResult::from).collect(), None),
        };
        (JobResult { frame_id: id, tiles, render_time, step_late, surface: None }, canvas)
    }

    /// A brick map from the controller (`Message::Bricks`): the frames it completes, or the
    /// controller's protocol error.
    pub fn set_map(
        &mut self,
        from_frame: u64,
        holders: Vec<Option<String>>,
    ) -> Result<Vec<Done>, AdoptionError> {
        let (map, out) = self.machine.set_map(self.now(), from_frame, holders)?;
        tracing::info!(from_frame, holders = ?map.holders, "object space: brick map");
        Ok(self.execute(out))
    }

    /// `LoadBrick`: starts loading the brick beside this node's own (an answer comes through
    /// [`ObjectNode::load_done`]), or the answer to send at once.
    pub fn load(&mut self, brick: u64, renderer: &RenderHandle) -> Option<Message> {
        let mut answer = None;
        for out in self.machine.load(brick) {
            match out {
                ObjectOutput::Load { brick, index } => {
                    tracing::info!(brick, "object space: adopting a brick: loading it");
                    spawn_load(
                        self.plan.clone(),
                        brick,
                        index,
                        renderer.clone(),
                        self.load_tx.clone(),
                        self.adopt_delay,
                    );
                }
                ObjectOutput::Send(msg) => answer = Some(msg),
                other => {
                    self.execute(vec![other]);
                }
            }
        }
        answer
    }

    /// An adoption's outcome: the answer for the controller.
    pub fn load_done(&mut self, done: LoadDone) -> Message {
        let msg = self.machine.load_done(done.brick, done.result.clone(), done.took);
        match (&msg, done.result) {
            (Message::BrickLoaded { resident_bytes, .. }, _) => tracing::info!(
                brick = done.brick,
                ms = done.took.as_secs_f64() * 1e3,
                resident_volume_bytes = resident_bytes,
                "object space: adopted brick loaded"
            ),
            (Message::BrickFailed { reason, .. }, _) => {
                tracing::warn!(brick = done.brick, "object space: cannot adopt the brick: {reason}")
            }
            _ => {}
        }
        msg
    }

    /// This node's render of a frame is done: sends each peer its pixels, composites its own.
    pub fn local_done(&mut self, done: JobResult) -> Vec<Done> {
        let (id, t0) = (done.frame_id, Instant::now());
        if let Some(late) = done.step_late {
            self.step_late.insert(id, late);
        }
        let rendered = done.tiles.into_iter().map(TileCanvas::from).collect();
        let out = self.machine.local_done(self.now(), id, done.render_time, rendered);
        self.machine.add_work(id, t0.elapsed());
        self.execute(out)
    }

    /// A peer's pixels: the frames they complete (a violation closes the peer's connection).
    pub fn peer(&mut self, item: PeerPixelsIn) -> Vec<Done> {
        let (id, t0) = (item.pixels.frame_id, Instant::now());
        let link = item.connection.link();
        self.links.keep(item.connection);
        let out = self.machine.peer(self.now(), &item.cert, link, item.pixels);
        self.machine.add_work(id, t0.elapsed());
        self.execute(out)
    }

    /// When the next compositing deadline passes ([`ObjectNode::handle_timeout`]).
    pub fn next_timeout(&self) -> Option<tokio::time::Instant> {
        self.machine.poll_timeout().map(|t| tokio::time::Instant::from_std(self.epoch + t))
    }

    /// Frames whose compositing deadline passed: composited with what arrived.
    pub fn handle_timeout(&mut self) -> Vec<Done> {
        let out = self.machine.handle_timeout(self.now());
        self.execute(out)
    }
}

/// A composited tile as the render thread's result (shown and kept for snapshots).
impl From<TileCanvas> for TileResult {
    fn from(t: TileCanvas) -> TileResult {
        TileResult {
            name: t.name,
            width: t.width,
            height: t.height,
            rgb8: t.rgb8,
            depth: t.depth,
            shading: t.shading,
            fetches: 0,
        }
    }
}

/// A rendered rectangle as the model composites it.
impl From<TileResult> for TileCanvas {
    fn from(r: TileResult) -> TileCanvas {
        // What the render thread read back says the form: the shading AOVs, or the colour.
        let form = if r.shading.is_empty() { PixelForm::Colour } else { PixelForm::Shading };
        TileCanvas {
            name: r.name,
            width: r.width,
            height: r.height,
            form,
            depth: r.depth,
            rgb8: r.rgb8,
            shading: r.shading,
        }
    }
}
