//! The clock of a wall's processes: `CLOCK_MONOTONIC`, which every process of one machine shares.
//!
//! The frame machines take time as a [`std::time::Duration`] since an epoch of the caller's
//! choosing. Both binaries choose [`epoch`], the instant that clock reads zero, so their times are
//! the clock's own readings: two daemons (and the controller) on one machine then agree exactly,
//! and the spread of their reported present times is the true swap skew, beside the one the
//! controller measures through its clock offset estimates. Across machines the offsets are
//! learned as always (`isowall_model::clock`).

use std::time::{Duration, Instant};

/// The instant `CLOCK_MONOTONIC` read zero (`std::time::Instant` is that clock on Linux), or now
/// where it cannot be had.
pub fn epoch() -> Instant {
    let reading = monotonic_now();
    // Read the clock first: the instant after it is no earlier, so the subtraction stays on the
    // clock's side of zero.
    Instant::now().checked_sub(reading).unwrap_or_else(Instant::now)
}

/// `CLOCK_MONOTONIC` now.
fn monotonic_now() -> Duration {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::Monotonic);
    Duration::new(u64::try_from(t.tv_sec).unwrap_or(0), u32::try_from(t.tv_nsec).unwrap_or(0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_epochs_agree_and_times_since_one_are_the_clocks_readings() {
        let (a, b) = (epoch(), epoch());
        // Two readings of one clock: the same epoch, within the clock's and Instant's rounding.
        let apart = if a > b { a - b } else { b - a };
        assert!(apart < Duration::from_micros(50), "{apart:?}");
        let since = a.elapsed();
        let reading = monotonic_now();
        assert!(reading >= since && reading - since < Duration::from_millis(5), "{reading:?} vs {since:?}");
        // A machine up for more than a moment: the epoch is in the past.
        assert!(since > Duration::from_millis(1));
    }
}
