// Shared include: the trilinear field of DESIGN.md ("Volume") over the `volume` storage buffer,
// with the dims in `params.dims`. Used by every kernel that reads the volume. Twin of
// `Volume::trilinear_voxel` / `Volume::gradient` in daemon/volume (the CPU side), which tests compare.
//
// Expects frame.wgsl before it (`params`, `volume`, `block_minmax`).

// Trilinear field evaluations made by this invocation ("trilinear fetches", 8 voxel reads each).
var<private> fetches: u32 = 0u;

// How the voxels are stored (`VoxelFormat::code` in daemon/volume/src/format.rs, whose
// `decode` is the CPU twin): 0 r32f, 1 r16f, 2 r16 unorm, 3 r8 unorm (both over
// `params.voxel_range`). A pipeline constant, so each pipeline holds only its own branch.
override VOXEL_FORMAT: u32 = 0u;

// An IEEE half's bits as f32, exactly (`half::f16::to_f32`), by bit operations: `unpack2x16float`
// needs the SHADER_FLOAT16_IN_FLOAT32 capability, which would make every pipeline of the kernel,
// the r32f one included, depend on it. Infinities and NaNs never occur (r16f clamps to +-65504).
fn half_to_f32(h: u32) -> f32 {
    let sign = (h & 0x8000u) << 16u;
    let e = (h >> 10u) & 0x1fu;
    let m = h & 0x3ffu;
    if e == 0u {
        // zero or subnormal: m * 2^-24, exact in f32
        return bitcast<f32>(sign | bitcast<u32>(f32(m) * 5.9604645e-8));
    }
    return bitcast<f32>(sign | ((e + 112u) << 23u) | (m << 13u));
}

// Level 0's sample (i, j, k): of the `volume` buffer, or through the page table where bricked.
fn voxel(i: i32, j: i32, k: i32) -> f32 {
    if BRICKED {
        return bricked_sample(vec3<i32>(i, j, k));
    }
    let n = vec3<i32>(params.dims.xyz);
    return packed_voxel(u32(i + n.x * (j + n.y * k)));
}

// Level 0's sample at linear index idx (x fastest; the index of the volume held whole).
fn voxel_at(idx: u32) -> f32 {
    if BRICKED {
        let n = params.dims.xyz;
        let c = vec3<u32>(idx % n.x, (idx / n.x) % n.y, idx / (n.x * n.y));
        return bricked_sample(vec3<i32>(c));
    }
    return packed_voxel(idx);
}

// The voxel at linear index idx (x fastest) of the `volume` buffer held whole.
fn packed_voxel(idx: u32) -> f32 {
    if VOXEL_FORMAT == 1u {
        return half_to_f32((volume[idx >> 1u] >> (16u * (idx & 1u))) & 0xffffu);
    }
    if VOXEL_FORMAT == 2u {
        let t = unpack2x16unorm(volume[idx >> 1u])[idx & 1u];
        return params.voxel_range.x * (1.0 - t) + params.voxel_range.y * t;
    }
    if VOXEL_FORMAT == 3u {
        let t = unpack4x8unorm(volume[idx >> 2u])[idx & 3u];
        return params.voxel_range.x * (1.0 - t) + params.voxel_range.y * t;
    }
    return bitcast<f32>(volume[idx]);
}

// The trilinear interpolant at continuous voxel coordinates `u`, clamped to the box; an axis with a
// single sample is constant along that axis.
fn trilinear_voxel(u: vec4<f32>) -> f32 {
    fetches += 1u;
    if BRICKED {
        return bricked_trilinear(u.xyz);
    }
    let n = vec3<i32>(params.dims.xyz);
    let x = clamp(u.xyz, vec3<f32>(0.0), vec3<f32>(max(n - 1, vec3<i32>(0))));
    let i0 = min(vec3<i32>(floor(x)), max(n - 2, vec3<i32>(0)));
    let fr = x - vec3<f32>(i0);
    let d = select(vec3<i32>(0), vec3<i32>(1), n > vec3<i32>(1));
    let i1 = i0 + d;
    let x00 = mix(voxel(i0.x, i0.y, i0.z), voxel(i1.x, i0.y, i0.z), fr.x);
    let x10 = mix(voxel(i0.x, i1.y, i0.z), voxel(i1.x, i1.y, i0.z), fr.x);
    let x01 = mix(voxel(i0.x, i0.y, i1.z), voxel(i1.x, i0.y, i1.z), fr.x);
    let x11 = mix(voxel(i0.x, i1.y, i1.z), voxel(i1.x, i1.y, i1.z), fr.x);
    return mix(mix(x00, x10, fr.y), mix(x01, x11, fr.y), fr.z);
}

