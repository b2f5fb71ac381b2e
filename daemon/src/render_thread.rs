//! The render thread of a wall node: it alone owns the GPU device. It renders the node's tiles for
//! each frame state it is sent, on the GPU from start to finish: each tile has its resources made
//! once ([`TileTarget`]: remade on a resize or a change of internal scale), progressive
//! accumulation runs on the GPU while the state is unchanged (the frame index advances the sample
//! pattern; any change restarts the running sums), and the compose kernel writes the tile's
//! presentable image. Where the node presents in windows, it also owns their surfaces (created
//! from its own wgpu instance): the swap ([`RenderHandle::present`]) draws the tile's image of the
//! frame. Only what leaves the node is read back, through a small ring of staging buffers mapped
//! without stalling the next frame: per-frame counters, colour and depth of object-space shares,
//! and the images of a snapshot ([`RenderHandle::snapshot`]). A time-varying volume's frame shows
//! its own step ([`TimeSteps`]): the whole volume, or in object space the node's brick of it.
//! In object space the windows show the composited tiles, never a brick's view: a canvas the
//! render thread filtered and composed, or the image the node composited on the CPU, uploaded
//! ([`RenderHandle::show`]).

use crate::bricked::{BrickedOnGpu, BrickedVolume, RayGuide};
use crate::presenter::Shown;
use anyhow::{Context, Result};
use isowall_model::config::BrickBudgets;
use isowall_model::frame_controller::SurfaceLevels;
use isowall_model::render_plan::RenderPlan;
use isowall_model::wire::Continuity;
use isowall_model::{RenderSettings, View};
use isowall_render::environment::Environment;
use isowall_render::gpu::present::{Presented, TileSurface};
use isowall_render::gpu::tile::{Presentable, ReadKind, ShownImages};
use isowall_render::gpu::ObjectSpace;
use isowall_render::gpu::{CanvasFrame, FrameRead, GpuRenderer, ReadbackRing, TileFrame, TileTarget};
use isowall_volume::region::StepRegion;
use isowall_volume::steps::{StepCache, StepState};
use isowall_volume::{BlockMinMax, Volume, VolumeInfo};
use std::collections::VecDeque;
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

/// One frame to render: the views of the node's tiles, the settings, and where in the
/// progressive accumulation it stands (0 restarts it).
pub struct TileJob {
    /// What to render (the model's plan: `isowall_model::render_plan`). object space: `bricks`
    /// names the brick each view renders (a node renders an adopted brick beside its own,
    /// `object.rs`), and the pixels are read back in `share`'s form to travel to the tiles'
    /// owners; screen space: the one volume, and the frame stays on the GPU.
    pub plan: RenderPlan,
    /// The node's name where the operator asked the tiles to identify themselves: each tile's
    /// image shows it and the tile's name in its top-left corner (screen space).
    pub identify: Option<String>,
}

/// A tile's image of a frame: 8-bit sRGB, rows top to bottom. Where the frame stayed on the GPU
/// (screen space), `rgb8` and `depth` are empty: presentation draws from the GPU and snapshots
/// read the image when asked.
#[derive(Clone)]
pub struct TileResult {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub rgb8: Vec<u8>,
    /// Distance along the ray per pixel, `+inf` where nothing is hit (object space composites by it).
    pub depth: Vec<f32>,
    /// object space, shading form: per pixel the AOVs the tile's owner filters and composes
    /// (`isowall_render::gpu::TileOutput::shading`); empty otherwise.
    pub shading: Vec<[[f32; 4]; 4]>,
    /// The trilinear fetches its render took (0 where it was not rendered here).
    pub fetches: u64,
}

/// A tile's canvas: its shading, rows top to bottom.
pub type Canvas = Vec<[[f32; 4]; 4]>;

/// object space, where the wall filters the composited tile: the canvases of a frame's tiles
/// (each tile's rectangle grown by `guard`), filtered and composed on the GPU.
pub struct CanvasJob {
    pub frame_id: u64,
    /// Per tile: its name, its view (its own rectangle) and its canvas (shading, rows top to
    /// bottom, of the rectangle grown by `guard`).
    pub tiles: Vec<(String, View, Canvas)>,
    pub settings: RenderSettings,
    pub guard: u32,
}

/// What the render thread uploads: the whole volume (screen space), a brick and its halo (object
/// space, `object.rs` reads it), or a bricked volume's coarsest level, the rest refined frame by
/// frame where the node's views look (screen space with `[volume] gpu_budget_mb`).
pub enum RenderVolume {
    Whole(Volume),
    Brick(Box<BrickData>),
    /// Screen space through the brick cache: refined each frame for the views it renders.
    Bricked(Box<(BrickedVolume, BrickBudgets)>),
}

/// What the render thread uploads in object space.
pub struct BrickData {
    /// The brick's index in the split (= its home node's index in `[[nodes]]`).
    pub index: usize,
    pub region: Volume,
    pub info: VolumeInfo,
    pub blocks: BlockMinMax,
    pub object: ObjectSpace,
}

pub struct JobResult {
    pub frame_id: u64,
    pub tiles: Vec<TileResult>,
    pub render_time: Duration,
    /// The frame's time step was not loaded when the job came: the step rendered and how long
    /// the render thread waited for it (bounded by [`TimeSteps::wait`]).
    pub step_late: Option<(u32, Duration)>,
    /// A bricked volume: the frame's surface pixels and how many level 0 drew.
    pub surface: Option<SurfaceLevels>,
}

/// A time-varying volume on the render thread: its steps, loaded ahead by the cache's own loader
/// thread, and the longest a frame waits for a step that is not loaded yet before it renders the
/// step it has (and says so).
pub struct TimeSteps {
    pub cache: StepsOf,
    pub wait: Duration,
}

/// What a time step is on a node: the whole volume (screen space) or, in object space, the
/// node's own brick and halo with the step's block grid (`object.rs` makes the cache); the
/// brick keeps its GPU buffers from step to step, rewritten in place.
pub enum StepsOf {
    Volume(StepCache<Volume>),
    Brick {
        /// The brick's index in the split, and what its GPU volume needs besides a step's data.
        index: usize,
        info: VolumeInfo,
        object: ObjectSpace,
        cache: StepCache<StepRegion>,
    },
}

impl StepsOf {
    fn steps(&self) -> usize {
        match self {
            StepsOf::Volume(c) => c.steps(),
            StepsOf::Brick { cache, .. } => cache.steps(),
        }
    }
}

