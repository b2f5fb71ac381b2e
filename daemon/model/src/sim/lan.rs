//! The LAN model every simulated wall runs on: a seeded PRNG, the virtual clock's event queue,
//! and [`Lan`], a switched network of per-node links (latency, jitter, per-packet loss with
//! QUIC-like retransmission, per-link bandwidth and a per-message NIC cost).
//!
//! A message of `b` bytes travels as `ceil(b / packet_payload)` packets (at least one), each
//! `packet_overhead` bytes longer on the wire (Ethernet, IP, UDP and QUIC headers). Its sender's
//! NIC is busy `per_message + wire bytes / bandwidth`, one message after the other (FIFO); the
//! switch forwards it onto the receiver's link, which is busy as long again (so many senders to
//! one receiver queue there: incast); it arrives `latency + jitter` after it left the sender, or
//! when the receiver's link has carried it, whichever is later. Messages between two endpoints
//! arrive in the order they were sent (a QUIC stream, a connection's messages). A lost packet is
//! sent again: a lost last packet costs `tail_loss_delay` (QUIC's probe timeout: nothing after it
//! reveals the loss), an earlier one `9/8` of the round trip (QUIC's packet-threshold detection).
//! Nothing else is modelled: no congestion control, no switch buffer limit, no CPU contention
//! between the NIC and the rest of the node.

use std::cmp::Ordering;
use std::collections::{BTreeMap, BinaryHeap};
use std::time::Duration;

/// xorshift64*: tiny, seeded, good enough for jitter and loss.
#[derive(Debug, Clone)]
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [0, d).
    pub fn below(&mut self, d: Duration) -> Duration {
        d.mul_f64(self.unit())
    }
}

/// An event at a virtual time; `seq` orders events at the same time as they were scheduled.
#[derive(Debug)]
pub struct Scheduled<E> {
    pub at: Duration,
    pub seq: u64,
    pub ev: E,
}

impl<E> PartialEq for Scheduled<E> {
    fn eq(&self, o: &Self) -> bool {
        (self.at, self.seq) == (o.at, o.seq)
    }
}
impl<E> Eq for Scheduled<E> {}
impl<E> PartialOrd for Scheduled<E> {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}
impl<E> Ord for Scheduled<E> {
    // Reversed: BinaryHeap pops the earliest.
    fn cmp(&self, o: &Self) -> Ordering {
        (o.at, o.seq).cmp(&(self.at, self.seq))
    }
}

/// The virtual clock's events, earliest first, ties in the order they were scheduled.
#[derive(Debug)]
pub struct Events<E> {
    heap: BinaryHeap<Scheduled<E>>,
    seq: u64,
}

impl<E> Default for Events<E> {
    fn default() -> Self {
        Events { heap: BinaryHeap::new(), seq: 0 }
    }
}

impl<E> Events<E> {
    pub fn push(&mut self, at: Duration, ev: E) {
        self.seq += 1;
        self.heap.push(Scheduled { at, seq: self.seq, ev });
    }

    pub fn next_at(&self) -> Option<Duration> {
        self.heap.peek().map(|s| s.at)
    }

    pub fn pop(&mut self) -> Option<(Duration, E)> {
        self.heap.pop().map(|s| (s.at, s.ev))
    }

    pub fn len(&self) -> usize {
        self.heap.len()
    }

    pub fn is_empty(&self) -> bool {
        self.heap.is_empty()
    }
}

/// The network's parameters (module notes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LanModel {
    /// One way, sender's NIC to receiver's NIC (switch and stacks included).
    pub latency: Duration,
    /// Extra delay per message, uniform in [0, jitter).
    pub jitter: Duration,
    /// Each node's link, each direction, bits per second.
    pub bandwidth_bps: f64,
    /// The NIC and stack's cost per message, on the sender's link and again on the receiver's.
    pub per_message: Duration,
    /// Message bytes per packet.
    pub packet_payload: usize,
    /// Header bytes per packet on the wire.
    pub packet_overhead: usize,
    /// Probability that a packet is lost (and sent again).
    pub loss: f64,
    /// What a lost last packet of a message costs (QUIC's probe timeout).
    pub tail_loss_delay: Duration,
}

