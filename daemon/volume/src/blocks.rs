//! Per-block min/max of the samples, for empty-space skipping.
//!
//! Block (bx, by, bz) covers the cells with indices `b*B .. (b+1)*B` on each axis, i.e. the samples
//! `b*B ..= (b+1)*B` (the shared face is in both blocks). The trilinear field anywhere in the
//! block's closed world box lies within [min, max] of those samples, so a block whose `max < iso`
//! holds no point of the object and a ray may cross it without sampling.

use crate::Volume;
use glam::DVec3;

#[derive(Clone, Debug)]
pub struct BlockMinMax {
    /// Cells per block edge.
    pub block: usize,
    /// Number of blocks on each axis.
    pub counts: [usize; 3],
    /// (min, max) per block, x fastest.
    pub minmax: Vec<[f32; 2]>,
}

impl BlockMinMax {
    /// Default cells per block edge.
    pub const DEFAULT_BLOCK: usize = 8;

    /// The smallest and largest value of the whole volume (every sample is in some block).
    pub fn value_range(&self) -> (f32, f32) {
        let lo = self.minmax.iter().map(|m| m[0]).fold(f32::INFINITY, f32::min);
        let hi = self.minmax.iter().map(|m| m[1]).fold(f32::NEG_INFINITY, f32::max);
        (lo, hi)
    }

    pub fn new(v: &Volume, block: usize) -> BlockMinMax {
        assert!(block >= 1);
        let dims = v.dims();
        // Cells per axis (at least one "cell" for a single-sample axis).
        let cells = dims.map(|n| n.max(2) - 1);
        let counts = cells.map(|c| c.div_ceil(block));
        let mut minmax = Vec::with_capacity(counts.iter().product());
        for bz in 0..counts[2] {
            for by in 0..counts[1] {
                for bx in 0..counts[0] {
                    let range = |b: usize, a: usize| {
                        let lo = (b * block).min(dims[a] - 1);
                        let hi = ((b + 1) * block).min(dims[a] - 1);
                        lo..=hi
                    };
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for k in range(bz, 2) {
                        for j in range(by, 1) {
                            for i in range(bx, 0) {
                                let x = v.at(i, j, k);
                                lo = lo.min(x);
                                hi = hi.max(x);
                            }
                        }
                    }
                    minmax.push([lo, hi]);
                }
            }
        }
        BlockMinMax { block, counts, minmax }
    }

    pub fn get(&self, bx: usize, by: usize, bz: usize) -> [f32; 2] {
        self.minmax[bx + self.counts[0] * (by + self.counts[1] * bz)]
    }

    /// The level above: blocks of `factor` x `factor` x `factor` of these blocks (`factor * block`
    /// cells per edge; fewer at the far edges), each with the min and max of the blocks it holds.
    /// Those cover exactly the samples of the coarse block's cells, so the coarse min/max bound the
    /// field in its closed box as the fine ones do in theirs (hierarchical empty-space skipping).
    pub fn coarsen(&self, factor: usize) -> BlockMinMax {
        assert!(factor >= 1);
        let counts = self.counts.map(|c| c.div_ceil(factor));
        let mut minmax = vec![[f32::INFINITY, f32::NEG_INFINITY]; counts.iter().product()];
        for bz in 0..self.counts[2] {
            for by in 0..self.counts[1] {
                for bx in 0..self.counts[0] {
                    let [lo, hi] = self.get(bx, by, bz);
                    let c = &mut minmax[bx / factor + counts[0] * (by / factor + counts[1] * (bz / factor))];
                    c[0] = c[0].min(lo);
                    c[1] = c[1].max(hi);
                }
            }
        }
        BlockMinMax { block: self.block * factor, counts, minmax }
    }

    /// Fraction of blocks that may contain the iso surface or object (max >= iso).
    pub fn occupied_fraction(&self, iso: f32) -> f64 {
        let n = self.minmax.iter().filter(|m| m[1] >= iso).count();
        n as f64 / self.minmax.len().max(1) as f64
    }