/// The frame's step `wanted` from `cache` where it is not the one `shown`: `Ok(Some(step))`
/// loaded, `Ok(None)` not loaded after waiting at most `wait`, `Err` why it cannot be, and
/// whether it was not loaded when asked for. `None`: the step shown is the one wanted.
#[allow(clippy::type_complexity)]
fn fetch<T>(
    cache: &StepCache<T>,
    wanted: u32,
    shown: u32,
    wait: Duration,
) -> Option<(Result<Option<Arc<T>>, String>, bool)> {
    // Asked even for the step shown: it makes the step current, so the ones after it load.
    let first = cache.get(wanted as usize);
    if wanted == shown {
        return None;
    }
    let late = matches!(first, StepState::Loading);
    let state = if late { cache.wait(wanted as usize, wait) } else { first };
    let state = match state {
        StepState::Ready(v) => Ok(Some(v)),
        StepState::Loading => Ok(None),
        StepState::Failed(e) => Err(e),
    };
    Some((state, late))
}

/// What the render thread holds of its first volume: uploaded whole (or a brick), or bricked.
enum Held {
    Volume(Box<isowall_render::gpu::GpuVolume>),
    Bricked(Box<BrickedOnGpu>),
}

/// The steps and which one is on the GPU.
struct StepsOnGpu {
    steps: TimeSteps,
    shown: u32,
}

/// How much lower than the rest of the process the render thread runs (a nice value).
pub const RENDER_NICENESS: i32 = 5;

/// Lowers this thread's priority by [`RENDER_NICENESS`] (Linux keeps a nice value per thread,
/// and the threads it starts inherit it: a software GPU's workers too). Rendering is the node's
/// bulk work; the network loop and the presenting thread keep the swap's time, and on a machine
/// whose cores the renders fill they must still wake when their time comes.
fn lower_priority() {
    let now = rustix::process::getpriority_process(None).unwrap_or(0);
    if let Err(e) = rustix::process::setpriority_process(None, now + RENDER_NICENESS) {
        tracing::debug!("cannot lower the render thread's priority: {e}");
    }
}

/// A window to present a tile in, with its size in pixels.
pub struct TileWindow {
    pub tile: String,
    pub window: Arc<winit::window::Window>,
    pub size: (u32, u32),
}

/// What the render thread is asked to do, in order.
enum Job {
    Render(Box<TileJob>),
    Window(WindowJob),
    /// The images of a frame's tiles (a snapshot), read back.
    Snapshot(u64, tokio::sync::oneshot::Sender<Result<Vec<TileResult>, String>>),
    /// object space: upload another brick (an adopted one); replies when it is on the GPU.
    Load(Box<BrickData>, tokio::sync::oneshot::Sender<Result<(), String>>),
    /// object space: drop a brick's volume (no longer this node's).
    Unload(usize),
    /// object space: filter and compose composited canvases; replies with the tiles' images.
    Canvas(Box<CanvasJob>, tokio::sync::oneshot::Sender<Result<Vec<TileResult>, String>>),
    /// object space: a frame's tiles composited on the CPU, for the windows.
    Show(u64, Vec<TileResult>),
}

/// The presentation jobs.
enum WindowJob {
    /// Create a surface per window (replacing any); replies with one line per surface.
    Attach(Vec<TileWindow>, mpsc::Sender<Result<Vec<String>, String>>),
    /// The swap: present `frame_id` on every surface at the instant given (now when `None`;
    /// `presenter::wait_until` first); replies with the frame presented.
    Present(u64, Option<Instant>, tokio::sync::oneshot::Sender<Shown>),
    Resize(String, u32, u32),
    Redraw(String),
}

/// A frame submitted to the GPU whose reads have not all arrived.
struct InFlight {
    frame_id: u64,
    step_late: Option<(u32, Duration)>,
    started: Instant,
    tiles: Vec<Option<TileResult>>,
    fetches: u64,
    hits: u64,
    level0_hits: u64,
}

/// A snapshot (or a frame's canvases) whose images have not all arrived.
struct SnapshotWait {
    frame_id: u64,
    reply: tokio::sync::oneshot::Sender<Result<Vec<TileResult>, String>>,
    tiles: Vec<Option<TileResult>>,
}

/// Staging buffers of the ring: enough for a few frames of a node's tiles in flight.
const READ_SLOTS: usize = 8;

/// The render thread's state between jobs.
/// A tile's identify label (`identify.rs`), drawn once for its text and the tile's size.
struct Label {
    text: String,
    tile: (u32, u32),
    size: (u32, u32),
    rgba: Vec<u8>,
}

struct RenderLoop {
    gpu: GpuRenderer,
    /// Identify labels drawn, one per tile.
    labels: Vec<Label>,
    /// By brick index (0: the whole volume in screen space); empty where the volume is bricked.
    volumes: Vec<(usize, isowall_render::gpu::GpuVolume)>,
    /// Screen space through the brick cache: its pool and host cache (DESIGN.md "Large volumes").
    bricked: Option<BrickedOnGpu>,
    /// The log has said how the still view's refinement ended (every brick it wants at level 0,
    /// or more than the pool holds); said again after the camera moves.
    still_said: bool,
    env: Option<isowall_render::gpu::GpuEnvironment>,
    targets: Vec<TileTarget>,
    /// object space: the composited tiles' resources, where the wall filters them.
    canvases: Vec<TileTarget>,
    /// object space: the images of tiles composited on the CPU, uploaded for the windows.
    shown: Vec<ShownImages>,
    /// The node renders bricks: its targets hold brick views, which no window shows.
    object_space: bool,
    surfaces: Vec<TileSurface>,
    /// The windows' presents wait for the swap's time with it.
    wait: crate::presenter::PreciseWait,
    ring: ReadbackRing<FrameRead>,
    frames: VecDeque<InFlight>,
    snapshots: Vec<SnapshotWait>,
    canvas_waits: Vec<SnapshotWait>,
    results: tokio::sync::mpsc::UnboundedSender<Result<JobResult, String>>,
    steps: Option<StepsOnGpu>,
}

/// The render thread: a [`RenderHandle`] to it and the thread to join.
pub struct TileRenderer {
    handle: RenderHandle,
    thread: Option<std::thread::JoinHandle<()>>,
    /// The GPU the render thread opened, as the node tells the controller.
    pub gpu: GpuInfo,
    /// What the render thread's presents to windows run as (`present_priority`).
    pub window_presents: crate::realtime::PresentScheduling,
}

