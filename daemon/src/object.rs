//! Object space on a wall node (`[wall] mode = "object"`; the model is `isowall_wall::bricks` and
//! `isowall_wall::composite`):
//!
//! - set-up ([`load_brick`]): a streaming pass over the volume gives the block min/max of the whole
//!   (one z-slice resident at a time), every node computes the same split from it at the config's
//!   iso, and this node reads only its brick and halo ([`isowall_volume::region`] says how each
//!   format is read). Resident afterwards: the brick and halo as f32 plus the whole volume's block
//!   grid (8 bytes per block); both are logged and the voxel bytes reported to the controller.
//! - each frame ([`ObjectNode::views`]): the brick is rendered over its covered window of every tile
//!   of the wall; ([`ObjectNode::local_done`]) each tile's rectangle goes to the node that shows it
//!   (direct send: one QUIC stream per frame per peer, node-to-node with mutual TLS, every node
//!   that shows tiles receiving from every other node, empty when nothing is covered), the node's own
//!   rectangles go to its [`Compositor`]; ([`ObjectNode::peer`]) peers' pixels arrive the same way.
//!   When a frame's tiles are composited the session reports Composited (bytes sent, compositing
//!   time, resident bytes) and Ready, and swaps as in screen space.
//! - a frame whose AO radius exceeds the halo (the config's radius sized it) is rendered with the
//!   radius bounded by the halo, and `seed` AO with `ours`, with a warning (the config check refuses
//!   both up front).
//!
//! Not done: a node that is down leaves its peers' tiles incomplete (they wait and straggle) rather
//! than its brick being taken over by the others.

use crate::tiles::{JobResult, TileResult};
use anyhow::{anyhow, Context, Result};
use isowall_net::transport;
use isowall_net::Identity;
use isowall_render::gpu::ObjectSpace;
use isowall_volume::io::RawSpec;
use isowall_volume::{BlockMinMax, Volume, VolumeInfo, VolumeSource, VoxelRange};
use isowall_wall::bricks::{self, Brick, Occupancy};
use isowall_wall::codec;
use isowall_wall::composite::{Composited, Compositor, Layer, PeerPixels};
use isowall_wall::config::WallConfig;
use isowall_wall::{AoMethod, AoRadius, Camera, RenderSettings, View};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What the render thread uploads in object space.
pub struct BrickData {
    pub region: Volume,
    pub info: VolumeInfo,
    pub blocks: BlockMinMax,
    pub object: ObjectSpace,
}

/// This node's brick, as set up.
pub struct BrickSetup {
    pub data: BrickData,
    pub brick: Brick,
    pub halo: [usize; 3],
}

/// Reads this node's brick and halo (module notes). `iso` is the config's (or the volume's
/// natural) iso value; `None`: the middle of the data range, from the block grid.
pub fn load_brick(config: &WallConfig, node: &str, raw: Option<&RawSpec>) -> Result<BrickSetup> {
    let start = Instant::now();
    let source: VolumeSource = config.volume_source().parse()?;
    let bricking = Arc::new(crate::progress::Bricking::new(node, &source.to_string()));
    let observer = bricking.clone();
    let stream = source
        .stream(raw)
        .with_context(|| format!("cannot open volume {source}"))?
        .on_progress(move |p| observer.report(p));
    let info = stream.info().clone();
    let blocks = stream
        .block_minmax(BlockMinMax::DEFAULT_BLOCK)
        .with_context(|| format!("cannot read volume {source}"))?;
    let iso = config.volume.iso.or(source.natural_iso()).unwrap_or_else(|| {
        let lo = blocks.minmax.iter().map(|m| m[0]).fold(f32::INFINITY, f32::min);
        let hi = blocks.minmax.iter().map(|m| m[1]).fold(f32::NEG_INFINITY, f32::max);
        0.5 * (lo as f64 + hi as f64)
    });
    let occ = Occupancy::from_minmax(blocks.block, blocks.counts, &blocks.minmax, iso);
    let n = config.nodes.len();
    let index = config
        .nodes
        .iter()
        .position(|x| x.name == node)
        .ok_or_else(|| anyhow!("no node '{node}' in the wall config"))?;
    let split = bricks::split(&occ, info.dims, info.spacing, n).map_err(|e| anyhow!("{source}: {e}"))?;
    let settings = config.render_settings(iso);
    let halo = bricks::halo_voxels(&settings, info.spacing).map_err(|e| anyhow!("[render] {e}"))?;
    let brick = split[index].clone();
    let (lo, hi) = brick.data_range(halo, info.dims);
    let region = stream.read_region(&VoxelRange { lo, hi });
    bricking.finish();
    let region = region.with_context(|| format!("cannot read volume {source}"))?;
    let (owned_min, owned_max) = brick.owned_planes(info.dims, info.origin, info.spacing);
    let whole_bytes = info.dims.iter().product::<usize>() * 4;
    tracing::info!(
        volume = %source,
        brick = index,
        bricks = n,
        owned = ?(brick.lo, brick.hi),
        halo = ?halo,
        data = ?(lo, hi),
        occupied_blocks = brick.occupied_blocks,
        resident_volume_bytes = region.resident_bytes(),
        block_grid_bytes = blocks.minmax.len() * 8,
        whole_volume_bytes = whole_bytes,
        partial_reads = stream.partial(),
        ms = start.elapsed().as_secs_f64() * 1e3,
        "object space: brick ready"
    );
    Ok(BrickSetup {
        data: BrickData {
            region,
            info,
            blocks,
            object: ObjectSpace { data_offset: lo, owned_min, owned_max },
        },
        brick,
        halo,
    })
}

