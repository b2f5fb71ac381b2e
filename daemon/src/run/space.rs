//! The node's space, one state: screen space (the node renders its own tiles) or object space (it
//! renders its brick, its pixels travel to the tiles' owners, peers' pixels come in, dead nodes'
//! bricks are adopted). Object space's parts are all there or none is.

use crate::object::{LoadDone, ObjectNode};
use crate::render_thread::RenderHandle;
use isowall_model::config::WallConfig;
use isowall_model::render_plan::RenderPlan;
use isowall_model::wire::{Continuity, FrameSpec};
use isowall_net::pixels::{PeerPixelsIn, PixelInbox};
use tokio::sync::mpsc::{Receiver, UnboundedReceiver};

pub(super) enum Space {
    Screen,
    Object(Box<ObjectSpace>),
}

/// Object space's state and what it waits on.
pub(super) struct ObjectSpace {
    /// The brick's compositing and peers (`object.rs`).
    pub node: ObjectNode,
    /// Peers' pixels as they arrive.
    pub peer_rx: Receiver<PeerPixelsIn>,
    /// Where admission hands peers' connections over.
    pub inbox: PixelInbox,
    /// Adopted bricks loaded (or not), for the controller.
    pub load_rx: UnboundedReceiver<LoadDone>,
}

/// What object space waits for besides the controller and the render thread.
pub(super) enum SpaceEvent {
    /// A peer's pixels (or its stream's end).
    Peer(PeerPixelsIn),
    /// The compositing deadline of a pending frame passed.
    Deadline,
    /// An adopted brick is loaded, or could not be.
    Loaded(LoadDone),
}

impl Space {
    pub fn object(&self) -> Option<&ObjectNode> {
        match self {
            Space::Object(o) => Some(&o.node),
            Space::Screen => None,
        }
    }

    pub fn object_mut(&mut self) -> Option<&mut ObjectNode> {
        match self {
            Space::Object(o) => Some(&mut o.node),
            Space::Screen => None,
        }
    }

    /// Where admission hands peers' connections over (none in screen space: they are refused).
    pub fn inbox(&self) -> Option<PixelInbox> {
        match self {
            Space::Object(o) => Some(o.inbox.clone()),
            Space::Screen => None,
        }
    }

    /// The next event of object space; never, in screen space. Cancel-safe (channel receives
    /// and a sleep), so it can lose a `select!` with nothing lost.
    pub async fn next(&mut self) -> SpaceEvent {
        let Space::Object(o) = self else { return std::future::pending().await };
        let ObjectSpace { node, peer_rx, load_rx, .. } = &mut **o;
        let deadline = node.next_timeout();
        tokio::select! {
            Some(item) = peer_rx.recv() => SpaceEvent::Peer(item),
            Some(done) = load_rx.recv() => SpaceEvent::Loaded(done),
            _ = sleep_until(deadline) => SpaceEvent::Deadline,
        }
    }

    /// What to render of a frame: the model's plan for this space.
    pub fn plan(
        &mut self,
        config: &WallConfig,
        tiles: &[String],
        spec: &FrameSpec,
        (accumulate_frame, continuity): (u32, Continuity),
        renderer: &RenderHandle,
    ) -> RenderPlan {
        match self {
            Space::Screen => RenderPlan::screen(config, tiles, spec, accumulate_frame, continuity),
            Space::Object(o) => o.node.plan(spec, accumulate_frame, continuity, renderer),
        }
    }
}

/// The next compositing deadline (never when none is pending).
async fn sleep_until(at: Option<tokio::time::Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}
