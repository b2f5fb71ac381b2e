//! Local daemons for `isowall up`: one `isowalld run` per node whose address is on loopback,
//! stopped when the controller exits (also on Ctrl-C or an error: they are killed on drop).

use anyhow::{Context, Result};
use isowall_wall::config::WallConfig;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

/// The `isowalld` binary: beside this executable, else on PATH.
pub fn daemon_binary() -> PathBuf {
    std::env::current_exe()
        .ok()
        .and_then(|p| p.parent().map(|d| d.join("isowalld")))
        .filter(|p| p.exists())
        .unwrap_or_else(|| PathBuf::from("isowalld"))
}

/// Whether a node address (`host:port`) is on this machine's loopback.
pub fn is_loopback(address: &str) -> bool {
    let host =
        address.rsplit_once(':').map_or(address, |(h, _)| h).trim_start_matches('[').trim_end_matches(']');
    host == "localhost" || host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

/// Running local daemons; killed when dropped.
pub struct LocalDaemons {
    children: Vec<(String, Child)>,
}

impl LocalDaemons {
    /// Starts a daemon for every loopback node of the wall, with `display` passed on as
    /// `--display` (and `--windowed` if asked). Their logs go to `log_dir/NODE.log`.
    pub fn start(config: &WallConfig, log_dir: &Path, display: &str, windowed: bool) -> Result<LocalDaemons> {
        let bin = daemon_binary();
        std::fs::create_dir_all(log_dir).with_context(|| format!("cannot create {}", log_dir.display()))?;
        let mut me = LocalDaemons { children: Vec::new() };
        for node in config.nodes.iter().filter(|n| is_loopback(&n.address)) {
            let log_path = log_dir.join(format!("{}.log", node.name));
            let log = std::fs::File::create(&log_path)
                .with_context(|| format!("cannot create {}", log_path.display()))?;
            let child = Command::new(&bin)
                .arg("run")
                .arg("--config")
                .arg(&config.path)
                .arg("--node")
                .arg(&node.name)
                .args(["--display", display])
                .args(windowed.then_some("--windowed"))
                .stdin(Stdio::null())
                .stdout(log.try_clone()?)
                .stderr(log)
                .spawn()
                .with_context(|| format!("cannot start {} for node {}", bin.display(), node.name))?;
            eprintln!("isowall: started node {} (pid {}, log {})", node.name, child.id(), log_path.display());
            me.children.push((node.name.clone(), child));
        }
        Ok(me)
    }

    /// Nodes whose daemon has exited, with its status.
    pub fn exited(&mut self) -> Vec<(String, String)> {
        self.children
            .iter_mut()
            .filter_map(|(n, c)| c.try_wait().ok().flatten().map(|s| (n.clone(), s.to_string())))
            .collect()
    }

    pub fn len(&self) -> usize {
        self.children.len()
    }
}

impl Drop for LocalDaemons {
    fn drop(&mut self) {
        for (name, child) in &mut self.children {
            if child.try_wait().ok().flatten().is_none() {
                let _ = child.kill();
            }
            let _ = child.wait();
            tracing::debug!(node = %name, "local daemon stopped");
        }
    }
}
