// Kernel::Reproject (daemon/render/src/gpu/reproject.rs): a tile's running sums carried over from
// its previous frame when only the camera moved (temporal reprojection), one invocation per pixel
// of the (low) rectangle, after the isosurface kernel of the new frame and before the AO kernel.
// The rule and its CPU twin are daemon/render/src/reproject.rs:
// - a hit p = eye + depth dir of the new frame is projected into the previous frame's camera; the
//   four previous pixels around the projection (bilinear taps) are candidates (with `nearest`,
//   the one the projection falls in, at weight 1);
// - a tap counts where it lies in the previous rectangle, had a hit, p lies within
//   `plane_tolerance` of its footprint (depth * 2 tan(fov_y / 2) / H) from its tangent plane, the
//   normals agree (dot >= `normal_agreement`) and both frames see the same side of the surface;
// - the new sums are the counting taps' sums blended by their bilinear weights, with
//   `accepted_share` (the renderer's rule) not renormalized: the rejected taps' share of the
//   history is dropped; without it renormalized to 1,
//   scaled to an age of at most `max_age` frames: sums * min(1, max_age / weight), the weight
//   (frames' worth of samples) being the w of the E sum;
//   before the cap, a history whose samples stand too far from p is scaled down
//   (`drift_tolerance`): the carried position sum over the weight is where the history's samples
//   were taken, on average; at a distance d of more than the tolerance (in footprints of p) the
//   sums are multiplied by (tolerance / d)^2;
// - every other pixel (no hit, no tap counting) starts at 0;
// - at every hit the position sum's w is the number of AO samples the pixel takes this frame
//   (`Spending` in reproject.rs): S, or by history S * clamp(target - weight, least, most) plus a
//   draw in [0, 1) per pixel and frame, rounded down, at least 1; the AO kernel reads it.
//
//#include camera.wgsl
//#include sampling.wgsl
//#include hit.wgsl

struct ReprojectParams {
    eye: vec4<f32>,              // this frame's camera
    forward: vec4<f32>,          // w: tan(fov_y / 2)
    right: vec4<f32>,
    up: vec4<f32>,
    prev_eye: vec4<f32>,         // the previous frame's camera
    prev_forward: vec4<f32>,     // w: tan(fov_y / 2)
    prev_right: vec4<f32>,
    prev_up: vec4<f32>,
    full_size: vec2<u32>,        // this frame's (low) full image
    rect_origin: vec2<u32>,      // this frame's rectangle in it
    rect_size: vec2<u32>,
    prev_full_size: vec2<u32>,   // the previous frame's
    prev_rect_origin: vec2<u32>,
    prev_rect_size: vec2<u32>,
    max_age: f32,                // frames of history kept at most
    plane_tolerance: f32,        // plane distance accepted, in previous pixel footprints
    normal_agreement: f32,       // the least dot of the two normals accepted
    nearest: u32,                // 1: the previous pixel the projection falls in, not bilinear
    accepted_share: u32,         // 1: the blend not renormalized (rejected taps' share dropped)
    drift_tolerance: f32,        // footprints the history's samples may stand from p, unscaled
    samples: u32,                // the frame's AO samples a pixel (S, FrameParams' ao_samples)
    frame: u32,                  // the frame's index in the sample sequence (FrameParams' frame)
    seed: u32,
    spending: u32,               // SPENDING_UNIFORM (S everywhere) or SPENDING_BY_HISTORY
    spend_target: f32,           // by history: S * clamp(target - weight, least, most) samples
    spend_least: f32,
    spend_most: f32,
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
}

// A read-only storage buffer, not a uniform: see frame.wgsl (lavapipe's uniform inlining).
@group(0) @binding(0) var<storage, read> reproject_params: ReprojectParams;
// The parameters as the functions read them: a private copy the entry point fills first (a
// storage read on lavapipe is a loop over the SIMD lanes; see denoise.wgsl).
var<private> params: ReprojectParams;
// This frame's isosurface kernel: w the hit flag (hit.wgsl); N (outward) and depth (w).
@group(0) @binding(1) var<storage, read> in_color: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> in_geometry: array<vec4<f32>>;
// The previous frame's: hit flag, geometry, and its running sums (bent + A; E rgb, weight w).
@group(0) @binding(3) var<storage, read> prev_color: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> prev_geometry: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> prev_ao: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> prev_ibl: array<vec4<f32>>;
// This frame's running sums, before the AO kernel adds its frame.
@group(0) @binding(7) var<storage, read_write> acc_ao: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> acc_ibl: array<vec4<f32>>;
// The previous frame's summed sample positions, and this frame's carried over.
@group(0) @binding(9) var<storage, read> prev_pos: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> acc_pos: array<vec4<f32>>;

// Where world point p falls in the previous full image, in pixels (x right, y down; pixel
// (i, j) covers [i, i + 1) x [j, j + 1)), or a negative z where it lies behind the camera.
fn previous_position(p: vec3<f32>) -> vec3<f32> {
    let d = p - params.prev_eye.xyz;
    let z = dot(d, params.prev_forward.xyz);
    if !(z > 0.0) {
        return vec3<f32>(0.0, 0.0, -1.0);
    }
    let size = vec2<f32>(params.prev_full_size);
    let tan_half = params.prev_forward.w;
    let sx = dot(d, params.prev_right.xyz) / z;
    let sy = dot(d, params.prev_up.xyz) / z;
    // camera_ray inverted: sx = (2 (x + 0.5) / W - 1) tan W / H, sy = (1 - 2 (y + 0.5) / H) tan.
    let u = (sx / (tan_half * size.x / size.y) + 1.0) * 0.5 * size.x;
    let v = (1.0 - sy / tan_half) * 0.5 * size.y;
    return vec3<f32>(u, v, z);
}

