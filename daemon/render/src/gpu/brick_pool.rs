//! The brick cache's GPU side (DESIGN.md "Large volumes"): a fixed pool of bricks and the page
//! tables that say which brick of which level each slot holds, in one storage buffer the volume
//! kernels read through `bricked_trilinear` / `bricked_sample` (shaders/volume.wgsl, compiled
//! with `BRICKED`). The bricks come from a [`BrickSource`] through a [`HostBrickCache`]
//! (daemon/volume/src/brick_cache.rs).
//!
//! The buffer, in 32-bit words: a header (levels, log2 of the cells per brick edge, samples per
//! brick edge, the pool's first word), 16 words of directory per level (dims and the page table's
//! first word; brick counts; and the map from level-0 voxel coordinates to the level's, as scale
//! and offset), the page tables (one word a brick: 0 where not resident, else its slot + 1), then
//! the pool's slots. Its size is fixed when the pool is made, from the GPU budget: nothing grows.
//! The coarsest level is pinned in the first slots, so every lookup finds a level.
//!
//! Empty-space skipping reads the block levels a whole volume has (`PerfOptions::block` for every
//! ray, `PerfOptions::ao_block` and `PerfOptions::coarse` for AO rays; the AO rays' own level only
//! where its min/max take at most an eighth of the GPU budget: at blocks of 4 they are 1/64 of
//! level 0's voxels' bytes), over level 0: a block's range is the union, over the level-0
//! bricks its samples lie in, of the exact range of those samples where the brick is resident and
//! of the brick's range where not (the source's, or unbounded where the source does not know it).
//! Skipping is thus conservative before refinement and, once the bricks a view wants are
//! resident, decides as the whole volume's levels do (a brick that is not wanted has max < iso,
//! so its blocks are skipped by both), which keeps the march's steps, and so the picture, the
//! same.

use super::resources::{brick_marks, next_resource_id, BlockLevel, MarchTexture};
use super::{GpuContext, GpuError, GpuRenderer, GpuVolume, PerfOptions};
use crate::Frame;
use isowall_model::camera::Rect;
use isowall_model::{RenderSettings, View};
use isowall_volume::brick_cache::{
    wanted_bricks, BrickKey, BrickLayout, BrickSource, HostBrickCache, ViewFootprint,
};
use isowall_volume::VoxelFormat;
use std::collections::{HashMap, HashSet};

/// The most bytes of bricks a round stages for the GPU before it waits for them to be written.
const STAGED_BYTES: u64 = 16 << 20;

/// Words before the first level's directory entry.
const HEADER_WORDS: usize = 4;
/// Words of one level's directory entry.
const LEVEL_WORDS: usize = 16;

/// What the pool has done since it was made.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PoolStats {
    /// Bricks written into the pool, and their bytes.
    pub uploads: u64,
    pub upload_bytes: u64,
    /// Bricks dropped from the pool to make room.
    pub evictions: u64,
    /// Wanted bricks found resident.
    pub hits: u64,
}

/// One round of [`BrickPool::refine`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Refinement {
    /// Bricks the round was asked for, and how many of them are resident after it.
    pub wanted: usize,
    pub resident: usize,
    /// Bricks uploaded in this round, and their bytes.
    pub uploaded: usize,
    pub upload_bytes: u64,
    /// Wanted bricks left out because the pool holds no slot that this round does not want:
    /// the view's set is larger than the pool.
    pub over_pool: usize,
}

impl Refinement {
    /// Every wanted brick is resident.
    pub fn complete(&self) -> bool {
        self.resident == self.wanted
    }
}

/// A fixed pool of bricks on the GPU and its page tables, with the [`GpuVolume`] the kernels bind.
pub struct BrickPool {
    layout: BrickLayout,
    volume: GpuVolume,
    /// The page tables, as on the GPU (every level's, in order).
    pages: Vec<u32>,
    /// Each level's page table's first word within `pages`.
    page_base: Vec<usize>,
    /// The buffer's word where `pages` starts, and the pool's first word.
    pages_word: usize,
    pool_word: usize,
    /// Per slot: the brick it holds and when it was last wanted (round number).
    slots: Vec<Option<(BrickKey, u64)>>,
    resident: HashMap<BrickKey, usize>,
    /// Slots `0..pinned` hold the coarsest level.
    pinned: usize,
    round: u64,
    stats: PoolStats,
    /// Bytes of the buffer and of the block min/max: what the pool holds on the GPU.
    bytes: u64,
    bounds: BlockBounds,
    /// A level-0 brick came or went since the block levels were last written.
    bounds_dirty: bool,
    /// Words of the brick marks, and the coarse level's index in `bounds` where there is one.
    marks_words: usize,
    coarse_bounds: Option<usize>,
}

