//! The console's frame loop: drives the wall frame after frame (as `isowall session` does, with
//! the session's camera logic), carries out the API's [`Command`]s between frames, asks the nodes
//! for images (snapshots, downscaled thumbnails) only when a request wants one, and publishes
//! the [`Status`].
//!
//! Images never hold up a frame: the loop sends the nodes the request and goes on; their answers
//! arrive between frames and go, as raw tiles, to every request waiting for that size, which
//! composes and encodes them off the loop (`pictures.rs`). A node that does not answer is given
//! up after [`THUMBNAIL_GIVE_UP`] ([`SNAPSHOT_GIVE_UP`] at full size); a request whose every
//! asker has left is dropped.

use super::commands::{ApiError, Captured, Command, ImagesReply};
use super::patch::Controls;
use super::shared::{unix_ms, Shared};
use super::status::{self, NodeHealth, Status};
use crate::controls::SessionState;
use crate::local::LocalDaemons;
use crate::path::CameraPath;
use crate::report::quantile;
use crate::wall::{FrameRequest, Wall};
use anyhow::Result;
use isowall_model::{Camera, Governor, Motion, RenderSettings, ViewFraming, WallConfig};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// How long a thumbnail waits for a node that does not answer.
pub const THUMBNAIL_GIVE_UP: Duration = Duration::from_secs(2);
/// How long a full-size snapshot waits for a node that does not answer.
pub const SNAPSHOT_GIVE_UP: Duration = Duration::from_secs(5);
/// The status is published this often at most.
const PUBLISH_EVERY: Duration = Duration::from_millis(100);

/// The scene the console starts with.
pub struct Scene {
    pub camera: Camera,
    pub settings: RenderSettings,
    pub range: (f64, f64),
    /// What the named views frame.
    pub framing: ViewFraming,
    /// The volume's time steps (1: none to play).
    pub steps: u32,
    pub demo: Option<(PathBuf, CameraPath)>,
}

struct Loop {
    shared: Arc<Shared>,
    controls: Controls,
    demo_path: Option<(PathBuf, CameraPath)>,
    demo_started: Option<Instant>,
    governor: Option<(f64, Governor)>,
    health: BTreeMap<String, NodeHealth>,
    /// When each recent frame's swap was released.
    released_at: VecDeque<(u64, Instant)>,
    /// Time between swaps of the recent frames.
    intervals: VecDeque<(u64, Duration)>,
    last_swap: Option<Instant>,
    /// Image requests waiting, by divisor.
    waiting: Vec<(u32, ImagesReply)>,
    /// The divisor of the request the nodes are answering.
    asked_divisor: Option<u32>,
    config: Arc<WallConfig>,
    /// Image requests made of the nodes.
    thumbnails: u64,
    /// The process ids of the daemons the console started (`--local`), by node.
    pids: HashMap<String, u32>,
    frame_samples: (u32, u32),
    started: Instant,
    published: Option<Instant>,
    /// Every node on this machine: their present times give the true swap skew.
    one_machine: bool,
    /// The nodes whose daemon the console started (their log is `logs/NODE.log`).
    local_logs: std::collections::BTreeSet<String>,
}

