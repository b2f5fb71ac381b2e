//! The node's space, one state: screen space (the node renders its own tiles), balanced screen
//! space (it renders the rectangles the controller's split gives it, of its own tiles and
//! others', and rectangles travel to their tiles' owners) or object space (it renders its brick,
//! its pixels travel to the tiles' owners, peers' pixels come in, dead nodes' bricks are
//! adopted). Each space's parts are all there or none is.

use crate::balanced::BalancedNode;
use crate::object::{LoadDone, ObjectNode};
use crate::render_thread::RenderHandle;
use isowall_model::config::WallConfig;
use isowall_model::render_plan::RenderPlan;
use isowall_model::wire::{Continuity, FrameSpec};
use isowall_net::pixels::{PeerPixelsIn, PixelInbox};
use tokio::sync::mpsc::{Receiver, UnboundedReceiver};

pub(super) enum Space {
    Screen,
    Balanced(Box<BalancedSpace>),
    Object(Box<ObjectSpace>),
}

/// Balanced screen space's state and what it waits on.
pub(super) struct BalancedSpace {
    /// The node's side of the balance (`balanced.rs`).
    pub node: BalancedNode,
    /// Peers' rectangles as they arrive.
    pub peer_rx: Receiver<PeerPixelsIn>,
    /// Where admission hands peers' connections over.
    pub inbox: PixelInbox,
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
    /// The compositing (or placing) deadline of a pending frame passed.
    Deadline,
    /// An adopted brick is loaded, or could not be.
    Loaded(LoadDone),
}

impl Space {
    pub fn object_mut(&mut self) -> Option<&mut ObjectNode> {
        match self {
            Space::Object(o) => Some(&mut o.node),
            _ => None,
        }
    }

    pub fn balanced_mut(&mut self) -> Option<&mut BalancedNode> {
        match self {
            Space::Balanced(b) => Some(&mut b.node),
            _ => None,
        }
    }

    /// Whether the node's tiles are put together on the CPU from pixels read back (and peers'),
    /// not shown from its render targets: object space and balanced screen space.
    pub fn composites(&self) -> bool {
        !matches!(self, Space::Screen)
    }

    /// Where admission hands peers' connections over (none in plain screen space: they are
    /// refused).
    pub fn inbox(&self) -> Option<PixelInbox> {
        match self {
            Space::Object(o) => Some(o.inbox.clone()),
            Space::Balanced(b) => Some(b.inbox.clone()),
            Space::Screen => None,
        }
    }

    /// Opens the endpoint the node sends its peers pixels from (inside the async runtime).
    pub fn open_endpoint(&mut self, identity: &isowall_net::Identity) -> anyhow::Result<()> {
        match self {
            Space::Object(o) => o.node.open_endpoint(identity),
            Space::Balanced(b) => b.node.open_endpoint(identity),
            Space::Screen => Ok(()),
        }
    }

    /// A new controller session: frame ids (and a balanced wall's splits) start afresh.
    pub fn reset(&mut self) {
        match self {
            Space::Object(o) => o.node.reset(),
            Space::Balanced(b) => b.node.reset(),
            Space::Screen => {}
        }
    }

    /// A frame state arrived from the controller (before the frame machine handles it).
    pub fn announce(&mut self, frame_id: u64) {
        match self {
            Space::Object(o) => o.node.announce(frame_id),
            Space::Balanced(b) => b.node.announce(frame_id),
            Space::Screen => {}
        }
    }

    /// The next event of object or balanced space; never, in plain screen space. Cancel-safe
    /// (channel receives and a sleep), so it can lose a `select!` with nothing lost.
    pub async fn next(&mut self) -> SpaceEvent {
        match self {
            Space::Screen => std::future::pending().await,
            Space::Balanced(b) => {
                let BalancedSpace { node, peer_rx, .. } = &mut **b;
                let deadline = node.next_timeout();
                tokio::select! {
                    Some(item) = peer_rx.recv() => SpaceEvent::Peer(item),
                    _ = sleep_until(deadline) => SpaceEvent::Deadline,
                }
            }
            Space::Object(o) => {
                let ObjectSpace { node, peer_rx, load_rx, .. } = &mut **o;
                let deadline = node.next_timeout();
                tokio::select! {
                    Some(item) = peer_rx.recv() => SpaceEvent::Peer(item),
                    Some(done) = load_rx.recv() => SpaceEvent::Loaded(done),
                    _ = sleep_until(deadline) => SpaceEvent::Deadline,
                }
            }
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
            Space::Balanced(b) => b.node.plan(spec, accumulate_frame, continuity),
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