/// The GPU adapter the render thread opened (from wgpu's `AdapterInfo`, as text: no wgpu type
/// leaves the render thread).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct GpuInfo {
    pub adapter: String,
    pub backend: String,
    pub driver: String,
    pub driver_info: String,
}

impl GpuInfo {
    fn of(info: &wgpu::AdapterInfo) -> GpuInfo {
        GpuInfo {
            adapter: info.name.clone(),
            backend: format!("{:?}", info.backend),
            driver: info.driver.clone(),
            driver_info: info.driver_info.clone(),
        }
    }
}

/// Sends jobs to the render thread (cloneable: the network and the window event loop hold one
/// each). The thread ends when every handle is gone.
#[derive(Clone)]
pub struct RenderHandle {
    jobs: mpsc::Sender<Job>,
}

impl TileRenderer {
    /// Starts the render thread: opens the GPU, uploads the volume (step 0 where `steps` is
    /// given) and environment, then renders jobs in order. Returns once the GPU is up (or with
    /// its error). Results go to `results`. Its presents to windows run real-time at
    /// `present_priority` (0: normal) from each wait's start to the present's return.
    pub fn start(
        volume: RenderVolume,
        env: Option<Environment>,
        results: tokio::sync::mpsc::UnboundedSender<Result<JobResult, String>>,
        steps: Option<TimeSteps>,
        present_priority: u8,
    ) -> Result<TileRenderer> {
        let (jobs, rx) = mpsc::channel::<Job>();
        type Ready = Result<(GpuInfo, crate::realtime::PresentScheduling), String>;
        let (ready_tx, ready_rx) = mpsc::channel::<Ready>();
        let thread = std::thread::Builder::new()
            .name("render".into())
            .spawn(move || {
                lower_priority();
                let (index, object_space) = match &volume {
                    RenderVolume::Whole(_) | RenderVolume::Bricked(_) => (0, false),
                    RenderVolume::Brick(b) => (b.index, true),
                };
                let setup = (move || -> Result<_, String> {
                    let gpu = GpuRenderer::new().map_err(|e| e.to_string())?;
                    let gv = match volume {
                        RenderVolume::Whole(v) => gpu.upload(&v).map(|gv| Held::Volume(Box::new(gv))),
                        RenderVolume::Brick(b) => gpu
                            .upload_brick(&b.region, &b.info, &b.blocks, b.object.clone())
                            .map(|gv| Held::Volume(Box::new(gv))),
                        RenderVolume::Bricked(b) => {
                            let (volume, budgets) = *b;
                            let on_gpu =
                                BrickedOnGpu::new(&gpu, volume, budgets).map_err(|e| format!("{e:#}"))?;
                            tracing::info!(
                                volume = %on_gpu.volume.name,
                                slots = on_gpu.pool.slots(),
                                gpu_mib = on_gpu.pool.gpu_bytes() >> 20,
                                host_mib = budgets.host >> 20,
                                upload_mib_per_frame = budgets.upload_per_frame as f64 / 1048576.0,
                                "the volume is read through the brick cache"
                            );
                            Ok(Held::Bricked(Box::new(on_gpu)))
                        }
                    }
                    .map_err(|e| e.to_string())?;
                    let genv = env
                        .as_ref()
                        .map(|e| gpu.upload_environment(e))
                        .transpose()
                        .map_err(|e| e.to_string())?;
                    Ok((gpu, gv, genv))
                })();
                let (wait, presents) = crate::presenter::PreciseWait::raised_for_presents(present_priority);
                let (gpu, first, genv) = match setup {
                    Ok(s) => {
                        let _ = ready_tx.send(Ok((GpuInfo::of(s.0.adapter_info()), presents)));
                        s
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                        return;
                    }
                };
                let (volumes, bricked) = match first {
                    Held::Volume(gv) => (vec![(index, *gv)], None),
                    Held::Bricked(b) => (Vec::new(), Some(*b)),
                };
                let mut r = RenderLoop {
                    gpu,
                    labels: Vec::new(),
                    volumes,
                    bricked,
                    still_said: false,
                    env: genv,
                    targets: Vec::new(),
                    canvases: Vec::new(),
                    shown: Vec::new(),
                    object_space,
                    surfaces: Vec::new(),
                    wait,
                    ring: ReadbackRing::new(READ_SLOTS),
                    frames: VecDeque::new(),
                    snapshots: Vec::new(),
                    canvas_waits: Vec::new(),
                    results,
                    steps: steps.map(|steps| StepsOnGpu { steps, shown: 0 }),
                };
                loop {
                    // Reads in flight: take the next job if there is one, else wait for the GPU.
                    let job = if r.waiting() {
                        match rx.try_recv() {
                            Ok(job) => job,
                            Err(mpsc::TryRecvError::Empty) => {
                                if !r.wait() {
                                    break;
                                }
                                continue;
                            }
                            Err(mpsc::TryRecvError::Disconnected) => break,
                        }
                    } else {
                        match rx.recv() {
                            Ok(job) => job,
                            Err(_) => break,
                        }
                    };
                    match job {
                        Job::Render(job) => {
                            if !r.render(&job) {
                                break;
                            }
                        }
                        Job::Window(w) => {
                            let on_show = OnShow {
                                object_space: r.object_space,
                                targets: &r.targets,
                                canvases: &r.canvases,
                                shown: &r.shown,
                            };
                            window_job(&r.gpu, &mut r.surfaces, &mut r.wait, on_show, w)
                        }
                        Job::Snapshot(frame_id, reply) => r.snapshot(frame_id, reply),
                        Job::Load(b, reply) => {
                            let gv = r.gpu.upload_brick(&b.region, &b.info, &b.blocks, b.object.clone());
                            let gv = gv.map(|gv| {
                                r.volumes.retain(|v| v.0 != b.index);
                                r.volumes.push((b.index, gv));
                            });
                            let _ = reply.send(gv.map_err(|e| format!("brick {}: {e}", b.index)));
                        }
                        Job::Unload(index) => {
                            // Never the first: the node's own brick stays.
                            if r.volumes.len() > 1 {
                                r.volumes.retain(|v| v.0 != index);
                            }
                        }
                        Job::Canvas(job, reply) => r.canvas(*job, reply),
                        Job::Show(frame_id, tiles) => r.show(frame_id, tiles),
                    }
                }
            })
            .context("cannot start the render thread")?;
        match ready_rx.recv() {
            Ok(Ok((gpu, window_presents))) => {
                tracing::info!(adapter = %gpu.adapter, backend = %gpu.backend, driver = %gpu.driver, "render thread ready");
                Ok(TileRenderer { handle: RenderHandle { jobs }, thread: Some(thread), gpu, window_presents })
            }
            Ok(Err(e)) => anyhow::bail!("GPU set-up failed: {e}"),
            Err(_) => anyhow::bail!("the render thread ended during set-up"),
        }
    }

