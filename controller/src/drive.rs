//! The controller's commands that talk to a wall: `keygen`, `up`, `orbit`, `snapshot`.

use crate::local::LocalDaemons;
use crate::picture::compose;
use crate::report::{quantile, report};
use crate::wall::{FrameRequest, Wall};
use anyhow::{anyhow, Context, Result};
use clap::Args;
use isowall_model::config::WallConfig;
use isowall_model::{Camera, Governor, Motion, RenderSettings, ViewFraming};
use isowall_net::CaMode;
use isowall_volume::brick_cache::BrickSource;
use isowall_volume::io::ome_zarr::{is_zarr, OmeZarr};
use isowall_volume::{BlockMinMax, Orientation, VolumeInfo, VolumeSource};
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
    /// Days the node and controller certificates are valid, from now
    #[arg(long, value_name = "N", default_value_t = isowall_net::keygen::DEFAULT_DAYS)]
    pub days: u32,
    /// Keep the folder's CA and issue the node and controller certificates again from it (new
    /// keys), e.g. before they expire; copy each node its new NODE.pem and NODE.key
    #[arg(long, conflicts_with = "force")]
    pub renew: bool,
    /// Replace the folder's CA: every certificate it signed stops working (copy every node's new
    /// files). Without it keygen refuses to touch a folder that holds a CA
    #[arg(long)]
    pub force: bool,
}

#[derive(Args)]
pub struct OrbitOptions {
    /// Frames to drive
    #[arg(long, default_value_t = 90)]
    pub frames: u64,
    /// Orbit step per frame, degrees about the world's up axis through the target
    #[arg(long, default_value_t = 4.0, value_parser = isowall_model::cli_args::degrees, allow_negative_numbers = true)]
    pub degrees_per_frame: f64,
    /// Frames per second at most (0: as fast as the wall swaps; else one frame a day to 1000)
    #[arg(long, default_value_t = 0.0, value_parser = parse_fps)]
    pub fps: f64,
    /// Quality governor: choose the AO samples per frame (at 1 sample, a lower internal
    /// resolution, 1/2 to 1/4) for this frame time (ms) while the camera moves, then hold them
    /// at full resolution while it is still (overrides `[render] target_frame_ms`)
    #[arg(long, value_name = "MS")]
    pub target_frame_ms: Option<f64>,
    /// After the orbit, this many frames with the camera still: the nodes refine progressively
    #[arg(long, default_value_t = 0)]
    pub still_frames: u64,
    /// For fault tests: after every frame's swap, the whole-wall snapshot to
    /// DIR/frame-NNNNNN.png (NNNNNN the frame id; a node down shows its placeholder) and a line
    /// `ID UNIX_MS TILE=FRAME_ID...` (the tiles that answered) in DIR/frames.txt
    #[arg(long, value_name = "DIR", hide = true)]
    pub record_frames: Option<PathBuf>,
    /// Time-varying volumes: the time step of the first frame (wrapped at the step count)
    #[arg(long, default_value_t = 0)]
    pub step: u32,
    /// Time-varying volumes: play, one time step a frame from --step (wrapping)
    #[arg(long)]
    pub play: bool,
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
    /// Serve the wall's metrics for Prometheus at http://ADDR/metrics while the run lasts (text
    /// format 0.0.4). ADDR must be a loopback address, e.g. 127.0.0.1:9184 (port 0: any free
    /// port, printed): there is no token here; a Prometheus on another machine scrapes
    /// `isowall console --token T`
    #[arg(long, value_name = "ADDR", value_parser = crate::metrics::loopback_addr)]
    pub metrics: Option<std::net::SocketAddr>,
    /// With --metrics: after the run (its nodes stopped), go on serving its final counts this
    /// many seconds, so that a scrape sees them (Prometheus scrapes every 15 s by default)
    #[arg(long, value_name = "S", default_value_t = 0, requires = "metrics", value_parser = clap::value_parser!(u64).range(0..=86400))]
    pub metrics_hold: u64,
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
    let mode = match (a.renew, a.force) {
        (true, _) => CaMode::Renew,
        (false, true) => CaMode::Replace,
        (false, false) => CaMode::New,
    };
    let report = isowall_net::keygen(&dir, &config.wall.name, &names, mode, a.days)?;
    let what = if mode == CaMode::Renew { "renewed the certificates: wrote" } else { "wrote" };
    println!(
        "{what} {} files to {}; certificates valid until {}, the CA until {} (keep ca.key off the \
         wall: it signs certificates)",
        report.files.len(),
        dir.display(),
        report.valid_until,
        report.ca_valid_until
    );
    Ok(())
}

