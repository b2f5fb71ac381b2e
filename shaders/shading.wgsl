// Shared include: direct light (Lambert or Blinn-Phong) without the ambient term, the twin of
// `isowall_model::render_state::shade` with a zero ambient. The ambient/IBL term is added when the
// frame is composed (see gpu/mod.rs). Expects `params` at module scope.

const SHADING_LAMBERT: u32 = 0u;
const SHADING_BLINN_PHONG: u32 = 1u;

// n: unit normal facing the viewer; l: unit direction towards the light; v: unit direction to the viewer.
fn direct_light(n: vec3<f32>, l: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    let ndl = max(dot(n, l), 0.0);
    var spec = 0.0;
    if params.shading == SHADING_BLINN_PHONG && ndl > 0.0 {
        let hl = l + v;
        let h = select(n, normalize(hl), dot(hl, hl) > 1e-12);
        spec = params.albedo.w * pow(max(dot(n, h), 0.0), params.shininess);
    }
    let lc = params.light_color.xyz;
    return params.albedo.xyz * lc * ndl + lc * spec;
}
