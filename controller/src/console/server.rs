//! The console's HTTP/1 server: hyper under the axum router, with the limits `axum::serve` does
//! not set. A client cannot hold the console by opening connections and sending nothing, or half
//! a request:
//! - at most [`Limits::max_connections`] connections are open at once (a WebSocket, once
//!   upgraded, counts against `api`'s own limit instead). When a new one comes past the limit,
//!   the oldest connection that is not in the middle of a request (it has sent no whole header
//!   yet, or waits idle between requests) is closed to make room; when every one is busy, the
//!   new one is closed. So a crowd of half-sent requests holds a newcomer out for no time at
//!   all, and the process never runs out of file descriptors;
//! - a connection that has not sent a request's whole header [`Limits::header_read_timeout`]
//!   after it was accepted or after its last response (idle keep-alive) is closed;
//! - a request body must arrive within [`Limits::body_timeout`] (`api::read_body_within`).
//!
//! Each request carries the client's address (`axum::extract::ConnectInfo`) for the per-client
//! limits of `pictures.rs`.

use axum::extract::ConnectInfo;
use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use std::collections::BTreeMap;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::oneshot;

/// The server's limits.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    pub max_connections: usize,
    pub header_read_timeout: Duration,
    pub body_timeout: Duration,
}

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            max_connections: 256,
            header_read_timeout: Duration::from_secs(5),
            body_timeout: Duration::from_secs(10),
        }
    }
}

/// The open connections, oldest first (ids increase), each with its requests under way and the
/// way to close it.
#[derive(Default)]
struct Table {
    next: u64,
    open: BTreeMap<u64, Entry>,
    /// Connections closed to make room (for the log).
    evicted: u64,
}

struct Entry {
    busy: usize,
    close: Option<oneshot::Sender<()>>,
}

type Shared = Arc<Mutex<Table>>;

fn lock(t: &Shared) -> std::sync::MutexGuard<'_, Table> {
    t.lock().unwrap_or_else(|e| e.into_inner())
}

/// Marks a connection busy while one of its requests is handled.
struct Busy(Shared, u64);

impl Busy {
    fn new(table: &Shared, id: u64) -> Busy {
        if let Some(e) = lock(table).open.get_mut(&id) {
            e.busy += 1;
        }
        Busy(table.clone(), id)
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        if let Some(e) = lock(&self.0).open.get_mut(&self.1) {
            e.busy -= 1;
        }
    }
}

/// Registers a new connection; past `max`, closes the oldest idle one, or says `None` (close the
/// new one) when every connection is busy.
fn admit(table: &Shared, max: usize) -> Option<(u64, oneshot::Receiver<()>)> {
    let mut t = lock(table);
    if t.open.len() >= max {
        let oldest_idle = t.open.iter().find(|(_, e)| e.busy == 0).map(|(id, _)| *id)?;
        if let Some(mut e) = t.open.remove(&oldest_idle) {
            if let Some(close) = e.close.take() {
                let _ = close.send(());
            }
        }
        t.evicted += 1;
        if t.evicted.is_power_of_two() {
            tracing::warn!(
                "console: {} connections closed to make room (at most {max} open; they had sent no whole request)",
                t.evicted
            );
        }
    }
    let id = t.next;
    t.next += 1;
    let (close, closed) = oneshot::channel();
    t.open.insert(id, Entry { busy: 0, close: Some(close) });
    Some((id, closed))
}

/// Serves `router` on `listener` under `limits` until `shutdown` resolves; connections under way
/// are then dropped. A connection's failure is its own (logged at debug), never the server's.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: Limits,
    shutdown: impl Future<Output = ()>,
) {
    let table: Shared = Arc::default();
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder.timer(TokioTimer::new()).header_read_timeout(limits.header_read_timeout);
    let mut last_error: Option<std::time::Instant> = None;
    tokio::pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            a = listener.accept() => match a {
                Ok(a) => a,
                Err(e) => {
                    // Out of file descriptors or the like: logged once a second at most, and
                    // tried again shortly (the connection waiting stays queued).
                    if last_error.is_none_or(|t| t.elapsed() > Duration::from_secs(1)) {
                        tracing::warn!("console: cannot accept a connection: {e}");
                        last_error = Some(std::time::Instant::now());
                    }
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = &mut shutdown => return,
        };
        let Some((id, closed)) = admit(&table, limits.max_connections.max(1)) else {
            tracing::debug!(
                "console: {peer} closed at once: {} connections, all busy",
                limits.max_connections
            );
            continue;
        };
        let _ = stream.set_nodelay(true);
        let (router, builder, table) = (router.clone(), builder.clone(), table.clone());
        tokio::spawn(async move {
            let in_service = table.clone();
            let service = hyper::service::service_fn(move |mut req: hyper::Request<Incoming>| {
                req.extensions_mut().insert(ConnectInfo::<SocketAddr>(peer));
                let busy = Busy::new(&in_service, id);
                let answer = hyper::service::Service::call(&TowerToHyperService::new(router.clone()), req);
                async move {
                    let r = answer.await;
                    drop(busy);
                    r
                }
            });
            let conn = builder.serve_connection(TokioIo::new(stream), service).with_upgrades();
            tokio::select! {
                r = conn => {
                    if let Err(e) = r {
                        tracing::debug!("console: connection from {peer}: {e}");
                    }
                }
                _ = closed => tracing::debug!("console: connection from {peer} closed to make room"),
            }
            lock(&table).open.remove(&id);
        });
    }
}