pub async fn run(
    mut wall: Wall,
    mut daemons: Option<LocalDaemons>,
    scene: Scene,
    shared: Arc<Shared>,
    mut commands: mpsc::Receiver<Command>,
) -> Result<()> {
    wall.sync_clocks(5).await;
    if let Some(d) = &daemons {
        shared.logs.lock().unwrap_or_else(std::sync::PoisonError::into_inner).extend(d.logs());
    }
    let now = Instant::now();
    let mut session = SessionState::new(scene.camera, scene.settings, scene.range);
    session.playback.steps = scene.steps.max(1);
    session.framing = Some(scene.framing);
    let controls = Controls {
        session,
        home: scene.camera,
        range: scene.range,
        env: wall.config.render.env.clone(),
        target_frame_ms: wall.config.render.target_frame_ms,
        orbit: false,
        orbit_degrees_per_second: 20.0,
        demo_available: scene.demo.is_some(),
        demo: false,
    };
    let mut me = Loop {
        shared,
        controls,
        demo_path: scene.demo,
        demo_started: None,
        governor: None,
        health: wall.config.nodes.iter().map(|n| (n.name.clone(), NodeHealth::new(now, unix_ms()))).collect(),
        released_at: VecDeque::new(),
        intervals: VecDeque::new(),
        last_swap: None,
        waiting: Vec::new(),
        asked_divisor: None,
        config: Arc::new(wall.config.clone()),
        thumbnails: 0,
        pids: HashMap::new(),
        frame_samples: (scene.settings.ao.samples, 1),
        started: now,
        published: None,
        one_machine: crate::wall::one_machine(&wall.config),
        local_logs: daemons
            .as_ref()
            .map(|d| d.logs().into_iter().map(|(n, _)| n).collect())
            .unwrap_or_default(),
    };
    let mut last = Instant::now();
    let mut frames = 0u64;
    loop {
        // Everything the API asked since the last frame; never waits.
        let mut moved = false;
        while let Ok(cmd) = commands.try_recv() {
            moved |= me.command(&mut wall, &mut daemons, cmd).await;
        }
        if commands.is_closed() && commands.is_empty() {
            break;
        }
        let dt = last.elapsed().as_secs_f64().min(0.25);
        last = Instant::now();
        moved |= me.advance(dt);
        let request = me.frame_request();
        if let Err(e) = wall.frame(&request).await {
            tracing::warn!("console: no frame: {e:#}");
            me.after_frame(&mut wall, &mut daemons, false, moved).await;
            tokio::time::sleep(Duration::from_millis(200)).await;
            continue;
        }
        me.after_frame(&mut wall, &mut daemons, true, moved).await;
        frames += 1;
        if frames % 30 == 29 {
            wall.sync_clocks(1).await;
        }
    }
    wall.close("the console is closed").await;
    drop(daemons);
    Ok(())
}

impl Loop {
    /// Carries out one command; `true` if it moved the camera (the governor's motion).
    async fn command(&mut self, wall: &mut Wall, daemons: &mut Option<LocalDaemons>, cmd: Command) -> bool {
        match cmd {
            Command::Restart(node, reason, reply) => {
                let reason = isowall_model::messages::printable(&reason);
                let r = match daemons.as_mut().filter(|d| d.has(&node)) {
                    Some(d) => {
                        tracing::info!(%node, %reason, "console: restarting the local daemon");
                        // Its connection goes with the process; the wall reconnects the new one.
                        d.restart(&node)
                            .map(|pid| format!("local daemon killed and started again (pid {pid})"))
                            .map_err(|e| ApiError::internal(format!("{e:#}")))
                    }
                    None => {
                        tracing::info!(%node, %reason, "console: asking the node to restart");
                        wall.restart(&node, &reason)
                            .await
                            .map(|()| {
                                "told to restart over its connection: its supervisor starts it again"
                                    .to_string()
                            })
                            .map_err(|e| ApiError::new(axum::http::StatusCode::CONFLICT, format!("{e:#}")))
                    }
                };
                if r.is_ok() {
                    self.published = None;
                }
                let _ = reply.send(r);
                false
            }
            Command::Identify(on, reply) => {
                wall.set_identify(on).await;
                self.published = None;
                let _ = reply.send(Ok(()));
                false
            }
            Command::CameraNow(reply) => {
                let _ = reply.send(Ok(self.controls.session.camera));
                false
            }
            Command::Render(p, reply) => {
                let r = self.controls.apply_render(&p).map_err(ApiError::refused);
                let _ = reply.send(r);
                false
            }
            Command::Camera(p, reply) => {
                let demo_before = self.controls.demo;
                let r = self.controls.apply_camera(&p).map_err(ApiError::refused);
                if self.controls.demo && !demo_before {
                    self.demo_started = Some(Instant::now());
                }
                let moved = r.is_ok();
                let _ = reply.send(r);
                moved
            }
            Command::Time(p, reply) => {
                let r = self.controls.apply_time(&p).map_err(ApiError::refused);
                // A step shown is a new picture (the governor's motion).
                let moved = r.is_ok() && p.step.is_some();
                let _ = reply.send(r);
                moved
            }
            Command::Images(divisor, reply) => {
                self.waiting.push((divisor, reply));
                self.ask_images(wall).await;
                false
            }
        }
    }

    /// Asks the nodes for the first waiting request's images unless a request is pending.
    async fn ask_images(&mut self, wall: &mut Wall) {
        if wall.images_pending() {
            return;
        }
        let Some(&(divisor, _)) = self.waiting.first() else { return };
        let give_up = if divisor <= 1 { SNAPSHOT_GIVE_UP } else { THUMBNAIL_GIVE_UP };
        if wall.request_images(divisor, give_up).await {
            self.asked_divisor = Some(divisor);
            self.thumbnails += 1;
        }
    }

