// Kernel::Ao (daemon/render/src/gpu/ao.rs): ambient occlusion, bent normal and the IBL term of one
// frame at every hit of the isosurface kernel's output, added into accumulators (progressive
// accumulation: frame k of K adds its estimate; the host divides by K). On a reprojected frame
// whose samples are spent by history (`ao_pass.z` not 0) each pixel takes its own number of
// samples, written by reproject.wgsl, and adds its estimate weighted by that number over the
// frame's `ao_samples`.
//
// Ours (DESIGN.md "AO"; the CPU twin is the reference's `AoSurface` and `ambient_at`):
// cosine-weighted directions around N as it is (the central-difference normal, NOT turned to the
// viewer; Ng where its gradient vanished, i.e. where N is the viewer fallback -dir) from the 2D set
// `ao_sequence` (R2 shifted, or Owen-scrambled Sobol, per pixel and frame: sampling.wgsl); origin on
// the surface, o = p + eps Ng (`ao_offset` = eps), Ng the trilinear field's own gradient in p's
// cell turned towards the arriving ray (a cap's face normal); a ray up to R (`ao_radius`, or to the
// box exit when unbounded) from where it enters the box; occluded as soon as f >= iso anywhere on
// it (t = 0 included). A direction under p's tangent plane (w . Ng <= 0) is occluded without
// marching (`under_tangent_plane`): from p itself it enters the object at once, and marched from
// o it would escape over a curved surface. Blocks whose max < iso are crossed without
// looking at them (performance: AO rays have their own, finer level, `ao_level`, and a coarse one,
// `coarse_level`, crossed whole where its max < iso; a ray in a block whose min >= iso is occluded
// without a fetch, `PERF_BLOCK_MIN_EXIT`). Two tests of the ray:
// - `ao_exact` 1 (the default, `exact_occluded`): the twin of the reference's `ao_ray_occluded`.
//   A 3D DDA walks the cells of the sample grid the ray crosses; in each cell the 8 corners are
//   loaded (one fetch), a cell whose corners are all < iso is passed, and otherwise the trilinear
//   interpolant along the segment (a cubic) is tested at both ends and at the roots of its
//   derivative inside the segment, where its maximum lies. No step: no sheet is too thin.
// - `ao_exact` 0 (`ours_occluded`): a march of `ao_step` (at most half a voxel by default) with a
//   sample f >= iso as the test: a variant for the speed/accuracy chart; it misses sheets thinner
//   than a step.
//
// Seed (`ao_method` 1): the 2008 RTPara shader, ported faithfully as the baseline (not our method):
// directions u = v = -1 + 2i/N on one diagonal of the disk, samples outside the disk skipped but
// counted, a march t = 0.01 .. 0.9 in steps of 0.01 in normalized texture space [0,1]^3, occluded on
// a vpold < iso < vp pair, no origin offset.
//
// IBL (`ibl`): 0 none: E = ambient (1 - A); 1 seed: E = L_env(bent) (1 - A); 2 bent:
// E = irradiance_SH9(bent) (1 - A); 3 rays: E = mean over samples of (1 - V_i) L_env(w_i).
// With 0 samples: A = 0, bent = N, and `rays` falls back to the SH9 irradiance at N.
//
//#include camera.wgsl
//#include frame.wgsl
//#include volume.wgsl
//#include sampling.wgsl
//#include environment.wgsl
//#include hit.wgsl

