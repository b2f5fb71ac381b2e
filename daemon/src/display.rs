//! Where a wall node shows its tiles (`isowalld run --display auto|window|offscreen`): a window per
//! tile where a display exists, otherwise offscreen (the rendered tiles are only kept, for
//! snapshots).
//!
//! With windows the threads are:
//! - the main thread runs winit's event loop (X11 wants it there): it opens the windows, follows
//!   their resizes and exposures, and shuts the node down when one is closed;
//! - the network thread runs the async runtime and the QUIC session (as the main thread does
//!   offscreen); it starts once the windows can present, and asks the render thread to present at
//!   each swap;
//! - the render thread owns the wgpu device and, from its own instance, the windows' surfaces.
//!
//! This build opens X11 windows only (winit's `x11` feature; Wayland sessions run X11 clients
//! through Xwayland).

use crate::render_thread::{RenderHandle, TileRenderer, TileWindow};
use anyhow::{anyhow, Context, Result};
use isowall_model::config::TileConfig;
use std::sync::Arc;
use winit::application::ApplicationHandler;
use winit::dpi::{PhysicalPosition, PhysicalSize};
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, EventLoop, EventLoopProxy};
use winit::monitor::MonitorHandle;
use winit::window::{Fullscreen, Window, WindowId};

/// `--display`: how the node presents its tiles.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum DisplayMode {
    /// Windows where a display exists (DISPLAY or WAYLAND_DISPLAY set and a window opens), else
    /// offscreen
    Auto,
    /// Windows, or fail
    Window,
    /// No windows: rendered tiles are kept for snapshots only
    Offscreen,
}

/// The outcome of [`choose`].
pub enum Display {
    Offscreen,
    /// A display is open; windows come when the event loop runs.
    Windows(Box<EventLoop<NodeEvent>>),
}

/// Sent to the event loop from other threads.
#[derive(Debug)]
pub enum NodeEvent {
    /// The network thread has ended (its result is in its join handle).
    NetworkEnded,
}

/// Called first in `main`, before anything opens Vulkan (and before any other thread exists, as
/// changing the environment needs). Mesa's device-select layer (an implicit Vulkan layer) asks
/// the Wayland compositor for the default GPU whenever the instance enables
/// `VK_KHR_wayland_surface` (wgpu always does, where available), and libwayland prints
/// `error: XDG_RUNTIME_DIR is invalid or not set in the environment.` where there is no runtime
/// directory: on every headless node, for every command. No Wayland compositor can be reached
/// there, so the probe can only fail: the layer is disabled (`NODEVICE_SELECT=1`, its own switch)
/// unless the user chose a device through it (`MESA_VK_DEVICE_SELECT`) or set the switch already.
/// The adapter is chosen by wgpu in any case (`GpuContext::new`).
pub fn quiet_vulkan_without_wayland() {
    let runtime_dir = std::env::var_os("XDG_RUNTIME_DIR").filter(|d| !d.is_empty());
    let reachable = runtime_dir.is_some_and(|d| std::path::Path::new(&d).is_dir());
    if !reachable
        && std::env::var_os("MESA_VK_DEVICE_SELECT").is_none()
        && std::env::var_os("NODEVICE_SELECT").is_none()
    {
        std::env::set_var("NODEVICE_SELECT", "1");
    }
}

/// The value of an environment variable that names a display, if set and not empty.
fn display_var(name: &str) -> Option<String> {
    std::env::var(name).ok().filter(|v| !v.is_empty())
}