// Whether the previous frame's pixel q (full-image coordinates) saw the surface at p with normal
// n along ray dir: inside the previous rectangle, a hit, p near its tangent plane, the normals
// agreeing, the same side seen.
fn consistent(q: vec2<i32>, p: vec3<f32>, n: vec3<f32>, dir: vec3<f32>) -> bool {
    let lo = vec2<i32>(params.prev_rect_origin);
    let hi = lo + vec2<i32>(params.prev_rect_size);
    if q.x < lo.x || q.y < lo.y || q.x >= hi.x || q.y >= hi.y {
        return false;
    }
    let local = vec2<u32>(q - lo);
    let j = local.x + local.y * params.prev_rect_size.x;
    if !is_hit(prev_color[j].w) {
        return false;
    }
    let qdir = camera_ray(vec2<u32>(q), params.prev_full_size, params.prev_forward, params.prev_right.xyz, params.prev_up.xyz);
    let gq = prev_geometry[j];
    let at = params.prev_eye.xyz + gq.w * qdir;
    let footprint = gq.w * 2.0 * params.prev_forward.w / f32(params.prev_full_size.y);
    let plane = abs(dot(gq.xyz, p - at));
    let agree = dot(n, gq.xyz) >= params.normal_agreement;
    let same_side = (dot(n, dir) < 0.0) == (dot(gq.xyz, qdir) < 0.0);
    return plane <= params.plane_tolerance * footprint && agree && same_side;
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    params = reproject_params;
    if gid.x >= params.rect_size.x || gid.y >= params.rect_size.y {
        return;
    }
    let i = gid.x + gid.y * params.rect_size.x;
    var ao = vec4<f32>(0.0);
    var ibl = vec4<f32>(0.0);
    var pos = vec4<f32>(0.0);
    if is_hit(in_color[i].w) {
        let dir = camera_ray(params.rect_origin + gid.xy, params.full_size, params.forward, params.right.xyz, params.up.xyz);
        let g = in_geometry[i];
        let p = params.eye.xyz + g.w * dir;
        let at = previous_position(p);
        if at.z > 0.0 {
            // The four previous pixels around the projection, bilinear weights over the
            // consistent ones (nearest: the taps' base is the pixel the projection falls in, at
            // weight 1, the other taps at 0).
            var f = at.xy - vec2<f32>(0.5);
            if params.nearest != 0u {
                f = floor(at.xy);
            }
            let base = floor(f);
            let t = f - base;
            let b = vec2<i32>(base);
            var wsum = 0.0;
            var sum_ao = vec4<f32>(0.0);
            var sum_ibl = vec4<f32>(0.0);
            var sum_pos = vec4<f32>(0.0);
            for (var k = 0; k < 4; k += 1) {
                let o = vec2<i32>(k & 1, k >> 1u);
                let w = select(1.0 - t.x, t.x, o.x == 1) * select(1.0 - t.y, t.y, o.y == 1);
                let q = b + o;
                if w > 0.0 && consistent(q, p, g.xyz, dir) {
                    let local = vec2<u32>(q - vec2<i32>(params.prev_rect_origin));
                    let j = local.x + local.y * params.prev_rect_size.x;
                    wsum += w;
                    sum_ao += w * prev_ao[j];
                    sum_ibl += w * prev_ibl[j];
                    sum_pos += w * prev_pos[j];
                }
            }
            if wsum > 0.0 {
                let norm = select(wsum, 1.0, params.accepted_share != 0u);
                ao = sum_ao / norm;
                ibl = sum_ibl / norm;
                pos = sum_pos / norm;
                if ibl.w > 0.0 {
                    let footprint = g.w * 2.0 * params.forward.w / f32(params.full_size.y);
                    let d = length(pos.xyz / ibl.w - p) / footprint;
                    if d > params.drift_tolerance {
                        let r = params.drift_tolerance / d;
                        ao *= r * r;
                        ibl *= r * r;
                        pos *= r * r;
                    }
                }
                let weight = ibl.w;
                if weight > params.max_age {
                    let keep = params.max_age / weight;
                    ao *= keep;
                    ibl *= keep;
                    pos *= keep;
                }
            }
        }
    }
    pos.w = 0.0;
    if is_hit(in_color[i].w) {
        let px = params.rect_origin + gid.xy;
        pos.w = f32(samples_taken(ibl.w, spend_key(px.x, px.y)));
    }
    acc_ao[i] = ao;
    acc_ibl[i] = ibl;
    acc_pos[i] = pos;
}

// `Spending::code()` in reproject.rs (checked by a test).
const SPENDING_UNIFORM: u32 = 0u;
const SPENDING_BY_HISTORY: u32 = 1u;

// `spend_key` in reproject.rs (the same constant, checked by a test).
const SPEND_SALT: u32 = 0x5bd1e995u;

fn spend_key(px: u32, py: u32) -> u32 {
    return hash(pixel_key(px, py, params.frame, params.seed) ^ SPEND_SALT);
}

// The AO samples a pixel carrying `weight` frames' worth of history takes (`Spending::samples`).
fn samples_taken(weight: f32, key: u32) -> u32 {
    if params.spending != SPENDING_BY_HISTORY {
        return params.samples;
    }
    let x = clamp(params.spend_target - weight, params.spend_least, params.spend_most) * f32(params.samples);
    let u = f32(key >> 8u) * (1.0 / 16777216.0);
    return max(u32(floor(x + u)), 1u);
}
