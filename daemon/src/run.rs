//! `isowalld run`: a wall node. It loads the volume, opens the GPU on its render thread, listens
//! for the controller over QUIC (mutual TLS against the wall CA), and drives the model's
//! [`NodeMachine`] with what arrives: render the node's tiles for each frame state, reply Ready,
//! present on Swap, answer snapshots with the last presented tiles. Presenting makes the rendered
//! tiles the shown ones (kept for snapshots) and, where the node has windows (`--display`, see
//! `display.rs`), draws them there first: `Presented` then carries the moment the windows were
//! presented. The network code only moves bytes and calls the state machine; the render thread
//! alone touches the GPU.

use crate::display::{self, Display, DisplayMode, WindowSetup};
use crate::object::{Done, LoadDone, ObjectNode};
use crate::presenter::{Presenter, Shown};
use crate::render::load_volume_within;
use crate::render_thread::{
    JobResult, RenderHandle, RenderVolume, StepsOf, TileJob, TileRenderer, TileResult, TimeSteps,
};
use anyhow::{anyhow, Context, Result};
use clap::Args;
use isowall_model::config::{WallConfig, WallMode};
use isowall_model::handshake_limit::{HandshakeLimit, HandshakeLimiter};
use isowall_model::messages::{Message, TileImage, RESTART_EXIT_CODE};
use isowall_model::node_machine::{NodeMachine, NodeOutput};
use isowall_model::wire::FrameSpec;
use isowall_net::pixels::{PeerPixelsIn, PixelInbox};
use isowall_net::tls::PeerIdentity;
use isowall_net::transport::{self, Channel, NetError};
use isowall_net::Identity;
use isowall_render::environment::{EnvSource, Environment};
use std::path::PathBuf;
use std::time::Instant;
use tokio::sync::mpsc::UnboundedReceiver;

#[derive(Args, Debug, Clone)]
pub struct RunArgs {
    /// The wall config (TOML)
    #[arg(long, value_name = "FILE")]
    pub config: PathBuf,
    /// This node's name in the config
    #[arg(long, value_name = "NAME")]
    pub node: String,
    /// Fault injection for tests and demos of the barrier: hold every frame this long after it
    /// has rendered before replying Ready (a slow node)
    #[arg(long, value_name = "MS", default_value_t = 0, hide_short_help = true)]
    pub slow_ms: u64,
    /// Fault injection for tests of object space: wait this long before reading a brick adopted
    /// from a dead node (a slow disk), so frames run while it loads
    #[arg(long, value_name = "MS", default_value_t = 0, hide_short_help = true)]
    pub adopt_delay_ms: u64,
    /// Where to show the tiles: a fullscreen window per tile (`window`), none (`offscreen`: tiles
    /// are kept for snapshots only), or `auto`: windows when a display exists (DISPLAY or
    /// WAYLAND_DISPLAY set and a window opens), else offscreen
    #[arg(long, value_enum, value_name = "MODE", default_value = "auto")]
    pub display: DisplayMode,
    /// Windows at the tiles' sizes instead of fullscreen (testing a wall on a desktop)
    #[arg(long)]
    pub windowed: bool,
    /// Reach peer NODE at HOST:PORT instead of its address in the wall config (object space sends
    /// pixels node to node): an override for NAT, relays and tests. Repeatable, one per peer
    #[arg(long = "peer-addr", value_name = "NODE=HOST:PORT", value_parser = crate::peer_addr::parse)]
    pub peer_addr: Vec<crate::peer_addr::PeerAddr>,
}

/// What the node needs beyond the network.
struct Node {
    name: String,
    config: WallConfig,
    tiles: Vec<String>,
    renderer: RenderHandle,
    /// The render thread presents in windows at each swap.
    on_screen: bool,
    results: UnboundedReceiver<Result<JobResult, String>>,
    epoch: Instant,
    limit: usize,
    /// The render thread is gone: the node must exit (and be restarted).
    render_dead: bool,
    /// The controller asked the node to restart (`Message::Restart`), and why.
    restart: Option<String>,
    /// The operator asked the tiles to show their names (`Message::Identify`).
    identify: bool,
    /// What the node tells the controller after its Hello: its version and GPU.
    info: isowall_model::messages::NodeInfo,
    /// Which controller drives the node: one at a time (the model's rule).
    seat: isowall_model::seat::Seat,
    /// The number of the next controller connection served or refused.
    next_link: u64,
    /// Fault injection: extra delay before Ready.
    slow: std::time::Duration,
    /// Rendered, waiting for the swap.
    pending: Option<JobResult>,
    /// Swapped, waiting for their present time: (frame, tiles), oldest first.
    presenting: std::collections::VecDeque<(u64, Vec<TileResult>)>,
    /// Presents at each swap's time where the node presents offscreen (`presenter.rs`).
    presenter: Presenter,
    /// Frames presented, from the presenter or the render thread's windows.
    shown_tx: tokio::sync::mpsc::UnboundedSender<Shown>,
    shown_rx: UnboundedReceiver<Shown>,
    /// The tiles on show (the last presented frame), for snapshots.
    shown: Option<(u64, Vec<TileResult>)>,
    // object space
    /// The brick's compositing and peers (`object.rs`); `None` in screen space.
    object: Option<ObjectNode>,
    /// Peers' pixels as they arrive, and who hands their connections over.
    peer_rx: Option<tokio::sync::mpsc::Receiver<PeerPixelsIn>>,
    inbox: Option<PixelInbox>,
    /// Adopted bricks loaded (or not), for the controller.
    load_rx: Option<UnboundedReceiver<LoadDone>>,
}

