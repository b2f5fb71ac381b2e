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
//!
//! The presenting thread runs real-time (`crate::realtime`) where `present_priority` asks and
//! the process may: the offscreen [`Presenter`] thread for its whole life (it does nothing but
//! wait and take the moment), the render thread only from the start of a swap's wait to its
//! present's return ([`PreciseWait::present_at`]), lowered before it renders again. What runs
//! real-time is bounded: a sleep, a spin of at most [`PreciseWait::MAX_SPIN`], the present
//! (which blocks in the driver asleep, not spinning, where a display is slow), no allocation
//! and no lock another thread holds.

use crate::realtime::{self, PresentScheduling};
use std::time::{Duration, Instant};

/// The precise wait of one presenting thread (see the module docs).
#[derive(Debug)]
pub struct PreciseWait {
    /// How late the last sleeps woke, newest last.
    overshoots: std::collections::VecDeque<Duration>,
    spin: Duration,
    /// The render thread's windows: raised to SCHED_FIFO at this priority for each wait and
    /// present (`None`: not raised, or refused once already).
    realtime: Option<u8>,
}

impl Default for PreciseWait {
    fn default() -> Self {
        PreciseWait {
            overshoots: std::collections::VecDeque::with_capacity(Self::WINDOW + 1),
            spin: Self::MIN_SPIN,
            realtime: None,
        }
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

    /// The render thread's wait: raised to SCHED_FIFO at `priority` for each wait and present
    /// (0: never). Tries once now, on the calling thread, and says what it runs as.
    pub fn raised_for_presents(priority: u8) -> (PreciseWait, PresentScheduling) {
        let mut w = PreciseWait::default();
        if priority == 0 {
            return (w, PresentScheduling::Off);
        }
        let nice = realtime::nice();
        match realtime::raise(priority).and_then(|()| realtime::lower(nice)) {
            Ok(()) => {
                w.realtime = Some(priority);
                (w, PresentScheduling::RealTime { priority, cpu: None })
            }
            Err(e) => (w, PresentScheduling::Refused(e)),
        }
    }

    /// Waits until `at` (if given) and runs `present`, real-time from the wait's start to the
    /// present's return where [`PreciseWait::raised_for_presents`] allowed it, then lowered to
    /// the thread's own scheduling again.
    pub fn present_at<T>(&mut self, at: Option<Instant>, present: impl FnOnce() -> T) -> T {
        let raised = self.realtime.map(|p| (realtime::nice(), realtime::raise(p)));
        if let Some((_, Err(e))) = &raised {
            tracing::warn!("the render thread's presents stay at normal scheduling: {e}");
            self.realtime = None;
        }
        if let Some(at) = at {
            self.wait_until(at);
        }
        let out = present();
        if let Some((nice, Ok(()))) = raised {
            if let Err(e) = realtime::lower(nice) {
                tracing::error!("the render thread could not return to normal scheduling: {e}");
            }
        }
        out
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
        if self.overshoots.len() == Self::WINDOW {
            self.overshoots.pop_front();
        }
        self.overshoots.push_back(overshoot);
        // The two largest, without sorting a copy (no allocation while real-time).
        let (mut first, mut second) = (Duration::ZERO, Duration::ZERO);
        for &o in &self.overshoots {
            if o > first {
                (first, second) = (o, first);
            } else if o > second {
                second = o;
            }
        }
        let second = if self.overshoots.len() == 1 { first } else { second };
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
    /// Starts the thread, real-time at `priority` (0: normal scheduling) and on core `cpu` where
    /// given; each swap's [`Shown`] goes to `shown`. Returns it with what it runs as. It ends
    /// when the presenter is dropped.
    pub fn start(
        shown: tokio::sync::mpsc::UnboundedSender<Shown>,
        priority: u8,
        cpu: Option<usize>,
    ) -> std::io::Result<(Presenter, PresentScheduling)> {
        let (jobs, rx) = std::sync::mpsc::channel::<(u64, Option<Instant>, Instant)>();
        let (told, scheduling) = std::sync::mpsc::channel::<PresentScheduling>();
        std::thread::Builder::new().name("presenter".into()).spawn(move || {
            let pinned = cpu.map(|c| realtime::pin_to(c).map(|()| c));
            let s = if priority == 0 {
                PresentScheduling::Off
            } else {
                match realtime::raise(priority) {
                    Err(e) => PresentScheduling::Refused(e),
                    Ok(()) => {
                        PresentScheduling::RealTime { priority, cpu: pinned.clone().and_then(Result::ok) }
                    }
                }
            };
            if let Some(Err(e)) = pinned {
                tracing::warn!("the presenting thread has no core of its own: {e}");
            }
            let _ = told.send(s);
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
        let s =
            scheduling.recv().map_err(|_| std::io::Error::other("the presenting thread ended at start"))?;
        Ok((Presenter { jobs }, s))
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
        let (p, _) = Presenter::start(tx, 0, None).unwrap();
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
