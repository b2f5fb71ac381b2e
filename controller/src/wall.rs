//! Driving a wall: connect to every node (QUIC, mutual TLS), feed the model's
//! [`FrameController`] with what arrives and carry out what it asks, frame after frame; gather
//! snapshots; report statistics. The network code only moves bytes and calls the state machine.

use crate::metrics::WallMetrics;
use anyhow::{anyhow, bail, Result};
use isowall_model::adoption::{AdoptionOutput, BrickAssigner};
use isowall_model::balance::claims::{cost_floor, Claims, Miss};
use isowall_model::balance::share::{split_to_wire, MAX_RECTS_PER_TILE};
use isowall_model::balance::{Balancer, Split, WorkRect};
use isowall_model::codec::{self, KindLimit};
use isowall_model::config::WallConfig;
use isowall_model::frame_controller::{ControllerOutput, FrameController, FrameStats};
use isowall_model::links::{Link as LinkId, Links};
use isowall_model::messages::{printable, Message, Role, TileImage};
use isowall_model::wire::{Continuity, FrameState, WireRectCost};
use isowall_model::{Camera, Governor, RenderSettings};
use isowall_net::transport::{self, Channel, ChannelSender};
use isowall_net::Identity;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// What arrives from a node's connection (or a reconnection attempt).
/// Messages and closes carry the connection they came on (its link number, the model's
/// [`Links`]): a late one from a node's previous connection is not about its current one.
enum Event {
    /// A node's message, and when it arrived (a Pong's time is that, not when it was handled).
    Message(String, LinkId, Message, Instant),
    Closed(String, LinkId, String),
    /// A node that was down is reachable again (handshake done).
    Reconnected(String, Link),
    /// A reconnection attempt failed; another may start.
    Unreachable(String),
}

/// An established, greeted connection to a node.
struct Link {
    connection: quinn::Connection,
    sender: ChannelSender,
    receiver: transport::ChannelReceiver,
}

/// Connects to node `name` at `address` and exchanges Hellos.
async fn establish(endpoint: quinn::Endpoint, name: String, address: String, limit: usize) -> Result<Link> {
    let addr = transport::resolve(&address)?;
    let conn = tokio::time::timeout(Duration::from_secs(3), transport::connect(&endpoint, addr, &name))
        .await
        .map_err(|_| anyhow!("no answer"))??;
    let greet = async {
        let Channel { connection, mut sender, mut receiver } =
            Channel::open(conn.clone(), &name, limit).await?;
        sender.send(&codec::hello(isowall_net::tls::CONTROLLER, Role::Controller)).await?;
        let first = tokio::time::timeout(Duration::from_secs(5), receiver.recv())
            .await
            .map_err(|_| anyhow!("no Hello"))??
            .ok_or_else(|| anyhow!("closed before Hello"))?;
        Ok::<_, anyhow::Error>((connection, sender, receiver, first))
    };
    let (connection, sender, receiver, first) = match greet.await {
        Ok(greeted) => greeted,
        // The node's close reason, where it gave one, says why (e.g. another controller drives it):
        // the stream only saw the connection lost.
        Err(e) => match tokio::time::timeout(Duration::from_secs(1), conn.closed()).await {
            Ok(quinn::ConnectionError::ApplicationClosed(c)) => {
                bail!("the node closed the connection: {}", printable(&String::from_utf8_lossy(&c.reason)))
            }
            // Closed here, not only dropped: the node, which may have seated it, frees the seat now.
            _ => {
                transport::close(&conn, &e.to_string());
                return Err(e);
            }
        },
    };
    let said =
        codec::check_hello(&first, Role::Daemon).map_err(|e| anyhow!("{}", printable(&e.to_string())))?;
    if said != name {
        transport::close(&connection, "wrong node");
        bail!("the node at {address} says it is '{}'", printable(&said));
    }
    Ok(Link { connection, sender, receiver })
}

/// How long a leaving controller waits for the nodes to close their side after its Bye, at most.
pub const GOODBYE_WAIT: Duration = Duration::from_secs(1);

/// A node that dies is reported down within this many deadlines.
pub const SILENT_DEADLINES: u32 = 3;

/// Events queued from the nodes' readers at most: a node that sends faster than the controller
/// handles waits (its QUIC stream's flow control holds it back), and memory stays bounded.
const EVENT_QUEUE: usize = 256;

/// Frames of statistics the controller keeps (a demo loops for hours: memory stays flat).
pub const HISTORY: usize = 1024;

/// Drops the oldest entries once `v` holds twice [`HISTORY`], keeping the last [`HISTORY`].
fn trim_history<T>(v: &mut Vec<T>) {
    if v.len() >= 2 * HISTORY {
        v.drain(..v.len() - HISTORY);
    }
}

/// What a front end asks of the wall for one frame ([`Wall::frame`]): the camera, the render
/// settings, the time step and the internal resolution divisor. `up`/`orbit`, the session, demos,
/// the bench table and the console all ask through it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameRequest {
    pub camera: Camera,
    pub settings: RenderSettings,
    /// The time step of a time-varying volume (0 otherwise).
    pub time_step: u32,
    /// The internal resolution divisor (1: full; the quality governor's).
    pub scale: u32,
}

impl FrameRequest {
    /// A frame of `camera` and `settings` at time step 0, full resolution.
    pub fn new(camera: Camera, settings: RenderSettings) -> FrameRequest {
        FrameRequest { camera, settings, time_step: 0, scale: 1 }
    }