/// The tiles on show (the last presented frame), each downscaled by `divisor` (1: as shown).
async fn shown_tiles(node: &Node, divisor: u32) -> Vec<TileImage> {
    let image =
        |t: &TileResult, id: u64| TileImage::downscale(&t.name, t.width, t.height, id, &t.rgb8, divisor);
    match &node.shown {
        // object space: the composited tiles, on the CPU.
        Some((id, tiles)) if node.object.is_some() => tiles.iter().map(|t| image(t, *id)).collect(),
        // screen space: the images stayed on the GPU; read them now.
        Some((id, _)) => match node.renderer.snapshot(*id).await {
            Ok(tiles) => tiles.iter().map(|t| image(t, *id)).collect(),
            Err(e) => {
                tracing::warn!(frame_id = id, "snapshot: {e:#}");
                Vec::new()
            }
        },
        None => Vec::new(),
    }
}

/// A time-varying volume's budget on a node: the bytes of steps kept loaded ahead (`[volume]
/// cache_bytes`) and the longest a frame waits for a step not loaded yet (half the wall's
/// deadline, at most 10 s).
fn step_budget(config: &WallConfig) -> (usize, std::time::Duration) {
    let cache_bytes = usize::try_from(config.cache_bytes()).unwrap_or(usize::MAX);
    let wait =
        std::time::Duration::from_millis(config.wall.deadline_ms / 2).min(std::time::Duration::from_secs(10));
    (cache_bytes, wait)
}

/// A time-varying volume's steps for the render thread in screen space (whole volumes), within
/// [`step_budget`]. `None` for a volume without time steps.
fn time_steps(
    config: &WallConfig,
    raw: Option<&isowall_volume::io::RawSpec>,
    limit: isowall_volume::io::VolumeLimit,
) -> Result<Option<TimeSteps>> {
    let source: isowall_volume::VolumeSource = config.volume_source().parse()?;
    let count = source.time_steps().with_context(|| format!("volume {source}"))?;
    if count < 2 {
        return Ok(None);
    }
    let (cache_bytes, wait) = step_budget(config);
    tracing::info!(volume = %source, steps = count, cache_bytes, "time-varying volume");
    let cache = isowall_volume::steps::StepCache::new(source, raw.cloned(), cache_bytes, limit)?;
    Ok(Some(TimeSteps { cache: StepsOf::Volume(cache), wait }))
}

