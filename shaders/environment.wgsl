// Shared include: the environment of IBL, the twin of daemon/render/src/environment.rs (its module
// doc is the contract): an equirectangular image, rows from the zenith, bilinear, wrapping in u and
// clamping in v; and the SH9 diffuse irradiance. Expects `env: array<vec4<f32>>` and `params`.

const PI: f32 = 3.14159265358979323846;

fn env_texel(row: i32, col: i32) -> vec3<f32> {
    return env[u32(row) * params.env_width + u32(col)].xyz;
}

fn env_lookup(d: vec3<f32>) -> vec3<f32> {
    let w = i32(params.env_width);
    let h = i32(params.env_height);
    let len = length(d);
    var u = 0.0;
    var v = 0.5;
    if len > 0.0 {
        u = fract(atan2(d.y, d.x) / (2.0 * PI) + 1.0);
        v = acos(clamp(d.z / len, -1.0, 1.0)) / PI;
    }
    let x = u * f32(w) - 0.5;
    let y = v * f32(h) - 0.5;
    let x0 = floor(x);
    let y0 = floor(y);
    let fx = x - x0;
    let fy = y - y0;
    let xi = i32(x0);
    let yi = i32(y0);
    let c0 = ((xi % w) + w) % w;
    let c1 = (((xi + 1) % w) + w) % w;
    let r0 = clamp(yi, 0, h - 1);
    let r1 = clamp(yi + 1, 0, h - 1);
    let top = mix(env_texel(r0, c0), env_texel(r0, c1), fx);
    let bot = mix(env_texel(r1, c0), env_texel(r1, c1), fx);
    return mix(top, bot, fy);
}

// E(n) = (1/pi) * integral L max(0, n.w) dw from the SH9 coefficients (constant L gives L).
fn sh_irradiance(n: vec3<f32>) -> vec3<f32> {
    let c0 = 0.28209479177387814;
    let c1 = 0.4886025119029199;
    let c2 = 1.0925484305920792;
    let c20 = 0.31539156525252005;
    let c22 = 0.5462742152960396;
    let a1 = 2.0 / 3.0;
    let a2 = 0.25;
    var e = params.sh[0].xyz * c0;
    e += a1 * c1 * (params.sh[1].xyz * n.y + params.sh[2].xyz * n.z + params.sh[3].xyz * n.x);
    e += a2 * (params.sh[4].xyz * (c2 * n.x * n.y) + params.sh[5].xyz * (c2 * n.y * n.z)
        + params.sh[6].xyz * (c20 * (3.0 * n.z * n.z - 1.0)) + params.sh[7].xyz * (c2 * n.x * n.z)
        + params.sh[8].xyz * (c22 * (n.x * n.x - n.y * n.y)));
    return max(e, vec3<f32>(0.0));
}