/// Picks the presentation for `mode`; logs the choice when it is offscreen.
pub fn choose(mode: DisplayMode) -> Result<Display> {
    if mode == DisplayMode::Offscreen {
        tracing::info!("presenting offscreen (--display offscreen)");
        return Ok(Display::Offscreen);
    }
    let (x11, wayland) = (display_var("DISPLAY"), display_var("WAYLAND_DISPLAY"));
    let problem = match (&x11, &wayland) {
        (None, None) => Some("there is no display (neither DISPLAY nor WAYLAND_DISPLAY is set)".to_string()),
        (None, Some(w)) => Some(format!(
            "WAYLAND_DISPLAY={w} but no DISPLAY: this build opens X11 windows only (run Xwayland)"
        )),
        (Some(_), _) => None,
    };
    let opened = match problem {
        Some(p) => Err(p),
        // winit panics where an X11 library it loads at run time is missing (libxkbcommon-x11):
        // that must not take a node down.
        None => match std::panic::catch_unwind(|| EventLoop::<NodeEvent>::with_user_event().build()) {
            Ok(built) => built.map_err(|e| {
                // winit says "os error at FILE:LINE: what"; keep the what.
                let e = e.to_string();
                let what =
                    e.strip_prefix("os error at ").and_then(|r| r.split_once(": ")).map_or(&*e, |x| x.1);
                format!("cannot open the X display {}: {what}", x11.as_deref().unwrap_or_default())
            }),
            Err(_) => Err(format!(
                "cannot open the X display {}: winit failed (an X11 library missing?)",
                x11.as_deref().unwrap_or_default()
            )),
        },
    };
    match opened {
        Ok(event_loop) => Ok(Display::Windows(Box::new(event_loop))),
        Err(e) if mode == DisplayMode::Auto => {
            if x11.is_some() || wayland.is_some() {
                tracing::warn!("{e}: presenting offscreen");
            } else {
                tracing::info!("{e}: presenting offscreen");
            }
            Ok(Display::Offscreen)
        }
        Err(e) => Err(anyhow!("--display window: {e}; use --display offscreen (or auto) on a headless node")),
    }
}

/// What the windows need to know.
pub struct WindowSetup {
    pub mode: DisplayMode,
    /// Windows at the tiles' sizes instead of fullscreen (desktop testing).
    pub windowed: bool,
    pub wall: String,
    pub node: String,
    pub tiles: Vec<TileConfig>,
}

/// Starts the network: called on the network thread with whether the windows present, and a
/// signal that the node is shutting down.
pub type StartNetwork = Box<dyn FnOnce(bool, tokio::sync::oneshot::Receiver<()>) -> Result<()> + Send>;

/// Runs the node with windows: the event loop on this (the main) thread until a window is closed
/// or the network ends, then shuts down in order: network, render thread (and its surfaces),
/// windows.
pub fn run_windows(
    event_loop: Box<EventLoop<NodeEvent>>,
    setup: WindowSetup,
    renderer: TileRenderer,
    network: StartNetwork,
) -> Result<()> {
    let mut app = App {
        proxy: event_loop.create_proxy(),
        setup,
        render: renderer.handle(),
        windows: Vec::new(),
        network: Some(network),
        net: None,
        error: None,
    };
    let ran = (*event_loop).run_app(&mut app).context("the window event loop failed");
    let App { windows, render, net, error, .. } = app;
    let mut result = match error {
        Some(e) => Err(e),
        None => ran,
    };
    if let Some((thread, stop)) = net {
        let _ = stop.send(());
        let net_result = thread.join().map_err(|_| anyhow!("the network thread panicked")).and_then(|r| r);
        if result.is_ok() {
            result = net_result;
        }
    }
    drop(render);
    renderer.join();
    drop(windows);
    result
}

struct App {
    proxy: EventLoopProxy<NodeEvent>,
    setup: WindowSetup,
    render: RenderHandle,
    windows: Vec<(WindowId, String, Arc<Window>)>,
    /// Taken when the network starts.
    network: Option<StartNetwork>,
    net: Option<(std::thread::JoinHandle<Result<()>>, tokio::sync::oneshot::Sender<()>)>,
    error: Option<anyhow::Error>,
}

