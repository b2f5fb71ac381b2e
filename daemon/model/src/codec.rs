//! The bytes of [`Message`]s: the one place that calls bincode.
//!
//! A message is bincode 2 (`config::standard()`: little-endian, variable-length integers) of the
//! serde form of [`Message`]. On a stream each message is a *frame*: a `u32` little-endian length,
//! then that many bytes of exactly one message.
//!
//! Nothing a peer sends can make the receiver allocate much more than it is willing to accept:
//! - [`Decoder`] reads a frame's length first and rejects one over its limit before buffering any
//!   of its body;
//! - inside a frame, bincode's own limit ([`bincode::config::Configuration::with_limit`]) bounds
//!   what decoding may claim, so a length field inside the message (a string, a byte buffer) that
//!   claims more than that fails before anything is allocated for it. Bincode counts what it
//!   decodes at its size in memory, not on the wire (a varint `u64` of one byte counts 8), so a
//!   valid body of `n` bytes claims up to [`CLAIM_PER_BYTE`] x `n`; the limit is the smallest power
//!   of two >= that ([`claim_limit`]): at most 16 x the frame, never more than 16 x the decoder's
//!   limit.
//!
//! - a kind of message may have a smaller limit of its own ([`Decoder::limit_kind`], e.g. a
//!   node's cost report, whose entries the split bounds): the kind is read from the frame's
//!   first bytes, and a frame over its kind's limit is refused before its body is buffered.
//!
//! Errors never panic; after one, a [`Decoder`] refuses everything (the stream has lost its
//! framing) and the caller closes the connection with the error as the reason.

use bincode::config;
use bincode::error::DecodeError;

use crate::messages::{Message, Role, PROTOCOL_VERSION};

/// Bytes of the length prefix.
pub const HEADER_LEN: usize = 4;
/// No decoder accepts a frame longer than this, whatever its limit (1 GiB).
pub const MAX_FRAME_LEN: usize = 1 << 30;
/// A sensible limit for what a daemon accepts from the controller: nothing it sends is large.
pub const DAEMON_LIMIT: usize = 1 << 20;
/// A sensible limit for what the controller accepts from a daemon: snapshots carry whole tiles
/// (four 4K tiles of RGB8 are about 100 MB).
pub const CONTROLLER_LIMIT: usize = 256 << 20;