pub fn run(a: &RunArgs) -> Result<()> {
    let mut config = WallConfig::load(&a.config).map_err(|e| anyhow!("{e}"))?;
    let node = config
        .node(&a.node)
        .ok_or_else(|| {
            let names: Vec<&str> = config.nodes.iter().map(|n| n.name.as_str()).collect();
            anyhow!("{}: no node '{}' (nodes: {})", a.config.display(), a.node, names.join(", "))
        })?
        .clone();
    crate::peer_addr::apply(&mut config, &node.name, &a.peer_addr)?;
    let identity = Identity::load(&config.cert_dir(), &node.name).with_context(|| {
        format!(
            "no certificate for node '{}': run `isowall keygen --config {}`",
            node.name,
            a.config.display()
        )
    })?;
    // Before the slow set-up, so that `--display window` without a display, or a port another
    // process holds, fails at once.
    let display = display::choose(a.display)?;
    transport::check_bindable(transport::resolve(&node.address)?)?;
    crate::notify::status("loading the volume");
    let raw = config.raw_spec().map_err(|e| anyhow!("{e}"))?;
    let limit = usize::try_from(config.wall.message_limit_bytes).unwrap_or(usize::MAX);
    // What the node's volume (or its brick and halo) may hold.
    let volume_limit =
        crate::render::volume_limit(config.volume.max_bytes.map(|b| (b, "[volume] max_bytes")), true)?;
    // object space: only the brick and its halo.
    let steps;
    let (volume, object, peer_rx, inbox, load_rx) = if config.wall.mode == WallMode::Object {
        let setup = crate::object::load_brick(&config, &node.name, raw.as_ref(), volume_limit)?;
        // A time-varying volume: the brick of every step, within the same budget.
        let (cache_bytes, wait) = step_budget(&config);
        steps = crate::object::brick_steps(&setup, cache_bytes)?.map(|cache| TimeSteps { cache, wait });
        let (load_tx, load_rx) = tokio::sync::mpsc::unbounded_channel();
        let mut object = ObjectNode::new(&config, &node.name, &setup, load_tx)?;
        object.adopt_delay = std::time::Duration::from_millis(a.adopt_delay_ms);
        let (tx, rx) = tokio::sync::mpsc::channel(64);
        let nodes = config.nodes.iter().map(|n| n.name.clone()).collect();
        if object.max_pixels_bytes() > limit {
            tracing::warn!(
                "object space: a peer's pixels for one frame may take up to {} bytes ({:?} form, raw), more than \
                 `[wall] message_limit_bytes` {limit}: a frame with that much in view composites without them; \
                 raise the limit where the tiles are large",
                object.max_pixels_bytes(),
                object.form()
            );
        }
        // A peer's stream may be no longer than what its bricks can send this node's tiles.
        let inbox =
            PixelInbox::new(tx, nodes, &node.name, limit.min(object.max_pixels_bytes()), object.deadline());
        (RenderVolume::Brick(Box::new(setup.data)), Some(object), Some(rx), Some(inbox), Some(load_rx))
    } else {
        let iso_from = format!("{}: [volume] iso", config.path.display());
        let (volume, _iso) = load_volume_within(
            Some(&config.volume_source()),
            raw.as_ref(),
            (config.volume.iso, &iso_from),
            &volume_limit,
        )?;
        steps = time_steps(&config, raw.as_ref(), volume_limit)?;
        (RenderVolume::Whole(volume), None, None, None, None)
    };
    let env_src: EnvSource = config.env_source().parse().context("[render] env")?;
    let env = Environment::from_source(&env_src).context("cannot load the environment")?;
    let (tx, results) = tokio::sync::mpsc::unbounded_channel();
    crate::notify::status("opening the GPU device");
    let renderer = TileRenderer::start(volume, Some(env), tx, steps)?;
    let addr = transport::resolve(&node.address)?;
    let setup = WindowSetup {
        mode: a.display,
        windowed: a.windowed,
        wall: config.wall.name.clone(),
        node: node.name.clone(),
        tiles: config.tiles_of(&node.name).into_iter().cloned().collect(),
    };
    let (shown_tx, shown_rx) = tokio::sync::mpsc::unbounded_channel();
    let mut state = Node {
        name: node.name.clone(),
        tiles: node.tiles.clone(),
        config,
        renderer: renderer.handle(),
        on_screen: false,
        results,
        // The clock every process of this machine shares: see `isowall_net::clock`.
        epoch: isowall_net::clock::epoch(),
        limit,
        slow: std::time::Duration::from_millis(a.slow_ms),
        render_dead: false,
        restart: None,
        identify: false,
        info: isowall_model::messages::NodeInfo {
            version: env!("CARGO_PKG_VERSION").to_string(),
            adapter: renderer.gpu.adapter.clone(),
            backend: renderer.gpu.backend.clone(),
            driver: renderer.gpu.driver.clone(),
            driver_info: renderer.gpu.driver_info.clone(),
        },
        seat: isowall_model::seat::Seat::new(&node.name, transport::IDLE_TIMEOUT),
        next_link: 0,
        pending: None,
        presenting: std::collections::VecDeque::new(),
        presenter: Presenter::start(shown_tx.clone()).context("cannot start the presenting thread")?,
        shown_tx,
        shown_rx,
        shown: None,
        object,
        peer_rx,
        inbox,
        load_rx,
    };
    match display {
        Display::Offscreen => network(state, addr, identity, None),
        Display::Windows(event_loop) => {
            let start = Box::new(move |on_screen: bool, stop| {
                state.on_screen = on_screen;
                network(state, addr, identity, Some(stop))
            });
            display::run_windows(event_loop, setup, renderer, start)
        }
    }
}

/// The node's network side: listens for controllers and serves them, one at a time, until `stop`
/// fires (then it closes the endpoint, telling a connected controller) or forever.
fn network(
    mut state: Node,
    addr: std::net::SocketAddr,
    identity: Identity,
    stop: Option<tokio::sync::oneshot::Receiver<()>>,
) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    runtime.block_on(async move {
        if let Some(o) = state.object.as_mut() {
            o.open_endpoint(&identity)?;
        }
        let endpoint = transport::server(addr, &identity)?;
        tracing::info!(node = %state.name, %addr, "listening for the controller");
        // Systemd (Type=notify) and scripts wait for this line.
        println!("isowalld: node {} ready on {addr}", state.name);
        // The render thread has its device (TileRenderer::start) and the endpoint is bound.
        crate::notify::ready(&format!("node {} listening on {addr}, waiting for the controller", state.name));
        // Handshakes run in their own tasks (a slow or silent peer holds up nobody). Only a
        // connection whose certificate is the controller's and whose Hello is checked queues
        // here, and only such a one may take over the session (cancel-safe); nodes' connections
        // go to the object-space inbox, everything else is refused without touching the session.
        let (conn_tx, mut conns) = tokio::sync::mpsc::channel::<Greeted>(2);
        let acceptor = endpoint.clone();
        let inbox = state.inbox.clone();
        let limit = state.limit;
        let live = LiveConnections::default();
        let handshakes = Handshakes::new(state.epoch);
        tokio::spawn(async move {
            while let Some(incoming) = acceptor.accept().await {
                // Before any crypto: a source whose handshakes keep failing or being refused
                // is refused here (the model's rule), so a flood costs no TLS work.
                let Some(source) = handshakes.start(&incoming) else {
                    incoming.refuse();
                    continue;
                };
                let (tx, inbox, live) = (conn_tx.clone(), inbox.clone(), live.clone());
                tokio::spawn(async move { admit(incoming, source, tx, inbox, live, limit).await });
            }
        });
        let serve_all = async {
            // One controller at a time: the next is served once the one before has gone.
            while let Some(conn) = conns.recv().await {
                serve(&mut state, &mut conns, conn).await?;
            }
            Ok::<(), anyhow::Error>(())
        };
        let Some(stop) = stop else { return serve_all.await };
        tokio::select! {
            r = serve_all => r,
            _ = stop => {
                crate::notify::stopping("a window was closed: the node is shutting down");
                endpoint.close(0u32.into(), b"the node is shutting down");
                let _ = tokio::time::timeout(std::time::Duration::from_secs(1), endpoint.wait_idle()).await;
                Ok(())
            }
        }
    })
}

