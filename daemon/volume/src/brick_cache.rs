//! The brick cache's host side (DESIGN.md "Large volumes"): a pyramid cut into bricks, the sources
//! bricks are read from, the host cache that holds decoded bricks within a byte budget, and the
//! rule that says which bricks a view wants at which level.
//!
//! - **A brick** (a *cache brick*, not object space's per-node brick) of a level with `cells`
//!   cells per edge covers the cells `b*cells .. (b+1)*cells` of that level on each axis and holds
//!   their samples `b*cells ..= (b+1)*cells`: `cells + 1` per edge, the far face shared with the
//!   next brick (the apron a trilinear lookup needs, so one lookup reads one brick). At the far
//!   edges of a level the missing samples repeat the last one (never read: a lookup's cell lies
//!   inside the level). These are the bricks of the per-brick min/max `isowalld convert` writes
//!   (`isowall_minmax/<level>`, brick = chunk) and of [`crate::BlockMinMax`].
//! - **The field at a point** is the trilinear interpolant of the finest level whose brick there is
//!   resident (the GPU side: `shaders/volume.wgsl`, `bricked_trilinear`). A still frame is the
//!   in-core picture once every brick [`wanted_bricks`] lists for it is resident at level 0.

use crate::io::ome_zarr_write::mean_level;
use crate::{BlockMinMax, Volume, VolumeError, VolumeInfo};
use glam::DVec3;
use std::collections::HashMap;
use std::sync::Arc;

/// Levels a pyramid may have in the cache (the GPU's directory holds this many).
pub const MAX_CACHE_LEVELS: usize = 16;

/// Cells per brick edge of an in-core volume's pyramid ([`InCorePyramid`]), where nothing else
/// chose them: 32 (a brick of 33^3 `f32` samples is 141 KiB), so that a pool of a few hundred MB
/// holds thousands of them and a view loads little it does not see. A store's bricks are its
/// chunks (64 as `convert` writes them), whose min/max it holds.
pub const DEFAULT_BRICK_CELLS: usize = 32;

/// A brick of the pyramid: its level and its index on x, y, z.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BrickKey {
    pub level: u8,
    pub brick: [u32; 3],
}

/// One level of a bricked pyramid.
#[derive(Clone, Debug, PartialEq)]
pub struct PyramidLevel {
    /// Samples on x, y, z.
    pub dims: [usize; 3],
    pub spacing: DVec3,
    /// World position of sample (0, 0, 0).
    pub origin: DVec3,
    /// Bricks on x, y, z.
    pub counts: [usize; 3],
}

impl PyramidLevel {
    /// The far corner of the level's box (the near one is `origin`), by the rule of
    /// [`crate::VolumeInfo::box_max`].
    pub fn box_max(&self) -> DVec3 {
        crate::VolumeInfo { name: String::new(), dims: self.dims, spacing: self.spacing, origin: self.origin }
            .box_max()
    }
}

/// The pyramid's levels (finest first) and how they are cut into bricks.
#[derive(Clone, Debug, PartialEq)]
pub struct BrickLayout {
    /// Cells per brick edge (a power of two, so that a cell's brick is a shift on the GPU).
    pub cells: usize,
    pub levels: Vec<PyramidLevel>,
}

impl BrickLayout {
    /// The layout of levels given as (dims, spacing, origin), finest first, with bricks of `cells`
    /// cells per edge.
    pub fn new(cells: usize, levels: &[([usize; 3], DVec3, DVec3)]) -> Result<BrickLayout, String> {
        if !cells.is_power_of_two() || !(2..=256).contains(&cells) {
            return Err(format!("bricks of {cells} cells per edge: a power of two in 2..=256 is needed"));
        }
        if levels.is_empty() || levels.len() > MAX_CACHE_LEVELS {
            return Err(format!("{} levels: 1..={MAX_CACHE_LEVELS} are cached", levels.len()));
        }
        let levels = levels
            .iter()
            .map(|&(dims, spacing, origin)| PyramidLevel {
                dims,
                spacing,
                origin,
                counts: dims.map(|n| (n.max(2) - 1).div_ceil(cells)),
            })
            .collect();
        Ok(BrickLayout { cells, levels })
    }

