//! QUIC endpoints and framed message channels. One bidirectional stream per connection carries
//! length-prefixed [`Message`]s (the model's codec frames them); a message over the wall's limit,
//! or bytes that do not decode, end that connection with a reason and nothing else.

use crate::tls::{Identity, TlsError};
use isowall_model::codec::{self, CodecError, Decoder};
use isowall_model::messages::Message;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

/// The application protocol name both sides announce.
pub const ALPN: &[u8] = b"isowall/1";

#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error(transparent)]
    Tls(#[from] TlsError),
    #[error("cannot listen on {addr}: {}", bind_reason(*addr, error))]
    Bind { addr: SocketAddr, error: std::io::Error },
    #[error("cannot resolve '{0}' to an address")]
    Resolve(String),
    #[error("connecting to {peer}: {reason}")]
    Connect { peer: String, reason: String },
    #[error("connection to {peer} lost: {reason}")]
    Connection { peer: String, reason: String },
    #[error("{peer} sent a bad message: {source}")]
    Codec { peer: String, source: CodecError },
}

/// Unidirectional streams a peer may have open at once (object space: frames of pixels).
pub const MAX_UNI_STREAMS: u32 = 8;
/// Bytes a peer may have in flight on one stream (flow control), at most.
pub const STREAM_FLOW_LIMIT: u32 = 4 << 20;
/// Bytes a peer may have in flight on one connection, all streams together, at most.
pub const CONNECTION_FLOW_LIMIT: u32 = 16 << 20;
/// Connections a server endpoint lets wait for their handshake at once, at most.
pub const MAX_INCOMING: usize = 64;
/// The round trip assumed before one is measured. A wall's links are a LAN, so RFC 9002's 333 ms,
/// meant for the Internet, would make a lost handshake packet wait about a second to be sent again
/// (two in a row three seconds, a controller's connect deadline); with 100 ms the first probe goes
/// after about 325 ms.
pub const INITIAL_RTT: Duration = Duration::from_millis(100);
/// A connection whose peer has sent nothing this long is closed (its process or host is gone):
/// keep-alives every 500 ms keep a live one open.
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(5);

/// A QUIC server configuration of `identity`'s TLS ([`Identity::server_tls`]) with the wall's
/// transport settings and at most [`MAX_INCOMING`] handshakes waiting.
fn server_config(identity: &Identity) -> Result<quinn::ServerConfig, TlsError> {
    let quic = quinn::crypto::rustls::QuicServerConfig::try_from(identity.server_tls()?)
        .map_err(|e| TlsError::Config(e.to_string()))?;
    let mut config = quinn::ServerConfig::with_crypto(Arc::new(quic));
    config.transport_config(Arc::new(transport_config()));
    config.max_incoming(MAX_INCOMING);
    Ok(config)
}

/// A QUIC client configuration of `identity`'s TLS ([`Identity::client_tls`]) with the wall's
/// transport settings.
fn client_config(identity: &Identity) -> Result<quinn::ClientConfig, TlsError> {
    let quic = quinn::crypto::rustls::QuicClientConfig::try_from(identity.client_tls()?)
        .map_err(|e| TlsError::Config(e.to_string()))?;
    let mut config = quinn::ClientConfig::new(Arc::new(quic));
    config.transport_config(Arc::new(transport_config()));
    Ok(config)
}

/// Transport settings: keep-alives so a dead peer is noticed within the idle timeout, and prompt
/// acknowledgements for a LAN.
///
/// A wall's traffic is a few messages per frame, each often the last packet in flight, so a lost
/// one is found only by the probe timeout (PTO = smoothed RTT + 4 x RTT variance + the peer's
/// max ACK delay). QUIC's default max ACK delay of 25 ms dominated that on a LAN: it set the
/// barrier's p99 under 1-5 % loss (`tests/tests/network.rs`). Through the ACK frequency extension
/// (both ends are quinn) every ack-eliciting packet is acknowledged at once and the delay asked
/// of the peer is 1 ms; acknowledgements for a few messages per frame cost little.
///
/// Limits, set here rather than left to quinn's defaults (which allow 100 streams of each kind, no
/// flow-control limit per connection, and datagrams): a peer may open one bidirectional stream at
/// a time (the message channel) and [`MAX_UNI_STREAMS`] unidirectional ones (object space: one per
/// frame of pixels), and have at most [`STREAM_FLOW_LIMIT`] bytes in flight per stream and
/// [`CONNECTION_FLOW_LIMIT`] per connection (QUIC flow control), so what a connection can make the
/// receiver buffer is bounded whatever the peer does; no datagrams.
pub fn transport_config() -> quinn::TransportConfig {
    let mut t = quinn::TransportConfig::default();
    t.max_concurrent_bidi_streams(quinn::VarInt::from_u32(1));
    t.max_concurrent_uni_streams(quinn::VarInt::from_u32(MAX_UNI_STREAMS));
    t.stream_receive_window(quinn::VarInt::from_u32(STREAM_FLOW_LIMIT));
    t.receive_window(quinn::VarInt::from_u32(CONNECTION_FLOW_LIMIT));
    t.send_window(u64::from(CONNECTION_FLOW_LIMIT));
    t.datagram_receive_buffer_size(None);
    t.initial_rtt(INITIAL_RTT);
    t.keep_alive_interval(Some(Duration::from_millis(500)));
    t.max_idle_timeout(Some(IDLE_TIMEOUT.try_into().expect("5 s is a valid idle timeout")));
    let mut acks = quinn::AckFrequencyConfig::default();
    acks.ack_eliciting_threshold(quinn::VarInt::from_u32(0)).max_ack_delay(Some(Duration::from_millis(1)));
    t.ack_frequency_config(Some(acks));
    t
}

