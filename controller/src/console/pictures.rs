//! Pictures of the wall for the API (`GET /api/snapshot.png`, full size or `?width=`): every
//! request that reaches the nodes goes through here, bounded per client and in total.
//!
//! - **Admission**: a client (by address) may have [`PER_CLIENT`] picture requests waiting, all
//!   clients together [`TOTAL`]; beyond that the request is refused at once (429, 503) with the
//!   reason.
//! - **Single flight and cache**: requests for the same size share one request of the nodes
//!   (thumbnail widths come to a few divisors, `frame_loop::divisor_for`); a picture is served
//!   again to whoever asks within [`THUMBNAIL_EVERY`] (a full-size one within [`SNAPSHOT_EVERY`]).
//! - **Rate**: the nodes are asked [`IMAGES_MAX_HZ`] times a second at most, all sizes together,
//!   and for a full-size snapshot once every [`SNAPSHOT_EVERY`] at most.
//! - **Off the frame loop**: the loop only forwards the request to the nodes and hands back their
//!   raw tiles; composing and PNG-encoding happen on a blocking thread here.
//! - **Cancelled when the client leaves**: a request of the nodes lives as long as one client
//!   waits for it; when the last one goes (its connection closed), the frame loop drops it. A
//!   client waits [`WAIT_AT_MOST`] at most.

use super::commands::{ApiError, Captured, Command, Picture};
use crate::picture::compose_scaled;
use axum::http::StatusCode;
use std::collections::HashMap;
use std::net::{IpAddr, Ipv4Addr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, oneshot, watch};

/// Requests of the nodes per second at most, all sizes together, however many clients ask.
pub const IMAGES_MAX_HZ: f64 = 4.0;
/// A thumbnail is served again to whoever asks within this time of its taking.
pub const THUMBNAIL_EVERY: Duration = Duration::from_millis(250);
/// Full-size snapshots are asked of the nodes at most this often (and served again meanwhile).
pub const SNAPSHOT_EVERY: Duration = Duration::from_secs(1);
/// Picture requests one client (address) may have waiting.
pub const PER_CLIENT: usize = 4;
/// Picture requests all clients together may have waiting.
pub const TOTAL: usize = 32;
/// The longest a client waits for a picture.
pub const WAIT_AT_MOST: Duration = Duration::from_secs(15);

type Answer = Option<Result<Arc<Picture>, ApiError>>;

/// The pictures served and being asked for (one per console).
#[derive(Default)]
pub struct Pictures {
    inner: Mutex<Inner>,
}

#[derive(Default)]
struct Inner {
    /// The last picture of each divisor, and when it was taken.
    cache: HashMap<u32, (Instant, Arc<Picture>)>,
    /// The request of the nodes under way for each divisor; its askers are its receivers.
    in_flight: HashMap<u32, Arc<watch::Sender<Answer>>>,
    /// Picture requests waiting, by client.
    waiting: HashMap<IpAddr, usize>,
    /// When the nodes may next be asked, for any size and for a full-size snapshot.
    next_ask: Option<Instant>,
    next_full: Option<Instant>,
}

/// A place among the waiting requests, given back when dropped.
struct Admitted<'a> {
    pictures: &'a Pictures,
    client: IpAddr,
}

impl Drop for Admitted<'_> {
    fn drop(&mut self) {
        let mut inner = self.pictures.inner.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = inner.waiting.get_mut(&self.client) {
            *n -= 1;
            if *n == 0 {
                inner.waiting.remove(&self.client);
            }
        }
    }
}

