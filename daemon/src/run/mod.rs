//! `isowalld run`: a wall node. It loads the volume, opens the GPU on its render thread, listens
//! for the controller over QUIC (mutual TLS against the wall CA), and drives the model's
//! [`NodeMachine`] with what arrives: render the node's tiles for each frame state, reply Ready,
//! present on Swap, answer snapshots with the last presented tiles. Presenting makes the rendered
//! tiles the shown ones (kept for snapshots) and, where the node has windows (`--display`, see
//! `display.rs`), draws them there first: `Presented` then carries the moment the windows were
//! presented. The network code only moves bytes and calls the state machine; the render thread
//! alone touches the GPU.

use crate::display::{self, Display, DisplayMode, WindowSetup};
use crate::object::ObjectNode;
use crate::presenter::{Presenter, Shown};
use crate::render::load_wall_volume;
use crate::render_thread::{
    JobResult, RenderHandle, RenderVolume, StepsOf, TileRenderer, TileResult, TimeSteps,
};
use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use isowall_model::config::{WallConfig, WallMode};
use isowall_model::messages::TileImage;
use isowall_net::pixels::PixelInbox;
use isowall_net::transport::{self};
use isowall_net::Identity;
use isowall_render::environment::{EnvSource, Environment};
use std::path::PathBuf;
use std::time::Instant;
use tokio::sync::mpsc::UnboundedReceiver;

mod admission;
mod session;
mod space;

use crate::balanced::BalancedNode;
use admission::{admit, Greeted, Handshakes, LiveConnections};
use session::serve;
use space::{BalancedSpace, ObjectSpace, Space};

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
    /// Screen or object space, and what object space waits on (`space.rs`).
    space: Space,
}