/// A peer's pixels as they arrive, with the connection they came on (closed on a violation).
pub struct PeerItem {
    pub cert: String,
    pub connection: quinn::Connection,
    pub pixels: PeerPixels,
}

/// The node's object-space state: its brick's geometry, the compositor of its tiles, the
/// outgoing connections to its peers.
pub struct ObjectNode {
    name: String,
    config: WallConfig,
    /// The brick's owned box (world) and the volume's spacing.
    owned: (glam::DVec3, glam::DVec3),
    spacing: glam::DVec3,
    halo: [usize; 3],
    pub resident_bytes: u64,
    compositor: Compositor,
    /// Per frame submitted: the covered window of each tile rendered, by tile.
    submitted: HashMap<u64, Vec<(String, isowall_wall::Window)>>,
    outbox: Outbox,
    compress: bool,
    /// Per frame: when this node's render finished, the bytes it sent, its render time.
    local: HashMap<u64, (Instant, u64, Duration)>,
    /// Per frame: time spent encoding, decoding and merging pixels.
    work: HashMap<u64, Duration>,
    background: [u8; 3],
    warned: Option<String>,
}

impl ObjectNode {
    pub fn new(config: &WallConfig, name: &str, setup: &BrickSetup) -> Result<ObjectNode> {
        let info = &setup.data.info;
        let owned = setup.brick.owned_box(info.origin, info.spacing);
        let tiles: Vec<(String, u32, u32)> =
            config.tiles_of(name).iter().map(|t| (t.name.clone(), t.width, t.height)).collect();
        let peers = config.nodes.iter().map(|n| n.name.clone());
        let mut addrs = HashMap::new();
        for n in &config.nodes {
            if n.name != name && !config.tiles_of(&n.name).is_empty() {
                addrs.insert(n.name.clone(), transport::resolve(&n.address)?);
            }
        }
        Ok(ObjectNode {
            name: name.to_string(),
            config: config.clone(),
            owned,
            spacing: info.spacing,
            halo: setup.halo,
            resident_bytes: setup.data.region.resident_bytes() as u64,
            compositor: Compositor::new(name, peers, tiles),
            submitted: HashMap::new(),
            outbox: Outbox { endpoint: None, addrs, conns: Arc::new(Mutex::new(HashMap::new())) },
            compress: config.wall.compress,
            local: HashMap::new(),
            work: HashMap::new(),
            background: [0; 3],
            warned: None,
        })
    }

    /// A new controller session: its frame ids start afresh.
    pub fn reset(&mut self) {
        self.compositor.reset();
        self.submitted.clear();
        self.local.clear();
        self.work.clear();
    }

    /// Opens the endpoint this node connects to its peers from (inside the async runtime).
    pub fn open_endpoint(&mut self, identity: &Identity) -> Result<()> {
        self.outbox.endpoint = Some(transport::client(identity)?);
        Ok(())
    }

    /// The frame's settings within what the halo allows (module notes).
    pub fn bound_settings(&mut self, frame_id: u64, s: &RenderSettings) -> RenderSettings {
        let mut s = *s;
        let mut why = None;
        if s.ao.method == AoMethod::Seed {
            why = Some(bricks::BrickError::SeedMethod.to_string());
            s.ao.method = AoMethod::Ours;
        }
        if let Err(e) = bricks::check_within_halo(&s, self.spacing, self.halo) {
            let sp = self.spacing;
            let step = s.step_voxels * sp.min_element();
            let offset = s.ao.offset_voxels * sp.min_element();
            let r = (0..3)
                .map(|a| (self.halo[a] - bricks::GRADIENT_STENCIL) as f64 * sp[a])
                .fold(f64::INFINITY, f64::min)
                - step
                - offset;
            s.ao.radius = AoRadius::World(r.max(0.0) * (1.0 - 1e-9));
            why = Some(format!("{e}; rendering with AO radius {r}"));
        }
        if let Some(w) = why {
            if self.warned.as_deref() != Some(&w) {
                tracing::warn!(frame_id, "object space: {w}");
                self.warned = Some(w);
            }
        }
        s
    }