/// Resolves `host:port` (the first address).
pub fn resolve(address: &str) -> Result<SocketAddr, NetError> {
    use std::net::ToSocketAddrs;
    address
        .to_socket_addrs()
        .ok()
        .and_then(|mut a| a.next())
        .ok_or_else(|| NetError::Resolve(address.to_string()))
}

/// Why a bind failed, in words: a port in use says so and how to find who holds it.
fn bind_reason(addr: SocketAddr, error: &std::io::Error) -> String {
    if error.kind() == std::io::ErrorKind::AddrInUse {
        format!(
            "the address is in use: another process holds UDP port {port} (QUIC runs over UDP; \
             `ss -ulpn 'sport = :{port}'` shows which) ({error})",
            port = addr.port()
        )
    } else {
        error.to_string()
    }
}

/// Whether `addr` can be listened on now (a UDP socket is bound there and closed at once), so a
/// daemon whose port is taken fails before its slow set-up rather than after.
pub fn check_bindable(addr: SocketAddr) -> Result<(), NetError> {
    std::net::UdpSocket::bind(addr).map(drop).map_err(|error| NetError::Bind { addr, error })
}

/// A server endpoint on `addr` that accepts only peers with a wall certificate.
pub fn server(addr: SocketAddr, identity: &Identity) -> Result<quinn::Endpoint, NetError> {
    quinn::Endpoint::server(server_config(identity)?, addr).map_err(|error| NetError::Bind { addr, error })
}

/// A client endpoint presenting `identity`.
pub fn client(identity: &Identity) -> Result<quinn::Endpoint, NetError> {
    let bind: SocketAddr = "0.0.0.0:0".parse().expect("valid address");
    let mut ep = quinn::Endpoint::client(bind).map_err(|error| NetError::Bind { addr: bind, error })?;
    ep.set_default_client_config(client_config(identity)?);
    Ok(ep)
}

/// Connects to the node `name` at `addr`; its certificate must be signed by the wall CA and name
/// exactly `name` (TLS's own check ignores case).
pub async fn connect(
    endpoint: &quinn::Endpoint,
    addr: SocketAddr,
    name: &str,
) -> Result<quinn::Connection, NetError> {
    let err = |reason: String| NetError::Connect { peer: format!("{name} ({addr})"), reason };
    let conn = endpoint
        .connect(addr, name)
        .map_err(|e| err(e.to_string()))?
        .await
        .map_err(|e| err(e.to_string()))?;
    match crate::tls::peer_identity(&conn) {
        Ok(crate::tls::PeerIdentity::Node(n)) if n == name => Ok(conn),
        Ok(other) => {
            let reason = format!("its certificate is {other}'s, not node `{name}`'s");
            close(&conn, &reason);
            Err(err(reason))
        }
        Err(e) => {
            close(&conn, &e);
            Err(err(e))
        }
    }
}

/// The sending half of a channel.
pub struct ChannelSender {
    pub peer: String,
    send: quinn::SendStream,
}

/// The receiving half of a channel.
pub struct ChannelReceiver {
    pub peer: String,
    recv: quinn::RecvStream,
    decoder: Decoder,
}

/// A framed, bidirectional message channel over one QUIC stream.
pub struct Channel {
    pub connection: quinn::Connection,
    pub sender: ChannelSender,
    pub receiver: ChannelReceiver,
}

