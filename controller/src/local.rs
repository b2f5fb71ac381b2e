//! Local daemons for `isowall up`: one `isowalld run` per node whose address is on loopback,
//! stopped when the controller exits: on an error or its end (they are killed on drop), and on
//! SIGTERM, SIGHUP or SIGINT (what `kill`, `timeout`, a service manager or a closed terminal
//! send), which the controller that started them catches to stop them first
//! ([`watch_signals`]). Not through a parent-death signal: a daemon outlives a controller
//! killed with SIGKILL, which a standby may take over from.

use anyhow::{Context, Result};
use isowall_model::config::WallConfig;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The local daemons this process runs, by pid: what a signal that ends it stops first.
static RUNNING: Mutex<Vec<u32>> = Mutex::new(Vec::new());
/// A command that stops on Ctrl-C by itself (and then drops its daemons) says so: SIGINT is then
/// left to it.
static INTERRUPT_HANDLED: AtomicBool = AtomicBool::new(false);
/// How long a daemon has to stop after SIGTERM before it is killed.
const STOP_GRACE: Duration = Duration::from_secs(3);

/// A command that ends itself cleanly on Ctrl-C (SIGINT) calls this: the signal watcher then
/// leaves SIGINT to it, and its daemons stop when it drops them.
pub fn interrupt_handled_by_command() {
    INTERRUPT_HANDLED.store(true, Ordering::Relaxed);
}

/// Catches SIGTERM, SIGHUP and SIGINT (once per process): each stops the local daemons (SIGTERM,
/// then SIGKILL after [`STOP_GRACE`]) and ends the process with 128 + the signal's number, as
/// the signal would have. SIGINT is left to a command that handles it
/// ([`interrupt_handled_by_command`]).
fn watch_signals() -> Result<()> {
    use tokio::signal::unix::{signal, SignalKind};
    static WATCHING: Mutex<bool> = Mutex::new(false);
    let mut watching = WATCHING.lock().unwrap_or_else(|e| e.into_inner());
    if *watching {
        return Ok(());
    }
    let rt = tokio::runtime::Builder::new_current_thread().enable_io().build()?;
    // Registered here, before the first daemon starts: no window in which a signal kills the
    // controller alone.
    let (mut term, mut hup, mut int) = {
        let _in = rt.enter();
        (signal(SignalKind::terminate())?, signal(SignalKind::hangup())?, signal(SignalKind::interrupt())?)
    };
    std::thread::Builder::new().name("isowall-signals".into()).spawn(move || {
        rt.block_on(async move {
            loop {
                let (name, code) = tokio::select! {
                    _ = term.recv() => ("SIGTERM", 15),
                    _ = hup.recv() => ("SIGHUP", 1),
                    _ = int.recv() => ("SIGINT", 2),
                };
                if name == "SIGINT" && INTERRUPT_HANDLED.load(Ordering::Relaxed) {
                    continue;
                }
                let n = stop_running();
                eprintln!("isowall: {name}: stopped {n} local node(s)");
                std::process::exit(128 + code);
            }
        })
    })?;
    *watching = true;
    Ok(())
}

/// Stops every running local daemon: SIGTERM, then SIGKILL for those still there after
/// [`STOP_GRACE`]. Returns how many there were.
fn stop_running() -> usize {
    use rustix::process::{kill_process, Pid, Signal};
    let pids: Vec<u32> = RUNNING.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let pid = |p: u32| i32::try_from(p).ok().and_then(Pid::from_raw);
    for p in pids.iter().filter_map(|&p| pid(p)) {
        let _ = kill_process(p, Signal::TERM);
    }
    let deadline = Instant::now() + STOP_GRACE;
    while Instant::now() < deadline && pids.iter().any(|&p| alive(p)) {
        std::thread::sleep(Duration::from_millis(20));
    }
    for p in pids.iter().filter(|&&p| alive(p)).filter_map(|&p| pid(p)) {
        let _ = kill_process(p, Signal::KILL);
    }
    pids.len()
}

/// Whether child `pid` still runs (not gone, not a zombie waiting to be reaped).
fn alive(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|s| {
            s.rsplit_once(')').and_then(|(_, rest)| rest.split_whitespace().next().map(str::to_owned))
        })
        .is_some_and(|state| state != "Z")
}