impl BrickPool {
    /// A pool within `budget` bytes of GPU memory (its buffer and the level-0 bricks' min/max)
    /// for `source`'s pyramid, with the coarsest level uploaded (through `cache`) and pinned.
    /// Refused where the budget cannot hold the coarsest level and one more brick, or the
    /// adapter's storage binding cannot.
    pub fn new(
        ctx: &GpuContext,
        perf: &PerfOptions,
        source: &dyn BrickSource,
        cache: &mut HostBrickCache,
        budget: u64,
    ) -> Result<BrickPool, GpuError> {
        let layout = source.layout().clone();
        // The block levels a whole volume has: every ray's, the AO rays' own where its min/max
        // take at most an eighth of the budget (1/64 of level 0's voxels' bytes at blocks of 4),
        // and the coarse one.
        let l0_blocks = |c: u32| -> u64 {
            layout.levels[0].dims.iter().map(|&n| ((n.max(2) - 1) as u64).div_ceil(u64::from(c))).product()
        };
        let ao =
            (perf.ao_block > 0 && perf.ao_block != perf.block && 8 * l0_blocks(perf.ao_block) <= budget / 8)
                .then_some(perf.ao_block);
        let coarse = (perf.coarse > 0).then_some(perf.coarse);
        let cells: Vec<usize> =
            [Some(perf.block), ao, coarse].into_iter().flatten().map(|c| c as usize).collect();
        let name = source.name().to_string();
        let levels = layout.levels.len();
        let mut page_base = Vec::with_capacity(levels);
        let mut n = 0;
        for l in 0..levels {
            page_base.push(n);
            n += layout.bricks(l);
        }
        let pages_word = HEADER_WORDS + LEVEL_WORDS * levels;
        let pool_word = pages_word + n;
        let brick_words = layout.brick_voxels();
        // Counted before anything is allocated: a store's pyramid may be far larger than the budget.
        // The marks: a bit per level-0 brick, then one per block of the coarse level.
        let marks_words = mark_words(&layout) + coarse.map_or(0, |c| l0_blocks(c).div_ceil(32) as usize);
        let minmax_bytes =
            8 * cells.iter().map(|&c| l0_blocks(c as u32)).sum::<u64>() + 4 * marks_words as u64;
        let fixed = 4 * pool_word as u64 + minmax_bytes;
        let limit = super::storage_binding_limit(&ctx.device.limits());
        let by_budget = budget.saturating_sub(fixed) / layout.brick_bytes();
        let by_binding = (limit / 4).saturating_sub(pool_word as u64) / brick_words as u64;
        let slots = by_budget.min(by_binding) as usize;
        let pinned = layout.bricks(layout.coarsest());
        if slots <= pinned {
            let why = if by_binding < by_budget { "the adapter's storage binding" } else { "the GPU budget" };
            return Err(GpuError::Settings(format!(
                "{name}: {why} holds {slots} bricks of {} bytes ({}^3 samples) after the page tables, but the coarsest level alone is {pinned} (a budget of at least {} bytes is needed)",
                layout.brick_bytes(),
                layout.samples(),
                fixed + (pinned as u64 + 1) * layout.brick_bytes()
            )));
        }
        if by_binding < by_budget {
            tracing::warn!(
                "{name}: the brick pool holds {slots} bricks, what one storage binding of {limit} bytes holds, not the {by_budget} of the GPU budget"
            );
        }
        let words = pool_word + slots * brick_words;
        let bounds = BlockBounds::new(&layout, source, &cells);
        let mut head = vec![0u32; pool_word];
        head[0] = levels as u32;
        head[1] = layout.cells.trailing_zeros();
        head[2] = layout.samples() as u32;
        head[3] = pool_word as u32;
        let l0 = &layout.levels[0];
        for (l, lv) in layout.levels.iter().enumerate() {
            let w = HEADER_WORDS + LEVEL_WORDS * l;
            // Level-0 voxel coordinates u map to the level's as (u * s0 + o0 - o) / s.
            let scale = l0.spacing / lv.spacing;
            let offset = (l0.origin - lv.origin) / lv.spacing;
            head[w..w + 3].copy_from_slice(&lv.dims.map(|d| d as u32));
            head[w + 3] = (pages_word + page_base[l]) as u32;
            head[w + 4..w + 7].copy_from_slice(&lv.counts.map(|c| c as u32));
            for a in 0..3 {
                head[w + 8 + a] = (scale[a] as f32).to_bits();
                head[w + 12 + a] = (offset[a] as f32).to_bits();
            }
        }
        let label = format!("brick pool of {name}");
        let voxels = ctx.validated("upload", || {
            ctx.create_buffer(&wgpu::BufferDescriptor {
                label: Some(&label),
                size: 4 * words as u64,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        })?;
        ctx.write_buffer(&voxels, 0, bytemuck::cast_slice(&head));
        let minmax = bounds.all.clone();
        let block_minmax = ctx.storage_init("brick min/max", bytemuck::cast_slice(&minmax))?;
        let (lo, hi) = source.value_range().unwrap_or((0.0, 0.0));
        let level = |k: usize| BlockLevel {
            counts: bounds.levels[k].counts.map(|c| c as u32),
            cells: bounds.levels[k].cells as u32,
            offset: bounds.levels[k].offset as u32,
        };
        let ao_level = ao.map(|_| level(1));
        let coarse_level = coarse.map(|_| level(cells.len() - 1));
        let (box_min, box_max) = (l0.origin, l0.box_max());
        let volume = GpuVolume {
            id: next_resource_id(),
            voxels,
            block_minmax,
            brick_marks: brick_marks(ctx, marks_words)?,
            marking: false,
            march: MarchTexture::new(ctx, &name, None)?,
            format: VoxelFormat::R32F,
            value_range: (lo, hi),
            voxel_bytes: 4 * words as u64,
            minmax_bytes,
            dims: l0.dims.map(|d| d as u32),
            block: bounds.levels[0].cells as u32,
            counts: bounds.levels[0].counts.map(|c| c as u32),
            ao_level,
            coarse_level,
            spacing: l0.spacing,
            box_min,
            box_max,
            name,
            object: None,
            bricked: true,
        };
        let mut pool = BrickPool {
            pages: vec![0; n],
            page_base,
            pages_word,
            pool_word,
            slots: vec![None; slots],
            resident: HashMap::new(),
            pinned,
            round: 0,
            stats: PoolStats::default(),
            bytes: 4 * words as u64 + minmax_bytes,
            volume,
            layout,
            bounds,
            bounds_dirty: false,
            marks_words,
            coarse_bounds: coarse.map(|_| cells.len() - 1),
        };
        let coarsest: Vec<BrickKey> = pool.layout.keys(pool.layout.coarsest()).collect();
        for (slot, key) in coarsest.into_iter().enumerate() {
            pool.upload(ctx, source, cache, key, slot)?;
        }
        pool.write_pages(ctx);
        Ok(pool)
    }

    /// The volume the kernels bind (its `id` changes whenever what it holds changes, so that a
    /// tile's accumulated samples start over).
    pub fn volume(&self) -> &GpuVolume {
        &self.volume
    }

    pub fn layout(&self) -> &BrickLayout {
        &self.layout
    }

    pub fn stats(&self) -> PoolStats {
        self.stats
    }

    /// Slots in the pool, the coarsest level's included.
    pub fn slots(&self) -> usize {
        self.slots.len()
    }

    /// Slots beside the pinned coarsest level: the most bricks one resident set can have.
    pub fn free_slots(&self) -> usize {
        self.slots.len() - self.pinned
    }

    /// Bytes the pool holds on the GPU: within the budget it was made with.
    pub fn gpu_bytes(&self) -> u64 {
        self.bytes
    }

    /// Whether `key` is resident.
    pub fn holds(&self, key: BrickKey) -> bool {
        self.resident.contains_key(&key)
    }

    /// Makes the bricks of `wanted` (most important first) resident, uploading at most
    /// `upload_cap` bytes in this round (at least one brick, so that refinement always moves).
    /// Room is made by evicting the bricks wanted longest ago, never one this round wants nor
    /// the pinned coarsest level; where none is left, the rest of `wanted` waits
    /// ([`Refinement::over_pool`]).
    pub fn refine(
        &mut self,
        ctx: &GpuContext,
        source: &dyn BrickSource,
        cache: &mut HostBrickCache,
        wanted: &[BrickKey],
        upload_cap: u64,
    ) -> Result<Refinement, GpuError> {
        self.round += 1;
        let round = self.round;
        let unique: HashSet<BrickKey> = wanted.iter().copied().collect();
        let mut r = Refinement { wanted: unique.len(), ..Refinement::default() };
        for key in wanted {
            if let Some(&slot) = self.resident.get(key) {
                self.slots[slot] = Some((*key, round));
                self.stats.hits += 1;
            }
        }
        let brick = self.layout.brick_bytes();
        // The round's uploads read from the source in parallel first (their host cache misses):
        // as many as its cap and the slots this round does not want can take.
        let room = (self.pinned..self.slots.len())
            .filter(|&s| self.slots[s].is_none_or(|(_, used)| used < round))
            .count() as u64;
        let to_upload: Vec<BrickKey> = wanted
            .iter()
            .copied()
            .filter(|k| !self.resident.contains_key(k))
            .take((upload_cap / brick).max(1).min(room) as usize)
            .collect();
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        cache
            .prefetch(source, &to_upload, threads)
            .map_err(|e| GpuError::Settings(format!("bricks of {}: {e}", source.name())))?;
        let mut changed = false;
        let mut staged = 0;
        for &key in wanted {
            if self.resident.contains_key(&key) {
                continue;
            }
            if r.uploaded > 0 && r.upload_bytes + brick > upload_cap {
                break;
            }
            let free = (self.pinned..self.slots.len())
                .filter(|&s| self.slots[s].is_none_or(|(_, used)| used < round))
                .min_by_key(|&s| self.slots[s].map_or(0, |(_, used)| used + 1));
            let Some(slot) = free else {
                r.over_pool += 1;
                continue;
            };
            if let Some((old, _)) = self.slots[slot].take() {
                self.resident.remove(&old);
                let i = self.page_index(old);
                self.pages[i] = 0;
                self.stats.evictions += 1;
                if old.level == 0 {
                    self.bounds.brick_changed(old.brick, None);
                    self.bounds_dirty = true;
                }
            }
            self.upload(ctx, source, cache, key, slot)?;
            self.slots[slot] = Some((key, round));
            r.uploaded += 1;
            r.upload_bytes += brick;
            changed = true;
            // Each write is staged in host memory until a submission carries it: a round of a
            // still frame may upload the whole pool, so the staged bytes are bounded.
            staged += brick;
            if staged >= STAGED_BYTES {
                staged = 0;
                ctx.queue.submit([]);
                ctx.wait()?;
            }
        }
        if changed {
            self.write_pages(ctx);
        }
        r.resident = unique.iter().filter(|k| self.resident.contains_key(k)).count();
        Ok(r)
    }

    fn page_index(&self, key: BrickKey) -> usize {
        self.page_base[key.level as usize] + self.layout.index(key)
    }

    /// Reads `key` (through the host cache) into `slot`, and notes it (the page table is written
    /// by the caller).
    fn upload(
        &mut self,
        ctx: &GpuContext,
        source: &dyn BrickSource,
        cache: &mut HostBrickCache,
        key: BrickKey,
        slot: usize,
    ) -> Result<(), GpuError> {
        let data = cache
            .get(source, key)
            .map_err(|e| GpuError::Settings(format!("brick {key:?} of {}: {e}", source.name())))?;
        let words = self.layout.brick_voxels();
        let at = 4 * (self.pool_word + slot * words) as u64;
        ctx.write_buffer(&self.volume.voxels, at, bytemuck::cast_slice(data.as_slice()));
        if key.level == 0 {
            self.bounds.brick_changed(key.brick, Some(data.as_slice()));
            self.bounds_dirty = true;
        }
        self.slots[slot] = Some((key, self.round));
        self.resident.insert(key, slot);
        let i = self.page_index(key);
        self.pages[i] = slot as u32 + 1;
        self.stats.uploads += 1;
        self.stats.upload_bytes += self.layout.brick_bytes();
        Ok(())
    }

    /// Clears the brick marks and has the kernels' frames after this mark the level-0 bricks
    /// their rays read ([`BrickPool::read_marks`]), until [`BrickPool::stop_marking`].
    pub fn clear_marks(&mut self, ctx: &GpuContext) {
        self.volume.marking = true;
        ctx.write_buffer(&self.volume.brick_marks, 0, &vec![0u8; 4 * self.marks_words]);
    }

    /// The level-0 bricks the rays of the frames since [`BrickPool::clear_marks`] read or relied
    /// on the min/max of (shaders/volume.wgsl, `mark_level0_brick`), resident or not; of a coarse
    /// block they did not skip, its bricks that are not resident and whose range reaches `iso`
    /// (`mark_coarse_block`). Waits for the GPU.
    pub fn read_marks(&self, ctx: &GpuContext, iso: f32) -> Result<Vec<BrickKey>, GpuError> {
        let marks = &self.volume.brick_marks;
        let staging = ctx.validated("brick marks readback", || {
            ctx.buffer(
                "brick marks",
                marks.size(),
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            )
        })?;
        let mut enc =
            ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("brick marks") });
        enc.copy_buffer_to_buffer(marks, 0, &staging, 0, None);
        ctx.queue.submit([enc.finish()]);
        let (bytes, _) = super::read_buffers(ctx, std::slice::from_ref(&staging))?;
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes[0]);
        let set = |first: usize, i: usize| words[first + (i >> 5)] & (1 << (i & 31)) != 0;
        let counts = self.layout.levels[0].counts;
        let key = |i: usize| BrickKey { level: 0, brick: unflatten(i, counts).map(|v| v as u32) };
        let mut marked: std::collections::BTreeSet<BrickKey> =
            (0..self.layout.bricks(0)).filter(|&i| set(0, i)).map(key).collect();
        if let Some(k) = self.coarse_bounds {
            let first = mark_words(&self.layout);
            for j in (0..self.bounds.blocks(k)).filter(|&j| set(first, j)) {
                for i in self.bounds.bricks_of_block(k, j) {
                    if !self.holds(key(i)) && self.bounds.brick_bound[i][1] >= iso {
                        marked.insert(key(i));
                    }
                }
            }
        }
        Ok(marked.into_iter().collect())
    }

    /// The kernels' frames after this mark nothing (the marks stay as they are until cleared).
    pub fn stop_marking(&mut self) {
        self.volume.marking = false;
    }

    /// Writes the page tables, and the block levels where they changed.
    fn write_pages(&mut self, ctx: &GpuContext) {
        ctx.write_buffer(&self.volume.voxels, 4 * self.pages_word as u64, bytemuck::cast_slice(&self.pages));
        // The block levels only where level 0 changed, each level's span of changed blocks (the
        // whole volume's levels are O(voxels / 512)).
        if std::mem::take(&mut self.bounds_dirty) {
            for (first, values) in self.bounds.take_dirty() {
                ctx.write_buffer(&self.volume.block_minmax, 8 * first as u64, bytemuck::cast_slice(values));
            }
        }
        self.volume.id = next_resource_id();
    }
}