    /// Samples per brick edge: the cells and the shared far face.
    pub fn samples(&self) -> usize {
        self.cells + 1
    }

    /// Samples in one brick.
    pub fn brick_voxels(&self) -> usize {
        self.samples().pow(3)
    }

    /// Bytes of one brick as `f32`.
    pub fn brick_bytes(&self) -> u64 {
        4 * self.brick_voxels() as u64
    }

    /// Bricks of level `l`.
    pub fn bricks(&self, l: usize) -> usize {
        self.levels[l].counts.iter().product()
    }

    /// Bricks of every level.
    pub fn total_bricks(&self) -> usize {
        (0..self.levels.len()).map(|l| self.bricks(l)).sum()
    }

    /// The coarsest level's index.
    pub fn coarsest(&self) -> usize {
        self.levels.len() - 1
    }

    /// Every brick of level `l`, x fastest.
    pub fn keys(&self, l: usize) -> impl Iterator<Item = BrickKey> + '_ {
        let [cx, cy, cz] = self.levels[l].counts;
        (0..cz).flat_map(move |z| {
            (0..cy).flat_map(move |y| {
                (0..cx).map(move |x| BrickKey { level: l as u8, brick: [x as u32, y as u32, z as u32] })
            })
        })
    }

    /// Index of a brick within its level (x fastest).
    pub fn index(&self, key: BrickKey) -> usize {
        let c = self.levels[key.level as usize].counts;
        let b = key.brick.map(|v| v as usize);
        b[0] + c[0] * (b[1] + c[1] * b[2])
    }

    /// The world box of a brick's cells, clamped to its level's box.
    pub fn brick_box(&self, key: BrickKey) -> (DVec3, DVec3) {
        let l = &self.levels[key.level as usize];
        let last = DVec3::new(l.dims[0] as f64, l.dims[1] as f64, l.dims[2] as f64) - 1.0;
        let b = DVec3::new(f64::from(key.brick[0]), f64::from(key.brick[1]), f64::from(key.brick[2]));
        let lo = (b * self.cells as f64).min(last);
        let hi = ((b + 1.0) * self.cells as f64).min(last);
        (l.origin + lo * l.spacing, l.origin + hi * l.spacing)
    }

    /// The brick of level `l` that holds world point p (clamped to the level's bricks).
    pub fn brick_at(&self, l: usize, p: DVec3) -> BrickKey {
        let lv = &self.levels[l];
        let u = (p - lv.origin) / lv.spacing / self.cells as f64;
        let b = [u.x, u.y, u.z];
        let brick = std::array::from_fn(|a| (b[a].floor().max(0.0) as usize).min(lv.counts[a] - 1) as u32);
        BrickKey { level: l as u8, brick }
    }

    /// A brick's samples cut out of its level's samples `level` (x fastest, `dims` of the level),
    /// the far edges repeating the last sample.
    pub fn cut(&self, key: BrickKey, level: &[f32]) -> Vec<f32> {
        let l = &self.levels[key.level as usize];
        let s = self.samples();
        let o = key.brick.map(|b| b as usize * self.cells);
        let mut out = Vec::with_capacity(self.brick_voxels());
        for k in 0..s {
            let z = (o[2] + k).min(l.dims[2] - 1);
            for j in 0..s {
                let y = (o[1] + j).min(l.dims[1] - 1);
                let row = l.dims[0] * (y + l.dims[1] * z);
                for i in 0..s {
                    out.push(level[row + (o[0] + i).min(l.dims[0] - 1)]);
                }
            }
        }
        out
    }
}

