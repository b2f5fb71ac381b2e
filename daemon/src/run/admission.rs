//! Admission: who gets a connection to the node. Handshakes are bounded per source address and in
//! time, a peer is named by its certificate, a controller must say Hello in time, and a node's
//! pixel connection goes to the object-space inbox; anything else is closed with the reason.
//! Nothing here touches the running session.

use anyhow::Result;
use isowall_model::handshake_limit::{HandshakeLimit, HandshakeLimiter};
use isowall_model::messages::Message;
use isowall_net::pixels::PixelInbox;
use isowall_net::tls::PeerIdentity;
use isowall_net::transport::{self, Channel};

/// How long a peer has for its QUIC handshake, and a controller then for its stream and Hello.
pub(super) const HANDSHAKE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);
pub(super) const HELLO_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);

/// Live connections a daemon keeps per identity, at most: the controller's session and one being
/// refused (or, once the session's connection has closed, served); a peer node connects once and
/// again after a failure.
pub(super) const MAX_CONNECTIONS_PER_IDENTITY: usize = 2;

/// A controller's connection whose certificate is the controller's and whose first message is
/// its Hello (checked): only such a connection may drive the node, and only while no other does.
pub(super) struct Greeted {
    pub(super) channel: Channel,
    pub(super) hello: Message,
}

/// The handshake limit of the accept loop (the model's [`HandshakeLimiter`] on the daemon's
/// clock), and its refusals logged at most once a second.
#[derive(Clone)]
pub(super) struct Handshakes {
    epoch: std::time::Instant,
    inner: std::sync::Arc<std::sync::Mutex<(HandshakeLimiter, Option<std::time::Instant>, u64)>>,
}

/// A handshake the limit let start: give it back ([`Source::admitted`]) once the connection
/// is admitted, so the wall's own connections never spend the limit.
pub(super) struct Source {
    ip: std::net::IpAddr,
    handshakes: Handshakes,
}

impl Source {
    pub(super) fn admitted(&self) {
        let now = self.handshakes.epoch.elapsed();
        self.handshakes.inner.lock().expect("not poisoned").0.admitted(now, self.ip);
    }
}

impl Handshakes {
    pub(super) fn new(epoch: std::time::Instant) -> Handshakes {
        let limiter = HandshakeLimiter::new(HandshakeLimit::DAEMON);
        Handshakes { epoch, inner: std::sync::Arc::new(std::sync::Mutex::new((limiter, None, 0))) }
    }

    /// `Some` when `incoming`'s handshake may start; `None`: refuse it (logged, at most once a
    /// second, with the count).
    pub(super) fn start(&self, incoming: &quinn::Incoming) -> Option<Source> {
        let remote = incoming.remote_address();
        let ip = remote.ip().to_canonical();
        let mut guard = self.inner.lock().expect("not poisoned");
        let (limiter, last_log, unlogged) = &mut *guard;
        if limiter.start(self.epoch.elapsed(), ip) {
            return Some(Source { ip, handshakes: self.clone() });
        }
        *unlogged += 1;
        if last_log.is_none_or(|t| t.elapsed() >= std::time::Duration::from_secs(1)) {
            let HandshakeLimit { per_second, burst } = HandshakeLimit::DAEMON;
            let (started, refused) = limiter.counts();
            tracing::warn!(
                %remote,
                refused_since_last_line = *unlogged,
                handshakes_started = started,
                refused_in_all = refused,
                "refused a connection before its handshake: too many failed or refused handshakes \
                 from {ip} ({burst} at once, then {per_second} a second)"
            );
            *last_log = Some(std::time::Instant::now());
            *unlogged = 0;
        }
        None
    }
}

/// Live verified connections per identity.
#[derive(Clone, Default)]
pub(super) struct LiveConnections(
    std::sync::Arc<std::sync::Mutex<std::collections::HashMap<PeerIdentity, usize>>>,
);

impl LiveConnections {
    /// Counts `connection` for `who` until it closes; `false` (not counted) past the limit.
    pub(super) fn admit(&self, who: &PeerIdentity, connection: &quinn::Connection) -> bool {
        {
            let mut live = self.0.lock().expect("not poisoned");
            let n = live.entry(who.clone()).or_default();
            if *n >= MAX_CONNECTIONS_PER_IDENTITY {
                return false;
            }
            *n += 1;
        }
        let (me, who, connection) = (self.clone(), who.clone(), connection.clone());
        tokio::spawn(async move {
            connection.closed().await;
            if let Some(n) = me.0.lock().expect("not poisoned").get_mut(&who) {
                *n = n.saturating_sub(1);
            }
        });
        true
    }
}

/// One incoming connection, in its own task: the handshake, then who it is. The controller's
/// queues for the session once its Hello is checked; another node's goes to the object-space
/// inbox; anything else is closed with the reason. Nothing here touches the running session.
pub(super) async fn admit(
    incoming: quinn::Incoming,
    source: Source,
    session: tokio::sync::mpsc::Sender<Greeted>,
    inbox: Option<PixelInbox>,
    live: LiveConnections,
    limit: usize,
) {
    let remote = incoming.remote_address();
    let conn = match tokio::time::timeout(HANDSHAKE_TIMEOUT, incoming).await {
        Ok(Ok(c)) => c,
        Ok(Err(e)) => {
            tracing::warn!(%remote, "refused a connection: {e}");
            return;
        }
        Err(_) => {
            tracing::warn!(%remote, "refused a connection: handshake timed out");
            return;
        }
    };
    let refuse = |peer: &dyn std::fmt::Display, reason: String| {
        tracing::warn!(%remote, %peer, "refused a connection: {reason}");
        transport::close(&conn, &reason);
    };
    let who = match isowall_net::tls::peer_identity(&conn) {
        Ok(who) => who,
        Err(e) => return refuse(&"unknown", e),
    };
    if !live.admit(&who, &conn) {
        let reason = format!("{who} already has {MAX_CONNECTIONS_PER_IDENTITY} connections open");
        return refuse(&who, reason);
    }
    match (&who, inbox) {
        (PeerIdentity::Node(_), Some(inbox)) => {
            source.admitted();
            inbox.accept(conn)
        }
        (PeerIdentity::Node(_), None) => {
            refuse(&who, format!("{who}'s certificate is not the controller's: it may not drive a node"))
        }
        (PeerIdentity::Controller, _) => match tokio::time::timeout(HELLO_TIMEOUT, greet(&conn, limit)).await
        {
            Ok(Ok(greeted)) => {
                source.admitted();
                let _ = session.send(greeted).await;
            }
            Ok(Err(reason)) => refuse(&who, reason),
            Err(_) => refuse(&who, format!("no stream and Hello within {} s", HELLO_TIMEOUT.as_secs())),
        },
    }
}

/// The controller's stream and its Hello (the first message), checked.
pub(super) async fn greet(conn: &quinn::Connection, limit: usize) -> Result<Greeted, String> {
    let peer = isowall_net::tls::CONTROLLER;
    let mut channel = Channel::accept(conn.clone(), peer, limit).await.map_err(|e| e.to_string())?;
    let hello = match channel.receiver.recv().await {
        Ok(Some(m)) => m,
        Ok(None) => return Err(format!("`{peer}` ended its stream before its Hello")),
        Err(e) => return Err(e.to_string()),
    };
    if let Err(e) = isowall_model::codec::check_hello(&hello, isowall_model::messages::Role::Controller) {
        return Err(
            isowall_model::messages::ProtocolError::new(peer, hello.kind(), e.to_string()).to_string()
        );
    }
    Ok(Greeted { channel, hello })
}
