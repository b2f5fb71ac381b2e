//! The operator lock: one operator at a time may change the wall. Whoever takes it
//! (`POST /api/lock`) gets a lock id, which its changes carry in the `X-Isowall-Lock` header;
//! while it is held, every other client's change is refused with 423 Locked, naming who holds it
//! and since when. The holder releases it (`POST /api/lock/release`), or it lapses after
//! [`OperatorLock::idle`] without a change from its holder. Reading (the status, the pictures, the
//! logs) is never locked. Time is passed in (`now`), so the rules are tested without a clock.

use std::time::Duration;

/// The longest holder name kept (the rest is cut).
pub const MAX_HOLDER_CHARS: usize = 64;
/// The default idle time after which a lock lapses.
pub const DEFAULT_IDLE: Duration = Duration::from_secs(300);

/// Who holds the lock.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Holder {
    pub id: String,
    pub holder: String,
    /// When it was taken (the caller's clock) and the Unix time (ms) then, for the page.
    pub since: Duration,
    pub since_unix_ms: u64,
    /// The holder's last change (or the taking).
    pub last_used: Duration,
}

/// Why a change is refused: the lock is someone else's.
#[derive(Clone, Debug, PartialEq)]
pub struct Locked {
    pub holder: String,
    pub since_unix_ms: u64,
    pub held_s: f64,
}

impl Locked {
    pub fn message(&self) -> String {
        format!(
            "the wall is locked by `{}` (for {:.0} s): changes need its lock id in X-Isowall-Lock, or wait until it is released",
            self.holder, self.held_s
        )
    }
}

/// The lock (see the module docs).
#[derive(Debug)]
pub struct OperatorLock {
    idle: Duration,
    held: Option<Holder>,
    /// How many times the holder changed (taken, released, lapsed): a page reading the status
    /// tells by it whether the status was made before or after its own take.
    changes: u64,
}

impl OperatorLock {
    pub fn new(idle: Duration) -> OperatorLock {
        OperatorLock { idle, held: None, changes: 0 }
    }

    pub fn idle(&self) -> Duration {
        self.idle
    }

    /// How many times the holder changed so far (see the field).
    pub fn changes(&self) -> u64 {
        self.changes
    }

    /// The holder at `now` (a lapsed lock is dropped first).
    pub fn holder(&mut self, now: Duration) -> Option<&Holder> {
        if self.held.as_ref().is_some_and(|h| now.saturating_sub(h.last_used) >= self.idle) {
            let h = self.held.take().expect("checked");
            self.changes += 1;
            tracing::info!(holder = %h.holder, "console: the operator lock lapsed after {:?} idle", self.idle);
        }
        self.held.as_ref()
    }

    fn locked(&self, h: &Holder, now: Duration) -> Locked {
        Locked {
            holder: h.holder.clone(),
            since_unix_ms: h.since_unix_ms,
            held_s: now.saturating_sub(h.since).as_secs_f64(),
        }
    }

    /// `holder` takes the lock with the fresh id `id` (the holder's own lock is renewed, same
    /// id, when `presented` is its id); refused while another holds it.
    pub fn take(
        &mut self,
        now: Duration,
        unix_ms: u64,
        holder: &str,
        id: String,
        presented: Option<&str>,
    ) -> Result<Holder, Locked> {
        if let Some(h) = self.holder(now) {
            if presented.is_some_and(|p| same(p, &h.id)) {
                let h = self.held.as_mut().expect("held");
                h.last_used = now;
                return Ok(h.clone());
            }
            return Err(self.locked(self.held.as_ref().expect("held"), now));
        }
        let holder: String = holder.chars().filter(|c| !c.is_control()).take(MAX_HOLDER_CHARS).collect();
        let h = Holder { id, holder, since: now, since_unix_ms: unix_ms, last_used: now };
        tracing::info!(holder = %h.holder, "console: the operator lock is taken");
        self.held = Some(h.clone());
        self.changes += 1;
        Ok(h)
    }

    /// Whether a change carrying `presented` may go ahead at `now`: always when nobody holds the
    /// lock; when its holder's id, which counts as the holder's use.
    pub fn check(&mut self, now: Duration, presented: Option<&str>) -> Result<(), Locked> {
        let Some(h) = self.holder(now) else { return Ok(()) };
        if presented.is_some_and(|p| same(p, &h.id)) {
            self.held.as_mut().expect("held").last_used = now;
            return Ok(());
        }
        Err(self.locked(self.held.as_ref().expect("held"), now))
    }