/// How long a peer has for its QUIC handshake, and a controller then for its stream and Hello.
const HANDSHAKE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);
const HELLO_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);

/// Live connections a daemon keeps per identity, at most: the controller's session and one being
/// refused (or, once the session's connection has closed, served); a peer node connects once and
/// again after a failure.
const MAX_CONNECTIONS_PER_IDENTITY: usize = 2;

/// A controller's connection whose certificate is the controller's and whose first message is
/// its Hello (checked): only such a connection may drive the node, and only while no other does.
struct Greeted {
    channel: Channel,
    hello: Message,
}

/// The handshake limit of the accept loop (the model's [`HandshakeLimiter`] on the daemon's
/// clock), and its refusals logged at most once a second.
#[derive(Clone)]
struct Handshakes {
    epoch: std::time::Instant,
    inner: std::sync::Arc<std::sync::Mutex<(HandshakeLimiter, Option<std::time::Instant>, u64)>>,
}

/// A handshake the limit let start: give it back ([`Source::admitted`]) once the connection
/// is admitted, so the wall's own connections never spend the limit.
struct Source {
    ip: std::net::IpAddr,
    handshakes: Handshakes,
}

impl Source {
    fn admitted(&self) {
        let now = self.handshakes.epoch.elapsed();
        self.handshakes.inner.lock().expect("not poisoned").0.admitted(now, self.ip);
    }
}

impl Handshakes {
    fn new(epoch: std::time::Instant) -> Handshakes {
        let limiter = HandshakeLimiter::new(HandshakeLimit::DAEMON);
        Handshakes { epoch, inner: std::sync::Arc::new(std::sync::Mutex::new((limiter, None, 0))) }
    }

    /// `Some` when `incoming`'s handshake may start; `None`: refuse it (logged, at most once a
    /// second, with the count).
    fn start(&self, incoming: &quinn::Incoming) -> Option<Source> {
        let remote = incoming.remote_address();
        let ip = remote.ip().to_canonical();
        let mut guard = self.inner.lock().expect("not poisoned");
        let (limiter, last_log, unlogged) = &mut *guard;
        if limiter.start(self.epoch.elapsed(), ip) {
            return Some(Source { ip, handshakes: self.clone() });
        }
        *unlogged += 1;
        if last_log.is_none_or(|t| t.elapsed() >= std::time::Duration::from_secs(1)) {
            let HandshakeLimit { per_second, burst } = HandshakeLimit::DAEMON;
            let (started, refused) = limiter.counts();
            tracing::warn!(
                %remote,
                refused_since_last_line = *unlogged,
                handshakes_started = started,
                refused_in_all = refused,
                "refused a connection before its handshake: too many failed or refused handshakes \
                 from {ip} ({burst} at once, then {per_second} a second)"
            );
            *last_log = Some(std::time::Instant::now());
            *unlogged = 0;
        }
        None
    }
}

/// Live verified connections per identity.
#[derive(Clone, Default)]
struct LiveConnections(std::sync::Arc<std::sync::Mutex<std::collections::HashMap<PeerIdentity, usize>>>);

impl LiveConnections {
    /// Counts `connection` for `who` until it closes; `false` (not counted) past the limit.
    fn admit(&self, who: &PeerIdentity, connection: &quinn::Connection) -> bool {
        {
            let mut live = self.0.lock().expect("not poisoned");
            let n = live.entry(who.clone()).or_default();
            if *n >= MAX_CONNECTIONS_PER_IDENTITY {
                return false;
            }
            *n += 1;
        }
        let (me, who, connection) = (self.clone(), who.clone(), connection.clone());
        tokio::spawn(async move {
            connection.closed().await;
            if let Some(n) = me.0.lock().expect("not poisoned").get_mut(&who) {
                *n = n.saturating_sub(1);
            }
        });
        true
    }
}

