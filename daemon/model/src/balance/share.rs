//! What a node makes of a frame's split, and the split on the wire.
//!
//! A node renders the split's rectangles that name it ([`NodeShare::renders`]): those of its own
//! tiles stay with it, the finished pixels of the others go to each tile's owner
//! ([`NodeShare::sends`]); an owner waits for the rectangles of its tiles that other nodes render
//! ([`NodeShare::expects`]: the [`Footprints`] that object space's compositor waits on and checks
//! what arrives against, so a rectangle is accepted only from the node the split gave it to, and
//! only as large as the split says, before anything is allocated or decompressed).
//!
//! On the wire, tiles and nodes travel as their index in the wall config, which both ends read.
//! [`split_from_wire`] checks the whole split before any of it is used: every index names a tile
//! or a node of the wall, every rectangle's rows lie inside its tile, the rectangles of a tile
//! follow each other from its first row to its last without a gap or an overlap (a tile of a node
//! that is down is absent: nobody shows it), and there are at most [`MAX_RECTS_PER_TILE`] per tile.

use std::collections::BTreeMap;

use crate::balance::{Split, WorkRect};
use crate::composite::{Footprints, TileRect};
use crate::config::WallConfig;
use crate::wire::{WireSplit, WireWorkRect};

/// The most rectangles one tile may be cut into on the wire (a band is at least a row, and the
/// balancer's bands are far fewer: [`super::DEFAULT_BANDS`]).
pub const MAX_RECTS_PER_TILE: usize = 256;

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum SplitError {
    #[error("the split has {rects} rectangles, more than {max} ({MAX_RECTS_PER_TILE} for each of the wall's {tiles} tiles)")]
    TooMany { rects: usize, max: usize, tiles: usize },
    #[error("rectangle {index}: `tile` = {tile}, but the wall has {tiles} tiles")]
    UnknownTile { index: usize, tile: u32, tiles: usize },
    #[error("rectangle {index}: `renderer` = {renderer}, but the wall has {nodes} nodes")]
    UnknownRenderer { index: usize, renderer: u32, nodes: usize },
    #[error("rectangle {index} of tile `{tile}`: rows {first_row}..{end} are not inside its {height} rows")]
    OutsideTile { index: usize, tile: String, first_row: u32, end: u64, height: u32 },
    #[error("rectangle {index} of tile `{tile}` starts at row {first_row}, but the tile's rectangles before it end at row {expected}")]
    NotContiguous { index: usize, tile: String, first_row: u32, expected: u32 },
    #[error("tile `{tile}`: its rectangles end at row {end}, not at its last row ({height})")]
    Incomplete { tile: String, end: u32, height: u32 },
    #[error("the split names tile `{tile}` rendered by `{renderer}`, which the wall config lacks")]
    NotInWall { tile: String, renderer: String },
}

/// `split` on the wire, tiles and nodes by their index in `config`.
pub fn split_to_wire(split: &Split, config: &WallConfig) -> Result<WireSplit, SplitError> {
    split
        .rects
        .iter()
        .map(|r| {
            let tile = config.tiles.iter().position(|t| t.name == r.tile);
            let renderer = config.nodes.iter().position(|n| n.name == r.renderer);
            match (tile, renderer) {
                (Some(t), Some(n)) => Ok(WireWorkRect {
                    tile: t as u32,
                    first_row: r.first_row,
                    rows: r.rows,
                    renderer: n as u32,
                }),
                _ => Err(SplitError::NotInWall { tile: r.tile.clone(), renderer: r.renderer.clone() }),
            }
        })
        .collect::<Result<Vec<_>, _>>()
        .map(|rects| WireSplit { rects })
}