// From the isosurface kernel: w says whether the pixel hit the surface (hit.wgsl).
@group(0) @binding(3) var<storage, read> in_color: array<vec4<f32>>;
// From the isosurface kernel: N (outward) and depth.
@group(0) @binding(4) var<storage, read> in_geometry: array<vec4<f32>>;
// The environment, equirectangular (environment.wgsl).
@group(0) @binding(5) var<storage, read> env: array<vec4<f32>>;
// Accumulated per frame: bent normal (xyz), A (w).
@group(0) @binding(6) var<storage, read_write> acc_ao: array<vec4<f32>>;
// Accumulated per frame: E (rgb); w: the frames' worth of samples added (each frame's shares sum
// to 1, so a still tile's w is its frame count; reproject.wgsl carries and ages it).
@group(0) @binding(7) var<storage, read_write> acc_ibl: array<vec4<f32>>;
// Trilinear fetches, added to the isosurface kernel's.
@group(0) @binding(8) var<storage, read_write> out_fetches: array<u32>;
// x: which of the frame's dispatches this is (a dynamic offset into 0, 1, 2, ...): it takes the
// samples [x * params.ao_pass.x, (x + 1) * params.ao_pass.x) of the frame's params.ao_samples and
// adds its share (its samples / all samples) of the frame's estimate (`AoDispatches` in
// daemon/render/src/gpu/ao.rs: lavapipe ends an invocation's loops past 65535 iterations in all).
@group(0) @binding(9) var<storage, read> ao_dispatch: vec4<u32>;
// Accumulated per frame: the hit position the samples were taken at (xyz, world; w 0), weighted
// as acc_ibl.w: divided by it, where a reprojected history stands (reproject.wgsl's drift test).
@group(0) @binding(10) var<storage, read_write> acc_pos: array<vec4<f32>>;

// The pipeline's path (`AoPath` in daemon/render/src/gpu/ao.rs): AO_PATH_ANY holds every method
// and test, the frame's parameters choosing; AO_PATH_EXACT only ours with the exact test and no
// environment rays (the defaults). A SIMD CPU driver runs every branch for each group of pixels,
// masked, whether a lane takes it or not: the default's pipeline holds none of the others' loads.
override AO_PATH: u32 = 0u;
const AO_PATH_ANY: u32 = 0u;
const AO_PATH_EXACT: u32 = 1u;

const AO_OURS: u32 = 0u;
const AO_SEED: u32 = 1u;
const IBL_NONE: u32 = 0u;
const IBL_SEED: u32 = 1u;
const IBL_BENT: u32 = 2u;
const IBL_RAYS: u32 = 3u;

// The part of the AO ray o + t w that is tested: from where it is in the box (t >= 0) to where it
// leaves the box or reaches the radius R (`ao_radius` < 0: unbounded). Empty when y < x.
fn ao_ray_range(o: vec3<f32>, inv: vec3<f32>) -> vec2<f32> {
    let tc = box_clip(o, inv);
    var t_end = tc.y;
    if params.ao_radius >= 0.0 {
        t_end = min(t_end, params.ao_radius);
    }
    return vec2<f32>(max(tc.x, 0.0), t_end);
}

// Ours: does o + t w reach f >= iso for some t in [0, R] (R clipped to the box)?
fn ours_occluded(o: vec3<f32>, w: vec3<f32>) -> bool {
    let inv = safe_inv(w);
    let range = ao_ray_range(o, inv);
    var t = range.x;
    let t_end = range.y;
    if !(t_end >= t) {
        return false;
    }
    let h = params.ao_step;
    let iso = params.iso;
    let ess = skipping();
    let level = ao_level();
    let coarse = coarse_level();
    for (var steps = 0u; steps < params.max_steps; steps += 1u) {
        if ess {
            let c = vec3<i32>(floor(to_global_voxel(o + (t + 1e-3 * h) * w)));
            let b = level_block(level, c);
            if level_range(level, b).y < iso {
                t = max(empty_exit(level, coarse, b, c, o, inv, iso), t + 1e-3 * h);
                if t >= t_end {
                    return false;
                }
                continue;
            }
            mark_block(b, level.cells);
        }
        if field(o + t * w) >= iso {
            return true;
        }
        if t >= t_end {
            return false;
        }
        t = min(t + h, t_end);
    }
    return false;
}

// Exact: the largest value of one cell's trilinear interpolant.
fn cell_max(c: array<f32, 8>) -> f32 {
    return max(max(max(c[0], c[1]), max(c[2], c[3])), max(max(c[4], c[5]), max(c[6], c[7])));
}

