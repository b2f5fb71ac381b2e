//! Object space compositing by direct send (DESIGN.md "Distribution"), sans-IO.
//!
//! Each frame, every node renders its brick over the covered rectangle of every tile
//! (`bricks::covered_window`) and sends each tile's rectangles to the node that shows the tile:
//! one [`PeerPixels`] per frame per peer (empty where its brick covers none of the peer's tiles,
//! so the peer knows it is done). A rectangle's pixels travel planar: the depth of every pixel
//! (f32 little-endian, distance along the ray, `+inf` where the brick has no hit), then their
//! colours (8-bit sRGB), each plane compressing well; with [`PixelEncoding::Lz4`] the whole is
//! LZ4-compressed (block format, lossless). The tile owner's [`Compositor`] keeps, per pixel,
//! the nearest hit of all bricks (its own included); pixels no brick hits show the background.
//! When its own render and every other node's pixels for a frame are in, the frame's tiles are
//! done (then Ready and the swap as in screen space).
//!
//! Everything a peer sends is checked before use: the tile must be the receiver's, the rectangle
//! inside it, the payload exactly the rectangle's size (decompressed into a buffer of exactly that
//! size, so a bomb cannot grow it), the sender the node its certificate names, one message per
//! frame per peer. A violation is a [`CompositeError`]: the caller closes that peer's connection.

use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};

/// Bytes per pixel before compression: depth (f32) and sRGB (3 x u8).
pub const BYTES_PER_PIXEL: usize = 7;
/// Frames a compositor holds at once (pixels of later frames can arrive before this node's
/// render of an earlier one); more is a misbehaving peer.
pub const MAX_PENDING_FRAMES: usize = 8;

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

/// A rectangle of a brick's render of one tile, decoded: position in the tile, the depth of each
/// pixel (`+inf`: no hit) and its 8-bit sRGB colour, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct Layer {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
    pub depth: Vec<f32>,
    pub rgb8: Vec<u8>,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CompositeError {
    #[error("node `{peer}` sent pixels for tile `{tile}`, which `{node}` does not show")]
    NotMyTile { peer: String, node: String, tile: String },
    #[error("node `{peer}` sent a {w}x{h} rectangle at ({x}, {y}) outside tile `{tile}` ({tw}x{th})")]
    OutsideTile { peer: String, tile: String, x: u32, y: u32, w: u32, h: u32, tw: u32, th: u32 },
    #[error("node `{peer}` sent a rectangle of tile `{tile}` whose {encoding:?} payload is not its {want} bytes: {why}")]
    BadPayload { peer: String, tile: String, encoding: PixelEncoding, want: usize, why: String },
    #[error("the connection of node `{cert}` carried pixels signed as node `{claimed}`")]
    WrongSender { cert: String, claimed: String },
    #[error("node `{peer}` is not a node of this wall, or is this node")]
    UnknownPeer { peer: String },
    #[error("node `{peer}` sent pixels for frame {frame_id} twice")]
    Twice { peer: String, frame_id: u64 },
    #[error("node `{peer}` sent pixels for frame {frame_id} while {pending} frames are pending (at most {MAX_PENDING_FRAMES})")]
    TooManyFrames { peer: String, frame_id: u64, pending: usize },
}