    /// The same frame at time step `step`.
    pub fn at_time_step(self, step: u32) -> FrameRequest {
        FrameRequest { time_step: step, ..self }
    }

    /// The governed frame, the one step every front end with a quality governor takes: where a
    /// governor is set, its AO samples and resolution divisor replace the request's.
    pub fn governed(mut self, governor: Option<&Governor>) -> FrameRequest {
        if let Some(g) = governor {
            self.settings.ao.samples = g.samples();
            self.scale = g.scale();
        }
        self
    }
}

/// A connected wall.
pub struct Wall {
    pub config: WallConfig,
    machine: FrameController,
    senders: HashMap<String, ChannelSender>,
    connections: HashMap<String, quinn::Connection>,
    /// Each node's current connection, by link number.
    links: Links,
    events: mpsc::Receiver<Event>,
    events_tx: mpsc::Sender<Event>,
    endpoint: quinn::Endpoint,
    epoch: Instant,
    next_frame: u64,
    /// Statistics of the last finished frames (at most [`HISTORY`]..2 x [`HISTORY`]).
    pub finished: Vec<FrameStats>,
    /// The last releases: (frame, barrier time, stragglers), bounded like `finished`.
    pub releases: Vec<(u64, Duration, Vec<String>)>,
    /// Swaps released since the wall came up (all of them, unlike `releases`).
    pub released: u64,
    snapshots: BTreeMap<String, Vec<TileImage>>,
    /// Images (a snapshot or a thumbnail) asked for and not yet complete: the nodes asked, and
    /// when to give up on them.
    images: Option<(Vec<String>, Instant)>,
    /// Bytes of tile images the nodes sent in snapshots and thumbnails, since the wall came up.
    pub snapshot_bytes: u64,
    /// Nodes with a reconnection attempt under way.
    reconnecting: std::collections::HashSet<String>,
    /// When each down node was last tried.
    last_try: HashMap<String, Instant>,
    /// object space: which node renders each brick (a dead node's goes to a survivor).
    bricks: Option<BrickAssigner>,
    /// Whether the tiles show their names (the operator's identify); told to each node again
    /// when it (re)connects.
    identify: bool,
    /// A balanced screen-space wall (`[wall] balance = true`): the split's state.
    balance: Option<WallBalance>,
    /// The metrics for Prometheus, fed from the same events as `finished`, `releases` and
    /// `snapshot_bytes` (shared with whatever serves `/metrics`).
    metrics: Arc<WallMetrics>,
}

/// A balanced wall's split on the controller: the model's rule, the split the nodes were sent
/// last, and the last frame begun (whether the next one shows the same image).
struct WallBalance {
    balancer: Balancer,
    /// Off: every node renders its own tiles (`Wall::set_balance`; the bench's unbalanced run).
    on: bool,
    sent: Option<Split>,
    /// The nodes the split was sent to.
    sent_to: Vec<String>,
    last: Option<FrameState>,
    /// Rows of the split sent last that another node than the tile's owner renders.
    moved_rows: u64,
    /// Splits sent that differ from the one before, since the wall came up (each makes the
    /// moved rectangles' render targets again on their nodes).
    changes: u64,
    /// Per frame (the last [`HISTORY`] or so), each node's work: the costs it reported.
    work: BTreeMap<u64, BTreeMap<String, u64>>,
    /// What the nodes' reports are held to: who delivered what the split gave it.
    claims: Claims,
    /// Nodes held out of the split so far, each time (a node that missed).
    misses: u64,
}