/// Where bricks come from: an OME-Zarr store ([`crate::io::ome_zarr::OmeZarr`]) or a volume held
/// in core ([`InCorePyramid`]).
pub trait BrickSource: Send + Sync {
    fn layout(&self) -> &BrickLayout;
    /// The (min, max) of every brick of level `l` (x fastest) where the source knows them without
    /// reading the voxels (a store `convert` wrote; an in-core pyramid); `None` otherwise (each
    /// brick is then wanted until read: conservative).
    fn ranges(&self, l: usize) -> Option<&[[f32; 2]]>;
    /// A brick's samples ([`BrickLayout::samples`] per edge, x fastest), read and decoded.
    fn read_brick(&self, key: BrickKey) -> Result<Vec<f32>, VolumeError>;
    /// A name for errors and logs.
    fn name(&self) -> &str;
    /// Level 0's smallest and largest sample, where the ranges are known.
    fn value_range(&self) -> Option<(f32, f32)> {
        self.ranges(0).map(|r| {
            r.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), m| (lo.min(m[0]), hi.max(m[1])))
        })
    }
    /// Level 0's bricks' ranges as a block grid (blocks of a brick's cells), where known: what
    /// frames a camera on the object at an iso ([`BlockMinMax::object_box`]) without a voxel read.
    fn level0_blocks(&self) -> Option<BlockMinMax> {
        let layout = self.layout();
        let l0 = &layout.levels[0];
        self.ranges(0).map(|r| BlockMinMax { block: layout.cells, counts: l0.counts, minmax: r.to_vec() })
    }
    /// Level 0's grid (the volume's dims, spacing and origin) under the source's name.
    fn level0_info(&self) -> VolumeInfo {
        let l0 = &self.layout().levels[0];
        VolumeInfo { name: self.name().to_string(), dims: l0.dims, spacing: l0.spacing, origin: l0.origin }
    }
}

/// A volume held in core as a bricked pyramid: level 0 is the volume, each next level its
/// [`mean_level`] (as `convert` writes them), until a level fits one brick.
pub struct InCorePyramid {
    layout: BrickLayout,
    levels: Vec<Volume>,
    ranges: Vec<Vec<[f32; 2]>>,
    name: String,
}

impl InCorePyramid {
    pub fn new(volume: Volume, cells: usize) -> Result<InCorePyramid, VolumeError> {
        let name = volume.name.clone();
        let mut levels = vec![volume];
        while levels.len() < MAX_CACHE_LEVELS
            && levels.last().is_some_and(|v| v.dims().iter().any(|&n| n > cells + 1))
        {
            let next = mean_level(levels.last().expect("one level"));
            levels.push(next);
        }
        let geometry: Vec<_> = levels.iter().map(|v| (v.dims(), v.spacing(), v.origin())).collect();
        let layout = BrickLayout::new(cells, &geometry)
            .map_err(|what| VolumeError::Format { path: name.clone().into(), what })?;
        let ranges = levels.iter().map(|v| BlockMinMax::new(v, cells).minmax).collect();
        Ok(InCorePyramid { layout, levels, ranges, name })
    }

    /// Level `l`'s samples.
    pub fn level(&self, l: usize) -> &Volume {
        &self.levels[l]
    }
}

impl BrickSource for InCorePyramid {
    fn layout(&self) -> &BrickLayout {
        &self.layout
    }
    fn ranges(&self, l: usize) -> Option<&[[f32; 2]]> {
        Some(&self.ranges[l])
    }
    fn read_brick(&self, key: BrickKey) -> Result<Vec<f32>, VolumeError> {
        Ok(self.layout.cut(key, self.levels[key.level as usize].data()))
    }
    fn name(&self) -> &str {
        &self.name
    }
}

/// Hits and misses of a [`HostBrickCache`], and the bytes it holds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HostCacheStats {
    pub hits: u64,
    pub misses: u64,
    /// Bricks evicted to stay within the budget.
    pub evictions: u64,
    pub bytes: u64,
    /// The most bytes ever held.
    pub peak_bytes: u64,
}