fn register(pid: u32) {
    RUNNING.lock().unwrap_or_else(|e| e.into_inner()).push(pid);
}

fn unregister(pid: u32) {
    RUNNING.lock().unwrap_or_else(|e| e.into_inner()).retain(|&p| p != pid);
}

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
    /// Each daemon's log, in the order of `children`, and where this run's lines begin in it.
    logs: Vec<PathBuf>,
    log_starts: Vec<u64>,
    /// How they were started, to start one again ([`LocalDaemons::restart`]).
    config_path: PathBuf,
    display: String,
    windowed: bool,
}

impl LocalDaemons {
    /// Starts a daemon for every loopback node of the wall, with `display` passed on as
    /// `--display` (and `--windowed` if asked). Their logs go to `log_dir/NODE.log`.
    pub fn start(config: &WallConfig, log_dir: &Path, display: &str, windowed: bool) -> Result<LocalDaemons> {
        let bin = daemon_binary();
        watch_signals().context("cannot watch for the signals that must stop the local nodes")?;
        std::fs::create_dir_all(log_dir).with_context(|| format!("cannot create {}", log_dir.display()))?;
        let mut me = LocalDaemons {
            children: Vec::new(),
            logs: Vec::new(),
            log_starts: Vec::new(),
            config_path: config.path.clone(),
            display: display.to_string(),
            windowed,
        };
        for node in config.nodes.iter().filter(|n| is_loopback(&n.address)) {
            // Appended to, never truncated: a second `up` of a running wall fails at the nodes'
            // ports, and the running nodes' logs must keep what they said.
            let log_path = log_dir.join(format!("{}.log", node.name));
            append_line(
                &log_path,
                &format!("--- isowall (pid {}) starts node {}", std::process::id(), node.name),
            )?;
            let start = std::fs::metadata(&log_path).map_or(0, |m| m.len());
            let child = me.spawn(&bin, &node.name, &log_path)?;
            eprintln!("isowall: started node {} (pid {}, log {})", node.name, child.id(), log_path.display());
            me.children.push((node.name.clone(), child));
            me.logs.push(log_path);
            me.log_starts.push(start);
        }
        Ok(me)
    }

    /// Starts `isowalld run` for `node`, its output appended to `log` (appending: a line written
    /// into the log by anyone else is never overwritten, and a restarted daemon's log goes on).
    fn spawn(&self, bin: &Path, node: &str, log: &Path) -> Result<Child> {
        let file = std::fs::OpenOptions::new()
            .append(true)
            .create(true)
            .open(log)
            .with_context(|| format!("cannot open {}", log.display()))?;
        let child = Command::new(bin)
            .arg("run")
            .arg("--config")
            .arg(&self.config_path)
            .arg("--node")
            .arg(node)
            .args(["--display", &self.display])
            .args(self.windowed.then_some("--windowed"))
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .with_context(|| format!("cannot start {} for node {node}", bin.display()))?;
        register(child.id());
        Ok(child)
    }

    /// Whether `node` is one of these daemons.
    pub fn has(&self, node: &str) -> bool {
        self.children.iter().any(|(n, _)| n == node)
    }

    /// (node, log file) of every daemon.
    pub fn logs(&self) -> Vec<(String, PathBuf)> {
        self.children.iter().map(|(n, _)| n.clone()).zip(self.logs.iter().cloned()).collect()
    }

    /// Kills `node`'s daemon (if it runs) and starts it again with the same arguments, its log
    /// going on; the new pid. The wall reconnects it as any node that comes back.
    pub fn restart(&mut self, node: &str) -> Result<u32> {
        let i = self
            .children
            .iter()
            .position(|(n, _)| n == node)
            .with_context(|| format!("node {node} is not a daemon this controller started"))?;
        {
            let child = &mut self.children[i].1;
            if child.try_wait().ok().flatten().is_none() {
                let _ = child.kill();
            }
            let _ = child.wait();
            unregister(child.id());
        }
        let log = self.logs[i].clone();
        let child = self.spawn(&daemon_binary(), node, &log)?;
        let pid = child.id();
        tracing::info!(%node, pid, log = %log.display(), "local daemon restarted");
        self.children[i].1 = child;
        Ok(pid)
    }