/// The wall camera and render settings for the configured volume (the controller reads the volume
/// only for its box, from the header, and its value range, a z-slice at a time).
pub(crate) fn scene(config: &WallConfig) -> Result<(Camera, RenderSettings)> {
    scene_and_range(config).map(|(c, s, _)| (c, s))
}

/// [`scene`] and the volume's value range.
pub(crate) fn scene_and_range(config: &WallConfig) -> Result<(Camera, RenderSettings, (f64, f64))> {
    scene_range_and_framing(config).map(|(c, s, r, _)| (c, s, r))
}

/// [`scene_and_range`] and what the named views frame (the object's box at the iso, the volume's
/// orientation, the wall image's size).
pub(crate) fn scene_range_and_framing(
    config: &WallConfig,
) -> Result<(Camera, RenderSettings, (f64, f64), ViewFraming)> {
    scene_with_box(config).map(|(scene, _)| scene)
}

/// A box in world units: its least and greatest corners.
pub(crate) type WorldBox = (glam::DVec3, glam::DVec3);

/// The wall camera, the render settings, the volume's value range and what the named views frame.
pub(crate) type Scene = (Camera, RenderSettings, (f64, f64), ViewFraming);

/// [`scene_range_and_framing`] and the volume's box, which a camera path is checked against.
pub(crate) fn scene_with_box(config: &WallConfig) -> Result<(Scene, WorldBox)> {
    let source: VolumeSource = config.volume_source().parse()?;
    let raw = config.raw_spec().map_err(|e| anyhow!("{e}"))?;
    let bar = crate::progress::spinner(format!("reading volume {source}"));
    let limit = match config.volume.max_bytes {
        Some(bytes) => isowall_volume::io::VolumeLimit::new(bytes, "[volume] max_bytes"),
        None => isowall_volume::io::VolumeLimit::default(),
    };
    // What the nodes would refuse, refused here from the header too; then only the value range
    // is kept of the data (the block grid), never the whole volume. Time steps: their first
    // step, read within the limit as a screen-space node reads it, gives the box and the range.
    let scanned = source.time_steps().map_err(anyhow::Error::from).and_then(|steps| {
        if steps > 1 {
            let v = source.load_step_within(raw.as_ref(), 0, &limit)?;
            let info =
                VolumeInfo { name: v.name.clone(), dims: v.dims(), spacing: v.spacing(), origin: v.origin() };
            let blocks = BlockMinMax::new(&v, BlockMinMax::DEFAULT_BLOCK);
            return Ok((info, blocks, v.orientation()));
        }
        // A store `convert` wrote: its metadata and per-brick min/max, never a voxel (it may be
        // larger than memory; the nodes read it through their brick caches).
        if let Some(scene) = store_scene(&source)? {
            if config.brick_budgets().is_none() {
                let [x, y, z] = scene.0.dims;
                let voxels = (x as u64).saturating_mul(y as u64).saturating_mul(z as u64);
                limit.check(voxels, &format!("{source} ({x}x{y}x{z})")).map_err(|e| anyhow!("{e}"))?;
            }
            return Ok(scene);
        }
        let stream = source.stream(raw.as_ref())?;
        let info = stream.info().clone();
        let [x, y, z] = info.dims;
        let voxels = (x as u64).saturating_mul(y as u64).saturating_mul(z as u64);
        limit.check(voxels, &format!("{source} ({x}x{y}x{z})")).map_err(|e| anyhow!("{e}"))?;
        let blocks = stream.block_minmax(BlockMinMax::DEFAULT_BLOCK)?;
        Ok((info, blocks, stream.orientation()))
    });
    bar.finish_and_clear();
    let (info, blocks, orientation) = scanned.with_context(|| format!("cannot read volume {source}"))?;
    let (lo, hi) = blocks.value_range();
    let iso = source
        .checked_iso(config.volume.iso, (lo, hi))
        .map_err(|e| anyhow!("{}: [volume] iso {e} ({source})", config.path.display()))?;
    // The default camera frames the surface at the iso (the blocks that reach it), as
    // `isowalld render` does.
    let volume_box = (info.box_min(), info.box_max());
    let fit = blocks.object_box(iso, info.dims, info.origin, info.spacing).unwrap_or(volume_box);
    Ok((
        (
            config.camera_framing(volume_box, fit, orientation),
            config.render_settings(iso),
            (lo as f64, hi as f64),
            ViewFraming { fit, orientation, size: config.wall_size() },
        ),
        volume_box,
    ))
}