impl Layer {
    /// A layer of `width x height` pixels at (x, y) of a tile: no hits, colour 0.
    pub fn empty(x: u32, y: u32, width: u32, height: u32) -> Layer {
        let n = width as usize * height as usize;
        Layer { x, y, width, height, depth: vec![f32::INFINITY; n], rgb8: vec![0; n * 3] }
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
        let mut raw = Vec::with_capacity(self.pixel_count() * BYTES_PER_PIXEL);
        for d in &self.depth {
            raw.extend_from_slice(&d.to_le_bytes());
        }
        raw.extend_from_slice(&self.rgb8);
        let (encoding, payload) = if compress {
            let c = lz4_flex::block::compress(&raw);
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
    /// Decodes the rectangle of a tile of `tile_size`, checking everything (module notes).
    pub fn decode(&self, peer: &str, tile_size: (u32, u32)) -> Result<Layer, CompositeError> {
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
        let n = self.width as usize * self.height as usize;
        let want = n * BYTES_PER_PIXEL;
        let bad = |why: String| CompositeError::BadPayload {
            peer: peer.to_string(),
            tile: self.tile.clone(),
            encoding: self.encoding,
            want,
            why,
        };
        let raw = match self.encoding {
            PixelEncoding::Raw => {
                if self.payload.len() != want {
                    return Err(bad(format!("it has {} bytes", self.payload.len())));
                }
                std::borrow::Cow::Borrowed(&self.payload[..])
            }
            PixelEncoding::Lz4 => {
                let mut out = vec![0u8; want];
                let got = lz4_flex::block::decompress_into(&self.payload, &mut out)
                    .map_err(|e| bad(format!("it does not decompress: {e}")))?;
                if got != want {
                    return Err(bad(format!("it decompresses to {got} bytes")));
                }
                std::borrow::Cow::Owned(out)
            }
        };
        let (d, c) = raw.split_at(n * 4);
        let depth: Vec<f32> =
            d.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        if let Some(i) = depth.iter().position(|v| v.is_nan() || *v < 0.0) {
            return Err(bad(format!("pixel {i} has depth {}", depth[i])));
        }
        Ok(Layer { x: self.x, y: self.y, width: self.width, height: self.height, depth, rgb8: c.to_vec() })
    }
}

/// A tile being composited: the nearest depth so far and its colour.
#[derive(Debug, Clone, PartialEq)]
pub struct TileCanvas {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub depth: Vec<f32>,
    pub rgb8: Vec<u8>,
}

impl TileCanvas {
    pub fn new(name: &str, width: u32, height: u32) -> TileCanvas {
        let n = width as usize * height as usize;
        TileCanvas {
            name: name.to_string(),
            width,
            height,
            depth: vec![f32::INFINITY; n],
            rgb8: vec![0; n * 3],
        }
    }

    /// Keeps, per pixel, the nearer of the canvas and the layer (a layer inside the tile).
    pub fn merge(&mut self, l: &Layer) {
        let w = l.width as usize;
        for row in 0..l.height as usize {
            let dst = (l.y as usize + row) * self.width as usize + l.x as usize;
            for i in 0..w {
                let s = row * w + i;
                if l.depth[s] < self.depth[dst + i] {
                    self.depth[dst + i] = l.depth[s];
                    self.rgb8[3 * (dst + i)..3 * (dst + i) + 3].copy_from_slice(&l.rgb8[3 * s..3 * s + 3]);
                }
            }
        }
    }

    /// Gives every pixel no brick hit the background.
    pub fn fill_background(&mut self, background: [u8; 3]) {
        for (d, c) in self.depth.iter().zip(self.rgb8.chunks_exact_mut(3)) {
            if !d.is_finite() {
                c.copy_from_slice(&background);
            }
        }
    }
}

#[derive(Debug)]
struct Pending {
    canvases: Vec<TileCanvas>,
    from: BTreeSet<String>,
    /// This node's own render is in, with the frame's background.
    local: Option<[u8; 3]>,
    /// The nodes whose pixels the frame needs, where set ([`Compositor::expect`]); all peers
    /// otherwise.
    expect: Option<BTreeSet<String>>,
}

/// A frame whose tiles are composited.
#[derive(Debug, Clone, PartialEq)]
pub struct Composited {
    pub frame_id: u64,
    pub tiles: Vec<TileCanvas>,
}

/// A tile owner's compositing state: frames waiting for this node's render or peers' pixels.
#[derive(Debug)]
pub struct Compositor {
    node: String,
    /// The nodes that send to this one: every other node of the wall.
    peers: BTreeSet<String>,
    /// This node's tiles: name and size.
    tiles: Vec<(String, u32, u32)>,
    pending: BTreeMap<u64, Pending>,
    /// The last frame done: pixels for it or older frames are stale.
    last_done: Option<u64>,
}

impl Compositor {
    pub fn new(
        node: &str,
        peers: impl IntoIterator<Item = String>,
        tiles: Vec<(String, u32, u32)>,
    ) -> Compositor {
        let peers = peers.into_iter().filter(|p| p != node).collect();
        Compositor { node: node.to_string(), peers, tiles, pending: BTreeMap::new(), last_done: None }
    }

    /// The nodes this one waits for each frame.
    pub fn peers(&self) -> &BTreeSet<String> {
        &self.peers
    }

    fn frame(&mut self, frame_id: u64) -> &mut Pending {
        let tiles = &self.tiles;
        self.pending.entry(frame_id).or_insert_with(|| Pending {
            canvases: tiles.iter().map(|(n, w, h)| TileCanvas::new(n, *w, *h)).collect(),
            from: BTreeSet::new(),
            local: None,
            expect: None,
        })
    }

    fn stale(&self, frame_id: u64) -> bool {
        self.last_done.is_some_and(|d| frame_id <= d)
    }

    /// This node's own layers of `frame_id` (tile name, layer), and the background for pixels no
    /// brick hits. Layers for tiles this node does not show are ignored (they go to peers).
    pub fn local(
        &mut self,
        frame_id: u64,
        layers: &[(String, Layer)],
        background: [u8; 3],
    ) -> Option<Composited> {
        if self.stale(frame_id) {
            return None;
        }
        let p = self.frame(frame_id);
        for (tile, layer) in layers {
            if let Some(c) = p.canvases.iter_mut().find(|c| &c.name == tile) {
                c.merge(layer);
            }
        }
        p.local = Some(background);
        self.poll(frame_id)
    }

    /// The nodes whose pixels `frame_id` needs (object space after a node died: the nodes that
    /// hold bricks in the frame's map, `crate::adoption`); other peers are not waited for. This
    /// node and names that are not peers are left out.
    pub fn expect(&mut self, frame_id: u64, nodes: impl IntoIterator<Item = String>) {
        if self.stale(frame_id) {
            return;
        }
        let want = nodes.into_iter().filter(|n| self.peers.contains(n)).collect();
        self.frame(frame_id).expect = Some(want);
    }

    /// `gone` render nothing any more (down): pending frames stop waiting for them. Returns the
    /// frames that this completes, oldest first (each drops the older ones, as always).
    pub fn forget(&mut self, gone: &[String]) -> Vec<Composited> {
        let ids: Vec<u64> = self.pending.keys().copied().collect();
        for p in self.pending.values_mut() {
            let want = p.expect.get_or_insert_with(|| self.peers.clone());
            want.retain(|n| !gone.contains(n));
        }
        ids.into_iter().filter_map(|id| self.poll(id)).collect()
    }

    /// A peer's pixels, from the connection whose certificate names `cert`.
    pub fn peer(&mut self, cert: &str, msg: PeerPixels) -> Result<Option<Composited>, CompositeError> {
        if msg.node != cert {
            return Err(CompositeError::WrongSender { cert: cert.to_string(), claimed: msg.node });
        }
        if !self.peers.contains(cert) {
            return Err(CompositeError::UnknownPeer { peer: cert.to_string() });
        }
        let id = msg.frame_id;
        if self.stale(id) {
            return Ok(None);
        }
        if !self.pending.contains_key(&id) && self.pending.len() >= MAX_PENDING_FRAMES {
            return Err(CompositeError::TooManyFrames {
                peer: cert.to_string(),
                frame_id: id,
                pending: self.pending.len(),
            });
        }
        // Decode everything before touching the frame: a bad message changes nothing.
        let mut layers = Vec::with_capacity(msg.rects.len());
        for r in &msg.rects {
            let Some(&(_, w, h)) = self.tiles.iter().find(|t| t.0 == r.tile) else {
                return Err(CompositeError::NotMyTile {
                    peer: cert.to_string(),
                    node: self.node.clone(),
                    tile: r.tile.clone(),
                });
            };
            layers.push((r.tile.clone(), r.decode(cert, (w, h))?));
        }
        let p = self.frame(id);
        if !p.from.insert(cert.to_string()) {
            return Err(CompositeError::Twice { peer: cert.to_string(), frame_id: id });
        }
        for (tile, l) in &layers {
            if let Some(c) = p.canvases.iter_mut().find(|c| &c.name == tile) {
                c.merge(l);
            }
        }
        Ok(self.poll(id))
    }

    /// The frame's tiles once everything is in; older pending frames are then dropped (they can
    /// no longer be shown).
    fn poll(&mut self, frame_id: u64) -> Option<Composited> {
        let p = self.pending.get(&frame_id)?;
        let background = p.local?;
        if !p.expect.as_ref().unwrap_or(&self.peers).iter().all(|n| p.from.contains(n)) {
            return None;
        }
        let mut p = self.pending.remove(&frame_id).expect("present");
        for c in &mut p.canvases {
            c.fill_background(background);
        }
        self.pending.retain(|&id, _| id > frame_id);
        self.last_done = Some(frame_id);
        Some(Composited { frame_id, tiles: p.canvases })
    }

    /// Forgets every frame: a new controller session numbers its frames afresh.
    pub fn reset(&mut self) {
        self.pending.clear();
        self.last_done = None;
    }

    /// Frames waiting.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer(x: u32, y: u32, w: u32, h: u32, f: impl Fn(u32, u32) -> (f32, u8)) -> Layer {
        let mut l = Layer::empty(x, y, w, h);
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
            assert_eq!(r.decode("p", (50, 40)).unwrap(), l);
        }
        let (raw, lz) = (l.encode("t", false).payload.len(), l.encode("t", true).payload.len());
        assert_eq!(raw, 40 * 30 * BYTES_PER_PIXEL);
        assert!(lz * 3 < raw, "lz4 {lz} raw {raw}");
    }