/// Decoded bricks on the host, least recently used evicted first, never more than `budget` bytes.
pub struct HostBrickCache {
    budget: u64,
    clock: u64,
    bricks: HashMap<BrickKey, (Arc<Vec<f32>>, u64)>,
    stats: HostCacheStats,
}

impl HostBrickCache {
    /// A cache of at most `budget` bytes; at least one brick of `layout` must fit.
    pub fn new(budget: u64, layout: &BrickLayout) -> Result<HostBrickCache, String> {
        if budget < layout.brick_bytes() {
            return Err(format!(
                "a host budget of {budget} bytes holds no brick of {} bytes ({}^3 samples)",
                layout.brick_bytes(),
                layout.samples()
            ));
        }
        Ok(HostBrickCache { budget, clock: 0, bricks: HashMap::new(), stats: HostCacheStats::default() })
    }

    pub fn stats(&self) -> HostCacheStats {
        self.stats
    }

    pub fn budget(&self) -> u64 {
        self.budget
    }

    /// Whether `key` is held (without touching it).
    pub fn holds(&self, key: BrickKey) -> bool {
        self.bricks.contains_key(&key)
    }

    /// The brick `key`, from the cache or read from `source` (evicting the least recently used
    /// bricks first, so the cache never holds more than its budget).
    pub fn get(&mut self, source: &dyn BrickSource, key: BrickKey) -> Result<Arc<Vec<f32>>, VolumeError> {
        self.clock += 1;
        if let Some((data, stamp)) = self.bricks.get_mut(&key) {
            *stamp = self.clock;
            self.stats.hits += 1;
            return Ok(data.clone());
        }
        let data = source.read_brick(key)?;
        Ok(self.hold(source.layout().brick_bytes(), key, data))
    }