// The trilinear blend of a cell's corners c (index dx + 2 dy + 4 dz) at local coordinates x
// (clamped to the cell: rounding may put a segment end a hair outside it).
fn cell_blend(c: array<f32, 8>, x: vec3<f32>) -> f32 {
    let l = clamp(x, vec3<f32>(0.0), vec3<f32>(1.0));
    let y0 = mix(mix(c[0], c[1], l.x), mix(c[2], c[3], l.x), l.y);
    let y1 = mix(mix(c[4], c[5], l.x), mix(c[6], c[7], l.x), l.y);
    return mix(y0, y1, l.z);
}

// One z layer of a cell's bilinear blend along x0 + s d (lo = 1 - x0, hi = x0): coefficients of
// 1, s, s^2 from the corners (x0 y0, x1 y0, x0 y1, x1 y1).
fn layer_poly(c00: f32, c10: f32, c01: f32, c11: f32, lo: vec3<f32>, hi: vec3<f32>, d: vec3<f32>) -> vec3<f32> {
    // Along x: constant and slope of each edge.
    let e0 = vec2<f32>(c00 * lo.x + c10 * hi.x, (c10 - c00) * d.x);
    let e1 = vec2<f32>(c01 * lo.x + c11 * hi.x, (c11 - c01) * d.x);
    // e0 * (lo.y - d.y s) + e1 * (hi.y + d.y s)
    return vec3<f32>(
        e0.x * lo.y + e1.x * hi.y,
        e0.y * lo.y - e0.x * d.y + e1.y * hi.y + e1.x * d.y,
        (e1.y - e0.y) * d.y,
    );
}

// Whether the trilinear blend of a cell reaches iso on the segment x0 + s d, s in [0, 1] (the twin
// of the reference's `reaches`): the cubic's maximum on the segment is at an end or at a root of
// its derivative. The values are blends at those points (convex combinations, accurate in f32);
// the cubic's coefficients only place the roots.
fn cell_reaches(c: array<f32, 8>, x0: vec3<f32>, d: vec3<f32>, iso: f32) -> bool {
    if cell_blend(c, x0) >= iso || cell_blend(c, x0 + d) >= iso {
        return true;
    }
    // Weights of the low and high corner per axis as linear polynomials in s: (constant, slope).
    let lo = vec3<f32>(1.0) - x0;
    let hi = x0;
    // Along x for both y of each z layer, then along y (the reference's Cell::cubic).
    let q0 = layer_poly(c[0], c[1], c[2], c[3], lo, hi, d);
    let q1 = layer_poly(c[4], c[5], c[6], c[7], lo, hi, d);
    // q0 * (lo.z - d.z s) + q1 * (hi.z + d.z s): the s, s^2, s^3 coefficients.
    let g1 = q0.y * lo.z - q0.x * d.z + q1.y * hi.z + q1.x * d.z;
    let g2 = q0.z * lo.z - q0.y * d.z + q1.z * hi.z + q1.y * d.z;
    let g3 = (q1.z - q0.z) * d.z;
    // Roots of g' = g1 + 2 g2 s + 3 g3 s^2, computed stably (the reference's quadratic_roots).
    let a = 3.0 * g3;
    let b = 2.0 * g2;
    var r = vec2<f32>(-1.0);
    if a == 0.0 {
        if b != 0.0 {
            r.x = -g1 / b;
        }
    } else {
        let disc = b * b - 4.0 * a * g1;
        if disc >= 0.0 {
            let qq = -0.5 * (b + select(-1.0, 1.0, b >= 0.0) * sqrt(disc));
            r.x = qq / a;
            r.y = select(r.x, g1 / select(1.0, qq, qq != 0.0), qq != 0.0);
        }
    }
    // Both roots, written out (no loop: lavapipe counts loop iterations against a budget).
    let in0 = r.x > 0.0 && r.x < 1.0 && cell_blend(c, x0 + r.x * d) >= iso;
    let in1 = r.y > 0.0 && r.y < 1.0 && cell_blend(c, x0 + r.y * d) >= iso;
    return in0 || in1;
}

// A value no ray parameter reaches (WGSL has no infinity).
const T_NEVER: f32 = 1e30;