    /// The views this node renders for a frame: its brick's covered window of every wall tile.
    pub fn views(&mut self, frame_id: u64, camera: Camera, settings: &RenderSettings) -> Vec<(String, View)> {
        self.background = srgb8_of(settings.background);
        let mut views = Vec::new();
        for t in &self.config.tiles {
            let Some(tile_view) = self.config.tile_view(camera, &t.name) else { continue };
            if let Some(w) = bricks::covered_window(&tile_view, self.owned.0, self.owned.1) {
                views.push((t.name.clone(), View { window: w, ..tile_view }));
            }
        }
        self.submitted.insert(frame_id, views.iter().map(|(n, v)| (n.clone(), v.window)).collect());
        // Keep only recent frames' windows.
        self.submitted.retain(|&id, _| id + 16 > frame_id);
        views
    }

    /// This node's render of a frame is done: sends each peer its pixels, composites its own.
    /// Returns the frame's composited tiles when nothing else is awaited.
    pub fn local_done(&mut self, done: JobResult) -> Option<JobResult> {
        let id = done.frame_id;
        let t0 = Instant::now();
        let windows = self.submitted.remove(&id).unwrap_or_default();
        // Layers by tile owner.
        let mut by_owner: HashMap<String, Vec<(String, Layer)>> = HashMap::new();
        for (r, (tile, w)) in done.tiles.iter().zip(&windows) {
            debug_assert_eq!(&r.name, tile);
            let Some(t) = self.config.tile(tile) else { continue };
            let Some(owner) = self.config.node_of_tile(tile) else { continue };
            let layer = Layer {
                x: w.x - t.x,
                y: w.y - t.y,
                width: r.width,
                height: r.height,
                depth: r.depth.clone(),
                rgb8: r.rgb8.clone(),
            };
            // Rectangles without a hit carry nothing the owner needs.
            if layer.any_hit() {
                by_owner.entry(owner.name.clone()).or_default().push((tile.clone(), layer));
            }
        }
        let mine = by_owner.remove(&self.name).unwrap_or_default();
        let mut sent = 0u64;
        for peer in self.outbox.addrs.keys().cloned().collect::<Vec<_>>() {
            let layers = by_owner.remove(&peer).unwrap_or_default();
            let rects = layers.iter().map(|(t, l)| l.encode(t, self.compress)).collect();
            let msg = PeerPixels { frame_id: id, node: self.name.clone(), rects };
            match codec::encode_pixels(&msg) {
                Ok(bytes) => {
                    sent += bytes.len() as u64;
                    self.outbox.send(peer, id, bytes);
                }
                Err(e) => tracing::error!(frame_id = id, %peer, "{e}"),
            }
        }
        // Compositing time runs from here: this node's render is done (encoding included).
        self.local.insert(id, (t0, sent, done.render_time));
        self.local.retain(|&k, _| k + 16 > id);
        let c = self.compositor.local(id, &mine, self.background);
        *self.work.entry(id).or_default() += t0.elapsed();
        self.work.retain(|&k, _| k + 16 > id);
        Some(self.finish(c?))
    }

    /// A peer's pixels: the composited frame when it completes it, or the error that closes the
    /// peer's connection.
    pub fn peer(&mut self, item: PeerItem) -> Option<JobResult> {
        let (id, t0) = (item.pixels.frame_id, Instant::now());
        let r = self.compositor.peer(&item.cert, item.pixels);
        if self.work.len() < 64 {
            *self.work.entry(id).or_default() += t0.elapsed();
        }
        match r {
            Ok(Some(c)) => Some(self.finish(c)),
            Ok(None) => None,
            Err(e) => {
                tracing::warn!(peer = %item.cert, "closing the peer's connection: {e}");
                transport::close(&item.connection, &e.to_string());
                None
            }
        }
    }

