//! What the console's HTTP handlers and its frame loop share: the state the handlers read
//! (`Shared`) and the thumbnail divisors; the commands they send the loop, its answers and the
//! API's errors are `commands.rs`'s. Neither `api.rs` nor `frame_loop.rs` imports the other.

use super::commands::Command;
use super::lock::OperatorLock;
use super::pictures::Pictures;
use super::server::Limits;
use super::status::Status;
use super::Access;
use crate::metrics::{ConsoleMetrics, WallMetrics};
use isowall_model::messages::MAX_THUMBNAIL_DIVISOR;
use prometheus_client::metrics::counter::Counter;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

/// Live WebSockets open at once, all clients together (each holds a connection).
pub const MAX_LIVE: usize = 64;

/// What the handlers share with the frame loop.
pub struct Shared {
    pub access: Access,
    /// The latest status (`None` until the first frame).
    pub status: watch::Sender<Option<Arc<Status>>>,
    pub commands: mpsc::Sender<Command>,
    /// Bytes of response bodies and WebSocket messages sent (a counter of the console's
    /// metrics too).
    pub served_bytes: Counter,
    /// The wall's metrics (fed by the frame loop's wall) and the console's own, for `/metrics`.
    pub metrics: Arc<WallMetrics>,
    pub console_metrics: ConsoleMetrics,
    /// Snapshots and thumbnails: asked of the nodes, shared and bounded.
    pub pictures: Arc<Pictures>,
    pub limits: Limits,
    /// Places for live WebSockets ([`MAX_LIVE`]).
    pub live_slots: Arc<tokio::sync::Semaphore>,
    /// The operator lock, on the clock of `epoch`.
    pub lock: std::sync::Mutex<OperatorLock>,
    pub epoch: Instant,
    /// The log file of each daemon the console started (`--local`), by node.
    pub logs: std::sync::Mutex<std::collections::HashMap<String, std::path::PathBuf>>,
    /// The camera bookmarks file (beside the wall config), and one writer at a time.
    pub bookmarks: std::path::PathBuf,
    pub bookmarks_writer: tokio::sync::Mutex<()>,
}

/// What the console is started with beyond its access rules.
pub struct Options {
    pub bookmarks: std::path::PathBuf,
    pub lock_idle: Duration,
    /// The wall's metrics (`Wall::metrics`).
    pub metrics: Arc<WallMetrics>,
}

impl Shared {
    pub fn new(access: Access, limits: Limits, options: Options) -> (Arc<Shared>, mpsc::Receiver<Command>) {
        let (commands, rx) = mpsc::channel(64);
        let (status, _) = watch::channel(None);
        let pictures = Arc::new(Pictures::default());
        let served_bytes = Counter::default();
        let console_metrics = ConsoleMetrics::new(&served_bytes);
        let live_slots = Arc::new(tokio::sync::Semaphore::new(MAX_LIVE));
        let shared = Shared {
            access,
            status,
            commands,
            served_bytes,
            metrics: options.metrics,
            console_metrics,
            pictures,
            limits,
            live_slots,
            lock: std::sync::Mutex::new(OperatorLock::new(options.lock_idle)),
            epoch: Instant::now(),
            logs: Default::default(),
            bookmarks: options.bookmarks,
            bookmarks_writer: tokio::sync::Mutex::new(()),
        };
        (Arc::new(shared), rx)
    }

    /// The operator lock (a poisoned mutex still holds a consistent lock: every change to it is
    /// one assignment).
    pub fn lock(&self) -> std::sync::MutexGuard<'_, OperatorLock> {
        self.lock.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// The divisors thumbnails are asked at: each about 1.5 times the one before, so that any
/// number of widths asked for comes to a dozen requests of the nodes at most.
const DIVISORS: [u32; 11] = [1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48];

/// The thumbnail downscale for a page `width` pixels wide: the smallest of [`DIVISORS`] (or
/// [`MAX_THUMBNAIL_DIVISOR`]) whose image fits.
pub fn divisor_for(wall_width: u32, width: u32) -> u32 {
    let fits = wall_width.div_ceil(width.max(1)).clamp(1, MAX_THUMBNAIL_DIVISOR);
    DIVISORS.iter().copied().find(|d| *d >= fits).unwrap_or(MAX_THUMBNAIL_DIVISOR)
}

/// The wall-clock time now, ms since the Unix epoch (for pages; rules use `Shared::epoch`).
pub fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_thumbnail_divisor_is_the_smallest_that_fits() {
        assert_eq!(divisor_for(328, 328), 1);
        assert_eq!(divisor_for(328, 400), 1);
        assert_eq!(divisor_for(328, 164), 2);
        assert_eq!(divisor_for(328, 163), 3);
        assert_eq!(divisor_for(7680, 640), 12);
        // Rounded up to the next of a few sizes: 328 / 70 needs 5, asked at 6.
        assert_eq!(divisor_for(328, 70), 6);
        assert_eq!(divisor_for(1 << 20, 1), MAX_THUMBNAIL_DIVISOR);
        assert_eq!(divisor_for(328, 0), MAX_THUMBNAIL_DIVISOR);
        // Every width from 1 to 4096 of a 7680-pixel wall: a dozen divisors at most.
        let distinct: std::collections::BTreeSet<u32> = (1..=4096).map(|w| divisor_for(7680, w)).collect();
        assert!(distinct.len() <= 12, "{distinct:?}");
    }
}
