// Kernel::Denoise (daemon/render/src/gpu/denoise.rs): one a-trous pass of the edge-aware spatial
// filter of the occlusion and IBL terms, one invocation per pixel of the (low) rectangle the other
// kernels ran over. The filter's definition and its CPU twin are daemon/render/src/denoise.rs: the
// B3-spline weights at offsets step * (-2 ..= 2) per axis, times the plane, normal and occlusion
// stops; the variance carried as sum w^2 var / (sum w)^2; no-hit pixels and pixels outside the
// rectangle are no one's neighbour.
//
// A prepare dispatch first writes, per pixel, what the passes' taps read: the raw signal (A, E.rgb:
// the running sums divided by the frame count, or by each pixel's own weight where the history
// was reprojected) and the guide (the hit's view-space position, xyz, and the binomial variance,
// w; w = -1 where there is no hit). Each pass then reads the previous one's signal and guide
// and the normal (three loads a tap: on a SIMD CPU driver a load is a loop over the lanes) and
// writes its own. The last pass writes `raw + strength (filtered - raw)` in running-sum form
// (E * frames in rgb, A * frames in w) into `out_denoised`, which compose reads in place of the
// running sum of E.
//
//#include camera.wgsl
//#include hit.wgsl

struct DenoiseParams {
    forward: vec4<f32>,     // w: tan(fov_y / 2)
    right: vec4<f32>,
    up: vec4<f32>,
    full_size: vec2<u32>,   // the (low) full image
    rect_origin: vec2<u32>, // the rectangle filtered, in the full image
    rect_size: vec2<u32>,
    step: u32,              // this pass's step, pixels
    prepare: u32,           // 1: the prepare dispatch (no filtering)
    last: u32,              // 1: write `out_denoised`
    frames: u32,            // frames in the running sums
    samples: f32,           // visibility samples per pixel in all (AO samples x frames)
    strength: f32,          // the filtered value's share of the output (last pass)
    sigma_plane: f32,
    sigma_occlusion: f32,
    normal_squarings: u32,  // the normal stop is max(n_p . n_q, 0)^(2^normal_squarings)
    per_pixel: u32,         // 1: a pixel's frames are its weight (acc_ibl.w), not `frames`
    frame_samples: f32,     // AO samples per frame (per_pixel)
    full_strength: f32,     // samples up to which the filter applies in full (per_pixel)
    _pad1: u32,
    _pad2: u32,
}

// One entry per pass, at a dynamic offset (a read-only storage buffer: see frame.wgsl).
@group(0) @binding(0) var<storage, read> pass_params: DenoiseParams;
// The pass's parameters as the functions read them: a private copy the entry point fills first,
// so that the 25 taps read registers (on lavapipe a storage read is a loop over the SIMD lanes,
// with a bounds check per lane and component, wherever it stands).
var<private> params: DenoiseParams;
// From the isosurface kernel: w the hit flag (hit.wgsl).
@group(0) @binding(1) var<storage, read> in_color: array<vec4<f32>>;
// From the isosurface kernel: N (outward) and depth (w).
@group(0) @binding(2) var<storage, read> in_geometry: array<vec4<f32>>;
// Running sums of the AO kernel: bent normal + A (w); E (rgb).
@group(0) @binding(3) var<storage, read> acc_ao: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> acc_ibl: array<vec4<f32>>;
// The previous pass's (A, E.rgb), and guide: position (xyz) and variance (w; -1: no hit).
@group(0) @binding(5) var<storage, read> src_signal: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> src_guide: array<vec4<f32>>;
// This pass's (A, E.rgb) and guide.
@group(0) @binding(7) var<storage, read_write> dst_signal: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> dst_guide: array<vec4<f32>>;
// The last pass's output, in running-sum form: E * frames (rgb), A * frames (w).
@group(0) @binding(9) var<storage, read_write> out_denoised: array<vec4<f32>>;

// The B3-spline weight of offset i (-2 ..= 2) along one axis.
fn b3(i: i32) -> f32 {
    let a = abs(i);
    if a == 0 {
        return 0.375;
    }
    if a == 1 {
        return 0.25;
    }
    return 0.0625;
}

// The pixel's ray from this kernel's parameters (camera.wgsl).
fn pixel_dir(px: vec2<u32>) -> vec3<f32> {
    return camera_ray(px, params.full_size, params.forward, params.right.xyz, params.up.xyz);
}

fn position(q: vec2<u32>, depth: f32) -> vec3<f32> {
    return pixel_dir(params.rect_origin + q) * depth;
}

// The frames' worth of samples in pixel i's running sums: the uniform count, or (a reprojected
// history) the pixel's own weight.
fn frames_of(i: u32) -> f32 {
    if params.per_pixel == 1u {
        return acc_ibl[i].w;
    }
    return f32(params.frames);
}

