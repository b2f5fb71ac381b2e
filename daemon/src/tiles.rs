//! The render thread of a wall node: it alone owns the GPU device. It renders the node's tiles for
//! each frame state it is sent, keeps progressive accumulation going while the state is unchanged
//! (the frame index advances the sample pattern; any change restarts the average), and hands back
//! 8-bit sRGB images of the tiles. Where the node presents in windows, it also owns their surfaces
//! (created from its own wgpu instance): a rendered frame is staged on them at once, and the swap
//! ([`RenderHandle::present`]) only draws and presents.

use anyhow::{Context, Result};
use isowall_render::environment::Environment;
use isowall_render::gpu::present::{Presented, TileSurface};
use isowall_render::gpu::GpuRenderer;
use isowall_render::output::srgb8;
use isowall_render::Frame;
use isowall_volume::Volume;
use isowall_wall::{lowres, RenderSettings, View};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

/// One frame to render: the views of the node's tiles, the settings, and where in the
/// progressive accumulation it stands (0 restarts it).
pub struct TileJob {
    pub frame_id: u64,
    pub tiles: Vec<(String, View)>,
    pub settings: RenderSettings,
    pub accumulate_frame: u32,
    /// object space: the brick each view renders, by index (a node renders an adopted brick
    /// beside its own, `object.rs`); empty: the one volume.
    pub bricks: Vec<usize>,
    /// The internal resolution divisor (1 ..= 4, `isowall_wall::lowres`): each tile renders its
    /// view of the image divided by it and is upsampled (nearest) to its full size.
    pub scale: u32,
}

/// A tile's image of a frame: 8-bit sRGB, rows top to bottom.
#[derive(Clone)]
pub struct TileResult {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub rgb8: Vec<u8>,
    /// Distance along the ray per pixel, `+inf` where nothing is hit (object space composites by it).
    pub depth: Vec<f32>,
}

/// What the render thread uploads: the whole volume (screen space) or a brick and its halo
/// (object space, `object.rs`).
pub enum RenderVolume {
    Whole(Volume),
    Brick(Box<crate::object::BrickData>),
}

pub struct JobResult {
    pub frame_id: u64,
    pub tiles: Vec<TileResult>,
    pub render_time: Duration,
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
    /// object space: upload another brick (an adopted one); replies when it is on the GPU.
    Load(Box<crate::object::BrickData>, tokio::sync::oneshot::Sender<Result<(), String>>),
    /// object space: drop a brick's volume (no longer this node's).
    Unload(usize),
}

/// The presentation jobs.
enum WindowJob {
    /// Create a surface per window (replacing any); replies with one line per surface.
    Attach(Vec<TileWindow>, mpsc::Sender<Result<Vec<String>, String>>),
    /// The swap: present `frame_id` (staged when it rendered) on every surface; replies with the
    /// moment the last surface was presented.
    Present(u64, tokio::sync::oneshot::Sender<Result<Instant, String>>),
    Resize(String, u32, u32),
    Redraw(String),
}

