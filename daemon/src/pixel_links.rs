//! A node's pixel streams to and from its peers, as object space and the balanced screen space
//! both use them: the outbox its pixels leave by, the peers' connections (to close the one whose
//! pixels break the rules), and the peers the last finished frame went without (logged when that
//! changes). The model's machines decide what to send and what to refuse; this carries it out.

use anyhow::{anyhow, Result};
use isowall_model::composite::Composited;
use isowall_model::config::WallConfig;
use isowall_model::object_machine::ObjectOutput;
use isowall_net::pixels::{PeerConnection, PixelOutbox};
use isowall_net::{transport, Identity};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::time::Duration;

pub struct PixelLinks {
    addrs: HashMap<String, SocketAddr>,
    outbox: Option<PixelOutbox>,
    /// The peers' open connections by link.
    connections: HashMap<u64, PeerConnection>,
    /// How long each wait for a peer may take (the wall's deadline).
    deadline: Duration,
    /// The peers the last finished frame went without.
    missing: Vec<String>,
}

impl PixelLinks {
    /// Links to `peers` (nodes of `config`, by name) at their configured addresses.
    pub fn new<'a>(config: &WallConfig, peers: impl IntoIterator<Item = &'a String>) -> Result<PixelLinks> {
        let mut addrs = HashMap::new();
        for peer in peers {
            let n = config.node(peer).ok_or_else(|| anyhow!("no node '{peer}' in the wall config"))?;
            addrs.insert(peer.clone(), transport::resolve(&n.address)?);
        }
        Ok(PixelLinks {
            addrs,
            outbox: None,
            connections: HashMap::new(),
            deadline: Duration::from_millis(config.wall.deadline_ms),
            missing: Vec::new(),
        })
    }

    /// The wall's deadline: each wait for a peer's stream ends there.
    pub fn deadline(&self) -> Duration {
        self.deadline
    }

    /// Opens the endpoint this node connects to its peers from (inside the async runtime).
    pub fn open_endpoint(&mut self, identity: &Identity) -> Result<()> {
        self.outbox = Some(PixelOutbox::new(identity, self.addrs.clone(), self.deadline)?);
        Ok(())
    }

    /// Keeps a peer's connection (its pixels came on it), so it can be closed by its link.
    pub fn keep(&mut self, connection: PeerConnection) {
        let link = connection.link();
        if !self.connections.contains_key(&link) {
            self.connections.retain(|_, c| c.is_open());
            self.connections.insert(link, connection);
        }
    }

    /// Carries out the pixel streams' outputs; returns the rest (finished frames, messages).
    pub fn execute(&mut self, outputs: Vec<ObjectOutput>) -> Vec<ObjectOutput> {
        let mut rest = Vec::new();
        for out in outputs {
            match out {
                ObjectOutput::SendPixels { peer, frame_id, bytes } => match &self.outbox {
                    Some(o) => o.send(&peer, frame_id, bytes),
                    None => tracing::error!(frame_id, %peer, "cannot send pixels: no client endpoint"),
                },
                ObjectOutput::ClosePeer { peer, link, reason } => {
                    tracing::warn!(%peer, link, "closing the peer's connection: {reason}");
                    if let Some(c) = self.connections.get(&link) {
                        c.close(&reason);
                    }
                }
                ObjectOutput::Dropped { peer, reason } => {
                    tracing::warn!(%peer, "dropped the peer's pixels, its connection kept: {reason}")
                }
                ObjectOutput::Reconnect { peer } => {
                    if let Some(o) = &self.outbox {
                        o.forget(&peer, "the peer is back: connecting to it afresh");
                    }
                }
                other => rest.push(other),
            }
        }
        rest
    }

    /// Logs the peers a finished frame went without, when they change.
    pub fn note_missing(&mut self, c: &Composited) {
        if c.missing == self.missing {
            return;
        }
        if c.missing.is_empty() {
            tracing::info!(frame_id = c.frame_id, "finished with every peer's pixels again");
        } else {
            tracing::warn!(
                frame_id = c.frame_id,
                missing = ?c.missing,
                "finished without the pixels of {} (not in by the deadline; not waited for until they send again)",
                c.missing.join(", ")
            );
        }
        self.missing = c.missing.clone();
    }
}
