//! `isowall console CONFIG`: the controller's frame loop (as `isowall session` drives it) plus an
//! HTTP server on the same tokio runtime, serving one page (embedded: `assets/`) and the JSON API
//! it uses (`api.rs`): the wall live as a thumbnail, a card per node, rolling charts of frame
//! time and measured swap skew, and the render, camera and time-step controls.
//!
//! The frame loop owns the [`Wall`](crate::wall::Wall); HTTP handlers never touch it. They read
//! the latest [`Status`](status::Status) (published by the loop a few times a second) and send
//! [`Command`]s that the loop carries out between frames, answering on a oneshot channel.
//! Thumbnails are downscaled at the nodes (`Message::ThumbnailRequest`) and asked for only when a
//! request wants one, at most [`pictures::IMAGES_MAX_HZ`] times a second whatever the number of
//! clients (`pictures.rs`: shared, bounded per client and in total, never in the frame loop's
//! way). The HTTP server (`server.rs`) bounds connections and the time to send a request.

mod api;
mod bookmarks;
mod commands;
mod frame_loop;
mod lock;
mod logs;
mod patch;
mod pictures;
mod server;
mod shared;
mod status;

use crate::drive::{load, runtime, scene_with_box, time_steps};
use crate::start::{self, StartArgs};
use anyhow::{bail, Context, Result};
use clap::Args;
use std::net::SocketAddr;
use std::path::PathBuf;

#[derive(Args)]
pub struct ConsoleArgs {
    /// The wall config (TOML)
    pub config: PathBuf,
    /// The HTTP address to serve the page and the API on; one that is not loopback needs --token
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:8080")]
    pub listen: String,
    /// A bearer token every API request must carry (`Authorization: Bearer T`; the page's
    /// WebSocket sends it as a subprotocol, never in a URL); at least 16 characters
    #[arg(long, value_name = "T")]
    pub token: Option<String>,
    /// Show the wall and its health only: no controls, and the API refuses every change
    #[arg(long)]
    pub read_only: bool,
    /// A camera path (keyframes in TOML, as `isowall demo --path`) the page can start and stop
    #[arg(long, value_name = "FILE")]
    pub demo_path: Option<PathBuf>,
    /// The operator lock lapses after this many seconds without a change from its holder
    #[arg(long, value_name = "S", default_value_t = lock::DEFAULT_IDLE.as_secs(), value_parser = clap::value_parser!(u64).range(1..=86400))]
    pub lock_idle_s: u64,
    /// The camera bookmarks file (default: beside the config, CONFIG.bookmarks.toml); its folder
    /// must be writable (a service whose config folder is read-only keeps them elsewhere)
    #[arg(long, value_name = "FILE")]
    pub bookmarks: Option<PathBuf>,
    #[command(flatten)]
    pub start: StartArgs,
}

/// Serves `/metrics` of `metrics` on `listener` (`isowall up --metrics`, a loopback address)
/// under the console's server limits, until `shutdown` resolves.
pub async fn serve_metrics(
    listener: tokio::net::TcpListener,
    metrics: std::sync::Arc<crate::metrics::WallMetrics>,
    shutdown: impl std::future::Future<Output = ()>,
) {
    server::serve(listener, api::metrics_router(metrics), server::Limits::default(), shutdown).await
}

/// The shortest token accepted.
pub const MIN_TOKEN_CHARS: usize = 16;

/// Who may use the console: checked before anything starts.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Access {
    pub listen: SocketAddr,
    pub token: Option<String>,
    pub read_only: bool,
}

/// Safe by default: loopback unless `--listen` names another address, which then needs a token.
pub fn access(listen: &str, token: Option<&str>, read_only: bool) -> Result<Access> {
    let addr: SocketAddr = listen
        .parse()
        .with_context(|| format!("--listen {listen}: not an address:port (e.g. 127.0.0.1:8080)"))?;
    if let Some(t) = token {
        if t.chars().count() < MIN_TOKEN_CHARS {
            bail!("--token: at least {MIN_TOKEN_CHARS} characters, not {}", t.chars().count());
        }
    }
    if !addr.ip().is_loopback() && token.is_none() {
        bail!(
            "--listen {addr} is not a loopback address: anyone who reaches it could drive the wall; \
             give --token T (a bearer token) or listen on 127.0.0.1"
        );
    }
    Ok(Access { listen: addr, token: token.map(str::to_string), read_only })
}

pub fn console(a: &ConsoleArgs) -> Result<()> {
    let access = access(&a.listen, a.token.as_deref(), a.read_only)?;
    let config = load(&a.config)?;
    let ((camera, settings, range, framing), volume_box) = scene_with_box(&config)?;
    let steps = time_steps(&config)?;
    let demo = match &a.demo_path {
        Some(p) => {
            let defaults = crate::path::Defaults {
                fov_y_deg: camera.fov_y_deg,
                iso: settings.iso,
                ao_samples: settings.ao.samples,
            };
            let path =
                crate::path::CameraPath::load(p, defaults, isowall_model::render_state::MAX_AO_SAMPLES)?;
            crate::demo::warn_misfits(&path, p, volume_box, framing.fit);
            Some((p.clone(), path))
        }
        None => None,
    };
    runtime()?.block_on(async {
        // Bind first: a taken port fails before any node is started.
        let listener = tokio::net::TcpListener::bind(access.listen)
            .await
            .with_context(|| format!("cannot listen on {}", access.listen))?;
        let local = listener.local_addr().context("listening address")?;
        let (daemons, wall) = start::open(config, &a.start).await?;
        let scene = frame_loop::Scene { camera, settings, range, framing, steps, demo };
        let limits = server::Limits::default();
        let options = shared::Options {
            bookmarks: a.bookmarks.clone().unwrap_or_else(|| bookmarks::path_for(&a.config)),
            lock_idle: std::time::Duration::from_secs(a.lock_idle_s),
            metrics: wall.metrics(),
        };
        let (shared, commands) = shared::Shared::new(access.clone(), limits, options);
        let looper = tokio::spawn(frame_loop::run(wall, daemons, scene, shared.clone(), commands));
        // Printed for scripts and tests: the page's address, once it serves.
        println!("isowall console: serving http://{local}/");
        // Ctrl-C ends this command cleanly (its local nodes stop when it drops them).
        crate::local::interrupt_handled_by_command();
        let server = server::serve(listener, api::router(shared.clone()), limits, async {
            let _ = tokio::signal::ctrl_c().await;
        });
        tokio::select! {
            () = server => {}
            r = looper => r.context("the console's frame loop")??,
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loopback_needs_no_token_and_anything_else_does() {
        let a = access("127.0.0.1:8080", None, false).unwrap();
        assert_eq!((a.listen.port(), a.token, a.read_only), (8080, None, false));
        assert!(access("[::1]:0", None, true).is_ok());
        let e = access("0.0.0.0:8080", None, false).unwrap_err().to_string();
        assert!(e.contains("not a loopback address") && e.contains("--token"), "{e}");
        let e = access("192.168.1.4:80", Some("short"), false).unwrap_err().to_string();
        assert!(e.contains("at least 16 characters, not 5"), "{e}");
        assert!(access("0.0.0.0:8080", Some("0123456789abcdef"), false).is_ok());
        let e = access("localhost:8080", None, false).unwrap_err().to_string();
        assert!(e.contains("not an address:port"), "{e}");
    }
}
