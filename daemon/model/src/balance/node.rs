//! A node of a load-balanced screen-space wall (`[wall] balance = true`), without I/O: what it
//! renders of a frame, what it sends, what it waits for, and what it reports.
//!
//! - The controller's split (`Message::Split`, from a frame on) is checked whole
//!   ([`super::share::split_from_wire`]); until one comes every node renders its own tiles.
//! - Each frame the node renders the rectangles its share names ([`NodeShare::renders`]), each
//!   as its own view: rows of a tile at the tile's full width, named by [`rect_view_name`], so a
//!   rectangle that keeps its renderer keeps its running sums and reprojection history (the
//!   render thread keeps a target per name), and one that moves starts afresh. A rectangle
//!   renders the filter's guard band around it as a tile does, so its edge pixels are filtered
//!   as the whole tile's are.
//! - Its pixels come back in the colour form. Those of other nodes' tiles go to each tile's owner
//!   in one `PeerPixels` a frame (empty where it has nothing for that owner, so the owner need
//!   not wait for its deadline); those of its own tiles are placed at once.
//! - An owner waits for exactly the rectangles its share expects, from exactly the nodes the
//!   split gave them to ([`NodeShare::expects`]): object space's [`Compositor`], whose checks
//!   (sender, tile, rectangle inside the footprint, bytes before decompression, a deadline)
//!   apply unchanged. Every rendered pixel is placed, a miss too (its depth is made finite), so
//!   the tile is the renderers' pixels exactly; a rectangle that did not come by the deadline
//!   shows the background, and the wall goes on.
//! - What each rectangle cost ([`rect_cost`]: its fetches and pixels, hardware-free) goes to the
//!   controller in `RectCosts`, and the bytes sent in `Composited`, before Ready.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use super::share::{split_from_wire, NodeShare, SplitError};
use super::{Split, WorkRect};
use crate::codec;
use crate::composite::{composite_deadline, Compositor, Layer, PeerPixels, PixelForm};
use crate::config::WallConfig;
use crate::links::Link;
use crate::messages::Message;
use crate::object_machine::{reconnect_back, refused_output, ObjectOutput};
use crate::render_plan::RenderPlan;
use crate::render_state::srgb8;
use crate::wire::{Continuity, FrameSpec, WireRectCost, WireSplit};

/// What one pixel costs in [`rect_cost`], in trilinear fetches: a pixel whose ray hits nothing
/// still costs its setup, march through empty blocks, compose and readback (on lavapipe a pixel
/// costs about what 3.4 fetches do; `docs/balance.md`).
pub const PIXEL_FETCHES: u64 = 3;

/// The splits kept besides the one in use (a frame in flight may still need an older one).
const SPLITS_KEPT: usize = 4;

/// Frames whose rectangles are remembered until they are rendered.
const FRAMES_KEPT: u64 = 16;

/// A rendered rectangle's cost, the balancer's unit: its fetches and [`PIXEL_FETCHES`] per pixel
/// rendered (at the frame's internal scale).
pub fn rect_cost(fetches: u64, pixels: u64) -> u64 {
    fetches.saturating_add(pixels.saturating_mul(PIXEL_FETCHES))
}

/// The name of the view (and render target) of rows `first_row .. first_row + rows` of `tile`.
pub fn rect_view_name(r: &WorkRect) -> String {
    format!("{}@{}+{}", r.tile, r.first_row, r.rows)
}

/// A rectangle the node rendered: by [`rect_view_name`], with its pixels in the colour form and
/// the fetches it took.
#[derive(Debug, Clone)]
pub struct RenderedRect {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub rgb8: Vec<u8>,
    /// `+inf` where the ray hit nothing.
    pub depth: Vec<f32>,
    pub fetches: u64,
}

/// Per frame this node started: its share, when its own render finished, what it sent.
#[derive(Debug, Clone, Default)]
struct Started {
    share: NodeShare,
    /// The frame's internal resolution divisor: a rectangle renders 1/scale^2 of its pixels.
    scale: u32,
    local_at: Option<Duration>,
    sent: u64,
    work: Duration,
}

/// A node's side of the balance (module docs).
#[derive(Debug)]
pub struct BalanceMachine {
    config: WallConfig,
    name: String,
    /// The controller's splits by the frame each starts with.
    splits: BTreeMap<u64, Split>,
    compositor: Compositor,
    compress: bool,
    background: [u8; 3],
    started: BTreeMap<u64, Started>,
}