impl App {
    /// One window per tile: fullscreen (borderless) with tile i on monitor i, the primary first;
    /// windowed at the tile's size where `--windowed` or where there is no monitor i.
    fn open_windows(&self, event_loop: &ActiveEventLoop) -> Result<Vec<TileWindow>> {
        let mut monitors: Vec<MonitorHandle> = event_loop.primary_monitor().into_iter().collect();
        for m in event_loop.available_monitors() {
            if !monitors.contains(&m) {
                monitors.push(m);
            }
        }
        let s = &self.setup;
        let mut out = Vec::new();
        for (i, tile) in s.tiles.iter().enumerate() {
            let mut attrs = Window::default_attributes()
                .with_title(format!("isowall {}: {} ({})", s.wall, tile.name, s.node))
                .with_inner_size(PhysicalSize::new(tile.width, tile.height));
            let monitor = if s.windowed { None } else { monitors.get(i).cloned() };
            match &monitor {
                Some(m) => {
                    // The monitor's geometry as well: with no window manager (a bare X server on
                    // a wall node) nobody acts on the fullscreen request, but the geometry holds.
                    let size = m.size();
                    attrs = attrs
                        .with_fullscreen(Some(Fullscreen::Borderless(Some(m.clone()))))
                        .with_position(m.position())
                        .with_inner_size(size)
                        .with_decorations(false);
                    if (size.width, size.height) != (tile.width, tile.height) {
                        tracing::warn!(
                            tile = %tile.name,
                            "monitor {} is {}x{}, the tile {}x{}: the image is stretched to fill it",
                            m.name().unwrap_or_else(|| format!("#{i}")),
                            size.width,
                            size.height,
                            tile.width,
                            tile.height
                        );
                    }
                }
                None if !s.windowed => tracing::warn!(
                    tile = %tile.name,
                    "no monitor {i} for this tile ({} found): windowed at {}x{}",
                    monitors.len(),
                    tile.width,
                    tile.height
                ),
                // Windowed (a wall tried out on one desktop): at the tile's place in the wall, so
                // the tiles sit side by side as on the wall (a window manager may move them).
                None => attrs = attrs.with_position(PhysicalPosition::new(tile.x as i32, tile.y as i32)),
            }
            let window = event_loop
                .create_window(attrs)
                .with_context(|| format!("cannot open a window for tile {}", tile.name))?;
            if monitor.is_some() {
                window.set_cursor_visible(false);
            }
            let size = window.inner_size();
            out.push(TileWindow {
                tile: tile.name.clone(),
                window: Arc::new(window),
                size: (size.width, size.height),
            });
        }
        Ok(out)
    }

    /// Opens the windows and their surfaces; `Ok(false)` where `auto` falls back to offscreen.
    fn start_windows(&mut self, event_loop: &ActiveEventLoop) -> Result<bool> {
        let auto = self.setup.mode == DisplayMode::Auto;
        let windows = match self.open_windows(event_loop) {
            Ok(w) => w,
            Err(e) if auto => {
                tracing::warn!("{e:#}: presenting offscreen");
                return Ok(false);
            }
            Err(e) => return Err(e),
        };
        let kept: Vec<(WindowId, String, Arc<Window>)> =
            windows.iter().map(|w| (w.window.id(), w.tile.clone(), w.window.clone())).collect();
        match self.render.attach(windows) {
            Ok(lines) => {
                for line in lines {
                    tracing::info!(windowed = self.setup.windowed, "presenting tile {line}");
                }
                self.windows = kept;
                Ok(true)
            }
            Err(e) if auto => {
                tracing::warn!("cannot present in windows ({e:#}): presenting offscreen");
                Ok(false)
            }
            Err(e) => Err(e.context("--display window: cannot present in a window")),
        }
    }

    fn tile_of(&self, id: WindowId) -> Option<&str> {
        self.windows.iter().find(|(w, ..)| *w == id).map(|(_, t, _)| t.as_str())
    }
}

impl ApplicationHandler<NodeEvent> for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        // Windows and the network start once (desktop platforms resume once).
        let Some(network) = self.network.take() else { return };
        let on_screen = match self.start_windows(event_loop) {
            Ok(on) => on,
            Err(e) => {
                self.error = Some(e);
                event_loop.exit();
                return;
            }
        };
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel();
        let proxy = self.proxy.clone();
        let spawned = std::thread::Builder::new().name("network".into()).spawn(move || {
            let r = network(on_screen, stop_rx);
            let _ = proxy.send_event(NodeEvent::NetworkEnded);
            r
        });
        match spawned {
            Ok(thread) => self.net = Some((thread, stop_tx)),
            Err(e) => {
                self.error = Some(anyhow!("cannot start the network thread: {e}"));
                event_loop.exit();
            }
        }
    }

    fn user_event(&mut self, event_loop: &ActiveEventLoop, event: NodeEvent) {
        match event {
            NodeEvent::NetworkEnded => event_loop.exit(),
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, id: WindowId, event: WindowEvent) {
        let Some(tile) = self.tile_of(id).map(str::to_string) else { return };
        match event {
            WindowEvent::CloseRequested | WindowEvent::Destroyed => {
                tracing::info!(%tile, "the window was closed: shutting down");
                event_loop.exit();
            }
            WindowEvent::Resized(size) => self.render.resize(&tile, size.width, size.height),
            WindowEvent::RedrawRequested => self.render.redraw(&tile),
            _ => {}
        }
    }
}
