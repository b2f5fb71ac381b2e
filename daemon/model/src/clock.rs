//! Clock offsets between the controller and a daemon, from Ping/Pong round trips.
//!
//! One sample: `t0` the controller's clock when it sent a Ping, `t1` the daemon's clock when the
//! Ping arrived, `t2` the controller's clock when the Pong arrived. Whatever the two one-way
//! delays, the daemon's offset (daemon clock - controller clock) lies in `[t1 - t2, t1 - t0]`;
//! its midpoint `t1 - (t0 + t2) / 2` is off by at most `rtt / 2`, `rtt = t2 - t0`, and by less the
//! more symmetric the delays. Queueing only ever adds delay, so the sample with the smallest round
//! trip of the last few is the tightest: [`ClockEstimator`] keeps the last N samples and uses it.
//! All times are integer microseconds.

use std::collections::VecDeque;

/// One Ping/Pong round trip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockSample {
    /// Controller clock at sending the Ping.
    pub t0_us: i64,
    /// Daemon clock at receiving it.
    pub t1_us: i64,
    /// Controller clock at receiving the Pong.
    pub t2_us: i64,
}

impl ClockSample {
    pub fn rtt_us(&self) -> i64 {
        self.t2_us.saturating_sub(self.t0_us)
    }

    /// Daemon clock - controller clock, assuming symmetric delays.
    pub fn offset_us(&self) -> i64 {
        let mid = self.t0_us as i128 + (self.t2_us as i128 - self.t0_us as i128) / 2;
        (self.t1_us as i128 - mid).clamp(i64::MIN as i128, i64::MAX as i128) as i64
    }
}

/// An estimated offset: daemon clock = controller clock + `offset_us`, within `error_us`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockOffset {
    pub offset_us: i64,
    /// Bound on |estimate - true offset|: half the round trip of the sample used (rounded up),
    /// plus 1 us for the clocks' microsecond truncation.
    pub error_us: i64,
    /// The round trip of the sample used.
    pub rtt_us: i64,
    /// Samples the estimate was chosen from.
    pub samples: usize,
}

impl ClockOffset {
    /// A daemon time in controller time.
    pub fn to_controller(&self, daemon_us: i64) -> i64 {
        daemon_us.saturating_sub(self.offset_us)
    }

    /// A controller time in daemon time.
    pub fn to_daemon(&self, controller_us: i64) -> i64 {
        controller_us.saturating_add(self.offset_us)
    }
}

/// The last `capacity` samples of one daemon; the estimate is the minimum-RTT sample's offset.
#[derive(Debug, Clone)]
pub struct ClockEstimator {
    samples: VecDeque<ClockSample>,
    capacity: usize,
}

impl Default for ClockEstimator {
    fn default() -> Self {
        ClockEstimator::new(ClockEstimator::DEFAULT_CAPACITY)
    }
}

impl ClockEstimator {
    /// Samples kept by default: with a ping every 500 ms, the last 8 s (clock drift of 50 ppm
    /// moves an offset by 0.4 ms in that time).
    pub const DEFAULT_CAPACITY: usize = 16;

    pub fn new(capacity: usize) -> Self {
        ClockEstimator { samples: VecDeque::new(), capacity: capacity.max(1) }
    }

    /// Adds a sample; one with a negative round trip (impossible) is refused and `false` returned.
    pub fn add(&mut self, sample: ClockSample) -> bool {
        if sample.t2_us < sample.t0_us {
            return false;
        }
        if self.samples.len() == self.capacity {
            self.samples.pop_front();
        }
        self.samples.push_back(sample);
        true
    }

    pub fn len(&self) -> usize {
        self.samples.len()
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    pub fn clear(&mut self) {
        self.samples.clear();
    }

    /// The current estimate, `None` before the first sample. Of samples with equal round trips
    /// the latest wins.
    pub fn estimate(&self) -> Option<ClockOffset> {
        let best = self.samples.iter().rev().min_by_key(|s| s.rtt_us())?;
        let rtt = best.rtt_us();
        Some(ClockOffset {
            offset_us: best.offset_us(),
            error_us: rtt / 2 + rtt % 2 + 1,
            rtt_us: rtt,
            samples: self.samples.len(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn symmetric_delays_give_the_exact_offset() {
        // Daemon 50 ms ahead, 2 ms each way.
        let s = ClockSample { t0_us: 1_000_000, t1_us: 1_000_000 + 2_000 + 50_000, t2_us: 1_004_000 };
        assert_eq!(s.rtt_us(), 4_000);
        assert_eq!(s.offset_us(), 50_000);
    }

    #[test]
    fn the_minimum_rtt_sample_wins_and_old_samples_leave() {
        let mut e = ClockEstimator::new(3);
        assert_eq!(e.estimate(), None);
        let offset = -50_000;
        // (up, down) one-way delays: asymmetric ones bias the midpoint by (up - down) / 2.
        for (i, (up, down)) in
            [(9_000, 1_000), (1_000, 1_000), (5_000, 500), (700, 3_000)].into_iter().enumerate()
        {
            let t0 = 10_000_000 * (i as i64 + 1);
            e.add(ClockSample { t0_us: t0, t1_us: t0 + up + offset, t2_us: t0 + up + down });
        }
        let est = e.estimate().unwrap();
        assert_eq!(est.samples, 3);
        assert_eq!(est.rtt_us, 2_000, "the (1000, 1000) sample");
        assert_eq!(est.offset_us, offset);
        assert_eq!(est.to_controller(est.to_daemon(123)), 123);
        // Push it out: the best left is (700, 3000), biased by (700 - 3000) / 2 = -1150, within rtt/2.
        e.add(ClockSample { t0_us: 0, t1_us: 20_000 + offset, t2_us: 40_000 });
        e.add(ClockSample { t0_us: 0, t1_us: 20_000 + offset, t2_us: 40_000 });
        let est = e.estimate().unwrap();
        assert_eq!(est.rtt_us, 3_700);
        assert_eq!(est.offset_us, offset - 1_150);
        assert!((est.offset_us - offset).abs() <= est.error_us);
    }

    #[test]
    fn impossible_samples_are_refused() {
        let mut e = ClockEstimator::default();
        assert!(!e.add(ClockSample { t0_us: 10, t1_us: 0, t2_us: 9 }));
        assert!(e.is_empty());
        let s = ClockSample { t0_us: i64::MIN, t1_us: i64::MAX, t2_us: i64::MIN };
        assert!(e.add(s));
        assert_eq!(e.estimate().unwrap().offset_us, i64::MAX);
    }
}
