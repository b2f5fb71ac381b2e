//! What `GET /api/status` and the `/api/live` WebSocket say: the wall's geometry, the frame
//! statistics (rolling series and quantiles), the render settings and camera, and a card per node.
//! [`NodeHealth`] decides a node's state from what each frame shows, with the time it changed.

use serde::Serialize;
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// Frames in the rolling series of the charts.
pub const SERIES: usize = 120;

#[derive(Clone, Debug, Serialize)]
pub struct Status {
    pub wall: WallInfo,
    pub frame: FrameInfo,
    pub render: RenderInfo,
    pub volume: VolumeInfo,
    pub camera: CameraInfo,
    pub orbit: OrbitInfo,
    pub demo: DemoInfo,
    pub time: TimeInfo,
    pub nodes: Vec<NodeCard>,
    pub console: ConsoleInfo,
}

#[derive(Clone, Debug, Serialize)]
pub struct WallInfo {
    pub name: String,
    pub mode: String,
    pub width: u32,
    pub height: u32,
    pub deadline_ms: u64,
    pub tiles: Vec<TileInfo>,
    /// Whether each tile shows its node's and its own name (`POST /api/identify`).
    pub identify: bool,
}

#[derive(Clone, Debug, Serialize)]
pub struct TileInfo {
    pub name: String,
    pub node: String,
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
    /// Hidden mullion pixels: left, right, top, bottom.
    pub bezel: [u32; 4],
}

