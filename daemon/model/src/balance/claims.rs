//! What the controller believes of a node's reports on a balanced wall (DESIGN.md "Distribution":
//! a node's reports are claims). A node's costs steer the split, so a node that says its rows
//! cost nothing would be given other nodes' rows; what keeps it from taking their screens is that
//! the split is checked against what each node delivered:
//! - a node given rectangles of another node's tile that the tile's owner composited without
//!   ([`Claims::missing`]), or that reported no cost for the rectangles it was given before its
//!   Ready ([`Claims::ready`]), *missed*;
//! - a node that missed is held out of the split ([`super::Balancer::set_held`]: it renders its
//!   own tiles and nothing else) for [`Claims::hold_frames`] frames, twice as long after each
//!   miss ([`FIRST_HOLD_FRAMES`], at most [`MAX_HOLD_FRAMES`]), and readmitted after that;
//! - so a node that lies whenever it is let in blanks another node's rows in at most the frame
//!   after each readmission, and its readmissions grow rarer: 4 in its first 200 frames.
//!
//! An owner's report names only peers the split gave rows of its own tiles in that frame; other
//! names are left out, so an owner can hold out only the nodes that owed it pixels (and a held
//! node only loses the rows it would have rendered for others: nothing is shown wrong).
//! No I/O and no clock: frames are counted by their ids.

use std::collections::{BTreeMap, BTreeSet};

use super::node::PIXEL_FETCHES;
use super::Split;
use crate::governor::MAX_SCALE;

/// Frames a node is held out after its first miss.
pub const FIRST_HOLD_FRAMES: u64 = 32;
/// The longest hold (about a minute at 60 fps).
pub const MAX_HOLD_FRAMES: u64 = 4096;
/// Frames whose rectangles are remembered for the reports that come after them.
const FRAMES_KEPT: usize = 16;

/// The least a rectangle of `rows` rows of a tile `width` pixels wide can cost, whatever its
/// rays do: its pixels at the coarsest internal scale, [`PIXEL_FETCHES`] each (the floor under a
/// claimed cost, [`super::Balancer::observe_claim`]).
pub fn cost_floor(width: u32, rows: u32) -> f64 {
    let pixels = u64::from(width.div_ceil(MAX_SCALE)) * u64::from(rows.div_ceil(MAX_SCALE));
    (pixels * PIXEL_FETCHES) as f64
}

/// One node's standing.
#[derive(Debug, Clone, Default)]
struct Standing {
    misses: u32,
    /// Held out of the splits of frames before this one.
    held_until: u64,
}

/// What one frame gave each node, and what came back.
#[derive(Debug, Clone, Default)]
struct Given {
    /// Per owner: the nodes the split gave rows of its tiles.
    owes: BTreeMap<String, BTreeSet<String>>,
    /// The nodes that rendered rectangles, and whether each reported their costs.
    reported: BTreeMap<String, bool>,
}

/// A node held out of the split: who, from which frame, until which, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Miss {
    pub node: String,
    pub frame_id: u64,
    /// The frame it is readmitted at.
    pub held_until: u64,
    /// Its misses so far, this one included.
    pub misses: u32,
    pub why: String,
}

/// The claims' state (module docs).
#[derive(Debug, Clone, Default)]
pub struct Claims {
    nodes: BTreeMap<String, Standing>,
    frames: BTreeMap<u64, Given>,
}

impl Claims {
    pub fn new() -> Claims {
        Claims::default()
    }

    /// Frames a node is held after its `misses`-th miss.
    pub fn hold_frames(misses: u32) -> u64 {
        let doublings = misses.saturating_sub(1).min(63);
        FIRST_HOLD_FRAMES.saturating_mul(1u64 << doublings).min(MAX_HOLD_FRAMES)
    }

    /// The nodes held out of frame `frame_id`'s split.
    pub fn held(&self, frame_id: u64) -> BTreeSet<String> {
        self.nodes.iter().filter(|(_, s)| frame_id < s.held_until).map(|(n, _)| n.clone()).collect()
    }

