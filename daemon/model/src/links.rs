//! Which connection of each node is its current one. A node that reconnects has an old
//! connection whose last messages and close may still arrive after the new one is up; each
//! connection gets a link number from a counter (never reused, unlike an address or a pointer)
//! when it is attached, and whatever arrives carries the number of the connection it came on.

use std::collections::HashMap;

/// A connection's number: stamped once, from a counter, never reused in a process.
pub type Link = u64;

/// The current link of each node (see the module notes).
#[derive(Debug, Default)]
pub struct Links {
    last: Link,
    current: HashMap<String, Link>,
}

impl Links {
    /// A new connection of `node`: its number, now `node`'s current link.
    pub fn attach(&mut self, node: &str) -> Link {
        self.last += 1;
        self.current.insert(node.to_string(), self.last);
        self.last
    }

    /// Whether `link` is `node`'s current connection (what it carries is about the node now).
    pub fn is_current(&self, node: &str, link: Link) -> bool {
        self.current.get(node) == Some(&link)
    }

    /// `node` has no current connection any more (closed, or dropped).
    pub fn detach(&mut self, node: &str) {
        self.current.remove(node);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_old_connections_close_after_a_reconnect_is_not_about_the_new_one() {
        let mut links = Links::default();
        let old = links.attach("node1");
        let other = links.attach("node2");
        assert!(links.is_current("node1", old));
        // node1 drops and comes back: its old connection's close arrives after the new one is up.
        links.detach("node1");
        assert!(!links.is_current("node1", old), "a detached node has no current link");
        let new = links.attach("node1");
        assert_ne!(old, new);
        assert!(!links.is_current("node1", old), "the old connection's close would take the new one down");
        assert!(links.is_current("node1", new));
        // Numbers are never reused, however often nodes reconnect; nodes are kept apart.
        let mut seen = std::collections::HashSet::from([old, other, new]);
        for _ in 0..1000 {
            links.detach("node1");
            assert!(seen.insert(links.attach("node1")));
        }
        assert!(links.is_current("node2", other));
        assert!(!links.is_current("node2", new));
    }
}
