//! Clock offsets between the controller and a daemon, from Ping/Pong round trips.
//!
//! One sample (NTP's four times): `t0` the controller's clock when it sent a Ping, `t1` the
//! daemon's clock when the Ping arrived, `held` how long the daemon held it before its Pong left
//! (by its clock), `t2` the controller's clock when the Pong arrived. Whatever the two one-way
//! delays, the daemon's offset (daemon clock - controller clock) lies in
//! `[t1 + held - t2, t1 - t0]`; its midpoint is off by at most `rtt / 2`,
//! `rtt = t2 - t0 - held` (the time on the wire), and by less the more symmetric the delays. The
//! hold (a busy daemon answering late) is on neither wire: left in, it would bias the offset by
//! half of it. Queueing only ever adds delay, so the sample with the smallest round
//! trip of the last few is the tightest: [`ClockEstimator`] keeps the last N samples and uses it.
//!
//! Real oscillators run at slightly different rates (tens of parts per million: 50 us a second),
//! so an offset ages. The estimator fits the offset's drift over the samples whose round trips
//! are near the shortest (the least queued) by least squares, and carries the best sample's offset
//! forward along it ([`ClockOffset::offset_at`]); [`ClockOffset::error_at`] bounds the estimate's
//! error at a given time from the sample's round trip and what the fit leaves uncertain.
//! All times are integer microseconds.

use std::collections::VecDeque;

/// One Ping/Pong round trip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockSample {
    /// Controller clock at sending the Ping.
    pub t0_us: i64,
    /// Daemon clock at receiving it.
    pub t1_us: i64,
    /// How long the daemon held it before the Pong left, by its clock.
    pub held_us: i64,
    /// Controller clock at receiving the Pong.
    pub t2_us: i64,
}

impl ClockSample {
    /// The time on the wire: the round trip less the daemon's hold.
    pub fn rtt_us(&self) -> i64 {
        self.t2_us.saturating_sub(self.t0_us).saturating_sub(self.held_us)
    }

    /// Daemon clock - controller clock, assuming symmetric delays:
    /// `((t1 - t0) + (t1 + held - t2)) / 2`.
    pub fn offset_us(&self) -> i64 {
        let (t0, t1, t2, held) =
            (self.t0_us as i128, self.t1_us as i128, self.t2_us as i128, self.held_us as i128);
        ((t1 - t0 + t1 + held - t2) / 2).clamp(i64::MIN as i128, i64::MAX as i128) as i64
    }
}

/// An estimated offset: daemon clock = controller clock + `offset_us`, within `error_us`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockOffset {
    pub offset_us: i64,
    /// Bound on |estimate - true offset| at `measured_at_us`: half the round trip of the sample
    /// used (rounded up), plus 1 us for the clocks' microsecond truncation; for a fitted line,
    /// the worst of its samples' and the slope's uncertainty carried to `measured_at_us`.
    pub error_us: i64,
    /// The shortest round trip of the samples kept.
    pub rtt_us: i64,
    /// Samples the estimate was chosen from.
    pub samples: usize,
    /// Controller clock when the sample used (for a line: the latest of its samples) came back
    /// (`t2`): the estimate ages from there.
    pub measured_at_us: i64,
    /// The offset's drift, parts per billion (node clock fast: positive), fitted over the
    /// samples near the shortest round trip; 0 until they span [`ClockEstimator::MIN_FIT_SPAN_US`].
    /// `offset_us` is the offset at `measured_at_us`.
    pub drift_ppb: i64,
    /// How far the drift may be off, parts per billion: the fitted samples' round-trip spread
    /// over their span, or [`DRIFT_PPM`] while there is no fit.
    pub drift_error_ppb: i64,
}

/// Clock drift allowed for, in parts per million of an estimate's age (crystal oscillators
/// drift by tens of ppm; twice the usual worst case).
pub const DRIFT_PPM: i64 = 100;

/// Slack added to every bound, in microseconds: the clocks' reading and the scheduler's jitter
/// between reading a clock and stamping a message.
pub const SLACK_US: i64 = 2_000;

impl ClockOffset {
    /// Whether the estimate is a fitted line (drift known), not a single sample's offset.
    pub fn is_fitted(&self) -> bool {
        self.drift_error_ppb < DRIFT_PPM * 1_000
    }

    /// The offset at controller time `controller_us`: the sample's, moved along the drift.
    pub fn offset_at(&self, controller_us: i64) -> i64 {
        let age = i128::from(controller_us) - i128::from(self.measured_at_us);
        let moved = age * i128::from(self.drift_ppb) / 1_000_000_000;
        (i128::from(self.offset_us) + moved).clamp(i64::MIN as i128, i64::MAX as i128) as i64
    }

