//! The frame protocol's messages (DESIGN.md "Distribution"): what a controller and its daemons say
//! to each other over one connection, and [`ProtocolError`], the reason a peer's connection is
//! closed when it breaks the protocol.
//!
//! One frame, as the controller sees it:
//!
//! ```text
//! controller                                   daemon
//!     Hello ------------------------------------> (both ways, first on a connection)
//!     FrameState(n) ----------------------------> renders its tiles
//!     <---------------------------------------- StepLate { n, .. } (only when its time step
//!                                                  was not loaded when the frame came)
//!     <---------------------------------------- Ready { n, render_us }
//!     (all up nodes ready, or the deadline)
//!     Swap { n, present_at } -------------------> presents at that time of its clock
//!     <---------------------------------------- Presented { n, node_time_us, waiting_from_us }
//!     Ping { id, t0 } --------------------------> (now and then: clock offsets)
//!     <---------------------------------------- Pong { id, t0, t1, sent, resident_bytes }
//!     SnapshotRequest / ThumbnailRequest { divisor } ---> (whenever asked)
//!     <---------------------------------------- Snapshot { tiles } (each 1/divisor the size)
//!     <---------------------------------------- NodeInfo (once, after its Hello: version, GPU)
//!     Identify { on } --------------------------> (the operator's: tiles show their names)
//!     Restart { reason } -----------------------> (the operator's: the daemon exits with
//!                                                  [`RESTART_EXIT_CODE`], its supervisor restarts it)
//! ```
//!
//! In object space a daemon also sends Composited before Ready, and when a node dies the
//! controller sends Bricks (the brick map from a frame on) to every node and LoadBrick to the
//! survivor that adopts its brick, which answers BrickLoaded or BrickFailed ([`crate::adoption`]).
//!
//! A load-balanced screen-space wall (`[wall] balance = true`, [`crate::balance`]) has the
//! controller send Split (the wall's work rectangles from a frame on) before the frame it starts
//! with; each daemon sends RectCosts (what each rectangle it rendered cost) and Composited (the
//! bytes it sent its peers, the peers it went without) before Ready.
//!
//! A daemon that reads its volume through a brick cache sends Surface (its surface pixels and
//! how many of them level 0 drew) before Ready.
//!
//! The bytes of these messages are [`crate::codec`]'s business; this module knows no encoding.

use serde::{Deserialize, Serialize};

use crate::wire::{FrameState, WireRectCost, WireSplit};

/// The protocol version of this build; a peer's [`Message::Hello`] must carry the same.
pub const PROTOCOL_VERSION: u16 = 12;

/// The furthest ahead a Swap's present time may be: a node never waits longer for one.
pub const MAX_SWAP_WAIT: std::time::Duration = std::time::Duration::from_secs(1);

/// The exit status of a daemon told to [`Message::Restart`]: not 0, so a supervisor that restarts
/// a failed service (systemd's `Restart=on-failure`) brings it back; 75 is `EX_TEMPFAIL`.
pub const RESTART_EXIT_CODE: i32 = 75;

/// The most characters of each of a [`NodeInfo`]'s texts; a longer one is refused on receipt.
pub const MAX_NODE_INFO_CHARS: usize = 256;

/// The most characters of a [`Message::Restart`]'s reason.
pub const MAX_RESTART_REASON_CHARS: usize = 256;

/// What a daemon says about itself once after its Hello: its build and its GPU (wgpu's
/// `AdapterInfo`, converted to text by the daemon). Each text is at most [`MAX_NODE_INFO_CHARS`].
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq, Default)]
pub struct NodeInfo {
    /// The isowalld version (the crate's, and `git describe` where the build had one).
    pub version: String,
    /// The GPU adapter's name.
    pub adapter: String,
    /// Its backend (`Vulkan`, `Metal`, ...).
    pub backend: String,
    /// The driver's name and its own description of itself (`driver_info`).
    pub driver: String,
    pub driver_info: String,
    /// What its presenting thread runs as (`SCHED_FIFO 10`, `normal (...)`): the reports show it
    /// beside the wake-up lateness.
    pub present: String,
}

