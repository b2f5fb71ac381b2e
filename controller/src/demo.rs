//! `isowall demo CONFIG --path FILE`: plays a scripted camera path (`path.rs`) on the wall with a
//! fixed frame clock (frame i shows the path at i / fps seconds, never the wall clock), once or
//! `--loop`ed, paced to `--fps` on screen, or as fast as the wall goes when recording: `--record
//! DIR` writes every frame's whole-wall image (bezels dark) as DIR/frame-NNNNNN.png, so a
//! recorded run is the same, file for file, every time.

use crate::drive::{load, runtime, scene_with_box};
use crate::path::{frame_time, CameraPath, Defaults};
use crate::picture::compose;
use crate::report::report;
use crate::start::{self, StartArgs};
use crate::wall::FrameRequest;
use anyhow::{bail, Context, Result};
use clap::Args;
use glam::DVec3;
use isowall_model::render_state::MAX_AO_SAMPLES;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(Args)]
pub struct DemoArgs {
    /// The wall config (TOML)
    pub config: PathBuf,
    /// The camera path: [[key]] tables with time, eye, target, up, fov, iso, ao_samples, step
    #[arg(long, value_name = "FILE")]
    pub path: PathBuf,
    /// The frame clock: frame i shows the path at i / FPS seconds (one frame a day to 1000)
    #[arg(long, default_value_t = 30.0, value_parser = crate::drive::parse_fps)]
    pub fps: f64,
    /// Start again at the end, until stopped (or --frames)
    #[arg(long = "loop")]
    pub looping: bool,
    /// Stop after this many frames (with or without --loop)
    #[arg(long)]
    pub frames: Option<u64>,
    /// Write every frame's whole-wall image to DIR/frame-NNNNNN.png (not paced: as fast as the
    /// wall renders; the images do not depend on how fast that is)
    #[arg(long, value_name = "DIR")]
    pub record: Option<PathBuf>,
    /// Do not pace to --fps on screen: as fast as the wall swaps (the frame clock stays fixed)
    #[arg(long)]
    pub unpaced: bool,
    #[command(flatten)]
    pub start: StartArgs,
}

/// Says, before the wall starts, where a camera path looks away from this wall's volume (a path
/// written for another volume plays with the surface in a corner or out of view), and how to
/// write one for it; the path plays anyway.
pub(crate) fn warn_misfits(path: &CameraPath, file: &Path, volume: (DVec3, DVec3), object: (DVec3, DVec3)) {
    let misfits = path.misfits(file, volume, object);
    if misfits.is_empty() {
        return;
    }
    for m in &misfits {
        tracing::warn!("camera path: {m}");
    }
    let c = ((object.0 + object.1) * 0.5).to_array();
    tracing::warn!(
        "camera path {}: it was written for another volume? Aim its targets at the object's centre \
         {c:?} and set its eyes around it (docs/operating.md, \"A camera path for your volume\")",
        file.display()
    );
}

pub fn demo(a: &DemoArgs) -> Result<()> {
    if !(a.fps.is_finite() && a.fps > 0.0) {
        bail!("--fps must be a positive number, not {}", a.fps);
    }
    let config = load(&a.config)?;
    let ((base, settings, _, framing), volume_box) = scene_with_box(&config)?;
    let defaults = Defaults { fov_y_deg: base.fov_y_deg, iso: settings.iso, ao_samples: settings.ao.samples };
    let path = CameraPath::load(&a.path, defaults, MAX_AO_SAMPLES)?;
    warn_misfits(&path, &a.path, volume_box, framing.fit);
    if let Some(dir) = &a.record {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let paced = a.record.is_none() && !a.unpaced;
    runtime()?.block_on(async {
        let (daemons, mut wall) = start::open(config, &a.start).await?;
        wall.sync_clocks(5).await;
        let started = Instant::now();
        let period = Duration::from_secs_f64(1.0 / a.fps);
        let mut i = 0u64;
        // Ctrl-C ends this command cleanly (its local nodes stop when it drops them).
        crate::local::interrupt_handled_by_command();
        let stop = tokio::signal::ctrl_c();
        tokio::pin!(stop);
        loop {
            if a.frames.is_some_and(|n| i >= n) {
                break;
            }
            let Some(t) = frame_time(i, a.fps, path.duration(), a.looping) else { break };
            let key = path.at(t);
            let mut s = settings;
            s.iso = key.iso;
            s.ao.samples = key.ao_samples;
            if paced {
                tokio::select! {
                    _ = tokio::time::sleep_until((started + period.mul_f64(i as f64)).into()) => {}
                    _ = &mut stop => break,
                }
            }
            let camera = key.camera();
            let request = FrameRequest::new(camera, s).at_time_step(key.step);
            tokio::select! {
                r = wall.frame(&request) => r?,
                _ = &mut stop => break,
            }
            if let Some(dir) = &a.record {
                let tiles = wall.snapshot().await;
                let id = wall.last_frame_id();
                let stale: Vec<String> = wall
                    .config
                    .tiles
                    .iter()
                    .filter(|t| !tiles.values().flatten().any(|img| img.name == t.name && img.frame_id == id))
                    .map(|t| t.name.clone())
                    .collect();
                if !stale.is_empty() {
                    bail!("frame {i}: no image of this frame from tile(s) {}", stale.join(", "));
                }
                let (w, h, rgb) = compose(&wall.config, &tiles);
                let out = dir.join(format!("frame-{i:06}.png"));
                image::save_buffer(&out, &rgb, w, h, image::ExtendedColorType::Rgb8)
                    .with_context(|| format!("cannot write {}", out.display()))?;
            }
            if i % 30 == 29 {
                wall.sync_clocks(1).await;
            }
            i += 1;
        }
        let elapsed = started.elapsed();
        wall.settle().await;
        print!("{}", report(&wall, elapsed));
        if let Some(dir) = &a.record {
            println!("wrote {i} frames to {}", dir.display());
        }
        wall.close("the demo is over").await;
        drop(daemons);
        Ok(())
    })
}
