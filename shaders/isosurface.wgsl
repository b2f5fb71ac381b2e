// Kernel::Isosurface (daemon/render/src/gpu/isosurface.rs): primary rays to the first hit of the
// isosurface, exactly as DESIGN.md defines it, then the normal and the direct light.
//
// - Ray through the pixel centre of the *full* image (a rectangle of it is rendered: wall tiles).
// - Box entry and exit; outside the box the field is empty, so entering the box where f >= iso is
//   a hit on the box face (a cap) with the face's outward normal.
// - A camera inside the box starts at the eye; inside the object it first has to leave it (the hit
//   is the first up-crossing), like the CPU reference.
// - March with `params.spacing.w` (world units; at most half a voxel by default), skipping blocks
//   whose max < iso (empty-space skipping, when flag bit 0 is set), then bisect the bracketing step
//   `params.refine_steps` times and finish with one secant step.
// - `TEXTURE_MARCH` (a pipeline constant, `PerfOptions::texture`): the march's samples come from
//   the hardware's trilinear filter of a copy of the volume (`march_volume`, a `texture_3d`
//   with a linear sampler) instead of the 8 loads of `field`; the bracketing step found is checked
//   and refined from the storage volume exactly as above (a bracket the exact field does not
//   confirm is marched on), so the hit is the exact field's wherever both see the crossing.
// - Object space (bricks.rs): the march runs over the whole box as above, but only the steps that
//   start in this brick (`owns`) sample and look for a crossing; the others only advance t, so t,
//   the samples and the hit are the single-node render's bit for bit, and each step's crossing is
//   found by exactly one brick (the tile owner keeps the nearest hit).
// - Normal: N = -grad f / |grad f| by central differences (h = one voxel per axis); the direction
//   towards the viewer where the gradient vanishes. Shading uses N turned towards the viewer.
//
//#include camera.wgsl
//#include frame.wgsl
//#include volume.wgsl
//#include shading.wgsl
//#include hit.wgsl

// Per pixel: direct light (linear, before exposure, no ambient); w: the hit flag (hit.wgsl: 1 on
// a hit, 0.75 on one drawn from a coarser level, 0 without).
@group(0) @binding(3) var<storage, read_write> out_color: array<vec4<f32>>;
// Per pixel: N (xyz, outward, unflipped) and depth (w); all 0 without a hit.
@group(0) @binding(4) var<storage, read_write> out_geometry: array<vec4<f32>>;
// Per pixel: trilinear fetches made.
@group(0) @binding(5) var<storage, read_write> out_fetches: array<u32>;
// The volume as a filterable texture (`TEXTURE_MARCH`; a 1x1x1 texel where it is off) and its
// linear, clamp-to-edge sampler.
@group(0) @binding(6) var march_volume: texture_3d<f32>;
@group(0) @binding(7) var march_sampler: sampler;

// Whether the march samples `march_volume` (`PerfOptions::texture`). A pipeline constant, so each
// pipeline holds only its own branch.
override TEXTURE_MARCH: bool = false;