    /// Reads the bricks of `keys` the cache does not hold, `threads` at a time on threads of
    /// their own (a store's chunks decode independently), and holds them as [`Self::get`] would,
    /// in the order given: at most as many as the budget holds, so that none pushes out another
    /// of them. The caller's `get`s then find them. Memory: the cache's budget and `threads`
    /// bricks being read.
    pub fn prefetch(
        &mut self,
        source: &dyn BrickSource,
        keys: &[BrickKey],
        threads: usize,
    ) -> Result<(), VolumeError> {
        let bytes = source.layout().brick_bytes();
        let fits = (self.budget / bytes) as usize;
        let mut seen = std::collections::HashSet::new();
        let missing: Vec<BrickKey> =
            keys.iter().copied().filter(|k| !self.holds(*k) && seen.insert(*k)).take(fits).collect();
        if threads < 2 || missing.len() < 2 {
            return Ok(());
        }
        for batch in missing.chunks(threads) {
            let read: Vec<Result<Vec<f32>, VolumeError>> = std::thread::scope(|s| {
                let readers: Vec<_> = batch.iter().map(|&k| s.spawn(move || source.read_brick(k))).collect();
                readers
                    .into_iter()
                    .map(|r| r.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
                    .collect()
            });
            for (&key, data) in batch.iter().zip(read) {
                self.clock += 1;
                self.hold(bytes, key, data?);
            }
        }
        Ok(())
    }

    /// Holds `data` (brick `key`, `bytes` bytes) as a miss, evicting the least recently used
    /// bricks first so the cache never holds more than its budget.
    fn hold(&mut self, bytes: u64, key: BrickKey, data: Vec<f32>) -> Arc<Vec<f32>> {
        self.stats.misses += 1;
        while self.stats.bytes + bytes > self.budget {
            let Some(oldest) = self.bricks.iter().min_by_key(|(_, (_, s))| *s).map(|(k, _)| *k) else {
                break;
            };
            self.bricks.remove(&oldest);
            self.stats.bytes -= bytes;
            self.stats.evictions += 1;
        }
        let data = Arc::new(data);
        self.bricks.insert(key, (data.clone(), self.clock));
        self.stats.bytes += bytes;
        self.stats.peak_bytes = self.stats.peak_bytes.max(self.stats.bytes);
        data
    }
}

/// What a view asks of the cache: where the eye is, how large a pixel is there, and what the
/// view's rays (and those that leave its surface) can reach.
#[derive(Clone, Copy, Debug)]
pub struct ViewFootprint {
    pub eye: DVec3,
    /// The angle one pixel subtends at the eye, radians (about `2 tan(fov_y / 2) / height`).
    pub pixel_angle: f64,
    /// Still: every wanted brick at level 0. Moving: the level whose voxel covers at most about
    /// one pixel at the brick's distance.
    pub still: bool,
    /// The planes (n, d) of the view's cone (`n . p + d >= 0` inside), where it is culled to.
    pub planes: Option<[(DVec3, f64); 4]>,
    /// How far outside the cone a ray can read (AO rays' reach and the gradient's stencil),
    /// world units; infinite for an unbounded AO radius (nothing culled).
    pub reach: f64,
    /// The kernels take an AO ray entering a block whose every sample reaches the iso as
    /// occluded without reading it (`PerfOptions::block_min_exit`): then a brick wholly inside
    /// the object is read by no ray that does not cross a surface, or its neighbours, first.
    pub interior_exit: bool,
}

impl ViewFootprint {
    /// Whether a box grown by `reach` meets the view's cone.
    pub fn sees(&self, lo: DVec3, hi: DVec3) -> bool {
        let Some(planes) = self.planes.filter(|_| self.reach.is_finite()) else { return true };
        let (lo, hi) = (lo - self.reach, hi + self.reach);
        planes.iter().all(|(n, d)| {
            // The box's corner furthest along n.
            let p = DVec3::new(
                if n.x >= 0.0 { hi.x } else { lo.x },
                if n.y >= 0.0 { hi.y } else { lo.y },
                if n.z >= 0.0 { hi.z } else { lo.z },
            );
            n.dot(p) + d >= 0.0
        })
    }
}

/// The level a brick of level 0 at distance `d` from the eye is wanted at while moving: the
/// coarsest whose voxel (its smallest spacing) covers at most one pixel there.
pub fn footprint_level(layout: &BrickLayout, d: f64, pixel_angle: f64) -> usize {
    let pixel = d.max(0.0) * pixel_angle;
    let mut level = 0;
    for (l, lv) in layout.levels.iter().enumerate() {
        if lv.spacing.min_element() <= pixel {
            level = l;
        }
    }
    level
}

/// The bricks a view wants, nearest first, each at the level it is wanted at: every level-0 brick
/// that can hold the surface (`min < iso <= max`, where the ranges are known; every brick where
/// they are not), a brick wholly inside the object only where a ray may read it without crossing
/// a surface first (on the volume box's faces, the eye's, or every one where AO rays read inside
/// the object: not [`ViewFootprint::interior_exit`]), and the 26 neighbours of each (the
/// gradient's stencil, the march's step into the object and the cell walk of AO rays reach into
/// them), that the view can see
/// ([`ViewFootprint::sees`]), at level 0 when still or at [`footprint_level`] while moving. The
/// coarsest level, which the pool always holds, is not listed.
pub fn wanted_bricks(source: &dyn BrickSource, iso: f32, view: &ViewFootprint) -> Vec<BrickKey> {
    let layout = source.layout();
    let counts = layout.levels[0].counts;
    let n = layout.bricks(0);
    let mut wanted = vec![false; n];
    let ranges = source.ranges(0);
    let index = |b: [usize; 3]| b[0] + counts[0] * (b[1] + counts[1] * b[2]);
    let eye = view.planes.map(|_| layout.brick_at(0, view.eye));
    for key in layout.keys(0) {
        let i = layout.index(key);
        let b = key.brick.map(|v| v as usize);
        let on_box_face = (0..3).any(|a| b[a] == 0 || b[a] + 1 == counts[a]);
        let core = match ranges.map(|r| r[i]) {
            None => true,
            // Wholly inside the object: only where a ray can start in it without crossing a
            // surface first (the box's faces, the eye's brick), or where AO rays sample inside.
            Some([lo, _]) if lo >= iso => !view.interior_exit || on_box_face || eye == Some(key),
            Some([_, hi]) => hi >= iso,
        };
        if core {
            for dz in 0..3 {
                for dy in 0..3 {
                    for dx in 0..3 {
                        let c = [b[0] + dx, b[1] + dy, b[2] + dz];
                        if (0..3).all(|a| c[a] >= 1 && c[a] - 1 < counts[a]) {
                            wanted[index([c[0] - 1, c[1] - 1, c[2] - 1])] = true;
                        }
                    }
                }
            }
        }
    }
    let coarsest = layout.coarsest();
    let mut listed: Vec<(f64, BrickKey)> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for key in layout.keys(0).filter(|k| wanted[layout.index(*k)]) {
        let (lo, hi) = layout.brick_box(key);
        if !view.sees(lo, hi) {
            continue;
        }
        let d = view.eye.clamp(lo, hi).distance(view.eye);
        let level = if view.still { 0 } else { footprint_level(layout, d, view.pixel_angle) };
        if level >= coarsest {
            continue;
        }
        let centre = (lo + hi) * 0.5;
        let at = layout.brick_at(level, centre);
        if seen.insert(at) {
            listed.push((d, at));
        }
    }
    listed.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    listed.into_iter().map(|(_, k)| k).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedural::Procedural;

    fn sphere() -> Volume {
        Procedural::Sphere.generate(Some(64))
    }
    /// A sphere of radius 12 about the centre of the 64^3 volume.
    const ISO: f32 = 10.0;

    #[test]
    fn a_brick_holds_its_cells_samples_and_the_shared_far_face() {
        let v = sphere();
        let p = InCorePyramid::new(v.clone(), 16).unwrap();
        let layout = p.layout();
        assert_eq!(layout.levels[0].counts, [4, 4, 4], "63 cells in bricks of 16");
        let key = BrickKey { level: 0, brick: [1, 2, 3] };
        let b = p.read_brick(key).unwrap();
        assert_eq!(b.len(), 17 * 17 * 17);
        // Sample (i, j, k) of the brick is sample (16 + i, 32 + j, 48 + k), the far edge repeated.
        for (i, j, k) in [(0, 0, 0), (16, 16, 15), (3, 7, 16)] {
            let z = (48 + k).min(63);
            assert_eq!(b[i + 17 * (j + 17 * k)], v.at(16 + i, 32 + j, z), "{i} {j} {k}");
        }
        // The pyramid stops where a level fits one brick: 64, 32, 16.
        assert_eq!(layout.levels.len(), 3);
        assert_eq!(layout.levels[2].counts, [1, 1, 1]);
    }

    #[test]
    fn the_host_cache_stays_within_its_budget_and_evicts_the_least_recently_used() {
        let p = InCorePyramid::new(sphere(), 16).unwrap();
        let bytes = p.layout().brick_bytes();
        let mut cache = HostBrickCache::new(3 * bytes, p.layout()).unwrap();
        let k = |x| BrickKey { level: 0, brick: [x, 0, 0] };
        for x in 0..3 {
            cache.get(&p, k(x)).unwrap();
        }
        cache.get(&p, k(0)).unwrap(); // 0 is now the most recent, 1 the least
        cache.get(&p, k(3)).unwrap();
        assert!(cache.holds(k(0)) && !cache.holds(k(1)) && cache.holds(k(2)) && cache.holds(k(3)));
        let s = cache.stats();
        assert_eq!((s.hits, s.misses, s.evictions), (1, 4, 1));
        assert!(s.peak_bytes <= 3 * bytes);
        assert!(HostBrickCache::new(bytes - 1, p.layout()).is_err());
    }

    #[test]
    fn bricks_read_ahead_on_threads_are_the_ones_read_alone_and_stay_within_the_budget() {
        let p = InCorePyramid::new(sphere(), 16).unwrap();
        let bytes = p.layout().brick_bytes();
        let mut cache = HostBrickCache::new(3 * bytes, p.layout()).unwrap();
        let k = |x| BrickKey { level: 0, brick: [x, 1, 2] };
        cache.get(&p, k(0)).unwrap();
        // Four asked (one held, one twice): the three missing are read, as many as the budget
        // holds, and evict the one held before.
        cache.prefetch(&p, &[k(0), k(1), k(2), k(1), k(3)], 2).unwrap();
        assert!(cache.holds(k(1)) && cache.holds(k(2)) && cache.holds(k(3)) && !cache.holds(k(0)));
        let s = cache.stats();
        assert_eq!((s.misses, s.evictions), (4, 1));
        assert!(s.peak_bytes <= 3 * bytes);
        for x in 1..4 {
            assert_eq!(*cache.get(&p, k(x)).unwrap(), p.read_brick(k(x)).unwrap(), "brick {x}");
        }
        assert_eq!(cache.stats().misses, 4, "the gets found what was read ahead");
    }

    #[test]
    fn a_still_view_wants_every_brick_near_the_object_at_level_0_nearest_first() {
        let p = InCorePyramid::new(sphere(), 8).unwrap();
        let layout = p.layout();
        let eye = DVec3::new(31.5, 31.5, 100.0);
        let still = wanted_bricks(
            &p,
            ISO,
            &ViewFootprint {
                eye,
                pixel_angle: 1e-3,
                still: true,
                planes: None,
                reach: 0.0,
                interior_exit: false,
            },
        );
        assert!(still.iter().all(|k| k.level == 0));
        // Every brick whose max >= iso is wanted, and none is listed twice.
        let ranges = p.ranges(0).unwrap();
        for key in layout.keys(0).filter(|k| ranges[layout.index(*k)][1] >= ISO) {
            assert!(still.contains(&key), "{key:?}");
        }
        let set: std::collections::HashSet<_> = still.iter().collect();
        assert_eq!(set.len(), still.len());
        let d = |k: &BrickKey| {
            let (lo, hi) = layout.brick_box(*k);
            eye.clamp(lo, hi).distance(eye)
        };
        assert!(still.windows(2).all(|w| d(&w[0]) <= d(&w[1])), "nearest first");
        // Far away and moving, a coarser level is enough.
        // Exactly the bricks within one brick (26-neighbourhood) of one whose max >= iso.
        let core: Vec<BrickKey> = layout.keys(0).filter(|k| ranges[layout.index(*k)][1] >= ISO).collect();
        let near = |k: &BrickKey| core.iter().any(|c| (0..3).all(|a| c.brick[a].abs_diff(k.brick[a]) <= 1));
        assert_eq!(still.len(), layout.keys(0).filter(near).count());
        assert!(still.iter().all(near));
        assert!(core.len() < still.len() && still.len() < layout.bricks(0), "{} {}", core.len(), still.len());
        // Far away and moving, a coarser level is enough: level 2's voxel (4 units) is under
        // the 5 units a pixel covers 500 units away.
        let eye = DVec3::new(31.5, 31.5, 500.0);
        let far = wanted_bricks(
            &p,
            ISO,
            &ViewFootprint {
                eye,
                pixel_angle: 1e-2,
                still: false,
                planes: None,
                reach: 0.0,
                interior_exit: false,
            },
        );
        assert!(!far.is_empty() && far.iter().all(|k| k.level == 2), "{far:?}");
        assert!(far.len() <= layout.bricks(2));
    }
}