impl NodeInfo {
    /// Checks every text's length (in characters) against [`MAX_NODE_INFO_CHARS`].
    pub fn validate(&self) -> Result<(), String> {
        for (field, text) in [
            ("version", &self.version),
            ("adapter", &self.adapter),
            ("backend", &self.backend),
            ("driver", &self.driver),
            ("driver_info", &self.driver_info),
            ("present", &self.present),
        ] {
            let n = text.chars().count();
            if n > MAX_NODE_INFO_CHARS {
                return Err(format!(
                    "NodeInfo `{field}` has {n} characters, more than {MAX_NODE_INFO_CHARS}"
                ));
            }
        }
        Ok(())
    }

    /// The same with every text made [`printable`] (control characters escaped).
    pub fn printable(&self) -> NodeInfo {
        NodeInfo {
            version: printable(&self.version),
            adapter: printable(&self.adapter),
            backend: printable(&self.backend),
            driver: printable(&self.driver),
            driver_info: printable(&self.driver_info),
            present: printable(&self.present),
        }
    }
}

/// Which side of a connection a peer is.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    Controller,
    Daemon,
}

impl Role {
    pub fn name(self) -> &'static str {
        match self {
            Role::Controller => "controller",
            Role::Daemon => "daemon",
        }
    }
}

/// One tile's last presented frame: 8-bit sRGB, rows top to bottom, `width * height * 3` bytes.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq)]
pub struct TileImage {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub frame_id: u64,
    /// Encoded as one byte string (not a sequence of numbers), so decoding it is a copy.
    #[serde(with = "byte_buf")]
    pub rgb8: Vec<u8>,
}

impl TileImage {
    /// The image `divisor` times smaller along each axis (`ceil(width / divisor)` x
    /// `ceil(height / divisor)`): each pixel the mean of the block of pixels it covers (blocks on
    /// the right and bottom edges may be partial). A divisor of 0 or 1 is a copy.
    pub fn downscaled(&self, divisor: u32) -> TileImage {
        TileImage::downscale(&self.name, self.width, self.height, self.frame_id, &self.rgb8, divisor)
    }

    /// [`TileImage::downscaled`] of the `width` x `height` image `rgb8` (borrowed: a daemon
    /// downscales the tile it shows without copying it first). Missing bytes count as black.
    pub fn downscale(
        name: &str,
        width: u32,
        height: u32,
        frame_id: u64,
        rgb8: &[u8],
        divisor: u32,
    ) -> TileImage {
        let d = divisor.max(1);
        let (w, h) = (width.div_ceil(d), height.div_ceil(d));
        let mut out = Vec::with_capacity(w as usize * h as usize * 3);
        for by in 0..h {
            let rows = by * d..((by + 1) * d).min(height);
            for bx in 0..w {
                let cols = bx * d..((bx + 1) * d).min(width);
                let mut sum = [0u64; 3];
                for y in rows.clone() {
                    for x in cols.clone() {
                        let i = (y as usize * width as usize + x as usize) * 3;
                        for (c, s) in sum.iter_mut().enumerate() {
                            *s += u64::from(rgb8.get(i + c).copied().unwrap_or(0));
                        }
                    }
                }
                let n = (rows.len() * cols.len()).max(1) as u64;
                out.extend(sum.map(|s| ((s + n / 2) / n) as u8));
            }
        }
        TileImage { name: name.to_string(), width: w, height: h, frame_id, rgb8: out }
    }

    /// Checks that `rgb8` holds exactly `width * height * 3` bytes.
    pub fn validate(&self) -> Result<(), String> {
        let want = self.width as u64 * self.height as u64 * 3;
        if self.rgb8.len() as u64 != want {
            return Err(format!(
                "tile `{}` is {}x{} but carries {} bytes instead of {want}",
                self.name,
                self.width,
                self.height,
                self.rgb8.len()
            ));
        }
        Ok(())
    }

