//! Which controller drives a node: one at a time.
//!
//! A node serves the first controller whose identity and Hello are checked, and refuses every
//! other one while that one's connection lives, with a reason the refused controller reads as the
//! QUIC close reason; the session of the first is never touched. A node is free again when its
//! controller's connection ends: it closed it (the controller stopped, or said Bye), or it was
//! silent for the QUIC idle timeout (its process died, or its host). So a controller restarted
//! after a crash waits at most that timeout for its old connection, and `isowall` keeps trying a
//! node it could not reach (once a second, within `--start-timeout`), so it takes over by itself.
//! The newest controller does not take over: two controllers would take a node from each other
//! every second forever.
//!
//! Sans-IO: the caller passes the time in and says when a connection ends.

use std::time::Duration;

/// The controller connection holding a node.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Holder {
    link: u64,
    since: Duration,
    from: String,
}

/// One node's seat (see the module docs).
#[derive(Debug, Clone)]
pub struct Seat {
    node: String,
    idle_timeout: Duration,
    holder: Option<Holder>,
    refused: u64,
}

impl Seat {
    /// The seat of node `node`, whose connections end after `idle_timeout` of silence.
    pub fn new(node: &str, idle_timeout: Duration) -> Seat {
        Seat { node: node.to_string(), idle_timeout, holder: None, refused: 0 }
    }

    /// Controller connection `link` (from address `from`) asks for the node at `now`: taken when
    /// the seat is free (or already its own), else `Err` with the reason to close it with.
    pub fn take(&mut self, now: Duration, link: u64, from: &str) -> Result<(), String> {
        match &self.holder {
            Some(h) if h.link != link => {
                self.refused += 1;
                Err(format!(
                    "{} is driven by another controller (from {}, for {:.1} s): stop it first; a \
                     controller that died frees it once its connection has been silent for {} s",
                    self.node,
                    h.from,
                    now.saturating_sub(h.since).as_secs_f64(),
                    self.idle_timeout.as_secs()
                ))
            }
            Some(_) => Ok(()),
            None => {
                self.holder = Some(Holder { link, since: now, from: from.to_string() });
                Ok(())
            }
        }
    }

    /// Connection `link` has ended; the seat is free if it held it.
    pub fn leave(&mut self, link: u64) {
        if self.holder.as_ref().is_some_and(|h| h.link == link) {
            self.holder = None;
        }
    }

    /// Whether a controller holds the node.
    pub fn is_taken(&self) -> bool {
        self.holder.is_some()
    }

    /// Controllers refused since the node started.
    pub fn refused(&self) -> u64 {
        self.refused
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(x: u64) -> Duration {
        Duration::from_secs(x)
    }

    #[test]
    fn a_second_controller_is_refused_with_why_until_the_first_leaves() {
        let mut seat = Seat::new("node0", s(5));
        seat.take(s(10), 1, "127.0.0.1:5000").unwrap();
        // Every second, forever: refused each time, the first keeps the node.
        for t in 11..20 {
            let why = seat.take(s(t), 2, "127.0.0.1:6000").unwrap_err();
            assert!(
                why.starts_with("node0 is driven by another controller (from 127.0.0.1:5000, for "),
                "{why}"
            );
            assert!(why.contains("stop it first") && why.contains("silent for 5 s"), "{why}");
        }
        assert!(why_for(&mut seat, 20).contains(&format!("for {:.1} s", 10.0)));
        assert_eq!(seat.refused(), 10);
        // A connection that is not the holder's ending changes nothing.
        seat.leave(2);
        assert!(seat.take(s(21), 3, "x").is_err());
        // The first closes (or its idle timeout ends it): the next one takes the node.
        seat.leave(1);
        assert!(!seat.is_taken());
        seat.take(s(22), 3, "127.0.0.1:7000").unwrap();
        assert!(seat.take(s(22), 3, "127.0.0.1:7000").is_ok(), "its own seat");
        assert!(seat.take(s(23), 1, "127.0.0.1:5000").is_err(), "the old one is refused now");
    }

    fn why_for(seat: &mut Seat, t: u64) -> String {
        seat.take(s(t), 9, "y").unwrap_err()
    }
}