#[derive(Clone, Debug, Default, Serialize)]
pub struct FrameInfo {
    /// The last frame released.
    pub id: u64,
    /// Swaps released since the wall came up.
    pub released: u64,
    /// Frames per second over the last two seconds.
    pub fps: f64,
    /// The last [`SERIES`] frames: time between swaps, ms.
    pub frame_ms: Vec<f64>,
    /// The last [`SERIES`] measured swap skews, ms (frames without a measurement left out).
    pub skew_ms: Vec<f64>,
    /// Quantiles over the controller's history (up to `wall::HISTORY` frames).
    pub frame_ms_p50: Option<f64>,
    pub frame_ms_p99: Option<f64>,
    pub skew_ms_p50: Option<f64>,
    pub skew_ms_p99: Option<f64>,
    /// The true swap skew where every node is on the console's machine (one clock), ms.
    pub true_skew_ms_p50: Option<f64>,
    pub true_skew_ms_p99: Option<f64>,
    /// The timed swap: `auto`, `off` or a fixed margin, and the margin of the last frame, ms
    /// (`null`: untimed).
    pub swap_margin: String,
    pub swap_margin_ms: Option<f64>,
    /// Swaps that came after their present time, over the controller's history.
    pub late_swaps: usize,
    /// `[wall] frame_rate` (`null`: unpaced), and the frame-interval jitter |interval - period|
    /// at the 99th percentile over the history, ms.
    pub frame_rate: Option<f64>,
    pub interval_jitter_ms_p99: Option<f64>,
    /// A volume read through the nodes' brick caches: the share of the last frame's surface
    /// pixels drawn with level 0, 0 ..= 1 (`null`: no brick cache).
    pub level0_share: Option<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct RenderInfo {
    pub iso: f64,
    pub ao_samples: u32,
    /// The most AO samples per frame the renderer takes (the slider's end).
    pub max_ao_samples: u32,
    pub ao_method: isowall_model::AoMethod,
    pub ibl: isowall_model::IblMethod,
    pub exposure: f64,
    pub shading: isowall_model::Shading,
    /// The spatial filter of occlusion and IBL (`off`, `on`; object space filters the composited
    /// tile where its config says `denoise = "on"`, and ignores it otherwise).
    pub denoise: isowall_model::Denoise,
    /// The quality governor's target (`None`: off, `ao_samples` every frame).
    pub target_frame_ms: Option<f64>,
    /// The samples and internal resolution divisor of the last frame (the governor's choice).
    pub frame_ao_samples: u32,
    pub frame_scale: u32,
}

#[derive(Clone, Debug, Serialize)]
pub struct VolumeInfo {
    pub source: String,
    /// The data's value range (the iso slider's), in the data's units.
    pub min: f64,
    pub max: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct CameraInfo {
    pub eye: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub fov_y: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct OrbitInfo {
    pub playing: bool,
    pub degrees_per_second: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct DemoInfo {
    /// The `--demo-path` file, if one was given.
    pub path: Option<String>,
    pub playing: bool,
    pub duration_s: Option<f64>,
}

/// A time-varying volume's playback (`steps` 1: a volume without time steps).
#[derive(Clone, Debug, Serialize)]
pub struct TimeInfo {
    pub steps: u32,
    /// The step of the next frame.
    pub step: u32,
    pub playing: bool,
    /// Steps per second while playing, and its bounds.
    pub rate: f64,
    pub min_rate: f64,
    pub max_rate: f64,
    /// Whether a node waited for the last frame's step (it was not loaded ahead in time).
    pub waited: bool,
    /// Frames among the controller's recent history (up to `wall::HISTORY`) that waited so.
    pub frames_waited: u64,
}

#[derive(Clone, Debug, Serialize)]
pub struct ConsoleInfo {
    pub read_only: bool,
    /// Whether requests need a bearer token.
    pub token: bool,
    pub uptime_s: f64,
    /// Bytes of tile images the nodes sent the controller (snapshots and thumbnails).
    pub node_image_bytes: u64,
    /// Thumbnails the nodes were asked for.
    pub thumbnails: u64,
    /// Bytes the console sent to pages and scripts (bodies and WebSocket messages).
    pub served_bytes: u64,
    /// Who holds the operator lock (`null`: nobody; changes are open to every client).
    pub lock: Option<LockInfo>,
    /// How many times the lock's holder had changed when this status was made: a page that took
    /// the lock at change N ignores the lock of a status made before it (`< N`).
    pub lock_changes: u64,
}

#[derive(Clone, Debug, Serialize)]
pub struct LockInfo {
    pub holder: String,
    pub since_unix_ms: u64,
    /// It lapses after this long without a change from its holder.
    pub idle_timeout_s: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct NodeCard {
    pub name: String,
    pub address: String,
    /// `up`, `straggling` (the last frame was released without it) or `down`.
    pub state: NodeState,
    /// Why it is not up.
    pub reason: Option<String>,
    /// How long it has been in this state, seconds.
    pub since_s: f64,
    /// Unix time (ms) it entered this state.
    pub since_unix_ms: u64,
    /// Its last reported render time and when its Ready arrived after the frame began, ms.
    pub render_ms: Option<f64>,
    pub ready_ms: Option<f64>,
    /// Resident memory of its daemon process, KiB, as the node tells with each Pong (about once
    /// a second; `null` until the first on its current connection).
    pub rss_kib: Option<u64>,
    /// The process id of a daemon the console started (`--local`).
    pub pid: Option<u32>,
    /// Object space: the volume bytes it holds (its brick and halo, as it reports).
    pub resident_volume_bytes: Option<u64>,
    pub tiles: Vec<String>,
    /// Object space: the bricks it renders now.
    pub bricks: Vec<usize>,
    /// Its clock offset's error bound, microseconds (`null` before its first Pong).
    pub clock_error_us: Option<i64>,
    /// Swaps that reached it after their present time, since the console started.
    pub late_swaps: u64,
    /// What the node told of itself (`Message::NodeInfo`, its texts bounded and made printable;
    /// `null` until it has): the isowalld version, and its GPU adapter, backend and driver.
    pub version: Option<String>,
    pub adapter: Option<String>,
    pub backend: Option<String>,
    pub driver: Option<String>,
    pub driver_info: Option<String>,
    /// What its presenting thread runs as (`SCHED_FIFO 10`, or normal and why).
    pub present: Option<String>,
    /// Whether the console started its daemon and reads its log (`/api/nodes/NAME/log`).
    pub local_log: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum NodeState {
    Up,
    Straggling,
    Down,
}

/// One node's state as the frames show it: down while disconnected, or after missing two
/// deadlines in a row (its connection may take longer to time out); straggling after missing one;
/// up once it is ready in time again.
#[derive(Clone, Debug)]
pub struct NodeHealth {
    pub state: NodeState,
    pub reason: Option<String>,
    pub since: Instant,
    pub since_unix_ms: u64,
    missed_in_a_row: u32,
}

impl NodeHealth {
    pub fn new(now: Instant, unix_ms: u64) -> NodeHealth {
        NodeHealth {
            state: NodeState::Up,
            reason: None,
            since: now,
            since_unix_ms: unix_ms,
            missed_in_a_row: 0,
        }
    }

    /// After a frame: whether the node is connected, and whether that frame was released without
    /// it (`None`: it took no part, e.g. it was down when the frame began).
    pub fn observe(&mut self, now: Instant, unix_ms: u64, connected: bool, missed: Option<bool>) {
        match missed {
            Some(true) => self.missed_in_a_row += 1,
            Some(false) => self.missed_in_a_row = 0,
            None => {}
        }
        let (state, reason) = if !connected {
            self.missed_in_a_row = 0;
            (NodeState::Down, Some("disconnected".to_string()))
        } else if self.missed_in_a_row >= 2 {
            (NodeState::Down, Some(format!("missed the last {} deadlines", self.missed_in_a_row)))
        } else if self.missed_in_a_row == 1 {
            (NodeState::Straggling, Some("missed the last deadline".to_string()))
        } else {
            (NodeState::Up, None)
        };
        if state != self.state {
            self.state = state;
            self.since = now;
            self.since_unix_ms = unix_ms;
        }
        self.reason = reason;
    }
}

/// Milliseconds of a duration, as the API reports them: to the microsecond (finer is noise, and
/// the digits would be most of the live status's bytes).
pub fn ms(d: Duration) -> f64 {
    (d.as_secs_f64() * 1e6).round() / 1e3
}

/// The last value of each node's render and ready times over `finished` (newest last).
pub fn last_times(
    finished: &[isowall_model::frame_controller::FrameStats],
) -> BTreeMap<String, (Option<f64>, Option<f64>)> {
    let mut out: BTreeMap<String, (Option<f64>, Option<f64>)> = BTreeMap::new();
    for f in finished.iter().rev().take(8) {
        for n in &f.per_node {
            let e = out.entry(n.node.clone()).or_default();
            if e.0.is_none() {
                e.0 = n.render.map(ms);
            }
            if e.1.is_none() {
                e.1 = n.ready_after.map(ms);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_node_straggles_after_one_miss_is_down_after_two_and_up_when_ready_again() {
        let t0 = Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let mut h = NodeHealth::new(t0, 0);
        h.observe(at(1), 1000, true, Some(false));
        assert_eq!((h.state, h.since), (NodeState::Up, t0));
        h.observe(at(2), 2000, true, Some(true));
        assert_eq!((h.state, h.since_unix_ms), (NodeState::Straggling, 2000));
        h.observe(at(3), 3000, true, Some(true));
        assert_eq!((h.state, h.since_unix_ms), (NodeState::Down, 3000));
        assert_eq!(h.reason.as_deref(), Some("missed the last 2 deadlines"));
        // Its connection times out: still down, since the first time it was.
        h.observe(at(4), 4000, false, None);
        assert_eq!(
            (h.state, h.since_unix_ms, h.reason.as_deref()),
            (NodeState::Down, 3000, Some("disconnected"))
        );
        // It rejoins: up at once (connected, no frame missed yet), then ready in time.
        h.observe(at(5), 5000, true, None);
        assert_eq!((h.state, h.since_unix_ms), (NodeState::Up, 5000));
        h.observe(at(6), 6000, true, Some(false));
        assert_eq!((h.state, h.since_unix_ms, h.reason), (NodeState::Up, 5000, None));
    }

    #[test]
    fn durations_are_reported_in_ms_to_the_microsecond() {
        assert_eq!(ms(Duration::from_nanos(23_464_399)), 23.464);
        assert_eq!(ms(Duration::from_nanos(23_464_500)), 23.465);
        assert_eq!(serde_json::to_string(&ms(Duration::from_micros(1_500))).unwrap(), "1.5");
        assert_eq!(ms(Duration::ZERO), 0.0);
    }
}
