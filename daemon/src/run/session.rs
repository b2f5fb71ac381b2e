//! The session loop: one seated controller at a time, its messages fed to the model's
//! [`NodeMachine`], its outputs carried out (render jobs, presents, snapshots, object space's
//! pixels and adoptions).

use super::admission::Greeted;
use super::space::SpaceEvent;
use super::{shown_tiles, Node};
use crate::object::Done;
use crate::presenter::Shown;
use crate::render_thread::{JobResult, TileJob, TileResult};
use anyhow::{anyhow, Result};
use isowall_model::messages::{Message, ProtocolError, RESTART_EXIT_CODE};
use isowall_model::node_machine::{NodeMachine, NodeOutput};
use isowall_model::wire::{Continuity, FrameSpec, FrameState};
use isowall_net::transport::{self, Channel, NetError};
use std::time::{Duration, Instant};

/// Serves one controller until its connection ends (it closes it, or it is silent for the QUIC
/// idle timeout). Another controller that connects meanwhile is refused with the reason, and the
/// session goes on undisturbed (the model's [`isowall_model::seat`]: the newest controller taking
/// over made two controllers take a node from each other every second forever). An error means
/// the node cannot go on (its render thread is gone): the process exits and its supervisor
/// restarts it.
pub(super) async fn serve(
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
    node.space.reset();
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
        let outputs = tokio::select! {
            m = msg_rx.recv() => match m.map(|(at, r)| (at.saturating_duration_since(node.epoch), r)) {
                Some((arrived, Ok(Some(msg)))) => match from_controller(node, &mut machine, arrived, msg) {
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
                Some(Ok(done)) => rendered(node, &mut machine, &mut sender, done).await,
                Some(Err(e)) => {
                    tracing::error!("render failed: {e}");
                    transport::close(&connection, &format!("render failed: {e}"));
                    break Ok(());
                }
                None => break Err(anyhow!("the render thread has stopped")),
            },
            Some(shown) = node.shown_rx.recv() => presented(node, &mut machine, shown),
            event = node.space.next() => space_event(node, &mut machine, &mut sender, event).await,
            Some(other) = conns.recv() => {
                refuse_second(node, other);
                Vec::new()
            }
        };
        match execute(node, &mut machine, &mut sender, outputs).await {
            Ok(()) => {}
            Err(Ended::Restart(reason)) => restart(&connection, &reason).await,
            // The node closes its side at once: it waits for nothing from a controller that is
            // leaving, so a close the network loses does not hold the seat, or count against the
            // controller's connections, for the idle timeout.
            Err(Ended::Goodbye) => {
                transport::close(&connection, "the controller said goodbye");
                break Ok(());
            }
            Err(Ended::Failed(e)) => {
                tracing::warn!("controller connection ended: {e}");
                transport::close(&connection, &e.to_string());
                break Ok(());
            }
        }
        if node.render_dead {
            transport::close(&connection, "the node's render thread has stopped");
            break Err(anyhow!("the render thread has stopped"));
        }
    };
    reader.abort();
    outcome
}

/// A message from the seated controller, arrived at `arrived` of the node's clock, to the
/// machine (object space hears of each frame state first; a Ping's Pong carries the memory).
fn from_controller(
    node: &mut Node,
    machine: &mut NodeMachine,
    arrived: Duration,
    msg: Message,
) -> Result<Vec<NodeOutput>, ProtocolError> {
    if let Message::FrameState(s) = &msg {
        node.space.announce(s.frame_id);
    }
    if matches!(msg, Message::Ping { .. }) {
        machine.set_resident_bytes(process_resident_bytes());
    }
    machine.handle(arrived, msg)
}

/// The render thread finished a frame's tiles (object space: they are done once the peers'
/// pixels are in, or their deadline passed).
async fn rendered(
    node: &mut Node,
    machine: &mut NodeMachine,
    sender: &mut transport::ChannelSender,
    done: JobResult,
) -> Vec<NodeOutput> {
    if !node.slow.is_zero() {
        tokio::time::sleep(node.slow).await;
    }
    if let Some(o) = node.space.object_mut() {
        let done = o.local_done(done);
        return composited(node, machine, sender, done).await;
    }
    if let Some(b) = node.space.balanced_mut() {
        let done = b.local_done(done);
        return composited(node, machine, sender, done).await;
    }
    frame_done(node, machine, sender, done, Vec::new()).await
}

/// Another controller came while one holds the seat: refused with the seat's reason, the
/// session undisturbed.
fn refuse_second(node: &mut Node, other: Greeted) {
    let from = other.channel.connection.remote_address();
    let link = node.next_link;
    node.next_link += 1;
    if let Err(reason) = node.seat.take(node.epoch.elapsed(), link, &from.to_string()) {
        tracing::warn!(%from, "refused a second controller: {reason}");
        transport::close(&other.channel.connection, &reason);
    }
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

/// object space or a balanced wall: what it waited for came (`Space::next`).
async fn space_event(
    node: &mut Node,
    machine: &mut NodeMachine,
    sender: &mut transport::ChannelSender,
    event: SpaceEvent,
) -> Vec<NodeOutput> {
    if let Some(b) = node.space.balanced_mut() {
        let done = match event {
            SpaceEvent::Peer(item) => b.peer(item),
            SpaceEvent::Deadline => b.handle_timeout(),
            SpaceEvent::Loaded(_) => Vec::new(),
        };
        return composited(node, machine, sender, done).await;
    }
    let Some(o) = node.space.object_mut() else { return Vec::new() };
    let done = match event {
        SpaceEvent::Peer(item) => o.peer(item),
        SpaceEvent::Deadline => o.handle_timeout(),
        SpaceEvent::Loaded(loaded) => {
            let msg = o.load_done(loaded);
            if let Err(e) = sender.send(&msg).await {
                tracing::warn!("{e}");
            }
            return Vec::new();
        }
    };
    composited(node, machine, sender, done).await
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
                                fetches: 0,
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
                    fetches: 0,
                })
                .collect();
            if let Err(e) = node.renderer.show(d.job.frame_id, images) {
                tracing::error!(frame_id = d.job.frame_id, node = %node.name, "{e:#}");
            }
        }
        out.extend(frame_done(node, machine, sender, d.job, d.reports).await);
    }
    out
}

