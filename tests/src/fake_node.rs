//! Nodes played by the tests (no GPU): a QUIC server with a node's own certificate that speaks the
//! protocol through the model's [`NodeMachine`], renders nothing and answers at once. Each attack
//! test keeps what its node does differently (lies, floods, silence) and hands the rest to
//! [`FakeNode::answer`].

use isowall_model::messages::Message;
use isowall_model::node_machine::{NodeMachine, NodeOutput};
use isowall_net::transport::{self, Channel, ChannelReceiver, ChannelSender};
use isowall_net::Identity;
use std::collections::VecDeque;
use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

/// How long a played node says each frame took to render.
pub const RENDER_TIME: Duration = Duration::from_micros(50);

/// The runtime the played nodes and the tests' own clients run on: two worker threads.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("a tokio runtime")
}

/// A QUIC server on `addr` presenting `keys/NAME.*`, the certificate of node `name`.
pub fn listen(keys: &Path, name: &str, addr: SocketAddr) -> quinn::Endpoint {
    let identity = Identity::load(keys, name)
        .unwrap_or_else(|e| panic!("{name}'s certificate in {}: {e}", keys.display()));
    transport::server(addr, &identity).unwrap_or_else(|e| panic!("listen as {name} on {addr}: {e}"))
}

/// One controller connection to a played node: its channel and the node's state machine.
pub struct FakeNode {
    pub connection: quinn::Connection,
    pub sender: ChannelSender,
    receiver: ChannelReceiver,
    pub machine: NodeMachine,
    epoch: Instant,
    queue: VecDeque<NodeOutput>,
}

impl FakeNode {
    /// Takes the controller's channel on `conn` and says Hello as node `name` showing `tiles`;
    /// `None` where the channel or the Hello fails.
    pub async fn greet(conn: quinn::Connection, name: &str, tiles: Vec<String>) -> Option<FakeNode> {
        let Channel { connection, mut sender, receiver } =
            Channel::accept(conn, "controller", 1 << 20).await.ok()?;
        let machine = NodeMachine::new(name, tiles);
        sender.send(&machine.hello()).await.ok()?;
        Some(FakeNode {
            connection,
            sender,
            receiver,
            machine,
            epoch: Instant::now(),
            queue: VecDeque::new(),
        })
    }

    /// Time since the greeting: the machine's clock.
    pub fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    /// The machine's next output: those still queued first, else those of the controller's next
    /// message. `None` once the channel ends or a message breaks the protocol.
    pub async fn next(&mut self) -> Option<NodeOutput> {
        while self.queue.is_empty() {
            let msg = self.receiver.recv().await.ok()??;
            let outputs = self.machine.handle(self.now(), msg).ok()?;
            self.queue.extend(outputs);
        }
        self.queue.pop_front()
    }

    /// Sends `msg`; `false` when the connection is gone.
    pub async fn send(&mut self, msg: &Message) -> bool {
        self.sender.send(msg).await.is_ok()
    }

    /// Frame `frame_id` rendered in `took`: the machine's outputs queued.
    pub fn rendered(&mut self, frame_id: u64, took: Duration) {
        let outputs = self.machine.render_done(self.now(), frame_id, took);
        self.queue.extend(outputs);
    }

    /// Frame `frame_id` presented now, whatever its present time: the machine's outputs queued.
    pub fn presented(&mut self, frame_id: u64) {
        let now = self.now();
        let outputs = self.machine.presented(now, frame_id, now);
        self.queue.extend(outputs);
    }

    /// What a node that renders nothing does with `out`: sends what the machine sends, renders
    /// in [`RENDER_TIME`] and presents at once; every other output is left unanswered. `false`
    /// when the connection is gone or the machine closed it.
    pub async fn answer(&mut self, out: NodeOutput) -> bool {
        match out {
            NodeOutput::Send(msg) => self.send(&msg).await,
            NodeOutput::Render { state, .. } => {
                self.rendered(state.frame_id, RENDER_TIME);
                true
            }
            NodeOutput::Present { frame_id, .. } => {
                self.presented(frame_id);
                true
            }
            NodeOutput::Closed { .. } => false,
            _ => true,
        }
    }
}