impl BalanceMachine {
    /// Node `name` of `config` on a wall whose swap barrier waits `barrier_deadline`: each frame
    /// waits for its peers' rectangles until [`composite_deadline`] of it from the frame's start,
    /// so that it is still ready for the barrier.
    pub fn new(config: &WallConfig, name: &str, barrier_deadline: Duration) -> BalanceMachine {
        let deadline = composite_deadline(barrier_deadline);
        let tiles = config.tiles_of(name).iter().map(|t| (t.name.clone(), t.width, t.height)).collect();
        let peers = config.nodes.iter().map(|n| n.name.clone());
        BalanceMachine {
            config: config.clone(),
            name: name.to_string(),
            splits: BTreeMap::new(),
            compositor: Compositor::new(name, peers, tiles, deadline, PixelForm::Colour),
            compress: config.wall.compress,
            background: [0; 3],
            started: BTreeMap::new(),
        }
    }

    /// The longest `PeerPixels` a peer may send this node: all its tiles' pixels in the colour
    /// form, with room for a rectangle's header per band.
    pub fn max_pixels_bytes(&self) -> usize {
        let tiles = self.config.tiles_of(&self.name);
        let pixels: usize = tiles.iter().map(|t| t.width as usize * t.height as usize).sum();
        let per_rect = 64 + tiles.iter().map(|t| t.name.len()).max().unwrap_or(0);
        let rects = tiles.len() * super::share::MAX_RECTS_PER_TILE;
        pixels * PixelForm::Colour.bytes_per_pixel() + rects * per_rect + 256
    }

    /// The nodes whose pixels this one may receive: every other node of the wall.
    pub fn peers(&self) -> impl Iterator<Item = &String> {
        self.compositor.peers().iter()
    }

    /// A new controller session: its frame ids start afresh, and so do its splits.
    pub fn reset(&mut self) {
        self.compositor.reset();
        self.splits.clear();
        self.started.clear();
    }

    /// A frame state arrived (before the frame machine handles it).
    pub fn announce(&mut self, frame_id: u64) {
        self.compositor.announce(frame_id);
    }

    /// The controller's split from `from_frame` on, checked whole; an error is the controller's
    /// protocol violation (nothing of it is used).
    ///
    /// A node whose tiles the split before left out (it was down) and this one has again is back
    /// from the dead, a new process: [`ObjectOutput::Reconnect`] it, as object space does, since
    /// the connection to the process before may not have timed out and loses what is sent on it.
    pub fn set_split(&mut self, from_frame: u64, wire: &WireSplit) -> Result<Vec<ObjectOutput>, SplitError> {
        let split = split_from_wire(wire, &self.config)?;
        let before = self.owners(&self.split_for(from_frame.saturating_sub(1)));
        let back = reconnect_back(&before, &self.owners(&split), &self.name);
        self.splits.insert(from_frame, split);
        while self.splits.len() > SPLITS_KEPT {
            self.splits.pop_first();
        }
        Ok(back)
    }

    /// The nodes whose tiles `split` shows.
    fn owners(&self, split: &Split) -> BTreeSet<String> {
        split.rects.iter().filter_map(|r| self.config.node_of_tile(&r.tile)).map(|n| n.name.clone()).collect()
    }

    /// The split of `frame_id`: the controller's latest from that frame or before, else every
    /// node rendering its own tiles.
    pub fn split_for(&self, frame_id: u64) -> Split {
        if let Some((_, s)) = self.splits.range(..=frame_id).next_back() {
            return s.clone();
        }
        let rects = self
            .config
            .tiles
            .iter()
            .filter_map(|t| {
                let owner = self.config.node_of_tile(&t.name)?;
                Some(WorkRect {
                    tile: t.name.clone(),
                    first_row: 0,
                    rows: t.height,
                    renderer: owner.name.clone(),
                })
            })
            .collect();
        Split { rects }
    }