// A bricked volume (DESIGN.md "Large volumes"; the host side is daemon/render/src/gpu/brick_pool.rs,
// which writes this layout, and daemon/volume/src/brick_cache.rs): the `volume` buffer holds, in
// words, a header (levels, log2 of the cells per brick edge, samples per brick edge, the pool's
// first word), each level's directory entry (16 words from word 4), the page tables (one word a
// brick: 0 where it is not resident, else its pool slot + 1) and the pool (slots of
// samples^3 f32, x fastest). A pipeline constant, so the whole volume's kernels hold no branch.
override BRICKED: bool = false;

struct BrickLevel {
    dims: vec3<i32>,
    pages: u32,        // the level's page table's first word
    counts: vec3<u32>, // bricks on x, y, z
    scale: vec3<f32>,  // level-0 voxel coordinates u map to this level's as u * scale + offset
    offset: vec3<f32>,
}

// The header (levels, log2 of cells per brick edge, samples per brick edge, the pool's first
// word) and the levels' directory entries, read once by each invocation (`load_bricks`, at the
// kernel's entry): on a SIMD CPU driver every storage load costs on every lane.
var<private> brick_head: vec4<u32>;
var<private> brick_level0: BrickLevel;
// The coarsest level's entry (always resident), and every level's for the walk over the
// coarser levels (`coarser_trilinear`): read there at each lookup, they made a frame of the
// coarse levels several times slower than one of level 0 on lavapipe.
var<private> brick_coarsest: BrickLevel;
var<private> brick_levels: array<BrickLevel, MAX_BRICK_LEVELS>;
// The most levels a bricked volume has (`MAX_CACHE_LEVELS` in daemon/volume/src/brick_cache.rs,
// which a test holds it to).
const MAX_BRICK_LEVELS: u32 = 16u;

fn load_bricks() {
    if BRICKED {
        brick_head = vec4<u32>(volume[0u], volume[1u], volume[2u], volume[3u]);
        for (var l = 0u; l < min(brick_head.x, MAX_BRICK_LEVELS); l += 1u) {
            brick_levels[l] = brick_level(l);
        }
        brick_level0 = brick_levels[0];
        brick_coarsest = brick_levels[brick_head.x - 1u];
    }
}

fn brick_level(l: u32) -> BrickLevel {
    let w = 4u + 16u * l;
    return BrickLevel(
        vec3<i32>(i32(volume[w]), i32(volume[w + 1u]), i32(volume[w + 2u])),
        volume[w + 3u],
        vec3<u32>(volume[w + 4u], volume[w + 5u], volume[w + 6u]),
        vec3<f32>(bitcast<f32>(volume[w + 8u]), bitcast<f32>(volume[w + 9u]), bitcast<f32>(volume[w + 10u])),
        vec3<f32>(bitcast<f32>(volume[w + 12u]), bitcast<f32>(volume[w + 13u]), bitcast<f32>(volume[w + 14u])),
    );
}

// The page (pool slot + 1, or 0) of brick b of `lv`.
fn brick_page(lv: BrickLevel, b: vec3<u32>) -> u32 {
    return volume[lv.pages + b.x + lv.counts.x * (b.y + lv.counts.y * b.z)];
}

// Sample `at` (the brick's own indices, 0 ..= cells) of the brick in `page`.
fn pool_sample(page: u32, at: vec3<i32>) -> f32 {
    let s = brick_head.z;
    let a = vec3<u32>(at);
    return bitcast<f32>(volume[brick_head.w + (page - 1u) * s * s * s + a.x + s * (a.y + s * a.z)]);
}