impl LanModel {
    /// A 10 Gbit/s Ethernet LAN behind one switch, QUIC with 1400-byte packets: 50 us one way,
    /// up to 20 us of jitter, 5 us per message at each end, 100 header bytes per packet (Ethernet
    /// with preamble and gap 38, IPv4 20, UDP 8, QUIC short header, stream frame and AEAD tag 34),
    /// one packet in 10^5 lost, 26 ms for a lost last packet (quinn's probe timeout: the round
    /// trip, 4 x its variance, the 25 ms maximum ACK delay).
    pub fn ten_gbe() -> LanModel {
        LanModel {
            latency: Duration::from_micros(50),
            jitter: Duration::from_micros(20),
            bandwidth_bps: 10e9,
            per_message: Duration::from_micros(5),
            packet_payload: 1400,
            packet_overhead: 100,
            loss: 1e-5,
            tail_loss_delay: Duration::from_millis(26),
        }
    }

    /// [`LanModel::ten_gbe`] at 1 Gbit/s.
    pub fn one_gbe() -> LanModel {
        LanModel { bandwidth_bps: 1e9, ..LanModel::ten_gbe() }
    }

    /// Packets a message of `bytes` takes (at least one).
    pub fn packets(&self, bytes: usize) -> usize {
        bytes.div_ceil(self.packet_payload.max(1)).max(1)
    }

    /// Bytes on the wire for a message of `bytes`.
    pub fn wire_bytes(&self, bytes: usize) -> usize {
        bytes + self.packets(bytes) * self.packet_overhead
    }

    /// How long one link is busy with a message of `bytes`: the per-message cost and its wire
    /// bytes at the link's bandwidth.
    pub fn link_time(&self, bytes: usize) -> Duration {
        self.per_message + Duration::from_secs_f64(self.wire_bytes(bytes) as f64 * 8.0 / self.bandwidth_bps)
    }

    /// The round trip without load or jitter.
    pub fn rtt(&self) -> Duration {
        2 * self.latency
    }
}

/// What a [`Lan`] carried.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LanCounts {
    pub messages: u64,
    pub packets: u64,
    /// Message bytes (not the wire's headers).
    pub bytes: u64,
    /// Messages that lost a packet and waited for its retransmission.
    pub retransmitted: u64,
    /// Of those, the ones whose last packet was lost (they waited a probe timeout).
    pub tail_losses: u64,
}

/// A switched LAN of `endpoints` links (module notes). Endpoints are numbered by the caller.
#[derive(Debug, Clone)]
pub struct Lan {
    model: LanModel,
    egress_free: Vec<Duration>,
    ingress_free: Vec<Duration>,
    /// The last arrival per (from, to): messages between two endpoints stay in order.
    last: BTreeMap<(usize, usize), Duration>,
    rng: Rng,
    counts: LanCounts,
}

impl Lan {
    pub fn new(model: LanModel, endpoints: usize, seed: u64) -> Lan {
        Lan {
            model,
            egress_free: vec![Duration::ZERO; endpoints],
            ingress_free: vec![Duration::ZERO; endpoints],
            last: BTreeMap::new(),
            rng: Rng(seed | 1),
            counts: LanCounts::default(),
        }
    }

    pub fn model(&self) -> &LanModel {
        &self.model
    }

    pub fn counts(&self) -> LanCounts {
        self.counts
    }

    /// The PRNG the network draws from (a simulation may draw its other chances from it too).
    pub fn rng(&mut self) -> &mut Rng {
        &mut self.rng
    }