impl Wall {
    /// Connects to every node at once and starts with the nodes it has: once one is up, the
    /// others have `grace` to answer; those that do not are named and tried again in the
    /// background (once a second each), and each joins at the frame after it answers. Fails only
    /// when no node answers within `timeout`.
    pub async fn connect(config: WallConfig, timeout: Duration, grace: Duration) -> Result<Wall> {
        let mut wall = Wall::new(config)?;
        let total = wall.config.nodes.len();
        let start = Instant::now();
        let mut first_up: Option<Instant> = None;
        let mut errors: BTreeMap<String, String> = BTreeMap::new();
        let bar = crate::progress::nodes(&wall.config.wall.name, total);
        let mut first_round = true;
        loop {
            wall.try_nodes(&mut errors, &bar, &mut first_up).await;
            if errors.is_empty() {
                bar.finish_and_clear();
                return Ok(wall);
            }
            let waiting: Vec<&str> = errors.keys().map(String::as_str).collect();
            bar.set_message(format!("waiting for {}", waiting.join(", ")));
            if first_round {
                // Name the unreachable nodes and why at once, not only at the timeout.
                for e in errors.values() {
                    crate::progress::say(&bar, &format!("isowall: cannot reach node {e}; retrying"));
                }
                first_round = false;
            }
            if first_up.is_some_and(|t| t.elapsed() >= grace) {
                bar.finish_and_clear();
                for e in errors.values() {
                    eprintln!("isowall: starting without node {e}; it joins when it answers");
                }
                let now = Instant::now();
                for node in errors.keys() {
                    wall.last_try.insert(node.clone(), now);
                }
                return Ok(wall);
            }
            if start.elapsed() > timeout {
                bar.finish_and_clear();
                let list: Vec<String> = errors.values().cloned().collect();
                bail!(
                    "cannot reach {} of {} nodes after {:?}:\n  {}",
                    errors.len(),
                    total,
                    timeout,
                    list.join("\n  ")
                );
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// One round of connecting: every node not up yet, at once (a dead one costs its timeout
    /// once, not per node). `errors` holds why each node is not up; `first_up` when the first
    /// came up.
    async fn try_nodes(
        &mut self,
        errors: &mut BTreeMap<String, String>,
        bar: &indicatif::ProgressBar,
        first_up: &mut Option<Instant>,
    ) {
        let mut tries = tokio::task::JoinSet::new();
        for node in self.config.nodes.clone() {
            if self.senders.contains_key(&node.name) {
                continue;
            }
            let (ep, limit) = (self.endpoint.clone(), self.limit());
            tries.spawn(async move {
                let r = establish(ep, node.name.clone(), node.address.clone(), limit).await;
                (node, r)
            });
        }
        let total = self.config.nodes.len();
        while let Some(done) = tries.join_next().await {
            let Ok((node, r)) = done else { continue };
            let why = match r {
                Ok(link) => match self.attach(&node.name, link).await {
                    Ok(()) => {
                        errors.remove(&node.name);
                        first_up.get_or_insert_with(Instant::now);
                        bar.set_position(self.senders.len() as u64);
                        let up = format!("isowall: node {} up ({}/{total})", node.name, self.senders.len());
                        crate::progress::say(bar, &up);
                        continue;
                    }
                    Err(e) => format!("{e:#}"),
                },
                Err(e) => printable(&format!("{e:#}")),
            };
            errors.insert(node.name.clone(), format!("{} ({}): {why}", node.name, node.address));
        }
    }

    /// The wall of `config`, no node connected yet: its frame machine set for the wall's
    /// deadline, pings and swap timing.
    fn new(config: WallConfig) -> Result<Wall> {
        let name = isowall_net::tls::CONTROLLER;
        let identity =
            Identity::load(&config.cert_dir(), name).map_err(|e| match e.remedy(name, &config.path) {
                Some(fix) => anyhow!("the controller's certificate: {e}: {fix}"),
                None => anyhow!("the controller's certificate: {e}"),
            })?;
        let endpoint = transport::client(&identity)?;
        let deadline = Duration::from_millis(config.wall.deadline_ms);
        let names: Vec<String> = config.nodes.iter().map(|n| n.name.clone()).collect();
        let (events_tx, events) = mpsc::channel(EVENT_QUEUE);
        let mut machine = FrameController::new(names.clone(), deadline);
        for node in &config.nodes {
            let tiles =
                config.tiles_of(&node.name).iter().map(|t| (t.name.clone(), t.width, t.height)).collect();
            machine.set_node_tiles(&node.name, tiles);
        }
        // A dead node is down once silent for 3 deadlines, pinged often enough to tell, in
        // either mode: in object space it stalls every frame (every node waits for its
        // pixels), in screen space every swap waits a deadline for it, and QUIC's idle timeout
        // alone would take 5 s. The controller asks every node something at least every ping
        // interval, so the silence counted from the first unanswered question is 3 deadlines
        // less one ping interval (at least 2.5 deadlines).
        let ping = FrameController::DEFAULT_PING_INTERVAL.min(deadline / 2);
        machine.set_ping_interval(Some(ping));
        machine.set_swap_timing(config.wall.swap_timing());
        machine.set_silence_limit(Some(deadline * SILENT_DEADLINES - ping));
        let metrics = Arc::new(WallMetrics::new(&names, one_machine(&config)));
        let mut wall = Wall {
            machine,
            config,
            senders: HashMap::new(),
            connections: HashMap::new(),
            links: Links::default(),
            events,
            events_tx,
            endpoint,
            // The clock every process of this machine shares: see `isowall_net::clock`.
            epoch: isowall_net::clock::epoch(),
            next_frame: 1,
            finished: Vec::new(),
            releases: Vec::new(),
            released: 0,
            snapshots: BTreeMap::new(),
            images: None,
            snapshot_bytes: 0,
            reconnecting: Default::default(),
            last_try: HashMap::new(),
            bricks: None,
            identify: false,
            balance: None,
            metrics,
        };
        if wall.config.wall.balance {
            wall.balance = Some(WallBalance {
                balancer: Balancer::for_wall(&wall.config),
                on: true,
                sent: None,
                sent_to: Vec::new(),
                last: None,
                moved_rows: 0,
                changes: 0,
                work: BTreeMap::new(),
                claims: Claims::new(),
                misses: 0,
            });
        }
        if wall.config.wall.mode == isowall_model::WallMode::Object {
            wall.bricks = Some(BrickAssigner::new(names));
        }
        Ok(wall)
    }

    fn limit(&self) -> usize {
        usize::try_from(self.config.wall.message_limit_bytes).unwrap_or(usize::MAX)
    }

    /// Starts reading a greeted link and tells the machine the node is up.
    async fn attach(&mut self, name: &str, link: Link) -> Result<()> {
        let Link { connection, sender, mut receiver } = link;
        // A balanced wall's cost reports are bounded before they are decoded: a split gives a
        // node at most MAX_RECTS_PER_TILE rectangles of each of the wall's tiles.
        if self.balance.is_some() {
            let most = self.config.tiles.len().saturating_mul(MAX_RECTS_PER_TILE);
            let sample = Message::RectCosts { frame_id: 0, costs: Vec::new() };
            let why = format!("a split gives at most {most} rectangles");
            receiver.limit_kind(KindLimit::of(&sample, codec::rect_costs_limit(most), why));
        }
        let tx = self.events_tx.clone();
        let node = name.to_string();
        let id = self.links.attach(name);
        tokio::spawn(async move {
            loop {
                // Waits while the queue is full: the node's stream is read no faster than handled.
                match receiver.recv().await {
                    Ok(Some(m)) => {
                        if tx.send(Event::Message(node.clone(), id, m, Instant::now())).await.is_err() {
                            break;
                        }
                    }
                    Ok(None) => {
                        let _ = tx.send(Event::Closed(node.clone(), id, "connection closed".into())).await;
                        break;
                    }
                    Err(e) => {
                        let _ = tx.send(Event::Closed(node.clone(), id, printable(&e.to_string()))).await;
                        break;
                    }
                }
            }
        });
        let now = self.now();
        let outputs = self.machine.node_up(now, name).map_err(|e| anyhow!("{e}"))?;
        self.senders.insert(name.to_string(), sender);
        self.connections.insert(name.to_string(), connection);
        self.metrics.set_up(name, true);
        self.execute(outputs).await;
        if self.identify {
            let message = Message::Identify { on: true };
            self.execute(vec![ControllerOutput::Send { node: name.to_string(), message }]).await;
        }
        // object space: its home brick is its own again; it gets the map before its first frame.
        if let Some(a) = self.bricks.as_mut() {
            let adoption = a.node_up(now, name);
            self.adoption(adoption).await;
            self.send_map(Some(name)).await;
        }
        Ok(())
    }

    /// object space: carries out the brick assigner's outputs, then sends a changed map to every
    /// node (it takes effect at the next frame; frames in flight stop waiting for a dead node).
    async fn adoption(&mut self, outputs: Vec<AdoptionOutput>) {
        let next = self.next_frame;
        for out in outputs {
            match out {
                AdoptionOutput::Load { node, brick } => {
                    eprintln!("isowall: brick {brick} goes to node {node}: it loads it");
                    // The machine expects the answer for this brick from this node, no other.
                    let send = self.machine.load_brick(&node, brick as u64);
                    self.execute(vec![send]).await;
                }
                AdoptionOutput::Adopted { node, brick, load, since_down } => eprintln!(
                    "isowall: node {node} adopted brick {brick} (loaded in {:.0} ms, {:.0} ms after its node went down); it renders it from frame {next}",
                    load.as_secs_f64() * 1e3,
                    since_down.as_secs_f64() * 1e3
                ),
                AdoptionOutput::Returned { node, brick } => {
                    eprintln!("isowall: brick {brick} is back with node {node} from frame {next}")
                }
                AdoptionOutput::Unheld { brick } => {
                    eprintln!("isowall: brick {brick} has no node up to render it")
                }
            }
        }
        if self.bricks.as_mut().is_some_and(BrickAssigner::take_changed) {
            self.send_map(None).await;
        }
    }

    /// A balanced wall: the split for the frame `state` begins, sent to every up node before the
    /// frame's state where it changed (or to a node that came back, which has none).
    async fn send_split(&mut self, state: &FrameState) {
        let mut up: Vec<String> = self.senders.keys().cloned().collect();
        up.sort();
        let Some(b) = self.balance.as_mut() else { return };
        let still = state.continuity(b.last.as_ref()) == Continuity::Same;
        b.last = Some(*state);
        b.balancer.set_nodes(up.iter().cloned());
        b.balancer.set_held(b.claims.held(state.frame_id));
        let split = if b.on { b.balancer.next_split(still).clone() } else { b.balancer.own_tiles() };
        let config = &self.config;
        b.claims.given(state.frame_id, &split, |t| config.node_of_tile(t).map(|n| n.name.as_str()));
        if b.sent.as_ref() == Some(&split) && b.sent_to == up {
            return;
        }
        if b.sent.as_ref() != Some(&split) {
            b.changes += 1;
        }
        b.sent_to = up.clone();
        let wire = match split_to_wire(&split, &self.config) {
            Ok(w) => w,
            Err(e) => {
                eprintln!("isowall: balance: cannot send the split: {e}");
                return;
            }
        };
        b.moved_rows = 0;
        for r in &split.rects {
            if self.config.node_of_tile(&r.tile).is_some_and(|o| o.name != r.renderer) {
                b.moved_rows += u64::from(r.rows);
            }
        }
        b.sent = Some(split);
        let message = Message::Split { from_frame: state.frame_id, split: wire };
        let sends =
            up.into_iter().map(|node| ControllerOutput::Send { node, message: message.clone() }).collect();
        Box::pin(self.execute(sends)).await;
    }

    /// A balanced wall: what each rectangle `node` rendered cost, for the split's rule and the
    /// node's work in the frame.
    fn observe_costs(&mut self, node: &str, frame_id: u64, costs: &[WireRectCost]) {
        let Some(b) = self.balance.as_mut() else { return };
        let work = b.work.entry(frame_id).or_default().entry(node.to_string()).or_default();
        *work = costs.iter().fold(*work, |w, c| w.saturating_add(c.cost));
        while b.work.len() > 2 * HISTORY {
            b.work.pop_first();
        }
        b.claims.costs(node, frame_id);
        for c in costs {
            let Some(tile) = self.config.tiles.get(c.tile as usize) else { continue };
            let rect = WorkRect {
                tile: tile.name.clone(),
                first_row: c.first_row,
                rows: c.rows,
                renderer: node.into(),
            };
            // Only a rectangle the split gave this node counts (a stale or made-up one is left
            // out); a frame's costs come before its Ready, so before the next frame's split. The
            // cost is a claim, held to what the rectangle's pixels and its prediction allow.
            if b.sent.as_ref().is_some_and(|s| s.rects.contains(&rect)) {
                b.balancer.observe_claim(&rect, c.cost as f64, cost_floor(tile.width, c.rows));
            }
        }
    }

    /// A balanced wall: `miss` holds a node out of the split; said once per hold.
    fn report_miss(&mut self, miss: Miss) {
        let Some(b) = self.balance.as_mut() else { return };
        b.misses += 1;
        eprintln!(
            "isowall: balance: node {} {} in frame {}: it renders only its own tiles until frame {} (miss {})",
            miss.node, miss.why, miss.frame_id, miss.held_until, miss.misses
        );
    }

    /// A balanced wall: how many times a node was held out of the split, and who is held now.
    pub fn held_out(&self) -> Option<(u64, Vec<String>)> {
        let b = self.balance.as_ref()?;
        Some((b.misses, b.balancer.held().iter().cloned().collect()))
    }

    /// A balanced wall: whether the split follows the costs (`true`, the config's default) or
    /// every node renders its own tiles, from the next frame on.
    pub fn set_balance(&mut self, on: bool) {
        if let Some(b) = self.balance.as_mut() {
            b.on = on;
        }
    }

    /// A balanced wall: each node's work in frame `frame_id` (the costs it reported; the nodes
    /// that reported nothing are absent).
    pub fn work(&self, frame_id: u64) -> Option<&BTreeMap<String, u64>> {
        self.balance.as_ref()?.work.get(&frame_id)
    }

    /// A balanced wall: the split sent last, the rows of it that travel to another node, and how
    /// many times the split changed since the wall came up.
    pub fn split(&self) -> Option<(&Split, u64, u64)> {
        let b = self.balance.as_ref()?;
        Some((b.sent.as_ref()?, b.moved_rows, b.changes))
    }

    /// object space: the brick map from the next frame on, to `only` or every up node.
    async fn send_map(&mut self, only: Option<&str>) {
        let Some(a) = &self.bricks else { return };
        let map = a.map(self.next_frame);
        let message = Message::Bricks { from_frame: map.from_frame, holders: map.holders };
        let nodes: Vec<String> = match only {
            Some(n) => vec![n.to_string()],
            None => self.senders.keys().cloned().collect(),
        };
        let sends =
            nodes.into_iter().map(|node| ControllerOutput::Send { node, message: message.clone() }).collect();
        Box::pin(self.execute(sends)).await;
    }

    /// Tries, in the background and at most once a second each, to reach the nodes that are down;
    /// a node that answers rejoins at the next frame.
    fn retry_down_nodes(&mut self) {
        let limit = self.limit();
        for node in self.config.nodes.clone() {
            if self.senders.contains_key(&node.name) || self.reconnecting.contains(&node.name) {
                continue;
            }
            if self.last_try.get(&node.name).is_some_and(|t| t.elapsed() < Duration::from_secs(1)) {
                continue;
            }
            self.last_try.insert(node.name.clone(), Instant::now());
            self.reconnecting.insert(node.name.clone());
            let (tx, ep) = (self.events_tx.clone(), self.endpoint.clone());
            tokio::spawn(async move {
                let ev = match establish(ep, node.name.clone(), node.address.clone(), limit).await {
                    Ok(link) => Event::Reconnected(node.name.clone(), link),
                    Err(_) => Event::Unreachable(node.name.clone()),
                };
                let _ = tx.send(ev).await;
            });
        }
    }

    /// The barrier's machine, for what the reports read of it.
    pub(crate) fn machine(&self) -> &FrameController {
        &self.machine
    }

    pub(crate) fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    /// Carries out the machine's outputs.
    async fn execute(&mut self, outputs: Vec<ControllerOutput>) {
        for out in outputs {
            match out {
                ControllerOutput::Send { node, message } => {
                    let failed = match self.senders.get_mut(&node) {
                        Some(s) => s.send(&message).await.err(),
                        None => None,
                    };
                    if let Some(e) = failed {
                        self.drop_node(&node, &e.to_string());
                        let now = self.now();
                        let more = self.machine.node_down(now, &node, &e.to_string());
                        Box::pin(self.execute(more)).await;
                    }
                }
                ControllerOutput::Released { frame_id, ready, stragglers, barrier } => {
                    let misses: Vec<Miss> = match self.balance.as_mut() {
                        Some(b) => ready.iter().filter_map(|n| b.claims.ready(n, frame_id)).collect(),
                        None => Vec::new(),
                    };
                    misses.into_iter().for_each(|m| self.report_miss(m));
                    if !stragglers.is_empty() {
                        eprintln!(
                            "isowall: frame {frame_id}: swap released without {} (missed the deadline)",
                            stragglers.join(", ")
                        );
                    }
                    self.metrics.released(barrier, &stragglers);
                    self.releases.push((frame_id, barrier, stragglers));
                    self.released += 1;
                    trim_history(&mut self.releases);
                }
                ControllerOutput::NodeDown { node, reason } => {
                    eprintln!("isowall: node {node} is down: {}", printable(&reason));
                    self.metrics.node_down(&node);
                    self.drop_node(&node, &reason);
                    let now = self.now();
                    if let Some(a) = self.bricks.as_mut() {
                        let adoption = a.node_down(now, &node);
                        Box::pin(self.adoption(adoption)).await;
                    }
                }
                ControllerOutput::BrickLoaded { node, brick, load, resident_bytes } => {
                    let now = self.now();
                    if let Some(a) = self.bricks.as_mut() {
                        a.set_resident(&node, resident_bytes);
                        let adoption = match usize::try_from(brick) {
                            Ok(b) => a.loaded(now, &node, b, load),
                            Err(_) => Vec::new(),
                        };
                        Box::pin(self.adoption(adoption)).await;
                    }
                }
                ControllerOutput::BrickFailed { node, brick, reason } => {
                    eprintln!("isowall: node {node} cannot load brick {brick}: {reason}");
                    if let Some(a) = self.bricks.as_mut() {
                        let adoption = match usize::try_from(brick) {
                            Ok(b) => a.load_failed(&node, b),
                            Err(_) => Vec::new(),
                        };
                        Box::pin(self.adoption(adoption)).await;
                    }
                }
                ControllerOutput::FrameDone { stats, .. } => {
                    if let Some(a) = self.bricks.as_mut() {
                        for n in &stats.per_node {
                            if let Some(b) = n.resident_bytes {
                                a.set_resident(&n.node, b);
                            }
                        }
                    }
                    self.metrics.finished(&stats);
                    self.finished.push(stats);
                    trim_history(&mut self.finished);
                }
                ControllerOutput::Snapshot { node, tiles } => {
                    let bytes = tiles.iter().map(|t| t.rgb8.len() as u64).sum::<u64>();
                    self.snapshot_bytes += bytes;
                    self.metrics.tile_images(&node, bytes);
                    self.snapshots.insert(node, tiles);
                }
                // Kept with the frame's statistics in any case; told within the node's budget.
                ControllerOutput::StepLate { node, frame_id, wanted, late, told: Some(held_back) } => {
                    let waited = late.waited.as_secs_f64() * 1e3;
                    let held = self.held_back(&node, held_back);
                    if late.shown_step == wanted {
                        tracing::info!(%node, frame_id, "waited {waited:.0} ms for time step {wanted}{held}");
                    } else {
                        eprintln!(
                            "isowall: node {node} showed time step {} in frame {frame_id}, not {wanted}: not loaded after {waited:.0} ms{held}",
                            late.shown_step
                        );
                    }
                }
                ControllerOutput::StepLate { told: None, .. } => {}
                ControllerOutput::PeerIgnored { node, what, held_back } => {
                    eprintln!("isowall: node {node}: {what}{}", self.held_back(&node, held_back));
                }
                ControllerOutput::RectCosts { node, frame_id, costs } => {
                    self.observe_costs(&node, frame_id, &costs)
                }
                ControllerOutput::PixelsMissing { node, frame_id, peers } => {
                    let misses = match self.balance.as_mut() {
                        Some(b) => b.claims.missing(&node, frame_id, &peers),
                        None => Vec::new(),
                    };
                    misses.into_iter().for_each(|m| self.report_miss(m));
                    if peers.is_empty() {
                        eprintln!(
                            "isowall: node {node} composites every peer's pixels again from frame {frame_id}"
                        );
                    } else {
                        eprintln!(
                            "isowall: node {node} composited frame {frame_id} without the pixels of {} (not in by its compositing deadline)",
                            peers.join(", ")
                        );
                    }
                }
            }
        }
    }

    /// What a line about `node` adds when the machine's line budget held `n` lines back before it.
    fn held_back(&self, node: &str, n: u64) -> String {
        if n == 0 {
            return String::new();
        }
        let every = self.machine.peer_log_interval().as_secs();
        format!(" ({n} more about node {node} not shown: at most a few lines per node per {every} s)")
    }

    /// Whether connection `id` is `node`'s current one.
    fn is_current(&self, node: &str, id: LinkId) -> bool {
        self.senders.contains_key(node) && self.links.is_current(node, id)
    }

    fn drop_node(&mut self, node: &str, reason: &str) {
        self.senders.remove(node);
        self.metrics.set_up(node, false);
        self.links.detach(node);
        if let Some(c) = self.connections.remove(node) {
            transport::close(&c, reason);
        }
    }

    /// Waits for the next event or timeout and lets the machine handle it.
    async fn step(&mut self) {
        self.step_until(None).await
    }

    /// [`Wall::step`], waking at `wake` (controller clock) at the latest.
    async fn step_until(&mut self, wake: Option<Duration>) {
        let timeout = [self.machine.poll_timeout(), wake].into_iter().flatten().min();
        let sleep = match timeout {
            Some(t) => t.saturating_sub(self.now()),
            None => Duration::from_millis(200),
        };
        let event = tokio::select! {
            biased;
            e = self.events.recv() => Some(e),
            _ = tokio::time::sleep(sleep) => None,
        };
        if let Some(e) = event {
            let outputs = self.on_event(e).await;
            self.execute(outputs).await;
            // What is queued already counts before any timer (a node is not silent because the
            // controller was busy), and timers still fire under a flood of events.
            for _ in 0..EVENT_QUEUE {
                let Ok(e) = self.events.try_recv() else { break };
                let outputs = self.on_event(Some(e)).await;
                self.execute(outputs).await;
            }
        }
        let now = self.now();
        if self.machine.poll_timeout().is_some_and(|t| now >= t) {
            let outputs = self.machine.handle_timeout(now);
            self.execute(outputs).await;
        }
    }

    /// Lets the machine handle what arrived from a node (or a reconnection attempt).
    async fn on_event(&mut self, event: Option<Event>) -> Vec<ControllerOutput> {
        match event {
            Some(Event::Message(node, id, _, _) | Event::Closed(node, id, _))
                if !self.is_current(&node, id) =>
            {
                Vec::new()
            }
            Some(Event::Message(node, _, msg, arrived)) => {
                let now = arrived.saturating_duration_since(self.epoch);
                match self.machine.handle(now, &node, msg) {
                    Ok(out) => out,
                    Err(err) => {
                        eprintln!("isowall: closing {node}: {}", printable(&err.to_string()));
                        self.drop_node(&node, &err.to_string());
                        self.machine.node_down(now, &node, &err.to_string())
                    }
                }
            }
            Some(Event::Closed(node, _, reason)) => {
                let now = self.now();
                self.machine.node_down(now, &node, &reason)
            }
            Some(Event::Reconnected(node, link)) => {
                self.reconnecting.remove(&node);
                if self.senders.contains_key(&node) {
                    transport::close(&link.connection, "already connected");
                } else if let Err(e) = self.attach(&node, link).await {
                    eprintln!("isowall: node {node} came back but: {e:#}");
                } else {
                    eprintln!("isowall: node {node} is back; it rejoins at frame {}", self.next_frame);
                }
                Vec::new()
            }
            Some(Event::Unreachable(node)) => {
                self.reconnecting.remove(&node);
                Vec::new()
            }
            None => Vec::new(),
        }
    }

    /// Pings every node a few times so present times can be compared across nodes.
    pub async fn sync_clocks(&mut self, rounds: usize) {
        for _ in 0..rounds {
            let now = self.now();
            let out = self.machine.ping(now);
            self.execute(out).await;
            let until = Instant::now() + Duration::from_millis(20);
            while Instant::now() < until {
                tokio::select! {
                    _ = self.step() => {}
                    _ = tokio::time::sleep_until(until.into()) => break,
                }
            }
        }
        self.clock_metrics();
    }

    /// The nodes' clock error bounds now, as the metrics' gauges.
    fn clock_metrics(&self) {
        for n in &self.config.nodes {
            let bound = self.clock_error_us(&n.name).map(|us| us.max(0) as f64 * 1e-6);
            self.metrics.set_clock_error(&n.name, bound);
        }
    }

    /// The wall's metrics, to serve (`/metrics`).
    pub fn metrics(&self) -> Arc<WallMetrics> {
        self.metrics.clone()
    }

    /// Runs one frame: begins it (on a paced wall, once the previous frame's present time has
    /// come: `FrameController::next_begin_at`) and waits until its swap is released.
    pub async fn frame(&mut self, request: &FrameRequest) -> Result<()> {
        while let Some(at) = self.machine.next_begin_at(self.now()) {
            self.step_until(Some(at)).await;
        }
        self.retry_down_nodes();
        let id = self.next_frame;
        self.next_frame += 1;
        let state = FrameState::new(id, &request.camera, &request.settings, request.scale)
            .at_time_step(request.time_step);
        self.send_split(&state).await;
        let now = self.now();
        let out = self.machine.begin_frame(now, state).map_err(|e| anyhow!("{e}"))?;
        self.execute(out).await;
        while self.releases.last().map(|r| r.0) != Some(id) {
            if self.senders.is_empty() && self.reconnecting.is_empty() {
                bail!("every node of the wall is down");
            }
            self.step().await;
        }
        self.clock_metrics();
        Ok(())
    }

    /// The present times of the wall's frames (margin, frame rate).
    pub fn swap_timing(&self) -> &isowall_model::swap_timing::SwapTiming {
        self.machine.swap_timing()
    }

    /// `node`'s clock offset's error bound now, microseconds (`None` before its first Pong).
    pub fn clock_error_us(&self, node: &str) -> Option<i64> {
        Some(self.machine.clock_offset(node)?.error_at(micros(self.now())))
    }

    /// Swaps that reached `node` after their present time.
    pub fn late_swaps(&self, node: &str) -> u64 {
        self.machine.counters(node).map_or(0, |c| c.late_swaps)
    }

    /// Times the swaps from the next release on (the config's `[wall] swap_margin_ms` and
    /// `frame_rate` otherwise), and forgets the frames' statistics so far: what follows is
    /// measured on its own.
    pub fn set_swap_timing(&mut self, timing: isowall_model::swap_timing::SwapTiming) {
        self.machine.set_swap_timing(timing);
        self.finished.clear();
        self.releases.clear();
    }

    /// The id of the last frame begun (0 before the first).
    pub fn last_frame_id(&self) -> u64 {
        self.next_frame - 1
    }

    /// Waits until every begun frame is finished (presented everywhere, or its present deadline);
    /// at once when this controller has begun none (a snapshot right after connecting).
    pub async fn settle(&mut self) {
        let last = self.next_frame - 1;
        if last == 0 {
            return;
        }
        let give_up = Instant::now() + Duration::from_millis(self.config.wall.deadline_ms) * 2;
        while self.finished.last().map(|f| f.frame_id) != Some(last) && Instant::now() < give_up {
            self.step().await;
        }
    }

    /// object space: the bricks `node` renders from the next frame on (empty in screen space).
    pub fn bricks_of(&self, node: &str) -> Vec<usize> {
        self.bricks.as_ref().map(|a| a.map(self.next_frame).bricks_of(node)).unwrap_or_default()
    }

    /// `node`'s process resident memory, as its last Pong said (every node, local or not).
    pub fn resident_bytes(&self, node: &str) -> Option<u64> {
        self.machine.resident_bytes(node)
    }

    /// Whether `node` is connected (it takes part in the next frame).
    /// The version and GPU `node` last told (`Message::NodeInfo`).
    pub fn node_info(&self, node: &str) -> Option<&isowall_model::messages::NodeInfo> {
        self.machine.node_info(node)
    }

    /// Asks `node` over its connection to restart (`Message::Restart`): it exits for its
    /// supervisor (systemd) to start it again, and rejoins as any node that comes back. Fails
    /// when the node is not connected.
    pub async fn restart(&mut self, node: &str, reason: &str) -> Result<()> {
        if !self.senders.contains_key(node) {
            bail!("node {node} is not connected: nothing to ask it (restart it on its machine)");
        }
        let reason: String = reason.chars().take(isowall_model::messages::MAX_RESTART_REASON_CHARS).collect();
        tracing::info!(%node, %reason, "asking the node to restart");
        let message = Message::Restart { reason };
        self.execute(vec![ControllerOutput::Send { node: node.to_string(), message }]).await;
        Ok(())
    }

    /// Every tile shows (`on`) or stops showing its node's and its own name from the next frame
    /// (`Message::Identify` to every connected node; a node that connects later is told too).
    pub async fn set_identify(&mut self, on: bool) {
        self.identify = on;
        tracing::info!(on, "identify: the tiles {} their names", if on { "show" } else { "no longer show" });
        let sends = self
            .senders
            .keys()
            .map(|node| ControllerOutput::Send { node: node.clone(), message: Message::Identify { on } })
            .collect();
        self.execute(sends).await;
    }

    pub fn identify(&self) -> bool {
        self.identify
    }

    pub fn is_up(&self, node: &str) -> bool {
        self.senders.contains_key(node)
    }

    /// Asks every up node for its last presented tiles downscaled by `divisor` (1: at full
    /// resolution, a snapshot), without waiting: the answers arrive while frames go on, and
    /// [`Wall::take_images`] hands them over once every node asked has answered or is down, or
    /// after `give_up` (a node that never answers holds nothing up longer). Nothing is asked
    /// while another request is pending: `false` then.
    pub async fn request_images(&mut self, divisor: u32, give_up: Duration) -> bool {
        if self.images.is_some() {
            return false;
        }
        self.snapshots.clear();
        let now = self.now();
        let out = if divisor <= 1 {
            self.machine.request_snapshot(now)
        } else {
            self.machine.request_thumbnail(now, divisor)
        };
        let asked: Vec<String> = self.senders.keys().cloned().collect();
        self.images = Some((asked, Instant::now() + give_up));
        self.execute(out).await;
        true
    }

    /// Whether images are asked for and not yet taken.
    pub fn images_pending(&self) -> bool {
        self.images.is_some()
    }

    /// Forgets the pending request (its asker is gone); answers still on their way are dropped
    /// when the next request is made.
    pub fn cancel_images(&mut self) {
        self.images = None;
        self.snapshots.clear();
    }

    /// The tiles of the pending request, once complete (see [`Wall::request_images`]).
    pub fn take_images(&mut self) -> Option<BTreeMap<String, Vec<TileImage>>> {
        let (asked, give_up) = self.images.as_ref()?;
        let waiting = asked.iter().any(|n| !self.snapshots.contains_key(n) && self.senders.contains_key(n));
        if waiting && Instant::now() < *give_up {
            return None;
        }
        self.images = None;
        Some(std::mem::take(&mut self.snapshots))
    }

    /// Gathers every node's last presented tiles at full resolution (a pending request is
    /// finished first), waiting at most 10 s for nodes that do not answer.
    pub async fn snapshot(&mut self) -> BTreeMap<String, Vec<TileImage>> {
        // The frames begun are presented first (at their present times, after their releases):
        // the snapshot shows the last one.
        self.settle().await;
        while self.images.is_some() && self.take_images().is_none() {
            self.step().await;
        }
        self.request_images(1, Duration::from_secs(10)).await;
        loop {
            if let Some(tiles) = self.take_images() {
                return tiles;
            }
            // A step returns at the next event or timer, within 200 ms.
            self.step().await;
        }
    }

    /// Says goodbye to every node and waits, at most [`GOODBYE_WAIT`], for each to close its side
    /// (a node does on Bye). QUIC sends a Bye again where the network lost it, so no node is left
    /// holding this controller's connection, with its seat, for the idle timeout after it has gone.
    pub async fn close(mut self, reason: &str) {
        for (node, s) in self.senders.iter_mut() {
            if let Err(e) = s.send(&Message::Bye { reason: reason.to_string() }).await {
                tracing::debug!(%node, "bye: {e}");
            }
        }
        let until = tokio::time::Instant::now() + GOODBYE_WAIT;
        for (node, c) in &self.connections {
            if tokio::time::timeout_at(until, c.closed()).await.is_err() {
                tracing::debug!(%node, "the node did not close its side within {GOODBYE_WAIT:?} of the Bye");
            }
        }
        for c in self.connections.values() {
            transport::close(c, reason);
        }
        // Reconnections still under way or queued hold connections too: close them all.
        self.endpoint.close(quinn::VarInt::from_u32(0), reason.as_bytes());
        self.endpoint.wait_idle().await;
        self.metrics.closed();
    }
}

/// Whether every node of the wall is on this machine (its address a loopback one): they and the
/// controller share one clock (`isowall_net::clock`), so their own present times give the true
/// swap skew.
pub fn one_machine(config: &WallConfig) -> bool {
    config.nodes.iter().all(|n| transport::resolve(&n.address).is_ok_and(|a| a.ip().is_loopback()))
}

/// A time since the wall's epoch in whole microseconds (saturating), as the wire carries times.
pub(crate) fn micros(t: Duration) -> i64 {
    i64::try_from(t.as_micros()).unwrap_or(i64::MAX)
}