// The trilinear interpolant, at level-0 voxel coordinates u0, of the finest level whose brick
// there is resident: the field of DESIGN.md "Large volumes". At level 0 it is
// `trilinear_voxel`'s arithmetic on the same samples, so a resident level 0 is the whole volume's
// picture bit for bit. The coarsest level is always resident (the pool pins it).
fn bricked_trilinear(u0: vec3<f32>) -> f32 {
    // Level 0, straight-line: the common case once refined.
    let c = level0_cell(u0);
    mark_level0_brick(c.b);
    let page = brick_page(brick_level0, c.b);
    if page != 0u {
        return brick_trilinear(page, c.x, c.i0, c.b, brick_level0.dims);
    }
    return coarser_trilinear(u0);
}

// Where a trilinear lookup at level-0 voxel coordinates u0 reads level 0: the coordinates clamped
// to the box, the cell and the brick that holds its 8 samples.
struct Level0Cell {
    x: vec3<f32>,
    i0: vec3<i32>,
    b: vec3<u32>,
}

fn level0_cell(u0: vec3<f32>) -> Level0Cell {
    let n = brick_level0.dims;
    let x = clamp(u0, vec3<f32>(0.0), vec3<f32>(max(n - 1, vec3<i32>(0))));
    let i0 = min(vec3<i32>(floor(x)), max(n - 2, vec3<i32>(0)));
    let b = min(vec3<u32>(i0) >> vec3<u32>(brick_head.y), brick_level0.counts - 1u);
    return Level0Cell(x, i0, b);
}

// Whether a lookup at level-0 voxel coordinates u0 reads level 0: always for a volume held whole;
// bricked, where level 0's brick there is resident.
fn level0_at(u0: vec3<f32>) -> bool {
    if !BRICKED {
        return true;
    }
    return brick_page(brick_level0, level0_cell(u0).b) != 0u;
}

// The 8-sample blend of `bricked_trilinear` in the brick in `page` (brick index b of its level),
// at the level's clamped coordinates x of cell i0, on a level of n samples.
fn brick_trilinear(page: u32, x: vec3<f32>, i0: vec3<i32>, b: vec3<u32>, n: vec3<i32>) -> f32 {
    let fr = x - vec3<f32>(i0);
    let d = select(vec3<i32>(0), vec3<i32>(1), n > vec3<i32>(1));
    let a0 = i0 - vec3<i32>(b << vec3<u32>(brick_head.y));
    let a1 = a0 + d;
    let x00 = mix(pool_sample(page, a0), pool_sample(page, vec3<i32>(a1.x, a0.y, a0.z)), fr.x);
    let x10 = mix(pool_sample(page, vec3<i32>(a0.x, a1.y, a0.z)), pool_sample(page, vec3<i32>(a1.x, a1.y, a0.z)), fr.x);
    let x01 = mix(pool_sample(page, vec3<i32>(a0.x, a0.y, a1.z)), pool_sample(page, vec3<i32>(a1.x, a0.y, a1.z)), fr.x);
    let x11 = mix(pool_sample(page, vec3<i32>(a0.x, a1.y, a1.z)), pool_sample(page, a1), fr.x);
    return mix(mix(x00, x10, fr.y), mix(x01, x11, fr.y), fr.z);
}

// `bricked_trilinear` past level 0: the finest resident coarser level's interpolant (the
// coarsest is always resident).
fn coarser_trilinear(u0: vec3<f32>) -> f32 {
    let levels = brick_head.x;
    for (var l = 1u; l < levels; l += 1u) {
        let lv = brick_levels[l];
        let n = lv.dims;
        let x = clamp(u0 * lv.scale + lv.offset, vec3<f32>(0.0), vec3<f32>(max(n - 1, vec3<i32>(0))));
        let i0 = min(vec3<i32>(floor(x)), max(n - 2, vec3<i32>(0)));
        let b = min(vec3<u32>(i0) >> vec3<u32>(brick_head.y), lv.counts - 1u);
        let page = brick_page(lv, b);
        if page != 0u || l + 1u == levels {
            return select(0.0, brick_trilinear(max(page, 1u), x, i0, b, n), page != 0u);
        }
    }
    return 0.0;
}