    pub fn handle(&self) -> RenderHandle {
        self.handle.clone()
    }

    /// Waits for the render thread to end (once every other [`RenderHandle`] is dropped): its
    /// window surfaces go before the windows do.
    pub fn join(self) {
        let TileRenderer { handle, thread, .. } = self;
        drop(handle);
        if let Some(t) = thread {
            let _ = t.join();
        }
    }
}

impl RenderHandle {
    fn send(&self, job: Job) -> Result<()> {
        self.jobs.send(job).map_err(|_| anyhow::anyhow!("the render thread has stopped"))
    }

    pub fn submit(&self, job: TileJob) -> Result<()> {
        self.send(Job::Render(Box::new(job)))
    }

    /// object space: uploads another brick beside the node's own (after the jobs already sent);
    /// resolves once it is on the GPU.
    pub async fn load(&self, brick: BrickData) -> Result<()> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.send(Job::Load(Box::new(brick), tx))?;
        rx.await.map_err(|_| anyhow::anyhow!("the render thread has stopped"))?.map_err(anyhow::Error::msg)
    }

    /// object space: drops a brick uploaded by [`RenderHandle::load`] (after the jobs already sent).
    pub fn unload(&self, brick: usize) -> Result<()> {
        self.send(Job::Unload(brick))
    }

    /// Creates the windows' surfaces on the render thread and waits for them: one line per
    /// surface (tile, size, format), or the first error.
    pub fn attach(&self, windows: Vec<TileWindow>) -> Result<Vec<String>> {
        let (tx, rx) = mpsc::channel();
        self.send(Job::Window(WindowJob::Attach(windows, tx)))?;
        rx.recv().map_err(|_| anyhow::anyhow!("the render thread has stopped"))?.map_err(anyhow::Error::msg)
    }

    /// object space: filters and composes a frame's composited canvases (after the jobs already
    /// sent); resolves to the tiles' images and depth.
    pub async fn compose_canvases(&self, job: CanvasJob) -> Result<Vec<TileResult>> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.send(Job::Canvas(Box::new(job), tx))?;
        rx.await.map_err(|_| anyhow::anyhow!("the render thread has stopped"))?.map_err(anyhow::Error::msg)
    }

    /// object space: the images of `frame_id`'s tiles as the node composited them on the CPU (8-bit
    /// sRGB; depth and shading are not needed), uploaded for the windows to show at the swap.
    pub fn show(&self, frame_id: u64, tiles: Vec<TileResult>) -> Result<()> {
        self.send(Job::Show(frame_id, tiles))
    }

    /// The images of `frame_id`'s tiles (8-bit sRGB), read back from the GPU; an error where the
    /// tiles no longer hold that frame.
    pub async fn snapshot(&self, frame_id: u64) -> Result<Vec<TileResult>> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.send(Job::Snapshot(frame_id, tx))?;
        rx.await.map_err(|_| anyhow::anyhow!("the render thread has stopped"))?.map_err(anyhow::Error::msg)
    }

    /// The swap: presents `frame_id` in every window at `at` (now when `None`); the receiver
    /// resolves to the frame presented, with when it was (the moment the last surface was).
    pub fn present(
        &self,
        frame_id: u64,
        at: Option<Instant>,
    ) -> Result<tokio::sync::oneshot::Receiver<Shown>> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.send(Job::Window(WindowJob::Present(frame_id, at, tx)))?;
        Ok(rx)
    }

    /// A tile's window changed size (pixels).
    pub fn resize(&self, tile: &str, width: u32, height: u32) {
        let _ = self.send(Job::Window(WindowJob::Resize(tile.to_string(), width, height)));
    }

    /// A tile's window needs its image again (exposed).
    pub fn redraw(&self, tile: &str) {
        let _ = self.send(Job::Window(WindowJob::Redraw(tile.to_string())));
    }
}

/// What the windows may show: in screen space the tiles' own targets; in object space the
/// composited tiles (a filtered canvas, or an image composited on the CPU), never a brick's view
/// (which the targets hold there, under its tile's name).
struct OnShow<'a> {
    object_space: bool,
    targets: &'a [TileTarget],
    canvases: &'a [TileTarget],
    shown: &'a [ShownImages],
}

impl<'a> OnShow<'a> {
    /// Tile `name`'s images; in object space, of a canvas and uploaded images (the session's
    /// form changed), those holding the later frame.
    fn tile(&self, name: &str) -> Option<&'a dyn Presentable> {
        if !self.object_space {
            if let Some(t) = self.targets.iter().find(|t| t.name == name) {
                return Some(t);
            }
            // A balanced wall: its targets hold rectangles; its tiles are placed on the CPU.
            return self.shown.iter().find(|t| t.name == name).map(|t| t as &dyn Presentable);
        }
        let canvas = self.canvases.iter().find(|t| t.name == name).map(|t| t as &dyn Presentable);
        let shown = self.shown.iter().find(|t| t.name == name).map(|t| t as &dyn Presentable);
        let latest =
            |p: &Option<&dyn Presentable>| p.and_then(|p| p.images().iter().filter_map(|i| i.frame_id).max());
        if latest(&shown) > latest(&canvas) {
            shown
        } else {
            canvas.or(shown)
        }
    }
}

