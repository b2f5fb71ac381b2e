//! The timed swap on a node: presenting at the Swap's present time.
//!
//! [`PreciseWait`] is the precise wait both presenting threads use: asleep until shortly before
//! the time, then a spin. A sleep overshoots by the kernel's timer slack and, on a machine whose
//! cores the renders fill, by the scheduler's wake-up: the spin is learned from the overshoots
//! of the thread's last sleeps ([`PreciseWait::spin`]), so it is as short as the machine allows. A node that presents offscreen presents on its own [`Presenter`] thread, so the wait never
//! holds up the network loop or the render thread; a node with windows presents on the render
//! thread, which owns the surfaces (`render_thread.rs`), with the same wait before it. Either way
//! the outcome comes back to the session loop as a [`Shown`], with the moment the presenting
//! thread took the swap up (its wait began: after the present time, the swap was late).

use std::time::{Duration, Instant};

/// The precise wait of one presenting thread (see the module docs).
#[derive(Debug)]
pub struct PreciseWait {
    /// How late the last sleeps woke, newest last.
    overshoots: std::collections::VecDeque<Duration>,
    spin: Duration,
}

impl Default for PreciseWait {
    fn default() -> Self {
        PreciseWait { overshoots: Default::default(), spin: Self::MIN_SPIN }
    }
}

impl PreciseWait {
    /// The shortest spin: a sleep's usual overshoot on an idle machine.
    pub const MIN_SPIN: Duration = Duration::from_micros(200);
    /// The longest: the CPU a spin may take from the renders (a longer one took a 2-core
    /// wall's frame rate down by up to a third without shortening the wait's tail: docs/swap.md).
    pub const MAX_SPIN: Duration = Duration::from_micros(500);
    /// Sleeps whose overshoots set the spin.
    pub const WINDOW: usize = 128;

    /// The spin the next wait ends with: the second largest overshoot of the last
    /// [`PreciseWait::WINDOW`] sleeps, and half again, within [`PreciseWait::MIN_SPIN`] and
    /// [`PreciseWait::MAX_SPIN`].
    #[cfg(test)]
    pub fn spin(&self) -> Duration {
        self.spin
    }

    /// Waits until `deadline` (at once if it has passed): asleep until [`PreciseWait::spin`]
    /// before it, then spinning.
    pub fn wait_until(&mut self, deadline: Instant) {
        let wake = deadline.checked_sub(self.spin);
        if let Some(wake) = wake.filter(|&w| w > Instant::now()) {
            std::thread::sleep(wake - Instant::now());
            self.learn(Instant::now().saturating_duration_since(wake));
        }
        while Instant::now() < deadline {
            std::hint::spin_loop();
        }
    }

    fn learn(&mut self, overshoot: Duration) {
        self.overshoots.push_back(overshoot);
        if self.overshoots.len() > Self::WINDOW {
            self.overshoots.pop_front();
        }
        let mut sorted: Vec<Duration> = self.overshoots.iter().copied().collect();
        sorted.sort_unstable();
        let second = sorted[sorted.len().saturating_sub(2)];
        self.spin = (second + second / 2).clamp(Self::MIN_SPIN, Self::MAX_SPIN);
    }
}

/// A frame presented (or not: `result` says why).
#[derive(Debug)]
pub struct Shown {
    pub frame_id: u64,
    /// When the presenting thread took the swap up.
    pub waiting_from: Instant,
    /// When it was presented.
    pub result: Result<Instant, String>,
}

/// The presenting thread of an offscreen node: presents (takes the moment) at each swap's time.
pub struct Presenter {
    /// (frame, present time, when it was handed over).
    jobs: std::sync::mpsc::Sender<(u64, Option<Instant>, Instant)>,
}

impl Presenter {
    /// Starts the thread; each swap's [`Shown`] goes to `shown`. It ends when the presenter is
    /// dropped.
    pub fn start(shown: tokio::sync::mpsc::UnboundedSender<Shown>) -> std::io::Result<Presenter> {
        let (jobs, rx) = std::sync::mpsc::channel::<(u64, Option<Instant>, Instant)>();
        std::thread::Builder::new().name("presenter".into()).spawn(move || {
            let mut wait = PreciseWait::default();
            let mut last_done: Option<Instant> = None;
            while let Ok((frame_id, at, handed)) = rx.recv() {
                // Handed over while this thread still waited for the previous frame's time: it
                // was ready for this one then (a paced frame queued for its slot is no slow node).
                let waiting_from = match last_done {
                    Some(done) if handed < done => handed,
                    _ => Instant::now(),
                };
                if let Some(at) = at {
                    wait.wait_until(at);
                }
                let shown_at = Instant::now();
                last_done = Some(shown_at);
                if shown.send(Shown { frame_id, waiting_from, result: Ok(shown_at) }).is_err() {
                    return;
                }
            }
        })?;
        Ok(Presenter { jobs })
    }

    /// Presents `frame_id` at `at` (`None`: now).
    pub fn present(&self, frame_id: u64, at: Option<Instant>) {
        // The thread only stops when this presenter is dropped.
        let _ = self.jobs.send((frame_id, at, Instant::now()));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_spin_follows_the_sleeps_overshoots_within_its_bounds() {
        let mut w = PreciseWait::default();
        assert_eq!(w.spin(), PreciseWait::MIN_SPIN);
        for us in [50, 900, 240, 30] {
            w.learn(Duration::from_micros(us));
        }
        // The second largest, 240 us, and half again.
        assert_eq!(w.spin(), Duration::from_micros(360));
        w.learn(Duration::from_millis(50));
        w.learn(Duration::from_millis(40));
        assert_eq!(w.spin(), PreciseWait::MAX_SPIN);
        for _ in 0..PreciseWait::WINDOW {
            w.learn(Duration::from_micros(10));
        }
        assert_eq!(w.spin(), PreciseWait::MIN_SPIN);
        // A wait ends at its deadline, not before.
        let at = Instant::now() + Duration::from_millis(5);
        w.wait_until(at);
        assert!(Instant::now() >= at);
    }

    #[test]
    fn a_presenter_presents_at_the_time_and_a_past_time_at_once() {
        let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
        let p = Presenter::start(tx).unwrap();
        let at = Instant::now() + Duration::from_millis(20);
        p.present(7, Some(at));
        p.present(8, None);
        let past = Instant::now();
        p.present(9, Some(past));
        let a = rx.blocking_recv().unwrap();
        assert_eq!(a.frame_id, 7);
        let shown = a.result.unwrap();
        assert!(shown >= at, "presented {:?} early", at - shown);
        assert!(a.waiting_from < at);
        // The next ones come after it, at once.
        let b = rx.blocking_recv().unwrap();
        assert_eq!(b.frame_id, 8);
        assert!(b.result.unwrap() >= shown);
        let c = rx.blocking_recv().unwrap();
        assert_eq!(c.frame_id, 9);
        assert!(c.waiting_from > past, "taken up after its time: a late swap");
    }
}