// Level 0's sample c: from its resident brick (a sample on a brick's low face is also the
// previous brick's far face, which is tried too), else the coarser levels' field there.
fn bricked_sample(c: vec3<i32>) -> f32 {
    let lv = brick_level0;
    let cells = brick_head.y;
    let u = vec3<u32>(max(c, vec3<i32>(0)));
    let b = min(u >> vec3<u32>(cells), lv.counts - 1u);
    var page = brick_page(lv, b);
    var at = b;
    if page == 0u {
        let on_face = (u & vec3<u32>((1u << cells) - 1u)) == vec3<u32>(0u) & b > vec3<u32>(0u);
        at = b - select(vec3<u32>(0u), vec3<u32>(1u), on_face);
        page = brick_page(lv, at);
    }
    mark_level0_brick(select(b, at, page != 0u));
    if page != 0u {
        return pool_sample(page, vec3<i32>(u - (at << vec3<u32>(cells))));
    }
    return coarsest_sample(vec3<f32>(c));
}

// The last level-0 brick this invocation marked (a ray's lookups mostly stay in one brick).
var<private> last_mark: u32 = 0xffffffffu;

// Marks level-0 brick b in `brick_marks` where the host asked for marks (`params.perf.w`): a
// ray read it, resident or not. A still frame whose marked bricks are all resident read level 0
// wherever it read the volume or relied on a block's min/max (`mark_block`), so it is the whole
// volume's frame; the host loads the marked bricks that are not (ray-guided rounds, DESIGN.md
// "Large volumes").
fn mark_level0_brick(b: vec3<u32>) {
    if params.perf.w == 0u {
        return;
    }
    let i = b.x + brick_level0.counts.x * (b.y + brick_level0.counts.y * b.z);
    if i != last_mark {
        last_mark = i;
        atomicOr(&brick_marks[i >> 5u], 1u << (i & 31u));
    }
}

// Marks block b of the coarse level (`brick_marks` after the level-0 bricks' words): a ray did
// not skip it on its min/max. It spans many bricks where they are smaller than it; the host loads
// only those that are not resident and whose range reaches iso (the others cannot change its
// max against iso). For a volume held whole, nothing.
fn mark_coarse_block(coarse: Level, b: vec3<u32>) {
    if !BRICKED || params.perf.w == 0u {
        return;
    }
    let c = brick_level0.counts;
    let first = (c.x * c.y * c.z + 31u) >> 5u;
    let i = b.x + coarse.counts.x * (b.y + coarse.counts.y * b.z);
    atomicOr(&brick_marks[first + (i >> 5u)], 1u << (i & 31u));
}

// Marks the level-0 bricks that make block b's min/max (the bricks holding its cells; a brick
// holds its far face, so a block's samples are all in them), where a ray did not skip the block
// on that min/max: the whole volume's exact range might have let it skip. A decision to skip is
// the whole volume's too (a brick's range where it is not resident bounds the exact one). For a
// volume held whole, nothing.
fn mark_block(b: vec3<u32>, cells: u32) {
    if !BRICKED || params.perf.w == 0u {
        return;
    }
    let shift = vec3<u32>(brick_head.y);
    let top = brick_level0.counts - 1u;
    let lo = min((b * cells) >> shift, top);
    let hi = min(((b + 1u) * cells - 1u) >> shift, top);
    for (var z = lo.z; z <= hi.z; z += 1u) {
        for (var y = lo.y; y <= hi.y; y += 1u) {
            for (var x = lo.x; x <= hi.x; x += 1u) {
                mark_level0_brick(vec3<u32>(x, y, z));
            }
        }
    }
}

// Where level 0 is not resident, the cell walks of AO rays read the coarsest level's sample
// nearest to level-0 sample position u0 (always resident). A loop over the levels here, as in
// `coarser_trilinear`, made the exact AO walk 5x slower on lavapipe even where no lane took it
// (the walk inlines this at each of its load sites); still frames refine to level 0, where
// this is never read.
fn coarsest_sample(u0: vec3<f32>) -> f32 {
    let lv = brick_coarsest;
    let n = lv.dims;
    let i = clamp(vec3<i32>(round(u0 * lv.scale + lv.offset)), vec3<i32>(0), max(n - 1, vec3<i32>(0)));
    let b = min(vec3<u32>(i) >> vec3<u32>(brick_head.y), lv.counts - 1u);
    let page = max(brick_page(lv, b), 1u);
    return pool_sample(page, i - vec3<i32>(b << vec3<u32>(brick_head.y)));
}

