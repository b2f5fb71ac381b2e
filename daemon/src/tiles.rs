//! The render thread of a wall node: it alone owns the GPU device. It renders the node's tiles for
//! each frame state it is sent, keeps progressive accumulation going while the state is unchanged
//! (the frame index advances the sample pattern; any change restarts the average), and hands back
//! 8-bit sRGB images of the tiles.

use anyhow::{Context, Result};
use isowall_render::environment::Environment;
use isowall_render::gpu::GpuRenderer;
use isowall_render::output::srgb8;
use isowall_render::Frame;
use isowall_volume::Volume;
use isowall_wall::{RenderSettings, View};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// One frame to render: the views of the node's tiles, the settings, and where in the
/// progressive accumulation it stands (0 restarts it).
pub struct TileJob {
    pub frame_id: u64,
    pub tiles: Vec<(String, View)>,
    pub settings: RenderSettings,
    pub accumulate_frame: u32,
}

/// A tile's image of a frame: 8-bit sRGB, rows top to bottom.
#[derive(Clone)]
pub struct TileResult {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub rgb8: Vec<u8>,
}

pub struct JobResult {
    pub frame_id: u64,
    pub tiles: Vec<TileResult>,
    pub render_time: Duration,
}

/// Handle to the render thread.
pub struct TileRenderer {
    jobs: mpsc::Sender<TileJob>,
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
        volume: Volume,
        env: Option<Environment>,
        results: tokio::sync::mpsc::UnboundedSender<Result<JobResult, String>>,
    ) -> Result<TileRenderer> {
        let (jobs, rx) = mpsc::channel::<TileJob>();
        let (ready_tx, ready_rx) = mpsc::channel::<Result<String, String>>();
        std::thread::Builder::new()
            .name("render".into())
            .spawn(move || {
                let setup = (|| -> Result<_, String> {
                    let gpu = GpuRenderer::new().map_err(|e| e.to_string())?;
                    let gv = gpu.upload(&volume).map_err(|e| e.to_string())?;
                    let genv = env
                        .as_ref()
                        .map(|e| gpu.upload_environment(e))
                        .transpose()
                        .map_err(|e| e.to_string())?;
                    Ok((gpu, gv, genv))
                })();
                let (gpu, gv, genv) = match setup {
                    Ok(s) => {
                        let _ = ready_tx.send(Ok(s.0.adapter_name().to_string()));
                        s
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                        return;
                    }
                };
                drop(volume);
                let mut acc: Vec<Accumulator> = Vec::new();
                for job in rx {
                    let start = Instant::now();
                    let mut out = Vec::new();
                    let mut failed = None;
                    if job.accumulate_frame == 0 || acc.len() != job.tiles.len() {
                        acc = job.tiles.iter().map(|_| Accumulator { sum: Vec::new(), frames: 0 }).collect();
                    }
                    for ((name, view), a) in job.tiles.iter().zip(acc.iter_mut()) {
                        let mut s = job.settings;
                        s.ao.frame = s.ao.frame.wrapping_add(job.accumulate_frame);
                        match gpu.render(&gv, view, &s, genv.as_ref()) {
                            Ok(r) => out.push(accumulate(name, a, r.frame)),
                            Err(e) => {
                                failed = Some(format!("tile {name}: {e}"));
                                break;
                            }
                        }
                    }
                    let msg = match failed {
                        Some(e) => Err(e),
                        None => {
                            Ok(JobResult { frame_id: job.frame_id, tiles: out, render_time: start.elapsed() })
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
                Ok(TileRenderer { jobs })
            }
            Ok(Err(e)) => anyhow::bail!("GPU set-up failed: {e}"),
            Err(_) => anyhow::bail!("the render thread ended during set-up"),
        }
    }

    pub fn submit(&self, job: TileJob) -> Result<()> {
        self.jobs.send(job).map_err(|_| anyhow::anyhow!("the render thread has stopped"))
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
    TileResult { name: name.to_string(), width: frame.width, height: frame.height, rgb8: srgb8(&frame) }
}