    /// How long ago frame `id`'s swap was released.
    fn age_of(&self, id: u64) -> Option<Duration> {
        self.released_at.iter().find(|(f, _)| *f == id).map(|(_, t)| t.elapsed())
    }

    /// Moves the camera and the time step by the demo path, or by the orbit and the playback,
    /// for `dt` seconds; `true` if the picture moved.
    fn advance(&mut self, dt: f64) -> bool {
        let c = &mut self.controls;
        if c.demo {
            if let Some((_, path)) = &self.demo_path {
                let start = *self.demo_started.get_or_insert_with(Instant::now);
                let t = start.elapsed().as_secs_f64().rem_euclid(path.duration().max(1e-9));
                let key = path.at(t);
                c.session.camera = key.camera();
                c.session.settings.iso = key.iso;
                c.session.settings.ao.samples = key.ao_samples;
                c.session.playback.show(key.step);
                return true;
            }
        }
        let step = c.session.playback.step;
        c.session.playback.advance(dt);
        let stepped = c.session.playback.step != step;
        if c.orbit {
            c.session.orbit_yaw(c.orbit_degrees_per_second * dt);
            return true;
        }
        stepped
    }

    /// The next frame: the operator's camera, settings and time step, governed.
    fn frame_request(&mut self) -> FrameRequest {
        let s = self.controls.session.settings;
        match self.controls.target_frame_ms {
            Some(t) => {
                if self.governor.as_ref().is_none_or(|(target, _)| *target != t) {
                    let max = isowall_model::render_state::MAX_AO_SAMPLES;
                    self.governor = Governor::new(t, s.ao.samples.clamp(1, max), 1, max).ok().map(|g| (t, g));
                }
            }
            None => self.governor = None,
        }
        let session = &self.controls.session;
        let request = FrameRequest::new(session.camera, s)
            .at_time_step(session.playback.step)
            .governed(self.governor.as_ref().map(|(_, g)| g));
        self.frame_samples = (request.settings.ao.samples, request.scale);
        request
    }

    async fn after_frame(
        &mut self,
        wall: &mut Wall,
        daemons: &mut Option<LocalDaemons>,
        ok: bool,
        moved: bool,
    ) {
        let now = Instant::now();
        if ok {
            let id = wall.last_frame_id();
            self.released_at.push_back((id, now));
            if let Some(prev) = self.last_swap {
                self.intervals.push_back((id, now - prev));
            }
            self.last_swap = Some(now);
            while self.released_at.len() > 256 {
                self.released_at.pop_front();
            }
            while self.intervals.len() > crate::wall::HISTORY {
                self.intervals.pop_front();
            }
            if let Some((_, g)) = &mut self.governor {
                let frame = wall.releases.last().map_or(Duration::ZERO, |r| r.1);
                g.observe(status::ms(frame), if moved { Motion::Moving } else { Motion::Still });
            }
        }
        // Node health from the frame just released (its stragglers missed the deadline).
        let release = wall.releases.last().filter(|r| ok && r.0 == wall.last_frame_id());
        let unix = unix_ms();
        for (name, h) in &mut self.health {
            let connected = wall.is_up(name);
            let missed = release.filter(|_| connected).map(|r| r.2.contains(name));
            h.observe(now, unix, connected, missed);
        }
        // Requests whose askers left are dropped, and the nodes' answer with them when nobody
        // waits for it any more.
        self.waiting.retain(|(_, r)| !r.is_closed());
        if let Some(d) = self.asked_divisor {
            if !self.waiting.iter().any(|(w, _)| *w == d) {
                wall.cancel_images();
                self.asked_divisor = None;
            }
        }
        // Images that came in: to every request waiting for them at their size.
        if let Some(tiles) = wall.take_images() {
            let divisor = self.asked_divisor.take().unwrap_or(1);
            let frame_id = tiles.values().flatten().map(|t| t.frame_id).min();
            let age = frame_id.and_then(|f| self.age_of(f));
            let captured = Arc::new(Captured {
                config: self.config.clone(),
                divisor,
                tiles,
                frame_id,
                age,
                taken: Instant::now(),
            });
            let (served, later): (Vec<_>, Vec<_>) =
                std::mem::take(&mut self.waiting).into_iter().partition(|(d, _)| *d == divisor);
            for (_, reply) in served {
                let _ = reply.send(Ok(captured.clone()));
            }
            self.waiting = later;
        }
        self.ask_images(wall).await;
        if self.published.is_none_or(|t| t.elapsed() >= PUBLISH_EVERY) {
            self.published = Some(Instant::now());
            // The status is the pids' only reader: looked up when it is published, not every frame.
            if let Some(d) = daemons.as_mut() {
                self.pids = d.pids().into_iter().collect();
            }
            let status = self.status(wall);
            self.shared.status.send_replace(Some(Arc::new(status)));
        }
    }

