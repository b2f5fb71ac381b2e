//! Object space when a node dies (DESIGN.md "Faults": "in object space its bricks go to the
//! others"), sans-IO: which node renders each brick, from which frame on.
//!
//! Brick i is the *home* brick of the wall's i-th node (`bricks::split` numbers them in the order
//! of `[[nodes]]`); every node loads its home brick at start-up and keeps it. The controller's
//! [`BrickAssigner`] holds the current [`BrickMap`] (brick -> the node that renders it):
//!
//! 1. A node goes down: its bricks have no holder from the next frame on (the map goes out at once,
//!    so the frames in flight stop waiting for its pixels: the wall does not straggle while the
//!    brick loads, it shows the image without that brick). Each such brick is offered to one
//!    survivor ([`AdoptionOutput::Load`]): the one with the fewest bricks held or loading, then the
//!    least resident volume bytes (as the nodes report them), then the first in `[[nodes]]`.
//! 2. The survivor reads the brick and its halo (the same partial read as at start-up), uploads it
//!    as a second volume and reports it loaded: the brick is its own from the next frame that
//!    begins ([`AdoptionOutput::Adopted`]); it renders both bricks each frame and sends their
//!    pixels together. A survivor that cannot load it says why, and the next survivor is asked.
//! 3. The node comes back (restarted, it has its home brick loaded again): the brick is its own
//!    again from the next frame ([`AdoptionOutput::Returned`]); the survivor drops its copy when it
//!    renders a frame whose map no longer gives it the brick. An adoption still loading is dropped.
//!
//! The map travels as `Message::Bricks { from_frame, holders }` to every node before the frame it
//! starts at (and to a node that comes up); a daemon keeps the last few maps ([`MapHistory`]) and
//! renders, sends and composites frame f by the map for f, so all nodes agree on every frame. A
//! tile owner waits, for frame f, for the pixels of every other node that holds a brick in the map
//! for f; a new map that leaves a node without bricks ends the wait for it in frames still pending.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Duration;

/// Maps a daemon keeps (frames in flight are few).
pub const MAPS_KEPT: usize = 16;

/// Who renders each brick from frame `from_frame` on: `holders[i]` is brick i's node, `None`
/// while nobody does (its home is down and no survivor has loaded it yet).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BrickMap {
    pub from_frame: u64,
    pub holders: Vec<Option<String>>,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AdoptionError {
    #[error("a brick map of {got} bricks for a wall of {want} nodes (one brick each)")]
    WrongLength { got: usize, want: usize },
    #[error("the brick map gives brick {brick} to `{node}`, which is not a node of this wall")]
    UnknownNode { brick: usize, node: String },
    #[error("brick {brick} does not exist: the wall has {bricks} bricks")]
    NoSuchBrick { brick: u64, bricks: usize },
}

impl BrickMap {
    /// Every brick at its home (`nodes` in the order of `[[nodes]]`), from frame 0.
    pub fn home(nodes: &[String]) -> BrickMap {
        BrickMap { from_frame: 0, holders: nodes.iter().cloned().map(Some).collect() }
    }

    /// Validates a map as it arrives (the wire's `Message::Bricks`).
    pub fn from_wire(
        from_frame: u64,
        holders: Vec<Option<String>>,
        nodes: &[String],
    ) -> Result<BrickMap, AdoptionError> {
        if holders.len() != nodes.len() {
            return Err(AdoptionError::WrongLength { got: holders.len(), want: nodes.len() });
        }
        for (brick, h) in holders.iter().enumerate() {
            if let Some(n) = h.as_ref().filter(|n| !nodes.contains(n)) {
                return Err(AdoptionError::UnknownNode { brick, node: n.clone() });
            }
        }
        Ok(BrickMap { from_frame, holders })
    }

    /// The bricks `node` renders.
    pub fn bricks_of(&self, node: &str) -> Vec<usize> {
        (0..self.holders.len()).filter(|&b| self.holders[b].as_deref() == Some(node)).collect()
    }

    /// The nodes that render at least one brick.
    pub fn participants(&self) -> BTreeSet<String> {
        self.holders.iter().flatten().cloned().collect()
    }
}

/// Checks a brick index from the wire against a wall of `bricks` bricks.
pub fn brick_index(brick: u64, bricks: usize) -> Result<usize, AdoptionError> {
    usize::try_from(brick).ok().filter(|&b| b < bricks).ok_or(AdoptionError::NoSuchBrick { brick, bricks })
}