// Ours, exact (`ao_exact` 1): does o + t w reach f >= iso for some t in [max(t_enter, 0),
// min(t_exit, R)]? The twin of the reference's `ao_ray_occluded` / `CellWalk`: a DDA over the
// cells of the sample grid (an axis with one sample is constant and never stepped), each segment
// tested exactly by `cell_reaches`. A cell is identified by its segment's midpoint, so rounding at
// the cell planes never picks a wrong cell. With empty-space skipping a block whose max < iso is
// left at its exit without loading a cell, and the DDA restarts there.
fn exact_occluded(o: vec3<f32>, w: vec3<f32>, start: vec3<i32>, start_corners: array<f32, 8>) -> bool {
    let inv = safe_inv(w);
    let range = ao_ray_range(o, inv);
    var t = range.x;
    let t_end = range.y;
    if !(t_end >= t) {
        return false;
    }
    let iso = params.iso;
    let ess = skipping();
    let n = vec3<i32>(params.dims.xyz);
    let multi = n > vec3<i32>(1);
    let top = max(n - 2, vec3<i32>(0));
    let d1 = select(vec3<i32>(0), vec3<i32>(1), multi);
    let level = ao_level();
    let coarse = coarse_level();
    // Voxels per unit t; an axis that (practically) does not move is never stepped: its cell
    // still comes from each segment's midpoint.
    let du = w / params.spacing.xyz;
    let nudge = 5e-4 * min(min(params.spacing.x, params.spacing.y), params.spacing.z);
    let moving = multi & (abs(du) > vec3<f32>(1e-10));
    let du_safe = select(vec3<f32>(1.0), du, moving);
    let step = select(vec3<f32>(0.0), sign(du), moving);
    // The DDA's start (t_init, u_init); the next cell plane per axis and the t where it is crossed.
    var t_init = t;
    var u_init = to_voxel(o + t * w).xyz;
    var plane = select(ceil(u_init) - 1.0, floor(u_init) + 1.0, du > vec3<f32>(0.0));
    var next = select(vec3<f32>(T_NEVER), t_init + (plane - u_init) / du_safe, moving);
    // Each pass enters a new cell or leaves a block (plus the odd empty segment where two planes
    // are crossed a rounding error apart).
    // The host's cap (`exact_walk_cap`: the whole box's, or the radius' where tighter).
    let max_iter = params.ao_pass.y;
    // The last loaded cell and its corners (index dx + 2 dy + 4 dz): at first the caller's cell of
    // the rays' origin, in which or next to which the walk starts.
    let stride = vec3<u32>(d1) * vec3<u32>(1u, u32(n.x), u32(n.x * n.y));
    var prev = start;
    var k0 = start_corners[0];
    var k1 = start_corners[1];
    var k2 = start_corners[2];
    var k3 = start_corners[3];
    var k4 = start_corners[4];
    var k5 = start_corners[5];
    var k6 = start_corners[6];
    var k7 = start_corners[7];
    for (var it = 0u; it < max_iter; it += 1u) {
        let t1 = max(min(min(next.x, next.y), min(next.z, t_end)), t);
        let um = u_init + (0.5 * (t + t1) - t_init) * du;
        let cell = clamp(vec3<i32>(floor(um)), vec3<i32>(0), top);
        if ess {
            // Blocks are indexed by global cell (object space: the buffer holds a brick).
            let gcell = cell + data_offset_cells();
            let b = level_block(level, gcell);
            let m = level_range(level, b);
            if m.y < iso {
                // Hierarchical: where the coarse block around it is empty too, leave that instead.
                // At least a sliver past t: where rounding puts the block's exit at or before t
                // (a DDA restart a hair before the face), the walk would otherwise stand still
                // and run out of iterations (found on the CT's anisotropic voxels). The field at
                // the face is below iso (the face samples are the empty block's), so a sliver of
                // nudge voxels cannot step over a crossing.
                let tb = max(max(empty_exit(level, coarse, b, gcell, o, inv, iso), t1), t + nudge);
                if tb >= t_end {
                    return false;
                }
                t = tb;
                t_init = tb;
                u_init = to_voxel(o + tb * w).xyz;
                plane = select(ceil(u_init) - 1.0, floor(u_init) + 1.0, du > vec3<f32>(0.0));
                next = select(vec3<f32>(T_NEVER), t_init + (plane - u_init) / du_safe, moving);
                continue;
            }
            // Early exit: the segment lies in a block whose every sample is >= iso, so f >= iso
            // on it (a trilinear blend is at least its smallest corner): occluded, no fetch.
            if (params.perf.x & PERF_BLOCK_MIN_EXIT) != 0u && m.x >= iso {
                return true;
            }
            // Neither decision was taken on the block's min/max: the whole volume's might have been.
            mark_block(b, level.cells);
        }
        // The cell's 8 corners, loaded 4 at a time (one face: a storage load costs per lane on a
        // SIMD CPU driver, masked lanes included, so the fewer load sites the pass has, the
        // better). Where the cell is the last loaded one (a ray's first cell, mostly), none is
        // loaded; where it is that cell's neighbour across one face (a step of the walk), 4
        // corners are that cell's and the far face is loaded. Elsewhere (a restart after an empty
        // block, two planes crossed at once) the pass loads the cell's low x face, labels it the
        // far face of a cell below in x and leaves the segment to the next pass, which is then
        // a step. (The walk's cap allows for it: each such extra pass follows a block exit or a
        // crossing of two planes, and the cap counts two passes for each.)
        let dc = cell - prev;
        let same = all(dc == vec3<i32>(0));
        let ad = abs(dc);
        let one = ad.x + ad.y + ad.z == 1;
        // The axis of the step (x where there is none) and whether it goes up (not where none).
        let ax = !one || ad.x == 1;
        let ay = one && ad.y == 1;
        let up = one && dc.x + dc.y + dc.z > 0;
        // Strides of the step's axis (sa) and of the face's two axes (sp, sq: x before y before z).
        let sa = select(select(stride.z, stride.y, ay), stride.x, ax);
        let sp = select(stride.x, stride.y, ax);
        let sq = select(stride.y, stride.z, ax || ay);
        let base = u32(cell.x + n.x * (cell.y + n.y * cell.z));
        let far = base + select(0u, sa, up);
        var f0 = 0.0;
        var f1 = 0.0;
        var f2 = 0.0;
        var f3 = 0.0;
        if !same {
            if BRICKED {
                // The same four samples by their coordinates (a bricked volume has no linear
                // index; recovering one is three integer divisions, lane by lane on a CPU driver).
                let ua = select(select(vec3<i32>(0, 0, 1), vec3<i32>(0, 1, 0), ay), vec3<i32>(1, 0, 0), ax);
                let up_ = select(vec3<i32>(1, 0, 0), vec3<i32>(0, 1, 0), ax) * d1;
                let uq = select(vec3<i32>(0, 1, 0), vec3<i32>(0, 0, 1), ax || ay) * d1;
                let fc = cell + select(vec3<i32>(0), ua * d1, up);
                // One load site for the four (each site inlines the lookup and its fallback).
                for (var q = 0u; q < 4u; q += 1u) {
                    let c = fc + select(vec3<i32>(0), up_, (q & 1u) != 0u) + select(vec3<i32>(0), uq, q >= 2u);
                    let f = bricked_sample(c);
                    f0 = select(f0, f, q == 0u);
                    f1 = select(f1, f, q == 1u);
                    f2 = select(f2, f, q == 2u);
                    f3 = select(f3, f, q == 3u);
                }
            } else {
                f0 = voxel_at(far);
                f1 = voxel_at(far + sp);
                f2 = voxel_at(far + sq);
                f3 = voxel_at(far + sp + sq);
            }
        }
        if !one && !same {
            prev = cell - vec3<i32>(1, 0, 0);
            k1 = f0;
            k3 = f1;
            k5 = f2;
            k7 = f3;
            continue;
        }
        fetches += 1u;
        // The near face: the last cell's far face.
        let n0 = select(select(k0, k4, up), select(select(k0, k2, up), select(k0, k1, up), ax), ax || ay);
        let n1 = select(select(k1, k5, up), select(select(k1, k3, up), select(k2, k3, up), ax), ax || ay);
        let n2 = select(select(k2, k6, up), select(select(k4, k6, up), select(k4, k5, up), ax), ax || ay);
        let n3 = select(select(k3, k7, up), select(select(k5, k7, up), select(k6, k7, up), ax), ax || ay);
        // Low (l) and high (h) face along the step's axis, each indexed by its other two axes.
        let l0 = select(f0, n0, up);
        let l1 = select(f1, n1, up);
        let l2 = select(f2, n2, up);
        let l3 = select(f3, n3, up);
        let h0 = select(n0, f0, up);
        let h1 = select(n1, f1, up);
        let h2 = select(n2, f2, up);
        let h3 = select(n3, f3, up);
        // Back to corner order dx + 2 dy + 4 dz (the same cell's as they are).
        k0 = select(l0, k0, same);
        k1 = select(select(select(l1, l1, ay), h0, ax), k1, same);
        k2 = select(select(select(l2, h0, ay), l1, ax), k2, same);
        k3 = select(select(select(l3, h1, ay), h1, ax), k3, same);
        k4 = select(select(select(h0, l2, ay), l2, ax), k4, same);
        k5 = select(select(select(h1, l3, ay), h2, ax), k5, same);
        k6 = select(select(select(h2, h2, ay), l3, ax), k6, same);
        k7 = select(h3, k7, same);
        prev = cell;
        let c = array<f32, 8>(k0, k1, k2, k3, k4, k5, k6, k7);
        if cell_max(c) >= iso {
            let x0 = select(vec3<f32>(0.0), u_init + (t - t_init) * du - vec3<f32>(cell), multi);
            let d = select(vec3<f32>(0.0), (t1 - t) * du, multi);
            if cell_reaches(c, x0, d, iso) {
                return true;
            }
        }
        if t1 >= t_end {
            return false;
        }
        let crossed = moving & (next <= vec3<f32>(t1));
        plane = select(plane, plane + step, crossed);
        next = select(next, t_init + (plane - u_init) / du_safe, crossed);
        t = t1;
    }
    return false;
}