/// An OME-Zarr store's grid, block ranges (its bricks') and orientation, from its metadata and
/// per-brick min/max; `None` where `source` is not a store or the store has no min/max (another
/// program wrote it: then it is scanned as any other file).
fn store_scene(source: &VolumeSource) -> Result<Option<(VolumeInfo, BlockMinMax, Option<Orientation>)>> {
    let VolumeSource::File(path) = source else {
        return Ok(None);
    };
    if !is_zarr(path) {
        return Ok(None);
    }
    let store = OmeZarr::open(path)?;
    let orientation = store.patient_axes().and_then(|p| p.orientation());
    let bricks = store.into_bricks(0)?;
    Ok(bricks.level0_blocks().map(|blocks| (bricks.level0_info(), blocks, orientation)))
}

/// The number of time steps of the configured volume (1 for a volume without time steps), from
/// file names or a header.
pub(crate) fn time_steps(config: &WallConfig) -> Result<u32> {
    let source: VolumeSource = config.volume_source().parse()?;
    let n = source.time_steps().with_context(|| format!("volume {source}"))?;
    Ok(u32::try_from(n).unwrap_or(u32::MAX).max(1))
}

/// The camera of frame `k` of an orbit: the eye turned about the world up axis (+z) through the
/// target.
pub fn orbit_camera(base: &Camera, k: u64, degrees_per_frame: f64) -> Camera {
    base.yawed(k as f64 * degrees_per_frame)
}

/// The governor of a drive, if a target is set (the flag before the config): it starts at the
/// configured samples (at least 1) and chooses 1 ..= MAX_AO_SAMPLES. With the flag's target, the
/// config's `denoise = "auto"` filters as with a target in the config.
fn governor(
    config: &WallConfig,
    settings: &mut RenderSettings,
    o: &OrbitOptions,
) -> Result<Option<Governor>> {
    let Some(target) = o.target_frame_ms.or(config.render.target_frame_ms) else {
        return Ok(None);
    };
    settings.denoise = config.denoise(Some(target));
    let g = Governor::new(target, settings.ao.samples.max(1), 1, isowall_model::render_state::MAX_AO_SAMPLES)
        .map_err(|e| anyhow!("--target-frame-ms: {e}"))?;
    Ok(Some(g))
}

/// What a governed drive did, in memory bounded however long it runs (a demo loops for hours): the
/// frame times of the last [`HISTORY`](crate::wall::HISTORY) moving frames after the first five
/// (the governor's settling), the samples of the first and the last [`GovernorLog::SAMPLES_SHOWN`]
/// frames, and counts.
#[derive(Default)]
pub(crate) struct GovernorLog {
    /// Frames seen, and moving frames after the first five.
    frames: u64,
    moving: u64,
    /// Frame times (frame state sent -> swap released) of the last moving frames after five.
    moving_ms: std::collections::VecDeque<Duration>,
    /// (samples, internal resolution divisor) per frame.
    first_samples: Vec<(u32, u32)>,
    last_samples: std::collections::VecDeque<(u32, u32)>,
    /// Still frames, and the samples of the last one.
    still: u64,
    still_samples: u32,
}

impl GovernorLog {
    /// Samples of this many frames at each end of the drive are reported.
    const SAMPLES_SHOWN: usize = 40;
    /// Moving frames the governor settles in (left out of the quantiles).
    const SETTLING: u64 = 5;

    fn push(&mut self, samples: u32, scale: u32, frame: Duration, motion: Motion) {
        self.frames += 1;
        if self.first_samples.len() < Self::SAMPLES_SHOWN {
            self.first_samples.push((samples, scale));
        } else {
            if self.last_samples.len() == Self::SAMPLES_SHOWN {
                self.last_samples.pop_front();
            }
            self.last_samples.push_back((samples, scale));
        }
        match motion {
            Motion::Moving => {
                self.moving += 1;
                if self.moving > Self::SETTLING {
                    if self.moving_ms.len() == crate::wall::HISTORY {
                        self.moving_ms.pop_front();
                    }
                    self.moving_ms.push_back(frame);
                }
            }
            Motion::Still => {
                self.still += 1;
                self.still_samples = samples;
            }
        }
    }