    #[test]
    fn bad_rects_are_errors_never_panics() {
        let l = layer(0, 0, 8, 8, |_, _| (1.0, 1));
        let good = l.encode("t", true);
        let mut r = good.clone();
        r.x = 60;
        assert!(matches!(r.decode("p", (64, 64)), Err(CompositeError::OutsideTile { .. })));
        let mut r = good.clone();
        r.width = u32::MAX;
        assert!(matches!(r.decode("p", (64, 64)), Err(CompositeError::OutsideTile { .. })));
        let mut r = good.clone();
        r.payload.truncate(r.payload.len() / 2);
        assert!(matches!(r.decode("p", (64, 64)), Err(CompositeError::BadPayload { .. })));
        let mut r = l.encode("t", false);
        r.payload.push(0);
        assert!(r.decode("p", (64, 64)).unwrap_err().to_string().contains("449 bytes"));
        // A small payload that claims to decompress to far more than the rectangle.
        let bomb = l.encode("t", false);
        let mut r = layer(0, 0, 8, 8, |_, _| (1.0, 1)).encode("t", true);
        r.payload = lz4_flex::block::compress(&vec![0u8; 1 << 20]);
        assert!(matches!(r.decode("p", (64, 64)), Err(CompositeError::BadPayload { .. })));
        let mut r = bomb;
        r.payload[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(r.decode("p", (64, 64)).unwrap_err().to_string().contains("depth NaN"));
    }

    #[test]
    fn the_owner_keeps_the_nearest_hit_and_waits_for_every_peer() {
        let mut c = Compositor::new("a", ["a", "b", "c"].map(String::from), vec![("t".into(), 4, 2)]);
        let near = layer(0, 0, 2, 2, |_, _| (1.0, 10));
        let far = layer(1, 0, 3, 2, |_, _| (2.0, 20));
        let miss = layer(0, 0, 4, 1, |_, _| (f32::INFINITY, 99));
        assert_eq!(c.local(1, &[("t".into(), far.clone())], [7, 7, 7]), None);
        let from_b = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![near.encode("t", true)] };
        assert_eq!(c.peer("b", from_b.clone()).unwrap(), None);
        assert_eq!(c.peer("b", from_b.clone()), Err(CompositeError::Twice { peer: "b".into(), frame_id: 1 }));
        let from_c = PeerPixels { frame_id: 1, node: "c".into(), rects: vec![miss.encode("t", false)] };
        let done = c.peer("c", from_c).unwrap().expect("all in");
        let t = &done.tiles[0];
        // Row 0: near, near, far, far; row 1 the same.
        let colours: Vec<u8> = t.rgb8.chunks(3).map(|p| p[0]).collect();
        assert_eq!(colours, vec![10, 10, 20, 20, 10, 10, 20, 20]);
        assert_eq!(t.depth[0], 1.0);
        // Stale pixels are ignored; the wrong sender, an unknown peer and other tiles are errors.
        assert_eq!(c.peer("b", from_b).unwrap(), None);
        let e = c.peer("c", PeerPixels { frame_id: 2, node: "b".into(), rects: vec![] }).unwrap_err();
        assert!(matches!(e, CompositeError::WrongSender { .. }));
        let e = c.peer("z", PeerPixels { frame_id: 2, node: "z".into(), rects: vec![] }).unwrap_err();
        assert!(matches!(e, CompositeError::UnknownPeer { .. }));
        let e =
            c.peer("b", PeerPixels { frame_id: 2, node: "b".into(), rects: vec![near.encode("u", false)] });
        assert!(matches!(e, Err(CompositeError::NotMyTile { .. })));
        // Uncovered pixels get the background; frames can complete before an older one, which is dropped.
        c.peer("b", PeerPixels { frame_id: 3, node: "b".into(), rects: vec![] }).unwrap();
        c.peer("c", PeerPixels { frame_id: 3, node: "c".into(), rects: vec![] }).unwrap();
        c.peer("b", PeerPixels { frame_id: 2, node: "b".into(), rects: vec![] }).unwrap();
        let done = c.local(3, &[], [5, 6, 7]).expect("frame 3");
        assert!(done.tiles[0].rgb8.chunks(3).all(|p| p == [5, 6, 7]));
        assert_eq!(c.pending(), 0);
        // A flood of future frames is refused.
        for id in 10..10 + MAX_PENDING_FRAMES as u64 {
            c.peer("b", PeerPixels { frame_id: id, node: "b".into(), rects: vec![] }).unwrap();
        }
        let e = c.peer("b", PeerPixels { frame_id: 99, node: "b".into(), rects: vec![] }).unwrap_err();
        assert!(matches!(e, CompositeError::TooManyFrames { .. }));
    }