// The field the march looks for a crossing with: `field`, or with `TEXTURE_MARCH` the hardware's
// trilinear filter of the same samples. Texel i's centre is sample i (texture coordinate
// (u + 0.5) / n, DESIGN.md's voxel-centre convention), u clamped to the box as `trilinear_voxel`
// clamps it, so both interpolate the same samples with the same weights (up to the filter's own
// weight precision).
fn march_field(p: vec3<f32>) -> f32 {
    if TEXTURE_MARCH {
        fetches += 1u;
        let n = vec3<f32>(params.dims.xyz);
        let u = clamp(to_voxel(p).xyz, vec3<f32>(0.0), max(n - 1.0, vec3<f32>(0.0)));
        return textureSampleLevel(march_volume, march_sampler, (u + 0.5) / n, 0.0).x;
    }
    return field(p);
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    params = frame_params;
    load_bricks();
    if gid.x >= params.rect_size.x || gid.y >= params.rect_size.y {
        return;
    }
    let out_index = gid.x + gid.y * params.rect_size.x;
    let dir = pixel_dir(params.rect_origin + gid.xy);
    let eye = params.eye.xyz;
    let iso = params.iso;
    let inv_dir = safe_inv(dir);
    let tc = box_clip(eye, inv_dir);
    let t_enter = tc.x;
    let t_exit = tc.y;

    var hit = false;
    var cap = false;
    var t_hit = 0.0;
    var cap_normal = vec3<f32>(0.0);

    if t_exit >= max(t_enter, 0.0) {
        var t = max(t_enter, 0.0);
        var below = true;
        // Object space: `below` is known at t only once the march is in this brick; a step that
        // starts in another brick is that brick's (it finds that step's crossing).
        var known = true;
        if owns(eye + t * dir) {
            let f0 = field(eye + t * dir);
            if t_enter >= 0.0 {
                // Entering the box from outside (empty): f >= iso at the face is a crossing up.
                if f0 >= iso {
                    hit = true;
                    cap = true;
                    t_hit = t_enter;
                    // The face entered: the axis whose slab gave t_enter (lowest axis on a tie).
                    let ta = (params.box_min.xyz - eye) * inv_dir;
                    let tb = (params.box_max.xyz - eye) * inv_dir;
                    let tmin3 = min(ta, tb);
                    var axis = 2u;
                    if tmin3.y >= tmin3.z {
                        axis = 1u;
                    }
                    if tmin3.x >= tmin3.y && tmin3.x >= tmin3.z {
                        axis = 0u;
                    }
                    cap_normal[axis] = -sign(dir[axis]);
                }
            } else {
                below = f0 < iso;
            }
        } else {
            known = false;
        }

        let step = params.spacing.w;
        let ess = skipping();
        var steps = 0u;
        var was_owned = false;
        // The step [lo, hi] where f crosses up to iso, refined after the march: a SIMD CPU driver
        // runs a loop's whole body on every pass, so a refinement inside it would cost its loads
        // on every step of every ray.
        var crossed = false;
        var lo = 0.0;
        var hi = 0.0;
        var f_hi = 0.0;
        while !hit && t < t_exit && steps < params.max_steps {
            steps += 1u;
            if ess {
                let b = block_of(eye + (t + 1e-3 * step) * dir);
                if block_max(b) < iso {
                    // No point of this block reaches iso: leave it without sampling. The field
                    // where we leave it is below iso too (the block's closure is bounded by max).
                    t = max(block_exit(b, eye, inv_dir), t + 1e-3 * step);
                    below = true;
                    known = true;
                    continue;
                }
                mark_block(b, params.dims.w);
            }
            let t_next = min(t + step, t_exit);
            if !owns(eye + t * dir) {
                if was_owned {
                    break;
                }
                known = false;
                t = t_next;
                continue;
            }
            was_owned = true;
            // One field evaluation per pass (on a SIMD CPU driver every load site of the loop
            // costs on every pass): where `below` is not known at t (object space: the ray enters
            // this brick), this pass finds it and the next one makes the step, not counted twice.
            let f = march_field(eye + select(t_next, t, !known) * dir);
            if !known {
                below = f < iso;
                known = true;
                steps -= 1u;
                continue;
            }
            var f_next = f;
            if TEXTURE_MARCH && below && f_next >= iso {
                // The filter's bracket, checked on the exact field: where the exact field is
                // still below iso at t_next, the march goes on from there.
                f_next = field(eye + t_next * dir);
            }
            if below && f_next >= iso {
                crossed = true;
                lo = t;
                hi = t_next;
                f_hi = f_next;
                break;
            }
            below = f_next < iso;
            t = t_next;
        }
        if crossed {
            // Refine in [lo, hi] with f(lo) < iso <= f(hi).
            var f_lo = field(eye + lo * dir);
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
        }
    }

    if !hit {
        out_color[out_index] = vec4<f32>(0.0);
        out_geometry[out_index] = vec4<f32>(0.0);
        out_fetches[out_index] = fetches;
        return;
    }

    let p = eye + t_hit * dir;
    var n: vec3<f32>;
    if cap {
        n = cap_normal;
    } else {
        // The gradient has vanished (a plateau) when it is below f32 rounding of the samples it
        // came from: then the normal faces the viewer (like the reference's relative threshold).
        let g = gradient(p);
        let gl = length(g.xyz);
        let min_spacing = min(min(params.spacing.x, params.spacing.y), params.spacing.z);
        let vanished = gl <= 1e-6 * g.w / min_spacing;
        n = select(-g.xyz / gl, -dir, vanished || gl != gl);
    }
    let v = -dir;
    let ns = select(-n, n, dot(n, v) >= 0.0);
    let drawn = select(HIT_COARSER, HIT_LEVEL0, level0_at(to_voxel(p).xyz));
    out_color[out_index] = vec4<f32>(direct_light(ns, params.light_dir.xyz, v), drawn);
    out_geometry[out_index] = vec4<f32>(n, t_hit);
    out_fetches[out_index] = fetches;
}
