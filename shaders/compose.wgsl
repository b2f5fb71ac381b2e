// Kernel::Compose (daemon/render/src/gpu/compose.rs): a tile's presentable image from the other
// kernels' outputs, on the GPU, one invocation per pixel of the tile's (full-resolution) rectangle.
//
// - Colour exactly as the CPU reference composes it: exposure * (direct + albedo * E), with E the
//   running sum of the AO kernel's IBL term over the accumulated frames divided by their count
//   (progressive accumulation: the mean of the frames' colours is the colour of their mean E; a
//   reprojected history divides by the pixel's own weight, the sum's w), or
//   the ambient light where neither AO nor IBL is on (count 0). Pixels without a hit take the
//   background as it is (no exposure).
// - The sRGB transfer and 8-bit rounding of `output::srgb8` (round half up of 255 * srgb(c)); the
//   stored value is that level / 255, which any unorm8 conversion keeps exactly.
// - The low-resolution upsample (`isowall_model::lowres::upsample_nearest`): the kernels ran over
//   the low rectangle; full pixel (x, y) of the rectangle takes low pixel
//   ((origin + (x, y)) / scale - low_origin). Scale 1 is the identity.
// - Depth per full pixel (distance along the ray, +inf without a hit: the bits of f32 infinity),
//   what object space composites by.
// - Per-frame counters of the tile's own low rectangle (each low pixel counted once; not the guard
//   band): trilinear fetches as a 64-bit sum (low word, high word), hits and pixels, summed per row
//   of that rectangle, then once per row into `counters`.

struct ComposeParams {
    background: vec4<f32>, // rgb: linear background; w: exposure
    albedo: vec4<f32>,     // rgb; w: 0
    ambient: vec4<f32>,    // rgb: E where neither AO nor IBL is on; w: 0
    low_origin: vec2<u32>, // the low rectangle's origin in the low image
    low_size: vec2<u32>,   // the low rectangle's size (the other kernels' rectangle)
    origin: vec2<u32>,     // the tile's rectangle origin in the full image
    size: vec2<u32>,       // the tile's rectangle size
    scale: u32,            // internal resolution divisor, 1 ..= 4
    frames: u32,           // frames in the running sums; 0: no AO or IBL (E = ambient)
    per_pixel: u32,        // 1: divide by each pixel's weight (the sum's w) instead of `frames`
    _pad1: u32,
    counted_origin: vec2<u32>, // the tile's own low rectangle within the low rectangle (a guard
    counted_size: vec2<u32>,   // band grows the latter): the pixels the counters count
}

//#include hit.wgsl

// A read-only storage buffer, not a uniform: see frame.wgsl (lavapipe's uniform inlining).
@group(0) @binding(0) var<storage, read> compose_params: ComposeParams;
// The parameters as the functions read them: a private copy the entry point fills first (a
// storage read on lavapipe is a loop over the SIMD lanes; see denoise.wgsl).
var<private> params: ComposeParams;
// From the isosurface kernel (low rectangle): direct light, w the hit flag (hit.wgsl).
@group(0) @binding(1) var<storage, read> in_color: array<vec4<f32>>;
// From the isosurface kernel (low rectangle): N and depth (w).
@group(0) @binding(2) var<storage, read> in_geometry: array<vec4<f32>>;
// From the AO kernel (low rectangle): running sum of E (rgb).
@group(0) @binding(3) var<storage, read> acc_ibl: array<vec4<f32>>;
// From both kernels (low rectangle): trilinear fetches of this frame per pixel.
@group(0) @binding(4) var<storage, read> in_fetches: array<u32>;
// The tile's presentable image, 8-bit sRGB values.
@group(0) @binding(5) var out_image: texture_storage_2d<rgba8unorm, write>;
// Depth per pixel of the rectangle, as f32 bits.
@group(0) @binding(6) var<storage, read_write> out_depth: array<u32>;
// fetches (low word, high word), hits, pixels counted, hits drawn with level 0 (hit.wgsl).
@group(0) @binding(7) var<storage, read_write> counters: array<atomic<u32>, 5>;

const INFINITY_BITS: u32 = 0x7f800000u;

// `isowall_model::render_state::linear_to_srgb` in f32: non-finite values are 0.
fn linear_to_srgb(x: f32) -> f32 {
    var c = 0.0;
    if x == x && abs(x) <= 3.40282347e38 {
        c = clamp(x, 0.0, 1.0);
    }
    if c <= 0.0031308 {
        return 12.92 * c;
    }
    return 1.055 * pow(c, 1.0 / 2.4) - 0.055;
}

// 8-bit level / 255 of a linear channel (`output::srgb8`).
fn encode(x: f32) -> f32 {
    return floor(linear_to_srgb(x) * 255.0 + 0.5) / 255.0;
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    params = compose_params;
    // The counters: the first invocation of each row of the tile's own low rectangle sums that row
    // and adds it once (no workgroup barrier: llvmpipe runs a workgroup that has one as coroutines).
    if gid.x == 0u && gid.y < params.counted_size.y {
        var lo = 0u;
        var hi = 0u;
        var hits = 0u;
        var level0 = 0u;
        let row = (gid.y + params.counted_origin.y) * params.low_size.x + params.counted_origin.x;
        for (var x = 0u; x < params.counted_size.x; x += 1u) {
            let f = in_fetches[row + x];
            let sum = lo + f;
            hi += select(0u, 1u, sum < lo);
            lo = sum;
            let w = in_color[row + x].w;
            hits += select(0u, 1u, is_hit(w));
            level0 += select(0u, 1u, is_level0_hit(w));
        }
        let old = atomicAdd(&counters[0], lo);
        hi += select(0u, 1u, old + lo < old); // carry into the high word
        atomicAdd(&counters[1], hi);
        atomicAdd(&counters[2], hits);
        atomicAdd(&counters[3], params.counted_size.x);
        atomicAdd(&counters[4], level0);
    }

    if gid.x >= params.size.x || gid.y >= params.size.y {
        return;
    }
    let s = max(params.scale, 1u);
    let low = (params.origin + gid.xy) / s - params.low_origin;
    let i = low.x + low.y * params.low_size.x;
    let d = in_color[i];
    var rgb = params.background.xyz;
    var depth = INFINITY_BITS;
    if is_hit(d.w) {
        var e = params.ambient.xyz;
        if params.frames > 0u {
            var k = f32(params.frames);
            if params.per_pixel == 1u {
                k = acc_ibl[i].w;
            }
            e = acc_ibl[i].xyz / k;
        }
        rgb = params.background.w * (d.xyz + params.albedo.xyz * e);
        depth = bitcast<u32>(in_geometry[i].w);
    }
    let image = vec4<f32>(encode(rgb.x), encode(rgb.y), encode(rgb.z), 1.0);
    textureStore(out_image, vec2<i32>(gid.xy), image);
    out_depth[gid.x + gid.y * params.size.x] = depth;
}