    /// The most bytes a [`Message::Snapshot`] of tiles with these names and sizes can take once
    /// encoded ([`crate::codec`]: bincode's variable-length integers at their longest), for
    /// checking that a wall's message limit lets a node send its snapshot.
    pub fn snapshot_len_bound<'a>(tiles: impl IntoIterator<Item = (&'a str, u32, u32)>) -> u64 {
        // Variant index (a u32) and tile count (a u64).
        let mut bytes = 5 + 9;
        for (name, width, height) in tiles {
            // Name (length + bytes), width, height, frame id, pixels (length + bytes).
            bytes += 9 + name.len() as u64 + 5 + 5 + 9 + 9 + u64::from(width) * u64::from(height) * 3;
        }
        bytes
    }
}

/// Everything said on a wall connection.
// FrameState is the large variant (about 300 bytes) and the most frequent one: boxing it would
// only add an allocation per frame.
#[allow(clippy::large_enum_variant)]
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq)]
pub enum Message {
    /// The first message on a connection, both ways.
    Hello { version: u16, name: String, role: Role },
    /// Controller -> daemon: render this frame.
    FrameState(FrameState),
    /// Daemon -> controller: rendered, waiting for the swap.
    Ready { frame_id: u64, render_us: u64 },
    /// Controller -> daemon: present the rendered frame at `present_at_us` of the daemon's own
    /// clock (the timed swap, [`crate::swap_timing`]); at once when `None`, or when that time
    /// has passed (a late swap). A time more than [`MAX_SWAP_WAIT`] ahead is a protocol error.
    Swap { frame_id: u64, present_at_us: Option<i64> },
    /// Daemon -> controller: presented at `node_time_us` of the daemon's own clock; its
    /// presenting thread was ready to wait for the present time at `waiting_from_us` (after the
    /// present time: the swap was late).
    Presented { frame_id: u64, node_time_us: i64, waiting_from_us: i64 },
    /// Controller -> daemon: clock sync; `t0_us` is the controller's clock at sending.
    Ping { id: u64, t0_us: i64 },
    /// Daemon -> controller: `t1_us` is the daemon's clock when the Ping arrived, `sent_us` when
    /// the Pong left (the hold between is on neither wire: [`crate::clock`]);
    /// `resident_bytes` the daemon process's resident memory then (0 where its OS does not say).
    Pong { id: u64, t0_us: i64, t1_us: i64, sent_us: i64, resident_bytes: u64 },
    /// Controller -> daemon: send me your tiles' last presented frames.
    SnapshotRequest,
    /// Daemon -> controller: its tiles' last presented frames.
    Snapshot { tiles: Vec<TileImage> },
    /// Either way, then close.
    Bye { reason: String },
    // object space
    /// Daemon -> controller, before Ready in object space: the bytes it sent its peers for the
    /// frame and its compositing time (its render done to its tiles composited: waiting for the
    /// peers' pixels and merging them), the part of it spent working (encoding its pixels for the
    /// peers, decoding theirs, merging), the volume bytes it holds (its brick and halo), and the
    /// peers whose pixels the frame went without (not in by its compositing deadline).
    Composited {
        frame_id: u64,
        bytes_sent: u64,
        composite_us: u64,
        merge_us: u64,
        resident_bytes: u64,
        missing: Vec<String>,
    },
    /// Controller -> daemon (object space): from frame `from_frame` on, brick i is rendered by
    /// node `holders[i]` (nobody where `None`); see `crate::adoption`.
    Bricks { from_frame: u64, holders: Vec<Option<String>> },
    /// Controller -> daemon (object space): load brick `brick` (with its halo) beside your own,
    /// and say when it is loaded; it becomes yours by a later `Bricks`.
    LoadBrick { brick: u64 },
    /// Daemon -> controller (object space): `brick` is loaded (`load_us` to read and upload it);
    /// `resident_bytes` is all the volume bytes the node holds now.
    BrickLoaded { brick: u64, load_us: u64, resident_bytes: u64 },
    /// Daemon -> controller (object space): `brick` could not be loaded, and why.
    BrickFailed { brick: u64, reason: String },
    /// Controller -> daemon: send me your tiles' last presented frames downscaled by `divisor`
    /// (1..=[`MAX_THUMBNAIL_DIVISOR`], [`TileImage::downscaled`]), answered with a Snapshot: a
    /// live thumbnail of the wall costs the nodes' links 1/divisor^2 of full tiles.
    ThumbnailRequest { divisor: u32 },
    /// Daemon -> controller, before Ready: the frame's time step was not loaded when the frame
    /// came; the node waited `waited_us` for it (a bounded wait) and rendered `shown_step`
    /// (the frame's own step once loaded in time, else the last one it had).
    StepLate { frame_id: u64, shown_step: u32, waited_us: u64 },
    /// Daemon -> controller, once after its Hello: its version and GPU ([`NodeInfo`]).
    NodeInfo(NodeInfo),
    /// Controller -> daemon: exit with [`RESTART_EXIT_CODE`] so the node's supervisor starts it
    /// again (the operator's restart); `reason` (at most [`MAX_RESTART_REASON_CHARS`]) is logged.
    /// Only the controller holding the node's seat can send it: every other one is refused
    /// before its first message (`crate::seat`).
    Restart { reason: String },
    /// Controller -> daemon: from the next frame on, each of its tiles shows (`on`) or stops
    /// showing its node's and its own name in its top-left corner (the operator's identify).
    Identify { on: bool },
    // load-balanced screen space
    /// Controller -> daemon (`[wall] balance = true`): from frame `from_frame` on, the wall's
    /// work rectangles are `split` (checked whole by `crate::balance::share::split_from_wire`).
    Split { from_frame: u64, split: WireSplit },
    /// Daemon -> controller, before Ready (`[wall] balance = true`): what each rectangle it
    /// rendered of the frame cost (`crate::balance::node::rect_cost`).
    RectCosts { frame_id: u64, costs: Vec<WireRectCost> },
    // the brick cache
    /// Daemon -> controller, before Ready, where the node reads its volume through a brick
    /// cache (`[volume] gpu_budget_mb`): of the frame's surface pixels on its tiles (`hits`), how
    /// many were drawn with level 0 where they lie (`level0`; the rest from a coarser level).
    /// Protocol 12.
    Surface { frame_id: u64, hits: u64, level0: u64 },
}