    /// A daemon time in controller time.
    pub fn to_controller(&self, daemon_us: i64) -> i64 {
        // The drift moves the offset by parts per million: evaluating it at the daemon time less
        // the sample's offset is within a microsecond of the exact inverse.
        daemon_us.saturating_sub(self.offset_at(daemon_us.saturating_sub(self.offset_us)))
    }

    /// A controller time in daemon time.
    pub fn to_daemon(&self, controller_us: i64) -> i64 {
        controller_us.saturating_add(self.offset_at(controller_us))
    }

    /// A bound on |estimate - true offset| at controller time `now_us` for an honest node: the
    /// sample's own bound and the drift's uncertainty over the estimate's age (no slack for
    /// scheduling: this is what the report shows as the node's clock error).
    pub fn error_at(&self, now_us: i64) -> i64 {
        let age = i128::from(now_us.saturating_sub(self.measured_at_us).max(0));
        let drifted = age * i128::from(self.drift_error_ppb) / 1_000_000_000;
        self.error_us.saturating_add(drifted.min(i128::from(i64::MAX)) as i64)
    }

    /// How far the true offset may be from this estimate at controller time `now_us`, generously
    /// (what a node's reported times are held to): the sample's own bound, drift since it was
    /// measured at [`DRIFT_PPM`] whatever the fit says, and [`SLACK_US`].
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
    /// Samples kept by default: with a ping every 500 ms, the last 16 s (the drift fit follows
    /// a clock 50 ppm off, which moves an offset by 0.8 ms in that time).
    pub const DEFAULT_CAPACITY: usize = 32;

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
        // A hold longer than the round trip (beyond what drift allows) cannot be.
        let trip = sample.t2_us.saturating_sub(sample.t0_us);
        if sample.held_us < 0 || sample.held_us > trip.saturating_add(trip / (1_000_000 / DRIFT_PPM) + 1) {
            return Err(format!("held {} us in a round trip of {trip} us", sample.held_us));
        }
        if let Some(est) = self.estimate() {
            let lo = sample.t1_us.saturating_add(sample.held_us).saturating_sub(sample.t2_us);
            let hi = sample.t1_us.saturating_sub(sample.t0_us);
            let bound = est.bound_us(sample.t2_us);
            let now_offset = est.offset_at(sample.t2_us);
            let (elo, ehi) = (now_offset.saturating_sub(bound), now_offset.saturating_add(bound));
            if hi < elo || lo > ehi {
                return Err(format!(
                    "t1 = {} us puts its clock offset in [{lo}, {hi}] us, but it is {} us within {bound} us",
                    sample.t1_us, now_offset
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

    /// The current estimate, `None` before the first sample. Once the least queued samples
    /// (round trips within [`ClockEstimator::FIT_TOLERANCE_US`], or twice, the shortest)
    /// are three or more spanning [`ClockEstimator::MIN_FIT_SPAN_US`], it is their least-squares
    /// line of offset against time, taken at the latest of them ([`ClockOffset::is_fitted`]):
    /// averaging many samples beats
    /// the single best one, and the line follows the drift. Before, it is the shortest round
    /// trip's offset (of equal ones the latest), with no drift.
    pub fn estimate(&self) -> Option<ClockOffset> {
        let best = self.samples.iter().rev().min_by_key(|s| s.rtt_us())?;
        let rtt = best.rtt_us();
        let clamp = |x: i128| x.clamp(i64::MIN as i128, i64::MAX as i128) as i64;
        let (offset_us, error_us, measured_at_us, drift_ppb, drift_error_ppb) = match self.fit(rtt) {
            Some(f) => (f.offset_us, f.error_us, f.at_us, f.drift_ppb, f.drift_error_ppb),
            None => {
                // The sample's offset is the one at its midpoint, and it ages from its t2.
                (best.offset_us(), rtt / 2 + rtt % 2 + 1, best.t2_us, 0, DRIFT_PPM * 1_000)
            }
        };
        Some(ClockOffset {
            offset_us: clamp(i128::from(offset_us)),
            error_us,
            rtt_us: rtt,
            samples: self.samples.len(),
            measured_at_us,
            drift_ppb,
            drift_error_ppb,
        })
    }

    /// Samples whose round trip is within this of the shortest (or the shortest again, if
    /// more) take part in the fit, weighted by how little they were queued beyond it.
    pub const FIT_TOLERANCE_US: i64 = 15;

    /// The offset is fitted once the samples taking part span this much of the controller's
    /// clock, and there are at least three of them.
    pub const MIN_FIT_SPAN_US: i64 = 1_000_000;

    /// The least-squares line of offset against time over the least queued samples, taken at
    /// the latest one's `t2`; `None` while they are too few or span too little. Its error: each
    /// offset is within half its round trip, so the line is within the worst of those at the
    /// samples' centre and its slope within their sum over the span (clamped to [`DRIFT_PPM`]),
    /// which carries to the latest sample.
    fn fit(&self, best_rtt: i64) -> Option<Fit> {
        let tolerance = Self::FIT_TOLERANCE_US.max(best_rtt);
        let good: Vec<&ClockSample> =
            self.samples.iter().filter(|s| s.rtt_us() <= best_rtt.saturating_add(tolerance)).collect();
        let mid = |s: &ClockSample| (s.t0_us as f64 + s.t2_us as f64) / 2.0;
        let lo = good.iter().map(|s| mid(s)).fold(f64::INFINITY, f64::min);
        let hi = good.iter().map(|s| mid(s)).fold(f64::NEG_INFINITY, f64::max);
        let span = hi - lo;
        if good.len() < 3 || !(span >= Self::MIN_FIT_SPAN_US as f64) {
            return None;
        }
        // Weighted by how little each was queued beyond the shortest round trip.
        let w = |s: &ClockSample| {
            1.0 / (1.0 + (s.rtt_us() - best_rtt) as f64 / Self::FIT_TOLERANCE_US as f64).powi(2)
        };
        let n: f64 = good.iter().map(|s| w(s)).sum();
        let mx = good.iter().map(|s| w(s) * mid(s)).sum::<f64>() / n;
        let my = good.iter().map(|s| w(s) * s.offset_us() as f64).sum::<f64>() / n;
        let sxx: f64 = good.iter().map(|s| w(s) * (mid(s) - mx).powi(2)).sum();
        let sxy: f64 = good.iter().map(|s| w(s) * (mid(s) - mx) * (s.offset_us() as f64 - my)).sum();
        let limit = (DRIFT_PPM * 1_000) as f64;
        let slope = (sxy / sxx * 1e9).clamp(-limit, limit);
        let worst = good.iter().map(|s| s.rtt_us()).max().unwrap_or(best_rtt);
        let slope_error = (worst as f64 / span * 1e9).min(limit);
        let latest = good.iter().max_by_key(|s| s.t2_us)?;
        let at = latest.t2_us as f64;
        let offset = my + slope * 1e-9 * (at - mx);
        let error = (worst / 2 + worst % 2 + 1) as f64 + slope_error * 1e-9 * (at - mx).abs();
        Some(Fit {
            offset_us: offset.round() as i64,
            error_us: error.ceil() as i64,
            at_us: latest.t2_us,
            drift_ppb: slope.round() as i64,
            drift_error_ppb: slope_error.ceil() as i64,
        })
    }
}

/// [`ClockEstimator::fit`]'s line.
struct Fit {
    offset_us: i64,
    error_us: i64,
    at_us: i64,
    drift_ppb: i64,
    drift_error_ppb: i64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn symmetric_delays_give_the_exact_offset() {
        // Daemon 50 ms ahead, 2 ms each way.
        let s =
            ClockSample { t0_us: 1_000_000, t1_us: 1_000_000 + 2_000 + 50_000, held_us: 0, t2_us: 1_004_000 };
        assert_eq!(s.rtt_us(), 4_000);
        assert_eq!(s.offset_us(), 50_000);
        // The daemon held the Ping 5 ms before answering: on neither wire, so no bias.
        let s = ClockSample { t0_us: 0, t1_us: 1_000 + 50_000, held_us: 5_000, t2_us: 7_000 };
        assert_eq!((s.rtt_us(), s.offset_us()), (2_000, 50_000));
        // Left in, the hold would have biased the offset by half of it.
        assert_eq!(ClockSample { held_us: 0, ..s }.offset_us(), 47_500);
        // A hold longer than the round trip is refused.
        let mut e = ClockEstimator::default();
        assert!(e.admit(ClockSample { held_us: 7_002, ..s }).unwrap_err().contains("held 7002 us"));
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
            e.add(ClockSample { t0_us: t0, t1_us: t0 + up + offset, held_us: 0, t2_us: t0 + up + down });
        }
        let est = e.estimate().unwrap();
        assert_eq!(est.samples, 3);
        assert_eq!(est.rtt_us, 2_000, "the (1000, 1000) sample");
        assert_eq!(est.offset_us, offset);
        assert_eq!(est.to_controller(est.to_daemon(123)), 123);
        // Push it out: the best left is (700, 3000), biased by (700 - 3000) / 2 = -1150, within rtt/2.
        e.add(ClockSample { t0_us: 0, t1_us: 20_000 + offset, held_us: 0, t2_us: 40_000 });
        e.add(ClockSample { t0_us: 0, t1_us: 20_000 + offset, held_us: 0, t2_us: 40_000 });
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
        e.admit(ClockSample { t0_us: 1_000_000, t1_us: 1_001_000 + offset, held_us: 0, t2_us: 1_002_000 })
            .unwrap();
        // 46 days ahead: refused, the estimate unchanged.
        let lie = 46 * 86_400 * 1_000_000i64;
        let s =
            ClockSample { t0_us: 2_000_000, t1_us: 2_001_000 + offset + lie, held_us: 0, t2_us: 2_002_000 };
        let why = e.admit(s).unwrap_err();
        assert!(why.contains("t1 = ") && why.contains("within"), "{why}");
        assert_eq!(e.len(), 1);
        // 10 ms off with a 2 ms round trip: refused too.
        let s = ClockSample { t0_us: 3_000_000, t1_us: 3_011_000 + offset, held_us: 0, t2_us: 3_002_000 };
        assert!(e.admit(s).is_err());
        // An honest sample with asymmetric delays and a long round trip overlaps: taken.
        let s = ClockSample { t0_us: 4_000_000, t1_us: 4_290_000 + offset, held_us: 0, t2_us: 4_300_000 };
        e.admit(s).unwrap();
        assert_eq!(e.estimate().unwrap().offset_us, offset);
        // Drift: 60 s later a clock 50 ppm fast is 3 ms further; 100 ppm of slack takes it.
        let s = ClockSample {
            t0_us: 64_000_000,
            t1_us: 64_001_000 + offset + 3_000,
            held_us: 0,
            t2_us: 64_002_000,
        };
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
            drift_ppb: 0,
            drift_error_ppb: DRIFT_PPM * 1_000,
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
    fn a_drifting_clock_is_followed_between_pings() {
        // A node clock 50 ppm fast, 3 s ahead, pinged every 500 ms over links of 40 to 80 us
        // each way (seeded): the shortest round trip of the last 16 may be seconds old, when
        // the offset has moved by 50 us a second since.
        let (ppm, offset) = (50i64, 3_000_000i64);
        let node = |c: i64| c + offset + c * ppm / 1_000_000;
        let mut e = ClockEstimator::default();
        let mut rng = 0x9e37_79b9_7f4a_7c15u64;
        let mut delay = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            40 + (rng % 40) as i64
        };
        let mut worst_unfitted = 0i64;
        for i in 1..=40i64 {
            let t0 = i * 500_000;
            let up = delay();
            let t2 = t0 + up + delay();
            e.admit(ClockSample { t0_us: t0, t1_us: node(t0 + up), held_us: 0, t2_us: t2 }).unwrap();
            let est = e.estimate().unwrap();
            // Half-way to the next ping: the truth against the estimate and its stated bound.
            let at = t0 + 250_000;
            let truth = node(at) - at;
            let err = (est.offset_at(at) - truth).abs();
            assert!(err <= est.error_at(at), "ping {i}: off by {err} us, bound {}", est.error_at(at));
            // What the shortest round trip's offset alone says (no drift).
            let best = e.samples.iter().rev().min_by_key(|s| s.rtt_us()).unwrap();
            let unfitted = (best.offset_us() - truth).abs();
            if i > 16 {
                worst_unfitted = worst_unfitted.max(unfitted);
                assert!(err <= 25, "ping {i}: off by {err} us with the drift fitted");
                assert!((est.drift_ppb - ppm * 1_000).abs() <= 10_000, "drift {} ppb", est.drift_ppb);
            }
        }
        // Without the drift the best sample's offset is up to its age x 50 ppm off.
        assert!(worst_unfitted > 100, "the sample's offset alone was {worst_unfitted} us off at most");
    }

    #[test]
    fn impossible_samples_are_refused() {
        let mut e = ClockEstimator::default();
        assert!(!e.add(ClockSample { t0_us: 10, t1_us: 0, held_us: 0, t2_us: 9 }));
        assert!(e.is_empty());
        let s = ClockSample { t0_us: i64::MIN, t1_us: i64::MAX, held_us: 0, t2_us: i64::MIN };
        assert!(e.add(s));
        assert_eq!(e.estimate().unwrap().offset_us, i64::MAX);
    }
}