impl Pictures {
    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn admit(&self, client: IpAddr) -> Result<Admitted<'_>, ApiError> {
        let mut inner = self.lock();
        let total: usize = inner.waiting.values().sum();
        if total >= TOTAL {
            return Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                format!("{total} picture requests are waiting for the wall already (at most {TOTAL}): try again later"),
            ));
        }
        let mine = inner.waiting.entry(client).or_insert(0);
        if *mine >= PER_CLIENT {
            return Err(ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                format!(
                    "{client} has {PER_CLIENT} picture requests waiting already (at most {PER_CLIENT} a client): wait for one"
                ),
            ));
        }
        *mine += 1;
        Ok(Admitted { pictures: self, client })
    }

    /// The wall downscaled by `divisor` (1: full size) for `client`: a recent picture of that
    /// size, or the one being taken, or a new request of the nodes (see the module's rules).
    pub async fn get(
        self: &Arc<Self>,
        commands: &mpsc::Sender<Command>,
        client: Option<IpAddr>,
        divisor: u32,
    ) -> Result<Arc<Picture>, ApiError> {
        let client = client.unwrap_or(IpAddr::V4(Ipv4Addr::UNSPECIFIED));
        let _admitted = self.admit(client)?;
        let mut rx = {
            let mut inner = self.lock();
            let fresh = if divisor <= 1 { SNAPSHOT_EVERY } else { THUMBNAIL_EVERY };
            if let Some((at, pic)) = inner.cache.get(&divisor) {
                if at.elapsed() < fresh {
                    return Ok(pic.clone());
                }
            }
            match inner.in_flight.get(&divisor) {
                Some(tx) => tx.subscribe(),
                None => {
                    let now = Instant::now();
                    let mut at = inner.next_ask.map_or(now, |t| t.max(now));
                    if divisor <= 1 {
                        at = inner.next_full.map_or(at, |t| t.max(at));
                        inner.next_full = Some(at + SNAPSHOT_EVERY);
                    }
                    inner.next_ask = Some(at + Duration::from_secs_f64(1.0 / IMAGES_MAX_HZ));
                    let (tx, rx) = watch::channel(None);
                    let tx = Arc::new(tx);
                    inner.in_flight.insert(divisor, tx.clone());
                    tokio::spawn(fetch(self.clone(), commands.clone(), divisor, at, tx));
                    rx
                }
            }
        };
        let waited = match tokio::time::timeout(WAIT_AT_MOST, rx.wait_for(Option::is_some)).await {
            Ok(Ok(answer)) => answer.clone().expect("waited for Some"),
            Ok(Err(_)) => Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "the picture request was dropped (its other clients left): try again",
            )),
            Err(_) => Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                format!("no picture of the wall within {WAIT_AT_MOST:?}"),
            )),
        };
        waited
    }
}

/// One request of the nodes for `divisor` at `at` (the rate's next place), composed and encoded
/// here; dropped, and with it the frame loop's request, as soon as no client waits for it.
async fn fetch(
    pictures: Arc<Pictures>,
    commands: mpsc::Sender<Command>,
    divisor: u32,
    at: Instant,
    tx: Arc<watch::Sender<Answer>>,
) {
    let stopped = || ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "the frame loop has stopped");
    let work = async {
        tokio::time::sleep_until(at.into()).await;
        let (reply, answer) = oneshot::channel();
        commands.send(Command::Images(divisor, reply)).await.map_err(|_| stopped())?;
        let captured = answer.await.map_err(|_| stopped())??;
        tokio::task::spawn_blocking(move || encode(&captured))
            .await
            .unwrap_or_else(|e| Err(ApiError::internal(format!("PNG encoder: {e}"))))
    };
    let result = tokio::select! {
        r = work => Some(r.map(Arc::new)),
        // Every client left: dropping `work` drops the frame loop's request too.
        () = tx.closed() => None,
    };
    let mut inner = pictures.lock();
    inner.in_flight.remove(&divisor);
    if let Some(r) = result {
        if let Ok(pic) = &r {
            inner.cache.insert(divisor, (pic.taken, pic.clone()));
        }
        tx.send_replace(Some(r));
    }
}

/// The captured tiles as one PNG.
fn encode(c: &Captured) -> Result<Picture, ApiError> {
    use image::ImageEncoder;
    let (w, h, rgb) = compose_scaled(&c.config, &c.tiles, c.divisor);
    let mut png = Vec::new();
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(&rgb, w, h, image::ExtendedColorType::Rgb8)
        .map_err(|e| ApiError::internal(format!("cannot encode the snapshot as PNG: {e}")))?;
    Ok(Picture { png, width: w, height: h, frame_id: c.frame_id, age: c.age, taken: c.taken })
}
