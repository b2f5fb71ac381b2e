//! Progress bars (indicatif, on stderr) for the controller's long waits: loading a volume and
//! bringing a wall up (nodes connected out of all). Where stderr is not a terminal the bars are
//! hidden and the same news goes out as plain lines, so logs and tests still read it.

use indicatif::{ProgressBar, ProgressStyle};
use std::time::Duration;

/// A spinner with the elapsed time, for work of unknown length (loading a volume).
pub fn spinner(message: String) -> ProgressBar {
    let bar = ProgressBar::new_spinner().with_message(message);
    bar.set_style(
        ProgressStyle::with_template("{spinner} {msg} ({elapsed})")
            .unwrap_or_else(|_| ProgressStyle::default_spinner()),
    );
    bar.enable_steady_tick(Duration::from_millis(120));
    bar
}

/// A bar of `n` nodes connected, its message naming those still awaited.
pub fn nodes(wall: &str, n: usize) -> ProgressBar {
    let bar = ProgressBar::new(n as u64).with_message(format!("connecting to wall '{wall}'"));
    bar.set_style(
        ProgressStyle::with_template("{bar:24} {pos}/{len} nodes up {msg} ({elapsed})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.enable_steady_tick(Duration::from_millis(200));
    bar
}

/// A line of news: above the bar on a terminal, else on stderr.
pub fn say(bar: &ProgressBar, line: &str) {
    if bar.is_hidden() {
        eprintln!("{line}");
    } else {
        bar.println(line);
    }
}