/// Words of a pyramid's brick marks: a bit per level-0 brick.
fn mark_words(layout: &BrickLayout) -> usize {
    layout.bricks(0).div_ceil(32)
}

/// A block level over level 0 ([`BlockBounds`]).
struct BoundLevel {
    cells: usize,
    counts: [usize; 3],
    /// Its first block in [`BlockBounds::all`].
    offset: usize,
    /// The blocks written since the GPU's copy was: the lowest and highest index.
    dirty: Option<(usize, usize)>,
}

/// The block levels of empty-space skipping over level 0, kept as the module says.
struct BlockBounds {
    levels: Vec<BoundLevel>,
    /// Every level's min/max, in order (the GPU's `block_minmax`).
    all: Vec<[f32; 2]>,
    /// Level 0's samples on each axis, cells per brick and bricks.
    dims: [usize; 3],
    brick_cells: usize,
    brick_counts: [usize; 3],
    /// Each level-0 brick's range where it is not resident.
    brick_bound: Vec<[f32; 2]>,
    /// Per resident level-0 brick, per level: the exact range of the samples within the brick
    /// of each block its cells meet ([`BlockBounds::blocks_of_brick`], x fastest).
    partial: HashMap<[u32; 3], Vec<Vec<[f32; 2]>>>,
}