/// One incoming connection, in its own task: the handshake, then who it is. The controller's
/// queues for the session once its Hello is checked; another node's goes to the object-space
/// inbox; anything else is closed with the reason. Nothing here touches the running session.
async fn admit(
    incoming: quinn::Incoming,
    source: Source,
    session: tokio::sync::mpsc::Sender<Greeted>,
    inbox: Option<PixelInbox>,
    live: LiveConnections,
    limit: usize,
) {
    let remote = incoming.remote_address();
    let conn = match tokio::time::timeout(HANDSHAKE_TIMEOUT, incoming).await {
        Ok(Ok(c)) => c,
        Ok(Err(e)) => {
            tracing::warn!(%remote, "refused a connection: {e}");
            return;
        }
        Err(_) => {
            tracing::warn!(%remote, "refused a connection: handshake timed out");
            return;
        }
    };
    let refuse = |peer: &dyn std::fmt::Display, reason: String| {
        tracing::warn!(%remote, %peer, "refused a connection: {reason}");
        transport::close(&conn, &reason);
    };
    let who = match isowall_net::tls::peer_identity(&conn) {
        Ok(who) => who,
        Err(e) => return refuse(&"unknown", e),
    };
    if !live.admit(&who, &conn) {
        let reason = format!("{who} already has {MAX_CONNECTIONS_PER_IDENTITY} connections open");
        return refuse(&who, reason);
    }
    match (&who, inbox) {
        (PeerIdentity::Node(_), Some(inbox)) => {
            source.admitted();
            inbox.accept(conn)
        }
        (PeerIdentity::Node(_), None) => {
            refuse(&who, format!("{who}'s certificate is not the controller's: it may not drive a node"))
        }
        (PeerIdentity::Controller, _) => match tokio::time::timeout(HELLO_TIMEOUT, greet(&conn, limit)).await
        {
            Ok(Ok(greeted)) => {
                source.admitted();
                let _ = session.send(greeted).await;
            }
            Ok(Err(reason)) => refuse(&who, reason),
            Err(_) => refuse(&who, format!("no stream and Hello within {} s", HELLO_TIMEOUT.as_secs())),
        },
    }
}

/// The controller's stream and its Hello (the first message), checked.
async fn greet(conn: &quinn::Connection, limit: usize) -> Result<Greeted, String> {
    let peer = isowall_net::tls::CONTROLLER;
    let mut channel = Channel::accept(conn.clone(), peer, limit).await.map_err(|e| e.to_string())?;
    let hello = match channel.receiver.recv().await {
        Ok(Some(m)) => m,
        Ok(None) => return Err(format!("`{peer}` ended its stream before its Hello")),
        Err(e) => return Err(e.to_string()),
    };
    if let Err(e) = isowall_model::codec::check_hello(&hello, isowall_model::messages::Role::Controller) {
        return Err(
            isowall_model::messages::ProtocolError::new(peer, hello.kind(), e.to_string()).to_string()
        );
    }
    Ok(Greeted { channel, hello })
}

/// Serves one controller until its connection ends (it closes it, or it is silent for the QUIC
/// idle timeout). Another controller that connects meanwhile is refused with the reason, and the
/// session goes on undisturbed (the model's [`isowall_model::seat`]: the newest controller taking
/// over made two controllers take a node from each other every second forever). An error means
/// the node cannot go on (its render thread is gone): the process exits and its supervisor
/// restarts it.
async fn serve(
    node: &mut Node,
    conns: &mut tokio::sync::mpsc::Receiver<Greeted>,
    greeted: Greeted,
) -> Result<()> {
    let link = node.next_link;
    node.next_link += 1;
    let remote = greeted.channel.connection.remote_address();
    if let Err(reason) = node.seat.take(node.epoch.elapsed(), link, &remote.to_string()) {
        // Not reached while serve runs one connection at a time; the rule says it all the same.
        transport::close(&greeted.channel.connection, &reason);
        return Ok(());
    }
    let served = serve_seated(node, conns, greeted).await;
    node.seat.leave(link);
    served
}

