//! Progress of a node's long start-up work: loading its volume (screen space: the whole volume,
//! a spinner) and bricking it (object space: the scan of the whole volume for the split, then the
//! read of the brick and halo, z-slice by z-slice from [`isowall_volume::VolumeStream`]).
//!
//! The same news goes three ways, so it reaches whoever is watching: a bar on stderr where stderr
//! is a terminal (hidden otherwise), `STATUS=` for `systemctl status` whenever the percentage
//! changes, and, where there is no bar, a `tracing` line at every quarter (the node's log, which
//! `isowall up` keeps in `wall-configs/logs/` for local walls).
//!
//! [`Counted`]: the frames of a long `isowalld render --frames K` or the chunks of an
//! `isowalld convert`, a bar on a terminal, else a plain line at every quarter.

use indicatif::{ProgressBar, ProgressStyle};
use isowall_volume::{Pass, Progress};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// A spinner for work of unknown length (a whole volume's load), with indicatif's default style.
pub fn spinner(message: String) -> ProgressBar {
    let bar = ProgressBar::new_spinner().with_message(message);
    bar.enable_steady_tick(Duration::from_millis(120));
    bar
}

/// What a pass has last reported: its percentage and quarter, to report only changes.
#[derive(Default)]
struct Seen {
    pass: Option<Pass>,
    percent: usize,
    quarter: usize,
}

/// The observer for [`isowall_volume::VolumeStream::on_progress`] while `node` bricks `volume`.
pub struct Bricking {
    node: String,
    volume: String,
    bar: ProgressBar,
    seen: Mutex<Seen>,
}

impl Bricking {
    pub fn new(node: &str, volume: &str) -> Bricking {
        let bar = ProgressBar::new(100).with_message(format!("bricking {volume}"));
        bar.set_style(
            ProgressStyle::with_template("{bar:24} {percent:>3}% {msg} ({elapsed})")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        Bricking {
            node: node.to_string(),
            volume: volume.to_string(),
            bar,
            seen: Mutex::new(Seen::default()),
        }
    }

    /// One report of a pass (called for every z-slice).
    pub fn report(&self, p: Progress) {
        let percent = (p.done * 100).checked_div(p.total).unwrap_or(100);
        let quarter = percent / 25;
        let what = match p.pass {
            Pass::Scan => "scanning the volume for the brick split",
            Pass::Read => "reading the brick and its halo",
        };
        let mut seen = self.seen.lock().unwrap_or_else(|e| e.into_inner());
        if seen.pass != Some(p.pass) {
            *seen = Seen { pass: Some(p.pass), percent: usize::MAX, quarter: usize::MAX };
            self.bar.reset();
            self.bar.set_message(format!("{what}: {}", self.volume));
        }
        if percent == seen.percent {
            return;
        }
        seen.percent = percent;
        self.bar.set_position(percent as u64);
        crate::notify::status(&format!("{what}: {percent}% ({} of {} slices)", p.done, p.total));
        // On a terminal the bar says it; in a log a line at every quarter.
        if quarter != seen.quarter && self.bar.is_hidden() {
            seen.quarter = quarter;
            tracing::info!(
                node = %self.node, volume = %self.volume, pass = p.pass.name(), done = p.done, total = p.total,
                "{what}: {percent}%"
            );
        }
    }

    /// Removes the bar (the work is done or failed; the log keeps the news).
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

impl Drop for Bricking {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}

/// Progress of work counted in units (a render's accumulated frames, a conversion's chunks): a
/// bar on stderr where it is a terminal, else a plain line (`COMMAND: UNIT K of N (P%), T s`) at
/// every quarter of them.
pub struct Counted {
    bar: ProgressBar,
    command: &'static str,
    unit: &'static str,
    total: u64,
    quarter: u64,
    start: Instant,
}

impl Counted {
    /// A render's `total` frames of `what`: `isowalld render: frame K of N (P%), T s`.
    pub fn frames(total: u32, what: &str) -> Counted {
        Counted::of("isowalld render", "frame", u64::from(total), what)
    }

    /// `total` units of `command`'s work on `what`.
    pub fn of(command: &'static str, unit: &'static str, total: u64, what: &str) -> Counted {
        let bar = ProgressBar::new(total).with_message(what.to_string());
        bar.set_style(
            ProgressStyle::with_template(&format!(
                "{{bar:24}} {unit} {{pos}}/{{len}} {{msg}} ({{elapsed}}, {{eta}} left)"
            ))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        Counted { bar, command, unit, total, quarter: 0, start: Instant::now() }
    }

    /// Unit `k` (from 1) is done.
    pub fn done(&mut self, k: u32) {
        self.done_of(u64::from(k));
    }

    /// Unit `k` (from 1) is done.
    pub fn done_of(&mut self, k: u64) {
        self.bar.set_position(k);
        if !self.bar.is_hidden() {
            return;
        }
        let quarter = k * 4 / self.total.max(1);
        if quarter > self.quarter {
            self.quarter = quarter;
            eprintln!(
                "{}: {} {k} of {} ({}%), {:.1} s",
                self.command,
                self.unit,
                self.total,
                k * 100 / self.total.max(1),
                self.start.elapsed().as_secs_f64()
            );
        }
    }
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}