    /// The samples per frame (`/N`: rendered at 1/N resolution), the frames between the first and
    /// the last ones shown elided.
    fn samples_text(&self) -> String {
        let one = |&(samples, scale): &(u32, u32)| {
            if scale > 1 {
                format!("{samples}/{scale}")
            } else {
                samples.to_string()
            }
        };
        let list = |v: &mut dyn Iterator<Item = &(u32, u32)>| v.map(one).collect::<Vec<_>>().join(" ");
        let skipped = self.frames - (self.first_samples.len() + self.last_samples.len()) as u64;
        let mut s = list(&mut self.first_samples.iter());
        if skipped > 0 {
            s += &format!(" ... ({skipped} frames) ...");
        }
        if !self.last_samples.is_empty() {
            s += " ";
            s += &list(&mut self.last_samples.iter());
        }
        s
    }
}

/// Drives the orbit, then `still_frames` frames at its last camera, calling `after_frame(k, wall)`
/// after frame k's swap; returns how long its frames took, when the first swap was released, and
/// the governor's frames (when one is set).
pub(crate) async fn drive(
    wall: &mut Wall,
    base: &Camera,
    settings: &RenderSettings,
    o: &OrbitOptions,
    mut governor: Option<Governor>,
    after_frame: &mut dyn FnMut(u64, &Wall),
) -> Result<(Duration, Option<Instant>, GovernorLog)> {
    wall.sync_clocks(5).await;
    let start = Instant::now();
    let period = (o.fps > 0.0).then(|| Duration::from_secs_f64(1.0 / o.fps));
    let mut first_swap = None;
    let mut governed = GovernorLog::default();
    let settings = *settings;
    let total = o.frames + o.still_frames;
    let steps = time_steps(&wall.config)?;
    for k in 0..total {
        let played = if o.play { k } else { 0 };
        let step = ((u64::from(o.step) + played) % u64::from(steps)) as u32;
        if let Some(p) = period {
            tokio::time::sleep_until((start + p.mul_f64(k as f64)).into()).await;
        }
        let camera = orbit_camera(base, k.min(o.frames.saturating_sub(1)), o.degrees_per_frame);
        let request = FrameRequest::new(camera, settings).at_time_step(step).governed(governor.as_ref());
        wall.frame(&request).await?;
        if let Some(dir) = &o.record_frames {
            record_frame(wall, dir).await?;
        }
        if let Some(g) = &mut governor {
            // The next frame moves while the orbit goes on.
            let motion = if k + 1 < o.frames { Motion::Moving } else { Motion::Still };
            let frame = wall.releases.last().map_or(Duration::ZERO, |r| r.1);
            governed.push(request.settings.ao.samples, request.scale, frame, motion);
            g.observe(frame.as_secs_f64() * 1e3, motion);
        }
        if k == 0 {
            first_swap = Some(Instant::now());
        }
        after_frame(k, wall);
        if k % 30 == 29 {
            wall.sync_clocks(1).await;
        }
    }
    let elapsed = start.elapsed();
    wall.settle().await;
    Ok((elapsed, first_swap, governed))
}

/// `--record-frames`: the snapshot of the frame just released once it is presented, and its line
/// in frames.txt.
async fn record_frame(wall: &mut Wall, dir: &std::path::Path) -> Result<()> {
    use std::io::Write;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let id = wall.last_frame_id();
    let tiles = wall.snapshot().await;
    let (w, h, rgb) = compose(&wall.config, &tiles);
    let out = dir.join(format!("frame-{id:06}.png"));
    image::save_buffer(&out, &rgb, w, h, image::ExtendedColorType::Rgb8)
        .with_context(|| format!("cannot write {}", out.display()))?;
    let unix_ms =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_millis();
    let mut line = format!("{id} {unix_ms}");
    for t in tiles.values().flatten() {
        line += &format!(" {}={}", t.name, t.frame_id);
    }
    let list = dir.join("frames.txt");
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&list)
        .with_context(|| format!("cannot write {}", list.display()))?;
    writeln!(f, "{line}").with_context(|| format!("cannot write {}", list.display()))?;
    Ok(())
}

