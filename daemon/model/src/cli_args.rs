//! The ranges of the command lines' numbers: one value parser per kind of flag, so that every
//! command that shares a flag (`isowalld render` and its benches, `isowall orbit` and
//! `isowall bench balance`) holds it to the same range, from the same constants as the wall
//! config and the frame state. A number out of range is refused by clap with the range named,
//! before anything is allocated for it.

use crate::config::MAX_DEADLINE_MS;
use crate::governor::MAX_SCALE;
use crate::render_state::MAX_AO_SAMPLES;

/// The most frames a bench drives or renders in one run (each is a row of its plan and output).
pub const MAX_BENCH_FRAMES: u32 = 100_000;
/// The most repeats of a measurement.
pub const MAX_REPEATS: usize = 1000;
/// The most seconds to wait for a wall's nodes to start.
pub const MAX_START_TIMEOUT_S: u64 = 3600;
/// The largest orbit step per frame, either way, in degrees.
pub const MAX_DEGREES_PER_FRAME: f64 = 360.0;

fn whole<T: std::str::FromStr>(s: &str) -> Result<T, String> {
    s.trim().parse::<T>().map_err(|_| format!("'{s}' is not a whole number"))
}

/// A whole number in `lo..=hi`, or why not (`what` names it).
pub fn whole_within<T: std::str::FromStr + PartialOrd + std::fmt::Display + Copy>(
    s: &str,
    lo: T,
    hi: T,
    what: &str,
) -> Result<T, String> {
    within(whole(s)?, lo, hi, what)
}

fn within<T: PartialOrd + std::fmt::Display + Copy>(v: T, lo: T, hi: T, what: &str) -> Result<T, String> {
    if lo <= v && v <= hi {
        Ok(v)
    } else {
        Err(format!("{what} {v} is outside {lo}..={hi}"))
    }
}

/// `WxH` image size, each side 1..=16384.
pub fn size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("expected WxH, e.g. 512x512, got '{s}'"))?;
    let (w, h): (u32, u32) = (whole(w)?, whole(h)?);
    if !(1..=16384).contains(&w) || !(1..=16384).contains(&h) {
        return Err(format!("{w}x{h}: each side must be 1..=16384"));
    }
    Ok((w, h))
}

/// AO samples per pixel per frame: 0 (no AO) ..= [`MAX_AO_SAMPLES`], as `render --ao-samples`.
pub fn ao_samples(s: &str) -> Result<u32, String> {
    within(whole(s)?, 0, MAX_AO_SAMPLES, "AO samples")
}

/// A comma-separated list of AO sample counts, each as [`ao_samples`].
pub fn sample_list(s: &str) -> Result<Vec<u32>, String> {
    s.split(',').map(ao_samples).collect()
}

/// Frames a bench drives: 1 ..= [`MAX_BENCH_FRAMES`].
pub fn bench_frames(s: &str) -> Result<u32, String> {
    within(whole(s)?, 1, MAX_BENCH_FRAMES, "frames")
}

/// Frames a bench drives, as a `u64` count: 1 ..= [`MAX_BENCH_FRAMES`].
pub fn bench_frames_u64(s: &str) -> Result<u64, String> {
    bench_frames(s).map(u64::from)
}

/// Frames of a still view after a run: 0 ..= [`MAX_BENCH_FRAMES`].
pub fn still_frames(s: &str) -> Result<u32, String> {
    within(whole(s)?, 0, MAX_BENCH_FRAMES, "still frames")
}

/// Repeats of a measurement: 1 ..= [`MAX_REPEATS`].
pub fn repeats(s: &str) -> Result<usize, String> {
    within(whole(s)?, 1, MAX_REPEATS, "repeats")
}

/// The internal resolution's divisor: 1 ..= [`MAX_SCALE`], as the governor's.
pub fn scale(s: &str) -> Result<u32, String> {
    within(whole(s)?, 1, MAX_SCALE, "scale")
}

/// A barrier deadline in milliseconds: 1 ..= [`MAX_DEADLINE_MS`], as `[wall] deadline_ms`.
pub fn deadline_ms(s: &str) -> Result<u64, String> {
    within(whole(s)?, 1, MAX_DEADLINE_MS, "deadline (ms)")
}

/// Seconds to wait for a wall to start: 1 ..= [`MAX_START_TIMEOUT_S`].
pub fn start_timeout(s: &str) -> Result<u64, String> {
    within(whole(s)?, 1, MAX_START_TIMEOUT_S, "start timeout (s)")
}

/// An orbit step or a turn in degrees: finite, within +-[`MAX_DEGREES_PER_FRAME`].
pub fn degrees(s: &str) -> Result<f64, String> {
    let d: f64 = s.trim().parse().map_err(|_| format!("'{s}' is not a number of degrees"))?;
    if !d.is_finite() {
        return Err(format!("{d} degrees is not a finite number"));
    }
    within(d, -MAX_DEGREES_PER_FRAME, MAX_DEGREES_PER_FRAME, "degrees")
}

/// A light's radiance or an exposure: a finite number >= 0, as `render --exposure`.
pub fn non_negative(s: &str) -> Result<f64, String> {
    let x: f64 = s.trim().parse().map_err(|_| format!("'{s}' is not a number"))?;
    if x.is_finite() && x >= 0.0 {
        Ok(x)
    } else {
        Err(format!("{x} must be a finite number >= 0"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_out_of_their_commands_range_are_refused_with_the_range() {
        assert_eq!(ao_samples("1024"), Ok(1024));
        assert!(ao_samples("4294967295").unwrap_err().contains("0..=1024"));
        assert!(ao_samples("-1").unwrap_err().contains("not a whole number"));
        assert_eq!(sample_list("4, 32"), Ok(vec![4, 32]));
        assert!(sample_list("4,2000").is_err());
        assert!(still_frames("4294967295").unwrap_err().contains("0..=100000"));
        assert_eq!(still_frames("0"), Ok(0));
        assert!(bench_frames("0").is_err());
        assert!(degrees("nan").unwrap_err().contains("not a finite"));
        assert!(degrees("inf").is_err());
        assert!(degrees("361").is_err());
        assert_eq!(degrees("-3"), Ok(-3.0));
        assert!(scale("5").unwrap_err().contains("1..=4"));
        assert!(deadline_ms("0").is_err());
        assert!(repeats("0").is_err());
        assert!(non_negative("-0.1").is_err() && non_negative("NaN").is_err());
        assert_eq!(size("16x9"), Ok((16, 9)));
        assert!(size("0x9").is_err() && size("16384x16385").is_err());
    }
}
