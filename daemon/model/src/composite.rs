//! Object space compositing by direct send (DESIGN.md "Distribution"), sans-IO.
//!
//! Each frame, every node renders its brick over the covered rectangle of every tile
//! (`bricks::covered_rect`) and sends each tile's rectangles to the node that shows the tile: one
//! [`PeerPixels`] per frame per peer (empty where its brick covers none of the peer's tiles, so the
//! peer knows it is done). A rectangle's pixels travel planar: the depth of every pixel (f32
//! little-endian, distance along the ray, `+inf` where the brick has no hit), then their colours
//! (8-bit sRGB), each plane compressing well; with [`PixelEncoding::Lz4`] the whole is
//! LZ4-compressed (block format, lossless, after its decoded size as a u32 little-endian). The tile
//! owner's [`Compositor`] keeps, per pixel, the nearest hit of all bricks (its own included);
//! pixels no brick hits show the background. When its own render and every other node's pixels for
//! a frame are in, the frame's tiles are done (then Ready and the swap as in screen space).
//!
//! That is the *colour form* ([`PixelForm::Colour`]). A wall whose tiles are filtered
//! (`WallConfig::filters_composited`) sends the *shading form* ([`PixelForm::Shading`]) instead:
//! the edge-aware filter must run on the composited tile, so per pixel the depth and the four AOV
//! vectors the GPU's compose and filter read ([`ShadingPixel`]) travel, the depth plane first as
//! above, then the 16 f32 (little-endian) of each pixel, pixel by pixel. The owner keeps all 16
//! values of the nearest layer; pixels no brick hits keep depth `+inf` and zeros (the GPU's
//! compose gives them the background). Such a wall composites each tile over its *canvas*, the
//! tile grown by the filter's guard band ([`crate::Rect::grown`], within the wall's image), so that
//! the filter sees beyond the tile's edges what the whole image has; tile sizes and rectangle
//! positions here are then the canvas's. The whole wall uses one form for a session: the receiver
//! checks every rectangle against its own form, and a shading value that is not finite is refused
//! (it would spread through the owner's filter).
//!
//! Everything a peer sends is checked before use, and before anything is decompressed: the sender
//! must be the node its certificate names, the frame no more than [`FRAMES_AHEAD`] frames past
//! the latest this node was told of ([`Compositor::announce`]), one message per frame per peer.
//! Every rectangle must be of a tile the receiver shows and lie inside it, and the size it claims
//! (a raw payload's length, the 4-byte size an LZ4 payload starts with) must be exactly the
//! rectangle's in the receiver's form; then, against the sender's *footprint* for the frame (the
//! screen rectangles its bricks may cover in the receiver's tiles, [`Footprints`]), the
//! rectangles may number at most one per brick and tile, each must lie inside its brick's
//! rectangle of that tile, and their decoded bytes (in the form's bytes per pixel) may sum to no
//! more than the footprint's. Only then is a payload decompressed,
//! into a buffer of exactly the rectangle's size. Pixels that arrive before the frame's footprint
//! is known wait compressed (the same checks, against the whole tiles, at arrival; the rest when
//! the footprint comes). A violation is a [`CompositeError`] naming the peer: the caller closes
//! that peer's connection.
//!
//! A frame waits for its peers until its *compositing deadline* (set when it starts,
//! [`Compositor::expect`]); then it composites what arrived and names the peers whose pixels did
//! not ([`Composited::missing`]). A peer that missed a deadline is not waited for again until
//! something from it arrives (its pixels for any frame, late ones included): a silent peer costs
//! one deadline, not one per frame, and a slow one is waited for again as soon as it shows up.

use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

/// Bytes per pixel of the colour form before compression: depth (f32) and sRGB (3 x u8).
pub const BYTES_PER_PIXEL: usize = PixelForm::Colour.bytes_per_pixel();
/// Frames a compositor holds at once (pixels of later frames can arrive before this node's
/// render of an earlier one); past it the oldest pending frame is dropped (it can no longer be
/// shown in time).
pub const MAX_PENDING_FRAMES: usize = 16;
/// Pixels may be for at most this many frames past the latest frame this node was told of.
pub const FRAMES_AHEAD: u64 = 8;
/// Bytes of the decoded size an LZ4 payload starts with (u32 little-endian).
pub const LZ4_SIZE_BYTES: usize = 4;

/// What a pixel carries between nodes (module notes); one form for the whole wall and session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelForm {
    /// Depth and the finished 8-bit sRGB colour: the tile owner shows the composite as it is.
    Colour,
    /// Depth and the AOVs the GPU composes and filters ([`ShadingPixel`]): the tile owner filters
    /// and composes the composite.
    Shading,
}

impl PixelForm {
    /// Bytes per pixel before compression: depth (f32) and sRGB (3 x u8), or depth (f32) and
    /// the 16 f32 of a [`ShadingPixel`].
    pub const fn bytes_per_pixel(self) -> usize {
        match self {
            PixelForm::Colour => 4 + 3,
            PixelForm::Shading => 4 + SHADING_VALUES * 4,
        }
    }
}

/// One pixel's AOVs in the shading form, in the order the GPU's compose and filter read them:
/// direct colour (rgb) and hit flag; normal (xyz) and depth; the AO running sum (bent normal,
/// A); the IBL running sum (E rgb, weight).
pub type ShadingPixel = [[f32; 4]; 4];

/// The f32 values of a [`ShadingPixel`].
pub const SHADING_VALUES: usize = 16;

#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelEncoding {
    Raw,
    Lz4,
}

/// One rectangle of a tile (position in the tile's own pixels) as it travels.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq)]
pub struct PixelRect {
    pub tile: String,
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
    pub encoding: PixelEncoding,
    #[serde(with = "crate::messages::byte_buf")]
    pub payload: Vec<u8>,
}

/// What one node sends another for one frame.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq)]
pub struct PeerPixels {
    pub frame_id: u64,
    /// The sender (must be the node its certificate names).
    pub node: String,
    pub rects: Vec<PixelRect>,
}

/// A rectangle of a brick's render of one tile, decoded: position in the tile (its canvas, in
/// the shading form), the depth of each pixel (`+inf`: no hit) and, by its `form`, its 8-bit sRGB
/// colour (3 bytes a pixel; `shading` empty) or its AOVs (`rgb8` empty), rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct Layer {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
    /// Which of `rgb8` and `shading` the layer carries (stated, not guessed from their lengths).
    pub form: PixelForm,
    pub depth: Vec<f32>,
    pub rgb8: Vec<u8>,
    pub shading: Vec<ShadingPixel>,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CompositeError {
    #[error("node `{peer}` sent pixels for tile `{tile}`, which `{node}` does not show")]
    NotMyTile { peer: String, node: String, tile: String },
    #[error("node `{peer}` sent a {w}x{h} rectangle at ({x}, {y}) outside tile `{tile}` ({tw}x{th})")]
    OutsideTile { peer: String, tile: String, x: u32, y: u32, w: u32, h: u32, tw: u32, th: u32 },
    #[error("node `{peer}` sent a rectangle of tile `{tile}` whose {encoding:?} payload is not {want} bytes of valid {form:?} pixels: {why}")]
    BadPayload {
        peer: String,
        tile: String,
        encoding: PixelEncoding,
        form: PixelForm,
        want: usize,
        why: String,
    },
    #[error("the connection of node `{cert}` carried pixels signed as node `{claimed}`")]
    WrongSender { cert: String, claimed: String },
    #[error("node `{peer}` is not a node of this wall, or is this node")]
    UnknownPeer { peer: String },
    #[error("node `{peer}` sent pixels for frame {frame_id} twice")]
    Twice { peer: String, frame_id: u64 },
    #[error("node `{peer}` sent pixels for frame {frame_id}, more than {FRAMES_AHEAD} frames ahead of frame {latest}, the latest this node was told of")]
    FarAhead { peer: String, frame_id: u64, latest: u64 },
    #[error("node `{peer}` sent {got} rectangles for frame {frame_id}; the frame gives it at most {max} rectangles of this node's tiles (its bricks' footprints, or its rows of a balanced split)")]
    TooManyRects { peer: String, frame_id: u64, got: usize, max: usize },
    #[error("node `{peer}` sent rectangles of {got} decoded bytes for frame {frame_id}; what the frame gives it of this node's tiles is {max} bytes")]
    TooManyBytes { peer: String, frame_id: u64, got: u64, max: u64 },
    #[error("node `{peer}` sent a {w}x{h} rectangle at ({x}, {y}) of tile `{tile}` for frame {frame_id}, outside what the frame gives it there")]
    OutsideFootprint { peer: String, tile: String, frame_id: u64, x: u32, y: u32, w: u32, h: u32 },
}

