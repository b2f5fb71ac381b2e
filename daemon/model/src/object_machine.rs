//! A wall node in object space, sans-IO: [`ObjectMachine`], beside the frame machine
//! ([`crate::node_machine::NodeMachine`]) of an object-space node. `now` is the daemon's own
//! clock (a [`Duration`] since any fixed epoch), as for the frame machine.
//!
//! Each frame the caller
//! - tells it of every frame state as it arrives ([`ObjectMachine::announce`]: peers' pixels may
//!   come for frames up to [`crate::composite::FRAMES_AHEAD`] past it);
//! - asks, when the frame machine says render, for the views to render
//!   ([`ObjectMachine::views`]: the covered rectangle of every wall tile (its canvas) for each
//!   brick the frame's brick map gives this node, and the adopted bricks to drop first); the
//!   frame starts waiting for its peers then, each within its *footprint* (the rectangles its
//!   bricks may cover in this node's tiles, by the same map and camera) and until the
//!   compositing deadline;
//! - hands it the rendered rectangles ([`ObjectMachine::local_done`]): it encodes each tile's
//!   rectangles for the node that shows the tile ([`ObjectOutput::SendPixels`], one message per
//!   peer per frame, empty where its bricks cover none of the peer's tiles) and composites its
//!   own;
//! - hands it every peer's pixels ([`ObjectMachine::peer`]), and calls
//!   [`ObjectMachine::handle_timeout`] at [`ObjectMachine::poll_timeout`];
//! - carries out the outputs: [`ObjectOutput::Composited`] (send [`ObjectMachine::report`] to
//!   the controller, then the frame is rendered for the frame machine), [`ObjectOutput::ClosePeer`]
//!   (a peer broke the rules: close the connection that carried it with the reason, nothing
//!   else stops), [`ObjectOutput::Dropped`] (a duplicate: log it, close nothing),
//!   [`ObjectOutput::Send`], [`ObjectOutput::Load`] (read a brick adopted from a dead node, then
//!   [`ObjectMachine::load_done`]), [`ObjectOutput::Reconnect`] (a node back from the dead:
//!   send to it on a new connection).
//!
//! A wall whose composited tiles are filtered (built with a guard band, `filter_guard`) sends
//! its pixels in the shading form ([`PixelForm::Shading`], `crate::composite`) and handles every
//! tile as its *canvas*: the tile's rectangle grown by the guard band within the wall's image
//! ([`Rect::grown`], [`ObjectMachine::canvas_rect`]). The views a brick renders cover its part of
//! the canvas (the guard band included), rectangles and footprints are placed in the canvas, and
//! a tile is composited over its whole canvas; the caller filters and composes it there and
//! crops the tile out of it. Without a guard, the colour form over the tiles themselves.
//!
//! The controller's brick maps ([`ObjectMachine::set_map`], `crate::adoption`) say which node
//! renders each brick from which frame on; frames are rendered, sent and composited by the map
//! for their frame id, so every node agrees. An adopted brick is dropped at the first frame whose
//! map gives it to another node; the node's own brick is never dropped.

use crate::adoption::{brick_index, AdoptionError, BrickMap, MapHistory};
use crate::bricks;
use crate::codec;
use crate::composite::{
    composite_deadline, CompositeError, Composited, Compositor, Footprints, Layer, Link, PeerPixels,
    PixelForm, Refused, TileCanvas, TileRect,
};
use crate::config::{TileConfig, WallConfig};
use crate::messages::Message;
use crate::render_plan::RenderPlan;
use crate::render_state::srgb8;
use crate::wire::{Continuity, FrameSpec};
use crate::{AoMethod, AoRadius, Camera, Rect, RenderSettings, View};
use glam::DVec3;
use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

/// Frames whose records (rectangles rendered, timings) are kept.
const FRAMES_KEPT: u64 = 16;

/// What every node computes at start-up from the volume (`bricks::split`): the owned box (world)
/// of every brick, which is this node's, its volume bytes, and the halo it was read with.
#[derive(Debug, Clone, PartialEq)]
pub struct BrickGeometry {
    /// Brick i's owned box (min, max), world units; brick i is the i-th node's home brick.
    pub owned: Vec<(DVec3, DVec3)>,
    pub own: usize,
    /// The volume bytes of this node's brick and halo.
    pub own_bytes: u64,
    pub spacing: DVec3,
    pub halo: [usize; 3],
}