/// The largest downscale a [`Message::ThumbnailRequest`] may ask for.
pub const MAX_THUMBNAIL_DIVISOR: u32 = 64;

impl Message {
    /// The message's name, for errors and logs.
    pub fn kind(&self) -> &'static str {
        match self {
            Message::Hello { .. } => "Hello",
            Message::FrameState(_) => "FrameState",
            Message::Ready { .. } => "Ready",
            Message::Swap { .. } => "Swap",
            Message::Presented { .. } => "Presented",
            Message::Ping { .. } => "Ping",
            Message::Pong { .. } => "Pong",
            Message::SnapshotRequest => "SnapshotRequest",
            Message::Snapshot { .. } => "Snapshot",
            Message::Bye { .. } => "Bye",
            Message::Composited { .. } => "Composited",
            Message::Bricks { .. } => "Bricks",
            Message::LoadBrick { .. } => "LoadBrick",
            Message::BrickLoaded { .. } => "BrickLoaded",
            Message::BrickFailed { .. } => "BrickFailed",
            Message::ThumbnailRequest { .. } => "ThumbnailRequest",
            Message::StepLate { .. } => "StepLate",
            Message::NodeInfo(_) => "NodeInfo",
            Message::Restart { .. } => "Restart",
            Message::Identify { .. } => "Identify",
            Message::Split { .. } => "Split",
            Message::RectCosts { .. } => "RectCosts",
            Message::Surface { .. } => "Surface",
        }
    }

    /// Who may send it: `None` for messages both sides send (Hello, Bye).
    pub fn sender(&self) -> Option<Role> {
        match self {
            Message::Hello { .. } | Message::Bye { .. } => None,
            Message::FrameState(_)
            | Message::Swap { .. }
            | Message::Ping { .. }
            | Message::SnapshotRequest
            | Message::ThumbnailRequest { .. }
            | Message::Bricks { .. }
            | Message::LoadBrick { .. }
            | Message::Restart { .. }
            | Message::Identify { .. }
            | Message::Split { .. } => Some(Role::Controller),
            Message::Ready { .. }
            | Message::Presented { .. }
            | Message::Pong { .. }
            | Message::Snapshot { .. }
            | Message::Composited { .. }
            | Message::BrickLoaded { .. }
            | Message::BrickFailed { .. }
            | Message::StepLate { .. }
            | Message::NodeInfo(_)
            | Message::RectCosts { .. }
            | Message::Surface { .. } => Some(Role::Daemon),
        }
    }
}