    fn status(&self, wall: &Wall) -> Status {
        use status::*;
        let cfg = &wall.config;
        let (width, height) = cfg.wall_size();
        let (lock, lock_changes) = self.lock_info();
        let s = &self.controls.session.settings;
        let c = &self.controls.session.camera;
        Status {
            wall: WallInfo {
                name: cfg.wall.name.clone(),
                mode: format!("{:?}", cfg.wall.mode).to_lowercase(),
                width,
                height,
                deadline_ms: cfg.wall.deadline_ms,
                tiles: tile_infos(cfg),
                identify: wall.identify(),
            },
            frame: self.frame_info(wall),
            render: RenderInfo {
                iso: s.iso,
                ao_samples: s.ao.samples,
                max_ao_samples: isowall_model::render_state::MAX_AO_SAMPLES,
                ao_method: s.ao.method,
                ibl: s.ao.ibl,
                exposure: s.exposure,
                shading: s.shading,
                denoise: s.denoise,
                target_frame_ms: self.controls.target_frame_ms,
                frame_ao_samples: self.frame_samples.0,
                frame_scale: self.frame_samples.1,
            },
            volume: VolumeInfo {
                source: cfg.volume_source(),
                min: self.controls.range.0,
                max: self.controls.range.1,
            },
            camera: CameraInfo {
                eye: c.eye.to_array(),
                target: c.target.to_array(),
                up: c.up.to_array(),
                fov_y: c.fov_y_deg,
            },
            orbit: OrbitInfo {
                playing: self.controls.orbit,
                degrees_per_second: self.controls.orbit_degrees_per_second,
            },
            demo: DemoInfo {
                path: self.demo_path.as_ref().map(|(p, _)| p.display().to_string()),
                playing: self.controls.demo,
                duration_s: self.demo_path.as_ref().map(|(_, p)| p.duration()),
            },
            time: {
                let p = &self.controls.session.playback;
                let waited = |f: &isowall_model::frame_controller::FrameStats| {
                    f.per_node.iter().any(|n| n.step_late.is_some())
                };
                TimeInfo {
                    steps: p.steps,
                    step: p.step,
                    playing: p.playing,
                    rate: p.rate,
                    min_rate: crate::controls::MIN_RATE,
                    max_rate: crate::controls::MAX_RATE,
                    waited: wall.finished.last().is_some_and(waited),
                    frames_waited: wall.finished.iter().filter(|f| waited(f)).count() as u64,
                }
            },
            nodes: self.node_cards(wall),
            console: ConsoleInfo {
                read_only: self.shared.access.read_only,
                token: self.shared.access.token.is_some(),
                uptime_s: self.started.elapsed().as_secs_f64(),
                node_image_bytes: wall.snapshot_bytes,
                thumbnails: self.thumbnails,
                served_bytes: self.shared.served_bytes.get(),
                lock,
                lock_changes,
            },
        }
    }

    /// Who holds the operator lock, and the count of its holder's changes, read under one guard
    /// so the two agree.
    fn lock_info(&self) -> (Option<status::LockInfo>, u64) {
        let mut lock = self.shared.lock();
        let now = self.shared.epoch.elapsed();
        let idle_s = lock.idle().as_secs_f64();
        let info = lock.holder(now).map(|h| status::LockInfo {
            holder: h.holder.clone(),
            since_unix_ms: h.since_unix_ms,
            idle_timeout_s: idle_s,
        });
        (info, lock.changes())
    }