/// A frame's views ([`ObjectMachine::views`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameViews {
    pub views: Vec<(String, View)>,
    /// The brick of each view.
    pub bricks: Vec<usize>,
    /// Adopted bricks to drop before rendering (the map gives them to another node).
    pub unload: Vec<usize>,
    /// Bricks the map gives this node that it has not loaded (left out).
    pub not_loaded: Vec<usize>,
}

/// A frame's start in object space ([`ObjectMachine::plan`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectPlan {
    /// What to render.
    pub plan: RenderPlan,
    /// Adopted bricks to drop before rendering (the map gives them to another node).
    pub unload: Vec<usize>,
    /// Bricks the map gives this node that it has not loaded (left out).
    pub not_loaded: Vec<usize>,
    /// Why the settings were bounded by the halo, when the reason is new.
    pub warning: Option<String>,
    /// Carry these out (pixels that came early and broke the rules).
    pub outputs: Vec<ObjectOutput>,
}

/// What the caller must do.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq)]
pub enum ObjectOutput {
    /// Send these bytes (one `PeerPixels`) to `peer`, on a stream of their own.
    SendPixels { peer: String, frame_id: u64, bytes: Vec<u8> },
    /// The frame's tiles are composited: send [`ObjectMachine::report`] to the controller; the
    /// frame is then rendered as far as the frame machine is concerned.
    Composited(Composited),
    /// A peer broke the rules: close the connection `link` (the one that carried what broke
    /// them, [`crate::composite::Link`]) with this reason.
    ClosePeer { peer: String, link: Link, reason: String },
    /// A peer's message was dropped (a second one for a frame: it changes nothing, and may come
    /// on another connection of the same certificate): log the reason, close nothing.
    Dropped { peer: String, reason: String },
    /// Send this to the controller.
    Send(Message),
    /// Read brick `index` (wire number `brick`) and its halo, upload it beside the node's own,
    /// then call [`ObjectMachine::load_done`].
    Load { brick: u64, index: usize },
    /// `peer` holds bricks again after a map without it: it is back from the dead, a new process.
    /// Send to it on a new connection: one to the process before may not have timed out yet,
    /// and what is sent on it is lost.
    Reconnect { peer: String },
}

/// Per frame: when this node's render finished, the bytes it sent its peers, its render time.
#[derive(Debug, Clone, Copy)]
struct LocalDone {
    at: Duration,
    sent: u64,
    render: Duration,
}

/// A node's object-space state (module notes).
#[derive(Debug)]
pub struct ObjectMachine {
    name: String,
    config: WallConfig,
    geometry: BrickGeometry,
    /// The bricks loaded (this node's own, and any adopted) and their volume bytes.
    held: BTreeMap<usize, u64>,
    maps: MapHistory,
    /// Adoptions under way (LoadBrick received, not answered).
    loading: BTreeSet<u64>,
    /// Why this node adopts no brick, where it cannot ([`ObjectMachine::refuse_adoptions`]).
    adoptions_refused: Option<String>,
    compositor: Compositor,
    /// The other nodes that show tiles: each gets one message per frame.
    receivers: Vec<String>,
    /// Per frame rendered: the covered rectangle of each view, by tile.
    submitted: BTreeMap<u64, Vec<(String, Rect)>>,
    local: BTreeMap<u64, LocalDone>,
    /// Per frame: time spent encoding, decoding and merging pixels ([`ObjectMachine::add_work`]).
    work: BTreeMap<u64, Duration>,
    compress: bool,
    background: [u8; 3],
    warned: Option<String>,
    /// The guard band every tile's canvas grows by (`None`: the tile itself, the colour form).
    guard: Option<u32>,
}