/// A rectangle of a tile, in the tile's own pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TileRect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl TileRect {
    pub fn contains(&self, r: &TileRect) -> bool {
        r.x >= self.x
            && r.y >= self.y
            && u64::from(r.x) + u64::from(r.width) <= u64::from(self.x) + u64::from(self.width)
            && u64::from(r.y) + u64::from(r.height) <= u64::from(self.y) + u64::from(self.height)
    }

    pub fn pixel_count(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }
}

/// A frame's footprints: for each node whose pixels it needs, the rectangle each brick of that
/// node may cover in each of this node's tiles (tile name, rectangle; one per brick and tile it
/// covers, none where it covers nothing).
pub type Footprints = BTreeMap<String, Vec<(String, TileRect)>>;

impl Layer {
    /// A layer of `width x height` pixels at (x, y) of a tile in `form`: no hits, colour or
    /// AOVs 0.
    pub fn empty(x: u32, y: u32, width: u32, height: u32, form: PixelForm) -> Layer {
        let n = width as usize * height as usize;
        let (rgb8, shading) = match form {
            PixelForm::Colour => (vec![0; n * 3], Vec::new()),
            PixelForm::Shading => (Vec::new(), vec![[[0.0; 4]; 4]; n]),
        };
        Layer { x, y, width, height, form, depth: vec![f32::INFINITY; n], rgb8, shading }
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Whether any pixel has a hit.
    pub fn any_hit(&self) -> bool {
        self.depth.iter().any(|d| d.is_finite())
    }

    /// The rectangle as it travels, LZ4-compressed when `compress` (and it pays: where the
    /// compressed form is not smaller the rectangle goes raw).
    pub fn encode(&self, tile: &str, compress: bool) -> PixelRect {
        let mut raw = Vec::with_capacity(self.pixel_count() * self.form.bytes_per_pixel());
        for d in &self.depth {
            raw.extend_from_slice(&d.to_le_bytes());
        }
        match self.form {
            PixelForm::Colour => raw.extend_from_slice(&self.rgb8),
            PixelForm::Shading => {
                for v in self.shading.iter().flatten().flatten() {
                    raw.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        let (encoding, payload) = if compress {
            let c = lz4_flex::block::compress_prepend_size(&raw);
            if c.len() < raw.len() {
                (PixelEncoding::Lz4, c)
            } else {
                (PixelEncoding::Raw, raw)
            }
        } else {
            (PixelEncoding::Raw, raw)
        };
        PixelRect {
            tile: tile.to_string(),
            x: self.x,
            y: self.y,
            width: self.width,
            height: self.height,
            encoding,
            payload,
        }
    }
}

impl PixelRect {
    pub fn rect(&self) -> TileRect {
        TileRect { x: self.x, y: self.y, width: self.width, height: self.height }
    }

    /// The bytes the payload decodes to, as it claims (a raw payload's length; the size an LZ4
    /// payload starts with), without decompressing anything.
    pub fn claimed_len(&self) -> Option<usize> {
        match self.encoding {
            PixelEncoding::Raw => Some(self.payload.len()),
            PixelEncoding::Lz4 => lz4_flex::block::uncompressed_size(&self.payload).ok().map(|(n, _)| n),
        }
    }

    /// Checks what can be checked without decompressing: the rectangle lies inside a tile (its
    /// canvas) of `tile_size`, and the payload claims exactly its bytes in `form`.
    pub fn check(&self, peer: &str, tile_size: (u32, u32), form: PixelForm) -> Result<(), CompositeError> {
        let (tw, th) = tile_size;
        let fits = self.width > 0
            && self.height > 0
            && self.x.checked_add(self.width).is_some_and(|r| r <= tw)
            && self.y.checked_add(self.height).is_some_and(|b| b <= th);
        if !fits {
            return Err(CompositeError::OutsideTile {
                peer: peer.to_string(),
                tile: self.tile.clone(),
                x: self.x,
                y: self.y,
                w: self.width,
                h: self.height,
                tw,
                th,
            });
        }
        let want = self.rect().pixel_count() as usize * form.bytes_per_pixel();
        match self.claimed_len() {
            Some(n) if n == want => Ok(()),
            claimed => Err(self.bad_payload(
                peer,
                form,
                want,
                match (self.encoding, claimed) {
                    (PixelEncoding::Raw, Some(n)) => format!("it has {n} bytes"),
                    (_, Some(n)) => format!("it claims to decompress to {n} bytes"),
                    (_, None) => format!("it is shorter than the {LZ4_SIZE_BYTES}-byte decoded size"),
                },
            )),
        }
    }

    fn bad_payload(&self, peer: &str, form: PixelForm, want: usize, why: String) -> CompositeError {
        CompositeError::BadPayload {
            peer: peer.to_string(),
            tile: self.tile.clone(),
            encoding: self.encoding,
            form,
            want,
            why,
        }
    }

    /// Pixel `i` of the rectangle, named by its position in the tile too.
    fn pixel_name(&self, i: usize) -> String {
        let w = self.width.max(1) as usize;
        format!("pixel {i} (at ({}, {}) of the tile)", self.x as usize + i % w, self.y as usize + i / w)
    }

    /// Decodes the rectangle of a tile (its canvas) of `tile_size` in `form`, checking
    /// everything (module notes).
    pub fn decode(
        &self,
        peer: &str,
        tile_size: (u32, u32),
        form: PixelForm,
    ) -> Result<Layer, CompositeError> {
        self.check(peer, tile_size, form)?;
        let n = self.width as usize * self.height as usize;
        let want = n * form.bytes_per_pixel();
        let bad = |why: String| self.bad_payload(peer, form, want, why);
        let raw = match self.encoding {
            PixelEncoding::Raw => std::borrow::Cow::Borrowed(&self.payload[..]),
            PixelEncoding::Lz4 => {
                // The claimed size is the rectangle's (checked): the buffer is exactly that.
                let mut out = vec![0u8; want];
                let got = lz4_flex::block::decompress_into(&self.payload[LZ4_SIZE_BYTES..], &mut out)
                    .map_err(|e| bad(format!("it does not decompress: {e}")))?;
                if got != want {
                    return Err(bad(format!("it decompresses to {got} bytes")));
                }
                std::borrow::Cow::Owned(out)
            }
        };
        let f32s = |b: &[u8]| -> Vec<f32> {
            b.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
        };
        let (d, c) = raw.split_at(n * 4);
        let depth = f32s(d);
        if let Some(i) = depth.iter().position(|v| v.is_nan() || *v < 0.0) {
            return Err(bad(format!("{} has depth {}", self.pixel_name(i), depth[i])));
        }
        let (rgb8, shading) = match form {
            PixelForm::Colour => (c.to_vec(), Vec::new()),
            PixelForm::Shading => {
                let values = f32s(c);
                // A NaN or an infinity would spread through the owner's filter to its neighbours.
                if let Some(k) = values.iter().position(|v| !v.is_finite()) {
                    let (i, vector, component) = (k / SHADING_VALUES, k % SHADING_VALUES / 4, k % 4);
                    return Err(bad(format!(
                        "{} has shading value {} (vector {vector}, component {component})",
                        self.pixel_name(i),
                        values[k]
                    )));
                }
                let shading = values
                    .chunks_exact(SHADING_VALUES)
                    .map(|p| std::array::from_fn(|v| std::array::from_fn(|c| p[4 * v + c])))
                    .collect();
                (Vec::new(), shading)
            }
        };
        Ok(Layer { x: self.x, y: self.y, width: self.width, height: self.height, form, depth, rgb8, shading })
    }
}

/// A tile being composited (in the shading form its canvas, the tile grown by the guard band):
/// the nearest depth so far and, by its `form`, that pixel's colour (`shading` empty) or AOVs
/// (`rgb8` empty), rows top to bottom. Also what a node's render of one view is handed back as
/// ([`crate::object_machine::ObjectMachine::local_done`]).
#[derive(Debug, Clone, PartialEq)]
pub struct TileCanvas {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub form: PixelForm,
    pub depth: Vec<f32>,
    pub rgb8: Vec<u8>,
    pub shading: Vec<ShadingPixel>,
}

impl TileCanvas {
    /// Makes the canvas's pixels (no hits) where it has none yet.
    fn allocate(&mut self) {
        if self.depth.len() != self.width as usize * self.height as usize {
            *self = TileCanvas::new(&self.name, self.width, self.height, self.form);
        }
    }

    /// A canvas with no hits: depth `+inf`, colour or AOVs 0.
    pub fn new(name: &str, width: u32, height: u32, form: PixelForm) -> TileCanvas {
        let Layer { depth, rgb8, shading, .. } = Layer::empty(0, 0, width, height, form);
        TileCanvas { name: name.to_string(), width, height, form, depth, rgb8, shading }
    }

    /// Keeps, per pixel, the nearer of the canvas and the layer (a layer inside the tile), with
    /// all its data: the colour, or all 16 AOV values. A layer of the other form is a caller's
    /// error and is left out.
    pub fn merge(&mut self, l: &Layer) {
        debug_assert_eq!(l.form, self.form, "a {:?} layer merged into a {:?} canvas", l.form, self.form);
        if l.form != self.form {
            return;
        }
        let w = l.width as usize;
        for row in 0..l.height as usize {
            let dst = (l.y as usize + row) * self.width as usize + l.x as usize;
            for i in 0..w {
                let s = row * w + i;
                if l.depth[s] < self.depth[dst + i] {
                    self.depth[dst + i] = l.depth[s];
                    match self.form {
                        PixelForm::Colour => self.rgb8[3 * (dst + i)..3 * (dst + i) + 3]
                            .copy_from_slice(&l.rgb8[3 * s..3 * s + 3]),
                        PixelForm::Shading => self.shading[dst + i] = l.shading[s],
                    }
                }
            }
        }
    }

    /// Gives every pixel no brick hit the background, in the colour form. In the shading form
    /// such pixels keep depth `+inf` and zeros: the GPU's compose gives them the background.
    pub fn fill_background(&mut self, background: [u8; 3]) {
        if self.form != PixelForm::Colour {
            return;
        }
        for (d, c) in self.depth.iter().zip(self.rgb8.chunks_exact_mut(3)) {
            if !d.is_finite() {
                c.copy_from_slice(&background);
            }
        }
    }
}

/// The compositing deadline of a wall whose swap barrier waits `barrier_deadline` for a frame:
/// nine tenths of it from the frame's start, so a node that composites at its deadline is still
/// ready for the barrier.
pub fn composite_deadline(barrier_deadline: Duration) -> Duration {
    barrier_deadline.mul_f64(0.9)
}

#[derive(Debug)]
struct Pending {
    canvases: Vec<TileCanvas>,
    from: BTreeSet<String>,
    /// This node's own render is in, with the frame's background.
    local: Option<[u8; 3]>,
    /// Once the frame started ([`Compositor::expect`]): the nodes whose pixels it needs (the
    /// keys) and where their bricks may cover this node's tiles.
    footprints: Option<Footprints>,
    /// When the frame started: its deadline runs from here.
    started: Option<Duration>,
    /// Pixels that came before the footprints, checked against the whole tiles, still compressed,
    /// with the link they came on.
    early: Vec<(String, Link, PeerPixels)>,
}

/// Which connection a peer's pixels came on ([`crate::links`]): a message refused later is
/// blamed on the connection that carried it, not on a newer one from the same peer.
pub use crate::links::Link;

/// Pixels refused when their frame started: the rule they broke, and the link that carried them.
#[derive(Debug, Clone, PartialEq)]
pub struct Refused {
    pub link: Link,
    pub error: CompositeError,
}

/// A frame whose tiles are composited.
#[derive(Debug, Clone, PartialEq)]
pub struct Composited {
    pub frame_id: u64,
    /// This node's tiles in the compositor's order: each the size it was given (in the shading
    /// form the tile's canvas, `ObjectMachine::canvas_rect`).
    pub tiles: Vec<TileCanvas>,
    /// The nodes whose pixels the frame needed and did not have by its deadline (or that were not
    /// waited for: they had missed an earlier deadline and sent nothing since), in name order.
    pub missing: Vec<String>,
}

/// A tile owner's compositing state: frames waiting for this node's render or peers' pixels.
#[derive(Debug)]
pub struct Compositor {
    node: String,
    /// The nodes that send to this one: every other node of the wall.
    peers: BTreeSet<String>,
    /// This node's tiles: name and size (of the canvas, in the shading form).
    tiles: Vec<(String, u32, u32)>,
    /// What every pixel carries on this wall.
    form: PixelForm,
    pending: BTreeMap<u64, Pending>,
    /// The last frame done: pixels for it or older frames are stale.
    last_done: Option<u64>,
    /// How long a frame waits for its peers after it starts.
    deadline: Duration,
    /// The latest frame this node was told of ([`Compositor::announce`]).
    latest: Option<u64>,
    /// Peers that missed a deadline and have sent nothing since: not waited for.
    late: BTreeSet<String>,
    /// Pending frames dropped to keep at most [`MAX_PENDING_FRAMES`].
    dropped: u64,
    refused: Vec<Refused>,
}

/// Checks a peer's rectangles against its footprint (module notes) and decodes them.
fn decode_within(
    tiles: &[(String, u32, u32)],
    form: PixelForm,
    cert: &str,
    msg: &PeerPixels,
    footprint: &[(String, TileRect)],
) -> Result<Vec<(String, Layer)>, CompositeError> {
    let frame_id = msg.frame_id;
    if msg.rects.len() > footprint.len() {
        return Err(CompositeError::TooManyRects {
            peer: cert.to_string(),
            frame_id,
            got: msg.rects.len(),
            max: footprint.len(),
        });
    }
    let bytes = |n: u64| n * form.bytes_per_pixel() as u64;
    let max = bytes(footprint.iter().map(|(_, r)| r.pixel_count()).sum());
    let got = bytes(msg.rects.iter().map(|r| r.rect().pixel_count()).sum());
    if got > max {
        return Err(CompositeError::TooManyBytes { peer: cert.to_string(), frame_id, got, max });
    }
    if let Some(r) =
        msg.rects.iter().find(|r| !footprint.iter().any(|(t, f)| *t == r.tile && f.contains(&r.rect())))
    {
        return Err(CompositeError::OutsideFootprint {
            peer: cert.to_string(),
            tile: r.tile.clone(),
            frame_id,
            x: r.x,
            y: r.y,
            w: r.width,
            h: r.height,
        });
    }
    msg.rects
        .iter()
        .map(|r| {
            let (_, w, h) = tiles.iter().find(|t| t.0 == r.tile).expect("checked at arrival");
            Ok((r.tile.clone(), r.decode(cert, (*w, *h), form)?))
        })
        .collect()
}

impl Pending {
    fn merge(&mut self, layers: &[(String, Layer)]) {
        for (tile, l) in layers {
            if let Some(c) = self.canvases.iter_mut().find(|c| &c.name == tile) {
                c.allocate();
                c.merge(l);
            }
        }
    }
}

impl Compositor {
    /// The compositor of `node` showing `tiles` (name, and the size of what it composites: the
    /// tile, or in the shading form its canvas), with pixels in `form` from `peers` (the wall's
    /// other nodes), each frame waiting `deadline` for them after it starts.
    pub fn new(
        node: &str,
        peers: impl IntoIterator<Item = String>,
        tiles: Vec<(String, u32, u32)>,
        deadline: Duration,
        form: PixelForm,
    ) -> Compositor {
        let peers = peers.into_iter().filter(|p| p != node).collect();
        Compositor {
            node: node.to_string(),
            peers,
            tiles,
            form,
            pending: BTreeMap::new(),
            last_done: None,
            deadline,
            latest: None,
            late: BTreeSet::new(),
            dropped: 0,
            refused: Vec::new(),
        }
    }

    /// What every pixel carries on this wall.
    pub fn form(&self) -> PixelForm {
        self.form
    }

    /// The nodes this one waits for each frame.
    pub fn peers(&self) -> &BTreeSet<String> {
        &self.peers
    }

    /// Peers not waited for (they missed a deadline and have sent nothing since).
    pub fn late(&self) -> &BTreeSet<String> {
        &self.late
    }

    /// Pending frames dropped because too many were pending.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    fn frame(&mut self, frame_id: u64) -> &mut Pending {
        if !self.pending.contains_key(&frame_id) && self.pending.len() >= MAX_PENDING_FRAMES {
            self.pending.pop_first();
            self.dropped += 1;
        }
        let (tiles, form) = (&self.tiles, self.form);
        self.pending.entry(frame_id).or_insert_with(|| Pending {
            // Allocated at their first merge: pixels that come early (before the frame starts)
            // wait compressed, so a peer's messages for frames ahead cost no canvas memory.
            canvases: tiles
                .iter()
                .map(|(n, w, h)| TileCanvas {
                    name: n.clone(),
                    width: *w,
                    height: *h,
                    form,
                    depth: Vec::new(),
                    rgb8: Vec::new(),
                    shading: Vec::new(),
                })
                .collect(),
            from: BTreeSet::new(),
            local: None,
            footprints: None,
            started: None,
            early: Vec::new(),
        })
    }

    fn stale(&self, frame_id: u64) -> bool {
        self.last_done.is_some_and(|d| frame_id <= d)
    }

    /// The controller told this node of `frame_id` (its frame state arrived): pixels may come for
    /// frames up to [`FRAMES_AHEAD`] past it. Pending frames further ahead (pixels that came
    /// before any frame was announced) are dropped.
    pub fn announce(&mut self, frame_id: u64) {
        let latest = self.latest.map_or(frame_id, |l| l.max(frame_id));
        self.latest = Some(latest);
        let before = self.pending.len();
        self.pending.retain(|&id, _| id <= latest.saturating_add(FRAMES_AHEAD));
        self.dropped += (before - self.pending.len()) as u64;
    }

    /// Every peer, every whole tile once: the footprint of a frame that starts without one.
    fn whole_tiles(&self) -> Footprints {
        let all: Vec<(String, TileRect)> = self
            .tiles
            .iter()
            .map(|(n, w, h)| (n.clone(), TileRect { x: 0, y: 0, width: *w, height: *h }))
            .collect();
        self.peers.iter().map(|p| (p.clone(), all.clone())).collect()
    }

    /// This node's own layers of `frame_id` (tile name, layer), and the background for pixels no
    /// brick hits. Layers for tiles this node does not show are ignored (they go to peers). A
    /// frame not started ([`Compositor::expect`]) starts now, waiting for every peer over whole
    /// tiles (the pixels that came before and break the rules: [`Compositor::take_refused`]).
    pub fn local(
        &mut self,
        now: Duration,
        frame_id: u64,
        layers: &[(String, Layer)],
        background: [u8; 3],
    ) -> Option<Composited> {
        if self.stale(frame_id) {
            return None;
        }
        if self.frame(frame_id).footprints.is_none() {
            let all = self.whole_tiles();
            let errors = self.expect(now, frame_id, all);
            self.refused.extend(errors);
        }
        let p = self.frame(frame_id);
        p.merge(layers);
        p.local = Some(background);
        self.poll(now, frame_id)
    }

    /// Pixels refused when a frame started inside [`Compositor::local`] (close those peers'
    /// connections).
    pub fn take_refused(&mut self) -> Vec<Refused> {
        std::mem::take(&mut self.refused)
    }

    /// `frame_id` starts at `now`: it needs the pixels of the nodes `footprints` names (the nodes
    /// that hold bricks in its map, `crate::adoption`; this node and names that are not peers are
    /// left out), each within its rectangles there, and waits for them until its deadline.
    /// Pixels that came earlier are checked and merged now; those that break the rules are
    /// returned (close those peers' connections) and count as not received.
    pub fn expect(&mut self, now: Duration, frame_id: u64, footprints: Footprints) -> Vec<Refused> {
        if self.stale(frame_id) {
            return Vec::new();
        }
        let footprints: Footprints = footprints.into_iter().filter(|(n, _)| self.peers.contains(n)).collect();
        let (tiles, form) = (self.tiles.clone(), self.form);
        let p = self.frame(frame_id);
        let mut errors = Vec::new();
        for (cert, link, msg) in std::mem::take(&mut p.early) {
            let fp = footprints.get(&cert).map_or(&[][..], |f| &f[..]);
            match decode_within(&tiles, form, &cert, &msg, fp) {
                Ok(layers) => p.merge(&layers),
                Err(error) => {
                    p.from.remove(&cert);
                    errors.push(Refused { link, error });
                }
            }
        }
        p.footprints = Some(footprints);
        p.started = Some(now);
        errors
    }

    /// `gone` render nothing any more (down): pending frames stop waiting for them. Returns the
    /// frames that this completes, oldest first (each drops the older ones, as always).
    pub fn forget(&mut self, now: Duration, gone: &[String]) -> Vec<Composited> {
        let ids: Vec<u64> = self.pending.keys().copied().collect();
        for p in self.pending.values_mut() {
            if let Some(f) = p.footprints.as_mut() {
                f.retain(|n, _| !gone.contains(n));
            }
        }
        ids.into_iter().filter_map(|id| self.poll(now, id)).collect()
    }

    /// `nodes` are back (a brick map gives them bricks again): waited for again even if they
    /// missed a deadline before.
    pub fn wait_again(&mut self, nodes: &[String]) {
        for n in nodes {
            self.late.remove(n);
        }
    }

    /// A peer's pixels, from the connection `link` whose certificate names `cert`. A second
    /// message for a frame from the same peer is [`CompositeError::Twice`]: dropped, changing
    /// nothing (it may come on another connection of the same certificate; the caller logs it
    /// and keeps the connection).
    pub fn peer(
        &mut self,
        now: Duration,
        cert: &str,
        link: Link,
        msg: PeerPixels,
    ) -> Result<Option<Composited>, CompositeError> {
        if msg.node != cert {
            return Err(CompositeError::WrongSender { cert: cert.to_string(), claimed: msg.node });
        }
        if !self.peers.contains(cert) {
            return Err(CompositeError::UnknownPeer { peer: cert.to_string() });
        }
        let id = msg.frame_id;
        if self.stale(id) {
            // Late, but alive: waited for again.
            self.late.remove(cert);
            return Ok(None);
        }
        if let Some(latest) = self.latest.filter(|l| id > l.saturating_add(FRAMES_AHEAD)) {
            return Err(CompositeError::FarAhead { peer: cert.to_string(), frame_id: id, latest });
        }
        // What the header says, against the whole tiles: at most one rectangle per brick (one
        // per node) and tile, each inside its tile, claiming exactly its size.
        let max = self.tiles.len() * (self.peers.len() + 1);
        if msg.rects.len() > max {
            return Err(CompositeError::TooManyRects {
                peer: cert.to_string(),
                frame_id: id,
                got: msg.rects.len(),
                max,
            });
        }
        for r in &msg.rects {
            let Some(&(_, w, h)) = self.tiles.iter().find(|t| t.0 == r.tile) else {
                return Err(CompositeError::NotMyTile {
                    peer: cert.to_string(),
                    node: self.node.clone(),
                    tile: r.tile.clone(),
                });
            };
            r.check(cert, (w, h), self.form)?;
        }
        if self.pending.get(&id).is_some_and(|p| p.from.contains(cert)) {
            return Err(CompositeError::Twice { peer: cert.to_string(), frame_id: id });
        }
        // Decoded now when the frame has started (a bad message changes nothing), else kept.
        let footprint =
            self.pending.get(&id).and_then(|p| p.footprints.as_ref()).map(|f| f.get(cert).cloned());
        let layers = match &footprint {
            Some(fp) => {
                Some(decode_within(&self.tiles, self.form, cert, &msg, fp.as_deref().unwrap_or(&[]))?)
            }
            None => None,
        };
        self.late.remove(cert);
        let p = self.frame(id);
        p.from.insert(cert.to_string());
        match layers {
            Some(layers) => p.merge(&layers),
            None => p.early.push((cert.to_string(), link, msg)),
        }
        Ok(self.poll(now, id))
    }

    /// The frame's tiles once this node's render and every awaited peer's pixels are in, or its
    /// deadline has passed; older pending frames are then dropped (they can no longer be shown).
    fn poll(&mut self, now: Duration, frame_id: u64) -> Option<Composited> {
        let p = self.pending.get(&frame_id)?;
        let background = p.local?;
        let expected: Vec<&String> = match &p.footprints {
            Some(f) => f.keys().collect(),
            None => self.peers.iter().collect(),
        };
        let waiting = expected.iter().any(|n| !p.from.contains(*n) && !self.late.contains(*n));
        let due = p.started.is_some_and(|s| now >= s + self.deadline);
        if waiting && !due {
            return None;
        }
        let missing: Vec<String> = expected.into_iter().filter(|n| !p.from.contains(*n)).cloned().collect();
        self.late.extend(missing.iter().cloned());
        let mut p = self.pending.remove(&frame_id).expect("present");
        for c in &mut p.canvases {
            c.allocate();
            c.fill_background(background);
        }
        self.pending.retain(|&id, _| id > frame_id);
        self.last_done = Some(frame_id);
        Some(Composited { frame_id, tiles: p.canvases, missing })
    }

    /// When the next frame's deadline passes (call [`Compositor::handle_timeout`] then).
    pub fn poll_timeout(&self) -> Option<Duration> {
        self.pending
            .values()
            .filter(|p| p.local.is_some())
            .filter_map(|p| p.started.map(|s| s + self.deadline))
            .min()
    }

    /// Frames whose deadline has passed at `now`, composited with what arrived.
    pub fn handle_timeout(&mut self, now: Duration) -> Vec<Composited> {
        let due: Vec<u64> = self
            .pending
            .iter()
            .filter(|(_, p)| p.local.is_some() && p.started.is_some_and(|s| now >= s + self.deadline))
            .map(|(&id, _)| id)
            .collect();
        due.into_iter().filter_map(|id| self.poll(now, id)).collect()
    }

    /// Forgets every frame: a new controller session numbers its frames afresh.
    pub fn reset(&mut self) {
        self.pending.clear();
        self.last_done = None;
        self.latest = None;
        self.late.clear();
    }

    /// Frames waiting.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Pixels the pending frames' canvases hold (allocated once a frame's first pixels merge).
    pub fn canvas_pixels(&self) -> usize {
        self.pending.values().flat_map(|p| &p.canvases).map(|c| c.depth.len()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const T: Duration = Duration::ZERO;
    const SECOND: Duration = Duration::from_secs(1);

    fn ms(x: u64) -> Duration {
        Duration::from_millis(x)
    }

    /// Footprints of whole 4x2 tiles `t`: per node, that many rectangles (one per brick).
    fn whole(nodes: &[(&str, usize)]) -> Footprints {
        let t = TileRect { x: 0, y: 0, width: 4, height: 2 };
        nodes.iter().map(|(n, k)| (n.to_string(), vec![("t".to_string(), t); *k])).collect()
    }

    fn empty(frame_id: u64, node: &str) -> PeerPixels {
        PeerPixels { frame_id, node: node.into(), rects: vec![] }
    }

    fn layer(x: u32, y: u32, w: u32, h: u32, f: impl Fn(u32, u32) -> (f32, u8)) -> Layer {
        let mut l = Layer::empty(x, y, w, h, PixelForm::Colour);
        for j in 0..h {
            for i in 0..w {
                let (d, c) = f(i, j);
                let k = (j * w + i) as usize;
                l.depth[k] = d;
                l.rgb8[3 * k..3 * k + 3].copy_from_slice(&[c, c, c]);
            }
        }
        l
    }

    #[test]
    fn rects_round_trip_raw_and_lz4_and_lz4_pays_on_sparse_hits() {
        let l =
            layer(
                3,
                2,
                40,
                30,
                |i, j| if (i + j) % 7 == 0 { (5.0 + i as f32, 200) } else { (f32::INFINITY, 10) },
            );
        for compress in [false, true] {
            let r = l.encode("t", compress);
            assert_eq!(r.encoding, if compress { PixelEncoding::Lz4 } else { PixelEncoding::Raw });
            assert_eq!(r.decode("p", (50, 40), PixelForm::Colour).unwrap(), l);
        }
        let (raw, lz) = (l.encode("t", false).payload.len(), l.encode("t", true).payload.len());
        assert_eq!(raw, 40 * 30 * BYTES_PER_PIXEL);
        assert!(lz * 3 < raw, "lz4 {lz} raw {raw}");
    }

    /// A shading layer whose pixel (i, j) is `f(i, j)`: its depth and a base value from which
    /// all 16 AOV values differ (value k is base + k).
    fn shading_layer(x: u32, y: u32, w: u32, h: u32, f: impl Fn(u32, u32) -> (f32, f32)) -> Layer {
        let mut l = Layer::empty(x, y, w, h, PixelForm::Shading);
        for j in 0..h {
            for i in 0..w {
                let (d, base) = f(i, j);
                let k = (j * w + i) as usize;
                l.depth[k] = d;
                l.shading[k] = std::array::from_fn(|v| std::array::from_fn(|c| base + (4 * v + c) as f32));
            }
        }
        l
    }

    #[test]
    fn shading_rects_round_trip_raw_and_lz4_depth_plane_first_then_each_pixels_16_values() {
        let l = shading_layer(3, 2, 40, 30, |i, j| {
            if (i + j) % 7 == 0 {
                (5.0 + i as f32, 0.25 * (i + 40 * j) as f32)
            } else {
                (f32::INFINITY, 0.0)
            }
        });
        for compress in [false, true] {
            let r = l.encode("t", compress);
            assert_eq!(r.encoding, if compress { PixelEncoding::Lz4 } else { PixelEncoding::Raw });
            assert_eq!(r.decode("p", (50, 40), PixelForm::Shading).unwrap(), l);
        }
        let raw = l.encode("t", false).payload;
        let n = 40 * 30;
        assert_eq!(raw.len(), n * PixelForm::Shading.bytes_per_pixel());
        assert_eq!(PixelForm::Shading.bytes_per_pixel(), 68);
        assert_eq!(PixelForm::Colour.bytes_per_pixel(), BYTES_PER_PIXEL);
        // Pixel 7 (a hit): its depth in the plane, then its 16 values after the plane, in order.
        assert_eq!(raw[7 * 4..8 * 4], l.depth[7].to_le_bytes());
        let at = n * 4 + 7 * 64;
        let values: Vec<f32> =
            raw[at..at + 64].chunks(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
        assert_eq!(values, l.shading[7].iter().flatten().copied().collect::<Vec<_>>());
        assert_eq!(values[5], l.shading[7][1][1]);
        let lz = l.encode("t", true).payload.len();
        assert!(lz * 3 < raw.len(), "lz4 {lz} raw {}", raw.len());
        // A layer without a single hit is still a shading layer: it encodes as one.
        let none = Layer::empty(0, 0, 2, 2, PixelForm::Shading);
        assert_eq!(none.encode("t", false).payload.len(), 4 * 68);
        assert_eq!(none.encode("t", true).decode("p", (4, 4), PixelForm::Shading).unwrap(), none);
    }

    #[test]
    fn a_shading_value_that_is_not_finite_is_refused_naming_the_pixel() {
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            for compress in [false, true] {
                let mut l = shading_layer(2, 1, 5, 4, |_, _| (1.0, 0.5));
                // Pixel 13 is (3, 2) of the layer, (5, 3) of the tile; vector 2, component 3.
                l.shading[13][2][3] = bad;
                let e = l.encode("t", compress).decode("p", (8, 8), PixelForm::Shading).unwrap_err();
                assert!(matches!(e, CompositeError::BadPayload { form: PixelForm::Shading, .. }), "{e}");
                let msg = e.to_string();
                assert!(msg.contains("node `p`") && msg.contains("tile `t`"), "{msg}");
                assert!(msg.contains("pixel 13 (at (5, 3) of the tile)"), "{msg}");
                assert!(msg.contains(&format!("shading value {bad} (vector 2, component 3)")), "{msg}");
            }
        }
        // A pixel without a hit may have depth +inf; its depth may not be NaN, as in colour.
        let mut l = shading_layer(0, 0, 2, 2, |_, _| (f32::INFINITY, 0.0));
        assert!(l.encode("t", true).decode("p", (2, 2), PixelForm::Shading).is_ok());
        l.depth[3] = f32::NAN;
        let e = l.encode("t", false).decode("p", (2, 2), PixelForm::Shading).unwrap_err();
        assert!(e.to_string().contains("pixel 3 (at (1, 1) of the tile) has depth NaN"), "{e}");
    }

    #[test]
    fn sizes_are_checked_in_the_receivers_form_before_anything_is_decompressed() {
        let colour = layer(0, 0, 8, 8, |_, _| (1.0, 1));
        let shading = shading_layer(0, 0, 8, 8, |_, _| (1.0, 1.0));
        // Each form's rectangle is refused by the other's check, raw or LZ4, naming the sizes.
        let r = colour.encode("t", false);
        let e = r.check("p", (8, 8), PixelForm::Shading).unwrap_err();
        assert!(e.to_string().contains("not 4352 bytes of valid Shading pixels: it has 448 bytes"), "{e}");
        assert!(shading.encode("t", false).check("p", (8, 8), PixelForm::Colour).is_err());
        assert!(shading.encode("t", true).check("p", (8, 8), PixelForm::Colour).is_err());
        // A colour-sized LZ4 claim whose body is not LZ4 at all: refused on its claim for a
        // shading receiver (nothing decompressed), and only at decompression for a colour one.
        let mut r = colour.encode("t", true);
        assert_eq!(r.encoding, PixelEncoding::Lz4);
        r.payload.truncate(LZ4_SIZE_BYTES);
        r.payload.extend_from_slice(&[0xff; 16]);
        let e = r.decode("p", (8, 8), PixelForm::Shading).unwrap_err();
        assert!(e.to_string().contains("claims to decompress to 448 bytes"), "{e}");
        let e = r.decode("p", (8, 8), PixelForm::Colour).unwrap_err();
        assert!(e.to_string().contains("does not decompress"), "{e}");
        // The same through a shading compositor: refused at arrival, naming the peer.
        let mut c = Compositor::new(
            "a",
            ["a", "b"].map(String::from),
            vec![("t".into(), 8, 8)],
            SECOND,
            PixelForm::Shading,
        );
        assert_eq!(c.form(), PixelForm::Shading);
        let msg = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![r] };
        let e = c.peer(T, "b", 1, msg).unwrap_err();
        assert!(matches!(e, CompositeError::BadPayload { want: 4352, .. }), "{e}");
        assert!(e.to_string().contains("node `b`"), "{e}");
        // The footprint's byte cap is in the form's bytes too: 2x2 pixels of 68 bytes.
        let corner = TileRect { x: 0, y: 0, width: 2, height: 2 };
        c.expect(T, 2, [("b".to_string(), vec![("t".to_string(), corner)])].into());
        let whole = shading_layer(0, 0, 4, 2, |_, _| (1.0, 1.0)).encode("t", true);
        let e =
            c.peer(T, "b", 1, PeerPixels { frame_id: 2, node: "b".into(), rects: vec![whole] }).unwrap_err();
        assert!(matches!(e, CompositeError::TooManyBytes { got: 544, max: 272, .. }), "{e}");
    }

    #[test]
    fn the_owner_keeps_all_16_values_of_the_nearer_layer_and_no_background_in_shading() {
        let mut c = Compositor::new(
            "a",
            ["a", "b"].map(String::from),
            vec![("t".into(), 4, 2)],
            SECOND,
            PixelForm::Shading,
        );
        // b's layer is nearer on the left half, a's own nearer on the right; (3, 1) is hit by none.
        let from_b = shading_layer(0, 0, 4, 2, |i, _| (if i < 2 { 1.0 } else { 3.0 }, 100.0 + i as f32));
        let own = shading_layer(0, 0, 4, 2, |i, j| {
            if (i, j) == (3, 1) {
                (f32::INFINITY, 0.0)
            } else {
                (2.0, 200.0 + i as f32)
            }
        });
        let mut from_b_missing = from_b.clone();
        from_b_missing.depth[7] = f32::INFINITY;
        from_b_missing.shading[7] = [[0.0; 4]; 4];
        assert_eq!(c.local(T, 1, &[("t".into(), own.clone())], [9, 9, 9]), None);
        let msg = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![from_b_missing.encode("t", true)] };
        let done = c.peer(T, "b", 1, msg).unwrap().expect("all in");
        let t = &done.tiles[0];
        assert_eq!((t.form, t.width, t.height), (PixelForm::Shading, 4, 2));
        assert!(t.rgb8.is_empty(), "the shading form carries no colour");
        for k in 0..8 {
            let (i, want) = (
                k % 4,
                if k == 7 {
                    None
                } else if k % 4 < 2 {
                    Some(&from_b)
                } else {
                    Some(&own)
                },
            );
            match want {
                Some(l) => {
                    assert_eq!(t.depth[k], l.depth[k], "pixel {k}");
                    assert_eq!(t.shading[k], l.shading[k], "pixel {k} (x {i}): all 16 values of the nearer");
                }
                None => {
                    assert_eq!(t.depth[k], f32::INFINITY);
                    assert_eq!(t.shading[k], [[0.0; 4]; 4], "no hit: zeros, not the background");
                }
            }
        }
    }

    #[test]
    fn bad_rects_are_errors_never_panics() {
        let l = layer(0, 0, 8, 8, |_, _| (1.0, 1));
        let good = l.encode("t", true);
        let mut r = good.clone();
        r.x = 60;
        assert!(matches!(
            r.decode("p", (64, 64), PixelForm::Colour),
            Err(CompositeError::OutsideTile { .. })
        ));
        let mut r = good.clone();
        r.width = u32::MAX;
        assert!(matches!(
            r.decode("p", (64, 64), PixelForm::Colour),
            Err(CompositeError::OutsideTile { .. })
        ));
        let mut r = good.clone();
        r.payload.truncate(r.payload.len() / 2);
        assert!(matches!(r.decode("p", (64, 64), PixelForm::Colour), Err(CompositeError::BadPayload { .. })));
        let mut r = l.encode("t", false);
        r.payload.push(0);
        assert!(r.decode("p", (64, 64), PixelForm::Colour).unwrap_err().to_string().contains("449 bytes"));
        // A small payload that claims to decompress to far more than the rectangle.
        let bomb = l.encode("t", false);
        let mut r = layer(0, 0, 8, 8, |_, _| (1.0, 1)).encode("t", true);
        r.payload = lz4_flex::block::compress(&vec![0u8; 1 << 20]);
        assert!(matches!(r.decode("p", (64, 64), PixelForm::Colour), Err(CompositeError::BadPayload { .. })));
        let mut r = bomb;
        r.payload[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(r.decode("p", (64, 64), PixelForm::Colour).unwrap_err().to_string().contains("depth NaN"));
    }

    #[test]
    fn the_owner_keeps_the_nearest_hit_and_waits_for_every_peer() {
        let mut c = Compositor::new(
            "a",
            ["a", "b", "c"].map(String::from),
            vec![("t".into(), 4, 2)],
            SECOND,
            PixelForm::Colour,
        );
        let near = layer(0, 0, 2, 2, |_, _| (1.0, 10));
        let far = layer(1, 0, 3, 2, |_, _| (2.0, 20));
        let miss = layer(0, 0, 4, 1, |_, _| (f32::INFINITY, 99));
        assert_eq!(c.local(T, 1, &[("t".into(), far.clone())], [7, 7, 7]), None);
        let from_b = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![near.encode("t", true)] };
        assert_eq!(c.peer(T, "b", 1, from_b.clone()).unwrap(), None);
        assert_eq!(
            c.peer(T, "b", 1, from_b.clone()),
            Err(CompositeError::Twice { peer: "b".into(), frame_id: 1 })
        );
        let from_c = PeerPixels { frame_id: 1, node: "c".into(), rects: vec![miss.encode("t", false)] };
        let done = c.peer(T, "c", 1, from_c).unwrap().expect("all in");
        let t = &done.tiles[0];
        // Row 0: near, near, far, far; row 1 the same.
        let colours: Vec<u8> = t.rgb8.chunks(3).map(|p| p[0]).collect();
        assert_eq!(colours, vec![10, 10, 20, 20, 10, 10, 20, 20]);
        assert_eq!(t.depth[0], 1.0);
        // Stale pixels are ignored; the wrong sender, an unknown peer and other tiles are errors.
        assert_eq!(c.peer(T, "b", 1, from_b).unwrap(), None);
        let e = c.peer(T, "c", 1, PeerPixels { frame_id: 2, node: "b".into(), rects: vec![] }).unwrap_err();
        assert!(matches!(e, CompositeError::WrongSender { .. }));
        let e = c.peer(T, "z", 1, PeerPixels { frame_id: 2, node: "z".into(), rects: vec![] }).unwrap_err();
        assert!(matches!(e, CompositeError::UnknownPeer { .. }));
        let e = c.peer(
            T,
            "b",
            1,
            PeerPixels { frame_id: 2, node: "b".into(), rects: vec![near.encode("u", false)] },
        );
        assert!(matches!(e, Err(CompositeError::NotMyTile { .. })));
        // Uncovered pixels get the background; frames can complete before an older one, which is dropped.
        c.peer(T, "b", 1, PeerPixels { frame_id: 3, node: "b".into(), rects: vec![] }).unwrap();
        c.peer(T, "c", 1, PeerPixels { frame_id: 3, node: "c".into(), rects: vec![] }).unwrap();
        c.peer(T, "b", 1, PeerPixels { frame_id: 2, node: "b".into(), rects: vec![] }).unwrap();
        let done = c.local(T, 3, &[], [5, 6, 7]).expect("frame 3");
        assert!(done.tiles[0].rgb8.chunks(3).all(|p| p == [5, 6, 7]));
        assert_eq!(c.pending(), 0);
        // Frames further ahead of the latest announced than FRAMES_AHEAD are refused, naming the
        // peer; those within are kept.
        c.announce(3);
        for id in 4..=3 + FRAMES_AHEAD {
            c.peer(T, "b", 1, empty(id, "b")).unwrap();
        }
        let e = c.peer(T, "b", 1, empty(4 + FRAMES_AHEAD, "b")).unwrap_err();
        assert!(matches!(e, CompositeError::FarAhead { latest: 3, .. }), "{e}");
        assert!(e.to_string().contains("node `b`"), "{e}");
        assert!(matches!(c.peer(T, "b", 1, empty(u64::MAX, "b")), Err(CompositeError::FarAhead { .. })));
        assert_eq!(c.pending(), FRAMES_AHEAD as usize);
    }

    #[test]
    fn pixels_for_frames_ahead_cost_no_canvas_until_the_frame_starts() {
        // A peer's messages for every frame it may send ahead (empty ones, a few bytes each) make
        // no canvas: in the shading form a 1080p tile's canvas is ~170 MB, and 8 frames of them
        // would be a memory bomb for 8 tiny messages.
        let mut c = two_nodes(PixelForm::Shading);
        c.announce(0);
        for id in 1..=FRAMES_AHEAD {
            c.peer(T, "b", 1, empty(id, "b")).unwrap();
        }
        assert_eq!(c.pending(), FRAMES_AHEAD as usize);
        assert_eq!(c.canvas_pixels(), 0, "canvases made for frames not started");
        // The frame starts and this node's render is in: its canvas is made and completes.
        c.expect(T, 1, whole(&[("b", 1)]));
        let l = Layer::empty(0, 0, 4, 2, PixelForm::Shading);
        let done = c.local(T, 1, &[("t".into(), l)], [0; 3]).expect("frame 1");
        assert_eq!((done.tiles[0].depth.len(), done.tiles[0].shading.len()), (8, 8));
        // A frame that completes without a single layer (b's message for it was empty) still
        // gives a whole canvas, of no hits.
        let done = c.local(T, 2, &[], [0; 3]).expect("frame 2: b's pixels came early");
        assert_eq!(done.tiles[0].depth, vec![f32::INFINITY; 8]);
        assert_eq!(done.tiles[0].shading.len(), 8);
        assert_eq!(c.canvas_pixels(), 0, "the frames still pending (3..=8) have no canvas");
    }

    /// Node `a`'s compositor of its one 4x2 tile `t`, with the pixels of `b`, in `form`.
    fn two_nodes(form: PixelForm) -> Compositor {
        Compositor::new("a", ["a", "b"].map(String::from), vec![("t".into(), 4, 2)], SECOND, form)
    }

    #[test]
    fn frames_before_any_announce_are_bounded_and_dropped_when_far_ahead() {
        let mut c = two_nodes(PixelForm::Colour);
        for id in [u64::MAX, u64::MAX - 1, 1 << 40].into_iter().chain(0..100) {
            c.peer(T, "b", 1, empty(id, "b")).unwrap();
        }
        // The oldest go first: the three far-future frames and 87..=99 are kept.
        assert_eq!(c.pending(), MAX_PENDING_FRAMES);
        c.announce(95);
        assert_eq!(c.pending(), MAX_PENDING_FRAMES - 3, "the far-future frames went at the announce");
        assert_eq!(c.dropped(), 103 - (MAX_PENDING_FRAMES as u64 - 3));
        assert!(matches!(c.peer(T, "b", 1, empty(u64::MAX, "b")), Err(CompositeError::FarAhead { .. })));
    }

    #[test]
    fn rectangles_are_capped_by_the_senders_footprint_before_anything_is_decompressed() {
        let mut c = Compositor::new(
            "a",
            ["a", "b", "c"].map(String::from),
            vec![("t".into(), 4, 2)],
            SECOND,
            PixelForm::Colour,
        );
        let corner = TileRect { x: 0, y: 0, width: 2, height: 2 };
        let fp: Footprints =
            [("b".to_string(), vec![("t".to_string(), corner)]), ("c".to_string(), vec![])].into();
        assert!(c.expect(T, 1, fp.clone()).is_empty());
        let inside = layer(0, 0, 2, 2, |_, _| (1.0, 10)).encode("t", true);
        // 200 rectangles: refused on their number (at most one per brick and tile).
        let bomb = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![inside.clone(); 200] };
        let e = c.peer(T, "b", 1, bomb).unwrap_err();
        assert!(matches!(e, CompositeError::TooManyRects { got: 200, max: 3, .. }), "{e}");
        let two = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![inside.clone(); 2] };
        assert!(matches!(c.peer(T, "b", 1, two), Err(CompositeError::TooManyRects { got: 2, max: 1, .. })));
        // A rectangle larger than the footprint, and one of its size elsewhere in the tile.
        let whole = PeerPixels {
            frame_id: 1,
            node: "b".into(),
            rects: vec![layer(0, 0, 4, 2, |_, _| (1.0, 1)).encode("t", true)],
        };
        let e = c.peer(T, "b", 1, whole).unwrap_err();
        assert!(matches!(e, CompositeError::TooManyBytes { got: 56, max: 28, .. }), "{e}");
        let moved = PeerPixels {
            frame_id: 1,
            node: "b".into(),
            rects: vec![layer(2, 0, 2, 2, |_, _| (1.0, 1)).encode("t", true)],
        };
        let e = c.peer(T, "b", 1, moved).unwrap_err();
        assert!(matches!(e, CompositeError::OutsideFootprint { x: 2, .. }), "{e}");
        assert!(e.to_string().contains("node `b`"), "{e}");
        // c's bricks cover none of this node's tiles: any rectangle is too many.
        let from_c = PeerPixels { frame_id: 1, node: "c".into(), rects: vec![inside.clone()] };
        assert!(matches!(c.peer(T, "c", 1, from_c), Err(CompositeError::TooManyRects { max: 0, .. })));
        // An LZ4 payload claiming 1 GiB: refused on its header, nothing allocated.
        let mut huge = inside.clone();
        huge.payload[..4].copy_from_slice(&(1u32 << 30).to_le_bytes());
        let e =
            c.peer(T, "b", 1, PeerPixels { frame_id: 1, node: "b".into(), rects: vec![huge] }).unwrap_err();
        assert!(e.to_string().contains("claims to decompress to 1073741824 bytes"), "{e}");
        // None of that counted: the good message still completes the frame.
        assert_eq!(c.peer(T, "c", 1, empty(1, "c")).unwrap(), None);
        let good = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![inside.clone()] };
        assert_eq!(c.peer(T, "b", 1, good).unwrap(), None);
        let done = c.local(T, 1, &[], [0, 0, 0]).expect("all in");
        assert_eq!(done.missing, Vec::<String>::new());
        assert_eq!(done.tiles[0].rgb8[0], 10);
        // Pixels before their frame starts wait compressed; at the start the footprint refuses
        // them (the peer counts as not received).
        let early = PeerPixels {
            frame_id: 2,
            node: "b".into(),
            rects: vec![layer(2, 0, 2, 2, |_, _| (1.0, 1)).encode("t", true)],
        };
        // They came on link 7; the peer reconnects meanwhile (link 8): the refusal names link 7.
        assert_eq!(c.peer(T, "b", 7, early).unwrap(), None);
        let errors = c.expect(T, 2, fp);
        assert!(
            matches!(
                errors[..],
                [Refused { link: 7, error: CompositeError::OutsideFootprint { frame_id: 2, .. } }]
            ),
            "{errors:?}"
        );
        c.peer(T, "c", 1, empty(2, "c")).unwrap();
        assert_eq!(c.local(T, 2, &[], [0, 0, 0]), None, "b's refused pixels do not count");
    }