    fn finish(&mut self, c: Composited) -> JobResult {
        let render_time = self.local.get(&c.frame_id).map_or(Duration::ZERO, |l| l.2);
        let tiles = c
            .tiles
            .into_iter()
            .map(|t| TileResult {
                name: t.name,
                width: t.width,
                height: t.height,
                rgb8: t.rgb8,
                depth: t.depth,
            })
            .collect();
        JobResult { frame_id: c.frame_id, tiles, render_time }
    }

    /// Bytes sent to peers for a frame, the time since this node's render of it finished, and the
    /// time spent encoding, decoding and merging its pixels.
    pub fn frame_stats(&self, frame_id: u64) -> (u64, Duration, Duration) {
        let work = self.work.get(&frame_id).copied().unwrap_or_default();
        self.local
            .get(&frame_id)
            .map_or((0, Duration::ZERO, work), |(at, sent, _)| (*sent, at.elapsed(), work))
    }
}

/// The sRGB8 of a linear background colour, as the renderer writes misses.
fn srgb8_of(c: [f64; 3]) -> [u8; 3] {
    let mut f = isowall_render::Frame::new(1, 1);
    f.color[0] = c.map(|x| x as f32);
    let v = isowall_render::output::srgb8(&f);
    [v[0], v[1], v[2]]
}

/// Outgoing connections to the peers that show tiles; one stream per frame per peer.
struct Outbox {
    endpoint: Option<quinn::Endpoint>,
    addrs: HashMap<String, SocketAddr>,
    conns: Arc<Mutex<HashMap<String, quinn::Connection>>>,
}

impl Outbox {
    fn send(&self, peer: String, frame_id: u64, bytes: Vec<u8>) {
        let Some(&addr) = self.addrs.get(&peer) else { return };
        let Some(endpoint) = self.endpoint.clone() else {
            tracing::error!(frame_id, %peer, "cannot send pixels: no client endpoint");
            return;
        };
        let conns = self.conns.clone();
        tokio::spawn(async move {
            let cached = conns.lock().expect("not poisoned").get(&peer).cloned();
            let conn = match cached.filter(|c| c.close_reason().is_none()) {
                Some(c) => c,
                None => match transport::connect(&endpoint, addr, &peer).await {
                    Ok(c) => {
                        conns.lock().expect("not poisoned").insert(peer.clone(), c.clone());
                        c
                    }
                    Err(e) => {
                        tracing::warn!(frame_id, %peer, "cannot send pixels: {e}");
                        return;
                    }
                },
            };
            let r = async {
                let mut s = conn.open_uni().await.map_err(|e| e.to_string())?;
                s.write_all(&bytes).await.map_err(|e| e.to_string())?;
                s.finish().map_err(|e| e.to_string())?;
                Ok::<(), String>(())
            }
            .await;
            if let Err(e) = r {
                tracing::warn!(frame_id, %peer, "sending pixels failed: {e}");
                conns.lock().expect("not poisoned").remove(&peer);
            }
        });
    }
}

/// Accepts peers' connections (the node's own server endpoint hands them over): each must carry
/// a wall node's certificate; every stream on it is one [`PeerPixels`], read up to `limit` bytes.
#[derive(Clone)]
pub struct Inbox {
    pub tx: tokio::sync::mpsc::Sender<PeerItem>,
    pub nodes: Vec<String>,
    pub own: String,
    pub limit: usize,
}

impl Inbox {
    /// Serves a peer's connection in its own task.
    pub fn accept(&self, conn: quinn::Connection) {
        let me = self.clone();
        tokio::spawn(async move {
            let remote = conn.remote_address();
            let Some(cert) =
                me.nodes.iter().find(|n| **n != me.own && isowall_net::tls::peer_is(&conn, n)).cloned()
            else {
                tracing::warn!(%remote, "refused a connection: its certificate is neither the controller's nor another node's");
                transport::close(&conn, "only the controller and the wall's other nodes may connect");
                return;
            };
            tracing::info!(peer = %cert, %remote, "peer connected (object space)");
            loop {
                let mut stream = match conn.accept_uni().await {
                    Ok(s) => s,
                    Err(e) => {
                        tracing::info!(peer = %cert, "peer connection ended: {e}");
                        return;
                    }
                };
                let bytes = match stream.read_to_end(me.limit).await {
                    Ok(b) => b,
                    Err(e) => {
                        let reason = format!("pixels from `{cert}`: {e} (limit {} bytes)", me.limit);
                        tracing::warn!("closing the peer's connection: {reason}");
                        transport::close(&conn, &reason);
                        return;
                    }
                };
                match codec::decode_pixels(&bytes) {
                    Ok(pixels) => {
                        let item = PeerItem { cert: cert.clone(), connection: conn.clone(), pixels };
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
