//! The quality governor (pure: frame times in, AO samples out; no clock of its own).
//!
//! Given a target frame time, it chooses the AO samples per pixel per frame while the frame state
//! changes (the camera moves), so that the wall's frame time stays near the target; once the state
//! stops changing it holds the count, so that every node keeps refining the same image by
//! progressive accumulation (a new count would be a new image and restart the average).
//!
//! It runs in the controller: the controller feeds it the wall's measured frame time (frame
//! state sent -> swap released, i.e. the slowest node plus the network) and sends the count it
//! chooses in the next frame state (`settings.ao.samples`, validated on the wire like any frame
//! state). So every node of a wall renders the same count, and with the pattern seeded by the
//! pixel's position in the whole wall and the frame index, tiles match at their edges; a node
//! never decides alone, so no two nodes can disagree.
//!
//! The rule, with hysteresis so that timing noise does not make the count flicker:
//! - a frame slower than `target * (1 + OVER)`: samples scaled by `target / measured * SHRINK`
//!   (time is roughly proportional to samples; the primary rays' fixed cost makes the cut too
//!   small rather than too large, and the next frame cuts again);
//! - a frame faster than `target * (1 - UNDER)`: samples scaled up by that ratio too, at most
//!   doubled per frame (a cheap frame is a weak estimate of the next);
//! - in between, or while the state is still: unchanged.
//!
//! When the samples are already at their minimum and a frame is still over the band, it lowers
//! the internal resolution instead: the divisor [`scale`](Governor::scale) (1 = full resolution,
//! at most [`MAX_SCALE`]) rises by one per slow frame; while it is over 1 the samples stay at
//! their minimum, and a frame under the band that would still fit at the next finer resolution
//! lowers it by one (resolution returns before any sample is added back). A still frame is always
//! rendered at scale 1: progressive refinement happens at full resolution (the moving scale is
//! remembered for when the camera moves again).
//!
//! A governed wall's moving frames, at few samples, are its noisiest: with the config's
//! `[render] denoise = "auto"` (the default) a wall with a governor target filters them
//! ([`DenoiseSetting::resolve`](crate::config::DenoiseSetting::resolve)); the filter fades as still
//! frames accumulate samples.

/// A frame more than this fraction over the target lowers the count.
pub const OVER: f64 = 0.10;
/// A frame more than this fraction under the target raises the count.
pub const UNDER: f64 = 0.25;
/// Safety factor of a cut: aim a little under the target.
pub const SHRINK: f64 = 0.9;
/// The largest internal resolution divisor the governor chooses (and the wire accepts).
pub const MAX_SCALE: u32 = 4;
/// The largest target accepted (ms): above it a wall is not interactive anyway.
pub const MAX_TARGET_MS: f64 = 60_000.0;

/// Why a governor cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GovernorError {
    #[error("target frame time {0} ms: a finite number of milliseconds in 1..=60000")]
    Target(f64),
    #[error("AO samples: min {min} must be at least 1 and at most max {max}")]
    Samples { min: u32, max: u32 },
}

/// Chooses AO samples per frame for a target frame time.
#[derive(Debug, Clone, PartialEq)]
pub struct Governor {
    target_ms: f64,
    min: u32,
    max: u32,
    samples: u32,
    /// The resolution divisor while moving (1 ..= MAX_SCALE).
    scale: u32,
    /// Whether the next frame is still (then [`Governor::scale`] is 1).
    still: bool,
}

/// Whether the frame state changed since the previous frame (the camera moved, settings changed)
/// or stayed the same (progressive refinement).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Motion {
    Moving,
    Still,
}

impl Governor {
    /// A governor aiming at `target_ms`, choosing between `min` and `max` samples, starting at
    /// `start` (clamped into that range).
    pub fn new(target_ms: f64, start: u32, min: u32, max: u32) -> Result<Governor, GovernorError> {
        if !target_ms.is_finite() || !(1.0..=MAX_TARGET_MS).contains(&target_ms) {
            return Err(GovernorError::Target(target_ms));
        }
        if min == 0 || min > max {
            return Err(GovernorError::Samples { min, max });
        }
        Ok(Governor { target_ms, min, max, samples: start.clamp(min, max), scale: 1, still: false })
    }

    pub fn target_ms(&self) -> f64 {
        self.target_ms
    }

    /// The samples per pixel per frame for the next frame.
    pub fn samples(&self) -> u32 {
        self.samples
    }