/// On one axis: the indices `i` of cells-`c` spans (cells `i*c .. (i+1)*c`, `count` of them)
/// whose cells meet the cells `lo .. hi` (at least cell `lo`). A span's samples `i*c ..= (i+1)*c`
/// are those of its cells, so a block's samples are all in the bricks holding its cells (a brick
/// holds its far face), and a brick's in the blocks holding its cells: the rule the kernels'
/// `mark_block` follows (shaders/volume.wgsl).
fn spans_meeting(c: usize, count: usize, lo: usize, hi: usize) -> std::ops::RangeInclusive<usize> {
    let first = (lo / c).min(count - 1);
    let last = (hi.max(lo + 1) - 1) / c;
    first..=last.min(count - 1)
}

type Span3 = [std::ops::RangeInclusive<usize>; 3];

/// Linear index `i` (x fastest) of a grid of `counts` as its indices on x, y, z.
fn unflatten(i: usize, counts: [usize; 3]) -> [usize; 3] {
    [i % counts[0], (i / counts[0]) % counts[1], i / (counts[0] * counts[1])]
}

/// Index of `b` within the box `r` (x fastest).
fn local_index(r: &Span3, b: [usize; 3]) -> usize {
    let n = |a: usize| r[a].end() - r[a].start() + 1;
    (b[0] - r[0].start()) + n(0) * ((b[1] - r[1].start()) + n(1) * (b[2] - r[2].start()))
}