/// A peer broke the protocol: the caller closes that peer's connection (with this as the reason)
/// and nothing else stops.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("protocol violation by `{peer}` ({message}): {problem}")]
pub struct ProtocolError {
    /// The peer: a node's name on the controller, `controller` on a daemon.
    pub peer: String,
    /// The offending message's kind ([`Message::kind`]).
    pub message: &'static str,
    pub problem: String,
}

/// Most characters of a peer's text shown: a reason is a line, not a document.
pub const PRINTABLE_CHARS: usize = 300;

/// Whether `c` reorders the text around it (Unicode's bidirectional formatting characters: the
/// embeddings, overrides and isolates, and the direction marks), which would make a peer's text
/// read as something else on a terminal or a page.
pub fn is_bidi_control(c: char) -> bool {
    matches!(c, '\u{200E}' | '\u{200F}' | '\u{061C}' | '\u{202A}'..='\u{202E}' | '\u{2066}'..='\u{2069}')
}

/// A peer's text (a reason, a name) made safe to print on a terminal, in a log line or on the
/// console's page: control characters (escape sequences, newlines, carriage returns) and
/// bidirectional formatting characters ([`is_bidi_control`]) written as escapes, at most
/// [`PRINTABLE_CHARS`] characters kept.
pub fn printable(text: &str) -> String {
    let mut out = String::new();
    for (i, c) in text.chars().enumerate() {
        if i == PRINTABLE_CHARS {
            out.push_str("...");
            break;
        }
        if c.is_control() || is_bidi_control(c) {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    out
}

impl ProtocolError {
    pub fn new(peer: &str, message: &'static str, problem: impl Into<String>) -> Self {
        ProtocolError { peer: peer.to_string(), message, problem: problem.into() }
    }
}

/// Serde glue for a `Vec<u8>` as one byte string (what `serde_bytes` does, without the crate).
pub(crate) mod byte_buf {
    use serde::de::{Deserializer, SeqAccess, Visitor};
    use serde::Serializer;
    use std::fmt;

    pub fn serialize<S: Serializer>(v: &[u8], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(v)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
        d.deserialize_byte_buf(BytesVisitor)
    }

    struct BytesVisitor;

    impl<'de> Visitor<'de> for BytesVisitor {
        type Value = Vec<u8>;

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("a byte string")
        }

        fn visit_bytes<E>(self, v: &[u8]) -> Result<Vec<u8>, E> {
            Ok(v.to_vec())
        }

        fn visit_byte_buf<E>(self, v: Vec<u8>) -> Result<Vec<u8>, E> {
            Ok(v)
        }

        // Self-describing formats (JSON) write bytes as a sequence of numbers.
        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<u8>, A::Error> {
            let mut v = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 16));
            while let Some(b) = seq.next_element()? {
                v.push(b);
            }
            Ok(v)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_message_has_a_kind_and_a_sender() {
        let m = Message::Ready { frame_id: 3, render_us: 10 };
        assert_eq!(m.kind(), "Ready");
        assert_eq!(m.sender(), Some(Role::Daemon));
        assert_eq!(Message::Swap { frame_id: 1, present_at_us: None }.sender(), Some(Role::Controller));
        assert_eq!(Message::Bye { reason: String::new() }.sender(), None);
    }

    #[test]
    fn node_info_texts_are_bounded_and_made_printable() {
        let mut i = NodeInfo {
            version: "0.1.0".into(),
            adapter: "llvmpipe".into(),
            backend: "Vulkan".into(),
            driver: "llvmpipe".into(),
            driver_info: "Mesa 24".into(),
            present: "SCHED_FIFO 10".into(),
        };
        assert_eq!(i.validate(), Ok(()));
        i.driver_info = "\u{1b}[31mred\n".into();
        assert_eq!(i.printable().driver_info, "\\u{1b}[31mred\\n");
        // A right-to-left override would make the text read as something else.
        i.driver_info = "Mesa \u{202E}42\u{2066}x\u{200F}".into();
        assert_eq!(i.printable().driver_info, "Mesa \\u{202e}42\\u{2066}x\\u{200f}");
        i.adapter = "é".repeat(MAX_NODE_INFO_CHARS);
        assert_eq!(i.validate(), Ok(()), "characters, not bytes");
        i.adapter.push('x');
        let e = i.validate().unwrap_err();
        assert!(e.contains("`adapter` has 257 characters, more than 256"), "{e}");
        assert_eq!(Message::NodeInfo(i).sender(), Some(Role::Daemon));
        assert_eq!(Message::Restart { reason: String::new() }.sender(), Some(Role::Controller));
    }

    #[test]
    fn tile_images_check_their_size() {
        let mut t = TileImage { name: "a".into(), width: 2, height: 3, frame_id: 0, rgb8: vec![0; 18] };
        assert!(t.validate().is_ok());
        t.rgb8.pop();
        assert!(t.validate().unwrap_err().contains("17 bytes instead of 18"));
    }

    #[test]
    fn a_snapshot_never_encodes_longer_than_its_bound() {
        // Sizes and frame ids at varint boundaries, where each integer takes its most bytes.
        for (w, h, id, name) in
            [(1, 1, 0, "a"), (251, 3, 250, "t00"), (300, 200, u64::MAX, "x"), (16, 12, 1 << 40, "t")]
        {
            let tiles: Vec<TileImage> = (0..3)
                .map(|i| TileImage {
                    name: format!("{name}{i}"),
                    width: w,
                    height: h,
                    frame_id: id,
                    rgb8: vec![7; (w * h * 3) as usize],
                })
                .collect();
            let bound =
                TileImage::snapshot_len_bound(tiles.iter().map(|t| (t.name.as_str(), t.width, t.height)));
            let len = crate::codec::encode(&Message::Snapshot { tiles }).unwrap().len() as u64;
            assert!(len <= bound, "{w}x{h}: {len} > {bound}");
            assert!(bound - len <= 3 * 46 + 14, "{w}x{h}: the bound {bound} is loose against {len}");
        }
    }

    #[test]
    fn thumbnails_average_blocks_and_keep_partial_edges() {
        // 5x3, red = x * 10, green = y * 10, blue = 7.
        let rgb8 = (0..3u8).flat_map(|y| (0..5u8).flat_map(move |x| [x * 10, y * 10, 7])).collect();
        let t = TileImage { name: "a".into(), width: 5, height: 3, frame_id: 4, rgb8 };
        let s = t.downscaled(2);
        assert_eq!((s.width, s.height, s.frame_id, s.name.as_str()), (3, 2, 4, "a"));
        assert!(s.validate().is_ok());
        // Block (0,0): x 0..2, y 0..2 -> red 5, green 5; block (2,1): x 4, y 2 -> red 40, green 20.
        assert_eq!(&s.rgb8[0..3], &[5, 5, 7]);
        assert_eq!(&s.rgb8[15..18], &[40, 20, 7]);
        assert_eq!(t.downscaled(1), t);
        assert_eq!(t.downscaled(0), t);
        let one = t.downscaled(64);
        assert_eq!((one.width, one.height, one.rgb8.as_slice()), (1, 1, [20u8, 10, 7].as_slice()));
    }

    #[test]
    fn tile_bytes_survive_json_too() {
        let t = TileImage { name: "a".into(), width: 1, height: 1, frame_id: 7, rgb8: vec![1, 2, 255] };
        let s = serde_json::to_string(&t).unwrap();
        assert_eq!(serde_json::from_str::<TileImage>(&s).unwrap(), t);
    }
}
