//! Bringing a wall up for the commands that drive one (`demo`, `session`): connect to a running
//! wall, or with `--local` first start a daemon for every loopback node (as `isowall up` does).

use crate::local::LocalDaemons;
use crate::wall::Wall;
use anyhow::{anyhow, bail, Result};
use clap::Args;
use isowall_model::config::WallConfig;
use std::time::Duration;

/// How long a wall that is starting waits, after its last node connected, for nodes that are
/// still on their way before it drives the ones it has.
pub const START_GRACE: Duration = Duration::from_secs(3);

#[derive(Args, Clone, Debug)]
pub struct StartArgs {
    /// Start a local `isowalld` for every loopback node first (stopped on exit), as `isowall up`
    #[arg(long)]
    pub local: bool,
    /// With --local: where the local nodes show their tiles (offscreen, window, auto)
    #[arg(long, default_value = "offscreen", value_parser = ["offscreen", "window", "auto"])]
    pub display: String,
    /// With --local --display window|auto: windows at the tiles' sizes instead of fullscreen
    #[arg(long)]
    pub windowed: bool,
    /// How long to wait for the nodes, seconds
    #[arg(long, default_value_t = 120)]
    pub start_timeout: u64,
}

/// Connects to the wall (starting local nodes with `--local`); the daemons, if any, stop when
/// the returned guard drops. Names every node that cannot be reached.
pub async fn open(config: WallConfig, a: &StartArgs) -> Result<(Option<LocalDaemons>, Wall)> {
    let mut daemons = if a.local {
        let log_dir = config.resolve("logs");
        let mut d = LocalDaemons::start(&config, &log_dir, &a.display, a.windowed)?;
        eprintln!("isowall: starting wall '{}': {} local node(s)", config.wall.name, d.len());
        tokio::task::block_in_place(|| d.wait_started(Duration::from_secs(a.start_timeout)));
        Some(d)
    } else {
        None
    };
    let timeout = Duration::from_secs(a.start_timeout);
    let wall = match daemons.as_mut() {
        Some(d) => connect_local(d, config, timeout).await?,
        None => Wall::connect(config, timeout, START_GRACE).await?,
    };
    Ok((daemons, wall))
}

/// Connects to a wall whose loopback nodes are `daemons`, started by this controller: a daemon
/// that has exited, or exits while the controller tries, stops it at once with that daemon's
/// reason (the end of its log), rather than trying its address until `timeout`, where another
/// process may answer in its place.
pub async fn connect_local(
    daemons: &mut LocalDaemons,
    config: WallConfig,
    timeout: Duration,
) -> Result<Wall> {
    if let Some(report) = daemons.exit_report() {
        bail!("{report}");
    }
    tokio::select! {
        wall = Wall::connect(config, timeout, START_GRACE) => {
            wall.map_err(|e| match daemons.exit_report() {
                Some(report) => anyhow!("{e:#}\n{report}"),
                None => e,
            })
        }
        report = daemons.first_exit() => Err(anyhow!("{report}")),
    }
}