    /// The frame rate, frame times and swap skews of the last frames.
    fn frame_info(&self, wall: &Wall) -> status::FrameInfo {
        use status::*;
        let now = Instant::now();
        let fps = {
            let recent: Vec<&(u64, Instant)> = self
                .released_at
                .iter()
                .filter(|(_, t)| now.duration_since(*t) < Duration::from_secs(2))
                .collect();
            match (recent.first(), recent.last()) {
                (Some(a), Some(b)) if recent.len() > 1 => {
                    (recent.len() - 1) as f64 / b.1.duration_since(a.1).as_secs_f64().max(1e-9)
                }
                _ => 0.0,
            }
        };
        let intervals: Vec<Duration> = self.intervals.iter().map(|x| x.1).collect();
        let skews: Vec<Duration> = wall.finished.iter().filter_map(|f| f.swap_skew).collect();
        let true_skews: Vec<Duration> = wall.finished.iter().filter_map(|f| f.node_clock_skew).collect();
        let tail = |v: &[Duration]| v[v.len().saturating_sub(SERIES)..].iter().map(|d| ms(*d)).collect();
        let q = |v: &[Duration], p: f64| quantile(v.to_vec(), p).map(ms);
        FrameInfo {
            id: wall.releases.last().map_or(0, |r| r.0),
            released: wall.released,
            fps,
            frame_ms: tail(&intervals),
            skew_ms: tail(&skews),
            frame_ms_p50: q(&intervals, 0.5),
            frame_ms_p99: q(&intervals, 0.99),
            skew_ms_p50: q(&skews, 0.5),
            skew_ms_p99: q(&skews, 0.99),
            true_skew_ms_p50: self.one_machine.then(|| q(&true_skews, 0.5)).flatten(),
            true_skew_ms_p99: self.one_machine.then(|| q(&true_skews, 0.99)).flatten(),
            swap_margin: wall.swap_timing().setting().to_string(),
            swap_margin_ms: wall.finished.last().and_then(|f| f.margin).map(ms),
            late_swaps: wall.finished.iter().map(|f| f.late_swaps).sum(),
            frame_rate: wall.swap_timing().period().map(|p| 1.0 / p.as_secs_f64()),
            interval_jitter_ms_p99: crate::report::interval_jitter(wall).and_then(|(_, j)| q(&j, 0.99)),
            level0_share: wall.finished.last().and_then(crate::report::frame_surface).map(|s| s.share()),
        }
    }

    /// Each node's card: health, times, memory, tiles and bricks, version and GPU.
    fn node_cards(&self, wall: &Wall) -> Vec<status::NodeCard> {
        use status::*;
        let cfg = &wall.config;
        let times = last_times(&wall.finished);
        let resident: BTreeMap<&str, u64> = wall
            .finished
            .iter()
            .rev()
            .take(8)
            .flat_map(|f| f.per_node.iter().filter_map(|n| n.resident_bytes.map(|b| (n.node.as_str(), b))))
            .collect();
        cfg.nodes
            .iter()
            .map(|n| {
                let h = &self.health[&n.name];
                let (render_ms, ready_ms) = times.get(&n.name).copied().unwrap_or_default();
                NodeCard {
                    name: n.name.clone(),
                    address: n.address.clone(),
                    state: h.state,
                    reason: h.reason.clone(),
                    since_s: h.since.elapsed().as_secs_f64(),
                    since_unix_ms: h.since_unix_ms,
                    render_ms,
                    ready_ms,
                    rss_kib: wall.resident_bytes(&n.name).map(|b| b / 1024),
                    pid: self.pids.get(&n.name).copied(),
                    resident_volume_bytes: resident.get(n.name.as_str()).copied(),
                    tiles: n.tiles.clone(),
                    bricks: wall.bricks_of(&n.name),
                    clock_error_us: wall.clock_error_us(&n.name),
                    late_swaps: wall.late_swaps(&n.name),
                    version: wall.node_info(&n.name).map(|i| i.version.clone()),
                    adapter: wall.node_info(&n.name).map(|i| i.adapter.clone()),
                    backend: wall.node_info(&n.name).map(|i| i.backend.clone()),
                    driver: wall.node_info(&n.name).map(|i| i.driver.clone()),
                    driver_info: wall.node_info(&n.name).map(|i| i.driver_info.clone()),
                    present: wall.node_info(&n.name).map(|i| i.present.clone()),
                    local_log: self.local_logs.contains(&n.name),
                }
            })
            .collect()
    }
}
/// The wall's tiles for the page: where each is, its node, its bezel.
fn tile_infos(cfg: &isowall_model::config::WallConfig) -> Vec<status::TileInfo> {
    use status::*;
    cfg.tiles
        .iter()
        .map(|t| TileInfo {
            name: t.name.clone(),
            node: cfg.node_of_tile(&t.name).map(|n| n.name.clone()).unwrap_or_default(),
            x: t.x,
            y: t.y,
            width: t.width,
            height: t.height,
            bezel: t.bezel,
        })
        .collect()
}