// Visibility samples behind pixel i's estimate.
fn samples_of(i: u32) -> f32 {
    if params.per_pixel == 1u {
        return params.frame_samples * acc_ibl[i].w;
    }
    return params.samples;
}

// The filtered value's share of pixel i's output (`denoise::strength`).
fn strength_of(i: u32) -> f32 {
    if params.per_pixel == 1u {
        let n = samples_of(i);
        if n <= 0.0 {
            return 0.0;
        }
        return min(sqrt(params.full_strength / n), 1.0);
    }
    return params.strength;
}

// The raw (A, E.rgb) of pixel i: the running sums over the frame count.
fn raw(i: u32) -> vec4<f32> {
    let k = frames_of(i);
    return vec4<f32>(acc_ao[i].w / k, acc_ibl[i].xyz / k);
}

fn variance_of(a: f32, n: f32) -> f32 {
    let p = (n * a + 1.0) / (n + 2.0);
    return p * (1.0 - p) / n;
}

// x^(2^normal_squarings) by squarings (a few loop iterations per neighbour, well within
// lavapipe's budget of an invocation's loop iterations).
fn normal_stop(x: f32) -> f32 {
    var y = x;
    for (var k = 0u; k < params.normal_squarings; k += 1u) {
        y = y * y;
    }
    return y;
}

// The guide's w where there is no hit.
const NO_HIT: f32 = -1.0;

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    params = pass_params;
    if gid.x >= params.rect_size.x || gid.y >= params.rect_size.y {
        return;
    }
    let w = params.rect_size.x;
    let i = gid.x + gid.y * w;
    if params.prepare == 1u {
        if !is_hit(in_color[i].w) {
            dst_guide[i] = vec4<f32>(0.0, 0.0, 0.0, NO_HIT);
            return;
        }
        let r = raw(i);
        dst_signal[i] = r;
        dst_guide[i] = vec4<f32>(position(gid.xy, in_geometry[i].w), variance_of(r.x, samples_of(i)));
        return;
    }
    let gp = src_guide[i];
    if gp.w == NO_HIT {
        dst_guide[i] = gp;
        if params.last == 1u {
            out_denoised[i] = acc_ibl[i];
        }
        return;
    }
    let g = in_geometry[i];
    let np = g.xyz;
    let pp = gp.xyz;
    let sp = src_signal[i];
    let pixel_size = 2.0 * params.forward.w / f32(params.full_size.y);
    let footprint = params.sigma_plane * g.w * pixel_size;
    let var_p = gp.w;
    let step = i32(params.step);
    var sum = vec4<f32>(0.0);
    var wsum = 0.0;
    var vsum = 0.0;
    for (var dy = -2; dy <= 2; dy += 1) {
        for (var dx = -2; dx <= 2; dx += 1) {
            let qx = i32(gid.x) + dx * step;
            let qy = i32(gid.y) + dy * step;
            if qx < 0 || qy < 0 || qx >= i32(params.rect_size.x) || qy >= i32(params.rect_size.y) {
                continue;
            }
            let q = u32(qx) + u32(qy) * w;
            let gq = src_guide[q];
            if gq.w == NO_HIT {
                continue;
            }
            let k = b3(dx) * b3(dy);
            let offset = sqrt(f32((dx * dx + dy * dy) * step * step));
            let plane = abs(dot(np, gq.xyz - pp));
            let w_plane = exp(-plane / max(footprint * offset, 1e-20));
            let w_normal = normal_stop(max(dot(np, in_geometry[q].xyz), 0.0));
            let s = src_signal[q];
            let var_q = gq.w;
            // Symmetric: the larger of the two estimates' variances (denoise.rs).
            let sigma_a = params.sigma_occlusion * sqrt(max(max(var_p, var_q), 0.0)) + 1e-6;
            let w_occ = exp(-abs(sp.x - s.x) / sigma_a);
            let wq = k * w_plane * w_normal * w_occ;
            sum += wq * s;
            wsum += wq;
            vsum += wq * wq * var_q;
        }
    }
    var filtered = sp;
    var variance = var_p;
    if wsum > 0.0 {
        filtered = sum / wsum;
        variance = vsum / (wsum * wsum);
    }
    dst_signal[i] = filtered;
    dst_guide[i] = vec4<f32>(pp, variance);
    if params.last == 1u {
        let r = raw(i);
        let v = r + strength_of(i) * (filtered - r);
        // Running-sum form over the uniform count, which compose divides by.
        let k = f32(params.frames);
        out_denoised[i] = vec4<f32>(v.yzw * k, v.x * k);
    }
}