impl ObjectMachine {
    /// Node `name` of `config` (an object-space wall), with the brick split of start-up.
    /// `filter_guard`: `None` for a wall that shows its composite as it is (the colour form, the
    /// tiles themselves); `Some(g)` for one that filters its composited tiles (the shading form,
    /// every tile's canvas grown by `g` pixels: module notes). The whole wall must agree on it.
    pub fn new(
        config: &WallConfig,
        name: &str,
        geometry: BrickGeometry,
        filter_guard: Option<u32>,
    ) -> ObjectMachine {
        let tiles: Vec<(String, u32, u32)> = config
            .tiles_of(name)
            .iter()
            .map(|t| {
                let c = canvas_of(config, filter_guard, t);
                (t.name.clone(), c.width, c.height)
            })
            .collect();
        let form = if filter_guard.is_some() { PixelForm::Shading } else { PixelForm::Colour };
        let nodes: Vec<String> = config.nodes.iter().map(|n| n.name.clone()).collect();
        let receivers =
            nodes.iter().filter(|n| n.as_str() != name && !config.tiles_of(n).is_empty()).cloned().collect();
        let deadline = composite_deadline(Duration::from_millis(config.wall.deadline_ms));
        ObjectMachine {
            name: name.to_string(),
            config: config.clone(),
            held: [(geometry.own, geometry.own_bytes)].into(),
            geometry,
            maps: MapHistory::new(nodes.clone()),
            loading: BTreeSet::new(),
            adoptions_refused: None,
            compositor: Compositor::new(name, nodes, tiles, deadline, form),
            receivers,
            submitted: BTreeMap::new(),
            local: BTreeMap::new(),
            work: BTreeMap::new(),
            compress: config.wall.compress,
            background: [0; 3],
            warned: None,
            guard: filter_guard,
        }
    }

    /// What this wall's pixels carry between nodes: the shading form where it filters its
    /// composited tiles (a guard band), else the colour form.
    pub fn form(&self) -> PixelForm {
        self.compositor.form()
    }

    /// The rectangle (in the wall image's pixels) that `tile` is rendered and composited over:
    /// the tile grown by the guard band within the wall's image, or the tile's own rectangle
    /// without one. Composited canvases are this size, rows top to bottom from its top-left.
    pub fn canvas_rect(&self, tile: &str) -> Option<Rect> {
        Some(canvas_of(&self.config, self.guard, self.config.tile(tile)?))
    }

    /// The view of `tile`'s canvas ([`ObjectMachine::canvas_rect`]) by `camera`.
    fn canvas_view(&self, camera: Camera, tile: &str) -> Option<View> {
        let view = self.config.tile_view(camera, tile)?;
        Some(View { rect: self.canvas_rect(tile)?, ..view })
    }