    /// The internal resolution divisor for the next frame: 1 for a still frame.
    pub fn scale(&self) -> u32 {
        if self.still {
            1
        } else {
            self.scale
        }
    }

    /// A frame rendered with [`samples`](Self::samples) took `frame_ms`; `motion` says whether
    /// the *next* frame's state differs from it. Returns the samples for the next frame. A
    /// measurement that is not a finite positive number is ignored.
    pub fn observe(&mut self, frame_ms: f64, motion: Motion) -> u32 {
        let was_still = self.still;
        self.still = motion == Motion::Still;
        if motion == Motion::Still || !frame_ms.is_finite() || frame_ms <= 0.0 {
            return self.samples;
        }
        if was_still && self.scale > 1 {
            // A still frame was at full resolution: it says nothing about one at this scale.
            return self.samples;
        }
        let slow = frame_ms > self.target_ms * (1.0 + OVER);
        let fast = frame_ms < self.target_ms * (1.0 - UNDER);
        if slow && self.samples == self.min {
            self.scale = (self.scale + 1).min(MAX_SCALE);
            return self.samples;
        }
        if self.scale > 1 {
            // Resolution comes back before any sample is added: samples stay at their minimum
            // while the scale is over 1. Back one step once the frame would still fit the band at
            // the finer resolution (time goes with pixels, 1 / scale squared).
            let finer = (self.scale as f64 / (self.scale - 1) as f64).powi(2);
            if fast && frame_ms * finer <= self.target_ms * (1.0 + OVER) {
                self.scale -= 1;
            }
            return self.samples;
        }
        let ratio = self.target_ms / frame_ms;
        let s = self.samples as f64;
        let next = if frame_ms > self.target_ms * (1.0 + OVER) {
            (s * ratio * SHRINK).floor()
        } else if frame_ms < self.target_ms * (1.0 - UNDER) {
            (s * (ratio * SHRINK).min(2.0)).floor().max(s + 1.0)
        } else {
            s
        };
        self.samples = (next.min(self.max as f64) as u32).clamp(self.min, self.max);
        self.samples
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A wall whose frame costs `base + per_sample * samples` ms.
    fn cost(base: f64, per_sample: f64) -> impl Fn(u32) -> f64 {
        move |s| base + per_sample * s as f64
    }

    fn run(g: &mut Governor, frames: usize, model: &impl Fn(u32) -> f64) -> Vec<u32> {
        (0..frames).map(|_| g.observe(model(g.samples()), Motion::Moving)).collect()
    }

    #[test]
    fn bad_targets_and_ranges_are_refused() {
        for t in [0.0, -5.0, f64::NAN, f64::INFINITY, 1e9] {
            assert!(matches!(Governor::new(t, 8, 1, 256), Err(GovernorError::Target(_))), "{t}");
        }
        assert!(Governor::new(100.0, 8, 0, 256).is_err());
        assert!(Governor::new(100.0, 8, 64, 32).is_err());
        assert_eq!(Governor::new(100.0, 9999, 1, 256).unwrap().samples(), 256);
    }

    #[test]
    fn a_slow_wall_converges_under_the_target_and_stays() {
        // 20 ms of primary rays, 2 ms per sample: the target of 100 ms allows 40 samples.
        let model = cost(20.0, 2.0);
        let mut g = Governor::new(100.0, 256, 1, 1024).unwrap();
        let trace = run(&mut g, 20, &model);
        let last = *trace.last().unwrap();
        assert!(model(last) <= 100.0 * (1.0 + OVER), "{trace:?}");
        assert!(model(last) >= 100.0 * (1.0 - UNDER), "{trace:?}");
        // Settled: the last ten frames did not change the count (hysteresis).
        assert!(trace[10..].iter().all(|&s| s == last), "{trace:?}");
    }

    #[test]
    fn a_fast_wall_raises_the_count_at_most_doubling() {
        let model = cost(5.0, 0.5);
        let mut g = Governor::new(100.0, 1, 1, 1024).unwrap();
        let trace = run(&mut g, 30, &model);
        let mut prev = 1;
        for &s in &trace {
            assert!(s <= prev * 2, "{trace:?}");
            prev = s;
        }
        let last = *trace.last().unwrap();
        assert!(model(last) >= 75.0 && model(last) <= 110.0, "{trace:?}: {} ms", model(last));
    }

    #[test]
    fn the_count_stays_within_its_range() {
        let mut g = Governor::new(10.0, 64, 4, 128).unwrap();
        assert_eq!(run(&mut g, 10, &cost(500.0, 1.0)).last(), Some(&4));
        let mut g = Governor::new(1000.0, 64, 4, 128).unwrap();
        assert_eq!(run(&mut g, 10, &cost(1.0, 0.01)).last(), Some(&128));
    }

    #[test]
    fn noise_inside_the_band_changes_nothing() {
        let mut g = Governor::new(100.0, 32, 1, 1024).unwrap();
        for ms in [92.0, 108.0, 80.0, 109.9, 76.0, 100.0] {
            assert_eq!(g.observe(ms, Motion::Moving), 32, "{ms}");
        }
    }

    #[test]
    fn a_still_state_holds_the_count_for_progressive_refinement() {
        let mut g = Governor::new(100.0, 32, 1, 1024).unwrap();
        assert_eq!(g.observe(400.0, Motion::Still), 32);
        assert_eq!(g.observe(10.0, Motion::Still), 32);
        // Moving again, it reacts.
        assert!(g.observe(400.0, Motion::Moving) < 32);
    }

    /// A wall whose frame costs `base + per_sample * samples` ms at full resolution, divided by
    /// the scale squared (pixels).
    fn scaled(g: &Governor, base: f64, per_sample: f64) -> f64 {
        let s = g.scale() as f64;
        (base + per_sample * g.samples() as f64) / (s * s)
    }

    #[test]
    fn the_scale_rises_only_at_the_minimum_samples() {
        // 200 ms per sample at full resolution: a 100 ms target needs a lower resolution.
        let mut g = Governor::new(100.0, 8, 1, 1024).unwrap();
        let mut trace = Vec::new();
        for _ in 0..10 {
            let ms = scaled(&g, 0.0, 200.0);
            let (samples, scale) = (g.samples(), g.scale());
            g.observe(ms, Motion::Moving);
            if g.scale() > scale {
                assert_eq!(samples, 1, "scale rose from {scale} at {samples} samples");
            }
            trace.push((g.samples(), g.scale()));
        }
        // Settled at half resolution and 1 sample, under the target (no flicker back to full
        // resolution, where it would be 200 ms; no sample added while the resolution is low).
        assert!(trace[5..].iter().all(|&st| st == (1, 2)), "{trace:?}");
        assert!(scaled(&g, 0.0, 200.0) <= 100.0 * (1.0 + OVER));
        // Never past the largest divisor, however slow.
        let mut g = Governor::new(10.0, 1, 1, 64).unwrap();
        for _ in 0..10 {
            g.observe(1000.0, Motion::Moving);
        }
        assert_eq!(g.scale(), MAX_SCALE);
        // Not while samples can still be cut.
        let mut g = Governor::new(100.0, 64, 1, 1024).unwrap();
        g.observe(300.0, Motion::Moving);
        assert_eq!(g.scale(), 1);
        assert!(g.samples() < 64);
    }

    #[test]
    fn the_scale_falls_back_before_samples_rise() {
        let mut g = Governor::new(100.0, 1, 1, 1024).unwrap();
        for _ in 0..3 {
            g.observe(1000.0, Motion::Moving);
        }
        assert_eq!((g.samples(), g.scale()), (1, 4));
        // Fast frames: first the resolution comes back, one step each, samples unchanged.
        for want in [3, 2, 1] {
            g.observe(10.0, Motion::Moving);
            assert_eq!((g.samples(), g.scale()), (1, want));
        }
        g.observe(10.0, Motion::Moving);
        assert_eq!(g.scale(), 1);
        assert!(g.samples() > 1);
    }

    #[test]
    fn still_frames_are_at_full_resolution() {
        let mut g = Governor::new(100.0, 1, 1, 1024).unwrap();
        g.observe(1000.0, Motion::Moving);
        assert_eq!(g.scale(), 2);
        g.observe(1000.0, Motion::Still);
        assert_eq!(g.scale(), 1);
        g.observe(1000.0, Motion::Still);
        assert_eq!(g.scale(), 1);
        // Moving again: the moving scale comes back, and the slow still frame did not raise it.
        g.observe(1000.0, Motion::Moving);
        assert_eq!(g.scale(), 2);
    }

    #[test]
    fn nonsense_measurements_are_ignored() {
        let mut g = Governor::new(100.0, 32, 1, 1024).unwrap();
        for ms in [f64::NAN, f64::INFINITY, -1.0, 0.0] {
            assert_eq!(g.observe(ms, Motion::Moving), 32);
        }
    }
}