/// The governor's report: its target, and the frame times it achieved while the camera moved
/// (after the first five frames, its settling; the last [`HISTORY`](crate::wall::HISTORY) of
/// them) with the samples it chose.
fn governor_report(target: Option<&Governor>, log: &GovernorLog) -> String {
    let Some(g) = target else {
        return String::new();
    };
    let ms: Vec<Duration> = log.moving_ms.iter().copied().collect();
    let fmt = |d: Option<Duration>| d.map_or("-".to_string(), |d| format!("{:.1} ms", d.as_secs_f64() * 1e3));
    let kept = if ms.len() as u64 + GovernorLog::SETTLING < log.moving {
        format!("last {} of {} frames", ms.len(), log.moving.saturating_sub(GovernorLog::SETTLING))
    } else {
        format!("{} frames", ms.len())
    };
    let mut s = format!(
        "governor: target {:.1} ms; moving frames after {}: p50 {} p90 {} ({kept}); samples per frame (/N: at 1/N resolution) {}\n",
        g.target_ms(),
        GovernorLog::SETTLING,
        fmt(quantile(ms.clone(), 0.5)),
        fmt(quantile(ms, 0.9)),
        log.samples_text()
    );
    if log.still > 0 {
        s += &format!(
            "governor: {} still frame(s) refined progressively at {} samples\n",
            log.still, log.still_samples
        );
    }
    s
}

/// Once a node is up, how long the others have before the wall starts without them (`up` and
/// `start --local` first wait until their local daemons listen or have exited).
/// The fewest frames per second `--fps` takes above 0 (one frame a day) and the most.
pub const MIN_FPS: f64 = 1.0 / 86_400.0;
pub const MAX_FPS: f64 = 1000.0;

/// `--fps`: 0, or a frame rate in [`MIN_FPS`]..=[`MAX_FPS`], so that its frame period is a
/// duration (1e-310 frames a second would be a period of 1e310 s).
pub fn parse_fps(s: &str) -> Result<f64, String> {
    let fps: f64 = s.trim().parse().map_err(|_| format!("'{s}' is not a number of frames per second"))?;
    if fps == 0.0 || (MIN_FPS..=MAX_FPS).contains(&fps) {
        Ok(fps)
    } else {
        Err(format!("{fps} frames per second is outside 0 or {MIN_FPS:.6} (one a day) to {MAX_FPS}"))
    }
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
    let d = crate::picture::bounded_divisor(&wall.config, 1);
    let scale = if d > 1 {
        format!(
            " at 1/{d} scale: the whole wall's image is over the {} bytes a snapshot takes",
            crate::picture::MAX_WALL_IMAGE_BYTES
        )
    } else {
        String::new()
    };
    println!("wrote {} ({w}x{h}{scale}, {got} of {} tiles)", out.display(), wall.config.tiles.len());
    Ok(())
}