/// A daemon's maps, by the frame each starts at (module notes).
#[derive(Debug, Clone)]
pub struct MapHistory {
    nodes: Vec<String>,
    maps: VecDeque<BrickMap>,
}

impl MapHistory {
    /// Every brick at home until a map says otherwise.
    pub fn new(nodes: Vec<String>) -> MapHistory {
        let home = BrickMap::home(&nodes);
        MapHistory { nodes, maps: VecDeque::from([home]) }
    }

    pub fn nodes(&self) -> &[String] {
        &self.nodes
    }

    /// The map frame `frame_id` is rendered and composited by.
    pub fn map_for(&self, frame_id: u64) -> &BrickMap {
        self.maps.iter().rev().find(|m| m.from_frame <= frame_id).unwrap_or(&self.maps[0])
    }

    /// The newest map.
    pub fn latest(&self) -> &BrickMap {
        self.maps.back().expect("never empty")
    }

    /// A new map (it replaces maps starting at the same frame or later). Returns the nodes that
    /// render nothing in it: frames still waiting for their pixels stop waiting.
    pub fn set(&mut self, map: BrickMap) -> Vec<String> {
        while self.maps.back().is_some_and(|m| m.from_frame >= map.from_frame) && self.maps.len() > 1 {
            self.maps.pop_back();
        }
        if self.maps.back().is_some_and(|m| m.from_frame >= map.from_frame) {
            self.maps.clear();
        }
        let holding = map.participants();
        self.maps.push_back(map);
        while self.maps.len() > MAPS_KEPT {
            self.maps.pop_front();
        }
        self.nodes.iter().filter(|n| !holding.contains(*n)).cloned().collect()
    }

    /// A new controller session: every brick at home again (the controller sends its map).
    pub fn reset(&mut self) {
        *self = MapHistory::new(std::mem::take(&mut self.nodes));
    }
}

/// What the controller must do for the assigner, in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AdoptionOutput {
    /// Send `LoadBrick { brick }` to `node`.
    Load { node: String, brick: usize },
    /// `node` loaded `brick` in `load` (as it reported) and renders it from the next frame;
    /// `since_down`: from its home going down to now.
    Adopted { node: String, brick: usize, load: Duration, since_down: Duration },
    /// `brick` is back with its home `node` from the next frame.
    Returned { node: String, brick: usize },
    /// No node is up to take `brick`: it stays unrendered until one is.
    Unheld { brick: usize },
}

/// The controller's brick assignment (module notes). Nodes by index in `[[nodes]]`; brick i's
/// home is node i.
#[derive(Debug, Clone)]
pub struct BrickAssigner {
    nodes: Vec<String>,
    up: Vec<bool>,
    holders: Vec<Option<usize>>,
    /// Adoptions under way: brick -> (the node loading it, when its home went down).
    loading: BTreeMap<usize, (usize, Duration)>,
    /// Adopters that could not load a brick: (brick, node), not asked again for it.
    refused: BTreeSet<(usize, usize)>,
    /// When each brick lost its holder.
    unheld_since: Vec<Option<Duration>>,
    /// Resident volume bytes per node, as reported (tie-break).
    resident: Vec<u64>,
    changed: bool,
}

impl BrickAssigner {
    /// Every brick at its home, every node up (the controller connects to all before the first
    /// frame; [`BrickAssigner::node_down`] for any that is not).
    pub fn new(nodes: Vec<String>) -> BrickAssigner {
        let n = nodes.len();
        BrickAssigner {
            nodes,
            up: vec![true; n],
            holders: (0..n).map(Some).collect(),
            loading: BTreeMap::new(),
            refused: BTreeSet::new(),
            unheld_since: vec![None; n],
            resident: vec![0; n],
            changed: false,
        }
    }

    fn index(&self, node: &str) -> Option<usize> {
        self.nodes.iter().position(|n| n == node)
    }

    /// The map as it stands, starting at `from_frame`.
    pub fn map(&self, from_frame: u64) -> BrickMap {
        BrickMap {
            from_frame,
            holders: self.holders.iter().map(|h| h.map(|i| self.nodes[i].clone())).collect(),
        }
    }

    /// Whether the map changed since the last call (then send it to every up node).
    pub fn take_changed(&mut self) -> bool {
        std::mem::take(&mut self.changed)
    }

