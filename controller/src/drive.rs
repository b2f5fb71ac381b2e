//! The controller's commands that talk to a wall: `keygen`, `up`, `orbit`, `snapshot`.

use crate::local::LocalDaemons;
use crate::wall::{compose, report, Wall};
use anyhow::{anyhow, Context, Result};
use clap::Args;
use glam::{DQuat, DVec3};
use isowall_volume::VolumeSource;
use isowall_wall::config::WallConfig;
use isowall_wall::{Camera, RenderSettings};
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(Args)]
pub struct KeygenArgs {
    /// The wall config: its nodes get certificates, written to its `[certificates] dir`
    #[arg(long, value_name = "FILE")]
    pub config: PathBuf,
    /// Write here instead of the config's certificate folder
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
}

#[derive(Args)]
pub struct OrbitOptions {
    /// Frames to drive
    #[arg(long, default_value_t = 90)]
    pub frames: u64,
    /// Orbit step per frame, degrees about the world's up axis through the target
    #[arg(long, default_value_t = 4.0)]
    pub degrees_per_frame: f64,
    /// Frames per second at most (0: as fast as the wall swaps)
    #[arg(long, default_value_t = 0.0)]
    pub fps: f64,
}

#[derive(Args)]
pub struct UpArgs {
    /// The wall config (TOML)
    pub config: PathBuf,
    #[command(flatten)]
    pub orbit: OrbitOptions,
    /// Write a whole-wall snapshot of the last frame here (PNG)
    #[arg(long, value_name = "FILE.png")]
    pub snapshot: Option<PathBuf>,
    /// How long to wait for the nodes to come up, seconds
    #[arg(long, default_value_t = 120)]
    pub start_timeout: u64,
    /// Where local nodes show their tiles (`isowalld run --display`): offscreen (snapshots
    /// only), window (a window per tile; needs a display), or auto
    #[arg(long, default_value = "offscreen", value_parser = ["offscreen", "window", "auto"])]
    pub display: String,
    /// With --display window|auto: windows at the tiles' sizes instead of fullscreen (a wall
    /// tried out on one desktop)
    #[arg(long)]
    pub windowed: bool,
}

#[derive(Args)]
pub struct OrbitArgs {
    /// The wall config (TOML)
    pub config: PathBuf,
    #[command(flatten)]
    pub orbit: OrbitOptions,
}

#[derive(Args)]
pub struct SnapshotArgs {
    /// The wall config (TOML)
    pub config: PathBuf,
    /// The whole-wall image to write (PNG)
    #[arg(long, value_name = "FILE.png")]
    pub out: PathBuf,
}

pub(crate) fn load(config: &std::path::Path) -> Result<WallConfig> {
    WallConfig::load(config).map_err(|e| anyhow!("{e}"))
}

pub fn keygen(a: &KeygenArgs) -> Result<()> {
    let config = load(&a.config)?;
    let dir = a.out.clone().unwrap_or_else(|| config.cert_dir());
    let names: Vec<String> = config.nodes.iter().map(|n| n.name.clone()).collect();
    let files = isowall_net::keygen(&dir, &config.wall.name, &names)?;
    println!(
        "wrote {} files to {} (keep ca.key off the wall: it signs certificates)",
        files.len(),
        dir.display()
    );
    Ok(())
}

/// The wall camera and render settings for the configured volume (the controller reads the volume
/// only for its box and default iso).
pub(crate) fn scene(config: &WallConfig) -> Result<(Camera, RenderSettings)> {
    scene_and_range(config).map(|(c, s, _)| (c, s))
}

/// [`scene`] and the volume's value range.
pub(crate) fn scene_and_range(config: &WallConfig) -> Result<(Camera, RenderSettings, (f64, f64))> {
    let source: VolumeSource = config.volume_source().parse()?;
    let raw = match (&config.volume.dims, &config.volume.voxel_type) {
        (Some(dims), Some(t)) => Some(isowall_volume::io::RawSpec {
            dims: *dims,
            voxel: t.parse().map_err(|e: String| anyhow!("[volume] type: {e}"))?,
            spacing: DVec3::from_array(config.volume.spacing.unwrap_or([1.0; 3])),
            big_endian: false,
            header_bytes: 0,
        }),
        _ => None,
    };
    let bar = crate::progress::spinner(format!("loading volume {source}"));
    let volume = source.load(raw.as_ref()).with_context(|| format!("cannot load volume {source}"));
    bar.finish_and_clear();
    let volume = volume?;
    let (lo, hi) = volume.value_range();
    let iso = config.volume.iso.or(source.natural_iso()).unwrap_or(0.5 * (lo as f64 + hi as f64));
    Ok((
        config.camera_for(volume.box_min(), volume.box_max()),
        config.render_settings(iso),
        (lo as f64, hi as f64),
    ))
}

