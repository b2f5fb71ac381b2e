// Kernel::Present (daemon/render/src/gpu/present.rs): draws a tile's image over its whole window,
// one triangle that covers the viewport. Not a compute kernel: a vertex and a fragment stage.
//
// The image is the tile's presentable image (compose.wgsl): 8-bit sRGB-encoded values already
// (what the PNG and the snapshot hold). Where the window's surface format is not sRGB the values
// pass through untouched; where it is (`SRGB_SURFACE`), they are decoded here and encoded again by
// the surface: either way the window shows the snapshot's values. Nearest sampling:
// where the window has the tile's size, every pixel is its own texel (pixel centres map to texel
// centres); elsewhere the image is stretched to fill the window.

@group(0) @binding(0) var tile: texture_2d<f32>;
@group(0) @binding(1) var nearest: sampler;
// 1: the surface is sRGB (it encodes what the fragment stage returns).
override SRGB_SURFACE: u32 = 0u;

fn srgb_to_linear(c: vec3<f32>) -> vec3<f32> {
    let lo = c / 12.92;
    let hi = pow((c + 0.055) / 1.055, vec3<f32>(2.4));
    return select(hi, lo, c <= vec3<f32>(0.04045));
}

struct VertexOut {
    @builtin(position) position: vec4<f32>,
    // Texture coordinates: (0, 0) the top-left corner of the image, (1, 1) the bottom-right.
    @location(0) uv: vec2<f32>,
}

@vertex
fn vs_main(@builtin(vertex_index) index: u32) -> VertexOut {
    // (0, 0), (2, 0), (0, 2): clip space (-1, -1), (3, -1), (-1, 3) covers [-1, 1]^2.
    let p = vec2<f32>(f32((index << 1u) & 2u), f32(index & 2u));
    var out: VertexOut;
    out.position = vec4<f32>(p * 2.0 - 1.0, 0.0, 1.0);
    out.uv = vec2<f32>(p.x, 1.0 - p.y);
    return out;
}

@fragment
fn fs_main(in: VertexOut) -> @location(0) vec4<f32> {
    let c = textureSample(tile, nearest, in.uv).rgb;
    if SRGB_SURFACE == 1u {
        return vec4<f32>(srgb_to_linear(c), 1.0);
    }
    return vec4<f32>(c, 1.0);
}