    /// The adoptions under way: (brick, node loading it).
    pub fn loading(&self) -> Vec<(usize, String)> {
        self.loading.iter().map(|(&b, &(n, _))| (b, self.nodes[n].clone())).collect()
    }

    /// A node's resident volume bytes (its Composited reports), for choosing adopters.
    pub fn set_resident(&mut self, node: &str, bytes: u64) {
        if let Some(i) = self.index(node) {
            self.resident[i] = bytes;
        }
    }

    /// The survivor to load `brick`: fewest bricks held or loading, then least resident bytes,
    /// then the first in the config; never the brick's home, nor one that refused it.
    fn adopter(&self, brick: usize) -> Option<usize> {
        let load = |n: usize| {
            self.holders.iter().filter(|h| **h == Some(n)).count()
                + self.loading.values().filter(|l| l.0 == n).count()
        };
        (0..self.nodes.len())
            .filter(|&n| self.up[n] && n != brick && !self.refused.contains(&(brick, n)))
            .min_by_key(|&n| (load(n), self.resident[n], n))
    }

    fn offer(&mut self, brick: usize, down_at: Duration, out: &mut Vec<AdoptionOutput>) {
        match self.adopter(brick) {
            Some(n) => {
                self.loading.insert(brick, (n, down_at));
                out.push(AdoptionOutput::Load { node: self.nodes[n].clone(), brick });
            }
            None => out.push(AdoptionOutput::Unheld { brick }),
        }
    }

    /// `node` is down: its bricks lose their holder now and go to survivors; adoptions it was
    /// loading go to others.
    pub fn node_down(&mut self, now: Duration, node: &str) -> Vec<AdoptionOutput> {
        let mut out = Vec::new();
        let Some(i) = self.index(node) else { return out };
        if !self.up[i] {
            return out;
        }
        self.up[i] = false;
        let mut orphans = Vec::new();
        for b in 0..self.holders.len() {
            if self.holders[b] == Some(i) {
                self.holders[b] = None;
                self.unheld_since[b] = Some(now);
                self.changed = true;
                orphans.push((b, now));
            }
        }
        let moved: Vec<(usize, Duration)> =
            self.loading.iter().filter(|(_, l)| l.0 == i).map(|(&b, l)| (b, l.1)).collect();
        for (b, at) in moved {
            self.loading.remove(&b);
            orphans.push((b, at));
        }
        orphans.sort_unstable();
        for (b, at) in orphans {
            self.offer(b, at, &mut out);
        }
        out
    }

    /// `node` is up again (restarted: its home brick is loaded): the brick returns to it, an
    /// adoption of it still loading is dropped, and bricks nobody holds are offered again.
    pub fn node_up(&mut self, now: Duration, node: &str) -> Vec<AdoptionOutput> {
        let mut out = Vec::new();
        let Some(i) = self.index(node) else { return out };
        let was_up = std::mem::replace(&mut self.up[i], true);
        self.refused.retain(|&(_, n)| n != i);
        if self.holders[i] != Some(i) {
            self.holders[i] = Some(i);
            self.unheld_since[i] = None;
            self.loading.remove(&i);
            self.changed = true;
            out.push(AdoptionOutput::Returned { node: node.to_string(), brick: i });
        }
        if !was_up {
            for b in 0..self.holders.len() {
                if self.holders[b].is_none() && !self.loading.contains_key(&b) {
                    self.offer(b, self.unheld_since[b].unwrap_or(now), &mut out);
                }
            }
        }
        out
    }

    /// `node` reports `brick` loaded (in `load`): it holds it from the next frame, if the brick
    /// is still its to adopt (a report for an adoption since dropped changes nothing).
    pub fn loaded(&mut self, now: Duration, node: &str, brick: usize, load: Duration) -> Vec<AdoptionOutput> {
        let Some(i) = self.index(node) else { return Vec::new() };
        match self.loading.get(&brick) {
            Some(&(n, down_at)) if n == i && self.up[i] => {
                self.loading.remove(&brick);
                self.holders[brick] = Some(i);
                self.unheld_since[brick] = None;
                self.changed = true;
                vec![AdoptionOutput::Adopted {
                    node: node.to_string(),
                    brick,
                    load,
                    since_down: now.saturating_sub(down_at),
                }]
            }
            _ => Vec::new(),
        }
    }

