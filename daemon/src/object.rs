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
//! - a node dies ([`isowall_wall::adoption`] has the rules): the controller sends a brick map
//!   (`Message::Bricks`) that gives its brick to nobody, and each node's pending frames stop waiting
//!   for it ([`ObjectNode::set_map`]); the survivor it chose gets `LoadBrick` and reads that brick
//!   and halo with the same partial read as at start-up ([`read_brick`], from the [`BrickPlan`]
//!   kept since start-up) on a blocking task, the render thread uploads it as a second volume
//!   between frames ([`spawn_load`]), and the node answers `BrickLoaded`; from the next map on it
//!   renders both bricks over every tile (one view per brick and tile) and sends their rectangles
//!   together. Frames are rendered, sent and composited by the map for their frame id, so every
//!   node agrees. An adopted brick is dropped (its GPU volume freed) at the first frame whose map
//!   gives it to another node (its home came back); the node's own brick is never dropped.
//!   `--adopt-delay-ms` (hidden) delays the read, so tests can watch frames run while it loads.

use crate::tiles::{JobResult, TileResult};
use anyhow::{anyhow, Context, Result};
use isowall_net::transport;
use isowall_net::Identity;
use isowall_render::gpu::ObjectSpace;
use isowall_volume::io::RawSpec;
use isowall_volume::region::VolumeStream;
use isowall_volume::{BlockMinMax, Volume, VolumeInfo, VolumeSource, VoxelRange};
use isowall_wall::adoption::{AdoptionError, BrickMap, MapHistory};
use isowall_wall::bricks::{self, Brick, Occupancy};
use isowall_wall::codec;
use isowall_wall::composite::{Composited, Compositor, Layer, PeerPixels};
use isowall_wall::config::WallConfig;
use isowall_wall::messages::Message;
use isowall_wall::{AoMethod, AoRadius, Camera, RenderSettings, View};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What the render thread uploads in object space.
pub struct BrickData {
    /// The brick's index in the split (= its home node's index in `[[nodes]]`).
    pub index: usize,
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
    pub plan: Arc<BrickPlan>,
}

/// What start-up computed, kept to read any brick later (one adopted from a dead node).
pub struct BrickPlan {
    pub source: VolumeSource,
    pub raw: Option<RawSpec>,
    pub info: VolumeInfo,
    /// The whole volume's block grid (every brick's GPU volume gets it).
    pub blocks: BlockMinMax,
    pub split: Vec<Brick>,
    pub halo: [usize; 3],
}

/// Reads brick `index` and its halo: the partial read of start-up, from `stream` (or the plan's
/// source opened again).
pub fn read_brick(plan: &BrickPlan, index: usize, stream: Option<&VolumeStream>) -> Result<BrickData> {
    let start = Instant::now();
    let source = &plan.source;
    let opened;
    let stream = match stream {
        Some(s) => s,
        None => {
            opened =
                source.stream(plan.raw.as_ref()).with_context(|| format!("cannot open volume {source}"))?;
            &opened
        }
    };
    let info = &plan.info;
    let brick = plan.split.get(index).ok_or_else(|| anyhow!("no brick {index} in the split"))?;
    let (lo, hi) = brick.data_range(plan.halo, info.dims);
    let region =
        stream.read_region(&VoxelRange { lo, hi }).with_context(|| format!("cannot read volume {source}"))?;
    let (owned_min, owned_max) = brick.owned_planes(info.dims, info.origin, info.spacing);
    tracing::info!(
        volume = %source,
        brick = index,
        bricks = plan.split.len(),
        owned = ?(brick.lo, brick.hi),
        halo = ?plan.halo,
        data = ?(lo, hi),
        occupied_blocks = brick.occupied_blocks,
        resident_volume_bytes = region.resident_bytes(),
        block_grid_bytes = plan.blocks.minmax.len() * 8,
        whole_volume_bytes = info.dims.iter().product::<usize>() * 4,
        partial_reads = stream.partial(),
        ms = start.elapsed().as_secs_f64() * 1e3,
        "object space: brick ready"
    );
    Ok(BrickData {
        index,
        region,
        info: info.clone(),
        blocks: plan.blocks.clone(),
        object: ObjectSpace { data_offset: lo, owned_min, owned_max },
    })
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
    let plan = Arc::new(BrickPlan { source, raw: raw.cloned(), info, blocks, split, halo });
    let data = read_brick(&plan, index, Some(&stream));
    bricking.finish();
    let data = data?;
    tracing::debug!(ms = start.elapsed().as_secs_f64() * 1e3, "object space: set-up done");
    Ok(BrickSetup { data, brick, halo, plan })
}

