// The camera convention (DESIGN.md "Camera"), the one WGSL copy, for every kernel whatever its
// parameters: the unit ray through the centre of pixel px of the FULL image of `full_size` pixels,
// `forward.xyz` the view direction and `forward.w` tan(fov_y / 2), `right` and `up` the camera's
// unit axes.
fn camera_ray(px: vec2<u32>, full_size: vec2<u32>, forward: vec4<f32>, right: vec3<f32>, up: vec3<f32>) -> vec3<f32> {
    let size = vec2<f32>(full_size);
    let tan_half = forward.w;
    let sx = ((f32(px.x) + 0.5) / size.x * 2.0 - 1.0) * tan_half * size.x / size.y;
    let sy = (1.0 - (f32(px.y) + 0.5) / size.y * 2.0) * tan_half;
    return normalize(forward.xyz + sx * right + sy * up);
}
