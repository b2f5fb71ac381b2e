//! What a peer may make the operator read: at most a few lines per peer per interval.
//!
//! A node's certificate can send as many messages as its connection carries; what they make the
//! controller print (an unsolicited message ignored, a time refused) must cost the sender, not the
//! operator's terminal or the log. [`PeerLog`] lets [`PeerLog::LINES`] lines per peer through in
//! each [`PeerLog::INTERVAL`] (a window that starts at the first line) and counts the rest, and
//! the next line let through says how many were held back. Sans-IO: the caller passes the time in.

use std::collections::BTreeMap;
use std::time::Duration;

#[derive(Debug, Clone, Copy, Default)]
struct Window {
    start: Duration,
    used: u32,
    held_back: u64,
}

/// The per-peer line budget (see the module docs).
#[derive(Debug, Clone)]
pub struct PeerLog {
    lines: u32,
    interval: Duration,
    peers: BTreeMap<String, Window>,
}

impl Default for PeerLog {
    fn default() -> Self {
        PeerLog::new(PeerLog::LINES, PeerLog::INTERVAL)
    }
}

impl PeerLog {
    /// Lines per peer per interval by default.
    pub const LINES: u32 = 5;
    /// The default interval.
    pub const INTERVAL: Duration = Duration::from_secs(10);

    pub fn new(lines: u32, interval: Duration) -> PeerLog {
        PeerLog { lines: lines.max(1), interval, peers: BTreeMap::new() }
    }

    /// The interval of the budget.
    pub fn interval(&self) -> Duration {
        self.interval
    }

    /// Whether a line about `peer` may be printed at `now`: `Some(n)` with `n` the lines held back
    /// since the last one printed (to say so on this one), `None` when it is held back (counted).
    /// Only the wall's own peers are ever keys, so the map stays as small as the wall.
    pub fn allow(&mut self, now: Duration, peer: &str) -> Option<u64> {
        let w = self.peers.entry(peer.to_string()).or_insert(Window { start: now, used: 0, held_back: 0 });
        if now >= w.start + self.interval || now < w.start {
            w.start = now;
            w.used = 0;
        }
        if w.used < self.lines {
            w.used += 1;
            Some(std::mem::take(&mut w.held_back))
        } else {
            w.held_back += 1;
            None
        }
    }

    /// Lines about `peer` held back and not yet told.
    pub fn held_back(&self, peer: &str) -> u64 {
        self.peers.get(peer).map_or(0, |w| w.held_back)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(x: u64) -> Duration {
        Duration::from_millis(x)
    }

    #[test]
    fn a_flood_prints_a_few_lines_per_interval_and_counts_the_rest() {
        let mut log = PeerLog::new(3, ms(1_000));
        // 60,000 lines' worth over 6 s of virtual time, from one peer.
        let mut printed = Vec::new();
        for i in 0..60_000u64 {
            let now = Duration::from_micros(i * 100);
            if let Some(held) = log.allow(now, "node1") {
                printed.push((now, held));
            }
        }
        assert_eq!(printed.len(), 18, "3 lines in each of 6 intervals: {printed:?}");
        assert_eq!(printed[0].1, 0);
        assert_eq!(printed[3], (ms(1_000), 10_000 - 3), "the first line of a window tells the rest");
        assert_eq!(log.held_back("node1"), 10_000 - 3);
        // Another peer has its own budget.
        assert_eq!(log.allow(ms(5_999), "node0"), Some(0));
    }

    #[test]
    fn a_quiet_peer_is_never_held_back() {
        let mut log = PeerLog::default();
        for i in 0..100u64 {
            assert_eq!(log.allow(Duration::from_secs(i * 3), "node0"), Some(0));
        }
    }
}