impl BlockBounds {
    fn new(layout: &BrickLayout, source: &dyn BrickSource, cells: &[usize]) -> BlockBounds {
        let l0 = &layout.levels[0];
        let mut offset = 0;
        let levels = cells
            .iter()
            .map(|&c| {
                let counts = l0.dims.map(|n| (n.max(2) - 1).div_ceil(c));
                let level = BoundLevel { cells: c, counts, offset, dirty: None };
                offset += counts.iter().product::<usize>();
                level
            })
            .collect();
        let brick_bound = match source.ranges(0) {
            Some(r) => r.to_vec(),
            None => vec![[f32::MIN, f32::MAX]; layout.bricks(0)],
        };
        let mut b = BlockBounds {
            levels,
            all: vec![[0.0; 2]; offset],
            dims: l0.dims,
            brick_cells: layout.cells,
            brick_counts: l0.counts,
            brick_bound,
            partial: HashMap::new(),
        };
        for k in 0..b.levels.len() {
            for j in 0..b.blocks(k) {
                b.recompute(k, j);
            }
            b.levels[k].dirty = None;
        }
        b
    }

    fn blocks(&self, k: usize) -> usize {
        self.levels[k].counts.iter().product()
    }

    /// The blocks of level k a level-0 brick's cells meet, as a box of indices per axis.
    fn blocks_of_brick(&self, k: usize, brick: [u32; 3]) -> Span3 {
        let (c, bc) = (self.levels[k].cells, self.brick_cells);
        std::array::from_fn(|a| {
            let lo = brick[a] as usize * bc;
            let hi = ((brick[a] as usize + 1) * bc).min(self.dims[a].max(2) - 1);
            spans_meeting(c, self.levels[k].counts[a], lo, hi)
        })
    }

    /// The level-0 bricks (linear indices) holding the cells of block j of level k: those its
    /// min/max is made of.
    fn bricks_of_block(&self, k: usize, j: usize) -> impl Iterator<Item = usize> + '_ {
        let l = &self.levels[k];
        let b = unflatten(j, l.counts);
        let [rx, ry, rz]: [_; 3] = std::array::from_fn(|a| {
            let lo = b[a] * l.cells;
            let hi = ((b[a] + 1) * l.cells).min(self.dims[a].max(2) - 1);
            spans_meeting(self.brick_cells, self.brick_counts[a], lo, hi)
        });
        let [bx, by] = [self.brick_counts[0], self.brick_counts[1]];
        rz.flat_map(move |z| {
            let rx = rx.clone();
            ry.clone().flat_map(move |y| rx.clone().map(move |x| x + bx * (y + by * z)))
        })
    }

    /// Recomputes block j of level k from its bricks.
    fn recompute(&mut self, k: usize, j: usize) {
        let b = unflatten(j, self.levels[k].counts);
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for i in self.bricks_of_block(k, j) {
            let key = unflatten(i, self.brick_counts).map(|v| v as u32);
            let m = match self.partial.get(&key) {
                Some(p) => p[k][local_index(&self.blocks_of_brick(k, key), b)],
                None => self.brick_bound[i],
            };
            lo = lo.min(m[0]);
            hi = hi.max(m[1]);
        }
        let l = &mut self.levels[k];
        self.all[l.offset + j] = [lo, hi];
        l.dirty = Some(l.dirty.map_or((j, j), |(a, z)| (a.min(j), z.max(j))));
    }

    /// A level-0 brick became resident with `data` (its samples), or (`None`) left. Each level's
    /// blocks within the brick are the finest level's (read from the samples) merged where a
    /// level's cells are a multiple of a finer one's: a block's samples within the brick are
    /// the union of its finer blocks' there.
    fn brick_changed(&mut self, brick: [u32; 3], data: Option<&[f32]>) {
        match data {
            Some(d) => {
                let mut order: Vec<usize> = (0..self.levels.len()).collect();
                order.sort_by_key(|&k| self.levels[k].cells);
                let mut parts: Vec<Vec<[f32; 2]>> = vec![Vec::new(); self.levels.len()];
                for (n, &k) in order.iter().enumerate() {
                    let finer = order[..n]
                        .iter()
                        .rev()
                        .copied()
                        .find(|&m| self.levels[k].cells.is_multiple_of(self.levels[m].cells));
                    parts[k] = match finer {
                        Some(m) => self.merged(brick, k, m, &parts[m]),
                        None => self.read_from_samples(brick, k, d),
                    };
                }
                self.partial.insert(brick, parts);
            }
            None => {
                self.partial.remove(&brick);
            }
        }
        for k in 0..self.levels.len() {
            let [rx, ry, rz] = self.blocks_of_brick(k, brick);
            let counts = self.levels[k].counts;
            for bz in rz {
                for by in ry.clone() {
                    for bx in rx.clone() {
                        self.recompute(k, bx + counts[0] * (by + counts[1] * bz));
                    }
                }
            }
        }
    }

    /// Level k's blocks within `brick`, from its samples `d`.
    fn read_from_samples(&self, brick: [u32; 3], k: usize, d: &[f32]) -> Vec<[f32; 2]> {
        let s = self.brick_cells + 1;
        let origin = brick.map(|b| b as usize * self.brick_cells);
        let c = self.levels[k].cells;
        let [rx, ry, rz] = self.blocks_of_brick(k, brick);
        // The block's samples within the brick, in the brick's indices.
        let span = |a: usize, b: usize| {
            let lo = (b * c).max(origin[a]);
            let hi = ((b + 1) * c).min(origin[a] + self.brick_cells).min(self.dims[a] - 1);
            (lo - origin[a])..=(hi - origin[a])
        };
        let mut out = Vec::new();
        for bz in rz {
            for by in ry.clone() {
                for bx in rx.clone() {
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for z in span(2, bz) {
                        for y in span(1, by) {
                            let row = s * (y + s * z);
                            for &v in &d[row + *span(0, bx).start()..=row + *span(0, bx).end()] {
                                lo = lo.min(v);
                                hi = hi.max(v);
                            }
                        }
                    }
                    out.push([lo, hi]);
                }
            }
        }
        out
    }

    /// Level k's blocks within `brick`, merged from level m's there (`finer`; m's cells divide k's).
    fn merged(&self, brick: [u32; 3], k: usize, m: usize, finer: &[[f32; 2]]) -> Vec<[f32; 2]> {
        let ratio = self.levels[k].cells / self.levels[m].cells;
        let fine = self.blocks_of_brick(m, brick);
        let [rx, ry, rz] = self.blocks_of_brick(k, brick);
        let mut out = Vec::new();
        for bz in rz {
            for by in ry.clone() {
                for bx in rx.clone() {
                    let b = [bx, by, bz];
                    // The finer blocks of this one that meet the brick's cells.
                    let r: Span3 = std::array::from_fn(|a| {
                        (b[a] * ratio).max(*fine[a].start())..=((b[a] + 1) * ratio - 1).min(*fine[a].end())
                    });
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for z in r[2].clone() {
                        for y in r[1].clone() {
                            for x in r[0].clone() {
                                let m = finer[local_index(&fine, [x, y, z])];
                                lo = lo.min(m[0]);
                                hi = hi.max(m[1]);
                            }
                        }
                    }
                    out.push([lo, hi]);
                }
            }
        }
        out
    }

    /// Each level's blocks written since the last call, as spans of `all` (offset, values).
    fn take_dirty(&mut self) -> Vec<(usize, &[[f32; 2]])> {
        let mut spans = Vec::new();
        for l in &mut self.levels {
            if let Some((a, z)) = l.dirty.take() {
                spans.push((l.offset + a, l.offset + z + 1));
            }
        }
        spans.into_iter().map(|(a, z)| (a, &self.all[a..z])).collect()
    }
}