// Continuous voxel coordinates of a world point in the whole volume's grid.
fn to_global_voxel(p: vec3<f32>) -> vec3<f32> {
    return (p - params.box_min.xyz) / params.spacing.xyz;
}

// Continuous voxel coordinates of a world point in the `volume` buffer: the whole volume's, less
// the brick's offset in object space (an exact subtraction of whole numbers, so the trilinear
// weights are the single-node render's bit for bit).
fn to_voxel(p: vec3<f32>) -> vec4<f32> {
    return vec4<f32>(to_global_voxel(p) - params.data_offset.xyz, 0.0);
}

// Object space: the buffer's offset in whole samples (0 in screen space).
fn data_offset_cells() -> vec3<i32> {
    return vec3<i32>(params.data_offset.xyz);
}

// Object space: whether the march step starting at p is this brick's (always, in screen space).
// p is clamped to the box first, so the bricks' half-open boxes give every step to exactly one.
fn owns(p: vec3<f32>) -> bool {
    if params.data_offset.w == 0.0 {
        return true;
    }
    let q = clamp(p, params.box_min.xyz, params.box_max.xyz);
    return all(q >= params.owned_min.xyz) && all(q < params.owned_max.xyz);
}

// The field at a world point, position clamped to the box (callers handle "outside is empty").
fn field(p: vec3<f32>) -> f32 {
    return trilinear_voxel(to_voxel(p));
}

// Central differences of the trilinear field, h = one voxel spacing per axis, stencil clamped.
// w: the largest |f| among the six samples, the scale for deciding that the gradient vanished.
fn gradient(p: vec3<f32>) -> vec4<f32> {
    let u = to_voxel(p);
    let s = params.spacing.xyz;
    let xp = trilinear_voxel(u + vec4<f32>(1.0, 0.0, 0.0, 0.0));
    let xm = trilinear_voxel(u - vec4<f32>(1.0, 0.0, 0.0, 0.0));
    let yp = trilinear_voxel(u + vec4<f32>(0.0, 1.0, 0.0, 0.0));
    let ym = trilinear_voxel(u - vec4<f32>(0.0, 1.0, 0.0, 0.0));
    let zp = trilinear_voxel(u + vec4<f32>(0.0, 0.0, 1.0, 0.0));
    let zm = trilinear_voxel(u - vec4<f32>(0.0, 0.0, 1.0, 0.0));
    let scale = max(max(max(abs(xp), abs(xm)), max(abs(yp), abs(ym))), max(abs(zp), abs(zm)));
    return vec4<f32>(vec3<f32>(xp - xm, yp - ym, zp - zm) / (2.0 * s), scale);
}

// 1 / dir with zero components replaced by tiny ones of the same side (WGSL has no infinities):
// their slab then spans (almost) all t, as it should.
fn safe_inv(dir: vec3<f32>) -> vec3<f32> {
    let tiny = vec3<f32>(1e-20);
    return 1.0 / select(dir, select(tiny, -tiny, dir < vec3<f32>(0.0)), abs(dir) < tiny);
}

// Entry and exit parameters of the ray o + t dir through the volume box (slabs); the ray misses
// when exit < max(entry, 0).
fn box_clip(o: vec3<f32>, inv_dir: vec3<f32>) -> vec2<f32> {
    let ta = (params.box_min.xyz - o) * inv_dir;
    let tb = (params.box_max.xyz - o) * inv_dir;
    let tmin3 = min(ta, tb);
    let tmax3 = max(ta, tb);
    return vec2<f32>(max(max(tmin3.x, tmin3.y), tmin3.z), min(min(tmax3.x, tmax3.y), tmax3.z));
}

// The block (of `params.dims.w` cells per edge) containing world point p.
fn block_of(p: vec3<f32>) -> vec3<u32> {
    let cells = to_global_voxel(p) / f32(params.dims.w);
    let c = vec3<i32>(floor(cells));
    return vec3<u32>(clamp(c, vec3<i32>(0), vec3<i32>(params.block_counts.xyz) - 1));
}