pub fn up(a: &UpArgs) -> Result<()> {
    let started = Instant::now();
    let config = load(&a.config)?;
    let (base, mut settings) = scene(&config)?;
    let gov = governor(&config, &mut settings, &a.orbit)?;
    // Bound before any node starts: a taken port fails first.
    let mut metrics_listener = match a.metrics {
        Some(addr) => {
            let l = std::net::TcpListener::bind(addr)
                .with_context(|| format!("--metrics: cannot listen on {addr}"))?;
            l.set_nonblocking(true).context("--metrics: a non-blocking listener")?;
            Some(l)
        }
        None => None,
    };
    let mut metrics_at = None;
    let log_dir = config.resolve("logs");
    let mut daemons = LocalDaemons::start(&config, &log_dir, &a.display, a.windowed)?;
    eprintln!("isowall: starting wall '{}': {} local node(s)", config.wall.name, daemons.len());
    daemons.wait_started(Duration::from_secs(a.start_timeout));
    let rt = runtime()?;
    let result = rt.block_on(async {
        let mut wall =
            crate::start::connect_local(&mut daemons, config, Duration::from_secs(a.start_timeout)).await?;
        eprintln!("isowall: wall up in {:.2} s", started.elapsed().as_secs_f64());
        if let Some(l) = metrics_listener.take() {
            let listener = tokio::net::TcpListener::from_std(l).context("--metrics")?;
            let at = format!("http://{}/metrics", listener.local_addr().context("--metrics")?);
            // Served until the runtime ends, after the run and --metrics-hold.
            tokio::spawn(crate::console::serve_metrics(listener, wall.metrics(), std::future::pending()));
            eprintln!("isowall: metrics at {at}");
            metrics_at = Some(at);
        }
        let mut pids = vec![("controller".to_string(), std::process::id())];
        pids.extend(daemons.pids());
        let mut watch = ResourceWatch::new(a.orbit.frames + a.orbit.still_frames, pids);
        let (elapsed, first_swap, governed) =
            drive(&mut wall, &base, &settings, &a.orbit, gov.clone(), &mut |k, w| watch.after_frame(k, w))
                .await?;
        if let Some(t) = first_swap {
            println!("first swap released {:.2} s after `isowall up` started", (t - started).as_secs_f64());
        }
        print!("{}", report(&wall, elapsed));
        print!("{}", governor_report(gov.as_ref(), &governed));
        print!("{}", watch.report(&wall));
        if let Some(out) = &a.snapshot {
            write_snapshot(&mut wall, out).await?;
        }
        wall.close("the controller is done").await;
        Ok::<(), anyhow::Error>(())
    });
    drop(daemons);
    if let (Ok(()), Some(at), 1..) = (&result, &metrics_at, a.metrics_hold) {
        eprintln!("isowall: the run is done; its final metrics stay at {at} for {} s", a.metrics_hold);
        rt.block_on(async { tokio::time::sleep(Duration::from_secs(a.metrics_hold)).await });
    }
    result
}

/// Resident memory and open descriptors of the controller and its local daemons, sampled once the
/// wall is warm (after a tenth of the frames, at most 100) and at the end, and the drift of the
/// frame time between the first run of frames after warm-up and the last one: what a soak run
/// reports.
struct ResourceWatch {
    warm: u64,
    pids: Vec<(String, u32)>,
    start: Vec<Option<crate::local::Resources>>,
    first_median: Option<Duration>,
}

impl ResourceWatch {
    fn new(frames: u64, pids: Vec<(String, u32)>) -> ResourceWatch {
        ResourceWatch { warm: (frames / 10).clamp(1, 100), pids, start: Vec::new(), first_median: None }
    }

    fn sample(&self) -> Vec<Option<crate::local::Resources>> {
        self.pids.iter().map(|(_, pid)| crate::local::resources(*pid)).collect()
    }

    /// Median barrier time of the last `n` released frames.
    fn median_of_last(wall: &Wall, n: u64) -> Option<Duration> {
        let r = &wall.releases;
        let from = r.len().saturating_sub(n as usize);
        crate::report::quantile(r[from..].iter().map(|x| x.1).collect(), 0.5)
    }

    fn after_frame(&mut self, k: u64, wall: &Wall) {
        if k + 1 == self.warm {
            self.start = self.sample();
        }
        if k + 1 == 2 * self.warm {
            self.first_median = Self::median_of_last(wall, self.warm);
        }
    }

    fn report(&self, wall: &Wall) -> String {
        if self.start.is_empty() {
            return String::new();
        }
        let end = self.sample();
        let mut s = format!(
            "resources after frame {} -> after frame {} (resident memory, open descriptors):\n",
            self.warm, wall.released
        );
        for (((name, pid), a), b) in self.pids.iter().zip(&self.start).zip(&end) {
            match (a, b) {
                (Some(a), Some(b)) => {
                    s += &format!(
                        "  {name} (pid {pid}): rss {:.1} -> {:.1} MiB ({:+} KiB), fds {} -> {}\n",
                        a.rss_kib as f64 / 1024.0,
                        b.rss_kib as f64 / 1024.0,
                        b.rss_kib as i64 - a.rss_kib as i64,
                        a.fds,
                        b.fds
                    )
                }
                _ => s += &format!("  {name} (pid {pid}): not readable (exited, or no /proc)\n"),
            }
        }
        if let (Some(first), Some(last)) = (self.first_median, Self::median_of_last(wall, self.warm)) {
            s += &format!(
                "frame time drift: barrier median {:.2} ms (frames {}..{}) -> {:.2} ms (last {} frames), x{:.2}\n",
                first.as_secs_f64() * 1e3,
                self.warm,
                2 * self.warm,
                last.as_secs_f64() * 1e3,
                self.warm,
                last.as_secs_f64() / first.as_secs_f64().max(1e-9)
            );
        }
        s
    }
}

