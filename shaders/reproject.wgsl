// Kernel::Reproject (daemon/render/src/gpu/reproject.rs): a tile's running sums carried over from
// its previous frame when only the camera moved (temporal reprojection), one invocation per pixel
// of the (low) rectangle, after the isosurface kernel of the new frame and before the AO kernel.
// The rule and its CPU twin are daemon/render/src/reproject.rs:
// - a hit p = eye + depth dir of the new frame is projected into the previous frame's camera and
//   rectangle; the previous pixel is the one whose square holds the projection (nearest pixel);
// - it is accepted where that pixel had a hit, p lies within `plane_tolerance` of the previous
//   pixel's footprint (depth * 2 tan(fov_y / 2) / H) from its tangent plane, the normals agree
//   (dot >= `normal_agreement`) and both frames see the same side of the surface;
// - the new sums are the previous pixel's, scaled to an age of at most `max_age` frames:
//   sums * min(1, max_age / weight), the weight (frames' worth of samples) being the w of the E sum;
// - every other pixel (no hit, outside the previous rectangle, rejected) starts at 0.
//
//#include camera.wgsl

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
    _pad0: u32,
}

// A read-only storage buffer, not a uniform: see frame.wgsl (lavapipe's uniform inlining).
@group(0) @binding(0) var<storage, read> params: ReprojectParams;
// This frame's isosurface kernel: w = 1 on a hit; N (outward) and depth (w).
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

// The index of the previous rectangle's pixel whose square holds world point p, or -1.
fn previous_pixel(p: vec3<f32>) -> i32 {
    let d = p - params.prev_eye.xyz;
    let z = dot(d, params.prev_forward.xyz);
    if !(z > 0.0) {
        return -1;
    }
    let size = vec2<f32>(params.prev_full_size);
    let tan_half = params.prev_forward.w;
    let sx = dot(d, params.prev_right.xyz) / z;
    let sy = dot(d, params.prev_up.xyz) / z;
    // camera_ray inverted: sx = (2 (x + 0.5) / W - 1) tan W / H, sy = (1 - 2 (y + 0.5) / H) tan.
    let u = (sx / (tan_half * size.x / size.y) + 1.0) * 0.5 * size.x;
    let v = (1.0 - sy / tan_half) * 0.5 * size.y;
    let lo = vec2<f32>(params.prev_rect_origin);
    let hi = lo + vec2<f32>(params.prev_rect_size);
    if !(u >= lo.x && v >= lo.y && u < hi.x && v < hi.y) {
        return -1;
    }
    let q = vec2<u32>(u32(floor(u)), u32(floor(v))) - params.prev_rect_origin;
    return i32(q.x + q.y * params.prev_rect_size.x);
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if gid.x >= params.rect_size.x || gid.y >= params.rect_size.y {
        return;
    }
    let i = gid.x + gid.y * params.rect_size.x;
    var ao = vec4<f32>(0.0);
    var ibl = vec4<f32>(0.0);
    if in_color[i].w >= 0.5 {
        let dir = camera_ray(params.rect_origin + gid.xy, params.full_size, params.forward, params.right.xyz, params.up.xyz);
        let g = in_geometry[i];
        let p = params.eye.xyz + g.w * dir;
        let j = previous_pixel(p);
        if j >= 0 && prev_color[j].w >= 0.5 {
            let ju = u32(j);
            let w = params.prev_rect_size.x;
            let qpx = params.prev_rect_origin + vec2<u32>(ju % w, ju / w);
            let qdir = camera_ray(qpx, params.prev_full_size, params.prev_forward, params.prev_right.xyz, params.prev_up.xyz);
            let gq = prev_geometry[ju];
            let q = params.prev_eye.xyz + gq.w * qdir;
            let footprint = gq.w * 2.0 * params.prev_forward.w / f32(params.prev_full_size.y);
            let plane = abs(dot(gq.xyz, p - q));
            let agree = dot(g.xyz, gq.xyz) >= params.normal_agreement;
            let same_side = (dot(g.xyz, dir) < 0.0) == (dot(gq.xyz, qdir) < 0.0);
            if plane <= params.plane_tolerance * footprint && agree && same_side {
                let weight = prev_ibl[ju].w;
                var keep = 1.0;
                if weight > params.max_age {
                    keep = params.max_age / weight;
                }
                ao = prev_ao[ju] * keep;
                ibl = prev_ibl[ju] * keep;
            }
        }
    }
    acc_ao[i] = ao;
    acc_ibl[i] = ibl;
}