    /// The world box of the object {f >= iso} at block resolution: the union of the closed boxes
    /// of the blocks with `max >= iso`, for a grid of `dims` samples at `origin` with `spacing`
    /// (the volume these blocks were made of). Those are the blocks a surface crossing can lie in
    /// (`min <= iso <= max`) and the blocks wholly inside the object (`min > iso`); the latter add
    /// nothing to the crossings' box except where the object meets the volume's box, whose face
    /// then closes it with a cap (DESIGN.md "Volume"), which is surface too. `None` where no
    /// block reaches `iso` (nothing to see).
    pub fn object_box(
        &self,
        iso: f64,
        dims: [usize; 3],
        origin: DVec3,
        spacing: DVec3,
    ) -> Option<(DVec3, DVec3)> {
        let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
        for bz in 0..self.counts[2] {
            for by in 0..self.counts[1] {
                for bx in 0..self.counts[0] {
                    if f64::from(self.get(bx, by, bz)[1]) < iso {
                        continue;
                    }
                    for (a, b) in [bx, by, bz].into_iter().enumerate() {
                        lo[a] = lo[a].min(b);
                        hi[a] = hi[a].max(b);
                    }
                }
            }
        }
        if lo[0] == usize::MAX {
            return None;
        }
        let last = dims.map(|n| n.max(1) - 1);
        let sample =
            |a: usize, b: usize| origin[a] + b.saturating_mul(self.block).min(last[a]) as f64 * spacing[a];
        Some((
            DVec3::new(sample(0, lo[0]), sample(1, lo[1]), sample(2, lo[2])),
            DVec3::new(sample(0, hi[0] + 1), sample(1, hi[1] + 1), sample(2, hi[2] + 1)),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_object_box_holds_the_blocks_that_reach_the_iso() {
        // A 40 x 30 x 20 grid, spacing (0.5, 1, 2) from (10, -5, 3), with a solid (value 10) over
        // samples x 12..=20, y 3..=9, z 0..=19 (it meets the box's z faces: caps), 0 elsewhere.
        let dims = [40, 30, 20];
        let (origin, spacing) = (DVec3::new(10.0, -5.0, 3.0), DVec3::new(0.5, 1.0, 2.0));
        let mut data = vec![0f32; dims.iter().product()];
        for k in 0..20 {
            for j in 3..=9 {
                for i in 12..=20 {
                    data[i + 40 * (j + 30 * k)] = 10.0;
                }
            }
        }
        let v = Volume::new("box", dims, spacing, origin, data).unwrap();
        let b = BlockMinMax::new(&v, 8);
        // Samples 12..=20 lie in blocks 1..=2 (samples 8..=24), 3..=9 in blocks 0..=1 (0..=16),
        // z in every block (0..=19): the box of those blocks' samples.
        let (lo, hi) = b.object_box(5.0, dims, origin, spacing).unwrap();
        let world = |i: f64, j: f64, k: f64| origin + spacing * DVec3::new(i, j, k);
        assert_eq!((lo, hi), (world(8.0, 0.0, 0.0), world(24.0, 16.0, 19.0)));
        // Every sample of the object is inside, and the box is well inside the volume's.
        assert!(lo.cmple(world(12.0, 3.0, 0.0)).all() && hi.cmpge(world(20.0, 9.0, 19.0)).all());
        assert!((hi - lo).x < 0.5 * (v.box_max() - v.box_min()).x);
        // An iso at the data's minimum: every block, the volume's box; above the maximum: none.
        assert_eq!(b.object_box(0.0, dims, origin, spacing), Some((v.box_min(), v.box_max())));
        assert_eq!(b.object_box(10.5, dims, origin, spacing), None);
        // The blocks of one level coarser give a box that holds the finer one.
        let (clo, chi) = b.coarsen(2).object_box(5.0, dims, origin, spacing).unwrap();
        assert!(clo.cmple(lo).all() && chi.cmpge(hi).all());
    }

    #[test]
    fn blocks_bound_every_sample_they_cover_including_shared_faces() {
        let dims = [19, 10, 5];
        let data: Vec<f32> = (0..dims.iter().product::<usize>()).map(|n| ((n * 7919) % 101) as f32).collect();
        let v = Volume::new("t", dims, DVec3::ONE, DVec3::ZERO, data).unwrap();
        let b = BlockMinMax::new(&v, 4);
        assert_eq!(b.counts, [5, 3, 1]);
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    // Every block whose closed cell range contains the sample bounds it.
                    for bx in [i / 4, i.saturating_sub(1) / 4] {
                        let bx = bx.min(b.counts[0] - 1);
                        let (by, bz) = ((j.min(8)) / 4, (k.min(3)) / 4);
                        let [lo, hi] = b.get(bx, by.min(b.counts[1] - 1), bz);
                        let x = v.at(i, j, k);
                        if i >= bx * 4 && i <= bx * 4 + 4 {
                            assert!(
                                lo <= x && x <= hi,
                                "sample ({i},{j},{k}) outside block ({bx},{by},{bz})"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn a_coarse_level_equals_blocks_of_its_size() {
        let dims = [23, 17, 9];
        let data: Vec<f32> = (0..dims.iter().product::<usize>()).map(|n| ((n * 7919) % 101) as f32).collect();
        let v = Volume::new("t", dims, DVec3::ONE, DVec3::ZERO, data).unwrap();
        for (block, factor) in [(2, 2), (4, 4), (3, 2), (8, 4)] {
            let coarse = BlockMinMax::new(&v, block).coarsen(factor);
            let direct = BlockMinMax::new(&v, block * factor);
            assert_eq!(coarse.block, direct.block);
            assert_eq!(coarse.counts, direct.counts, "block {block} factor {factor}");
            assert_eq!(coarse.minmax, direct.minmax, "block {block} factor {factor}");
        }
    }
}