/// The tiles on show (the last presented frame), each downscaled by `divisor` (1: as shown).
async fn shown_tiles(node: &Node, divisor: u32) -> Vec<TileImage> {
    let image =
        |t: &TileResult, id: u64| TileImage::downscale(&t.name, t.width, t.height, id, &t.rgb8, divisor);
    match &node.shown {
        // object space and a balanced wall: the tiles put together on the CPU.
        Some((id, tiles)) if node.space.composites() => tiles.iter().map(|t| image(t, *id)).collect(),
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
    let identity = Identity::load(&config.cert_dir(), &node.name).map_err(|e| {
        match e.remedy(&node.name, &a.config) {
            Some(fix) => anyhow!("node '{}': {e}: {fix}", node.name),
            None => anyhow!("node '{}': {e}", node.name),
        }
    })?;
    // Before the slow set-up, so that `--display window` without a display, or a port another
    // process holds, fails at once.
    let display = display::choose(a.display)?;
    transport::check_bindable(transport::resolve(&node.address)?)?;
    crate::notify::status("loading the volume");
    let raw = config.raw_spec().map_err(|e| anyhow!("{e}"))?;
    let limit = usize::try_from(config.wall.message_limit_bytes).unwrap_or(usize::MAX);
    // What the node's volume (or its brick and halo) may hold.
    // Held whole, the volume must fit one storage binding; through the brick cache only the
    // limit on what a source that cannot be read by bricks loads whole applies.
    let budgets = config.brick_budgets();
    let volume_limit = crate::render::volume_limit(
        config.volume.max_bytes.map(|b| (b, "[volume] max_bytes")),
        budgets.is_none(),
    )?;
    // object space: only the brick and its halo.
    let steps;
    let (volume, space) = if config.wall.mode == WallMode::Object {
        let setup = crate::object::load_brick(&config, &node.name, raw.as_ref(), volume_limit)?;
        // A time-varying volume: the brick of every step, within the same budget.
        let (cache_bytes, wait) = step_budget(&config);
        steps = crate::object::brick_steps(&setup, cache_bytes)?.map(|cache| TimeSteps { cache, wait });
        let (load_tx, load_rx) = tokio::sync::mpsc::unbounded_channel();
        let mut object = ObjectNode::new(&config, &node.name, &setup, load_tx)?;
        object.adopt_delay = std::time::Duration::from_millis(a.adopt_delay_ms);
        let (tx, peer_rx) = tokio::sync::mpsc::channel(64);
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
        let space = ObjectSpace { node: object, peer_rx, inbox, load_rx };
        (RenderVolume::Brick(Box::new(setup.data)), Space::Object(Box::new(space)))
    } else {
        let volume = match budgets {
            None => {
                steps = time_steps(&config, raw.as_ref(), volume_limit.clone())?;
                RenderVolume::Whole(load_wall_volume(&config, &volume_limit)?.0)
            }
            Some(budgets) => {
                // Refused before any step is loaded: the steps would load whole.
                let source: isowall_volume::VolumeSource = config.volume_source().parse()?;
                if source.time_steps().with_context(|| format!("volume {source}"))? > 1 {
                    bail!(
                        "{}: [volume] gpu_budget_mb: a time-varying volume is not read through the brick cache yet: its steps load whole (remove gpu_budget_mb)",
                        config.path.display()
                    );
                }
                steps = None;
                let bricked = crate::bricked::BrickedVolume::open(
                    Some(&config.volume_source()),
                    raw.as_ref(),
                    (config.volume.iso, &crate::render::wall_iso_from(&config)),
                    0,
                    &volume_limit,
                )?;
                RenderVolume::Bricked(Box::new((bricked, budgets)))
            }
        };
        let space = if config.wall.balance {
            let balanced = BalancedNode::new(&config, &node.name)?;
            let (tx, peer_rx) = tokio::sync::mpsc::channel(64);
            let nodes = config.nodes.iter().map(|n| n.name.clone()).collect();
            if balanced.max_pixels_bytes() > limit {
                tracing::warn!(
                    "balance: the rectangles of this node's tiles one peer sends a frame may take up to {} bytes \
                     (raw), more than `[wall] message_limit_bytes` {limit}: a frame with that much is placed \
                     without them; raise the limit where the tiles are large",
                    balanced.max_pixels_bytes()
                );
            }
            // A peer's stream may be no longer than all of this node's tiles.
            let inbox = PixelInbox::new(
                tx,
                nodes,
                &node.name,
                limit.min(balanced.max_pixels_bytes()),
                balanced.deadline(),
            );
            Space::Balanced(Box::new(BalancedSpace { node: balanced, peer_rx, inbox }))
        } else {
            Space::Screen
        };
        (volume, space)
    };
    let env_src: EnvSource = config.env_source().parse().context("[render] env")?;
    let env = Environment::from_source(&env_src).context("cannot load the environment")?;
    let (tx, results) = tokio::sync::mpsc::unbounded_channel();
    // The presenting thread ahead of the renders: real-time, and a core of its own where given
    // (the render thread, started next, and its workers are kept off that core).
    let present_priority = node.present_priority(&config.wall);
    if let Some(cpu) = node.present_cpu {
        if let Err(e) = crate::realtime::keep_off(cpu) {
            tracing::warn!("present_cpu {cpu}: {e}: the render threads may use it too");
        }
    }
    crate::notify::status("opening the GPU device");
    let windows = matches!(display, Display::Windows(_));
    let renderer =
        TileRenderer::start(volume, Some(env), tx, steps, if windows { present_priority } else { 0 })?;
    let (shown_tx, shown_rx) = tokio::sync::mpsc::unbounded_channel();
    let (presenter, offscreen_presents) = Presenter::start(
        shown_tx.clone(),
        if windows { 0 } else { present_priority },
        node.present_cpu.filter(|_| !windows),
    )
    .context("cannot start the presenting thread")?;
    let presenting = if windows { renderer.window_presents.clone() } else { offscreen_presents };
    match &presenting {
        crate::realtime::PresentScheduling::Refused(why) => tracing::warn!(
            "the presenting thread runs at normal scheduling: real-time (SCHED_FIFO {present_priority}) was refused ({why}): {}",
            crate::realtime::refused_advice(present_priority)
        ),
        other => tracing::info!("the presenting thread runs {}", other.describe()),
    }
    let addr = transport::resolve(&node.address)?;
    let setup = WindowSetup {
        mode: a.display,
        windowed: a.windowed,
        wall: config.wall.name.clone(),
        node: node.name.clone(),
        tiles: config.tiles_of(&node.name).into_iter().cloned().collect(),
    };
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
        identify: false,
        info: isowall_model::messages::NodeInfo {
            version: env!("CARGO_PKG_VERSION").to_string(),
            adapter: renderer.gpu.adapter.clone(),
            backend: renderer.gpu.backend.clone(),
            driver: renderer.gpu.driver.clone(),
            driver_info: renderer.gpu.driver_info.clone(),
            present: presenting.describe(),
        },
        seat: isowall_model::seat::Seat::new(&node.name, transport::IDLE_TIMEOUT),
        next_link: 0,
        pending: None,
        presenting: std::collections::VecDeque::new(),
        presenter,
        shown_tx,
        shown_rx,
        shown: None,
        space,
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
        state.space.open_endpoint(&identity)?;
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
        let inbox = state.space.inbox();
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