/// The presentation jobs of the render thread.
fn window_job(
    gpu: &GpuRenderer,
    surfaces: &mut Vec<TileSurface>,
    wait: &mut crate::presenter::PreciseWait,
    on_show: OnShow,
    job: WindowJob,
) {
    let target = |name: &str| on_show.tile(name);
    match job {
        WindowJob::Attach(windows, reply) => {
            surfaces.clear();
            let made: Result<Vec<TileSurface>, String> = windows
                .into_iter()
                .map(|w| TileSurface::new(&gpu.ctx, &w.tile, w.window, w.size).map_err(|e| e.to_string()))
                .collect();
            let answer = made.map(|made| {
                *surfaces = made;
                surfaces
                    .iter_mut()
                    .map(|s| {
                        // Black until the first frame.
                        if let Err(e) = s.redraw(&gpu.ctx, None) {
                            tracing::warn!("{e}");
                        }
                        let (w, h) = s.size();
                        format!("{} {w}x{h} {:?}", s.name, s.format())
                    })
                    .collect()
            });
            let _ = reply.send(answer);
        }
        WindowJob::Present(frame_id, at, reply) => {
            let waiting_from = Instant::now();
            let result = wait.present_at(at, || {
                let mut result = Ok(());
                for s in surfaces.iter_mut() {
                    match s.present(&gpu.ctx, target(&s.name), frame_id) {
                        Ok(Presented::Frame) => {}
                        Ok(p) => tracing::debug!(tile = %s.name, frame_id, ?p, "presented without the frame"),
                        Err(e) => result = Err(e.to_string()),
                    }
                }
                result
            });
            let _ = reply.send(Shown { frame_id, waiting_from, result: result.map(|()| Instant::now()) });
        }
        WindowJob::Resize(tile, width, height) => {
            for s in surfaces.iter_mut().filter(|s| s.name == tile) {
                if let Err(e) = s
                    .resize(&gpu.ctx, width, height)
                    .and_then(|()| s.redraw(&gpu.ctx, target(&tile)).map(drop))
                {
                    tracing::warn!("{e}");
                }
            }
        }
        WindowJob::Redraw(tile) => {
            for s in surfaces.iter_mut().filter(|s| s.name == tile) {
                if let Err(e) = s.redraw(&gpu.ctx, target(&tile)) {
                    tracing::warn!("{e}");
                }
            }
        }
    }
}

impl RenderLoop {
    /// Renders a job's tiles (each submitted as soon as it is recorded); its result is sent once
    /// its reads arrive. False when the results' receiver is gone.
    fn render(&mut self, job: &TileJob) -> bool {
        let plan = &job.plan;
        let started = Instant::now();
        let step_late = self.show_step(plan.frame_id, plan.time_step);
        match self.submit(job) {
            Ok(()) => {
                let n = plan.views.len();
                self.frames.push_back(InFlight {
                    frame_id: plan.frame_id,
                    step_late,
                    started,
                    tiles: vec![None; n],
                    fetches: 0,
                    hits: 0,
                    level0_hits: 0,
                });
                self.deliver_ready()
            }
            Err(e) => self.results.send(Err(e)).is_ok(),
        }
    }

    /// A time-varying volume: puts the frame's step on the GPU (the current one for the cache,
    /// so it loads the ones after it): the whole volume, or the node's brick written into its
    /// buffers (a new upload only where the sizes differ). A step not loaded yet is waited for
    /// at most [`TimeSteps::wait`]; then the frame renders the step it has. `Some((shown,
    /// waited))` where the step was not loaded when the frame came.
    fn show_step(&mut self, frame_id: u64, wanted: u32) -> Option<(u32, Duration)> {
        let RenderLoop { gpu, volumes, steps, .. } = self;
        let on = steps.as_mut()?;
        let count = on.steps.cache.steps().max(1);
        let wanted = (wanted as usize % count) as u32;
        let t0 = Instant::now();
        let (put, late) = match &on.steps.cache {
            StepsOf::Volume(cache) => {
                let (state, late) = fetch(cache, wanted, on.shown, on.steps.wait)?;
                let put = state.and_then(|v| {
                    v.map(|v| {
                        let gv = gpu.upload(&v).map_err(|e| format!("cannot upload it: {e}"))?;
                        volumes.retain(|v| v.0 != 0);
                        volumes.insert(0, (0, gv));
                        Ok(())
                    })
                    .transpose()
                });
                (put, late)
            }
            StepsOf::Brick { index, info, object, cache } => {
                let (state, late) = fetch(cache, wanted, on.shown, on.steps.wait)?;
                let put = state.and_then(|r| {
                    r.map(|r| {
                        let held = volumes.iter_mut().find(|v| v.0 == *index);
                        if held.is_some_and(|v| v.1.rewrite_brick(&gpu.ctx, &r.region, &r.blocks).is_ok()) {
                            return Ok(());
                        }
                        let gv = gpu
                            .upload_brick(&r.region, info, &r.blocks, object.clone())
                            .map_err(|e| format!("cannot upload brick {index}: {e}"))?;
                        volumes.retain(|v| v.0 != *index);
                        volumes.insert(0, (*index, gv));
                        Ok(())
                    })
                    .transpose()
                });
                (put, late)
            }
        };
        match put {
            Ok(Some(())) => on.shown = wanted,
            Ok(None) => tracing::warn!(
                frame_id,
                "time step {wanted} is not loaded after waiting {:.0} ms: rendering step {}",
                on.steps.wait.as_secs_f64() * 1e3,
                on.shown
            ),
            Err(e) => {
                tracing::warn!(
                    frame_id,
                    "time step {wanted} cannot be shown: {e}; rendering step {}",
                    on.shown
                )
            }
        }
        (late || on.shown != wanted).then(|| (on.shown, t0.elapsed()))
    }

