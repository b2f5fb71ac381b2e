// Shared include: the frame's parameters, bound at 0 by every kernel, with the volume (1) and its
// per-block min/max (2). Twin: `FrameParams` in daemon/render/src/gpu/frame_params.rs, whose
// layout a test checks against this declaration (naga). No vec3 members.

struct FrameParams {
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
    spacing: vec4<f32>,      // w: primary march step, world units
    dims: vec4<u32>,         // w: cells per block edge
    block_counts: vec4<u32>, // w: flags (bit 0: empty-space skipping)
    full_size: vec2<u32>,
    rect_origin: vec2<u32>,
    rect_size: vec2<u32>,
    shading: u32,
    iso: f32,
    shininess: f32,
    refine_steps: u32,
    max_steps: u32,
    ao_samples: u32,
    ao_method: u32,          // 0 ours, 1 seed (the 2008 baseline)
    ibl: u32,                // 0 none, 1 seed, 2 bent, 3 rays
    frame: u32,
    seed: u32,
    ao_radius: f32,          // world units; < 0: unbounded (to the box)
    ao_offset: f32,          // eps: AO rays start at p + eps Ng, world units
    ao_step: f32,            // AO march step, world units
    env_width: u32,
    env_height: u32,
    ao_exact: u32,           // ours: 1 exact per-cell test, 0 march with ao_step
    ao_sequence: u32,        // ours' 2D set: 0 R2, 1 Sobol (Owen-scrambled)
    // 1: the AO kernel sums the sample positions (a temporal tile's drift test)
    positions: u32,
    sh: array<vec4<f32>, 9>, // SH9 of the environment (rgb), for IBL `bent`
    // object space (bricks.rs): the volume buffer holds a brick and its halo.
    data_offset: vec4<f32>,  // xyz: global sample index of the buffer's first sample; w: 1 in object space
    owned_min: vec4<f32>,    // a point q (clamped to the box) is this brick's when
    owned_max: vec4<f32>,    //   owned_min <= q < owned_max on every axis
    // performance
    ao_blocks: vec4<u32>,    // AO rays' block level: counts (xyz), cells per edge (w; 0: the primary level)
    coarse: vec4<u32>,       // coarse block level of AO rays: counts (xyz), cells per edge (w; 0: none)
    perf: vec4<u32>,         // x: flags (bit 0: an AO ray entering a block with min >= iso is occluded);
                             // y, z: offsets of the AO and coarse levels in block_minmax;
                             // w: 1 where the kernels mark the bricks rays read (brick_marks)
    voxel_range: vec4<f32>,  // xy: the value range the unorm voxel formats span (lo, hi); zw: 0
    ao_pass: vec4<u32>,      // x: AO samples per dispatch (ao.wgsl); y: the exact AO walk's
                             // iteration cap per ray; z: 0, or the most samples a pixel takes
                             // where the reprojection spent them by history; w: 0
}

const FLAG_EMPTY_SPACE_SKIPPING: u32 = 1u;
const PERF_BLOCK_MIN_EXIT: u32 = 1u;

// A read-only storage buffer, not a uniform: Mesa's lavapipe (22.x) inlines uniform values into a
// new compiled shader variant per uniform buffer it sees and keeps every variant, so a uniform
// that changes each frame grew a daemon by ~1.5 MB a frame (found by the soak test).
@group(0) @binding(0) var<storage, read> frame_params: FrameParams;
// The frame's parameters as every function reads them: a private copy that each kernel's entry
// point fills first (`params = frame_params;`), so that the loops read registers. On lavapipe a
// storage read is a loop over the SIMD lanes (a bounds check per lane and component) wherever it
// stands, and the AO walk read the parameters on every pass of every ray
// (docs/bench/kernel-time-lavapipe.md, "Fourth session").
var<private> params: FrameParams;
// The voxels packed as `VOXEL_FORMAT` (volume.wgsl) stores them: one f32's bits, two halves or two
// unorm16, or four unorm8 per word, the first voxel in the lowest bits.
@group(0) @binding(1) var<storage, read> volume: array<u32>;
@group(0) @binding(2) var<storage, read> block_minmax: array<vec2<f32>>; // primary, AO, coarse levels
// Ray-guided refinement of a bricked volume (`mark_level0_brick` in volume.wgsl): one bit per
// level-0 brick, set where a ray read that brick or relied on its min/max; the host clears and
// reads it (daemon/render/src/gpu/brick_pool.rs). A volume held whole binds one unused word.
@group(0) @binding(11) var<storage, read_write> brick_marks: array<atomic<u32>>;

// Unit ray through the centre of pixel px of the FULL image (camera.wgsl, which the kernel
// includes before this file).
fn pixel_dir(px: vec2<u32>) -> vec3<f32> {
    return camera_ray(px, params.full_size, params.forward, params.right.xyz, params.up.xyz);
}