/// What a view of a bricked volume asks of the cache ([`wanted_bricks`]): its eye, pixel size,
/// cone, and how far its rays can read outside the cone (the AO radius and offset, and two
/// voxels for the gradient's stencil and the AO walk's cells; unbounded AO: nothing culled;
/// without AO samples no AO ray is cast, the two voxels alone).
pub fn footprint(
    view: &View,
    settings: &RenderSettings,
    perf: &PerfOptions,
    spacing: glam::DVec3,
    still: bool,
) -> ViewFootprint {
    let c = &view.camera;
    let pixel_angle = 2.0 * (c.fov_y_deg.to_radians() / 2.0).tan() / f64::from(view.full.1.max(1));
    let voxel = spacing.max_element();
    let reach = match settings.ao.radius_world(spacing) {
        _ if settings.ao.samples == 0 => 2.0 * voxel,
        Some(r) => r + (settings.ao.offset_voxels + settings.ao.step_voxels + 2.0) * voxel,
        None => f64::INFINITY,
    };
    ViewFootprint {
        eye: c.eye,
        pixel_angle,
        still,
        planes: Some(view.side_planes()),
        reach,
        interior_exit: perf.block_min_exit,
    }
}

/// The bricks `views` want together: each view's [`wanted_bricks`] (from its [`footprint`]), the
/// lists taken in turn so that every view's nearest come first, each brick once. The views of a
/// node's tiles, so that its pool holds what its tiles see.
pub fn wanted_by_views(
    source: &dyn BrickSource,
    views: &[View],
    settings: &RenderSettings,
    perf: &PerfOptions,
    still: bool,
) -> Vec<BrickKey> {
    let spacing = source.layout().levels[0].spacing;
    let lists: Vec<Vec<BrickKey>> = views
        .iter()
        .map(|v| wanted_bricks(source, settings.iso as f32, &footprint(v, settings, perf, spacing, still)))
        .collect();
    let mut seen = HashSet::new();
    let longest = lists.iter().map(Vec::len).max().unwrap_or(0);
    (0..longest)
        .flat_map(|k| lists.iter().filter_map(move |l| l.get(k).copied()))
        .filter(|key| seen.insert(*key))
        .collect()
}

/// A still frame rendered through a pool ([`GpuRenderer::render_converged`]).
pub struct Converged {
    pub frame: Frame,
    /// GPU time of the rounds' frames.
    pub gpu_time: std::time::Duration,
    /// Screen regions the frame was finished in (1: the pool held the whole view's bricks).
    pub passes: usize,
    /// The most level-0 bricks the kept frame of one pass read.
    pub most_wanted: usize,
    /// Ray-guided rounds: the frames rendered, each pass's last (the one kept) included.
    pub rounds: usize,
    /// Time spent loading the rounds' bricks: reading them (through the host cache), uploading
    /// them and updating the page tables and block levels.
    pub loading: std::time::Duration,
}