    /// `node` could not load `brick`: the next survivor is asked.
    pub fn load_failed(&mut self, node: &str, brick: usize) -> Vec<AdoptionOutput> {
        let mut out = Vec::new();
        let Some(i) = self.index(node) else { return out };
        if let Some(&(n, down_at)) = self.loading.get(&brick).filter(|l| l.0 == i) {
            let _ = n;
            self.loading.remove(&brick);
            self.refused.insert((brick, i));
            self.offer(brick, down_at, &mut out);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("node{i}")).collect()
    }

    fn ms(v: u64) -> Duration {
        Duration::from_millis(v)
    }

    #[test]
    fn a_dead_nodes_brick_goes_unheld_then_to_the_least_loaded_survivor_once_loaded() {
        let mut a = BrickAssigner::new(names(4));
        assert!(!a.take_changed());
        // Resident bytes decide between survivors holding one brick each: node2 holds the least.
        for (n, b) in [("node0", 900), ("node1", 800), ("node2", 700), ("node3", 750)] {
            a.set_resident(n, b);
        }
        let out = a.node_down(ms(1000), "node1");
        assert_eq!(out, vec![AdoptionOutput::Load { node: "node2".into(), brick: 1 }]);
        // From the next frame nobody renders brick 1 (the wall does not wait for it).
        assert!(a.take_changed());
        let m = a.map(7);
        assert_eq!(m.from_frame, 7);
        assert_eq!(m.holders, vec![Some("node0".into()), None, Some("node2".into()), Some("node3".into())]);
        assert!(!m.participants().contains("node1"));
        assert_eq!(a.loading(), vec![(1, "node2".to_string())]);
        // Someone else's report changes nothing; node2's makes it the holder.
        assert!(a.loaded(ms(1100), "node0", 1, ms(50)).is_empty());
        assert!(!a.take_changed());
        let out = a.loaded(ms(1250), "node2", 1, ms(200));
        assert_eq!(
            out,
            vec![AdoptionOutput::Adopted {
                node: "node2".into(),
                brick: 1,
                load: ms(200),
                since_down: ms(250)
            }]
        );
        assert!(a.take_changed());
        assert_eq!(a.map(9).bricks_of("node2"), vec![1, 2]);
        // A second death: node2 holds two bricks now, so node3 (fewest, then least bytes) takes node0's.
        let out = a.node_down(ms(2000), "node0");
        assert_eq!(out, vec![AdoptionOutput::Load { node: "node3".into(), brick: 0 }]);
    }

    #[test]
    fn the_restarted_node_gets_its_brick_back_and_a_pending_adoption_is_dropped() {
        let mut a = BrickAssigner::new(names(3));
        a.node_down(ms(0), "node0");
        assert_eq!(a.loading(), vec![(0, "node1".to_string())]);
        // node0 comes back before node1 finished loading: brick 0 is home again, the load is moot.
        a.take_changed();
        let out = a.node_up(ms(300), "node0");
        assert_eq!(out, vec![AdoptionOutput::Returned { node: "node0".into(), brick: 0 }]);
        assert!(a.take_changed());
        assert!(a.loading().is_empty());
        assert!(a.loaded(ms(400), "node1", 0, ms(100)).is_empty());
        assert_eq!(a.map(3).holders, vec![Some("node0".into()), Some("node1".into()), Some("node2".into())]);
        // Adopted, then the home returns: the holder becomes the home again.
        a.node_down(ms(1000), "node2");
        let adopter = a.loading()[0].1.clone();
        assert_eq!(adopter, "node0");
        a.loaded(ms(1100), &adopter, 2, ms(90));
        assert_eq!(a.map(5).holders[2].as_deref(), Some("node0"));
        a.take_changed();
        let out = a.node_up(ms(5000), "node2");
        assert_eq!(out, vec![AdoptionOutput::Returned { node: "node2".into(), brick: 2 }]);
        assert!(a.take_changed());
        assert_eq!(a.map(6), BrickMap { from_frame: 6, holders: BrickMap::home(&names(3)).holders });
        // A node coming up that was never down (a replaced connection) changes nothing.
        assert!(a.node_up(ms(6000), "node1").is_empty());
        assert!(!a.take_changed());
    }

