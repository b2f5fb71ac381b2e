//! A lossy UDP relay on loopback for the bad-network tests: datagrams between a client (the
//! controller, or a daemon talking to a peer) and a target (a daemon's QUIC port) pass through it,
//! and each one is dropped with probability `loss` or delivered after `delay` ± `jitter` (so late
//! datagrams overtake each other, as on a real network). The drop and delay of every datagram come
//! from a seeded generator, so a run's impairment pattern is reproducible.

use std::collections::{BinaryHeap, HashMap};
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// What the relay does to every datagram, both ways.
#[derive(Clone, Copy, Debug)]
pub struct Impairment {
    /// Probability in [0, 1] that a datagram is dropped.
    pub loss: f64,
    /// Mean one-way delay added.
    pub delay: Duration,
    /// Uniform spread around `delay` (each datagram gets `delay` + U(-jitter, +jitter), at least 0).
    pub jitter: Duration,
    /// Seed of the drop/delay pattern.
    pub seed: u64,
}

/// Datagram counts of a relay, both directions together.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RelayCounts {
    pub forwarded: u64,
    pub dropped: u64,
}

/// One datagram waiting for its delivery time.
struct Due {
    at: Instant,
    seq: u64,
    socket: Arc<UdpSocket>,
    to: SocketAddr,
    bytes: Vec<u8>,
}

impl PartialEq for Due {
    fn eq(&self, o: &Self) -> bool {
        (self.at, self.seq) == (o.at, o.seq)
    }
}
impl Eq for Due {}
impl PartialOrd for Due {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Due {
    /// Earliest first in a max-heap.
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        (o.at, o.seq).cmp(&(self.at, self.seq))
    }
}

/// State shared by the relay's threads.
struct Shared {
    impairment: Mutex<Impairment>,
    rng: Mutex<u64>,
    queue: Mutex<BinaryHeap<Due>>,
    wake: Condvar,
    stop: AtomicBool,
    seq: AtomicU64,
    forwarded: AtomicU64,
    dropped: AtomicU64,
}