/// An adoption's outcome ([`spawn_load`]): the brick, its owned box and bytes, or why not.
pub struct LoadDone {
    pub brick: u64,
    pub result: Result<(usize, (glam::DVec3, glam::DVec3), u64), String>,
    pub took: Duration,
}

/// Loads brick `brick` beside the node's own (module notes): reads it on a blocking task, then
/// has the render thread upload it after the jobs already queued; the outcome goes to `done`.
pub fn spawn_load(
    plan: Arc<BrickPlan>,
    brick: u64,
    renderer: crate::tiles::RenderHandle,
    done: tokio::sync::mpsc::UnboundedSender<LoadDone>,
    delay: Duration,
) {
    tokio::spawn(async move {
        tokio::time::sleep(delay).await;
        // The load time reported leaves out the injected delay.
        let t0 = Instant::now();
        let result = async {
            let index = isowall_wall::adoption::brick_index(brick, plan.split.len())?;
            let p = plan.clone();
            let data = tokio::task::spawn_blocking(move || read_brick(&p, index, None))
                .await
                .map_err(|e| anyhow!("the reading task failed: {e}"))??;
            let bytes = data.region.resident_bytes() as u64;
            let owned = plan.split[index].owned_box(plan.info.origin, plan.info.spacing);
            renderer.load(data).await?;
            Ok::<_, anyhow::Error>((index, owned, bytes))
        }
        .await
        .map_err(|e| format!("{e:#}"));
        let _ = done.send(LoadDone { brick, result, took: t0.elapsed() });
    });
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
    /// The bricks loaded (this node's own, and any adopted): owned box (world), volume bytes.
    held: std::collections::BTreeMap<usize, ((glam::DVec3, glam::DVec3), u64)>,
    /// This node's own brick (never dropped).
    own: usize,
    plan: Arc<BrickPlan>,
    /// The brick maps by the frame each starts at.
    maps: MapHistory,
    /// Adoptions under way (LoadBrick received, not answered).
    loading: std::collections::BTreeSet<u64>,
    load_tx: tokio::sync::mpsc::UnboundedSender<LoadDone>,
    /// Fault injection (`--adopt-delay-ms`): a wait before reading an adopted brick.
    pub adopt_delay: Duration,
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
    /// The node's object-space state; adoptions' outcomes go to `load_tx` (the session hands them
    /// to [`ObjectNode::load_done`]).
    pub fn new(
        config: &WallConfig,
        name: &str,
        setup: &BrickSetup,
        load_tx: tokio::sync::mpsc::UnboundedSender<LoadDone>,
    ) -> Result<ObjectNode> {
        let info = &setup.data.info;
        let owned = setup.brick.owned_box(info.origin, info.spacing);
        let own = setup.data.index;
        let resident = setup.data.region.resident_bytes() as u64;
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
            held: [(own, (owned, resident))].into(),
            own,
            plan: setup.plan.clone(),
            maps: MapHistory::new(config.nodes.iter().map(|n| n.name.clone()).collect()),
            loading: Default::default(),
            load_tx,
            adopt_delay: Duration::ZERO,
            spacing: info.spacing,
            halo: setup.halo,
            resident_bytes: resident,
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
        self.maps.reset();
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

    /// The views this node renders for a frame: the covered window of every wall tile for each
    /// brick the frame's map gives it (its own; adopted ones), with the brick of each view, and
    /// the adopted bricks to drop first (the map no longer gives them to this node).
    pub fn views(&mut self, frame_id: u64, camera: Camera, settings: &RenderSettings) -> FrameViews {
        self.background = srgb8_of(settings.background);
        let map = self.maps.map_for(frame_id).clone();
        let mine = map.bricks_of(&self.name);
        // Adopted bricks the map gives to another node (their home is back); one loaded and not
        // given to anybody yet (the adoption takes effect with a later map) stays.
        let unload: Vec<usize> = self
            .held
            .keys()
            .copied()
            .filter(|&b| {
                b != self.own
                    && map.holders.get(b).is_some_and(|h| h.as_deref().is_some_and(|n| n != self.name))
            })
            .collect();
        for b in &unload {
            self.held.remove(b);
            tracing::info!(frame_id, brick = b, "object space: dropping adopted brick (its home is back)");
        }
        self.resident_bytes = self.held.values().map(|h| h.1).sum();
        self.compositor.expect(frame_id, map.participants());
        let (mut views, mut bricks) = (Vec::new(), Vec::new());
        for b in mine {
            let Some(&(owned, _)) = self.held.get(&b) else {
                tracing::error!(
                    frame_id,
                    brick = b,
                    "object space: the map gives this node a brick it has not loaded"
                );
                continue;
            };
            for t in &self.config.tiles {
                let Some(tile_view) = self.config.tile_view(camera, &t.name) else { continue };
                if let Some(w) = bricks::covered_window(&tile_view, owned.0, owned.1) {
                    views.push((t.name.clone(), View { window: w, ..tile_view }));
                    bricks.push(b);
                }
            }
        }
        self.submitted.insert(frame_id, views.iter().map(|(n, v)| (n.clone(), v.window)).collect());
        // Keep only recent frames' windows.
        self.submitted.retain(|&id, _| id + 16 > frame_id);
        FrameViews { views, bricks, unload }
    }

    /// A brick map from the controller (`Message::Bricks`): frames from `from_frame` on follow
    /// it; pending frames stop waiting for nodes it leaves without bricks, and those it completes
    /// are returned. An invalid map is the controller's protocol error.
    pub fn set_map(
        &mut self,
        from_frame: u64,
        holders: Vec<Option<String>>,
    ) -> Result<Vec<JobResult>, AdoptionError> {
        let map = BrickMap::from_wire(from_frame, holders, self.maps.nodes())?;
        tracing::info!(from_frame, holders = ?map.holders, "object space: brick map");
        let gone = self.maps.set(map);
        let done = self.compositor.forget(&gone);
        Ok(done.into_iter().map(|c| self.finish(c)).collect())
    }

    /// `LoadBrick`: starts loading the brick beside this node's own (an answer comes through
    /// [`ObjectNode::load_done`]); one already loaded is answered at once.
    pub fn load(&mut self, brick: u64, renderer: &crate::tiles::RenderHandle) {
        let held = usize::try_from(brick).ok().and_then(|b| self.held.get(&b).map(|h| (b, *h)));
        if let Some((b, (owned, bytes))) = held {
            let _ =
                self.load_tx.send(LoadDone { brick, result: Ok((b, owned, bytes)), took: Duration::ZERO });
        } else if self.loading.insert(brick) {
            tracing::info!(brick, "object space: adopting a brick: loading it");
            spawn_load(self.plan.clone(), brick, renderer.clone(), self.load_tx.clone(), self.adopt_delay);
        }
    }

    /// An adoption's outcome: the answer for the controller.
    pub fn load_done(&mut self, done: LoadDone) -> Message {
        self.loading.remove(&done.brick);
        match done.result {
            Ok((b, owned, bytes)) => {
                self.held.insert(b, (owned, bytes));
                let resident: u64 = self.held.values().map(|h| h.1).sum();
                tracing::info!(
                    brick = b,
                    ms = done.took.as_secs_f64() * 1e3,
                    resident_volume_bytes = resident,
                    "object space: adopted brick loaded"
                );
                Message::BrickLoaded {
                    brick: done.brick,
                    load_us: done.took.as_micros() as u64,
                    resident_bytes: resident,
                }
            }
            Err(reason) => {
                tracing::warn!(brick = done.brick, "object space: cannot adopt the brick: {reason}");
                Message::BrickFailed { brick: done.brick, reason }
            }
        }
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
        // The nodes that take part in the frame (a dead node's tiles get nothing).
        let participants = self.maps.map_for(id).participants();
        for peer in
            self.outbox.addrs.keys().filter(|p| participants.contains(*p)).cloned().collect::<Vec<_>>()
        {
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

/// A frame's views ([`ObjectNode::views`]).
pub struct FrameViews {
    pub views: Vec<(String, View)>,
    /// The brick of each view.
    pub bricks: Vec<usize>,
    /// Adopted bricks to drop before rendering.
    pub unload: Vec<usize>,
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