pub fn orbit(a: &OrbitArgs) -> Result<()> {
    let config = load(&a.config)?;
    let (base, mut settings) = scene(&config)?;
    let gov = governor(&config, &mut settings, &a.orbit)?;
    runtime()?.block_on(async {
        let mut wall = Wall::connect(config, Duration::from_secs(10), crate::start::START_GRACE).await?;
        let (elapsed, _, governed) =
            drive(&mut wall, &base, &settings, &a.orbit, gov.clone(), &mut |_, _| {}).await?;
        print!("{}", report(&wall, elapsed));
        print!("{}", governor_report(gov.as_ref(), &governed));
        wall.close("the controller is done").await;
        Ok(())
    })
}

pub fn snapshot(a: &SnapshotArgs) -> Result<()> {
    let config = load(&a.config)?;
    runtime()?.block_on(async {
        let mut wall = Wall::connect(config, Duration::from_secs(10), crate::start::START_GRACE).await?;
        write_snapshot(&mut wall, &a.out).await?;
        wall.close("snapshot taken").await;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_rate_is_0_or_a_period_that_is_a_duration() {
        for ok in ["0", "30", "0.5", "1000"] {
            let fps = parse_fps(ok).unwrap();
            if fps > 0.0 {
                let _ = Duration::from_secs_f64(1.0 / fps); // panics on a period past Duration's range
            }
        }
        for bad in ["1e-310", "-1", "1001", "inf", "NaN", "fast"] {
            assert!(parse_fps(bad).is_err(), "{bad}");
        }
        // Where clap meets it: `demo --fps 1e-310` is a usage error, not a panic.
        use clap::Parser;
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            orbit: OrbitOptions,
        }
        let e = Cli::try_parse_from(["x", "--fps", "1e-310"]).err().expect("refused");
        assert!(e.to_string().contains("frames per second is outside"), "{e}");
    }

    #[test]
    fn the_governor_log_stays_bounded_on_long_runs() {
        let mut log = GovernorLog::default();
        let n = 10 * crate::wall::HISTORY as u64;
        for k in 0..n {
            // Frame k takes k ms and uses k % 7 + 1 samples.
            log.push((k % 7 + 1) as u32, 1, Duration::from_millis(k), Motion::Moving);
        }
        for _ in 0..3 {
            log.push(9, 1, Duration::from_millis(1), Motion::Still);
        }
        assert_eq!(log.moving_ms.len(), crate::wall::HISTORY);
        assert_eq!(log.first_samples.len() + log.last_samples.len(), 2 * GovernorLog::SAMPLES_SHOWN);
        // The quantiles are of the last HISTORY moving frames: n - HISTORY .. n ms.
        assert_eq!(log.moving_ms.front(), Some(&Duration::from_millis(n - crate::wall::HISTORY as u64)));
        let g = Governor::new(100.0, 1, 1, 64).unwrap();
        let r = governor_report(Some(&g), &log);
        assert!(r.contains(&format!("last {} of {} frames", crate::wall::HISTORY, n - 5)), "{r}");
        assert!(r.contains(&format!("({} frames) ...", n + 3 - 80)), "{r}");
        assert!(r.starts_with("governor: target 100.0 ms; moving frames after 5: p50 9"), "{r}");
        assert!(r.contains("3 still frame(s) refined progressively at 9 samples"), "{r}");
        assert!(r.lines().next().unwrap().ends_with("9 9 9"), "{r}");
    }

    #[test]
    fn a_short_run_reports_every_frame() {
        let mut log = GovernorLog::default();
        for k in 0..8u64 {
            // The last two frames at half resolution.
            let scale = if k >= 6 { 2 } else { 1 };
            log.push(k as u32 + 1, scale, Duration::from_millis(10 * (k + 1)), Motion::Moving);
        }
        let g = Governor::new(100.0, 1, 1, 64).unwrap();
        let r = governor_report(Some(&g), &log);
        assert!(
            r.contains("(3 frames); samples per frame (/N: at 1/N resolution) 1 2 3 4 5 6 7/2 8/2\n"),
            "{r}"
        );
        assert!(r.contains("p50 70.0 ms"), "{r}");
        assert!(!r.contains("still"), "{r}");
    }
}