    #[test]
    fn a_frame_waits_only_for_the_nodes_its_map_names_and_stops_waiting_for_the_dead() {
        let mut c = Compositor::new("a", ["a", "b", "c"].map(String::from), vec![("t".into(), 4, 2)]);
        let near = layer(0, 0, 2, 2, |_, _| (1.0, 10));
        let far = layer(0, 0, 4, 2, |_, _| (2.0, 20));
        // Frame 1 by the home map: a waits for b and c; c dies: b's pixels do not complete it.
        assert_eq!(c.local(1, &[], [0, 0, 0]), None);
        let b1 = PeerPixels { frame_id: 1, node: "b".into(), rects: vec![far.encode("t", true)] };
        assert_eq!(c.peer("b", b1).unwrap(), None);
        // The map that leaves c without bricks ends the wait: frame 1 completes without c.
        let done = c.forget(&["c".to_string()]);
        assert_eq!(done.len(), 1);
        assert_eq!(done[0].frame_id, 1);
        assert!(done[0].tiles[0].rgb8.chunks(3).all(|p| p[0] == 20));
        // Frame 2: b holds c's brick too (two rectangles of the same tile in one message); the map
        // names only b (c, and names that are no peers, are not waited for).
        c.expect(2, ["b".to_string(), "a".to_string(), "zz".to_string()]);
        let b2 = PeerPixels {
            frame_id: 2,
            node: "b".into(),
            rects: vec![far.encode("t", false), near.encode("t", true)],
        };
        assert_eq!(c.peer("b", b2).unwrap(), None);
        let done = c.local(2, &[], [0, 0, 0]).expect("only b was expected");
        let colours: Vec<u8> = done.tiles[0].rgb8.chunks(3).map(|p| p[0]).collect();
        assert_eq!(colours, vec![10, 10, 20, 20, 10, 10, 20, 20]);
        // Frame 3 expects c again (it came back): b alone does not complete it.
        c.expect(3, ["b".to_string(), "c".to_string()]);
        c.peer("b", PeerPixels { frame_id: 3, node: "b".into(), rects: vec![] }).unwrap();
        assert_eq!(c.local(3, &[], [0, 0, 0]), None);
        assert!(c.peer("c", PeerPixels { frame_id: 3, node: "c".into(), rects: vec![] }).unwrap().is_some());
        // Stale frames are not revived by expect.
        c.expect(2, ["b".to_string()]);
        assert_eq!(c.pending(), 0);
    }
}
