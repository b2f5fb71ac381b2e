// Kernel::Ao (daemon/render/src/gpu/ao.rs): ambient occlusion, bent normal and the IBL term of one
// frame at every hit of the isosurface kernel's output, added into accumulators (progressive
// accumulation: frame k of K adds its estimate; the host divides by K).
//
// Ours (DESIGN.md "AO"): cosine-weighted directions around N (turned to the viewer) from the R2
// set shifted per pixel and frame (sampling.wgsl), origin offset along N by `ao_offset`, a march of
// `ao_step` (at most half a voxel) up to R (`ao_radius`, or to the box exit when unbounded);
// occluded as soon as a sample has f >= iso; blocks whose max < iso are crossed without sampling,
// blocks that may hold the object are always marched.
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
//#include frame.wgsl
//#include volume.wgsl
//#include sampling.wgsl
//#include environment.wgsl

// From the isosurface kernel: w = 1 on a hit.
@group(0) @binding(3) var<storage, read> in_color: array<vec4<f32>>;
// From the isosurface kernel: N (outward) and depth.
@group(0) @binding(4) var<storage, read> in_geometry: array<vec4<f32>>;
// The environment, equirectangular (environment.wgsl).
@group(0) @binding(5) var<storage, read> env: array<vec4<f32>>;
// Accumulated per frame: bent normal (xyz), A (w).
@group(0) @binding(6) var<storage, read_write> acc_ao: array<vec4<f32>>;
// Accumulated per frame: E (rgb).
@group(0) @binding(7) var<storage, read_write> acc_ibl: array<vec4<f32>>;
// Trilinear fetches, added to the isosurface kernel's.
@group(0) @binding(8) var<storage, read_write> out_fetches: array<u32>;

const AO_OURS: u32 = 0u;
const AO_SEED: u32 = 1u;
const IBL_NONE: u32 = 0u;
const IBL_SEED: u32 = 1u;
const IBL_BENT: u32 = 2u;
const IBL_RAYS: u32 = 3u;

// Ours: does o + t w reach f >= iso for some t in [0, R] (R clipped to the box)?
fn ours_occluded(o: vec3<f32>, w: vec3<f32>) -> bool {
    let inv = safe_inv(w);
    let tc = box_clip(o, inv);
    var t = max(tc.x, 0.0);
    var t_end = tc.y;
    if params.ao_radius >= 0.0 {
        t_end = min(t_end, params.ao_radius);
    }
    if t_end < t {
        return false;
    }
    let h = params.ao_step;
    let iso = params.iso;
    let ess = skipping();
    for (var steps = 0u; steps < params.max_steps; steps += 1u) {
        if ess {
            let b = block_of(o + (t + 1e-3 * h) * w);
            if block_max(b) < iso {
                t = max(block_exit(b, o, inv), t + 1e-3 * h);
                if t >= t_end {
                    return false;
                }
                continue;
            }
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
    if gid.x >= params.window_size.x || gid.y >= params.window_size.y {
        return;
    }
    let idx = gid.x + gid.y * params.window_size.x;
    if in_color[idx].w < 0.5 {
        return;
    }
    let px = params.window_origin + gid.xy;
    let dir = pixel_dir(px);
    let g = in_geometry[idx];
    let p = params.eye.xyz + g.w * dir;
    let ns = select(-g.xyz, g.xyz, dot(g.xyz, -dir) >= 0.0);
    let basis = onb(ns);
    let n_samples = params.ao_samples;
    let want_rays = params.ibl == IBL_RAYS;

    var occluded = 0u;
    var bent = vec3<f32>(0.0);
    var rays = vec3<f32>(0.0);
    if params.ao_method == AO_SEED {
        let f_p = field(p);
        for (var i = 0u; i < n_samples; i += 1u) {
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
    } else {
        let key = pixel_key(px.x, px.y, params.frame, params.seed);
        let o = p + params.ao_offset * ns;
        for (var i = 0u; i < n_samples; i += 1u) {
            let w = cosine_direction(ns, basis, r2_point(i, key));
            if ours_occluded(o, w) {
                occluded += 1u;
            } else {
                bent += w;
                if want_rays {
                    rays += env_lookup(w);
                }
            }
        }
    }
    var a = 0.0;
    if n_samples > 0u {
        a = f32(occluded) / f32(n_samples);
    }
    let bl = length(bent);
    let bent_n = select(ns, bent / bl, bl > 0.0);
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
                e = rays / f32(n_samples);
            } else {
                e = sh_irradiance(ns);
            }
        }
        default: {
            e = params.ambient.xyz * (1.0 - a);
        }
    }
    acc_ao[idx] += vec4<f32>(bent_n, a);
    acc_ibl[idx] += vec4<f32>(e, 0.0);
    out_fetches[idx] += fetches;
}