/// [`serve`] once the controller holds the node's seat.
async fn serve_seated(
    node: &mut Node,
    conns: &mut tokio::sync::mpsc::Receiver<Greeted>,
    greeted: Greeted,
) -> Result<()> {
    let Greeted { channel, hello } = greeted;
    let remote = channel.connection.remote_address();
    tracing::info!(%remote, "controller connected");
    crate::notify::status(&format!("serving the controller at {remote}"));
    let Channel { connection, mut sender, mut receiver } = channel;
    let mut machine = NodeMachine::new(node.name.clone(), node.tiles.clone());
    node.identify = false;
    node.pending = None;
    node.presenting.clear();
    if let Some(o) = node.object.as_mut() {
        o.reset();
    }
    if let Err(e) = sender.send(&machine.hello()).await {
        tracing::warn!("{e}");
        return Ok(());
    }
    if let Err(e) = machine.handle(node.epoch.elapsed(), hello) {
        transport::close(&connection, &e.to_string());
        return Ok(());
    }
    // Once per connection: the operator's console shows the node's version and GPU.
    if let Err(e) = sender.send(&Message::NodeInfo(node.info.clone())).await {
        tracing::warn!("{e}");
        return Ok(());
    }
    // Each message with the moment it arrived: a Ping's time is that, not when the loop got to it.
    type Arrived = (Instant, Result<Option<Message>, NetError>);
    let (msg_tx, mut msg_rx) = tokio::sync::mpsc::channel::<Arrived>(16);
    let reader = tokio::spawn(async move {
        loop {
            let r = receiver.recv().await;
            let end = !matches!(r, Ok(Some(_)));
            if msg_tx.send((Instant::now(), r)).await.is_err() || end {
                break;
            }
        }
    });
    let outcome = loop {
        let composite_deadline = node.object.as_ref().and_then(|o| o.next_timeout());
        let outputs = tokio::select! {
            m = msg_rx.recv() => match m.map(|(at, r)| (at.saturating_duration_since(node.epoch), r)) {
                Some((arrived, Ok(Some(msg)))) => match {
                    if let (Some(o), Message::FrameState(s)) = (node.object.as_mut(), &msg) {
                        o.announce(s.frame_id);
                    }
                    if matches!(msg, Message::Ping { .. }) {
                        machine.set_resident_bytes(process_resident_bytes());
                    }
                    machine.handle(arrived, msg)
                } {
                    Ok(out) => out,
                    Err(e) => {
                        tracing::warn!("closing the controller connection: {e}");
                        transport::close(&connection, &e.to_string());
                        break Ok(());
                    }
                },
                Some((_, Ok(None))) | None => {
                    tracing::info!("the controller closed the connection");
                    transport::close(&connection, "the controller ended its stream");
                    break Ok(());
                }
                Some((_, Err(e))) => {
                    tracing::warn!("controller connection ended: {e}");
                    transport::close(&connection, &e.to_string());
                    break Ok(());
                }
            },
            r = node.results.recv() => match r {
                Some(Ok(done)) => {
                    if !node.slow.is_zero() {
                        tokio::time::sleep(node.slow).await;
                    }
                    // object space: the tiles are done once the peers' pixels are in (or their
                    // deadline passed).
                    match node.object.as_mut() {
                        Some(o) => {
                            let done = o.local_done(done);
                            composited(node, &mut machine, &mut sender, done).await
                        }
                        None => frame_done(node, &mut machine, &mut sender, done, None).await,
                    }
                }
                Some(Err(e)) => {
                    tracing::error!("render failed: {e}");
                    transport::close(&connection, &format!("render failed: {e}"));
                    break Ok(());
                }
                None => break Err(anyhow!("the render thread has stopped")),
            },
            Some(shown) = node.shown_rx.recv() => presented(node, &mut machine, shown),
            Some(item) = recv_peer(&mut node.peer_rx) => {
                let done = node.object.as_mut().map(|o| o.peer(item)).unwrap_or_default();
                composited(node, &mut machine, &mut sender, done).await
            }
            _ = sleep_until(composite_deadline) => {
                let done = node.object.as_mut().map(|o| o.handle_timeout()).unwrap_or_default();
                composited(node, &mut machine, &mut sender, done).await
            }
            Some(done) = recv_load(&mut node.load_rx) => {
                if let Some(o) = node.object.as_mut() {
                    let msg = o.load_done(done);
                    if let Err(e) = sender.send(&msg).await {
                        tracing::warn!("{e}");
                    }
                }
                Vec::new()
            }
            Some(other) = conns.recv() => {
                let from = other.channel.connection.remote_address();
                let link = node.next_link;
                node.next_link += 1;
                if let Err(reason) = node.seat.take(node.epoch.elapsed(), link, &from.to_string()) {
                    tracing::warn!(%from, "refused a second controller: {reason}");
                    transport::close(&other.channel.connection, &reason);
                }
                Vec::new()
            }
        };
        if let Err(e) = execute(node, &mut machine, &mut sender, outputs).await {
            if let Some(reason) = node.restart.take() {
                restart(&connection, &reason).await;
            }
            tracing::warn!("controller connection ended: {e}");
            break Ok(());
        }
        if node.render_dead {
            transport::close(&connection, "the node's render thread has stopped");
            break Err(anyhow!("the render thread has stopped"));
        }
    };
    reader.abort();
    outcome
}

/// The controller holding the seat asked the node to restart: the connection is closed with the
/// reason and the process exits with [`RESTART_EXIT_CODE`], not 0, so that its supervisor
/// (systemd's `Restart=on-failure`, `wall-configs/systemd/`) starts it again; the controller
/// reconnects it as it does any node that comes back.
async fn restart(connection: &quinn::Connection, reason: &str) -> ! {
    tracing::warn!(
        reason = %reason,
        "the controller asked this node to restart: exiting with status {RESTART_EXIT_CODE} for its supervisor to start it again"
    );
    crate::notify::stopping(&format!("restarting at the controller's request: {reason}"));
    transport::close(connection, "the node restarts at the controller's request");
    // The close goes out before the process does (bounded).
    let _ = tokio::time::timeout(std::time::Duration::from_millis(300), connection.closed()).await;
    std::process::exit(RESTART_EXIT_CODE)
}

/// A frame presented (by the presenter, or the windows on the render thread): its tiles are the
/// ones on show, and the machine sends Presented with its times by the node's clock.
fn presented(node: &mut Node, machine: &mut NodeMachine, shown: Shown) -> Vec<NodeOutput> {
    let Shown { frame_id, waiting_from, result } = shown;
    let at = result.unwrap_or_else(|e| {
        tracing::warn!(frame_id, node = %node.name, "presenting failed: {e}");
        Instant::now()
    });
    while let Some((id, tiles)) = node.presenting.pop_front() {
        if id > frame_id {
            node.presenting.push_front((id, tiles));
            break;
        }
        if id == frame_id {
            node.shown = Some((id, tiles));
            break;
        }
    }
    let since = |t: Instant| t.saturating_duration_since(node.epoch);
    machine.presented(since(at), frame_id, since(waiting_from))
}

/// object space: the next peer's pixels (never, in screen space).
async fn recv_peer(rx: &mut Option<tokio::sync::mpsc::Receiver<PeerPixelsIn>>) -> Option<PeerPixelsIn> {
    match rx {
        Some(rx) => rx.recv().await,
        None => std::future::pending().await,
    }
}

