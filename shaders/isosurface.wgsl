// Kernel::Isosurface (daemon/render/src/gpu/isosurface.rs): primary rays to the first hit of the
// isosurface, exactly as DESIGN.md defines it, then normal, direct shading and the AOVs.
//
// - Ray through the pixel centre of the *full* image (a window of it is rendered: wall tiles).
// - Box entry and exit; outside the box the field is empty, so entering the box where f >= iso is
//   a hit on the box face (a cap) with the face's outward normal.
// - A camera inside the box starts at the eye; inside the object it first has to leave it (the hit
//   is the first up-crossing), like the CPU reference.
// - March with `params.spacing.w` (world units; at most half a voxel by default), skipping blocks
//   whose max < iso (empty-space skipping, when flag bit 0 is set), then bisect the bracketing step
//   `params.refine_steps` times and finish with one secant step.
// - Normal: N = -grad f / |grad f| by central differences (h = one voxel per axis); the direction
//   towards the viewer where the gradient vanishes. Shading uses N turned towards the viewer.
//
//#include volume.wgsl
//#include shading.wgsl

// Twin: `IsoParams` in isosurface.rs (layout checked by a test against this declaration).
struct IsoParams {
    eye: vec4<f32>,
    forward: vec4<f32>,      // w: tan(fov_y / 2)
    right: vec4<f32>,
    up: vec4<f32>,
    light_dir: vec4<f32>,    // towards the light, world space
    light_color: vec4<f32>,
    ambient: vec4<f32>,
    albedo: vec4<f32>,       // w: specular
    background: vec4<f32>,   // w: exposure
    box_min: vec4<f32>,
    box_max: vec4<f32>,
    spacing: vec4<f32>,      // w: march step, world units
    dims: vec4<u32>,         // w: cells per block edge
    block_counts: vec4<u32>, // w: flags (bit 0: empty-space skipping)
    full_size: vec2<u32>,
    window_origin: vec2<u32>,
    window_size: vec2<u32>,
    shading: u32,
    iso: f32,
    shininess: f32,
    refine_steps: u32,
    max_steps: u32,
    _pad: u32,
}

const FLAG_EMPTY_SPACE_SKIPPING: u32 = 1u;

@group(0) @binding(0) var<uniform> params: IsoParams;
@group(0) @binding(1) var<storage, read> volume: array<f32>;
@group(0) @binding(2) var<storage, read> block_minmax: array<vec2<f32>>;
// Per pixel: linear colour after exposure (w: 1 on a hit, else 0).
@group(0) @binding(3) var<storage, read_write> out_color: array<vec4<f32>>;
// Per pixel: N (xyz, outward, unflipped) and depth (w); all 0 without a hit.
@group(0) @binding(4) var<storage, read_write> out_geometry: array<vec4<f32>>;
// Per pixel: trilinear fetches made.
@group(0) @binding(5) var<storage, read_write> out_fetches: array<u32>;

// The block (of `params.dims.w` cells per edge) containing world point p.
fn block_of(p: vec3<f32>) -> vec3<u32> {
    let cells = to_voxel(p).xyz / f32(params.dims.w);
    let c = vec3<i32>(floor(cells));
    return vec3<u32>(clamp(c, vec3<i32>(0), vec3<i32>(params.block_counts.xyz) - 1));
}

fn block_max(b: vec3<u32>) -> f32 {
    let n = params.block_counts.xyz;
    return block_minmax[b.x + n.x * (b.y + n.y * b.z)].y;
}