    fn submit(&mut self, job: &TileJob) -> Result<(), String> {
        let plan = &job.plan;
        // The tiles' resources, kept where they fit, made where they do not (start, resize, scale,
        // the filter turned on or off: a denoised tile renders a guard band of the filter's reach
        // beyond its edges, so that the wall's tiles filter their edge pixels as one image).
        // A brick's view (object space) is not filtered: its pixels are not the image's until
        // composited; the tile's owner filters the composited canvas (`RenderLoop::canvas`).
        let settings = plan.view_settings();
        let denoise = settings.denoise.is_on();
        let guard = if denoise { isowall_render::denoise::reach() } else { 0 };
        let mut targets = std::mem::take(&mut self.targets);
        let mut kept = Vec::with_capacity(plan.views.len());
        for (name, view) in &plan.views {
            let reuse =
                targets.iter().position(|t| t.name == *name && t.fits_with_guard(view, plan.scale, guard));
            let target = match reuse {
                Some(i) => targets.swap_remove(i),
                None => TileTarget::with_guard(&self.gpu, name, view, plan.scale, guard)
                    .map_err(|e| format!("tile {name}: {e}"))?,
            };
            kept.push(target);
        }
        self.targets = kept;
        self.refine_bricks(plan, &settings, guard)?;
        for k in 0..plan.views.len() {
            while !self.ring.has_free_slot() {
                self.ring.wait_oldest(&self.gpu.ctx).map_err(|e| e.to_string())?;
                self.take_reads();
            }
            let (name, view) = &plan.views[k];
            let gv = match plan.bricks.get(k) {
                None => match &self.bricked {
                    Some(b) => Some(b.pool.volume()),
                    None => self.volumes.first().map(|v| &v.1),
                },
                Some(b) => self.volumes.iter().find(|v| v.0 == *b).map(|v| &v.1),
            };
            let Some(gv) = gv else {
                return Err(format!("tile {name}: brick {:?} is not loaded", plan.bricks.get(k)));
            };
            let frame = TileFrame {
                frame_id: plan.frame_id,
                volume: gv,
                view,
                settings: &settings,
                env: self.env.as_ref(),
                continuity: plan.continuity,
                // A moving camera carries each pixel's history over; object space does not (a
                // brick's pixels are not the tile's until composited).
                temporal: plan.views_are_tiles(),
                share: plan.share,
            };
            self.gpu
                .render_tile(&mut self.targets[k], &frame, &mut self.ring)
                .map_err(|e| format!("tile {name}: {e}"))?;
            // Only a tile's own view shows its name (not a balanced wall's rectangle of it).
            if let Some(node) =
                job.identify.as_ref().filter(|_| plan.views_are_tiles() && plan.share.is_none())
            {
                let text = format!("{node} {name}");
                let max = (view.rect.width, view.rect.height);
                let at = match self.labels.iter().position(|l| l.text == text && l.tile == max) {
                    Some(i) => i,
                    None => {
                        self.labels.retain(|l| !l.text.ends_with(&format!(" {name}")));
                        let (w, h, rgba) = crate::identify::label(&text, max);
                        self.labels.push(Label { text, tile: max, size: (w, h), rgba });
                        self.labels.len() - 1
                    }
                };
                let label = &self.labels[at];
                self.gpu
                    .stamp(&self.targets[k], &label.rgba, label.size)
                    .map_err(|e| format!("tile {name}: {e}"))?;
            }
        }
        self.after_bricked_frame(plan.frame_id, settings.iso)
    }

    /// A still frame of a ray-guided refinement ([`crate::bricked::RayGuide`]) has rendered:
    /// reads the bricks its rays read, for the next frame's round, and says once how the
    /// refinement ended.
    fn after_bricked_frame(&mut self, frame_id: u64, iso: f64) -> Result<(), String> {
        let Some(b) = self.bricked.as_mut() else {
            return Ok(());
        };
        let Some(g) = b.after_frame(&self.gpu, iso).map_err(|e| format!("the brick cache: {e:#}"))? else {
            return Ok(());
        };
        tracing::debug!(frame_id, read = g.read, missing = g.missing, "bricks the frame's rays read");
        let free = b.pool.free_slots();
        if g.missing == 0 && !self.still_said {
            self.still_said = true;
            tracing::info!(
                frame_id,
                "this node's still view has the {} bricks its rays read at level 0 (of the volume's {}; its footprint wanted more than the pool's {} slots), {} MiB uploaded so far",
                g.read,
                b.pool.layout().bricks(0),
                free,
                b.pool.stats().upload_bytes >> 20
            );
        } else if g.over_pool && !self.still_said {
            self.still_said = true;
            tracing::warn!(
                frame_id,
                "this node's still view's rays read {} bricks at level 0 and its pool holds {} of them: the rest is drawn from coarser levels; raise [volume] gpu_budget_mb to at least {} for level 0 everywhere",
                g.read,
                free,
                b.needed_mib(g.read - free)
            );
        }
        Ok(())
    }

    /// Screen space through the brick cache: one round of uploads for the bricks the frame's
    /// views want (their guard bands included), at level 0 unless the camera moves. A round that
    /// changed what the pool holds gives the pool's volume a new id (`BrickPool::refine`), and a
    /// tile whose volume changed starts its accumulation and history over (`render_tile`):
    /// still or moving, its picture changed.
    fn refine_bricks(
        &mut self,
        plan: &RenderPlan,
        settings: &isowall_model::RenderSettings,
        guard: u32,
    ) -> Result<(), String> {
        let Some(b) = self.bricked.as_mut() else {
            return Ok(());
        };
        let still = plan.continuity != Continuity::ViewMoved;
        if plan.continuity == Continuity::Changed {
            // A new picture (iso, settings, volume): the bricks its rays read are found anew.
            b.guide = RayGuide::default();
            self.still_said = false;
        }
        let views: Vec<View> =
            plan.views.iter().map(|(_, v)| View { rect: v.rect.grown(guard, v.full), ..*v }).collect();
        let t0 = Instant::now();
        let r =
            b.refine(&self.gpu, &views, settings, still).map_err(|e| format!("the brick cache: {e:#}"))?;
        tracing::debug!(
            frame_id = plan.frame_id,
            still,
            refine_ms = t0.elapsed().as_secs_f64() * 1e3,
            wanted = r.wanted,
            resident = r.resident,
            uploaded = r.uploaded,
            upload_bytes = r.upload_bytes,
            "bricks"
        );
        if !still {
            self.still_said = false;
        } else if b.guide.active {
            // Said once its rays' bricks are read (`after_bricked_frame`).
        } else if r.complete() && !self.still_said {
            self.still_said = true;
            tracing::info!(
                frame_id = plan.frame_id,
                "this node's still view has its {} bricks at level 0 (of the volume's {}), {} MiB uploaded so far",
                r.wanted,
                b.pool.layout().bricks(0),
                b.pool.stats().upload_bytes >> 20
            );
        }
        Ok(())
    }

    /// Uploads a frame's tiles composited on the CPU for the windows (only where the node has
    /// windows: its session sends them then); a tile's images are made at its first frame and
    /// remade when its size changes. A failure is the windows' alone: logged, the frame goes on.
    fn show(&mut self, frame_id: u64, tiles: Vec<TileResult>) {
        for t in tiles {
            let size = (t.width, t.height);
            let at = match self.shown.iter().position(|s| s.name == t.name && s.size() == size) {
                Some(i) => i,
                None => match ShownImages::new(&self.gpu, &t.name, size) {
                    Ok(images) => {
                        self.shown.retain(|s| s.name != t.name);
                        self.shown.push(images);
                        self.shown.len() - 1
                    }
                    Err(e) => {
                        tracing::warn!(frame_id, tile = %t.name, "cannot show the composited tile: {e}");
                        continue;
                    }
                },
            };
            if let Err(e) = self.gpu.show_image(&mut self.shown[at], frame_id, &t.rgb8) {
                tracing::warn!(frame_id, tile = %t.name, "cannot show the composited tile: {e}");
            }
        }
    }