impl Shared {
    /// SplitMix64 step: a uniform number in [0, 1) from the relay's seeded sequence.
    fn uniform(&self) -> f64 {
        let mut s = self.rng.lock().unwrap();
        *s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = *s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Drops the datagram or queues it for delivery from `socket` to `to`.
    fn pass(&self, socket: &Arc<UdpSocket>, to: SocketAddr, bytes: &[u8]) {
        let imp = *self.impairment.lock().unwrap();
        if self.uniform() < imp.loss {
            self.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let spread = (2.0 * self.uniform() - 1.0) * imp.jitter.as_secs_f64();
        let delay = Duration::from_secs_f64((imp.delay.as_secs_f64() + spread).max(0.0));
        let due = Due {
            at: Instant::now() + delay,
            seq: self.seq.fetch_add(1, Ordering::Relaxed),
            socket: socket.clone(),
            to,
            bytes: bytes.to_vec(),
        };
        self.queue.lock().unwrap().push(due);
        self.wake.notify_one();
    }
}

/// A running relay: clients send to [`Relay::addr`] as if it were the target. Stopped on drop.
pub struct Relay {
    pub addr: SocketAddr,
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
}

const POLL: Duration = Duration::from_millis(50);

impl Relay {
    /// Starts a relay on a free loopback port in front of `target`.
    pub fn start(target: SocketAddr, impairment: Impairment) -> std::io::Result<Relay> {
        let listen = Arc::new(UdpSocket::bind("127.0.0.1:0")?);
        listen.set_read_timeout(Some(POLL))?;
        let addr = listen.local_addr()?;
        let shared = Arc::new(Shared {
            impairment: Mutex::new(impairment),
            rng: Mutex::new(impairment.seed),
            queue: Mutex::new(BinaryHeap::new()),
            wake: Condvar::new(),
            stop: AtomicBool::new(false),
            seq: AtomicU64::new(0),
            forwarded: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
        });
        let mut threads = Vec::new();
        // The delivery thread: sends each queued datagram at its time.
        let s = shared.clone();
        threads.push(std::thread::spawn(move || deliver(&s)));
        // The client side: one upstream socket per client address, with a thread carrying the
        // target's answers back to that client.
        let s = shared.clone();
        threads.push(std::thread::spawn(move || {
            let mut upstream: HashMap<SocketAddr, Arc<UdpSocket>> = HashMap::new();
            let mut answers = Vec::new();
            let mut buf = vec![0u8; 65536];
            while !s.stop.load(Ordering::Relaxed) {
                let Ok((n, client)) = listen.recv_from(&mut buf) else { continue };
                let up = match upstream.get(&client) {
                    Some(u) => u.clone(),
                    None => {
                        let Ok(u) = UdpSocket::bind("127.0.0.1:0") else { continue };
                        let _ = u.set_read_timeout(Some(POLL));
                        let u = Arc::new(u);
                        upstream.insert(client, u.clone());
                        let (s2, u2, back) = (s.clone(), u.clone(), listen.clone());
                        answers.push(std::thread::spawn(move || {
                            let mut buf = vec![0u8; 65536];
                            while !s2.stop.load(Ordering::Relaxed) {
                                if let Ok((n, _)) = u2.recv_from(&mut buf) {
                                    s2.pass(&back, client, &buf[..n]);
                                }
                            }
                        }));
                        u
                    }
                };
                s.pass(&up, target, &buf[..n]);
            }
            for a in answers {
                let _ = a.join();
            }
        }));
        Ok(Relay { addr, shared, threads })
    }

    /// Changes what the relay does from now on (datagrams already queued keep their delivery
    /// time), restarting its drop/delay sequence from the new seed; the counts start again at 0.
    /// Connections through the relay stay up, so one set of daemons can be tried at several
    /// loss rates.
    pub fn set_impairment(&self, impairment: Impairment) {
        *self.shared.impairment.lock().unwrap() = impairment;
        *self.shared.rng.lock().unwrap() = impairment.seed;
        self.shared.forwarded.store(0, Ordering::Relaxed);
        self.shared.dropped.store(0, Ordering::Relaxed);
    }

    pub fn counts(&self) -> RelayCounts {
        RelayCounts {
            forwarded: self.shared.forwarded.load(Ordering::Relaxed),
            dropped: self.shared.dropped.load(Ordering::Relaxed),
        }
    }
}

fn deliver(s: &Shared) {
    let mut queue = s.queue.lock().unwrap();
    while !s.stop.load(Ordering::Relaxed) {
        let now = Instant::now();
        match queue.peek().map(|d| d.at) {
            Some(at) if at <= now => {
                let d = queue.pop().expect("peeked");
                drop(queue);
                // Counted before it is sent, so that whoever receives it sees it counted.
                s.forwarded.fetch_add(1, Ordering::Relaxed);
                if d.socket.send_to(&d.bytes, d.to).is_err() {
                    s.forwarded.fetch_sub(1, Ordering::Relaxed);
                }
                queue = s.queue.lock().unwrap();
            }
            Some(at) => queue = s.wake.wait_timeout(queue, (at - now).min(POLL)).unwrap().0,
            None => queue = s.wake.wait_timeout(queue, POLL).unwrap().0,
        }
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        self.shared.wake.notify_all();
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn echo() -> (SocketAddr, Arc<AtomicBool>, JoinHandle<()>) {
        let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
        sock.set_read_timeout(Some(POLL)).unwrap();
        let addr = sock.local_addr().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let s = stop.clone();
        let t = std::thread::spawn(move || {
            let mut buf = [0u8; 2048];
            while !s.load(Ordering::Relaxed) {
                if let Ok((n, from)) = sock.recv_from(&mut buf) {
                    let _ = sock.send_to(&buf[..n], from);
                }
            }
        });
        (addr, stop, t)
    }

    /// Sends `n` numbered datagrams through the relay to an echo server; returns those that came
    /// back, in arrival order, and how long the first one took to come back.
    fn round_trip(imp: Impairment, n: u32) -> (Vec<u32>, RelayCounts, Duration) {
        let (target, stop, t) = echo();
        let relay = Relay::start(target, imp).unwrap();
        let client = UdpSocket::bind("127.0.0.1:0").unwrap();
        client.set_read_timeout(Some(Duration::from_millis(300))).unwrap();
        let reader = client.try_clone().unwrap();
        let relay_addr = relay.addr;
        // Read while sending: a burst larger than the socket buffers would be lost in the kernel.
        let start = Instant::now();
        let got = std::thread::spawn(move || {
            let mut got = Vec::new();
            let mut first = None;
            let mut buf = [0u8; 16];
            while let Ok((len, from)) = reader.recv_from(&mut buf) {
                first.get_or_insert_with(|| start.elapsed());
                assert_eq!(from, relay_addr, "answers come from the relay's address");
                assert_eq!(len, 4);
                got.push(u32::from_le_bytes(buf[..4].try_into().unwrap()));
            }
            (got, first.unwrap_or_default())
        });
        for i in 0..n {
            client.send_to(&i.to_le_bytes(), relay.addr).unwrap();
            // A breath every 64 datagrams (the sender's pace): no socket buffer on the way overflows.
            if i % 64 == 63 {
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        let (got, took) = got.join().unwrap();
        let counts = relay.counts();
        drop(relay);
        stop.store(true, Ordering::Relaxed);
        t.join().unwrap();
        (got, counts, took)
    }

    #[test]
    fn a_clean_relay_delivers_everything_in_order() {
        let imp = Impairment { loss: 0.0, delay: Duration::ZERO, jitter: Duration::ZERO, seed: 1 };
        let (got, counts, _) = round_trip(imp, 200);
        assert_eq!(got, (0..200).collect::<Vec<_>>());
        assert_eq!(counts, RelayCounts { forwarded: 400, dropped: 0 });
    }

    #[test]
    fn loss_drops_about_the_asked_fraction_both_ways() {
        let imp = Impairment { loss: 0.05, delay: Duration::ZERO, jitter: Duration::ZERO, seed: 7 };
        let (got, counts, _) = round_trip(imp, 2000);
        // 2000 out, ~1900 back: each datagram passes twice, so ~9.75% are lost on the round trip.
        let lost = 2000 - got.len();
        assert!((120..280).contains(&lost), "lost {lost} of 2000 round trips at 5% each way");
        // A round trip is lost by exactly one drop (a datagram dropped on the way out never returns).
        assert_eq!(counts.dropped, lost as u64);
        // Forwarded: every returned datagram twice, plus those dropped on the way back once.
        let returned = 2 * got.len() as u64;
        assert!((returned..=returned + counts.dropped).contains(&counts.forwarded), "{counts:?}");
    }

    #[test]
    fn a_new_impairment_applies_to_the_next_datagrams_and_restarts_the_counts() {
        let (target, stop, t) = echo();
        let clean = Impairment { loss: 0.0, delay: Duration::ZERO, jitter: Duration::ZERO, seed: 5 };
        let relay = Relay::start(target, clean).unwrap();
        let client = UdpSocket::bind("127.0.0.1:0").unwrap();
        client.set_read_timeout(Some(Duration::from_millis(300))).unwrap();
        let mut buf = [0u8; 16];
        client.send_to(b"ping", relay.addr).unwrap();
        assert!(client.recv_from(&mut buf).is_ok(), "a clean relay answers");
        assert_eq!(relay.counts(), RelayCounts { forwarded: 2, dropped: 0 });
        relay.set_impairment(Impairment { loss: 1.0, ..clean });
        assert_eq!(relay.counts(), RelayCounts::default());
        client.send_to(b"ping", relay.addr).unwrap();
        assert!(client.recv_from(&mut buf).is_err(), "a relay that drops everything answers nothing");
        assert_eq!(relay.counts(), RelayCounts { forwarded: 0, dropped: 1 });
        drop(relay);
        stop.store(true, Ordering::Relaxed);
        t.join().unwrap();
    }

    #[test]
    fn delay_and_jitter_delay_and_reorder() {
        let imp = Impairment {
            loss: 0.0,
            delay: Duration::from_millis(20),
            jitter: Duration::from_millis(10),
            seed: 3,
        };
        let (got, counts, took) = round_trip(imp, 300);
        assert_eq!(counts.dropped, 0);
        let mut sorted = got.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..300).collect::<Vec<_>>(), "nothing lost");
        assert_ne!(got, sorted, "jitter of 10 ms reorders datagrams sent back to back");
        // Two passes of >= 10 ms each (20 ms ± 10 ms).
        assert!(took >= Duration::from_millis(20), "the first round trip took {took:?}");
    }
}