/// Why bytes could not become a message, or a message bytes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    #[error("cannot encode a {kind} message: {reason}")]
    Encode { kind: &'static str, reason: String },
    #[error("a frame of {len} bytes is over the limit of {limit} bytes")]
    TooLong { len: usize, limit: usize },
    #[error("a {kind} of {len} bytes is over its limit of {limit} bytes ({why})")]
    KindTooLong { kind: &'static str, len: usize, limit: usize, why: String },
    #[error("malformed message in a frame of {len} bytes: {reason}")]
    Malformed { len: usize, reason: String },
    #[error("{extra} bytes of garbage after a {kind} message inside its frame")]
    TrailingBytes { kind: &'static str, extra: usize },
    /// The stream ended inside a frame: `have` bytes of it (header included) had arrived, of
    /// `need` (`None` while the 4-byte length itself was incomplete).
    #[error("the stream ended inside a frame: {have} of {} bytes", need.map_or("at least 4".to_string(), |n| n.to_string()))]
    Truncated { have: usize, need: Option<usize> },
    #[error("the stream broke earlier ({0}); close the connection")]
    Broken(Box<CodecError>),
}

/// Why a connection's first message does not open it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HandshakeError {
    #[error("the first message must be Hello, not {0}")]
    NotHello(&'static str),
    #[error("peer `{name}` speaks protocol version {theirs}, this build speaks {ours}")]
    Version { name: String, ours: u16, theirs: u16 },
    #[error("peer `{name}` says it is a {got}, expected a {expected}")]
    Role { name: String, expected: &'static str, got: &'static str },
    #[error("peer name `{0}` is empty or not printable")]
    BadName(String),
}

/// Checks a connection's first message: a [`Message::Hello`] of this protocol version from a
/// peer of the `expected` role. Returns the peer's name.
pub fn check_hello(msg: &Message, expected: Role) -> Result<String, HandshakeError> {
    let Message::Hello { version, name, role } = msg else {
        return Err(HandshakeError::NotHello(msg.kind()));
    };
    if *version != PROTOCOL_VERSION {
        return Err(HandshakeError::Version { name: name.clone(), ours: PROTOCOL_VERSION, theirs: *version });
    }
    if *role != expected {
        return Err(HandshakeError::Role { name: name.clone(), expected: expected.name(), got: role.name() });
    }
    if name.is_empty() || name.len() > 256 || name.chars().any(|c| c.is_control()) {
        return Err(HandshakeError::BadName(name.escape_debug().to_string()));
    }
    Ok(name.clone())
}

/// A Hello of this build.
pub fn hello(name: &str, role: Role) -> Message {
    Message::Hello { version: PROTOCOL_VERSION, name: name.to_string(), role }
}

fn encode_err(msg: &Message, e: impl std::fmt::Display) -> CodecError {
    CodecError::Encode { kind: msg.kind(), reason: e.to_string() }
}

/// The bytes of one message (no length prefix).
pub fn encode(msg: &Message) -> Result<Vec<u8>, CodecError> {
    bincode::serde::encode_to_vec(msg, config::standard()).map_err(|e| encode_err(msg, e))
}

/// One frame: the message's length as `u32` little-endian, then the message.
pub fn frame(msg: &Message) -> Result<Vec<u8>, CodecError> {
    let mut out = vec![0u8; HEADER_LEN];
    bincode::serde::encode_into_std_write(msg, &mut out, config::standard())
        .map_err(|e| encode_err(msg, e))?;
    let len = out.len() - HEADER_LEN;
    if len > MAX_FRAME_LEN {
        return Err(CodecError::TooLong { len, limit: MAX_FRAME_LEN });
    }
    out[..HEADER_LEN].copy_from_slice(&(len as u32).to_le_bytes());
    Ok(out)
}

/// Decodes `body` with bincode's limit `N`.
fn decode_limited<T: serde::de::DeserializeOwned, const N: usize>(
    body: &[u8],
) -> Result<(T, usize), DecodeError> {
    bincode::serde::decode_from_slice(body, config::standard().with_limit::<N>())
}

/// What bincode may claim per byte of a body, at most: every value counts its size in memory
/// (`u64`, `i64`, `usize` lengths and `f64`: 8) for at least one byte on the wire. (No wire type
/// holds a 128-bit integer, which would count 16.)
pub const CLAIM_PER_BYTE: usize = 8;

/// Bincode's limit for a body of `len` bytes: the smallest power of two >= [`CLAIM_PER_BYTE`] x
/// `len`, and at least 4 KiB; `None` past what any frame may be ([`MAX_FRAME_LEN`]).
pub fn claim_limit(len: usize) -> Option<usize> {
    if len > MAX_FRAME_LEN {
        return None;
    }
    Some((len * CLAIM_PER_BYTE).next_power_of_two().max(1 << 12))
}

/// Decodes `body` with bincode's limit [`claim_limit`] of its length.
fn decode_bounded<T: serde::de::DeserializeOwned>(body: &[u8]) -> Result<(T, usize), DecodeError> {
    let Some(limit) = claim_limit(body.len()) else { return Err(DecodeError::LimitExceeded) };
    macro_rules! try_limits {
        ($($shift:literal),*) => {
            $(
                if limit == (1usize << $shift) {
                    return decode_limited::<T, { 1usize << $shift }>(body);
                }
            )*
        };
    }
    try_limits!(12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32, 33);
    Err(DecodeError::LimitExceeded)
}

/// Decodes exactly one message from `body` (a frame without its length prefix): every byte must
/// belong to the message.
pub fn decode(body: &[u8]) -> Result<Message, CodecError> {
    let (msg, used): (Message, usize) =
        decode_bounded(body).map_err(|e| CodecError::Malformed { len: body.len(), reason: e.to_string() })?;
    if used != body.len() {
        return Err(CodecError::TrailingBytes { kind: msg.kind(), extra: body.len() - used });
    }
    Ok(msg)
}

/// Object space: the bytes of one node's pixels for a peer (bincode, no length prefix: they fill
/// one QUIC stream, which the receiver reads up to the wall's message limit).
pub fn encode_pixels(p: &crate::composite::PeerPixels) -> Result<Vec<u8>, CodecError> {
    bincode::serde::encode_to_vec(p, config::standard())
        .map_err(|e| CodecError::Encode { kind: "PeerPixels", reason: e.to_string() })
}

/// Object space: decodes exactly one [`crate::composite::PeerPixels`] from a peer's stream, with
/// the same bounded limits as messages.
pub fn decode_pixels(body: &[u8]) -> Result<crate::composite::PeerPixels, CodecError> {
    let (p, used) =
        decode_bounded(body).map_err(|e| CodecError::Malformed { len: body.len(), reason: e.to_string() })?;
    if used != body.len() {
        return Err(CodecError::TrailingBytes { kind: "PeerPixels", extra: body.len() - used });
    }
    Ok(p)
}

/// The code bincode writes first for a message of this kind (its variant's index, a varint).
pub fn kind_code(msg: &Message) -> u32 {
    let bytes = encode(msg).expect("a message encodes");
    read_kind(&bytes).expect("an encoded message starts with its kind").0
}

/// The kind code at the start of `body` and its length in bytes (bincode's varint: a byte under
/// 251 is the value; 251 and 252 announce a `u16` and a `u32`); `None` until enough has arrived.
fn read_kind(body: &[u8]) -> Option<(u32, usize)> {
    match *body.first()? {
        b @ 0..=250 => Some((u32::from(b), 1)),
        251 => Some((u32::from(u16::from_le_bytes(body.get(1..3)?.try_into().ok()?)), 3)),
        252 => Some((u32::from_le_bytes(body.get(1..5)?.try_into().ok()?), 5)),
        // A kind beyond u32 is no message: decoding refuses it.
        _ => Some((u32::MAX, 1)),
    }
}

/// A limit on one kind of message, below the decoder's ([`Decoder::limit_kind`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KindLimit {
    pub code: u32,
    pub kind: &'static str,
    pub limit: usize,
    /// Why, for the error (e.g. "at most 512 rectangles").
    pub why: String,
}

impl KindLimit {
    /// A limit of `limit` bytes on the kind of `sample`.
    pub fn of(sample: &Message, limit: usize, why: impl Into<String>) -> KindLimit {
        KindLimit { code: kind_code(sample), kind: sample.kind(), limit, why: why.into() }
    }
}

/// The most bytes a [`Message::RectCosts`] of `entries` rectangles takes: its kind, frame id and
/// count (varints of at most 5, 9 and 9 bytes) and each entry's three `u32` and one `u64`
/// (5, 5, 5 and 9 bytes at most).
pub fn rect_costs_limit(entries: usize) -> usize {
    5 + 9 + 9 + entries.saturating_mul(24)
}

/// Splits a byte stream into messages. Feed it what arrives with [`Decoder::push`], then call
/// [`Decoder::next`] until it returns `Ok(None)`.
#[derive(Debug)]
pub struct Decoder {
    limit: usize,
    kinds: Vec<KindLimit>,
    buf: Vec<u8>,
    /// Bytes of `buf` before this are consumed.
    start: usize,
    broken: Option<CodecError>,
    /// Whether [`Decoder::next`] has returned `broken` itself yet (later calls wrap it in
    /// [`CodecError::Broken`]).
    reported: bool,
}

impl Decoder {
    /// A decoder that accepts frames of at most `limit` bytes (clamped to [`MAX_FRAME_LEN`]).
    pub fn new(limit: usize) -> Self {
        Decoder {
            limit: limit.min(MAX_FRAME_LEN),
            kinds: Vec::new(),
            buf: Vec::new(),
            start: 0,
            broken: None,
            reported: false,
        }
    }

    /// Frames of `k.kind` are refused over `k.limit` bytes (one limit per kind: a later one
    /// replaces it).
    pub fn limit_kind(&mut self, k: KindLimit) {
        self.kinds.retain(|o| o.code != k.code);
        self.kinds.push(k);
    }

    pub fn limit(&self) -> usize {
        self.limit
    }

    /// Bytes received and not yet decoded.
    pub fn buffered(&self) -> usize {
        self.buf.len() - self.start
    }

    /// Whether an error broke the stream (every later [`Decoder::next`] fails).
    pub fn is_broken(&self) -> bool {
        self.broken.is_some()
    }

    /// Appends received bytes. A frame header over the limit breaks the decoder at once, and its
    /// bytes are dropped rather than kept.
    pub fn push(&mut self, bytes: &[u8]) {
        if self.broken.is_some() {
            return;
        }
        if self.start > 0 && self.start == self.buf.len() {
            self.buf.clear();
            self.start = 0;
        }
        self.buf.extend_from_slice(bytes);
        if let Err(e) = self.check_header() {
            self.fail(e);
        }
    }

    /// The length of the frame at the front, if its header has arrived and is within the limit.
    fn check_header(&self) -> Result<Option<usize>, CodecError> {
        let avail = &self.buf[self.start..];
        if avail.len() < HEADER_LEN {
            return Ok(None);
        }
        let len = u32::from_le_bytes([avail[0], avail[1], avail[2], avail[3]]) as usize;
        if len > self.limit {
            return Err(CodecError::TooLong { len, limit: self.limit });
        }
        let body = &avail[HEADER_LEN..avail.len().min(HEADER_LEN + len)];
        if let Some((code, _)) = read_kind(body) {
            if let Some(k) = self.kinds.iter().find(|k| k.code == code && len > k.limit) {
                return Err(CodecError::KindTooLong {
                    kind: k.kind,
                    len,
                    limit: k.limit,
                    why: k.why.clone(),
                });
            }
        }
        Ok(Some(len))
    }

    fn fail(&mut self, e: CodecError) {
        self.broken = Some(e);
        self.buf = Vec::new();
        self.start = 0;
    }

    /// The stream ended: `Err` ([`CodecError::Truncated`]) if part of a frame is still buffered
    /// (or the error that broke the decoder earlier); `Ok` if it ended between frames.
    pub fn finish(&mut self) -> Result<(), CodecError> {
        if let Some(e) = &self.broken {
            return Err(CodecError::Broken(Box::new(e.clone())));
        }
        let have = self.buffered();
        if have == 0 {
            return Ok(());
        }
        let need = self.check_header().ok().flatten().map(|len| HEADER_LEN + len);
        let e = CodecError::Truncated { have, need };
        self.fail(e.clone());
        self.reported = true;
        Err(e)
    }

    /// The next complete message: `Ok(None)` while more bytes are needed. The first error is
    /// returned as it is (a frame header over the limit, found by [`Decoder::push`], included);
    /// every later call returns it as [`CodecError::Broken`].
    #[allow(clippy::should_implement_trait)]
    pub fn next(&mut self) -> Result<Option<Message>, CodecError> {
        if let Some(e) = &self.broken {
            if !std::mem::replace(&mut self.reported, true) {
                return Err(e.clone());
            }
            return Err(CodecError::Broken(Box::new(e.clone())));
        }
        let len = match self.check_header() {
            Ok(Some(len)) => len,
            Ok(None) => {
                self.compact();
                return Ok(None);
            }
            Err(e) => {
                self.fail(e.clone());
                self.reported = true;
                return Err(e);
            }
        };
        if self.buffered() < HEADER_LEN + len {
            self.compact();
            return Ok(None);
        }
        let body = &self.buf[self.start + HEADER_LEN..self.start + HEADER_LEN + len];
        let result = decode(body);
        self.start += HEADER_LEN + len;
        match result {
            Ok(msg) => {
                self.compact();
                Ok(Some(msg))
            }
            Err(e) => {
                self.fail(e.clone());
                self.reported = true;
                Err(e)
            }
        }
    }

    /// Drops consumed bytes; gives back the memory of a large frame once it is decoded.
    fn compact(&mut self) {
        if self.start == self.buf.len() {
            self.buf.clear();
            self.start = 0;
            if self.buf.capacity() > 1 << 20 {
                self.buf = Vec::new();
            }
        } else if self.start > 0 && self.start >= self.buf.len() / 2 {
            self.buf.drain(..self.start);
            self.start = 0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kind_over_its_own_limit_is_refused_before_its_body_is_buffered() {
        use crate::wire::WireRectCost;
        let costs = |n: usize| Message::RectCosts {
            frame_id: 7,
            costs: vec![
                WireRectCost { tile: u32::MAX, first_row: u32::MAX, rows: u32::MAX, cost: u64::MAX };
                n
            ],
        };
        let mut d = Decoder::new(CONTROLLER_LIMIT);
        d.limit_kind(KindLimit::of(&costs(0), rect_costs_limit(4), "at most 4 rectangles"));
        // Four fit, and other kinds are untouched by the limit.
        d.push(&frame(&costs(4)).unwrap());
        assert_eq!(d.next().unwrap(), Some(costs(4)));
        let ping = Message::Ping { id: 1, t0_us: 2 };
        d.push(&frame(&ping).unwrap());
        assert_eq!(d.next().unwrap(), Some(ping));
        // Five: refused from the header and the kind's first byte, the rest never buffered.
        let big = frame(&costs(5)).unwrap();
        d.push(&big[..HEADER_LEN + 1]);
        assert!(d.is_broken() && d.buffered() == 0);
        let e = d.next().unwrap_err().to_string();
        assert!(e.contains("a RectCosts of") && e.contains("at most 4 rectangles"), "{e}");
        // The kind code is the variant's, whatever the fields.
        assert_eq!(kind_code(&costs(0)), kind_code(&costs(9)));
        assert_ne!(kind_code(&costs(0)), kind_code(&Message::Ping { id: 1, t0_us: 2 }));
    }
    use crate::camera::Camera;
    use crate::messages::TileImage;
    use crate::render_state::RenderSettings;
    use crate::wire::FrameState;
    use glam::DVec3;

    fn all_messages() -> Vec<Message> {
        let cam =
            Camera { eye: DVec3::new(0.0, -5.0, 1.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 30.0 };
        vec![
            hello("node-a", Role::Daemon),
            hello("controller", Role::Controller),
            Message::FrameState(FrameState::new(u64::MAX - 1, &cam, &RenderSettings::new(300.0), 4)),
            Message::Ready { frame_id: 12, render_us: 16_667 },
            Message::Swap { frame_id: 12, present_at_us: None },
            Message::Presented { frame_id: 12, node_time_us: -42, waiting_from_us: -42 },
            Message::Ping { id: 7, t0_us: i64::MIN },
            Message::Pong { id: 7, t0_us: 1, t1_us: i64::MAX, sent_us: i64::MAX, resident_bytes: u64::MAX },
            Message::SnapshotRequest,
            Message::ThumbnailRequest { divisor: 8 },
            Message::Snapshot {
                tiles: vec![
                    TileImage {
                        name: "left".into(),
                        width: 4,
                        height: 2,
                        frame_id: 12,
                        rgb8: (0..24).collect(),
                    },
                    TileImage { name: "right".into(), width: 0, height: 0, frame_id: 12, rgb8: vec![] },
                ],
            },
            Message::Bye { reason: "shutting down: état normal".into() },
        ]
    }

    #[test]
    fn every_message_round_trips_alone_and_in_a_stream() {
        let msgs = all_messages();
        let mut stream = Vec::new();
        for m in &msgs {
            assert_eq!(&decode(&encode(m).unwrap()).unwrap(), m);
            stream.extend(frame(m).unwrap());
        }
        // Fed one byte at a time, then all at once.
        let mut d = Decoder::new(DAEMON_LIMIT);
        let mut got = Vec::new();
        for b in &stream {
            d.push(std::slice::from_ref(b));
            while let Some(m) = d.next().unwrap() {
                got.push(m);
            }
        }
        assert_eq!(got, msgs);
        assert_eq!(d.buffered(), 0);
        let mut d = Decoder::new(DAEMON_LIMIT);
        d.push(&stream);
        let mut got = Vec::new();
        while let Some(m) = d.next().unwrap() {
            got.push(m);
        }
        assert_eq!(got, msgs);
    }

    /// Bodies of exactly `len` bytes: `dense` items that claim the most per byte, then a byte
    /// string sized to fill the rest (`None` where a varint length's width skips `len`).
    fn message_of_len(len: usize, shape: usize) -> Option<Message> {
        let empty_tile = || TileImage { name: String::new(), width: 0, height: 0, frame_id: 0, rgb8: vec![] };
        let filled = |dense: usize, pad: usize| match shape {
            // Empty tiles: 5 bytes each, claiming 32 (lengths and u64s count 8, u32s 4).
            0 => {
                let mut tiles = vec![empty_tile(); dense];
                tiles.push(TileImage { rgb8: vec![7; pad], ..empty_tile() });
                Message::Snapshot { tiles }
            }
            // One tile's pixels: about one claimed byte per byte.
            1 => Message::Snapshot { tiles: vec![TileImage { rgb8: vec![7; pad + dense], ..empty_tile() }] },
            // A brick map of empty names (2 bytes claiming 9) and a long reason-like name.
            _ => {
                let mut holders = vec![Some(String::new()); dense];
                holders.push(Some("n".repeat(pad)));
                Message::Bricks { from_frame: u64::MAX, holders }
            }
        };
        for dense in [len / 8, len / 8 + 1, len / 8 + 2] {
            let base = encode(&filled(dense, 0)).ok()?.len();
            if base > len {
                continue;
            }
            // A byte string of `pad` bytes adds `pad` and widens its varint length past 250.
            for widen in [0usize, 2, 4, 8] {
                let Some(pad) = (len - base).checked_sub(widen) else { continue };
                let m = filled(dense, pad);
                if encode(&m).ok()?.len() == len {
                    return Some(m);
                }
            }
        }
        None
    }

    #[test]
    fn valid_messages_of_every_size_around_the_limits_round_trip() {
        // Around every power of two from 512 B to 4 MiB: the old limits (powers of 4 >= the
        // body), and where the claim of a dense body (up to 8 x its length) crosses the new ones.
        let mut tried = 0;
        for shift in 9..=22 {
            let edge = 1usize << shift;
            for len in edge - 3..=edge + 3 {
                for shape in 0..3 {
                    let Some(m) = message_of_len(len, shape) else { continue };
                    let body = encode(&m).unwrap();
                    assert_eq!(body.len(), len);
                    let got = decode(&body).unwrap_or_else(|e| panic!("shape {shape}, {len} bytes: {e}"));
                    assert!(got == m, "shape {shape}, {len} bytes: decoded differently");
                    let mut d = Decoder::new(MAX_FRAME_LEN);
                    d.push(&frame(&m).unwrap());
                    assert!(d.next().unwrap().is_some_and(|g| g == m), "shape {shape}, {len} bytes, framed");
                    tried += 1;
                }
            }
        }
        assert!(tried >= 14 * 7 * 2, "only {tried} messages could be built at the sizes wanted");
        // The limit is a power of two and covers 8 claimed bytes per body byte.
        for len in [0, 1, 511, 512, 513, 16_384, 16_385, MAX_FRAME_LEN] {
            let limit = claim_limit(len).unwrap();
            assert!(limit.is_power_of_two() && limit >= CLAIM_PER_BYTE * len && limit >= 4096, "{len}");
            assert!(limit < 2 * CLAIM_PER_BYTE * len.max(512), "{len}: {limit}");
        }
        assert_eq!(claim_limit(MAX_FRAME_LEN + 1), None);
    }

    #[test]
    fn tile_bytes_are_one_byte_string() {
        let t =
            TileImage { name: String::new(), width: 100, height: 100, frame_id: 0, rgb8: vec![200; 30_000] };
        let n = encode(&Message::Snapshot { tiles: vec![t] }).unwrap().len();
        // 30000 bytes + a few of lengths and numbers: no per-byte overhead.
        assert!(n < 30_020, "{n}");
    }

    #[test]
    fn an_oversized_length_is_rejected_before_its_body_is_buffered() {
        let mut d = Decoder::new(1000);
        d.push(&1001u32.to_le_bytes());
        assert!(d.is_broken(), "the header alone breaks the decoder");
        assert_eq!(d.buffered(), 0);
        // Reported as it is once, then as what broke the stream.
        assert_eq!(d.next(), Err(CodecError::TooLong { len: 1001, limit: 1000 }));
        assert_eq!(
            d.next(),
            Err(CodecError::Broken(Box::new(CodecError::TooLong { len: 1001, limit: 1000 })))
        );
        d.push(&[0u8; 4096]);
        assert_eq!(d.buffered(), 0, "a broken decoder keeps nothing");

        let mut d = Decoder::new(usize::MAX);
        assert_eq!(d.limit(), MAX_FRAME_LEN);
        d.push(&u32::MAX.to_le_bytes());
        assert!(matches!(d.next(), Err(CodecError::TooLong { .. })));
        assert!(matches!(d.next(), Err(CodecError::Broken(e)) if matches!(*e, CodecError::TooLong { .. })));
    }

    #[test]
    fn a_length_inside_a_frame_cannot_make_bincode_allocate() {
        // A Bye whose reason claims 2^40 bytes, inside a 12-byte frame: bincode's limit stops it
        // before it allocates (were it to try, the test would abort).
        let mut body = encode(&Message::Bye { reason: String::new() }).unwrap();
        assert_eq!(body.pop(), Some(0)); // the empty string's length
        body.push(253); // varint: u64 follows
        body.extend((1u64 << 40).to_le_bytes());
        let e = decode(&body).unwrap_err();
        assert!(
            matches!(&e, CodecError::Malformed { reason, .. } if reason.to_lowercase().contains("limit")),
            "{e}"
        );
        // The same for a tile's pixels, through the decoder.
        let mut body = encode(&Message::Snapshot {
            tiles: vec![TileImage { name: "t".into(), width: 1, height: 1, frame_id: 1, rgb8: vec![] }],
        })
        .unwrap();
        body.pop();
        body.push(253);
        body.extend((1u64 << 33).to_le_bytes());
        let mut d = Decoder::new(DAEMON_LIMIT);
        d.push(&(body.len() as u32).to_le_bytes());
        d.push(&body);
        assert!(matches!(d.next(), Err(CodecError::Malformed { .. })));
    }

    #[test]
    fn a_truncated_frame_waits_for_the_rest() {
        let f = frame(&Message::Ready { frame_id: 99, render_us: 1234 }).unwrap();
        let mut d = Decoder::new(DAEMON_LIMIT);
        d.push(&f[..2]);
        assert_eq!(d.next(), Ok(None));
        d.push(&f[2..f.len() - 1]);
        assert_eq!(d.next(), Ok(None));
        assert_eq!(d.next(), Ok(None));
        d.push(&f[f.len() - 1..]);
        assert_eq!(d.next(), Ok(Some(Message::Ready { frame_id: 99, render_us: 1234 })));
        assert_eq!(d.next(), Ok(None));
        assert_eq!(d.finish(), Ok(()), "the stream may end between frames");
    }

    #[test]
    fn a_stream_that_ends_inside_a_frame_is_truncated() {
        let f = frame(&Message::Swap { frame_id: 7, present_at_us: None }).unwrap();
        let mut d = Decoder::new(DAEMON_LIMIT);
        d.push(&f[..f.len() - 1]);
        assert_eq!(d.next(), Ok(None));
        let e = d.finish().unwrap_err();
        assert_eq!(e, CodecError::Truncated { have: f.len() - 1, need: Some(f.len()) });
        assert_eq!(
            e.to_string(),
            format!("the stream ended inside a frame: {} of {} bytes", f.len() - 1, f.len())
        );
        assert!(d.is_broken());
        assert!(matches!(d.next(), Err(CodecError::Broken(_))));
        // Inside the length itself.
        let mut d = Decoder::new(DAEMON_LIMIT);
        d.push(&f[..2]);
        assert_eq!(d.finish(), Err(CodecError::Truncated { have: 2, need: None }));
        assert!(matches!(d.finish(), Err(CodecError::Broken(_))));
        let e = CodecError::Truncated { have: 2, need: None };
        assert_eq!(e.to_string(), "the stream ended inside a frame: 2 of at least 4 bytes");
    }

    #[test]
    fn trailing_garbage_inside_a_frame_is_an_error() {
        let mut body = encode(&Message::Swap { frame_id: 5, present_at_us: None }).unwrap();
        body.extend([1, 2, 3]);
        assert_eq!(decode(&body), Err(CodecError::TrailingBytes { kind: "Swap", extra: 3 }));
        let mut d = Decoder::new(DAEMON_LIMIT);
        d.push(&(body.len() as u32).to_le_bytes());
        d.push(&body);
        assert!(matches!(d.next(), Err(CodecError::TrailingBytes { .. })));
        assert!(d.is_broken());
    }

    #[test]
    fn garbage_errors_and_never_panics() {
        // An unknown variant, an empty frame, a bad UTF-8 name.
        assert!(matches!(decode(&[200]), Err(CodecError::Malformed { .. })));
        assert!(matches!(decode(&[]), Err(CodecError::Malformed { .. })));
        let mut body = encode(&hello("ab", Role::Daemon)).unwrap();
        let n = body.len();
        body[n - 3] = 0xff; // inside the name
        assert!(decode(&body).is_err());
        // Random frames: errors or messages, no panic. (xorshift, seeded)
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        let mut ok = 0;
        for _ in 0..20_000 {
            let len = (rnd() % 40) as usize;
            let body: Vec<u8> = (0..len).map(|_| rnd() as u8 % 16).collect();
            ok += decode(&body).is_ok() as u32;
            let mut d = Decoder::new(64);
            let stream: Vec<u8> = (0..len).map(|_| rnd() as u8).collect();
            d.push(&stream);
            while let Ok(Some(_)) = d.next() {}
        }
        assert!(ok > 0, "some random bodies are valid small messages");
    }

    #[test]
    fn hello_checks_version_role_and_name() {
        assert_eq!(check_hello(&hello("n1", Role::Daemon), Role::Daemon), Ok("n1".into()));
        let old = Message::Hello { version: PROTOCOL_VERSION + 1, name: "n1".into(), role: Role::Daemon };
        let e = check_hello(&old, Role::Daemon).unwrap_err();
        assert_eq!(
            e,
            HandshakeError::Version {
                name: "n1".into(),
                ours: PROTOCOL_VERSION,
                theirs: PROTOCOL_VERSION + 1
            }
        );
        assert!(e.to_string().contains(&format!("version {}", PROTOCOL_VERSION + 1)));
        // Through the codec, as a peer would send it.
        let mut d = Decoder::new(DAEMON_LIMIT);
        d.push(&frame(&old).unwrap());
        assert!(matches!(
            check_hello(&d.next().unwrap().unwrap(), Role::Daemon),
            Err(HandshakeError::Version { .. })
        ));
        assert!(matches!(
            check_hello(&hello("n1", Role::Controller), Role::Daemon),
            Err(HandshakeError::Role { .. })
        ));
        assert_eq!(
            check_hello(&Message::SnapshotRequest, Role::Daemon),
            Err(HandshakeError::NotHello("SnapshotRequest"))
        );
        assert!(matches!(
            check_hello(&hello("", Role::Daemon), Role::Daemon),
            Err(HandshakeError::BadName(_))
        ));
        assert!(matches!(
            check_hello(&hello("a\nb", Role::Daemon), Role::Daemon),
            Err(HandshakeError::BadName(_))
        ));
    }
}