/// A frame's tiles are done (rendered; in object space, composited): keep them for the swap and
/// tell the controller (object space: `report`, the machine's Composited, first).
async fn frame_done(
    node: &mut Node,
    machine: &mut NodeMachine,
    sender: &mut transport::ChannelSender,
    done: JobResult,
    reports: Vec<Message>,
) -> Vec<NodeOutput> {
    let (id, t) = (done.frame_id, done.render_time);
    if machine.rendering() != Some(id) {
        // A frame the frame machine no longer waits for (superseded, or of an older session).
        return Vec::new();
    }
    for msg in reports {
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
    if let Some(s) = done.surface {
        let msg = Message::Surface { frame_id: id, hits: s.hits, level0: s.level0 };
        if let Err(e) = sender.send(&msg).await {
            tracing::warn!("{e}");
        }
    }
    node.pending = Some(done);
    machine.render_done(node.epoch.elapsed(), id, t)
}

/// Why the session ends after [`execute`].
enum Ended {
    /// The controller said Bye.
    Goodbye,
    /// The controller asked the node to restart (the reason).
    Restart(String),
    /// Its connection failed, or what it asked cannot be carried out.
    Failed(NetError),
}

impl From<NetError> for Ended {
    fn from(e: NetError) -> Ended {
        Ended::Failed(e)
    }
}

/// Carries out the machine's outputs (and those they lead to).
async fn execute(
    node: &mut Node,
    machine: &mut NodeMachine,
    sender: &mut transport::ChannelSender,
    outputs: Vec<NodeOutput>,
) -> Result<(), Ended> {
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
                render(node, &state, (accumulate_frame, continuity))
            }
            NodeOutput::Present { frame_id, at } => present(node, frame_id, at),
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
            NodeOutput::Bricks { from_frame, holders } => match node.space.object_mut() {
                Some(o) => match o.set_map(from_frame, holders) {
                    Ok(done) => queue.extend(composited(node, machine, sender, done).await),
                    Err(e) => {
                        let reason = format!("protocol violation by `controller` (Bricks): {e}");
                        tracing::warn!("closing the controller connection: {reason}");
                        return Err(NetError::Connection { peer: "controller".into(), reason }.into());
                    }
                },
                None => tracing::warn!("ignoring a brick map: this wall is not in object mode"),
            },
            // A balanced wall: the split from a frame on (`balanced.rs`).
            NodeOutput::Split { from_frame, split } => match node.space.balanced_mut() {
                Some(b) => {
                    if let Err(e) = b.set_split(from_frame, &split) {
                        let reason = format!("protocol violation by `controller` (Split): {e}");
                        tracing::warn!("closing the controller connection: {reason}");
                        return Err(NetError::Connection { peer: "controller".into(), reason }.into());
                    }
                }
                None => tracing::warn!("ignoring a split: this wall does not balance (`[wall] balance`)"),
            },
            NodeOutput::LoadBrick { brick } => match node.space.object_mut() {
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
                if on && node.space.composites() {
                    tracing::warn!("identify: tiles put together from other nodes' pixels do not show names; only plain screen space does");
                }
                node.identify = on;
            }
            NodeOutput::Restart { reason } => return Err(Ended::Restart(reason)),
            NodeOutput::Closed { reason } => {
                tracing::info!(
                    "the controller said goodbye: {}",
                    isowall_model::messages::printable(&reason)
                );
                return Err(Ended::Goodbye);
            }
        }
    }
    Ok(())
}

/// Renders a frame: the node's space makes the model's plan, the render thread carries it out.
fn render(node: &mut Node, state: &FrameState, (accumulate_frame, continuity): (u32, Continuity)) {
    let spec = match FrameSpec::try_from(state) {
        Ok(s) => s,
        Err(e) => {
            tracing::warn!("frame {}: {e}", state.frame_id);
            return;
        }
    };
    let _span = tracing::info_span!("frame", frame_id = spec.frame_id, node = %node.name).entered();
    let plan =
        node.space.plan(&node.config, &node.tiles, &spec, (accumulate_frame, continuity), &node.renderer);
    tracing::debug!(accumulate_frame, scale = plan.scale, views = plan.views.len(), "render");
    let identify = node.identify.then(|| node.name.clone());
    if let Err(e) = node.renderer.submit(TileJob { plan, identify }) {
        tracing::error!("{e}");
        node.render_dead = true;
    }
}

/// The Swap came: the frame's tiles become the ones presenting, shown at `at` of the node's clock
/// (now when `None`) in its windows or by the presenting thread.
fn present(node: &mut Node, frame_id: u64, at: Option<Duration>) {
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
                let _ = node.shown_tx.send(Shown { frame_id, waiting_from: now, result: Err(e.to_string()) });
            }
        }
    } else {
        node.presenter.present(frame_id, at);
    }
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