    /// The holder releases it (`presented` must be its id).
    pub fn release(&mut self, now: Duration, presented: Option<&str>) -> Result<(), Locked> {
        match self.holder(now) {
            None => Ok(()),
            Some(h) if presented.is_some_and(|p| same(p, &h.id)) => {
                tracing::info!(holder = %h.holder, "console: the operator lock is released");
                self.held = None;
                self.changes += 1;
                Ok(())
            }
            Some(_) => Err(self.locked(self.held.as_ref().expect("held"), now)),
        }
    }
}

/// Ids compared in constant time.
fn same(a: &str, b: &str) -> bool {
    use subtle::ConstantTimeEq;
    a.len() == b.len() && bool::from(a.as_bytes().ct_eq(b.as_bytes()))
}

/// A lock id nobody can guess: 128 bits from the standard library's randomly keyed hasher
/// (seeded from the OS), mixed with the time and a counter.
pub fn fresh_id(unix_ms: u64) -> String {
    use std::hash::{BuildHasher, Hasher};
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let part = |salt: u64| {
        let mut h = std::collections::hash_map::RandomState::new().build_hasher();
        h.write_u64(unix_ms);
        h.write_u64(n);
        h.write_u64(salt);
        h.finish()
    };
    format!("{:016x}{:016x}", part(1), part(2))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(x: u64) -> Duration {
        Duration::from_secs(x)
    }

    #[test]
    fn one_holder_changes_others_are_refused_until_release_or_idle() {
        let mut lock = OperatorLock::new(s(60));
        assert_eq!(lock.check(s(0), None), Ok(()), "nobody holds it: open");
        let a = lock.take(s(10), 1_000, "alice\n", "id-a".into(), None).unwrap();
        assert_eq!((a.holder.as_str(), a.since_unix_ms), ("alice", 1_000));
        assert_eq!(lock.changes(), 1, "taken");
        let refused = lock.take(s(11), 2_000, "bob", "id-b".into(), None).unwrap_err();
        assert_eq!((refused.holder.as_str(), refused.since_unix_ms, refused.held_s), ("alice", 1_000, 1.0));
        assert!(refused.message().contains("locked by `alice`"), "{}", refused.message());
        assert!(lock.check(s(12), None).is_err());
        assert!(lock.check(s(12), Some("id-b")).is_err());
        assert!(lock.check(s(12), Some("id-a2")).is_err());
        // The holder's changes go ahead and keep it alive past the first idle time.
        assert_eq!(lock.check(s(60), Some("id-a")), Ok(()));
        assert!(lock.check(s(119), None).is_err(), "used at 60 s: held until 120 s");
        // Renewing with its own id keeps the id.
        assert_eq!(lock.take(s(100), 0, "alice", "other".into(), Some("id-a")).unwrap().id, "id-a");
        assert!(lock.release(s(101), Some("id-b")).is_err(), "only the holder releases");
        assert_eq!(lock.changes(), 1, "renewals, uses and refusals change no holder");
        assert_eq!(lock.release(s(101), Some("id-a")), Ok(()));
        assert_eq!(lock.changes(), 2, "released");
        assert_eq!(lock.check(s(102), None), Ok(()));
        // Idle: lapses.
        lock.take(s(200), 0, "bob", "id-b".into(), None).unwrap();
        assert!(lock.check(s(259), None).is_err());
        assert_eq!(lock.check(s(260), None), Ok(()), "60 s idle: lapsed");
        assert!(lock.holder(s(260)).is_none());
        assert_eq!(lock.changes(), 4, "taken by bob, lapsed");
    }

    #[test]
    fn ids_differ_and_holders_are_bounded() {
        let a = fresh_id(5);
        let b = fresh_id(5);
        assert_ne!(a, b);
        assert_eq!(a.len(), 32);
        let mut lock = OperatorLock::new(DEFAULT_IDLE);
        let h = lock.take(s(0), 0, &"x".repeat(500), a, None).unwrap();
        assert_eq!(h.holder.chars().count(), MAX_HOLDER_CHARS);
    }
}
