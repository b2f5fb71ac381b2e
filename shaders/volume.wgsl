// Shared include: the trilinear field of DESIGN.md ("Volume") over the `volume` storage buffer,
// with the dims in `params.dims`. Used by every kernel that reads the volume. Twin of
// `Volume::trilinear_voxel` / `Volume::gradient` in daemon/volume (the CPU side), which tests compare.
//
// Expects at module scope: `params` (with dims, box_min, spacing), `volume: array<f32>`.

// Trilinear field evaluations made by this invocation ("trilinear fetches", 8 voxel reads each).
var<private> fetches: u32 = 0u;

fn voxel(i: i32, j: i32, k: i32) -> f32 {
    let n = vec3<i32>(params.dims.xyz);
    return volume[u32(i + n.x * (j + n.y * k))];
}

// The trilinear interpolant at continuous voxel coordinates `u`, clamped to the box; an axis with a
// single sample is constant along that axis.
fn trilinear_voxel(u: vec4<f32>) -> f32 {
    fetches += 1u;
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

// Continuous voxel coordinates of a world point.
fn to_voxel(p: vec3<f32>) -> vec4<f32> {
    return vec4<f32>((p - params.box_min.xyz) / params.spacing.xyz, 0.0);
}

// The field at a world point, position clamped to the box (callers handle "outside is empty").
fn field(p: vec3<f32>) -> f32 {
    return trilinear_voxel(to_voxel(p));
}

// Central differences of the trilinear field, h = one voxel spacing per axis, stencil clamped.
fn gradient(p: vec3<f32>) -> vec3<f32> {
    let u = to_voxel(p);
    let s = params.spacing.xyz;
    let gx = trilinear_voxel(u + vec4<f32>(1.0, 0.0, 0.0, 0.0)) - trilinear_voxel(u - vec4<f32>(1.0, 0.0, 0.0, 0.0));
    let gy = trilinear_voxel(u + vec4<f32>(0.0, 1.0, 0.0, 0.0)) - trilinear_voxel(u - vec4<f32>(0.0, 1.0, 0.0, 0.0));
    let gz = trilinear_voxel(u + vec4<f32>(0.0, 0.0, 1.0, 0.0)) - trilinear_voxel(u - vec4<f32>(0.0, 0.0, 1.0, 0.0));
    return vec3<f32>(gx, gy, gz) / (2.0 * s);
}
