//! How many handshakes a daemon starts for one source address (pure: time is passed in).
//!
//! A TLS handshake costs the daemon a signature and a certificate check; a peer holding any of
//! the wall's certificates (or none) could reconnect hundreds of times a second and starve a small
//! node's CPU. So each source IP has a token bucket: a handshake takes a token before it starts
//! (none left: the connection is refused before any crypto), and one whose connection is then
//! admitted (the controller with its Hello, another node with its pixels) gives it back. Only
//! handshakes that fail or are refused spend the bucket, so the wall's own connections, however
//! often they come back, are never held up by the limit, while a hostile source gets
//! [`HandshakeLimit::burst`] attempts and then [`HandshakeLimit::per_second`].
//!
//! The buckets kept are bounded: full buckets are forgotten (a source not seen is as good as a
//! full bucket), and past [`MAX_SOURCES`] sources with spent buckets the rest share one bucket.

use std::collections::HashMap;
use std::net::IpAddr;
use std::time::Duration;

/// Source addresses with a bucket of their own, at most; others share one.
pub const MAX_SOURCES: usize = 4096;

/// Handshakes per source IP: `burst` at once, then `per_second`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HandshakeLimit {
    pub per_second: f64,
    pub burst: f64,
}

impl HandshakeLimit {
    /// A daemon's: 8 at once, then 4 a second (a wall's reconnects after a restart, a few tools
    /// run in a row, all fit; a flood gets 4 handshakes a second).
    pub const DAEMON: HandshakeLimit = HandshakeLimit { per_second: 4.0, burst: 8.0 };
}

#[derive(Clone, Copy, Debug)]
struct Bucket {
    tokens: f64,
    at: Duration,
}

/// The buckets of every source (see the module notes).
#[derive(Debug)]
pub struct HandshakeLimiter {
    limit: HandshakeLimit,
    buckets: HashMap<Option<IpAddr>, Bucket>,
    started: u64,
    refused: u64,
}

impl HandshakeLimiter {
    pub fn new(limit: HandshakeLimit) -> HandshakeLimiter {
        HandshakeLimiter { limit, buckets: HashMap::new(), started: 0, refused: 0 }
    }

    /// Whether a handshake from `source` may start at `now` (it takes a token); `false`: refuse
    /// the connection before its handshake.
    pub fn start(&mut self, now: Duration, source: IpAddr) -> bool {
        let key = self.key(now, source);
        let bucket = self.refilled(now, key);
        if bucket.tokens >= 1.0 {
            bucket.tokens -= 1.0;
            self.started += 1;
            true
        } else {
            self.refused += 1;
            false
        }
    }

    /// The connection from `source` whose handshake started was admitted: its token comes back.
    pub fn admitted(&mut self, now: Duration, source: IpAddr) {
        // A source without a bucket of its own had it forgotten when full, or shares one.
        let key = [Some(source), None].into_iter().find(|k| self.buckets.contains_key(k));
        let Some(key) = key else { return };
        let burst = self.limit.burst;
        let bucket = self.refilled(now, key);
        bucket.tokens = (bucket.tokens + 1.0).min(burst);
    }

    /// Handshakes started and connections refused before their handshake, so far.
    pub fn counts(&self) -> (u64, u64) {
        (self.started, self.refused)
    }

    /// Sources with a bucket of their own now.
    pub fn sources(&self) -> usize {
        self.buckets.len()
    }

    /// The bucket key of `source`: its own, or the shared one when too many sources are spent.
    fn key(&mut self, now: Duration, source: IpAddr) -> Option<IpAddr> {
        if self.buckets.contains_key(&Some(source)) || self.buckets.len() < MAX_SOURCES {
            return Some(source);
        }
        let limit = self.limit;
        self.buckets.retain(|k, b| k.is_none() || refill(limit, b, now) < limit.burst);
        if self.buckets.len() < MAX_SOURCES {
            Some(source)
        } else {
            None
        }
    }

