//! When a released frame is shown: the timed swap's present time and the frame grid.
//!
//! A frame released at controller time `now` is presented by every node at one moment `T`, on
//! the controller's clock, a margin after the release ([`SwapTiming::present_at`]); each node's
//! Swap carries `T` in that node's clock (the controller's offset estimate for it), and the node
//! waits until then. The margin has to cover the Swaps' delivery to the last node and the node's
//! wake-up: with [`MarginSetting::Auto`] it is learned from what the nodes report
//! ([`SwapTiming::observe`]: from the release to the moment a node was ready to wait): each
//! frame's slowest node, over the last [`SwapTiming::WINDOW`] frames, at the
//! [`SwapTiming::QUANTILE`] (a lone retransmitted Swap does not hold the wall's latency up for a
//! window; a node slow every frame does set it), with a quarter of headroom and
//! [`SwapTiming::HEADROOM`] more, within [`SwapTiming::FLOOR`] and [`SwapTiming::CEILING`].
//! A node's report is a claim: one node alone can hold a frame's delay at most
//! [`SwapTiming::ONE_NODE_SHARE`] above the next slowest node's (above zero on a wall of one), so
//! a node that says it was ready late every frame raises the wall's latency by that much, not to
//! the ceiling.
//! A node whose Swap comes after its `T` presents at once: a late swap, which the learning takes
//! in too.
//!
//! With a frame rate, present times fall on a steady grid of the controller's clock (period
//! `1 / rate`, from the first paced present): a frame ready in time takes the first slot at least
//! a margin after its release, one that is not waits for the next slot. Present times never go
//! backwards. Sans-IO: times are passed in.

use std::collections::VecDeque;
use std::fmt;
use std::str::FromStr;
use std::time::Duration;

/// `[wall] swap_margin_ms`: how the margin between a release and its present time is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum MarginSetting {
    /// Learned from the nodes' reports (the default).
    #[default]
    Auto,
    /// This margin, always.
    Fixed(Duration),
    /// No present time: a node presents when its Swap arrives (the untimed swap).
    Off,
}

impl MarginSetting {
    /// The largest margin a config may fix: a second (a present time further out than that is
    /// refused by nodes as a protocol error).
    pub const MAX: Duration = Duration::from_secs(1);
}

impl FromStr for MarginSetting {
    type Err = String;

    /// `auto`, `off`, or milliseconds in (0, 1000] (a fraction is fine).
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim() {
            t if t.eq_ignore_ascii_case("auto") => Ok(MarginSetting::Auto),
            t if t.eq_ignore_ascii_case("off") => Ok(MarginSetting::Off),
            t => {
                let ms: f64 = t.parse().map_err(|_| {
                    format!("swap margin {s:?} is not `auto`, `off` or a number of milliseconds")
                })?;
                MarginSetting::from_ms(ms)
            }
        }
    }
}

impl MarginSetting {
    /// A fixed margin of `ms` milliseconds, in (0, 1000].
    pub fn from_ms(ms: f64) -> Result<Self, String> {
        if !(ms > 0.0 && ms <= Self::MAX.as_secs_f64() * 1e3) {
            return Err(format!(
                "swap margin {ms} ms is not in (0, {}] ms (write `off` for no present time)",
                Self::MAX.as_millis()
            ));
        }
        Ok(MarginSetting::Fixed(Duration::from_secs_f64(ms / 1e3)))
    }
}

impl fmt::Display for MarginSetting {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MarginSetting::Auto => f.write_str("auto"),
            MarginSetting::Off => f.write_str("off"),
            MarginSetting::Fixed(d) => write!(f, "{} ms", d.as_secs_f64() * 1e3),
        }
    }
}

/// The present times of a wall's frames (see the module docs).
#[derive(Debug, Clone)]
pub struct SwapTiming {
    setting: MarginSetting,
    period: Option<Duration>,
    margin: Duration,
    /// The largest release-to-ready delay of each of the last frames, newest last.
    frames: VecDeque<Duration>,
    /// The two largest delays of the frame being observed, largest first (folded into `frames`
    /// at `frame_done`).
    current: Option<(Duration, Option<Duration>)>,
    last_present: Option<Duration>,
    grid_origin: Option<Duration>,
}

impl SwapTiming {
    /// The learned margin never goes below this (a LAN's delivery and a thread's wake-up).
    pub const FLOOR: Duration = Duration::from_micros(200);
    /// Nor above this: a node that needs more is late, not waited for.
    pub const CEILING: Duration = Duration::from_millis(25);
    /// The learned margin before any report.
    pub const INITIAL: Duration = Duration::from_millis(2);
    /// Frames whose delays the learned margin covers.
    pub const WINDOW: usize = 256;
    /// The share of the window's frames whose slowest node the learned margin covers.
    pub const QUANTILE: f64 = 0.99;
    /// Added to the learned margin beyond its quarter of headroom.
    pub const HEADROOM: Duration = Duration::from_micros(100);
    /// How far one node's delay may stand above the next slowest node's in a frame: a busy
    /// node's wake-up (3.6-5.3 ms late at p99 where its cores are full, docs/swap.md) fits.
    pub const ONE_NODE_SHARE: Duration = Duration::from_millis(5);