    /// Frame `frame_id` goes out with `split`; `owner_of(tile)` names a tile's owner.
    pub fn given<'a>(&mut self, frame_id: u64, split: &Split, owner_of: impl Fn(&str) -> Option<&'a str>) {
        let mut g = Given::default();
        for r in &split.rects {
            g.reported.insert(r.renderer.clone(), false);
            if let Some(owner) = owner_of(&r.tile).filter(|o| *o != r.renderer) {
                g.owes.entry(owner.to_string()).or_default().insert(r.renderer.clone());
            }
        }
        self.frames.insert(frame_id, g);
        while self.frames.len() > FRAMES_KEPT {
            self.frames.pop_first();
        }
    }

    /// `node` reported the costs of its rectangles of frame `frame_id`.
    pub fn costs(&mut self, node: &str, frame_id: u64) {
        if let Some(r) = self.frames.get_mut(&frame_id).and_then(|g| g.reported.get_mut(node)) {
            *r = true;
        }
    }

    /// `node` is ready with frame `frame_id`: a miss where it rendered rectangles and reported
    /// no costs for them (`None` also while it is held already: one miss a hold).
    pub fn ready(&mut self, node: &str, frame_id: u64) -> Option<Miss> {
        let unreported = self.frames.get(&frame_id)?.reported.get(node) == Some(&false);
        if !unreported {
            return None;
        }
        self.miss(node, frame_id, "reported no costs for the rectangles it rendered".into())
    }

    /// `owner` composited frame `frame_id` without the pixels of `peers`: a miss for each peer
    /// the split gave rows of `owner`'s tiles in that frame (others are not its to name).
    pub fn missing(&mut self, owner: &str, frame_id: u64, peers: &[String]) -> Vec<Miss> {
        let Some(owed) = self.frames.get(&frame_id).and_then(|g| g.owes.get(owner)).cloned() else {
            return Vec::new();
        };
        peers
            .iter()
            .filter(|p| owed.contains(*p))
            .filter_map(|p| self.miss(p, frame_id, format!("did not deliver its rows of {owner}'s tiles")))
            .collect()
    }

    /// A miss of `node` in `frame_id`, unless it is held already (the reports of frames under
    /// way when it was held out count once).
    fn miss(&mut self, node: &str, frame_id: u64, why: String) -> Option<Miss> {
        let s = self.nodes.entry(node.to_string()).or_default();
        if frame_id < s.held_until {
            return None;
        }
        s.misses = s.misses.saturating_add(1);
        s.held_until = frame_id.saturating_add(1).saturating_add(Self::hold_frames(s.misses));
        Some(Miss { node: node.into(), frame_id, held_until: s.held_until, misses: s.misses, why })
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Balancer, WorkRect};
    use super::*;

    #[test]
    fn holds_double_with_each_miss_up_to_the_cap() {
        assert_eq!(Claims::hold_frames(1), FIRST_HOLD_FRAMES);
        assert_eq!(Claims::hold_frames(2), 2 * FIRST_HOLD_FRAMES);
        assert_eq!(Claims::hold_frames(4), 8 * FIRST_HOLD_FRAMES);
        assert_eq!(Claims::hold_frames(u32::MAX), MAX_HOLD_FRAMES);
    }

    fn owner(tile: &str) -> Option<&'static str> {
        match tile {
            "t0" => Some("n0"),
            "t1" => Some("n1"),
            _ => None,
        }
    }

    fn split(rects: &[(&str, u32, u32, &str)]) -> Split {
        Split {
            rects: rects
                .iter()
                .map(|&(t, f, r, n)| WorkRect { tile: t.into(), first_row: f, rows: r, renderer: n.into() })
                .collect(),
        }
    }

    #[test]
    fn an_owner_can_name_only_the_nodes_that_owed_it_pixels() {
        let mut c = Claims::new();
        c.given(5, &split(&[("t0", 0, 50, "n0"), ("t0", 50, 50, "n1"), ("t1", 0, 100, "n1")]), owner);
        // n1 names n0, which owed it nothing: left out.
        assert!(c.missing("n1", 5, &["n0".into()]).is_empty());
        // A frame never given: nothing.
        assert!(c.missing("n0", 9, &["n1".into()]).is_empty());
        let m = c.missing("n0", 5, &["n1".into()]);
        assert_eq!(m.len(), 1);
        assert_eq!((m[0].node.as_str(), m[0].held_until, m[0].misses), ("n1", 6 + FIRST_HOLD_FRAMES, 1));
        assert_eq!(c.held(6), BTreeSet::from(["n1".to_string()]));
        assert!(c.held(6 + FIRST_HOLD_FRAMES).is_empty(), "readmitted");
    }

    #[test]
    fn a_renderer_that_reports_no_costs_by_its_ready_missed() {
        let mut c = Claims::new();
        c.given(1, &split(&[("t0", 0, 100, "n0"), ("t1", 0, 100, "n1")]), owner);
        c.costs("n0", 1);
        assert_eq!(c.ready("n0", 1), None);
        let m = c.ready("n1", 1).expect("n1 sent no costs");
        assert!(m.why.contains("no costs"), "{m:?}");
        // Held already: the next frames' misses are not counted again.
        c.given(2, &split(&[("t0", 0, 100, "n0"), ("t1", 0, 100, "n1")]), owner);
        assert_eq!(c.ready("n1", 2), None);
        // A node the split gave nothing owes no costs.
        assert_eq!(c.ready("n2", 1), None);
    }

    /// A 2-node wall where n1 says every rectangle costs nothing and never sends the rows of
    /// n0's tile it is given: over 200 frames, n0 composites without them in at most 4 frames
    /// (the frame after each readmission), and the rest of the time n1 renders its own tile.
    #[test]
    fn a_node_that_lies_whenever_it_is_let_in_holes_at_most_two_percent_of_the_frames() {
        let tiles =
            vec![("t0".to_string(), "n0".to_string(), 120), ("t1".to_string(), "n1".to_string(), 120)];
        let mut b = Balancer::new(tiles, 32, super::super::DEFAULT_HYSTERESIS, 1.0).unwrap();
        let mut c = Claims::new();
        let floor = |r: &WorkRect| cost_floor(32, r.rows);
        let mut holes = 0;
        for frame in 1..=200u64 {
            b.set_held(c.held(frame));
            let split = b.next_split(false).clone();
            c.given(frame, &split, owner);
            let mut delivered = true;
            for r in &split.rects {
                // n0's tile holds the scan: 100 units a row, 5 in n1's; n0 says so, n1 claims 0.
                let per_row = if r.tile == "t0" { 100.0 } else { 5.0 };
                let claim = if r.renderer == "n1" { 0.0 } else { per_row * f64::from(r.rows) };
                b.observe_claim(r, claim, floor(r));
                c.costs(&r.renderer, frame);
                if r.renderer == "n1" && r.tile == "t0" {
                    delivered = false;
                }
            }
            if !delivered {
                holes += 1;
                let misses = c.missing("n0", frame, &["n1".into()]);
                assert_eq!(misses.len(), 1, "frame {frame}");
            }
        }
        assert!(holes <= 4, "{holes} of 200 frames of n0 had a hole");
        assert!(holes >= 1, "the lie took rows at least once: the test measures something");
    }
}