    fn refilled(&mut self, now: Duration, key: Option<IpAddr>) -> &mut Bucket {
        let limit = self.limit;
        let bucket = self.buckets.entry(key).or_insert(Bucket { tokens: limit.burst, at: now });
        bucket.tokens = refill(limit, bucket, now);
        bucket.at = bucket.at.max(now);
        bucket
    }
}

/// The tokens of `b` at `now` (time going backwards refills nothing).
fn refill(limit: HandshakeLimit, b: &Bucket, now: Duration) -> f64 {
    let dt = now.saturating_sub(b.at).as_secs_f64();
    (b.tokens + dt * limit.per_second).min(limit.burst)
}

#[cfg(test)]
mod tests {
    use super::*;

    const ATTACKER: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(192, 0, 2, 7));
    const WALL: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(192, 0, 2, 1));

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    #[test]
    fn a_flood_gets_its_burst_then_the_rate() {
        let mut l = HandshakeLimiter::new(HandshakeLimit::DAEMON);
        // 450 attempts a second for 10 s on a virtual clock, none admitted.
        let mut started = 0;
        for i in 0..4500u64 {
            if l.start(Duration::from_micros(i * 1_000_000 / 450), ATTACKER) {
                started += 1;
            }
        }
        // 8 at once, then 4 a second for 10 s (at most one more for the partial second).
        assert!((8 + 39..=8 + 41).contains(&started), "{started} handshakes started");
        assert_eq!(l.counts(), (started, 4500 - started));
    }

    #[test]
    fn admitted_connections_spend_nothing_and_other_sources_are_not_held_up() {
        let mut l = HandshakeLimiter::new(HandshakeLimit::DAEMON);
        // The wall's own connections, 100 in one instant, each admitted: never refused.
        for _ in 0..100 {
            assert!(l.start(ms(0), WALL));
            l.admitted(ms(0), WALL);
        }
        // The attacker spends its bucket; the wall's source still has its own.
        let refused = (0..100).filter(|_| !l.start(ms(1), ATTACKER)).count();
        assert_eq!(refused, 92);
        assert!(l.start(ms(1), WALL));
        // The attacker's bucket refills at the rate: one more after 250 ms.
        assert!(!l.start(ms(200), ATTACKER));
        assert!(l.start(ms(260), ATTACKER));
        assert!(!l.start(ms(261), ATTACKER));
        // A refund never fills a bucket past its burst.
        let mut l = HandshakeLimiter::new(HandshakeLimit::DAEMON);
        l.admitted(ms(0), WALL);
        assert_eq!((0..20).filter(|_| l.start(ms(0), WALL)).count(), 8);
    }

    #[test]
    fn spent_sources_are_bounded_and_full_buckets_forgotten() {
        let mut l = HandshakeLimiter::new(HandshakeLimit { per_second: 1.0, burst: 1.0 });
        let ip = |i: u32| IpAddr::V4(std::net::Ipv4Addr::from(0x0a00_0000 + i));
        for i in 0..(MAX_SOURCES as u32 + 10) {
            assert!(l.start(ms(0), ip(i)) || i >= MAX_SOURCES as u32);
        }
        assert!(l.sources() <= MAX_SOURCES + 1, "{} buckets", l.sources());
        // Past the bound the rest share one bucket: one handshake, then refused.
        assert!(!l.start(ms(0), ip(MAX_SOURCES as u32 + 20)));
        // A second later every bucket is full again and forgotten when room is needed.
        assert!(l.start(ms(1000), ip(MAX_SOURCES as u32 + 30)));
        assert!(l.sources() <= 2, "{} buckets", l.sources());
    }

    #[test]
    fn time_going_backwards_refills_nothing() {
        let mut l = HandshakeLimiter::new(HandshakeLimit { per_second: 1.0, burst: 1.0 });
        assert!(l.start(ms(5000), ATTACKER));
        assert!(!l.start(ms(0), ATTACKER));
        assert!(!l.start(ms(5500), ATTACKER));
        assert!(l.start(ms(6000), ATTACKER));
    }
}