/// The split a peer sent, checked whole (module docs) against `config`.
pub fn split_from_wire(wire: &WireSplit, config: &WallConfig) -> Result<Split, SplitError> {
    let (tiles, nodes) = (config.tiles.len(), config.nodes.len());
    let max = tiles.saturating_mul(MAX_RECTS_PER_TILE);
    if wire.rects.len() > max {
        return Err(SplitError::TooMany { rects: wire.rects.len(), max, tiles });
    }
    // Per tile, the row its rectangles have reached.
    let mut reached: Vec<Option<u32>> = vec![None; tiles];
    let mut rects = Vec::with_capacity(wire.rects.len());
    for (index, w) in wire.rects.iter().enumerate() {
        let Some(tile) = config.tiles.get(w.tile as usize) else {
            return Err(SplitError::UnknownTile { index, tile: w.tile, tiles });
        };
        let Some(renderer) = config.nodes.get(w.renderer as usize) else {
            return Err(SplitError::UnknownRenderer { index, renderer: w.renderer, nodes });
        };
        let end = u64::from(w.first_row) + u64::from(w.rows);
        if w.rows == 0 || end > u64::from(tile.height) {
            let (first_row, height) = (w.first_row, tile.height);
            return Err(SplitError::OutsideTile { index, tile: tile.name.clone(), first_row, end, height });
        }
        let expected = reached[w.tile as usize].unwrap_or(0);
        if w.first_row != expected {
            let (tile, first_row) = (tile.name.clone(), w.first_row);
            return Err(SplitError::NotContiguous { index, tile, first_row, expected });
        }
        reached[w.tile as usize] = Some(end as u32);
        rects.push(WorkRect {
            tile: tile.name.clone(),
            first_row: w.first_row,
            rows: w.rows,
            renderer: renderer.name.clone(),
        });
    }
    for (tile, end) in config.tiles.iter().zip(&reached) {
        if let Some(end) = *end {
            if end != tile.height {
                return Err(SplitError::Incomplete { tile: tile.name.clone(), end, height: tile.height });
            }
        }
    }
    Ok(Split { rects })
}

/// What one node does with a frame's split (module docs).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct NodeShare {
    /// The rectangles it renders, of its own tiles and of others', in the split's order.
    pub renders: Vec<WorkRect>,
    /// Of those, the ones of other nodes' tiles, by the tile's owner.
    pub sends: BTreeMap<String, Vec<WorkRect>>,
    /// The rectangles of its own tiles that other nodes render, by renderer, in the tile's own
    /// pixels.
    pub expects: Footprints,
}

impl NodeShare {
    /// `node`'s share of `split` on the wall `config` (rectangles of tiles the config lacks, or
    /// that no node shows, are left out).
    pub fn of(split: &Split, config: &WallConfig, node: &str) -> NodeShare {
        let mut share = NodeShare::default();
        for r in &split.rects {
            let Some(owner) = config.node_of_tile(&r.tile) else { continue };
            if r.renderer == node {
                share.renders.push(r.clone());
                if owner.name != node {
                    share.sends.entry(owner.name.clone()).or_default().push(r.clone());
                }
            } else if owner.name == node {
                if let Some(rect) = tile_rect(config, r) {
                    share.expects.entry(r.renderer.clone()).or_default().push((r.tile.clone(), rect));
                }
            }
        }
        share
    }
}

