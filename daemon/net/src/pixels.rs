//! Object space's pixel streams, node to node (direct send): one unidirectional QUIC stream per
//! frame per peer carries one `PeerPixels` (the model's codec makes and reads the bytes; the
//! model's `ObjectMachine` decides what to send and checks what arrives).
//!
//! Every wait for a peer has a deadline: a stream must be read whole within the wall's deadline
//! (else it is stopped, and that frame goes on without it), and a send must be written within it
//! (else the stream is reset); a peer that does not keep up has at most [`SENDS_IN_FLIGHT`]
//! sends under way, later frames' pixels for it are dropped. A stream longer than the limit is
//! refused unread, and so is a connection whose certificate is not another node's of the wall;
//! a refusal closes that connection with a reason naming the peer, nothing else.

use crate::transport::{self, NetError};
use crate::Identity;
use isowall_model::codec;
use isowall_model::composite::PeerPixels;
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Sends under way to one peer at most (each ends within the deadline).
pub const SENDS_IN_FLIGHT: usize = 4;

/// The QUIC application error code of a stream stopped or reset on a deadline.
const STREAM_DEADLINE: u32 = 2;

/// A peer's connection, to close when what it sends breaks the rules, and its link number: a
/// counter stamped when it was accepted, never reused (the model's `composite::Link`), so what it
/// carried is told apart from what a newer connection of the same certificate carries.
#[derive(Clone, Debug)]
pub struct PeerConnection {
    connection: quinn::Connection,
    link: isowall_model::links::Link,
}

/// The next link number of an accepted peer connection.
static NEXT_LINK: AtomicU64 = AtomicU64::new(1);

impl PeerConnection {
    fn new(connection: quinn::Connection) -> PeerConnection {
        PeerConnection { connection, link: NEXT_LINK.fetch_add(1, Ordering::Relaxed) }
    }

    /// Closes the connection with a reason the peer reads.
    pub fn close(&self, reason: &str) {
        transport::close(&self.connection, reason);
    }

    pub fn link(&self) -> isowall_model::links::Link {
        self.link
    }

    /// Whether the connection is still open.
    pub fn is_open(&self) -> bool {
        self.connection.close_reason().is_none()
    }
}

/// A peer's pixels as they arrive: the node its certificate names, its connection, the pixels.
#[derive(Debug)]
pub struct PeerPixelsIn {
    pub cert: String,
    pub connection: PeerConnection,
    pub pixels: PeerPixels,
}

/// Outgoing connections to the peers that show tiles (connected on first use, again after a
/// failure); one stream per frame per peer.
pub struct PixelOutbox {
    endpoint: quinn::Endpoint,
    addrs: HashMap<String, SocketAddr>,
    conns: Arc<Mutex<HashMap<String, quinn::Connection>>>,
    in_flight: HashMap<String, Arc<AtomicUsize>>,
    deadline: Duration,
}

impl PixelOutbox {
    /// An outbox presenting `identity` to the peers at `addrs` (inside the async runtime), each
    /// send given `deadline`.
    pub fn new(
        identity: &Identity,
        addrs: HashMap<String, SocketAddr>,
        deadline: Duration,
    ) -> Result<PixelOutbox, NetError> {
        let in_flight = addrs.keys().map(|k| (k.clone(), Arc::new(AtomicUsize::new(0)))).collect();
        Ok(PixelOutbox {
            endpoint: transport::client(identity)?,
            addrs,
            conns: Arc::new(Mutex::new(HashMap::new())),
            in_flight,
            deadline,
        })
    }

    /// Closes the connection to `peer`, if there is one, with `reason`: the next send connects
    /// afresh (the peer is a new process; the connection to the one before may not have timed out).
    pub fn forget(&self, peer: &str, reason: &str) {
        if let Some(c) = self.conns.lock().expect("not poisoned").remove(peer) {
            tracing::info!(%peer, "closing the connection to the peer: {reason}");
            transport::close(&c, reason);
        }
    }