impl GpuRenderer {
    /// The still frame of `view` of `pool`'s volume with every brick it reads at level 0: the
    /// whole volume's frame (DESIGN.md "Large volumes"), found by ray-guided rounds. Each round
    /// renders the region (all `frames`, as the kept frame would be) and reads back the level-0
    /// bricks its rays read or relied on the min/max of (`brick_marks`); where all of them are
    /// resident the round's frame is kept, else they are loaded and the region rendered again.
    /// The set grows only with what rays read, so a round never loads a brick behind the
    /// first hits it finds. Where a region's bricks outgrow the pool beside its pinned coarsest
    /// level, the region is halved along its longer side and each half finished in its own pass
    /// (a pixel is the same whichever rectangle renders it; with the filter on, a region is
    /// rendered with the filter's guard band and cut back). Refused only where one pixel's
    /// bricks exceed the pool.
    #[allow(clippy::too_many_arguments)]
    pub fn render_converged(
        &self,
        pool: &mut BrickPool,
        source: &dyn BrickSource,
        cache: &mut HostBrickCache,
        view: &View,
        settings: &RenderSettings,
        env: Option<&super::GpuEnvironment>,
        frames: u32,
    ) -> Result<Converged, GpuError> {
        self.prepare(pool.volume())?;
        let free = pool.free_slots();
        let guard = if settings.denoise.is_on() { crate::denoise::reach() } else { 0 };
        let mut frame = Frame::new(view.rect.width, view.rect.height);
        let mut done = Converged {
            frame: Frame::new(0, 0),
            gpu_time: std::time::Duration::ZERO,
            passes: 0,
            most_wanted: 0,
            rounds: 0,
            loading: std::time::Duration::ZERO,
        };
        let spacing = pool.layout().levels[0].spacing;
        // Each region with the bricks the rays of the region it was cut from read (none for the
        // whole view): the part of them its own cone can reach is loaded before its first round.
        let mut regions: Vec<(Rect, std::rc::Rc<Vec<BrickKey>>)> = vec![(view.rect, Default::default())];
        while let Some((rect, hint)) = regions.pop() {
            let grown = View { rect: rect.grown(guard, view.full), ..*view };
            let fp = footprint(&grown, settings, &self.perf, spacing, true);
            let layout = pool.layout();
            let predicted: Vec<BrickKey> = hint
                .iter()
                .copied()
                .filter(|k| {
                    let (lo, hi) = layout.brick_box(*k);
                    fp.sees(lo, hi)
                })
                .collect();
            if predicted.len() > free && rect.width * rect.height > MIN_PREDICTED_CUT {
                // Over the pool already by what the parent's rays read here: cut without a round.
                // (The cone grown by the AO reach takes more than the rays read: small regions
                // are left to their rounds.)
                let (a, b) = halves(rect);
                regions.push((b, hint.clone()));
                regions.push((a, hint));
                continue;
            }
            if !predicted.is_empty() && predicted.len() <= free {
                let loading = std::time::Instant::now();
                pool.refine(&self.ctx, source, cache, &predicted, u64::MAX)?;
                done.loading += loading.elapsed();
            }
            // The level-0 bricks this region's rounds have read so far.
            let mut needed = std::collections::BTreeSet::new();
            let mut restarts = 0;
            loop {
                pool.clear_marks(&self.ctx);
                let part = self.render_accumulated(pool.volume(), &grown, settings, env, frames)?;
                done.gpu_time += part.gpu_time;
                done.rounds += 1;
                let marked = pool.read_marks(&self.ctx, settings.iso as f32);
                pool.stop_marking();
                let marked = marked?;
                let missing = marked.iter().filter(|k| !pool.holds(**k)).count();
                let last = marked.len();
                needed.extend(marked.iter().copied());
                tracing::debug!(
                    region = ?(rect.x, rect.y, rect.width, rect.height),
                    read = needed.len(),
                    missing,
                    "a ray-guided round of a still frame through the brick pool"
                );
                if missing == 0 {
                    done.passes += 1;
                    done.most_wanted = done.most_wanted.max(last);
                    paste(&mut frame, view.rect, &part.frame, grown.rect, rect);
                    break;
                }
                if needed.len() > free && last <= free && restarts < MAX_ROUND_RESTARTS {
                    // The earlier rounds' coarser pictures read bricks this one does not: start
                    // the set over from this round's (a few times, so that rounds end).
                    restarts += 1;
                    needed = marked.into_iter().collect();
                } else if needed.len() > free {
                    if rect.width <= 1 && rect.height <= 1 {
                        let over = (needed.len() - free) as u64;
                        let bytes = pool.gpu_bytes() + over * pool.layout().brick_bytes();
                        return Err(GpuError::Settings(format!(
                            "{}: one pixel's still frame reads {} bricks and the pool holds {free} beside the coarsest level: raise the GPU budget to at least {} MiB",
                            source.name(),
                            needed.len(),
                            bytes.div_ceil(1 << 20)
                        )));
                    }
                    // Cut at once into about as many regions as the set is larger than the pool
                    // (a round of a region that is then cut is spent).
                    let read = std::rc::Rc::new(needed.iter().copied().collect::<Vec<_>>());
                    let parts = parts(rect, needed.len().div_ceil(free));
                    regions.extend(parts.into_iter().rev().map(|r| (r, read.clone())));
                    break;
                }
                let wanted: Vec<BrickKey> = needed.iter().copied().collect();
                let loading = std::time::Instant::now();
                let r = pool.refine(&self.ctx, source, cache, &wanted, u64::MAX)?;
                done.loading += loading.elapsed();
                if !r.complete() {
                    return Err(GpuError::Settings(format!(
                        "{}: {} of {} bricks of a region are resident after its round",
                        source.name(),
                        r.resident,
                        r.wanted
                    )));
                }
            }
        }
        done.frame = frame;
        Ok(done)
    }
}

/// The fewest pixels a region is cut into parts by what its parent's rays read, without a round.
const MIN_PREDICTED_CUT: u32 = 32 * 32;

/// How often a region's ray-guided rounds start their set of bricks over from the last round's
/// before the region is cut in two.
const MAX_ROUND_RESTARTS: usize = 4;

/// `rect` cut into at least `n` parts where it has the pixels: halves of halves (along the longer
/// side), the nearest power of two at or above `n`.
fn parts(rect: Rect, n: usize) -> Vec<Rect> {
    let pixels = |r: &Rect| r.width * r.height;
    let mut parts = vec![rect];
    while parts.len() < n && parts.iter().any(|r| pixels(r) > 1) {
        parts = parts
            .into_iter()
            .flat_map(|r| if pixels(&r) > 1 { <[Rect; 2]>::from(halves(r)).to_vec() } else { vec![r] })
            .collect();
    }
    parts
}