    /// What to render of a frame at `now`: the share's rectangles, each its own view, read back
    /// in the colour form. The frame starts waiting for the rectangles others render of this
    /// node's tiles; early pixels that break the rules come back as outputs.
    pub fn plan(
        &mut self,
        now: Duration,
        spec: &FrameSpec,
        accumulate_frame: u32,
        continuity: Continuity,
    ) -> (RenderPlan, Vec<ObjectOutput>) {
        let share = NodeShare::of(&self.split_for(spec.frame_id), &self.config, &self.name);
        let views = share
            .renders
            .iter()
            .filter_map(|r| {
                let mut view = self.config.tile_view(spec.camera, &r.tile)?;
                view.rect.y += r.first_row;
                view.rect.height = r.rows;
                Some((rect_view_name(r), view))
            })
            .collect();
        // The GPU's background is f32.
        self.background = spec.settings.background.map(|c| srgb8(f64::from(c as f32)));
        let refused = self.compositor.expect(now, spec.frame_id, share.expects.clone());
        self.started.insert(spec.frame_id, Started { share, scale: spec.scale.max(1), ..Default::default() });
        self.started.retain(|&k, _| k.saturating_add(FRAMES_KEPT) > spec.frame_id);
        let plan = RenderPlan::of_views(spec, views, accumulate_frame, continuity, Some(PixelForm::Colour));
        (plan, refused.into_iter().map(refused_output).collect())
    }

    /// This node's render of `frame_id` is done at `now`: the rectangles of other nodes' tiles go
    /// to their owners, its own are placed, and the controller's `RectCosts` is the first output.
    pub fn local_done(
        &mut self,
        now: Duration,
        frame_id: u64,
        mut rendered: Vec<RenderedRect>,
    ) -> Vec<ObjectOutput> {
        let Some(st) = self.started.get_mut(&frame_id) else { return Vec::new() };
        let mut costs = Vec::new();
        let mut mine: Vec<(String, Layer)> = Vec::new();
        let mut by_owner: BTreeMap<String, Vec<(String, Layer)>> =
            st.share.sends.keys().map(|o| (o.clone(), Vec::new())).collect();
        for rect in &st.share.renders {
            let name = rect_view_name(rect);
            let Some(r) = rendered.iter_mut().find(|r| r.name == name) else { continue };
            let (Some(tile), Some(owner)) = (
                self.config.tiles.iter().position(|t| t.name == rect.tile),
                self.config.node_of_tile(&rect.tile),
            ) else {
                continue;
            };
            let n = r.width as usize * r.height as usize;
            let fits = r.rgb8.len() == 3 * n && r.depth.len() == n && r.height == rect.rows;
            debug_assert!(fits, "rectangle `{name}`: a bad render");
            if !fits {
                continue;
            }
            // The pixels its kernels ran for (at the frame's scale), not those shown.
            let rendered = u64::from(r.width.div_ceil(st.scale)) * u64::from(r.height.div_ceil(st.scale));
            costs.push(WireRectCost {
                tile: tile as u32,
                first_row: rect.first_row,
                rows: rect.rows,
                cost: rect_cost(r.fetches, rendered),
            });
            // Placed whatever it shows: a miss gets a depth that wins over an empty canvas.
            // Moved, not copied: the render's own buffers become the layer's (a frame's pixels).
            let mut depth = std::mem::take(&mut r.depth);
            depth.iter_mut().filter(|d| !d.is_finite()).for_each(|d| *d = f32::MAX);
            let layer = Layer {
                x: 0,
                y: rect.first_row,
                width: r.width,
                height: r.height,
                form: PixelForm::Colour,
                depth,
                rgb8: std::mem::take(&mut r.rgb8),
                shading: Vec::new(),
            };
            if owner.name == self.name {
                mine.push((rect.tile.clone(), layer));
            } else {
                by_owner.entry(owner.name.clone()).or_default().push((rect.tile.clone(), layer));
            }
        }
        let mut out = vec![ObjectOutput::Send(Message::RectCosts { frame_id, costs })];
        for (peer, layers) in by_owner {
            let rects = layers.iter().map(|(t, l)| l.encode(t, self.compress)).collect();
            let msg = PeerPixels { frame_id, node: self.name.clone(), rects };
            // Encoding cannot fail for these types; a failure sends nothing (the owner's deadline
            // covers it).
            if let Ok(bytes) = codec::encode_pixels(&msg) {
                st.sent += bytes.len() as u64;
                out.push(ObjectOutput::SendPixels { peer, frame_id, bytes });
            }
        }
        st.local_at = Some(now);
        let done = self.compositor.local(now, frame_id, &mine, self.background);
        out.extend(self.compositor.take_refused().into_iter().map(refused_output));
        out.extend(done.map(ObjectOutput::Composited));
        out
    }

    /// A peer's pixels, from the connection `link` whose certificate names `cert`.
    pub fn peer(&mut self, now: Duration, cert: &str, link: Link, pixels: PeerPixels) -> Vec<ObjectOutput> {
        match self.compositor.peer(now, cert, link, pixels) {
            Ok(done) => done.map(ObjectOutput::Composited).into_iter().collect(),
            Err(e) => vec![refused_output(crate::composite::Refused { link, error: e })],
        }
    }