    /// A message of `bytes` handed to `from`'s NIC at `now` for `to`: when it has arrived whole.
    pub fn send(&mut self, now: Duration, from: usize, to: usize, bytes: usize) -> Duration {
        let m = self.model;
        let busy = m.link_time(bytes);
        let tx_start = now.max(self.egress_free[from]);
        let tx_end = tx_start + busy;
        self.egress_free[from] = tx_end;
        let flight = m.latency + self.rng.below(m.jitter);
        let rx_end = (tx_end + flight).max(self.ingress_free[to] + busy);
        self.ingress_free[to] = rx_end;
        let packets = m.packets(bytes);
        let mut at = rx_end;
        if m.loss > 0.0 {
            let tail = self.rng.unit() < m.loss;
            let earlier = packets > 1 && self.rng.unit() < 1.0 - (1.0 - m.loss).powi(packets as i32 - 1);
            if tail {
                at += m.tail_loss_delay;
                self.counts.tail_losses += 1;
            } else if earlier {
                at += m.rtt().mul_f64(9.0 / 8.0);
            }
            if tail || earlier {
                self.counts.retransmitted += 1;
            }
        }
        let last = self.last.entry((from, to)).or_default();
        at = at.max(*last);
        *last = at;
        self.counts.messages += 1;
        self.counts.packets += packets as u64;
        self.counts.bytes += bytes as u64;
        at
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn us(x: u64) -> Duration {
        Duration::from_micros(x)
    }

    fn quiet() -> LanModel {
        LanModel { jitter: Duration::ZERO, loss: 0.0, ..LanModel::ten_gbe() }
    }

    #[test]
    fn one_message_takes_its_link_time_and_the_latency() {
        let m = quiet();
        // 14 000 bytes: 10 packets, 15 000 bytes on the wire: 12 us at 10 Gbit/s, and 5 us.
        assert_eq!(m.packets(14_000), 10);
        assert_eq!(m.wire_bytes(14_000), 15_000);
        assert_eq!(m.link_time(14_000), us(17));
        let mut lan = Lan::new(m, 3, 1);
        assert_eq!(lan.send(us(100), 0, 1, 14_000), us(100 + 17 + 50));
        // A second message from the same sender waits for the first to leave.
        assert_eq!(lan.send(us(100), 0, 2, 14_000), us(100 + 34 + 50));
    }

    #[test]
    fn senders_to_one_receiver_queue_on_its_link() {
        let m = quiet();
        let mut lan = Lan::new(m, 5, 1);
        let busy = m.link_time(1_400_000); // 1000 packets: 1.2 ms
        let arrivals: Vec<Duration> = (1..5).map(|s| lan.send(Duration::ZERO, s, 0, 1_400_000)).collect();
        for (i, at) in arrivals.iter().enumerate() {
            // The first arrives after its own transmission and the latency; each next one a
            // link time later (the receiver's link carries one at a time).
            assert_eq!(*at, busy + m.latency + busy * i as u32, "sender {}", i + 1);
        }
    }

    #[test]
    fn a_lost_packet_delays_its_message_by_the_retransmission() {
        let lossy = LanModel { loss: 1.0, ..quiet() };
        let mut lan = Lan::new(lossy, 2, 1);
        let at = lan.send(Duration::ZERO, 0, 1, 100);
        assert_eq!(at, lossy.link_time(100) + lossy.latency + lossy.tail_loss_delay);
        assert_eq!(lan.counts().tail_losses, 1);
        let mut lan = Lan::new(LanModel { loss: 1e-3, ..quiet() }, 2, 7);
        let mut late = 0;
        for i in 0..2000u64 {
            let now = us(i * 100_000); // past any retransmission of the one before
            if lan.send(now, 0, 1, 140_000) > now + quiet().link_time(140_000) + quiet().latency {
                late += 1;
            }
        }
        // 100 packets each at 1e-3: about one message in ten loses one.
        let c = lan.counts();
        assert_eq!(late, c.retransmitted);
        assert!((100..=320).contains(&late), "{c:?}");
    }
}