    #[test]
    fn a_failed_load_asks_the_next_survivor_and_a_dead_adopter_passes_it_on() {
        let mut a = BrickAssigner::new(names(3));
        assert_eq!(
            a.node_down(ms(0), "node2"),
            vec![AdoptionOutput::Load { node: "node0".into(), brick: 2 }]
        );
        assert_eq!(a.load_failed("node0", 2), vec![AdoptionOutput::Load { node: "node1".into(), brick: 2 }]);
        // node1 dies while loading brick 2: its own brick and brick 2 need a holder; only node0 is
        // up, and it refused brick 2.
        let out = a.node_down(ms(100), "node1");
        assert_eq!(
            out,
            vec![
                AdoptionOutput::Load { node: "node0".into(), brick: 1 },
                AdoptionOutput::Unheld { brick: 2 }
            ]
        );
        // node1 returns: brick 1 is home, brick 2 is offered again, to node1.
        let out = a.node_up(ms(900), "node1");
        assert_eq!(
            out,
            vec![
                AdoptionOutput::Returned { node: "node1".into(), brick: 1 },
                AdoptionOutput::Load { node: "node1".into(), brick: 2 }
            ]
        );
        // The time since down counts from the first death of brick 2's home.
        let out = a.loaded(ms(1000), "node1", 2, ms(80));
        assert_eq!(
            out,
            vec![AdoptionOutput::Adopted {
                node: "node1".into(),
                brick: 2,
                load: ms(80),
                since_down: ms(1000)
            }]
        );
        // Nobody up: every brick unheld.
        let mut b = BrickAssigner::new(names(1));
        assert_eq!(b.node_down(ms(0), "node0"), vec![AdoptionOutput::Unheld { brick: 0 }]);
    }

    #[test]
    fn daemons_keep_maps_by_frame_and_name_the_nodes_left_without_bricks() {
        let nodes = names(3);
        let mut h = MapHistory::new(nodes.clone());
        assert_eq!(h.map_for(5).bricks_of("node1"), vec![1]);
        let gone = h.set(BrickMap {
            from_frame: 10,
            holders: vec![Some("node0".into()), None, Some("node2".into())],
        });
        assert_eq!(gone, vec!["node1".to_string()]);
        assert_eq!(h.map_for(9).bricks_of("node1"), vec![1]);
        assert_eq!(h.map_for(10).holders[1], None);
        let gone = h.set(BrickMap {
            from_frame: 12,
            holders: vec![Some("node0".into()), Some("node2".into()), Some("node2".into())],
        });
        assert_eq!(gone, vec!["node1".to_string()]);
        assert_eq!(h.map_for(13).bricks_of("node2"), vec![1, 2]);
        assert_eq!(h.map_for(11).bricks_of("node2"), vec![2]);
        // A map for the same frame replaces the one before it.
        assert!(h.set(BrickMap::home(&nodes).clone_from_frame(12)).is_empty());
        assert_eq!(h.map_for(12).bricks_of("node2"), vec![2]);
        assert_eq!(h.latest().from_frame, 12);
        for f in 13..40 {
            h.set(BrickMap::home(&nodes).clone_from_frame(f));
        }
        assert!(h.map_for(100).from_frame == 39 && h.maps.len() == MAPS_KEPT);
        // A new session numbers frames afresh: back to the home map.
        h.reset();
        assert_eq!(h.map_for(1), &BrickMap::home(&nodes));
        h.set(BrickMap::home(&nodes).clone_from_frame(30));
        h.set(BrickMap::home(&nodes).clone_from_frame(2));
        assert_eq!(h.latest().from_frame, 2);
    }

    #[test]
    fn maps_and_bricks_from_the_wire_are_checked() {
        let nodes = names(2);
        let e = BrickMap::from_wire(1, vec![None], &nodes).unwrap_err();
        assert_eq!(e, AdoptionError::WrongLength { got: 1, want: 2 });
        let e = BrickMap::from_wire(1, vec![None, Some("mallory".into())], &nodes).unwrap_err();
        assert!(e.to_string().contains("`mallory`, which is not a node"), "{e}");
        assert!(BrickMap::from_wire(1, vec![None, Some("node0".into())], &nodes).is_ok());
        assert_eq!(brick_index(1, 2), Ok(1));
        assert_eq!(brick_index(2, 2), Err(AdoptionError::NoSuchBrick { brick: 2, bricks: 2 }));
        assert!(brick_index(u64::MAX, 2).is_err());
    }

    impl BrickMap {
        fn clone_from_frame(&self, f: u64) -> BrickMap {
            BrickMap { from_frame: f, ..self.clone() }
        }
    }
}