// The trilinear interpolant's own gradient at p inside p's cell (world units): the twin of
// `Volume::cell_gradient`. One fetch (the cell's 8 corners).
fn cell_gradient(p: vec3<f32>) -> vec3<f32> {
    fetches += 1u;
    let n = vec3<i32>(params.dims.xyz);
    let x = clamp(to_voxel(p).xyz, vec3<f32>(0.0), vec3<f32>(max(n - 1, vec3<i32>(0))));
    let i0 = min(vec3<i32>(floor(x)), max(n - 2, vec3<i32>(0)));
    let f = x - vec3<f32>(i0);
    let i1 = i0 + select(vec3<i32>(0), vec3<i32>(1), n > vec3<i32>(1));
    let c0 = voxel(i0.x, i0.y, i0.z);
    let c1 = voxel(i1.x, i0.y, i0.z);
    let c2 = voxel(i0.x, i1.y, i0.z);
    let c3 = voxel(i1.x, i1.y, i0.z);
    let c4 = voxel(i0.x, i0.y, i1.z);
    let c5 = voxel(i1.x, i0.y, i1.z);
    let c6 = voxel(i0.x, i1.y, i1.z);
    let c7 = voxel(i1.x, i1.y, i1.z);
    let gx = mix(mix(c1 - c0, c3 - c2, f.y), mix(c5 - c4, c7 - c6, f.y), f.z);
    let gy = mix(mix(c2 - c0, c3 - c1, f.x), mix(c6 - c4, c7 - c5, f.x), f.z);
    let gz = mix(mix(c4 - c0, c5 - c1, f.x), mix(c6 - c2, c7 - c3, f.x), f.y);
    return vec3<f32>(gx, gy, gz) / params.spacing.xyz;
}