    /// Waits until every daemon listens (its log says `ready on`), or one has exited (the wall
    /// cannot start as configured: [`LocalDaemons::exit_report`] says why), at most `timeout`:
    /// then a wall started with the nodes it has waits for no daemon still loading.
    pub fn wait_started(&mut self, timeout: std::time::Duration) {
        let start = std::time::Instant::now();
        while start.elapsed() < timeout {
            if !self.exited().is_empty() {
                return;
            }
            // This run's lines only: an earlier run's "ready on" stays in the log above them.
            let starting = self.logs.iter().zip(&self.log_starts).any(|(log, &start)| {
                !std::fs::read(log).is_ok_and(|t| {
                    String::from_utf8_lossy(t.get(start as usize..).unwrap_or_default()).contains("ready on")
                })
            });
            if !starting {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    }

    /// Why the daemons that have exited did (`None` while every one runs): for each, its node,
    /// its exit status and the last lines of its log, where a daemon says why it stopped (e.g.
    /// its port in use).
    pub fn exit_report(&mut self) -> Option<String> {
        const LINES: usize = 4;
        let mut report = Vec::new();
        for ((name, child), log) in self.children.iter_mut().zip(&self.logs) {
            let Some(status) = child.try_wait().ok().flatten() else { continue };
            let text = std::fs::read_to_string(log).unwrap_or_default();
            let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
            let tail = lines[lines.len().saturating_sub(LINES)..].join("\n    ");
            report.push(format!(
                "local node {name} exited ({status}); the end of {}:\n    {tail}",
                log.display()
            ));
        }
        (!report.is_empty()).then(|| report.join("\n"))
    }

    /// Resolves when a daemon has exited, with [`LocalDaemons::exit_report`].
    pub async fn first_exit(&mut self) -> String {
        loop {
            if let Some(report) = self.exit_report() {
                return report;
            }
            tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        }
    }

    /// Nodes whose daemon has exited, with its status.
    pub fn exited(&mut self) -> Vec<(String, String)> {
        self.children
            .iter_mut()
            .filter_map(|(n, c)| c.try_wait().ok().flatten().map(|s| (n.clone(), s.to_string())))
            .collect()
    }

    /// (node, pid) of every local daemon still running.
    pub fn pids(&mut self) -> Vec<(String, u32)> {
        self.children
            .iter_mut()
            .filter_map(|(n, c)| c.try_wait().ok().flatten().is_none().then(|| (n.clone(), c.id())))
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
            unregister(child.id());
            tracing::debug!(node = %name, "local daemon stopped");
        }
    }
}

/// Appends `line` to the file at `path` (created if absent).
fn append_line(path: &Path, line: &str) -> Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .append(true)
        .create(true)
        .open(path)
        .with_context(|| format!("cannot open {}", path.display()))?;
    writeln!(f, "{line}").with_context(|| format!("cannot write {}", path.display()))
}

/// What a process holds: resident memory and open file descriptors (Linux `/proc`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resources {
    pub rss_kib: u64,
    pub fds: usize,
}

/// Reads `/proc/PID/status` (VmRSS) and counts `/proc/PID/fd`; `None` where the process is gone
/// or `/proc` is not there.
pub fn resources(pid: u32) -> Option<Resources> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let rss_kib =
        status.lines().find_map(|l| l.strip_prefix("VmRSS:"))?.split_whitespace().next()?.parse().ok()?;
    let fds = std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count();
    Some(Resources { rss_kib, fds })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resources_of_this_process_grow_with_what_it_holds() {
        let Some(before) = resources(std::process::id()) else {
            if cfg!(target_os = "linux") {
                panic!("/proc is readable on Linux");
            }
            return;
        };
        assert!(before.rss_kib > 0 && before.fds >= 3, "{before:?}");
        let files: Vec<std::fs::File> = (0..8).map(|_| tempfile_in_tmp()).collect();
        let block = std::hint::black_box(vec![1u8; 32 << 20]);
        let after = resources(std::process::id()).unwrap();
        assert!(after.fds >= before.fds + 8, "{before:?} -> {after:?}");
        assert!(after.rss_kib >= before.rss_kib + 30 * 1024, "{before:?} -> {after:?}");
        drop((files, block));
    }

    fn tempfile_in_tmp() -> std::fs::File {
        std::fs::File::open(std::env::temp_dir()).expect("the temp folder opens")
    }

    #[test]
    fn a_gone_process_has_no_resources() {
        assert_eq!(resources(u32::MAX), None);
    }
}