    /// When the next waiting frame's deadline passes.
    pub fn poll_timeout(&self) -> Option<Duration> {
        self.compositor.poll_timeout()
    }

    /// Frames whose deadline passed: placed with what arrived.
    pub fn handle_timeout(&mut self, now: Duration) -> Vec<ObjectOutput> {
        self.compositor.handle_timeout(now).into_iter().map(ObjectOutput::Composited).collect()
    }

    /// Time the caller spent on a frame's pixels (encoding, decoding, placing).
    pub fn add_work(&mut self, frame_id: u64, work: Duration) {
        if let Some(st) = self.started.get_mut(&frame_id) {
            st.work += work;
        }
    }

    /// The controller's `Composited` for a placed frame at `now`: the bytes sent to peers, the
    /// time from this node's render done to now, the work in it, and the peers it went without.
    pub fn report(&self, now: Duration, done: &crate::composite::Composited) -> Message {
        let us = |d: Duration| u64::try_from(d.as_micros()).unwrap_or(u64::MAX);
        let st = self.started.get(&done.frame_id);
        Message::Composited {
            frame_id: done.frame_id,
            bytes_sent: st.map_or(0, |s| s.sent),
            composite_us: st.and_then(|s| s.local_at).map_or(0, |at| us(now.saturating_sub(at))),
            merge_us: us(st.map_or(Duration::ZERO, |s| s.work)),
            resident_bytes: 0,
            missing: done.missing.clone(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::balance::share::split_to_wire;
    use crate::balance::Balancer;
    use crate::composite::Composited;
    use crate::{Camera, RenderSettings};
    use glam::DVec3;

    /// A 2x1 wall of 32x24 tiles, one node each (tile `tK` on node `nK`).
    fn wall() -> WallConfig {
        let mut toml = String::from(
            "[wall]\nname = \"w\"\nbalance = true\n[camera]\neye = [0, -10, 0]\ntarget = [0, 0, 0]\nup = [0, 0, 1]\n\
             [volume]\nsource = \"procedural:engine\"\n",
        );
        for k in 0..2 {
            toml += &format!("[[tiles]]\nname = \"t{k}\"\nx = {}\ny = 0\nwidth = 32\nheight = 24\n", 32 * k);
        }
        for k in 0..2 {
            toml += &format!(
                "[[nodes]]\nname = \"n{k}\"\naddress = \"127.0.0.1:{}\"\ntiles = [\"t{k}\"]\n",
                7000 + k
            );
        }
        WallConfig::parse(&toml, std::path::Path::new("w.toml")).unwrap()
    }

    fn spec(frame_id: u64) -> FrameSpec {
        let camera =
            Camera { eye: DVec3::new(0.0, -10.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 40.0 };
        FrameSpec { frame_id, camera, settings: RenderSettings::new(0.5), scale: 1, time_step: 0 }
    }

    /// A fake render of `plan`'s views: every pixel's colour says its wall position, the left
    /// half of each row misses, and a rectangle's fetches are its rows.
    fn render(plan: &RenderPlan) -> Vec<RenderedRect> {
        plan.views
            .iter()
            .map(|(name, v)| {
                let (w, h) = (v.rect.width, v.rect.height);
                let mut rgb8 = Vec::new();
                let mut depth = Vec::new();
                for y in 0..h {
                    for x in 0..w {
                        rgb8.extend([(v.rect.x + x) as u8, (v.rect.y + y) as u8, 7]);
                        depth.push(if x < w / 2 { f32::INFINITY } else { 1.0 + y as f32 });
                    }
                }
                RenderedRect { name: name.clone(), width: w, height: h, rgb8, depth, fetches: u64::from(h) }
            })
            .collect()
    }

    /// Runs one frame on both nodes: each renders its share, the pixels cross, each places its
    /// tile. Returns each node's placed frames and its messages for the controller.
    fn frame(ms: &mut [BalanceMachine; 2], id: u64) -> ([Vec<Composited>; 2], [Vec<Message>; 2]) {
        let (mut done, mut sent) = ([Vec::new(), Vec::new()], [Vec::new(), Vec::new()]);
        let mut outs = Vec::new();
        for m in ms.iter_mut() {
            m.announce(id);
            let (p, refused) = m.plan(Duration::ZERO, &spec(id), 0, Continuity::Same);
            assert!(refused.is_empty());
            outs.push(m.local_done(Duration::ZERO, id, render(&p)));
        }
        for (k, outs) in outs.into_iter().enumerate() {
            for o in outs {
                match o {
                    ObjectOutput::SendPixels { bytes, .. } => {
                        let px = codec::decode_pixels(&bytes).unwrap();
                        for o in ms[1 - k].peer(Duration::ZERO, &format!("n{k}"), 1, px) {
                            let ObjectOutput::Composited(c) = o else { panic!("{o:?}") };
                            done[1 - k].push(c);
                        }
                    }
                    ObjectOutput::Composited(c) => done[k].push(c),
                    ObjectOutput::Send(m) => sent[k].push(m),
                    other => panic!("{other:?}"),
                }
            }
        }
        (done, sent)
    }

    /// The expected tile `k`: the fake render of the whole tile, its misses placed too.
    fn whole(k: u32) -> Vec<u8> {
        let mut rgb8 = Vec::new();
        for y in 0..24u32 {
            for x in 0..32u32 {
                rgb8.extend([(32 * k + x) as u8, y as u8, 7]);
            }
        }
        rgb8
    }

    #[test]
    fn a_balanced_frame_places_every_rectangle_where_the_unbalanced_one_has_it() {
        let config = wall();
        let d = Duration::from_secs(1);
        let mut ms = [BalanceMachine::new(&config, "n0", d), BalanceMachine::new(&config, "n1", d)];
        // Without a split every node renders its own tile, whole.
        let (done, sent) = frame(&mut ms, 1);
        for k in 0..2 {
            assert_eq!(done[k].len(), 1, "node {k}");
            assert_eq!(done[k][0].tiles[0].rgb8, whole(k as u32));
            assert!(done[k][0].missing.is_empty());
            let Message::RectCosts { frame_id: 1, costs } = &sent[k][0] else { panic!("{:?}", sent[k]) };
            assert_eq!(costs.len(), 1);
            assert_eq!(costs[0].cost, rect_cost(24, 32 * 24));
        }
        // Tile t0 costs far more: n1 takes part of it from frame 2 on.
        let mut b = Balancer::for_wall(&config);
        for r in b.split().rects.clone() {
            b.observe(&r, if r.tile == "t0" { 100.0 } else { 1.0 });
        }
        let split = b.next_split(false).clone();
        assert!(split.rects.iter().any(|r| r.tile == "t0" && r.renderer == "n1"), "{split:?}");
        let wire = split_to_wire(&split, &config).unwrap();
        for m in &mut ms {
            m.set_split(2, &wire).unwrap();
        }
        let (done, sent) = frame(&mut ms, 2);
        for (k, done) in done.iter().enumerate() {
            assert_eq!(done.len(), 1, "node {k}");
            assert_eq!(done[0].tiles[0].rgb8, whole(k as u32), "node {k}: the same picture");
        }
        // n1 reports its own tile and its rectangle of t0; what it reports is what it rendered.
        let Message::RectCosts { costs, .. } = &sent[1][0] else { panic!() };
        assert_eq!(costs.len(), 2, "{costs:?}");
        assert!(costs.iter().any(|c| c.tile == 0
            && c.first_row > 0
            && c.cost == rect_cost(u64::from(c.rows), 32 * u64::from(c.rows))));
        // The split's frames: frame 1 still had none.
        assert_eq!(ms[0].split_for(1).rects.len(), 2);
        assert_eq!(ms[0].split_for(9), split);
    }

    #[test]
    fn a_rectangle_not_in_by_the_deadline_shows_the_background_and_a_foreign_one_is_refused() {
        let config = wall();
        let d = Duration::from_millis(100);
        let mut owner = BalanceMachine::new(&config, "n0", d);
        let mut b = Balancer::for_wall(&config);
        for r in b.split().rects.clone() {
            b.observe(&r, if r.tile == "t0" { 100.0 } else { 1.0 });
        }
        let wire = split_to_wire(b.next_split(false), &config).unwrap();
        owner.set_split(1, &wire).unwrap();
        owner.announce(1);
        let (plan, _) = owner.plan(Duration::ZERO, &spec(1), 0, Continuity::Same);
        let out = owner.local_done(Duration::ZERO, 1, render(&plan));
        assert!(!out.iter().any(|o| matches!(o, ObjectOutput::Composited(_))), "it waits for n1");
        // n1 sends rows of t0 it was not given: refused, its connection closed.
        let rect = Layer::empty(0, 0, 32, 1, PixelForm::Colour).encode("t0", false);
        let bad = PeerPixels { frame_id: 1, node: "n1".into(), rects: vec![rect] };
        let out = owner.peer(Duration::ZERO, "n1", 5, bad);
        assert!(matches!(&out[..], [ObjectOutput::ClosePeer { link: 5, .. }]), "{out:?}");
        // The deadline passes: the tile is placed without n1's rows, which show the background.
        let at = composite_deadline(d);
        assert!(at < d);
        assert_eq!(owner.poll_timeout(), Some(at));
        assert!(owner.handle_timeout(at - Duration::from_millis(1)).is_empty());
        let done = owner.handle_timeout(at);
        let [ObjectOutput::Composited(c)] = &done[..] else { panic!("{done:?}") };
        assert_eq!(c.missing, vec!["n1".to_string()]);
        let given = plan.views.iter().map(|(_, v)| v.rect.height).sum::<u32>();
        assert!(given < 24);
        let bg = srgb8(f64::from(spec(1).settings.background[0] as f32));
        let last_row = &c.tiles[0].rgb8[3 * 32 * 23..];
        assert_eq!(last_row[0], bg, "a row n1 held shows the background");
        assert_eq!(&c.tiles[0].rgb8[..3 * 32], &whole(0)[..3 * 32], "n0's own rows are placed");
    }

    /// A node the split before left out (down) and this one has again is back, a new process:
    /// its peers send to it on a new connection. Once, when it comes back; not for itself.
    #[test]
    fn a_node_back_from_the_dead_is_sent_to_on_a_new_connection() {
        let config = wall();
        let reconnects = |out: Vec<ObjectOutput>| -> Vec<String> {
            out.into_iter()
                .filter_map(|o| match o {
                    ObjectOutput::Reconnect { peer } => Some(peer),
                    _ => None,
                })
                .collect()
        };
        let mut b = Balancer::for_wall(&config);
        b.set_nodes(["n0".to_string()]);
        let without = split_to_wire(b.next_split(false), &config).unwrap();
        b.set_nodes(["n0".to_string(), "n1".to_string()]);
        let with = split_to_wire(b.next_split(false), &config).unwrap();
        let mut m = BalanceMachine::new(&config, "n0", Duration::from_secs(1));
        assert!(reconnects(m.set_split(3, &with).unwrap()).is_empty(), "n1 never left");
        assert!(reconnects(m.set_split(5, &without).unwrap()).is_empty(), "n1 is down");
        assert_eq!(reconnects(m.set_split(9, &with).unwrap()), ["n1"]);
        assert!(reconnects(m.set_split(12, &with).unwrap()).is_empty(), "the same nodes again");
        let mut back = BalanceMachine::new(&config, "n1", Duration::from_secs(1));
        assert!(reconnects(back.set_split(5, &without).unwrap()).is_empty());
        assert!(reconnects(back.set_split(9, &with).unwrap()).is_empty(), "not to itself");
    }

    #[test]
    fn a_rectangle_costs_the_pixels_it_rendered_at_the_frames_scale() {
        let config = wall();
        let mut m = BalanceMachine::new(&config, "n1", Duration::from_secs(1));
        m.announce(1);
        let spec = FrameSpec { scale: 4, ..spec(1) };
        let (plan, _) = m.plan(Duration::ZERO, &spec, 0, Continuity::ViewMoved);
        assert_eq!(plan.scale, 4);
        let out = m.local_done(Duration::ZERO, 1, render(&plan));
        let ObjectOutput::Send(Message::RectCosts { costs, .. }) = &out[0] else { panic!("{out:?}") };
        // A 32x24 tile at 1/4 scale: 8x6 pixels rendered, and its 24 rows' fetches.
        assert_eq!(costs[0].cost, rect_cost(24, 8 * 6));
    }

    #[test]
    fn a_hostile_split_is_refused_whole_and_changes_nothing() {
        let config = wall();
        let mut m = BalanceMachine::new(&config, "n0", Duration::from_secs(1));
        let before = m.split_for(5);
        let bad = WireSplit {
            rects: vec![crate::wire::WireWorkRect { tile: 0, first_row: 0, rows: 30, renderer: 1 }],
        };
        assert!(m.set_split(1, &bad).is_err());
        assert_eq!(m.split_for(5), before);
    }
}