// Whether the hit at p with normal n is a cap: n is a box face's outward normal exactly (as the
// isosurface kernel writes it) and p lies on that face.
fn is_cap(p: vec3<f32>, n: vec3<f32>) -> bool {
    let tol = 1e-3 * params.spacing.xyz;
    let lo = (n == vec3<f32>(-1.0)) & (abs(p - params.box_min.xyz) <= tol);
    let hi = (n == vec3<f32>(1.0)) & (abs(p - params.box_max.xyz) <= tol);
    return dot(abs(n), vec3<f32>(1.0)) == 1.0 && any(lo | hi);
}

// Ng at p reached along dir: -grad / |grad| of the cell's own gradient, turned so Ng . dir <= 0;
// -dir where it vanishes.
fn geometric_normal(p: vec3<f32>, dir: vec3<f32>) -> vec3<f32> {
    let g = cell_gradient(p);
    let len = length(g);
    if !(len > 0.0) || len != len || len > 3.4e38 {
        return -dir;
    }
    let ng = -g / len;
    return select(ng, -ng, dot(ng, dir) > 0.0);
}

// DESIGN.md "AO": a direction under p's tangent plane (w . Ng <= 0) is occluded, without marching
// (the twin of the reference's `under_tangent_plane`).
fn under_tangent_plane(w: vec3<f32>, ng: vec3<f32>) -> bool {
    return dot(w, ng) <= 0.0;
}