    /// Timing by `setting`, paced at `frame_rate` frames a second (`None`: unpaced, a frame is
    /// presented as soon as its margin allows). The rate must be positive and finite (the
    /// config checks it).
    pub fn new(setting: MarginSetting, frame_rate: Option<f64>) -> SwapTiming {
        let margin = match setting {
            MarginSetting::Fixed(d) => d,
            MarginSetting::Off => Duration::ZERO,
            MarginSetting::Auto => Self::INITIAL,
        };
        SwapTiming {
            setting,
            period: frame_rate
                .filter(|r| r.is_finite() && *r > 0.0)
                .map(|r| Duration::from_secs_f64(1.0 / r)),
            margin,
            frames: VecDeque::new(),
            current: None,
            last_present: None,
            grid_origin: None,
        }
    }

    pub fn setting(&self) -> MarginSetting {
        self.setting
    }

    /// The frame grid's period, when paced.
    pub fn period(&self) -> Option<Duration> {
        self.period
    }

    /// The margin a release now would get (zero when off).
    pub fn margin(&self) -> Duration {
        self.margin
    }

    /// The present time of a frame released at `now`, on the controller's clock; `None` when
    /// the swap is untimed (margin off and unpaced).
    pub fn present_at(&mut self, now: Duration) -> Option<Duration> {
        if self.setting == MarginSetting::Off && self.period.is_none() {
            return None;
        }
        let earliest = now + self.margin;
        let at = match self.period {
            None => self.last_present.map_or(earliest, |last| earliest.max(last)),
            Some(period) => {
                let origin = *self.grid_origin.get_or_insert(earliest);
                let after = earliest.max(self.last_present.map_or(origin, |l| l + period));
                let slots = after.saturating_sub(origin).as_nanos().div_ceil(period.as_nanos().max(1));
                origin + period * u32::try_from(slots).unwrap_or(u32::MAX)
            }
        };
        self.last_present = Some(at);
        Some(at)
    }

    /// A node's report for the frame being presented: `delay` from the release to the moment
    /// it was ready to wait for the present time (through its clock offset).
    pub fn observe(&mut self, delay: Duration) {
        self.current = Some(match self.current {
            None => (delay, None),
            Some((a, _)) if delay > a => (delay, Some(a)),
            Some((a, b)) => (a, Some(b.map_or(delay, |b| b.max(delay)))),
        });
    }

