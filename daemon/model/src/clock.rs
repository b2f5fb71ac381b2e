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
    /// Controller clock when the sample used came back (`t2`): the estimate ages from there.
    pub measured_at_us: i64,
}

/// Clock drift allowed for, in parts per million of an estimate's age (crystal oscillators
/// drift by tens of ppm; twice the usual worst case).
pub const DRIFT_PPM: i64 = 100;

/// Slack added to every bound, in microseconds: the clocks' reading and the scheduler's jitter
/// between reading a clock and stamping a message.
pub const SLACK_US: i64 = 2_000;

impl ClockOffset {
    /// A daemon time in controller time.
    pub fn to_controller(&self, daemon_us: i64) -> i64 {
        daemon_us.saturating_sub(self.offset_us)
    }

    /// A controller time in daemon time.
    pub fn to_daemon(&self, controller_us: i64) -> i64 {
        controller_us.saturating_add(self.offset_us)
    }

    /// How far the true offset may be from this estimate at controller time `now_us`: the
    /// sample's own bound, drift since it was measured ([`DRIFT_PPM`]) and [`SLACK_US`].
    pub fn bound_us(&self, now_us: i64) -> i64 {
        let age = now_us.saturating_sub(self.measured_at_us).max(0);
        self.error_us.saturating_add(age / (1_000_000 / DRIFT_PPM)).saturating_add(SLACK_US)
    }

    /// Whether `daemon_us`, a time a daemon reports by its own clock, can be a moment between
    /// controller times `from_us` and `to_us` (what a message's round trip allows) given this
    /// estimate at controller time `to_us`. `Err` says by how much it cannot.
    pub fn check_between(&self, daemon_us: i64, from_us: i64, to_us: i64) -> Result<i64, String> {
        let at = self.to_controller(daemon_us);
        let bound = self.bound_us(to_us);
        if at < from_us.saturating_sub(bound) {
            return Err(format!(
                "{} us before the earliest it can be (offset {} us, within {bound} us)",
                from_us.saturating_sub(at),
                self.offset_us
            ));
        }
        if at > to_us.saturating_add(bound) {
            return Err(format!(
                "{} us after the latest it can be (offset {} us, within {bound} us)",
                at.saturating_sub(to_us),
                self.offset_us
            ));
        }
        Ok(at)
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
        self.admit(sample).is_ok()
    }

    /// Adds a sample, or says why it cannot be true: a negative round trip, or a daemon time
    /// `t1` that puts the offset, `[t1 - t2, t1 - t0]` whatever the one-way delays, outside what
    /// the current estimate allows ([`ClockOffset::bound_us`]). A daemon's clock is monotonic
    /// (its process's), so an honest sample always overlaps the estimate: one that does not is a
    /// lie, refused before it can move the estimate. The first sample is taken as it comes (there
    /// is nothing to hold it to); a node that lies from its first Pong on only moves its own
    /// offset, and its Presented times are then held to the swap's round trip through it.
    pub fn admit(&mut self, sample: ClockSample) -> Result<(), String> {
        if sample.t2_us < sample.t0_us {
            return Err(format!("round trip from {} us to {} us is negative", sample.t0_us, sample.t2_us));
        }
        if let Some(est) = self.estimate() {
            let lo = sample.t1_us.saturating_sub(sample.t2_us);
            let hi = sample.t1_us.saturating_sub(sample.t0_us);
            let bound = est.bound_us(sample.t2_us);
            let (elo, ehi) = (est.offset_us.saturating_sub(bound), est.offset_us.saturating_add(bound));
            if hi < elo || lo > ehi {
                return Err(format!(
                    "t1 = {} us puts its clock offset in [{lo}, {hi}] us, but it is {} us within {bound} us",
                    sample.t1_us, est.offset_us
                ));
            }
        }
        if self.samples.len() == self.capacity {
            self.samples.pop_front();
        }
        self.samples.push_back(sample);
        Ok(())
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
            measured_at_us: best.t2_us,
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
    fn a_sample_the_estimate_rules_out_is_refused_and_an_honest_one_taken() {
        let mut e = ClockEstimator::default();
        let offset = 3_000_000;
        // A 2 ms round trip at 1 s: offset known within 1 ms.
        e.admit(ClockSample { t0_us: 1_000_000, t1_us: 1_001_000 + offset, t2_us: 1_002_000 }).unwrap();
        // 46 days ahead: refused, the estimate unchanged.
        let lie = 46 * 86_400 * 1_000_000i64;
        let s = ClockSample { t0_us: 2_000_000, t1_us: 2_001_000 + offset + lie, t2_us: 2_002_000 };
        let why = e.admit(s).unwrap_err();
        assert!(why.contains("t1 = ") && why.contains("within"), "{why}");
        assert_eq!(e.len(), 1);
        // 10 ms off with a 2 ms round trip: refused too.
        let s = ClockSample { t0_us: 3_000_000, t1_us: 3_011_000 + offset, t2_us: 3_002_000 };
        assert!(e.admit(s).is_err());
        // An honest sample with asymmetric delays and a long round trip overlaps: taken.
        let s = ClockSample { t0_us: 4_000_000, t1_us: 4_290_000 + offset, t2_us: 4_300_000 };
        e.admit(s).unwrap();
        assert_eq!(e.estimate().unwrap().offset_us, offset);
        // Drift: 60 s later a clock 50 ppm fast is 3 ms further; 100 ppm of slack takes it.
        let s = ClockSample { t0_us: 64_000_000, t1_us: 64_001_000 + offset + 3_000, t2_us: 64_002_000 };
        e.admit(s).unwrap();
    }

    #[test]
    fn a_daemon_time_is_held_to_its_round_trip() {
        let o = ClockOffset {
            offset_us: 50_000,
            error_us: 1_001,
            rtt_us: 2_000,
            samples: 1,
            measured_at_us: 1_000_000,
        };
        // Swap sent at 1.1 s, Presented back at 1.12 s: a present at 1.11 s (controller time) is fine.
        assert_eq!(o.check_between(1_110_000 + 50_000, 1_100_000, 1_120_000), Ok(1_110_000));
        let bound = o.bound_us(1_120_000);
        assert_eq!(bound, 1_001 + 12 + SLACK_US);
        assert!(o.check_between(1_120_000 + bound + 50_000, 1_100_000, 1_120_000).is_ok());
        let late = o.check_between(1_120_000 + bound + 1 + 50_000, 1_100_000, 1_120_000).unwrap_err();
        assert!(late.contains("after the latest"), "{late}");
        let early = o.check_between(1_000_000, 1_100_000, 1_120_000).unwrap_err();
        assert!(early.contains("before the earliest"), "{early}");
        assert!(o.check_between(i64::MAX, 0, 1).is_err() && o.check_between(i64::MIN, 0, 1).is_err());
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