// The 2008 march (baseline): texture-space steps of 0.01 from the hit point p itself.
fn seed_occluded(p: vec3<f32>, w: vec3<f32>, f_p: f32) -> bool {
    let size = params.box_max.xyz - params.box_min.xyz;
    let ext = select(size, vec3<f32>(1.0), size <= vec3<f32>(0.0));
    let q = (p - params.box_min.xyz) / ext;
    let iso = params.iso;
    var vpold = f_p;
    for (var s = 1u; s <= 90u; s += 1u) {
        let qt = q + (f32(s) * 0.01) * w;
        if any(qt < vec3<f32>(0.0)) || any(qt > vec3<f32>(1.0)) {
            return false;
        }
        let vp = field(params.box_min.xyz + qt * ext);
        if vpold < iso && iso < vp {
            return true;
        }
        vpold = vp;
    }
    return false;
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    params = frame_params;
    load_bricks();
    if gid.x >= params.rect_size.x || gid.y >= params.rect_size.y {
        return;
    }
    let idx = gid.x + gid.y * params.rect_size.x;
    if !is_hit(in_color[idx].w) {
        return;
    }
    let px = params.rect_origin + gid.xy;
    let dir = pixel_dir(px);
    let g = in_geometry[idx];
    let p = params.eye.xyz + g.w * dir;
    let ns = select(-g.xyz, g.xyz, dot(g.xyz, -dir) >= 0.0);
    let basis = onb(ns);
    // The pixel's samples this frame: the frame's, or where a reprojection spent them by history
    // (`ao_pass.z`, the most a pixel takes, not 0), the number it wrote into the position sum's w
    // (held to [1, ao_pass.z], which the dispatches cover).
    var n_samples = params.ao_samples;
    if params.ao_pass.z != 0u {
        n_samples = clamp(u32(acc_pos[idx].w), 1u, params.ao_pass.z);
    }
    // This dispatch's samples [first, last) of the pixel's n_samples.
    let first = min(ao_dispatch.x * params.ao_pass.x, n_samples);
    let last = min(first + params.ao_pass.x, n_samples);
    if n_samples > 0u && first >= last {
        return;
    }
    let any_path = AO_PATH == AO_PATH_ANY;
    let want_rays = any_path && params.ibl == IBL_RAYS;
    let exact = !any_path || params.ao_exact == 1u;
    // The bent normal where no ray is open: the hemisphere's axis (N_s for the seed and AO off).
    var axis = ns;

    var occluded = 0u;
    var bent = vec3<f32>(0.0);
    var rays = vec3<f32>(0.0);
    if any_path && params.ao_method == AO_SEED {
        let f_p = field(p);
        for (var i = first; i < last; i += 1u) {
            let u = -1.0 + 2.0 * f32(i) / f32(n_samples);
            let x0 = 2.0 * u - 1.0;
            let r2 = 2.0 * x0 * x0;
            if r2 > 1.0 {
                continue; // skipped, yet counted in the denominator
            }
            let w = x0 * basis.t + x0 * basis.bt + sqrt(1.0 - r2) * ns;
            if seed_occluded(p, w, f_p) {
                occluded += 1u;
            } else {
                bent += w;
                if want_rays {
                    rays += env_lookup(w);
                }
            }
        }
    } else if n_samples > 0u {
        var ng = g.xyz;
        if !is_cap(p, g.xyz) {
            ng = geometric_normal(p, dir);
        }
        // The hemisphere's axis: N as it is; Ng where N is the vanished gradient's fallback -dir.
        axis = select(g.xyz, ng, all(g.xyz == -dir));
        let axis_basis = onb(axis);
        let key = pixel_key(px.x, px.y, params.frame, params.seed);
        let o = p + params.ao_offset * ng;
        // The cell of o and its corners, loaded once for all the pixel's rays: each exact walk
        // starts in it or next to it.
        var start = vec3<i32>(0);
        var start_corners = array<f32, 8>();
        if exact {
            let n = vec3<i32>(params.dims.xyz);
            start = clamp(vec3<i32>(floor(to_voxel(o).xyz)), vec3<i32>(0), max(n - 2, vec3<i32>(0)));
            let i1 = start + select(vec3<i32>(0), vec3<i32>(1), n > vec3<i32>(1));
            start_corners = array<f32, 8>(
                voxel(start.x, start.y, start.z),
                voxel(i1.x, start.y, start.z),
                voxel(start.x, i1.y, start.z),
                voxel(i1.x, i1.y, start.z),
                voxel(start.x, start.y, i1.z),
                voxel(i1.x, start.y, i1.z),
                voxel(start.x, i1.y, i1.z),
                voxel(i1.x, i1.y, i1.z),
            );
        }
        // The default (exact, no environment rays) in a loop of its own: a SIMD CPU driver runs
        // every branch of a loop's body on every pass, masked, so the marched test and the
        // environment lookup (storage loads each) would cost every sample without a lane taking
        // them; outside the loop they cost once per pixel.
        if exact && !want_rays {
            for (var i = first; i < last; i += 1u) {
                let w = cosine_direction(axis, axis_basis, ao_point(params.ao_sequence, i, key));
                if under_tangent_plane(w, ng) {
                    occluded += 1u;
                } else if exact_occluded(o, w, start, start_corners) {
                    occluded += 1u;
                } else {
                    bent += w;
                }
            }
        } else if any_path {
            for (var i = first; i < last; i += 1u) {
                let w = cosine_direction(axis, axis_basis, ao_point(params.ao_sequence, i, key));
                var hit: bool;
                if under_tangent_plane(w, ng) {
                    hit = true;
                } else if exact {
                    hit = exact_occluded(o, w, start, start_corners);
                } else {
                    hit = ours_occluded(o, w);
                }
                if hit {
                    occluded += 1u;
                } else {
                    bent += w;
                    if want_rays {
                        rays += env_lookup(w);
                    }
                }
            }
        }
    }
    // This dispatch's A over its own samples; its share of the frame (its samples over the
    // frame's: the dispatches' shares add up to 1, a single dispatch has share 1 exactly; a pixel
    // whose samples were spent by history adds n_samples / ao_samples in all).
    let taken = last - first;
    var a = 0.0;
    var share = 1.0;
    if n_samples > 0u {
        a = f32(occluded) / f32(taken);
        share = f32(taken) / f32(params.ao_samples);
    }
    let bl = length(bent);
    let bent_n = select(axis, bent / bl, bl > 0.0);
    var e: vec3<f32>;
    switch params.ibl {
        case IBL_SEED: {
            e = env_lookup(bent_n) * (1.0 - a);
        }
        case IBL_BENT: {
            e = sh_irradiance(bent_n) * (1.0 - a);
        }
        case IBL_RAYS: {
            if n_samples > 0u {
                e = rays / f32(taken);
            } else {
                e = sh_irradiance(ns);
            }
        }
        default: {
            e = params.ambient.xyz * (1.0 - a);
        }
    }
    acc_ao[idx] += share * vec4<f32>(bent_n, a);
    acc_ibl[idx] += vec4<f32>(share * e, share);
    if params.positions != 0u {
        acc_pos[idx] += vec4<f32>(share * p, 0.0);
    }
    out_fetches[idx] += fetches;
}