/// The camera of frame `k` of an orbit: the eye turned about the world up axis (+z) through the
/// target.
pub fn orbit_camera(base: &Camera, k: u64, degrees_per_frame: f64) -> Camera {
    let rot = DQuat::from_rotation_z((k as f64 * degrees_per_frame).to_radians());
    Camera { eye: base.target + rot * (base.eye - base.target), up: rot * base.up, ..*base }
}

/// Drives the orbit; returns how long its frames took and when the first swap was released.
async fn drive(
    wall: &mut Wall,
    base: &Camera,
    settings: &RenderSettings,
    o: &OrbitOptions,
) -> Result<(Duration, Option<Instant>)> {
    wall.sync_clocks(5).await;
    let start = Instant::now();
    let period = (o.fps > 0.0).then(|| Duration::from_secs_f64(1.0 / o.fps));
    let mut first_swap = None;
    for k in 0..o.frames {
        if let Some(p) = period {
            tokio::time::sleep_until((start + p.mul_f64(k as f64)).into()).await;
        }
        wall.frame(&orbit_camera(base, k, o.degrees_per_frame), settings).await?;
        if k == 0 {
            first_swap = Some(Instant::now());
        }
        if k % 30 == 29 {
            wall.sync_clocks(1).await;
        }
    }
    let elapsed = start.elapsed();
    wall.settle().await;
    Ok((elapsed, first_swap))
}

pub(crate) fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("async runtime")
}

pub(crate) async fn write_snapshot(wall: &mut Wall, out: &std::path::Path) -> Result<()> {
    let tiles = wall.snapshot().await;
    let (w, h, rgb) = compose(&wall.config, &tiles);
    image::save_buffer(out, &rgb, w, h, image::ExtendedColorType::Rgb8)
        .with_context(|| format!("cannot write {}", out.display()))?;
    let got: usize = tiles.values().map(Vec::len).sum();
    println!("wrote {} ({w}x{h}, {got} of {} tiles)", out.display(), wall.config.tiles.len());
    Ok(())
}

pub fn up(a: &UpArgs) -> Result<()> {
    let started = Instant::now();
    let config = load(&a.config)?;
    let (base, settings) = scene(&config)?;
    let log_dir = config.resolve("logs");
    let mut daemons = LocalDaemons::start(&config, &log_dir, &a.display, a.windowed)?;
    eprintln!("isowall: starting wall '{}': {} local node(s)", config.wall.name, daemons.len());
    let rt = runtime()?;
    let result = rt.block_on(async {
        let mut wall = Wall::connect(config, Duration::from_secs(a.start_timeout)).await.map_err(|e| {
            let dead = daemons.exited();
            if dead.is_empty() {
                e
            } else {
                let list: Vec<String> = dead.iter().map(|(n, s)| format!("{n} ({s})")).collect();
                anyhow!("{e:#}\nlocal daemons that exited: {} (see {})", list.join(", "), log_dir.display())
            }
        })?;
        eprintln!("isowall: wall up in {:.2} s", started.elapsed().as_secs_f64());
        let (elapsed, first_swap) = drive(&mut wall, &base, &settings, &a.orbit).await?;
        if let Some(t) = first_swap {
            println!("first swap released {:.2} s after `isowall up` started", (t - started).as_secs_f64());
        }
        print!("{}", report(&wall, elapsed));
        if let Some(out) = &a.snapshot {
            write_snapshot(&mut wall, out).await?;
        }
        wall.close("the controller is done").await;
        Ok::<(), anyhow::Error>(())
    });
    drop(daemons);
    result
}

pub fn orbit(a: &OrbitArgs) -> Result<()> {
    let config = load(&a.config)?;
    let (base, settings) = scene(&config)?;
    runtime()?.block_on(async {
        let mut wall = Wall::connect(config, Duration::from_secs(10)).await?;
        let (elapsed, _) = drive(&mut wall, &base, &settings, &a.orbit).await?;
        print!("{}", report(&wall, elapsed));
        wall.close("the controller is done").await;
        Ok(())
    })
}

pub fn snapshot(a: &SnapshotArgs) -> Result<()> {
    let config = load(&a.config)?;
    runtime()?.block_on(async {
        let mut wall = Wall::connect(config, Duration::from_secs(10)).await?;
        write_snapshot(&mut wall, &a.out).await?;
        wall.close("snapshot taken").await;
        Ok(())
    })
}