    /// The wall's config the machine was made with.
    pub fn config(&self) -> &WallConfig {
        &self.config
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// The other nodes that show tiles (this node sends each one message per frame).
    pub fn receivers(&self) -> &[String] {
        &self.receivers
    }

    /// The volume bytes this node holds (its brick and any adopted).
    pub fn resident_bytes(&self) -> u64 {
        self.held.values().sum()
    }

    /// Peers not waited for (they missed a deadline and have sent nothing since).
    pub fn late_peers(&self) -> &BTreeSet<String> {
        self.compositor.late()
    }

    /// The compositor (for its counts).
    pub fn compositor(&self) -> &Compositor {
        &self.compositor
    }

    /// The most bytes one peer's pixels for one frame may take on the wire: raw rectangles (LZ4
    /// is used only where smaller, in this wall's form) of every tile's canvas of this node, once
    /// per brick of the wall, and their framing. A stream longer than this is refused unread.
    pub fn max_pixels_bytes(&self) -> usize {
        let tiles = self.config.tiles_of(&self.name);
        let pixels: usize = tiles
            .iter()
            .filter_map(|t| self.canvas_rect(&t.name))
            .map(|c| c.width as usize * c.height as usize)
            .sum();
        let bricks = self.geometry.owned.len().max(1);
        let per_rect = 64 + tiles.iter().map(|t| t.name.len()).max().unwrap_or(0);
        bricks * (pixels * self.form().bytes_per_pixel() + tiles.len() * per_rect) + 256
    }

    /// A new controller session: its frame ids start afresh.
    pub fn reset(&mut self) {
        self.compositor.reset();
        self.maps.reset();
        self.submitted.clear();
        self.local.clear();
        self.work.clear();
    }

    /// A frame state arrived (before the frame machine handles it).
    pub fn announce(&mut self, frame_id: u64) {
        self.compositor.announce(frame_id);
    }

    /// The frame's settings within what the halo allows: an AO radius past the halo is bounded
    /// by it, `seed` AO is rendered as `ours`. Returns the warning when it is new.
    pub fn bound_settings(&mut self, s: &RenderSettings) -> (RenderSettings, Option<String>) {
        let (sp, halo) = (self.geometry.spacing, self.geometry.halo);
        let mut s = *s;
        let mut why = None;
        if s.ao.method == AoMethod::Seed {
            why = Some(bricks::BrickError::SeedMethod.to_string());
            s.ao.method = AoMethod::Ours;
        }
        if let Err(e) = bricks::check_within_halo(&s, sp, halo) {
            let step = s.step_voxels * sp.min_element();
            let offset = s.ao.offset_voxels * sp.min_element();
            let r = (0..3)
                .map(|a| (halo[a] - bricks::GRADIENT_STENCIL) as f64 * sp[a])
                .fold(f64::INFINITY, f64::min)
                - step
                - offset;
            s.ao.radius = AoRadius::World(r.max(0.0) * (1.0 - 1e-9));
            why = Some(format!("{e}; rendering with AO radius {r}"));
        }
        let new = why.filter(|w| self.warned.as_ref() != Some(w));
        if let Some(w) = &new {
            self.warned = Some(w.clone());
        }
        (s, new)
    }

    /// The rectangles `brick` may cover in each of this node's tiles (their canvases, placed
    /// from the canvas's top-left), seen by `camera`.
    fn footprint_of(&self, camera: Camera, brick: usize, out: &mut Vec<(String, TileRect)>) {
        let Some(&(lo, hi)) = self.geometry.owned.get(brick) else { return };
        for t in self.config.tiles_of(&self.name) {
            let Some(view) = self.canvas_view(camera, &t.name) else { continue };
            if let Some(w) = bricks::covered_rect(&view, lo, hi) {
                let c = view.rect;
                let rect = TileRect { x: w.x - c.x, y: w.y - c.y, width: w.width, height: w.height };
                out.push((t.name.clone(), rect));
            }
        }
    }

    /// Frame `frame_id` starts rendering at `now` (module notes): the views, and the pixels that
    /// came early and break the rules ([`ObjectOutput::ClosePeer`]). `background` is the sRGB8
    /// of pixels no brick hits.
    pub fn views(
        &mut self,
        now: Duration,
        frame_id: u64,
        camera: Camera,
        background: [u8; 3],
    ) -> (FrameViews, Vec<ObjectOutput>) {
        self.background = background;
        let map = self.maps.map_for(frame_id).clone();
        // Adopted bricks the map gives to another node (their home is back); one loaded and not
        // given to anybody yet (the adoption takes effect with a later map) stays.
        let unload: Vec<usize> = self
            .held
            .keys()
            .copied()
            .filter(|&b| {
                b != self.geometry.own
                    && map.holders.get(b).is_some_and(|h| h.as_deref().is_some_and(|n| n != self.name))
            })
            .collect();
        for b in &unload {
            self.held.remove(b);
        }
        // What each peer's bricks may cover of this node's tiles.
        let mut footprints = Footprints::new();
        for peer in map.participants().into_iter().filter(|p| *p != self.name) {
            let mut fp = Vec::new();
            for b in map.bricks_of(&peer) {
                self.footprint_of(camera, b, &mut fp);
            }
            footprints.insert(peer, fp);
        }
        let refused = self.compositor.expect(now, frame_id, footprints);
        let (mut views, mut bricks) = (Vec::new(), Vec::new());
        let (mine, not_loaded): (Vec<usize>, Vec<usize>) =
            map.bricks_of(&self.name).into_iter().partition(|b| self.held.contains_key(b));
        for b in mine {
            let (lo, hi) = self.geometry.owned[b];
            for t in &self.config.tiles {
                let Some(tile_view) = self.canvas_view(camera, &t.name) else { continue };
                if let Some(w) = bricks::covered_rect(&tile_view, lo, hi) {
                    views.push((t.name.clone(), View { rect: w, ..tile_view }));
                    bricks.push(b);
                }
            }
        }
        self.submitted.insert(frame_id, views.iter().map(|(n, v)| (n.clone(), v.rect)).collect());
        self.submitted.retain(|&id, _| id.saturating_add(FRAMES_KEPT) > frame_id);
        (FrameViews { views, bricks, unload, not_loaded }, refused.into_iter().map(refused_output).collect())
    }

    /// Frame `spec` starts rendering at `now` ([`crate::render_plan`]): the node's bricks over
    /// the rectangles they cover, with the settings bounded by the halo, at scale 1 (tiles are
    /// composited by full-resolution depth), the pixels read back in the wall's form; and what
    /// goes with it ([`ObjectPlan`]).
    pub fn plan(
        &mut self,
        now: Duration,
        spec: &FrameSpec,
        accumulate_frame: u32,
        continuity: Continuity,
    ) -> ObjectPlan {
        let (settings, warning) = self.bound_settings(&spec.settings);
        // As the renderer writes a miss: the colour in f32, then 8-bit sRGB.
        let background = settings.background.map(|c| srgb8(f64::from(c as f32)));
        let (v, outputs) = self.views(now, spec.frame_id, spec.camera, background);
        let plan = RenderPlan {
            frame_id: spec.frame_id,
            views: v.views,
            bricks: v.bricks,
            settings,
            scale: 1,
            accumulate_frame,
            continuity,
            time_step: spec.time_step,
            share: Some(self.form()),
        };
        ObjectPlan { plan, unload: v.unload, not_loaded: v.not_loaded, warning, outputs }
    }

    /// A brick map from the controller (`Message::Bricks`): frames from `from_frame` on follow
    /// it; pending frames stop waiting for nodes it leaves without bricks (those it completes
    /// are returned). An invalid map is the controller's protocol error.
    pub fn set_map(
        &mut self,
        now: Duration,
        from_frame: u64,
        holders: Vec<Option<String>>,
    ) -> Result<(BrickMap, Vec<ObjectOutput>), AdoptionError> {
        let map = BrickMap::from_wire(from_frame, holders, self.maps.nodes())?;
        // Nodes that hold bricks again (back from the dead) are waited for again.
        let (before, after) = (self.maps.latest().participants(), map.participants());
        let back: Vec<String> = after.difference(&before).cloned().collect();
        self.compositor.wait_again(&back);
        let mut out = reconnect_back(&before, &after, &self.name);
        let gone = self.maps.set(map.clone());
        let done = self.compositor.forget(now, &gone);
        out.extend(done.into_iter().map(ObjectOutput::Composited));
        Ok((map, out))
    }

    /// `LoadBrick`: load the brick beside this node's own ([`ObjectOutput::Load`], answered by
    /// [`ObjectMachine::load_done`]); one already held is answered at once, one that does not
    /// exist is refused.
    pub fn load(&mut self, brick: u64) -> Vec<ObjectOutput> {
        let index = match brick_index(brick, self.geometry.owned.len()) {
            Ok(i) => i,
            Err(e) => return vec![ObjectOutput::Send(Message::BrickFailed { brick, reason: e.to_string() })],
        };
        if self.held.contains_key(&index) {
            let resident_bytes = self.resident_bytes();
            return vec![ObjectOutput::Send(Message::BrickLoaded { brick, load_us: 0, resident_bytes })];
        }
        if let Some(reason) = &self.adoptions_refused {
            return vec![ObjectOutput::Send(Message::BrickFailed { brick, reason: reason.clone() })];
        }
        if self.loading.insert(brick) {
            vec![ObjectOutput::Load { brick, index }]
        } else {
            Vec::new()
        }
    }

    /// From now on every `LoadBrick` of a brick this node does not hold is answered
    /// `BrickFailed` with `reason` (a node that cannot adopt, e.g. one whose volume has time
    /// steps: the adopter would have to load the brick of every step).
    pub fn refuse_adoptions(&mut self, reason: String) {
        self.adoptions_refused = Some(reason);
    }

    /// An adoption's outcome (the brick's volume bytes, or why not) after `took`: the answer
    /// for the controller.
    pub fn load_done(&mut self, brick: u64, result: Result<u64, String>, took: Duration) -> Message {
        self.loading.remove(&brick);
        let index = brick_index(brick, self.geometry.owned.len());
        match (result, index) {
            (Ok(bytes), Ok(index)) => {
                self.held.insert(index, bytes);
                let load_us = u64::try_from(took.as_micros()).unwrap_or(u64::MAX);
                Message::BrickLoaded { brick, load_us, resident_bytes: self.resident_bytes() }
            }
            (Err(reason), _) => Message::BrickFailed { brick, reason },
            (_, Err(e)) => Message::BrickFailed { brick, reason: e.to_string() },
        }
    }

    /// This node's render of `frame_id` is done at `now`, after `render`: `rendered` holds each
    /// view of [`ObjectMachine::views`], in order (named by its tile, the view rectangle's size,
    /// rows top to bottom, in this wall's form: depth and sRGB8 colour, or depth and AOVs).
    /// Returns each peer's pixels to send, and the frame when nothing else is awaited. A
    /// rendered rectangle of the other form, or whose data is not its size, is a caller's error
    /// and is left out.
    pub fn local_done(
        &mut self,
        now: Duration,
        frame_id: u64,
        render: Duration,
        rendered: Vec<TileCanvas>,
    ) -> Vec<ObjectOutput> {
        let rects = self.submitted.remove(&frame_id).unwrap_or_default();
        // Layers by tile owner; rectangles without a hit carry nothing the owner needs.
        let mut by_owner: BTreeMap<String, Vec<(String, Layer)>> = BTreeMap::new();
        let form = self.form();
        for (r, (tile, w)) in rendered.into_iter().zip(&rects) {
            debug_assert_eq!(&r.name, tile);
            let (Some(c), Some(owner)) = (self.canvas_rect(tile), self.config.node_of_tile(tile)) else {
                continue;
            };
            let n = r.width as usize * r.height as usize;
            let fits = match form {
                PixelForm::Colour => r.rgb8.len() == 3 * n,
                PixelForm::Shading => r.shading.len() == n,
            };
            debug_assert!(r.form == form && fits && r.depth.len() == n, "tile `{tile}`: a bad render");
            if r.form != form || !fits || r.depth.len() != n {
                continue;
            }
            let layer = Layer {
                x: w.x - c.x,
                y: w.y - c.y,
                width: r.width,
                height: r.height,
                form,
                depth: r.depth,
                rgb8: r.rgb8,
                shading: r.shading,
            };
            if layer.any_hit() {
                by_owner.entry(owner.name.clone()).or_default().push((tile.clone(), layer));
            }
        }
        let mine = by_owner.remove(&self.name).unwrap_or_default();
        let mut out = Vec::new();
        let mut sent = 0u64;
        // The nodes that take part in the frame (a dead node's tiles get nothing).
        let participants = self.maps.map_for(frame_id).participants();
        for peer in self.receivers.iter().filter(|p| participants.contains(*p)) {
            let layers = by_owner.remove(peer).unwrap_or_default();
            let rects = layers.iter().map(|(t, l)| l.encode(t, self.compress)).collect();
            let msg = PeerPixels { frame_id, node: self.name.clone(), rects };
            // Encoding cannot fail for these types; a failure sends nothing (the peer's deadline
            // covers it).
            if let Ok(bytes) = codec::encode_pixels(&msg) {
                sent += bytes.len() as u64;
                out.push(ObjectOutput::SendPixels { peer: peer.clone(), frame_id, bytes });
            }
        }
        // Compositing time runs from here: this node's render is done (encoding included).
        self.local.insert(frame_id, LocalDone { at: now, sent, render });
        self.local.retain(|&k, _| k.saturating_add(FRAMES_KEPT) > frame_id);
        let done = self.compositor.local(now, frame_id, &mine, self.background);
        out.extend(self.compositor.take_refused().into_iter().map(refused_output));
        out.extend(done.map(ObjectOutput::Composited));
        out
    }

    /// This node's render time of `frame_id` (zero when unknown).
    pub fn render_time(&self, frame_id: u64) -> Duration {
        self.local.get(&frame_id).map_or(Duration::ZERO, |l| l.render)
    }

    /// A peer's pixels, from the connection `link` whose certificate names `cert`.
    pub fn peer(&mut self, now: Duration, cert: &str, link: Link, pixels: PeerPixels) -> Vec<ObjectOutput> {
        match self.compositor.peer(now, cert, link, pixels) {
            Ok(done) => done.map(ObjectOutput::Composited).into_iter().collect(),
            Err(e) => vec![refused_output(Refused { link, error: e })],
        }
    }

    /// When [`ObjectMachine::handle_timeout`] must be called next.
    pub fn poll_timeout(&self) -> Option<Duration> {
        self.compositor.poll_timeout()
    }

    /// Frames whose compositing deadline has passed: composited with what arrived.
    pub fn handle_timeout(&mut self, now: Duration) -> Vec<ObjectOutput> {
        self.compositor.handle_timeout(now).into_iter().map(ObjectOutput::Composited).collect()
    }

    /// Time the caller spent on a frame's pixels (encoding, decoding, merging: the calls above).
    /// Only frames this node rendered count (a peer's frame id can be anything).
    pub fn add_work(&mut self, frame_id: u64, work: Duration) {
        if !self.local.contains_key(&frame_id) && !self.submitted.contains_key(&frame_id) {
            return;
        }
        *self.work.entry(frame_id).or_default() += work;
        self.work.retain(|&k, _| k.saturating_add(FRAMES_KEPT) > frame_id);
    }

    /// The controller's `Composited` for a composited frame at `now`: bytes sent to peers,
    /// compositing time (this node's render done to now), work, resident volume bytes, and the
    /// peers whose pixels it went without.
    pub fn report(&self, now: Duration, done: &Composited) -> Message {
        let us = |d: Duration| u64::try_from(d.as_micros()).unwrap_or(u64::MAX);
        let local = self.local.get(&done.frame_id);
        Message::Composited {
            frame_id: done.frame_id,
            bytes_sent: local.map_or(0, |l| l.sent),
            composite_us: local.map_or(0, |l| us(now.saturating_sub(l.at))),
            merge_us: us(self.work.get(&done.frame_id).copied().unwrap_or_default()),
            resident_bytes: self.resident_bytes(),
            missing: done.missing.clone(),
        }
    }
}

/// The rectangle of the wall's image `tile` is composited over with a guard band of `guard`
/// ([`ObjectMachine::canvas_rect`]).
fn canvas_of(config: &WallConfig, guard: Option<u32>, tile: &TileConfig) -> Rect {
    match guard {
        Some(g) => tile.rect().grown(g, config.wall_size()),
        None => tile.rect(),
    }
}

/// The peers that take part in `after` and did not in `before`, each back from the dead (a new
/// process): [`ObjectOutput::Reconnect`] each, `own` excepted. The rule object space's brick maps
/// and the balanced screen space's splits share.
pub(crate) fn reconnect_back(
    before: &BTreeSet<String>,
    after: &BTreeSet<String>,
    own: &str,
) -> Vec<ObjectOutput> {
    after
        .difference(before)
        .filter(|peer| *peer != own)
        .map(|peer| ObjectOutput::Reconnect { peer: peer.clone() })
        .collect()
}

/// What to do about refused pixels: drop a duplicate, close the link that carried the rest.
pub(crate) fn refused_output(Refused { link, error: e }: Refused) -> ObjectOutput {
    let peer = match &e {
        CompositeError::WrongSender { cert, .. } => cert.clone(),
        CompositeError::NotMyTile { peer, .. }
        | CompositeError::OutsideTile { peer, .. }
        | CompositeError::BadPayload { peer, .. }
        | CompositeError::UnknownPeer { peer }
        | CompositeError::Twice { peer, .. }
        | CompositeError::FarAhead { peer, .. }
        | CompositeError::TooManyRects { peer, .. }
        | CompositeError::TooManyBytes { peer, .. }
        | CompositeError::OutsideFootprint { peer, .. } => peer.clone(),
    };
    match e {
        CompositeError::Twice { .. } => ObjectOutput::Dropped { peer, reason: e.to_string() },
        _ => ObjectOutput::ClosePeer { peer, link, reason: e.to_string() },
    }
}