/// Rectangle `r` in its tile's own pixels (the tile's full width), where the wall has the tile.
pub fn tile_rect(config: &WallConfig, r: &WorkRect) -> Option<TileRect> {
    let tile = config.tiles.iter().find(|t| t.name == r.tile)?;
    Some(TileRect { x: 0, y: r.first_row, width: tile.width, height: r.rows })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::balance::Balancer;

    /// A 2x2 wall of 64x48 tiles, one node each (tile `tK` on node `nK`).
    fn wall() -> WallConfig {
        let mut toml = String::from(
            "[wall]\nname = \"w\"\n[camera]\neye = [0, -10, 0]\ntarget = [0, 0, 0]\nup = [0, 0, 1]\n\
             [volume]\nsource = \"procedural:engine\"\n",
        );
        for k in 0..4 {
            let (x, y) = (64 * (k % 2), 48 * (k / 2));
            toml += &format!("[[tiles]]\nname = \"t{k}\"\nx = {x}\ny = {y}\nwidth = 64\nheight = 48\n");
        }
        for k in 0..4 {
            toml += &format!(
                "[[nodes]]\nname = \"n{k}\"\naddress = \"127.0.0.1:{}\"\ntiles = [\"t{k}\"]\n",
                7000 + k
            );
        }
        WallConfig::parse(&toml, std::path::Path::new("w.toml")).unwrap()
    }

    /// A balanced split of `wall()` where tile t0 holds nearly all the work.
    fn busy_split(config: &WallConfig) -> Split {
        let mut b = Balancer::for_wall(config);
        for r in b.split().rects.clone() {
            b.observe(&r, if r.tile == "t0" { 100.0 } else { 1.0 });
        }
        b.next_split(false).clone()
    }

    #[test]
    fn a_split_crosses_the_wire_unchanged() {
        let config = wall();
        let split = busy_split(&config);
        assert!(split.rects.iter().any(|r| r.tile == "t0" && r.renderer != "n0"), "{split:?}");
        let wire = split_to_wire(&split, &config).unwrap();
        assert_eq!(split_from_wire(&wire, &config).unwrap(), split);
        let foreign = Split {
            rects: vec![WorkRect { tile: "t9".into(), first_row: 0, rows: 48, renderer: "n0".into() }],
        };
        assert!(matches!(split_to_wire(&foreign, &config), Err(SplitError::NotInWall { .. })));
    }

    #[test]
    fn every_pixel_is_rendered_once_and_each_owner_expects_what_is_sent_to_it() {
        let config = wall();
        let split = busy_split(&config);
        let shares: BTreeMap<String, NodeShare> =
            config.nodes.iter().map(|n| (n.name.clone(), NodeShare::of(&split, &config, &n.name))).collect();
        // Each row of each tile is rendered by exactly one node.
        for t in &config.tiles {
            let mut rows = vec![0u32; t.height as usize];
            for s in shares.values() {
                for r in s.renders.iter().filter(|r| r.tile == t.name) {
                    for row in r.first_row..r.first_row + r.rows {
                        rows[row as usize] += 1;
                    }
                }
            }
            assert!(rows.iter().all(|&c| c == 1), "tile {}: {rows:?}", t.name);
        }
        // What a node sends an owner is what the owner expects from it, rectangle for rectangle.
        let mut sent = 0;
        for (node, s) in &shares {
            for (owner, rects) in &s.sends {
                let want: Vec<(String, TileRect)> =
                    rects.iter().map(|r| (r.tile.clone(), tile_rect(&config, r).unwrap())).collect();
                assert_eq!(shares[owner].expects.get(node), Some(&want), "{node} -> {owner}");
                sent += rects.len();
            }
        }
        let expected: usize = shares.values().flat_map(|s| s.expects.values()).map(Vec::len).sum();
        assert!(sent > 0);
        assert_eq!(sent, expected);
        // The busy tile's owner renders only its own pixels; the others send it theirs.
        assert!(shares["n0"].sends.is_empty());
        assert!(shares["n0"].expects.len() >= 2, "{:?}", shares["n0"].expects);
    }

    #[test]
    fn a_hostile_split_is_refused_whole_with_the_rectangle_and_field_named() {
        let config = wall();
        let ok = split_to_wire(&busy_split(&config), &config).unwrap();
        let with = |f: &dyn Fn(&mut Vec<WireWorkRect>)| {
            let mut w = ok.clone();
            f(&mut w.rects);
            split_from_wire(&w, &config).unwrap_err()
        };
        let e = with(&|r| r[1].tile = 4);
        assert_eq!(e, SplitError::UnknownTile { index: 1, tile: 4, tiles: 4 });
        assert!(e.to_string().contains("rectangle 1: `tile` = 4"), "{e}");
        let e = with(&|r| r[0].renderer = u32::MAX);
        assert!(matches!(e, SplitError::UnknownRenderer { index: 0, nodes: 4, .. }), "{e}");
        // Rows past the tile, also where first_row + rows overflows a u32, and empty rectangles.
        let e = with(&|r| r[0].rows = u32::MAX);
        assert!(matches!(e, SplitError::OutsideTile { index: 0, height: 48, .. }), "{e}");
        let e = with(&|r| r[0].rows = 0);
        assert!(matches!(e, SplitError::OutsideTile { index: 0, .. }), "{e}");
        // A rectangle that overlaps the one before it, or leaves a gap, or a tile left short.
        let t0: Vec<usize> =
            ok.rects.iter().enumerate().filter(|(_, r)| r.tile == 0).map(|(i, _)| i).collect();
        assert!(t0.len() >= 2, "{ok:?}");
        let e = with(&|r| r[t0[1]].first_row -= 1);
        assert!(matches!(e, SplitError::NotContiguous { .. }), "{e}");
        let e = with(&|r| r.swap(t0[0], t0[1]));
        assert!(matches!(e, SplitError::NotContiguous { .. }), "{e}");
        let last = *t0.last().unwrap();
        let e = with(&|r| {
            r.remove(last);
        });
        assert!(matches!(e, SplitError::Incomplete { ref tile, .. } if tile == "t0"), "{e}");
        // More rectangles than the wall's tiles may hold: refused before any is looked at.
        let many = WireSplit {
            rects: vec![
                WireWorkRect { tile: 0, first_row: 0, rows: 1, renderer: 0 };
                4 * MAX_RECTS_PER_TILE + 1
            ],
        };
        assert!(matches!(split_from_wire(&many, &config), Err(SplitError::TooMany { .. })));
        // A tile left out altogether (its node is down) is a valid split.
        let mut down = ok.clone();
        down.rects.retain(|r| r.tile != 3);
        assert!(split_from_wire(&down, &config).is_ok());
    }
}
