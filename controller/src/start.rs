//! Bringing a wall up for the commands that drive one (`demo`, `session`): connect to a running
//! wall, or with `--local` first start a daemon for every loopback node (as `isowall up` does).

use crate::local::LocalDaemons;
use crate::wall::Wall;
use anyhow::{anyhow, Result};
use clap::Args;
use isowall_model::config::WallConfig;
use std::time::Duration;

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
    let log_dir = config.resolve("logs");
    match Wall::connect(config, Duration::from_secs(a.start_timeout), crate::drive::START_GRACE).await {
        Ok(wall) => Ok((daemons, wall)),
        Err(e) => {
            let dead = daemons.as_mut().map(|d| d.exited()).unwrap_or_default();
            if dead.is_empty() {
                Err(e)
            } else {
                let list: Vec<String> = dead.iter().map(|(n, s)| format!("{n} ({s})")).collect();
                Err(anyhow!(
                    "{e:#}\nlocal daemons that exited: {} (see {})",
                    list.join(", "),
                    log_dir.display()
                ))
            }
        }
    }
}