    /// Sends `bytes` (a frame's pixels) to `peer` in a task of its own.
    pub fn send(&self, peer: &str, frame_id: u64, bytes: Vec<u8>) {
        let (Some(&addr), Some(count)) = (self.addrs.get(peer), self.in_flight.get(peer)) else {
            tracing::error!(frame_id, %peer, "cannot send pixels: not a peer that shows tiles");
            return;
        };
        if count.fetch_add(1, Ordering::SeqCst) >= SENDS_IN_FLIGHT {
            count.fetch_sub(1, Ordering::SeqCst);
            tracing::warn!(frame_id, %peer, "dropping pixels: {SENDS_IN_FLIGHT} sends to it are still under way");
            return;
        }
        let (endpoint, conns, count, deadline) =
            (self.endpoint.clone(), self.conns.clone(), count.clone(), self.deadline);
        let peer = peer.to_string();
        tokio::spawn(async move {
            let cached = conns.lock().expect("not poisoned").get(&peer).cloned();
            let send = async {
                let conn = match cached.filter(|c| c.close_reason().is_none()) {
                    Some(c) => c,
                    None => {
                        let c =
                            transport::connect(&endpoint, addr, &peer).await.map_err(|e| e.to_string())?;
                        conns.lock().expect("not poisoned").insert(peer.clone(), c.clone());
                        c
                    }
                };
                let mut s = conn.open_uni().await.map_err(|e| e.to_string())?;
                match tokio::time::timeout(deadline, s.write_all(&bytes)).await {
                    Ok(r) => r.map_err(|e| e.to_string())?,
                    Err(_) => {
                        let _ = s.reset(quinn::VarInt::from_u32(STREAM_DEADLINE));
                        return Err(format!(
                            "not written within the deadline of {} ms",
                            deadline.as_millis()
                        ));
                    }
                }
                s.finish().map_err(|e| e.to_string())
            };
            let r = match tokio::time::timeout(deadline, send).await {
                Ok(r) => r,
                Err(_) => Err(format!("no connection within the deadline of {} ms", deadline.as_millis())),
            };
            if let Err(e) = r {
                tracing::warn!(frame_id, %peer, "sending pixels failed: {e}");
                conns.lock().expect("not poisoned").remove(&peer);
            }
            count.fetch_sub(1, Ordering::SeqCst);
        });
    }
}

/// Takes peers' connections (the node's server endpoint hands them over) and hands their pixels
/// to `tx`.
#[derive(Clone)]
pub struct PixelInbox {
    tx: tokio::sync::mpsc::Sender<PeerPixelsIn>,
    /// The wall's nodes.
    nodes: Vec<String>,
    own: String,
    /// The longest stream read.
    limit: usize,
    /// How long a stream may take to arrive whole.
    deadline: Duration,
}

impl PixelInbox {
    /// The inbox of node `own` of a wall of `nodes`, streams of at most `limit` bytes each read
    /// within `deadline`.
    pub fn new(
        tx: tokio::sync::mpsc::Sender<PeerPixelsIn>,
        nodes: Vec<String>,
        own: &str,
        limit: usize,
        deadline: Duration,
    ) -> PixelInbox {
        PixelInbox { tx, nodes, own: own.to_string(), limit, deadline }
    }

    /// Serves a peer's connection in its own task: each must carry another node's certificate.
    pub fn accept(&self, conn: quinn::Connection) {
        let me = self.clone();
        tokio::spawn(async move {
            let remote = conn.remote_address();
            let Some(cert) =
                me.nodes.iter().find(|n| **n != me.own && crate::tls::peer_is(&conn, n)).cloned()
            else {
                tracing::warn!(%remote, "refused a connection: its certificate is neither the controller's nor another node's");
                transport::close(&conn, "only the controller and the wall's other nodes may connect");
                return;
            };
            let peer = PeerConnection::new(conn.clone());
            tracing::info!(peer = %cert, %remote, link = peer.link, "peer connected (object space)");
            loop {
                let mut stream = match conn.accept_uni().await {
                    Ok(s) => s,
                    Err(e) => {
                        tracing::info!(peer = %cert, "peer connection ended: {e}");
                        return;
                    }
                };
                let bytes = match tokio::time::timeout(me.deadline, stream.read_to_end(me.limit)).await {
                    Ok(Ok(b)) => b,
                    Ok(Err(e)) => {
                        let reason = format!("pixels from `{cert}`: {e} (limit {} bytes)", me.limit);
                        tracing::warn!("closing the peer's connection: {reason}");
                        transport::close(&conn, &reason);
                        return;
                    }
                    Err(_) => {
                        let _ = stream.stop(quinn::VarInt::from_u32(STREAM_DEADLINE));
                        tracing::warn!(
                            peer = %cert,
                            "pixels from `{cert}` not complete within the deadline of {} ms: stream stopped",
                            me.deadline.as_millis()
                        );
                        continue;
                    }
                };
                match codec::decode_pixels(&bytes) {
                    Ok(pixels) => {
                        let item = PeerPixelsIn { cert: cert.clone(), connection: peer.clone(), pixels };
                        if me.tx.send(item).await.is_err() {
                            return;
                        }
                    }
                    Err(e) => {
                        let reason = format!("bad pixels from `{cert}`: {e}");
                        tracing::warn!("closing the peer's connection: {reason}");
                        transport::close(&conn, &reason);
                        return;
                    }
                }
            }
        });
    }
}