    /// Filters and composes a frame's canvases; the reply goes once their images arrive.
    fn canvas(
        &mut self,
        job: CanvasJob,
        reply: tokio::sync::oneshot::Sender<Result<Vec<TileResult>, String>>,
    ) {
        let result = (|| -> Result<usize, String> {
            let mut canvases = std::mem::take(&mut self.canvases);
            let mut kept = Vec::with_capacity(job.tiles.len());
            for (name, view, _) in &job.tiles {
                let reuse =
                    canvases.iter().position(|t| t.name == *name && t.fits_with_guard(view, 1, job.guard));
                kept.push(match reuse {
                    Some(i) => canvases.swap_remove(i),
                    None => TileTarget::with_guard(&self.gpu, name, view, 1, job.guard)
                        .map_err(|e| format!("tile {name}: {e}"))?,
                });
            }
            self.canvases = kept;
            for (k, (name, view, shading)) in job.tiles.iter().enumerate() {
                while !self.ring.has_free_slot() {
                    self.ring.wait_oldest(&self.gpu.ctx).map_err(|e| e.to_string())?;
                    self.take_reads();
                }
                let frame = CanvasFrame {
                    frame_id: job.frame_id,
                    volume: &self.volumes[0].1,
                    view,
                    settings: &job.settings,
                    env: self.env.as_ref(),
                };
                self.gpu
                    .compose_canvas(&mut self.canvases[k], &frame, shading, &mut self.ring)
                    .map_err(|e| format!("tile {name}: {e}"))?;
            }
            Ok(job.tiles.len())
        })();
        match result {
            Ok(0) => {
                let _ = reply.send(Ok(Vec::new()));
            }
            Ok(n) => {
                self.canvas_waits.push(SnapshotWait { frame_id: job.frame_id, reply, tiles: vec![None; n] })
            }
            Err(e) => {
                let _ = reply.send(Err(e));
            }
        }
    }

    /// Asks for the images of `frame_id`'s tiles; the reply goes once they arrive.
    fn snapshot(
        &mut self,
        frame_id: u64,
        reply: tokio::sync::oneshot::Sender<Result<Vec<TileResult>, String>>,
    ) {
        let mut asked = 0;
        for i in 0..self.targets.len() {
            while !self.ring.has_free_slot() {
                if let Err(e) = self.ring.wait_oldest(&self.gpu.ctx) {
                    let _ = reply.send(Err(e.to_string()));
                    return;
                }
                self.take_reads();
            }
            if let Err(e) = self.gpu.read_tile_image(&self.targets[i], frame_id, &mut self.ring) {
                let _ = reply.send(Err(e.to_string()));
                return;
            }
            asked += 1;
        }
        if asked == 0 {
            let _ = reply.send(Ok(Vec::new()));
            return;
        }
        self.snapshots.push(SnapshotWait { frame_id, reply, tiles: vec![None; asked] });
    }

    /// Moves arrived reads into their frames and snapshots; answers completed snapshots.
    fn take_reads(&mut self) {
        let period = self.gpu.ctx.queue.get_timestamp_period();
        for read in self.ring.take_ready() {
            let (tag, out) = match FrameRead::decode(read, period) {
                Ok(r) => r,
                Err(e) => {
                    tracing::warn!("{e}");
                    continue;
                }
            };
            let result = TileResult {
                name: tag.tile.clone(),
                width: tag.width,
                height: tag.height,
                rgb8: out.rgb8.unwrap_or_default(),
                depth: out.depth.unwrap_or_default(),
                shading: out.shading.unwrap_or_default(),
                fetches: out.counters.fetches,
            };
            let tiles = match tag.kind {
                ReadKind::Canvas => {
                    self.canvas_waits.iter_mut().find(|s| s.frame_id == tag.frame_id).map(|s| &mut s.tiles)
                }
                ReadKind::Snapshot => {
                    self.snapshots.iter_mut().find(|s| s.frame_id == tag.frame_id).map(|s| &mut s.tiles)
                }
                ReadKind::Frame => self.frames.iter_mut().find(|f| f.frame_id == tag.frame_id).map(|f| {
                    f.fetches += out.counters.fetches;
                    f.hits += out.counters.hits;
                    f.level0_hits += out.counters.level0_hits;
                    &mut f.tiles
                }),
            };
            // Reads arrive in the order they were recorded: the tiles' order.
            if let Some(slot) = tiles.and_then(|t| t.iter_mut().find(|t| t.is_none())) {
                *slot = Some(result);
            }
        }
        for waits in [&mut self.snapshots, &mut self.canvas_waits] {
            let mut i = 0;
            while i < waits.len() {
                if waits[i].tiles.iter().all(Option::is_some) {
                    let s = waits.remove(i);
                    let _ = s.reply.send(Ok(s.tiles.into_iter().flatten().collect()));
                } else {
                    i += 1;
                }
            }
        }
    }

    /// Sends the results of frames whose reads have all arrived, in order. False when the
    /// results' receiver is gone.
    fn deliver_ready(&mut self) -> bool {
        if let Err(e) = self.ring.poll(&self.gpu.ctx) {
            tracing::warn!("{e}");
        }
        self.take_reads();
        while self.frames.front().is_some_and(|f| f.tiles.iter().all(Option::is_some)) {
            let f = self.frames.pop_front().expect("front");
            let render_time = f.started.elapsed();
            tracing::debug!(
                frame_id = f.frame_id,
                fetches = f.fetches,
                hits = f.hits,
                level0_hits = f.level0_hits,
                render_ms = render_time.as_secs_f64() * 1e3,
                "frame rendered"
            );
            let tiles = f.tiles.into_iter().flatten().collect();
            let surface =
                self.bricked.is_some().then_some(SurfaceLevels { hits: f.hits, level0: f.level0_hits });
            let result =
                JobResult { frame_id: f.frame_id, tiles, render_time, step_late: f.step_late, surface };
            if self.results.send(Ok(result)).is_err() {
                return false;
            }
        }
        true
    }

    /// Whether reads are awaited.
    fn waiting(&self) -> bool {
        self.ring.in_flight() > 0
    }