/// object space: the next compositing deadline (never when none is pending).
async fn sleep_until(at: Option<tokio::time::Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

/// object space: frames composited, in order.
async fn composited(
    node: &mut Node,
    machine: &mut NodeMachine,
    sender: &mut transport::ChannelSender,
    done: Vec<Done>,
) -> Vec<NodeOutput> {
    let mut out = Vec::new();
    for mut d in done {
        // The wall filters the composited tile: the render thread filters and composes it.
        if let Some(canvas) = d.canvas.take() {
            let sizes: Vec<(String, u32, u32)> =
                canvas.tiles.iter().map(|(n, v, _)| (n.clone(), v.rect.width, v.rect.height)).collect();
            match node.renderer.compose_canvases(canvas).await {
                Ok(tiles) => d.job.tiles = tiles,
                Err(e) => {
                    tracing::error!(frame_id = d.job.frame_id, node = %node.name, "composing the tiles failed: {e:#}");
                    // Black tiles of the right size: the frame still swaps with the wall.
                    d.job.tiles = sizes
                        .into_iter()
                        .map(|(name, width, height)| {
                            let n = width as usize * height as usize;
                            TileResult {
                                name,
                                width,
                                height,
                                rgb8: vec![0; 3 * n],
                                depth: vec![f32::INFINITY; n],
                                shading: Vec::new(),
                            }
                        })
                        .collect();
                }
            }
        } else if node.on_screen && machine.rendering() == Some(d.job.frame_id) {
            // Composited here on the CPU: the windows show it from images the render thread
            // uploads (its own targets hold this node's brick views). Not a frame the frame
            // machine no longer waits for (`frame_done` drops it).
            let images = d
                .job
                .tiles
                .iter()
                .map(|t| TileResult {
                    name: t.name.clone(),
                    width: t.width,
                    height: t.height,
                    rgb8: t.rgb8.clone(),
                    depth: Vec::new(),
                    shading: Vec::new(),
                })
                .collect();
            if let Err(e) = node.renderer.show(d.job.frame_id, images) {
                tracing::error!(frame_id = d.job.frame_id, node = %node.name, "{e:#}");
            }
        }
        out.extend(frame_done(node, machine, sender, d.job, Some(d.report)).await);
    }
    out
}

/// object space: the next adoption's outcome (never, in screen space).
async fn recv_load(rx: &mut Option<UnboundedReceiver<LoadDone>>) -> Option<LoadDone> {
    match rx {
        Some(rx) => rx.recv().await,
        None => std::future::pending().await,
    }
}

/// A frame's tiles are done (rendered; in object space, composited): keep them for the swap and
/// tell the controller (object space: `report`, the machine's Composited, first).
async fn frame_done(
    node: &mut Node,
    machine: &mut NodeMachine,
    sender: &mut transport::ChannelSender,
    done: JobResult,
    report: Option<Message>,
) -> Vec<NodeOutput> {
    let (id, t) = (done.frame_id, done.render_time);
    if machine.rendering() != Some(id) {
        // A frame the frame machine no longer waits for (superseded, or of an older session).
        return Vec::new();
    }
    if let Some(msg) = report {
        tracing::debug!(frame_id = id, ?msg, "composited");
        if let Err(e) = sender.send(&msg).await {
            tracing::warn!("{e}");
        }
    }
    if let Some((shown_step, waited)) = done.step_late {
        crate::notify::status(&format!(
            "frame {id}: its time step was not loaded in time; waited {:.0} ms, showed step {shown_step}",
            waited.as_secs_f64() * 1e3
        ));
        let waited_us = u64::try_from(waited.as_micros()).unwrap_or(u64::MAX);
        if let Err(e) = sender.send(&Message::StepLate { frame_id: id, shown_step, waited_us }).await {
            tracing::warn!("{e}");
        }
    }
    node.pending = Some(done);
    machine.render_done(node.epoch.elapsed(), id, t)
}

/// Carries out the machine's outputs (and those they lead to).
async fn execute(
    node: &mut Node,
    machine: &mut NodeMachine,
    sender: &mut transport::ChannelSender,
    outputs: Vec<NodeOutput>,
) -> Result<(), NetError> {
    let mut queue: std::collections::VecDeque<NodeOutput> = outputs.into();
    while let Some(out) = queue.pop_front() {
        match out {
            NodeOutput::Send(mut m) => {
                // A Pong says when it leaves: the hold since the Ping arrived is on neither wire.
                if let Message::Pong { sent_us, .. } = &mut m {
                    *sent_us = i64::try_from(node.epoch.elapsed().as_micros()).unwrap_or(i64::MAX);
                }
                sender.send(&m).await?
            }
            NodeOutput::Render { state, accumulate_frame, continuity } => {
                let spec = match FrameSpec::try_from(&state) {
                    Ok(s) => s,
                    Err(e) => {
                        tracing::warn!("frame {}: {e}", state.frame_id);
                        continue;
                    }
                };
                let _span =
                    tracing::info_span!("frame", frame_id = spec.frame_id, node = %node.name).entered();
                let (tiles, settings, bricks) = match node.object.as_mut() {
                    // object space: each brick it holds over its covered rectangle of every tile.
                    Some(o) => {
                        let s = o.bound_settings(spec.frame_id, &spec.settings);
                        let v = o.views(spec.frame_id, spec.camera, &s);
                        for b in v.unload {
                            let _ = node.renderer.unload(b);
                        }
                        (v.views, s, v.bricks)
                    }
                    None => (
                        node.tiles
                            .iter()
                            .filter_map(|t| node.config.tile_view(spec.camera, t).map(|v| (t.clone(), v)))
                            .collect(),
                        spec.settings,
                        Vec::new(),
                    ),
                };
                // object space composites full-resolution depth: it always renders at scale 1.
                let scale = if node.object.is_some() { 1 } else { spec.scale };
                tracing::debug!(accumulate_frame, scale, "render");
                if let Err(e) = node.renderer.submit(TileJob {
                    frame_id: spec.frame_id,
                    tiles,
                    settings,
                    accumulate_frame,
                    continuity,
                    bricks,
                    scale,
                    // object space: the shares travel to the tiles' owners.
                    share: node.object.as_ref().map(|o| o.form()),
                    time_step: spec.time_step,
                    identify: node.identify.then(|| node.name.clone()),
                }) {
                    tracing::error!("{e}");
                    node.render_dead = true;
                }
            }
            NodeOutput::Present { frame_id, at } => {
                if let Some(p) = node.pending.take().filter(|p| p.frame_id == frame_id) {
                    node.presenting.push_back((frame_id, p.tiles));
                }
                // The node's clock is the instants since its epoch.
                let at = at.map(|t| node.epoch + t);
                if node.on_screen {
                    match node.renderer.present(frame_id, at) {
                        Ok(rx) => {
                            let tx = node.shown_tx.clone();
                            tokio::spawn(async move {
                                if let Ok(shown) = rx.await {
                                    let _ = tx.send(shown);
                                }
                            });
                        }
                        Err(e) => {
                            let now = Instant::now();
                            let _ = node.shown_tx.send(Shown {
                                frame_id,
                                waiting_from: now,
                                result: Err(e.to_string()),
                            });
                        }
                    }
                } else {
                    node.presenter.present(frame_id, at);
                }
            }
            NodeOutput::LateSwap { frame_id, late_by } => {
                tracing::info!(
                    frame_id,
                    node = %node.name,
                    late_by_us = late_by.as_micros() as u64,
                    "late swap: the Swap came after its present time; presented at once"
                );
            }
            NodeOutput::SnapshotWanted => {
                sender.send(&Message::Snapshot { tiles: shown_tiles(node, 1).await }).await?;
            }
            // A live thumbnail: downscaled here, so the link carries 1/divisor^2 of the pixels.
            NodeOutput::ThumbnailWanted { divisor } => {
                sender.send(&Message::Snapshot { tiles: shown_tiles(node, divisor).await }).await?;
            }
            // object space: a brick map, an adoption (`object.rs`).
            NodeOutput::Bricks { from_frame, holders } => match node.object.as_mut() {
                Some(o) => match o.set_map(from_frame, holders) {
                    Ok(done) => queue.extend(composited(node, machine, sender, done).await),
                    Err(e) => {
                        let reason = format!("protocol violation by `controller` (Bricks): {e}");
                        tracing::warn!("closing the controller connection: {reason}");
                        return Err(NetError::Connection { peer: "controller".into(), reason });
                    }
                },
                None => tracing::warn!("ignoring a brick map: this wall is not in object mode"),
            },
            NodeOutput::LoadBrick { brick } => match node.object.as_mut() {
                Some(o) => {
                    if let Some(answer) = o.load(brick, &node.renderer) {
                        sender.send(&answer).await?;
                    }
                }
                None => {
                    let reason = "this wall is not in object mode".to_string();
                    sender.send(&Message::BrickFailed { brick, reason }).await?;
                }
            },
            NodeOutput::Identify { on } => {
                tracing::info!(
                    on,
                    "identify: the tiles {} their names",
                    if on { "show" } else { "no longer show" }
                );
                if on && node.object.is_some() {
                    tracing::warn!("identify: object space tiles are composited elsewhere; only screen space shows names");
                }
                node.identify = on;
            }
            NodeOutput::Restart { reason } => {
                node.restart = Some(reason.clone());
                return Err(NetError::Connection { peer: "controller".into(), reason });
            }
            NodeOutput::Closed { reason } => {
                tracing::info!(
                    "the controller said goodbye: {}",
                    isowall_model::messages::printable(&reason)
                );
                return Err(NetError::Connection { peer: "controller".into(), reason });
            }
        }
    }
    Ok(())
}

/// This process's resident memory (`VmRSS` of `/proc/self/status`), told to the controller with
/// each Pong for the operator's node cards; 0 where the OS does not say.
fn process_resident_bytes() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kib =
        status.lines().find_map(|l| l.strip_prefix("VmRSS:")?.trim().strip_suffix("kB")?.trim().parse().ok());
    kib.unwrap_or(0u64) * 1024
}

#[cfg(test)]
mod tests {
    #[test]
    fn this_process_has_resident_memory_on_linux() {
        let bytes = super::process_resident_bytes();
        if cfg!(target_os = "linux") {
            // A test binary holds at least a few MiB, and far less than this machine's memory.
            assert!(bytes > 1 << 20 && bytes < 1 << 40, "{bytes}");
        } else {
            assert_eq!(bytes, 0);
        }
    }
}