    #[test]
    fn a_frame_composites_what_arrived_by_its_deadline_names_the_missing_and_goes_on() {
        let mut c = Compositor::new(
            "a",
            ["a", "b", "c"].map(String::from),
            vec![("t".into(), 4, 2)],
            SECOND,
            PixelForm::Colour,
        );
        let near = layer(0, 0, 2, 2, |_, _| (1.0, 10));
        let t0 = ms(5000);
        c.announce(1);
        c.expect(t0, 1, whole(&[("b", 1), ("c", 1)]));
        assert_eq!(c.local(t0 + ms(20), 1, &[], [7, 7, 7]), None);
        let b1 = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![near.encode("t", true)] };
        assert_eq!(c.peer(t0 + ms(30), "b", 1, b1).unwrap(), None);
        // c is silent: the frame waits until its deadline, then composites without c.
        assert_eq!(c.poll_timeout(), Some(t0 + SECOND));
        assert!(c.handle_timeout(t0 + ms(999)).is_empty());
        let done = c.handle_timeout(t0 + SECOND);
        assert_eq!(done.len(), 1);
        assert_eq!(done[0].missing, vec!["c".to_string()]);
        assert_eq!(done[0].tiles[0].rgb8[..6], [10, 10, 10, 10, 10, 10]);
        assert_eq!(c.poll_timeout(), None);
        // c missed a deadline: frame 2 does not wait for it (still named).
        let t1 = t0 + ms(1100);
        c.announce(2);
        c.expect(t1, 2, whole(&[("b", 1), ("c", 1)]));
        c.peer(t1 + ms(5), "b", 1, empty(2, "b")).unwrap();
        let done = c.local(t1 + ms(10), 2, &[], [7, 7, 7]).expect("c is not waited for");
        assert_eq!(done.missing, vec!["c".to_string()]);
        // c's late pixels of frame 1 arrive: it is alive, frame 3 waits for it again.
        assert_eq!(c.peer(t1 + ms(20), "c", 1, empty(1, "c")).unwrap(), None);
        assert!(c.late().is_empty());
        let t2 = t1 + ms(100);
        c.announce(3);
        c.expect(t2, 3, whole(&[("b", 1), ("c", 1)]));
        c.peer(t2, "b", 1, empty(3, "b")).unwrap();
        assert_eq!(c.local(t2 + ms(10), 3, &[], [7, 7, 7]), None);
        let done = c.peer(t2 + ms(400), "c", 1, empty(3, "c")).unwrap().expect("c in time");
        assert!(done.missing.is_empty());
        // A frame whose own render is done after its deadline composites at once.
        c.announce(4);
        c.expect(t2 + ms(500), 4, whole(&[("b", 1), ("c", 1)]));
        let done = c.local(t2 + ms(1600), 4, &[], [7, 7, 7]).expect("due");
        assert_eq!(done.missing, vec!["b".to_string(), "c".to_string()]);
    }

    #[test]
    fn a_frame_waits_only_for_the_nodes_its_map_names_and_stops_waiting_for_the_dead() {
        let mut c = Compositor::new(
            "a",
            ["a", "b", "c"].map(String::from),
            vec![("t".into(), 4, 2)],
            SECOND,
            PixelForm::Colour,
        );
        let near = layer(0, 0, 2, 2, |_, _| (1.0, 10));
        let far = layer(0, 0, 4, 2, |_, _| (2.0, 20));
        // Frame 1 by the home map: a waits for b and c; c dies: b's pixels do not complete it.
        assert_eq!(c.local(T, 1, &[], [0, 0, 0]), None);
        let b1 = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![far.encode("t", true)] };
        assert_eq!(c.peer(T, "b", 1, b1).unwrap(), None);
        // The map that leaves c without bricks ends the wait: frame 1 completes without c.
        let done = c.forget(T, &["c".to_string()]);
        assert_eq!(done.len(), 1);
        assert_eq!(done[0].frame_id, 1);
        assert!(done[0].tiles[0].rgb8.chunks(3).all(|p| p[0] == 20));
        // Frame 2: b holds c's brick too (two rectangles of the same tile in one message); the map
        // names only b (c, and names that are no peers, are not waited for).
        c.expect(T, 2, whole(&[("b", 2), ("a", 1), ("zz", 1)]));
        let b2 = PeerPixels {
            frame_id: 2,
            node: "b".into(),
            rects: vec![far.encode("t", false), near.encode("t", true)],
        };
        assert_eq!(c.peer(T, "b", 1, b2).unwrap(), None);
        let done = c.local(T, 2, &[], [0, 0, 0]).expect("only b was expected");
        let colours: Vec<u8> = done.tiles[0].rgb8.chunks(3).map(|p| p[0]).collect();
        assert_eq!(colours, vec![10, 10, 20, 20, 10, 10, 20, 20]);
        // Frame 3 expects c again (it came back): b alone does not complete it.
        c.expect(T, 3, whole(&[("b", 1), ("c", 1)]));
        c.peer(T, "b", 1, PeerPixels { frame_id: 3, node: "b".into(), rects: vec![] }).unwrap();
        assert_eq!(c.local(T, 3, &[], [0, 0, 0]), None);
        assert!(c
            .peer(T, "c", 1, PeerPixels { frame_id: 3, node: "c".into(), rects: vec![] })
            .unwrap()
            .is_some());
        // Stale frames are not revived by expect.
        c.expect(T, 2, whole(&[("b", 1)]));
        assert_eq!(c.pending(), 0);
    }
}