    /// Blocks until the oldest read arrives, then delivers what is complete.
    fn wait(&mut self) -> bool {
        if let Err(e) = self.ring.wait_oldest(&self.gpu.ctx) {
            tracing::warn!("{e}");
        }
        self.deliver_ready()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use isowall_model::composite::PixelForm;
    use isowall_model::wire::Continuity;
    use isowall_model::{Camera, Rect};
    use isowall_render::gpu::GpuError;

    type Results = tokio::sync::mpsc::UnboundedReceiver<Result<JobResult, String>>;

    /// The render thread on a small scene, or `None` (after a message) where no Vulkan adapter
    /// exists; under `CI=true` a missing adapter fails instead (GPU tests never skip silently).
    fn renderer() -> Option<(TileRenderer, Results)> {
        match GpuRenderer::new() {
            Ok(_) => {}
            Err(e @ GpuError::NoAdapter(_)) if std::env::var("CI").as_deref() != Ok("true") => {
                eprintln!("skipping GPU test: {e}");
                return None;
            }
            Err(e) => panic!("GPU set-up failed: {e}"),
        }
        let src: isowall_volume::VolumeSource = "procedural:sphere-over-plane:48".parse().unwrap();
        let volume = src.load(None).unwrap();
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        Some((TileRenderer::start(RenderVolume::Whole(volume), None, tx, None, 0).unwrap(), rx))
    }

    fn camera() -> Camera {
        Camera {
            eye: glam::DVec3::new(-30.0, -60.0, 70.0),
            target: glam::DVec3::new(24.0, 24.0, 16.0),
            up: glam::DVec3::Z,
            fov_y_deg: 40.0,
        }
    }

    /// Renders `tiles` as frame `frame_id` and returns the result.
    fn render(
        r: &TileRenderer,
        rx: &mut Results,
        frame_id: u64,
        tiles: Vec<(String, View)>,
        settings: &RenderSettings,
        scale: u32,
        read_pixels: bool,
    ) -> JobResult {
        let plan = RenderPlan {
            frame_id,
            views: tiles,
            bricks: Vec::new(),
            settings: *settings,
            scale,
            accumulate_frame: 0,
            continuity: Continuity::Changed,
            time_step: 0,
            share: read_pixels.then_some(PixelForm::Colour),
        };
        let job = TileJob { plan, identify: None };
        r.handle().submit(job).unwrap();
        let result = rx.blocking_recv().unwrap().unwrap();
        assert_eq!(result.frame_id, frame_id);
        result
    }

    /// The whole image of 96 x 72 pixels as two tiles split at an odd column (not a multiple of
    /// the scale), rendered by the render thread at `scale` and put back together.
    fn wall_image(
        r: &TileRenderer,
        rx: &mut Results,
        whole: &View,
        settings: &RenderSettings,
        scale: u32,
    ) -> Vec<u8> {
        let (w, h) = whole.full;
        let left = View { rect: Rect { x: 0, y: 0, width: 47, height: h }, ..*whole };
        let right = View { rect: Rect { x: 47, y: 0, width: w - 47, height: h }, ..*whole };
        let tiles = vec![("left".into(), left), ("right".into(), right)];
        let result = render(r, rx, scale as u64, tiles, settings, scale, true);
        let mut image = vec![0u8; (w * h * 3) as usize];
        for (t, x0) in result.tiles.iter().zip([0, 47]) {
            assert_eq!(t.height, h);
            for y in 0..h {
                for x in 0..t.width {
                    let (src, dst) = (((y * t.width + x) * 3) as usize, ((y * w + x0 + x) * 3) as usize);
                    image[dst..dst + 3].copy_from_slice(&t.rgb8[src..src + 3]);
                }
            }
        }
        image
    }

    #[test]
    fn a_frame_at_scale_2_is_the_half_size_image_upsampled() {
        let Some((r, mut rx)) = renderer() else { return };
        let mut settings = RenderSettings::new(0.0);
        settings.ao.samples = 2;
        let whole = View::whole(camera(), 96, 72);
        let full = wall_image(&r, &mut rx, &whole, &settings, 1);
        let halved = wall_image(&r, &mut rx, &whole, &settings, 2);

        // The half-size image rendered alone (48 x 36, same camera, same sample pattern seeding),
        // upsampled nearest: every full pixel (x, y) takes the half pixel (x / 2, y / 2).
        let half =
            render(&r, &mut rx, 10, vec![("half".into(), View::whole(camera(), 48, 36))], &settings, 1, true);
        let half = &half.tiles[0].rgb8;
        let mut want = vec![0u8; 96 * 72 * 3];
        for y in 0..72 {
            for x in 0..96 {
                let (s, d) = (((y / 2) * 48 + x / 2) * 3, (y * 96 + x) * 3);
                want[d..d + 3].copy_from_slice(&half[s..s + 3]);
            }
        }
        let differ = halved.iter().zip(&want).filter(|(a, b)| a != b).count();
        assert_eq!(differ, 0, "{differ} channel values differ from the upsampled half-size render");
        // And it is not the full-resolution image: the scale reached the render.
        let differ = halved.iter().zip(&full).filter(|(a, b)| a != b).count();
        assert!(differ > 96 * 72 / 10, "only {differ} channel values differ from the full-resolution frame");
        drop(rx);
        r.join();
    }

    #[test]
    fn screen_space_frames_stay_on_the_gpu_and_a_snapshot_reads_the_image() {
        let Some((r, mut rx)) = renderer() else { return };
        let mut settings = RenderSettings::new(0.0);
        settings.ao.samples = 2;
        let view = View::whole(camera(), 64, 48);
        let shared = render(&r, &mut rx, 1, vec![("t".into(), view)], &settings, 1, true);
        let kept = render(&r, &mut rx, 2, vec![("t".into(), view)], &settings, 1, false);
        assert!(
            kept.tiles[0].rgb8.is_empty() && kept.tiles[0].depth.is_empty(),
            "screen space read pixels back"
        );
        let snap = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap()
            .block_on(r.handle().snapshot(2))
            .unwrap();
        assert_eq!(snap.len(), 1);
        assert_eq!((snap[0].width, snap[0].height), (64, 48));
        // Frames 1 and 2 are the same state and both restart (accumulate_frame 0): same image.
        assert_eq!(snap[0].rgb8, shared.tiles[0].rgb8, "the snapshot is not the frame's image");
        let lit = shared.tiles[0].depth.iter().filter(|d| d.is_finite()).count();
        assert!(lit > 64 * 48 / 10, "only {lit} pixels hit");
        // A frame no longer held is refused, not answered with another frame's image.
        let gone =
            tokio::runtime::Builder::new_current_thread().build().unwrap().block_on(r.handle().snapshot(99));
        assert!(gone.is_err());
        drop(rx);
        r.join();
    }
}