impl Channel {
    /// Opens the channel (the connecting side).
    pub async fn open(connection: quinn::Connection, peer: &str, limit: usize) -> Result<Channel, NetError> {
        let (send, recv) = connection
            .open_bi()
            .await
            .map_err(|e| NetError::Connection { peer: peer.to_string(), reason: e.to_string() })?;
        Ok(Channel::new(connection, peer, send, recv, limit))
    }

    /// Accepts the channel (the listening side).
    pub async fn accept(
        connection: quinn::Connection,
        peer: &str,
        limit: usize,
    ) -> Result<Channel, NetError> {
        let (send, recv) = connection
            .accept_bi()
            .await
            .map_err(|e| NetError::Connection { peer: peer.to_string(), reason: e.to_string() })?;
        Ok(Channel::new(connection, peer, send, recv, limit))
    }

    fn new(
        connection: quinn::Connection,
        peer: &str,
        send: quinn::SendStream,
        recv: quinn::RecvStream,
        limit: usize,
    ) -> Channel {
        Channel {
            connection,
            sender: ChannelSender { peer: peer.to_string(), send },
            receiver: ChannelReceiver { peer: peer.to_string(), recv, decoder: Decoder::new(limit) },
        }
    }

    /// Closes the connection with a reason the peer sees.
    pub fn close(&self, reason: &str) {
        close(&self.connection, reason);
    }
}

/// Closes a connection with an application reason (trimmed to fit a frame).
pub fn close(connection: &quinn::Connection, reason: &str) {
    let reason: String = reason.chars().take(200).collect();
    connection.close(quinn::VarInt::from_u32(1), reason.as_bytes());
}

impl ChannelSender {
    pub async fn send(&mut self, message: &Message) -> Result<(), NetError> {
        let bytes =
            codec::frame(message).map_err(|source| NetError::Codec { peer: self.peer.clone(), source })?;
        self.send
            .write_all(&bytes)
            .await
            .map_err(|e| NetError::Connection { peer: self.peer.clone(), reason: e.to_string() })
    }

    /// Writes `bytes` to the stream as they are, framed or not. For tests that play a misbehaving
    /// peer (oversized, truncated or undecodable frames); the binaries send only through
    /// [`ChannelSender::send`].
    pub async fn send_raw(&mut self, bytes: &[u8]) -> Result<(), NetError> {
        self.send
            .write_all(bytes)
            .await
            .map_err(|e| NetError::Connection { peer: self.peer.clone(), reason: e.to_string() })
    }

    /// Finishes the stream (the peer's receiver sees its end). For tests, like
    /// [`ChannelSender::send_raw`].
    pub fn finish(&mut self) -> Result<(), NetError> {
        self.send
            .finish()
            .map_err(|e| NetError::Connection { peer: self.peer.clone(), reason: e.to_string() })
    }
}

impl ChannelReceiver {
    /// Frames of one kind of message are refused over a limit of their own, before their bodies
    /// are buffered ([`isowall_model::codec::Decoder::limit_kind`]).
    pub fn limit_kind(&mut self, k: codec::KindLimit) {
        self.decoder.limit_kind(k);
    }

    /// The next message; `None` when the peer finished the stream cleanly, between two frames (a
    /// stream that ends inside a frame is a [`CodecError::Truncated`] error).
    pub async fn recv(&mut self) -> Result<Option<Message>, NetError> {
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            match self.decoder.next() {
                Ok(Some(m)) => return Ok(Some(m)),
                Ok(None) => {}
                Err(source) => return Err(NetError::Codec { peer: self.peer.clone(), source }),
            }
            match self.recv.read(&mut buf).await {
                Ok(Some(n)) => self.decoder.push(&buf[..n]),
                Ok(None) => {
                    self.decoder
                        .finish()
                        .map_err(|source| NetError::Codec { peer: self.peer.clone(), source })?;
                    return Ok(None);
                }
                Err(e) => {
                    return Err(NetError::Connection { peer: self.peer.clone(), reason: e.to_string() })
                }
            }
        }
    }
}

/// Shared handle for a sender used from several tasks.
pub type SharedSender = Arc<tokio::sync::Mutex<ChannelSender>>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_port_in_use_is_named_with_its_address() {
        let taken = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let addr = taken.local_addr().unwrap();
        let e = check_bindable(addr).unwrap_err().to_string();
        assert!(
            e.starts_with(&format!(
                "cannot listen on {addr}: the address is in use: another process holds UDP port {}",
                addr.port()
            )),
            "{e}"
        );
        drop(taken);
        check_bindable(addr).unwrap();
    }
}