// Largest sample of block b: the field anywhere in the block's closed box is at most this.
fn block_max(b: vec3<u32>) -> f32 {
    let n = params.block_counts.xyz;
    return block_minmax[b.x + n.x * (b.y + n.y * b.z)].y;
}

// The extra block levels of AO rays (performance), indexed by cell: a level is (counts xyz, cells
// per edge w) with its min/max at `offset` in `block_minmax`, after the primary rays' level.
// `shift`: log2 of cells where they are a power of two (`POW2_LEVELS`), computed once with the
// level rather than at every block lookup of a walk.
struct Level {
    counts: vec3<u32>,
    cells: u32,
    offset: u32,
    shift: u32,
}

fn make_level(counts: vec3<u32>, cells: u32, offset: u32) -> Level {
    return Level(counts, cells, offset, countTrailingZeros(cells));
}

// The AO rays' fine level (the primary rays' level where none was uploaded).
fn ao_level() -> Level {
    if params.ao_blocks.w == 0u {
        return make_level(params.block_counts.xyz, params.dims.w, 0u);
    }
    return make_level(params.ao_blocks.xyz, params.ao_blocks.w, params.perf.y);
}

// The coarse level over it; cells 0 when there is none.
fn coarse_level() -> Level {
    return make_level(params.coarse.xyz, params.coarse.w, params.perf.z);
}

// Whether every block level's cells per edge is a power of two (`PerfOptions::pow2_levels`): then
// a cell's block is a shift, not an integer division, which a SIMD CPU driver (llvmpipe) runs
// lane by lane. A pipeline constant, so each pipeline holds only its own branch.
override POW2_LEVELS: bool = false;

// The block of `level` holding cell c.
fn level_block(level: Level, c: vec3<i32>) -> vec3<u32> {
    let u = vec3<u32>(max(c, vec3<i32>(0)));
    var b: vec3<u32>;
    if POW2_LEVELS {
        b = u >> vec3<u32>(level.shift);
    } else {
        b = u / level.cells;
    }
    return min(b, level.counts - 1u);
}

// Min and max of the samples of block b of `level`.
fn level_range(level: Level, b: vec3<u32>) -> vec2<f32> {
    let n = level.counts;
    return block_minmax[level.offset + b.x + n.x * (b.y + n.y * b.z)];
}

// Ray parameter where the ray o + t dir leaves block b of `level` (cell c's) beyond t, or, where
// the coarse level exists and cell c's coarse block is empty too, that coarse block
// (hierarchical). One exit computed, of the block chosen: a SIMD CPU driver runs both sides of a
// branch.
fn empty_exit(level: Level, coarse: Level, b: vec3<u32>, c: vec3<i32>, o: vec3<f32>, inv_dir: vec3<f32>, iso: f32) -> f32 {
    var block = b;
    var cells = level.cells;
    if coarse.cells > 0u {
        let cb = level_block(coarse, c);
        if level_range(coarse, cb).y < iso {
            block = cb;
            cells = coarse.cells;
        } else {
            mark_coarse_block(coarse, cb);
        }
    }
    return level_exit(block, f32(cells), o, inv_dir);
}

// Ray parameter where the ray o + t dir leaves block b (its box clamped to the volume box).
fn block_exit(b: vec3<u32>, o: vec3<f32>, inv_dir: vec3<f32>) -> f32 {
    return level_exit(b, f32(params.dims.w), o, inv_dir);
}

// Ray parameter where the ray leaves block b of a level of `bs` cells per edge (clamped to the box).
fn level_exit(b: vec3<u32>, bs: f32, o: vec3<f32>, inv_dir: vec3<f32>) -> f32 {
    let lo = params.box_min.xyz + vec3<f32>(b) * bs * params.spacing.xyz;
    let hi = min(lo + bs * params.spacing.xyz, params.box_max.xyz);
    let tmax = max((lo - o) * inv_dir, (hi - o) * inv_dir);
    return min(min(tmax.x, tmax.y), tmax.z);
}

// Whether empty-space skipping is on for this frame.
fn skipping() -> bool {
    return (params.block_counts.w & FLAG_EMPTY_SPACE_SKIPPING) != 0u;
}