/// The render thread: a [`RenderHandle`] to it and the thread to join.
pub struct TileRenderer {
    handle: RenderHandle,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Sends jobs to the render thread (cloneable: the network and the window event loop hold one
/// each). The thread ends when every handle is gone.
#[derive(Clone)]
pub struct RenderHandle {
    jobs: mpsc::Sender<Job>,
}

/// Running sum of a tile's linear colour over the accumulated frames.
struct Accumulator {
    sum: Vec<[f32; 3]>,
    frames: u32,
}

impl TileRenderer {
    /// Starts the render thread: opens the GPU, uploads the volume and environment, then renders
    /// jobs in order. Returns once the GPU is up (or with its error). Results go to `results`.
    pub fn start(
        volume: RenderVolume,
        env: Option<Environment>,
        results: tokio::sync::mpsc::UnboundedSender<Result<JobResult, String>>,
    ) -> Result<TileRenderer> {
        let (jobs, rx) = mpsc::channel::<Job>();
        let (ready_tx, ready_rx) = mpsc::channel::<Result<String, String>>();
        let thread = std::thread::Builder::new()
            .name("render".into())
            .spawn(move || {
                let setup = (|| -> Result<_, String> {
                    let gpu = GpuRenderer::new().map_err(|e| e.to_string())?;
                    let gv = match &volume {
                        RenderVolume::Whole(v) => gpu.upload(v),
                        RenderVolume::Brick(b) => {
                            gpu.upload_brick(&b.region, &b.info, &b.blocks, b.object.clone())
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
                let (gpu, first, genv) = match setup {
                    Ok(s) => {
                        let _ = ready_tx.send(Ok(s.0.adapter_name().to_string()));
                        s
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                        return;
                    }
                };
                // By brick index (0: the whole volume in screen space).
                let index = match &volume {
                    RenderVolume::Whole(_) => 0,
                    RenderVolume::Brick(b) => b.index,
                };
                let mut volumes = vec![(index, first)];
                drop(volume);
                let mut acc: Vec<Accumulator> = Vec::new();
                let mut surfaces: Vec<TileSurface> = Vec::new();
                for job in rx {
                    let job = match job {
                        Job::Render(job) => job,
                        Job::Window(w) => {
                            window_job(&gpu, &mut surfaces, w);
                            continue;
                        }
                        Job::Load(b, reply) => {
                            let r = gpu.upload_brick(&b.region, &b.info, &b.blocks, b.object.clone());
                            let r = r.map(|gv| {
                                volumes.retain(|v| v.0 != b.index);
                                volumes.push((b.index, gv));
                            });
                            let _ = reply.send(r.map_err(|e| format!("brick {}: {e}", b.index)));
                            continue;
                        }
                        Job::Unload(index) => {
                            // Never the first: the node's own brick stays.
                            if volumes.len() > 1 {
                                volumes.retain(|v| v.0 != index);
                            }
                            continue;
                        }
                    };
                    let start = Instant::now();
                    let mut out = Vec::new();
                    let mut failed = None;
                    if job.accumulate_frame == 0 || acc.len() != job.tiles.len() {
                        acc = job.tiles.iter().map(|_| Accumulator { sum: Vec::new(), frames: 0 }).collect();
                    }
                    for (k, ((name, view), a)) in job.tiles.iter().zip(acc.iter_mut()).enumerate() {
                        let mut s = job.settings;
                        s.ao.frame = s.ao.frame.wrapping_add(job.accumulate_frame);
                        let gv = match job.bricks.get(k) {
                            None => Some(&volumes[0].1),
                            Some(b) => volumes.iter().find(|v| v.0 == *b).map(|v| &v.1),
                        };
                        let Some(gv) = gv else {
                            failed =
                                Some(format!("tile {name}: brick {:?} is not loaded", job.bricks.get(k)));
                            break;
                        };
                        let low = lowres::scaled_view(view, job.scale);
                        match gpu.render(gv, &low, &s, genv.as_ref()) {
                            Ok(r) => out.push(upsample(accumulate(name, a, r.frame), view, job.scale)),
                            Err(e) => {
                                failed = Some(format!("tile {name}: {e}"));
                                break;
                            }
                        }
                    }
                    let msg = match failed {
                        Some(e) => Err(e),
                        None => {
                            let render_time = start.elapsed();
                            stage(&gpu, &mut surfaces, job.frame_id, &out);
                            Ok(JobResult { frame_id: job.frame_id, tiles: out, render_time })
                        }
                    };
                    if results.send(msg).is_err() {
                        break;
                    }
                }
            })
            .context("cannot start the render thread")?;
        match ready_rx.recv() {
            Ok(Ok(adapter)) => {
                tracing::info!(%adapter, "render thread ready");
                Ok(TileRenderer { handle: RenderHandle { jobs }, thread: Some(thread) })
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
        let TileRenderer { handle, thread } = self;
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
    pub async fn load(&self, brick: crate::object::BrickData) -> Result<()> {
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

    /// The swap: presents `frame_id` in every window; resolves to when it was presented.
    pub async fn present(&self, frame_id: u64) -> Result<Instant> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.send(Job::Window(WindowJob::Present(frame_id, tx)))?;
        rx.await.map_err(|_| anyhow::anyhow!("the render thread has stopped"))?.map_err(anyhow::Error::msg)
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

/// Uploads a rendered frame's tiles to their windows' surfaces, ready for the swap.
fn stage(gpu: &GpuRenderer, surfaces: &mut [TileSurface], frame_id: u64, tiles: &[TileResult]) {
    for s in surfaces.iter_mut() {
        if let Some(t) = tiles.iter().find(|t| t.name == s.name) {
            if let Err(e) = s.stage(&gpu.ctx, frame_id, t.width, t.height, &t.rgb8) {
                tracing::warn!("{e}");
            }
        }
    }
}

/// The presentation jobs of the render thread.
fn window_job(gpu: &GpuRenderer, surfaces: &mut Vec<TileSurface>, job: WindowJob) {
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
                        if let Err(e) = s.redraw(&gpu.ctx) {
                            tracing::warn!("{e}");
                        }
                        let (w, h) = s.size();
                        format!("{} {w}x{h} {:?}", s.name, s.format())
                    })
                    .collect()
            });
            let _ = reply.send(answer);
        }
        WindowJob::Present(frame_id, reply) => {
            let mut result = Ok(());
            for s in surfaces.iter_mut() {
                match s.present(&gpu.ctx, frame_id) {
                    Ok(Presented::Frame) => {}
                    Ok(p) => tracing::debug!(tile = %s.name, frame_id, ?p, "presented without the frame"),
                    Err(e) => result = Err(e.to_string()),
                }
            }
            let _ = reply.send(result.map(|()| Instant::now()));
        }
        WindowJob::Resize(tile, width, height) => {
            for s in surfaces.iter_mut().filter(|s| s.name == tile) {
                if let Err(e) = s.resize(&gpu.ctx, width, height).and_then(|()| s.redraw(&gpu.ctx).map(drop))
                {
                    tracing::warn!("{e}");
                }
            }
        }
        WindowJob::Redraw(tile) => {
            for s in surfaces.iter_mut().filter(|s| s.name == tile) {
                if let Err(e) = s.redraw(&gpu.ctx) {
                    tracing::warn!("{e}");
                }
            }
        }
    }
}

/// A tile's image rendered (and accumulated) at `lowres::scaled_view(view, scale)`, upsampled
/// (nearest) to `view`. Only what leaves the render thread is upsampled (colour and depth), after
/// accumulation, so the running sum stays at the low resolution; nearest upsampling commutes with
/// the per-pixel average and the sRGB encoding, so the result is the same as upsampling first.
pub fn upsample(tile: TileResult, view: &View, scale: u32) -> TileResult {
    if scale <= 1 {
        return tile;
    }
    let rgb: Vec<[u8; 3]> = tile.rgb8.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    TileResult {
        name: tile.name,
        width: view.window.width,
        height: view.window.height,
        rgb8: lowres::upsample_nearest(&rgb, view, scale).into_iter().flatten().collect(),
        depth: lowres::upsample_nearest(&tile.depth, view, scale),
    }
}

/// Adds a frame to the tile's running sum and returns the averaged image.
fn accumulate(name: &str, a: &mut Accumulator, mut frame: Frame) -> TileResult {
    if a.sum.len() != frame.color.len() {
        a.sum = vec![[0.0; 3]; frame.color.len()];
        a.frames = 0;
    }
    a.frames += 1;
    let k = a.frames as f32;
    for (s, c) in a.sum.iter_mut().zip(frame.color.iter_mut()) {
        for i in 0..3 {
            s[i] += c[i];
            c[i] = s[i] / k;
        }
    }
    let depth =
        frame.depth.iter().zip(&frame.hit).map(|(&d, &h)| if h { d } else { f32::INFINITY }).collect();
    TileResult {
        name: name.to_string(),
        width: frame.width,
        height: frame.height,
        rgb8: srgb8(&frame),
        depth,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use isowall_render::gpu::GpuError;
    use isowall_wall::{Camera, Window};

    /// The render thread on a small scene, or `None` (after a message) where no Vulkan adapter
    /// exists; under `CI=true` a missing adapter fails instead (GPU tests never skip silently).
    fn renderer() -> Option<(TileRenderer, tokio::sync::mpsc::UnboundedReceiver<Result<JobResult, String>>)> {
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
        Some((TileRenderer::start(RenderVolume::Whole(volume), None, tx).unwrap(), rx))
    }

    /// The whole image of 96 x 72 pixels as two tiles split at an odd column (not a multiple of
    /// the scale), rendered by the render thread at `scale` and put back together.
    fn wall_image(
        r: &TileRenderer,
        rx: &mut tokio::sync::mpsc::UnboundedReceiver<Result<JobResult, String>>,
        whole: &View,
        settings: &RenderSettings,
        scale: u32,
    ) -> Vec<u8> {
        let (w, h) = whole.full;
        let left = View { window: Window { x: 0, y: 0, width: 47, height: h }, ..*whole };
        let right = View { window: Window { x: 47, y: 0, width: w - 47, height: h }, ..*whole };
        let job = TileJob {
            frame_id: scale as u64,
            tiles: vec![("left".into(), left), ("right".into(), right)],
            settings: *settings,
            accumulate_frame: 0,
            bricks: Vec::new(),
            scale,
        };
        r.handle().submit(job).unwrap();
        let result = rx.blocking_recv().unwrap().unwrap();
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
        let camera = Camera {
            eye: glam::DVec3::new(-30.0, -60.0, 70.0),
            target: glam::DVec3::new(24.0, 24.0, 16.0),
            up: glam::DVec3::Z,
            fov_y_deg: 40.0,
        };
        let mut settings = RenderSettings::new(0.0);
        settings.ao.samples = 2;
        let whole = View::whole(camera, 96, 72);
        let full = wall_image(&r, &mut rx, &whole, &settings, 1);
        let halved = wall_image(&r, &mut rx, &whole, &settings, 2);

        // The half-size image rendered alone (48 x 36, same camera, same sample pattern seeding),
        // upsampled nearest: every full pixel (x, y) takes the half pixel (x / 2, y / 2).
        let gpu = GpuRenderer::new().unwrap();
        let src: isowall_volume::VolumeSource = "procedural:sphere-over-plane:48".parse().unwrap();
        let gv = gpu.upload(&src.load(None).unwrap()).unwrap();
        let half = gpu.render(&gv, &View::whole(camera, 48, 36), &settings, None).unwrap().frame;
        let half = srgb8(&half);
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
}
