//! Load-balanced screen space on a wall node (`[wall] balance = true`): the I/O around the
//! model's [`BalanceMachine`] (`isowall_model::balance::node`: what the node renders of a frame,
//! what it sends and waits for, what it reports; the split's rule is the controller's
//! `isowall_model::balance::Balancer`).
//!
//! - The controller's `Split` (from a frame on) is checked whole before it is used; a bad one is
//!   the controller's protocol violation.
//! - Each frame the render thread renders the node's rectangles (each its own view and target)
//!   and reads them back in the colour form; those of other nodes' tiles leave on the pixel
//!   streams of [`isowall_net::pixels`] (one stream per frame per owner, node to node with
//!   mutual TLS, every wait bounded by the wall's deadline), its own are placed at once.
//! - Peers' rectangles go to the machine as they arrive: accepted only from the node the split
//!   gave them to, within their rows, their size checked before anything is decompressed; a peer
//!   that breaks the rules has its connection closed with the machine's reason.
//! - When a frame's tiles are placed (everything in, or the deadline passed) the session sends
//!   `RectCosts` and `Composited`, then Ready, and swaps as in screen space. The windows show
//!   the placed tiles from images the render thread uploads.

use crate::object::Done;
use crate::pixel_links::PixelLinks;
use crate::render_thread::{JobResult, TileResult};
use anyhow::Result;
use isowall_model::balance::node::{BalanceMachine, RenderedRect};
use isowall_model::balance::share::SplitError;
use isowall_model::config::WallConfig;
use isowall_model::messages::Message;
use isowall_model::object_machine::ObjectOutput;
use isowall_model::render_plan::RenderPlan;
use isowall_model::wire::{Continuity, FrameSpec, WireSplit};
use isowall_net::pixels::PeerPixelsIn;
use isowall_net::Identity;
use std::collections::HashMap;
use std::time::{Duration, Instant};

/// The node's side of a balanced wall.
pub struct BalancedNode {
    machine: BalanceMachine,
    links: PixelLinks,
    /// The machine's clock.
    epoch: Instant,
    /// Per frame: its render time and time step report, until it is placed.
    rendered: HashMap<u64, (Duration, Option<(u32, Duration)>)>,
    /// `RectCosts` for the controller, sent with the frame's `Composited`.
    costs: HashMap<u64, Message>,
}

impl BalancedNode {
    pub fn new(config: &WallConfig, name: &str) -> Result<BalancedNode> {
        let deadline = Duration::from_millis(config.wall.deadline_ms);
        let machine = BalanceMachine::new(config, name, deadline);
        let links = PixelLinks::new(config, machine.peers())?;
        Ok(BalancedNode {
            machine,
            links,
            epoch: Instant::now(),
            rendered: HashMap::new(),
            costs: HashMap::new(),
        })
    }

    fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    /// The longest pixel stream a peer may send this node.
    pub fn max_pixels_bytes(&self) -> usize {
        self.machine.max_pixels_bytes()
    }

    /// The wall's deadline: each wait for a peer ends there.
    pub fn deadline(&self) -> Duration {
        self.links.deadline()
    }

    /// Opens the endpoint this node connects to its peers from (inside the async runtime).
    pub fn open_endpoint(&mut self, identity: &Identity) -> Result<()> {
        self.links.open_endpoint(identity)
    }

    /// A new controller session: its frame ids and splits start afresh.
    pub fn reset(&mut self) {
        self.machine.reset();
        self.rendered.clear();
        self.costs.clear();
    }

    /// A frame state arrived from the controller.
    pub fn announce(&mut self, frame_id: u64) {
        self.machine.announce(frame_id);
    }

    /// The controller's split from `from_frame` on.
    pub fn set_split(&mut self, from_frame: u64, split: &WireSplit) -> Result<(), SplitError> {
        let back = self.machine.set_split(from_frame, split)?;
        tracing::debug!(from_frame, rects = split.rects.len(), "balance: split");
        let rest = self.links.execute(back);
        debug_assert!(rest.is_empty(), "a split only renews connections");
        Ok(())
    }

    /// What this node renders of a frame: the machine's rectangles.
    pub fn plan(&mut self, spec: &FrameSpec, accumulate_frame: u32, continuity: Continuity) -> RenderPlan {
        let (plan, refused) = self.machine.plan(self.now(), spec, accumulate_frame, continuity);
        let rest = self.links.execute(refused);
        debug_assert!(rest.is_empty(), "a frame starting places nothing");
        plan
    }

    /// This node's rectangles of a frame are rendered: sends the peers theirs, places its own.
    pub fn local_done(&mut self, done: JobResult) -> Vec<Done> {
        let (id, t0) = (done.frame_id, Instant::now());
        self.rendered.insert(id, (done.render_time, done.step_late));
        self.rendered.retain(|&f, _| f.saturating_add(16) > id);
        let rects = done
            .tiles
            .into_iter()
            .map(|t| RenderedRect {
                name: t.name,
                width: t.width,
                height: t.height,
                rgb8: t.rgb8,
                depth: t.depth,
                fetches: t.fetches,
            })
            .collect();
        let out = self.machine.local_done(self.now(), id, rects);
        self.machine.add_work(id, t0.elapsed());
        self.execute(out)
    }

    /// A peer's pixels: the frames they complete (a violation closes the peer's connection).
    pub fn peer(&mut self, item: PeerPixelsIn) -> Vec<Done> {
        let (id, t0) = (item.pixels.frame_id, Instant::now());
        let link = item.connection.link();
        self.links.keep(item.connection);
        let out = self.machine.peer(self.now(), &item.cert, link, item.pixels);
        self.machine.add_work(id, t0.elapsed());
        self.execute(out)
    }

    /// When the next waiting frame's deadline passes.
    pub fn next_timeout(&self) -> Option<tokio::time::Instant> {
        self.machine.poll_timeout().map(|t| tokio::time::Instant::from_std(self.epoch + t))
    }

    /// Frames whose deadline passed: placed with what arrived.
    pub fn handle_timeout(&mut self) -> Vec<Done> {
        let out = self.machine.handle_timeout(self.now());
        self.execute(out)
    }

    /// Carries out the machine's outputs; returns the placed frames.
    fn execute(&mut self, outputs: Vec<ObjectOutput>) -> Vec<Done> {
        let mut done = Vec::new();
        for out in self.links.execute(outputs) {
            match out {
                ObjectOutput::Send(m @ Message::RectCosts { frame_id, .. }) => {
                    self.costs.insert(frame_id, m);
                }
                ObjectOutput::Composited(c) => {
                    self.links.note_missing(&c);
                    let id = c.frame_id;
                    let mut reports = Vec::new();
                    reports.extend(self.costs.remove(&id));
                    self.costs.retain(|&f, _| f > id);
                    reports.push(self.machine.report(self.now(), &c));
                    let (render_time, step_late) = self.rendered.remove(&id).unwrap_or_default();
                    // Placed in the colour form: `object.rs`'s conversion of a canvas.
                    let tiles = c.tiles.into_iter().map(TileResult::from).collect();
                    let job = JobResult { frame_id: id, tiles, render_time, step_late, surface: None };
                    done.push(Done { job, reports, canvas: None });
                }
                other => tracing::error!("balance: an output it does not make: {other:?}"),
            }
        }
        done
    }
}