    /// The frame's reports are all in: the learned margin follows them.
    pub fn frame_done(&mut self) {
        let Some((slowest, next)) = self.current.take() else { return };
        let d = slowest.min(next.unwrap_or(Duration::ZERO) + Self::ONE_NODE_SHARE);
        self.frames.push_back(d);
        if self.frames.len() > Self::WINDOW {
            self.frames.pop_front();
        }
        if self.setting == MarginSetting::Auto {
            let mut sorted: Vec<Duration> = self.frames.iter().copied().collect();
            sorted.sort_unstable();
            let at = ((sorted.len() as f64 * Self::QUANTILE).ceil() as usize).clamp(1, sorted.len()) - 1;
            let worst = sorted[at];
            self.margin = (worst + worst / 4 + Self::HEADROOM).clamp(Self::FLOOR, Self::CEILING);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn us(x: u64) -> Duration {
        Duration::from_micros(x)
    }

    #[test]
    fn the_setting_reads_auto_off_and_milliseconds() {
        assert_eq!("auto".parse::<MarginSetting>(), Ok(MarginSetting::Auto));
        assert_eq!(" OFF ".parse::<MarginSetting>(), Ok(MarginSetting::Off));
        assert_eq!("1.5".parse::<MarginSetting>(), Ok(MarginSetting::Fixed(us(1_500))));
        for bad in ["0", "-1", "1001", "nan", "inf", "soon"] {
            let e = bad.parse::<MarginSetting>().unwrap_err();
            assert!(e.contains("swap margin"), "{bad}: {e}");
        }
    }

    #[test]
    fn the_learned_margin_covers_the_slowest_delivery_of_the_window() {
        let mut t = SwapTiming::new(MarginSetting::Auto, None);
        assert_eq!(t.present_at(us(10_000)), Some(us(10_000) + SwapTiming::INITIAL));
        // Four nodes ready 300..600 us after the release: 600 x 5/4 + 100 = 850 us.
        for d in [300, 400, 600, 500] {
            t.observe(us(d));
        }
        t.frame_done();
        assert_eq!(t.margin(), us(850));
        // Slow frames raise it once they are more than 1% of the window; it stays while they
        // are in the window, then leaves. Two lone slow frames (lost packets) do not.
        for _ in 0..SwapTiming::WINDOW - 1 {
            t.observe(us(400));
            t.frame_done();
        }
        for _ in 0..2 {
            t.observe(us(9_000));
            t.frame_done();
        }
        assert_eq!(t.margin(), us(600), "two slow frames of 256");
        t.observe(us(4_000));
        t.frame_done();
        assert_eq!(t.margin(), us(5_100), "three slow frames of 256: the third slowest");
        for _ in 0..SwapTiming::WINDOW - 3 {
            t.observe(us(400));
            t.frame_done();
        }
        assert_eq!(t.margin(), us(5_100));
        t.observe(us(400));
        t.frame_done();
        assert_eq!(t.margin(), us(600));
        // Within the floor and the ceiling.
        t.observe(us(1));
        for _ in 0..SwapTiming::WINDOW {
            t.observe(us(1));
            t.frame_done();
        }
        assert_eq!(t.margin(), SwapTiming::FLOOR);
        for _ in 0..SwapTiming::WINDOW {
            t.observe(Duration::from_secs(3));
            t.observe(Duration::from_secs(3));
            t.frame_done();
        }
        assert_eq!(t.margin(), SwapTiming::CEILING);
    }

    #[test]
    fn one_node_that_says_it_is_late_every_frame_raises_the_margin_by_its_share_only() {
        let mut t = SwapTiming::new(MarginSetting::Auto, None);
        for _ in 0..SwapTiming::WINDOW {
            // Three honest nodes ready 300..500 us after the release; a fourth claims 25 ms.
            for d in [300, 500, 400, 25_000] {
                t.observe(us(d));
            }
            t.frame_done();
        }
        let want = us(500) + SwapTiming::ONE_NODE_SHARE;
        assert_eq!(t.margin(), want + want / 4 + SwapTiming::HEADROOM);
        assert!(t.margin() < SwapTiming::CEILING / 3, "{:?}", t.margin());
        // Two nodes late together are waited for, up to the ceiling.
        for _ in 0..SwapTiming::WINDOW {
            for d in [300, 20_000, 400, 20_000] {
                t.observe(us(d));
            }
            t.frame_done();
        }
        assert_eq!(t.margin(), SwapTiming::CEILING);
    }

    #[test]
    fn a_fixed_margin_stays_and_off_gives_no_present_time() {
        let mut t = SwapTiming::new(MarginSetting::Fixed(us(700)), None);
        t.observe(us(5_000));
        t.frame_done();
        assert_eq!(t.present_at(us(1_000)), Some(us(1_700)));
        let mut off = SwapTiming::new(MarginSetting::Off, None);
        assert_eq!(off.present_at(us(1_000)), None);
        assert_eq!(off.margin(), Duration::ZERO);
    }

    #[test]
    fn present_times_never_go_back() {
        let mut t = SwapTiming::new(MarginSetting::Fixed(us(5_000)), None);
        assert_eq!(t.present_at(us(10_000)), Some(us(15_000)));
        t = SwapTiming { setting: MarginSetting::Fixed(us(100)), margin: us(100), ..t };
        // Released 1 ms later with a smaller margin: not before the previous present.
        assert_eq!(t.present_at(us(11_000)), Some(us(15_000)));
    }

    #[test]
    fn paced_frames_fall_on_the_grid_and_a_late_one_waits_for_the_next_slot() {
        let mut t = SwapTiming::new(MarginSetting::Fixed(us(1_000)), Some(50.0));
        let period = us(20_000);
        assert_eq!(t.period(), Some(period));
        let origin = t.present_at(us(5_000)).unwrap();
        assert_eq!(origin, us(6_000));
        // Released early (rendered fast): the next slot, not sooner.
        assert_eq!(t.present_at(us(7_000)), Some(origin + period));
        // Released 3 ms before the slot after: a margin fits, that slot.
        assert_eq!(t.present_at(origin + period * 2 - us(3_000)), Some(origin + period * 2));
        // Released 0.5 ms before a slot: the margin does not fit, the slot after it.
        assert_eq!(t.present_at(origin + period * 3 - us(500)), Some(origin + period * 4));
        // Off but paced: on the grid with no margin.
        let mut p = SwapTiming::new(MarginSetting::Off, Some(25.0));
        let o = p.present_at(us(1)).unwrap();
        assert_eq!(p.present_at(o + us(1)), Some(o + us(40_000)));
    }
}