// Ray parameter where the ray leaves block b (world box of its cells, clamped to the volume box).
fn block_exit(b: vec3<u32>, eye: vec3<f32>, inv_dir: vec3<f32>) -> f32 {
    let bs = f32(params.dims.w);
    let lo = params.box_min.xyz + vec3<f32>(b) * bs * params.spacing.xyz;
    let hi = min(lo + bs * params.spacing.xyz, params.box_max.xyz);
    let t0 = (lo - eye) * inv_dir;
    let t1 = (hi - eye) * inv_dir;
    let tmax = max(t0, t1);
    return min(min(tmax.x, tmax.y), tmax.z);
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if gid.x >= params.window_size.x || gid.y >= params.window_size.y {
        return;
    }
    let out_index = gid.x + gid.y * params.window_size.x;
    let px = params.window_origin + gid.xy;
    let size = vec2<f32>(params.full_size);
    let tan_half = params.forward.w;
    let sx = ((f32(px.x) + 0.5) / size.x * 2.0 - 1.0) * tan_half * size.x / size.y;
    let sy = (1.0 - (f32(px.y) + 0.5) / size.y * 2.0) * tan_half;
    let dir = normalize(params.forward.xyz + sx * params.right.xyz + sy * params.up.xyz);
    let eye = params.eye.xyz;
    let iso = params.iso;

    // Box entry and exit (slabs). WGSL gives no infinities, so a zero direction component is
    // replaced by a tiny one of the same side: its slab then spans (almost) all t, as it should.
    let tiny = vec3<f32>(1e-20);
    let dir_safe = select(dir, select(tiny, -tiny, dir < vec3<f32>(0.0)), abs(dir) < tiny);
    let inv_dir = 1.0 / dir_safe;
    let ta = (params.box_min.xyz - eye) * inv_dir;
    let tb = (params.box_max.xyz - eye) * inv_dir;
    let tmin3 = min(ta, tb);
    let tmax3 = max(ta, tb);
    let t_enter = max(max(tmin3.x, tmin3.y), tmin3.z);
    let t_exit = min(min(tmax3.x, tmax3.y), tmax3.z);

    var hit = false;
    var cap = false;
    var t_hit = 0.0;
    var cap_normal = vec3<f32>(0.0);

    if t_exit >= max(t_enter, 0.0) {
        var t = max(t_enter, 0.0);
        var below = true;
        let f0 = field(eye + t * dir);
        if t_enter >= 0.0 {
            // Entering the box from outside (empty): f >= iso at the face is a crossing up.
            if f0 >= iso {
                hit = true;
                cap = true;
                t_hit = t_enter;
                // The face entered: the axis whose slab gave t_enter, facing against the ray.
                var axis = 0u;
                if tmin3.y >= tmin3.x && tmin3.y >= tmin3.z {
                    axis = 1u;
                }
                if tmin3.z >= tmin3.x && tmin3.z >= tmin3.y {
                    axis = 2u;
                }
                cap_normal[axis] = -sign(dir[axis]);
            }
        } else {
            below = f0 < iso;
        }

        let step = params.spacing.w;
        let ess = (params.block_counts.w & FLAG_EMPTY_SPACE_SKIPPING) != 0u;
        var steps = 0u;
        while !hit && t < t_exit && steps < params.max_steps {
            steps += 1u;
            if ess {
                let b = block_of(eye + (t + 1e-3 * step) * dir);
                if block_max(b) < iso {
                    // No point of this block reaches iso: leave it without sampling. The field
                    // where we leave it is below iso too (the block's closure is bounded by max).
                    t = max(block_exit(b, eye, inv_dir), t + 1e-3 * step);
                    below = true;
                    continue;
                }
            }
            let t_next = min(t + step, t_exit);
            let f_next = field(eye + t_next * dir);
            if below && f_next >= iso {
                // Refine in [lo, hi] with f(lo) < iso <= f(hi).
                var lo = t;
                var hi = t_next;
                var f_lo = field(eye + lo * dir);
                var f_hi = f_next;
                for (var i = 0u; i < params.refine_steps; i += 1u) {
                    let mid = 0.5 * (lo + hi);
                    let fm = field(eye + mid * dir);
                    if fm >= iso {
                        hi = mid;
                        f_hi = fm;
                    } else {
                        lo = mid;
                        f_lo = fm;
                    }
                }
                let denom = f_hi - f_lo;
                t_hit = select(hi, lo + (iso - f_lo) / denom * (hi - lo), denom > 0.0);
                t_hit = clamp(t_hit, lo, hi);
                hit = true;
                break;
            }
            below = f_next < iso;
            t = t_next;
        }
    }

    if !hit {
        out_color[out_index] = vec4<f32>(params.background.xyz, 0.0);
        out_geometry[out_index] = vec4<f32>(0.0);
        out_fetches[out_index] = fetches;
        return;
    }

    let p = eye + t_hit * dir;
    var n: vec3<f32>;
    if cap {
        n = cap_normal;
    } else {
        let g = gradient(p);
        let gl = length(g);
        n = select(-dir, -g / gl, gl > 0.0 && gl == gl);
    }
    let v = -dir;
    let ns = select(-n, n, dot(n, v) >= 0.0);
    let rgb = shade(ns, params.light_dir.xyz, v) * params.background.w;
    out_color[out_index] = vec4<f32>(rgb, 1.0);
    out_geometry[out_index] = vec4<f32>(n, t_hit);
    out_fetches[out_index] = fetches;
}