/// `rect` cut in two along its longer side.
fn halves(rect: Rect) -> (Rect, Rect) {
    if rect.width >= rect.height {
        let w = rect.width / 2;
        (Rect { width: w, ..rect }, Rect { x: rect.x + w, width: rect.width - w, ..rect })
    } else {
        let h = rect.height / 2;
        (Rect { height: h, ..rect }, Rect { y: rect.y + h, height: rect.height - h, ..rect })
    }
}

/// Copies the pixels of `region` from `part` (a frame of `part_rect`) into `whole` (a frame of
/// `whole_rect`); all three rectangles are in the full image.
fn paste(whole: &mut Frame, whole_rect: Rect, part: &Frame, part_rect: Rect, region: Rect) {
    whole.fetches += part.fetches;
    for y in region.y..region.y + region.height {
        for x in region.x..region.x + region.width {
            let to = ((y - whole_rect.y) * whole_rect.width + (x - whole_rect.x)) as usize;
            let from = ((y - part_rect.y) * part_rect.width + (x - part_rect.x)) as usize;
            whole.color[to] = part.color[from];
            whole.depth[to] = part.depth[from];
            whole.normal[to] = part.normal[from];
            whole.hit[to] = part.hit[from];
            whole.occlusion[to] = part.occlusion[from];
            whole.bent_normal[to] = part.bent_normal[from];
            whole.ibl[to] = part.ibl[from];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::BlockBounds;
    use crate::shaders::tests::wgsl_constants;
    use crate::shaders::Kernel;
    use isowall_volume::brick_cache::{BrickKey, BrickSource, InCorePyramid, MAX_CACHE_LEVELS};
    use isowall_volume::procedural::Procedural;
    use isowall_volume::{BlockMinMax, VolumeSource};

    #[test]
    fn a_region_is_cut_into_parts_that_cover_it_once() {
        use isowall_model::camera::Rect;
        for (rect, n, expect) in [
            (Rect { x: 3, y: 1, width: 5, height: 3 }, 3, 4),
            (Rect { x: 0, y: 0, width: 64, height: 64 }, 16, 16),
            (Rect { x: 0, y: 0, width: 2, height: 1 }, 8, 2),
            (Rect { x: 7, y: 7, width: 1, height: 1 }, 8, 1),
        ] {
            let parts = super::parts(rect, n);
            assert_eq!(parts.len(), expect, "{rect:?} into {n}: {parts:?}");
            let mut covered = std::collections::HashMap::new();
            for p in &parts {
                assert!(p.width > 0 && p.height > 0, "{p:?}");
                for y in p.y..p.y + p.height {
                    for x in p.x..p.x + p.width {
                        *covered.entry((x, y)).or_insert(0) += 1;
                    }
                }
            }
            assert_eq!(covered.len(), (rect.width * rect.height) as usize, "{rect:?}: {parts:?}");
            assert!(covered.values().all(|&c| c == 1), "{rect:?}: {parts:?}");
            assert!(covered.keys().all(|&(x, y)| x >= rect.x
                && y >= rect.y
                && x < rect.x + rect.width
                && y < rect.y + rect.height));
        }
    }

    #[test]
    fn with_every_brick_resident_the_block_levels_are_the_whole_volumes() {
        // 37 samples: the last brick of 8 cells is cut short, the blocks of 32 too.
        let volume = VolumeSource::Procedural { kind: Procedural::Torus, size: Some(37) }.load(None).unwrap();
        let pyramid = InCorePyramid::new(volume.clone(), 8).unwrap();
        let cells = [8, 4, 32];
        let mut bounds = BlockBounds::new(pyramid.layout(), &pyramid, &cells);
        let whole: Vec<[f32; 2]> = cells.iter().flat_map(|&c| BlockMinMax::new(&volume, c).minmax).collect();
        let keys: Vec<BrickKey> = pyramid.layout().keys(0).collect();
        // None resident: each block bounded by its bricks' ranges, so never tighter than its own.
        let contains = |outer: &[f32; 2], inner: &[f32; 2]| outer[0] <= inner[0] && outer[1] >= inner[1];
        assert!(bounds.all.iter().zip(&whole).all(|(b, w)| contains(b, w)));
        assert!(bounds.all != whole, "the bricks' ranges are looser than some blocks'");
        for key in &keys {
            let data = pyramid.read_brick(*key).unwrap();
            bounds.brick_changed(key.brick, Some(&data));
        }
        assert!(bounds.all == whole, "every brick resident: the whole volume's block levels");
        // Dirty spans cover every changed block, then nothing is left to write.
        let spans = bounds.take_dirty();
        assert_eq!(spans.iter().map(|(_, v)| v.len()).sum::<usize>(), whole.len());
        assert!(bounds.take_dirty().is_empty());
        // One brick leaves: its blocks go back to its range, the others stay exact.
        bounds.brick_changed(keys[5].brick, None);
        assert!(bounds.all != whole && bounds.all.iter().zip(&whole).all(|(b, w)| contains(b, w)));
        let data = pyramid.read_brick(keys[5]).unwrap();
        bounds.brick_changed(keys[5].brick, Some(&data));
        assert!(bounds.all == whole);
    }

    #[test]
    fn the_kernels_hold_as_many_levels_as_the_cache_makes() {
        for kernel in [Kernel::Isosurface, Kernel::Ao] {
            let levels = wgsl_constants(kernel).get("MAX_BRICK_LEVELS").copied();
            assert_eq!(levels, Some(MAX_CACHE_LEVELS as u32), "{kernel:?}");
        }
    }
}
