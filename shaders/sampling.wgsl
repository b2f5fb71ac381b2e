// Shared include: AO sample patterns, the twin of daemon/render/src/sampling.rs (its module doc is
// the contract). Integer parts are bit-exact with the CPU; the disk mapping is f32 on both sides.

fn hash(x0: u32) -> u32 {
    var x = x0;
    x ^= x >> 16u;
    x *= 0x7feb352du;
    x ^= x >> 15u;
    x *= 0x846ca68bu;
    x ^= x >> 16u;
    return x;
}

// px, py: the pixel in the FULL image (the wall), never the rectangle.
fn pixel_key(px: u32, py: u32, frame: u32, seed: u32) -> u32 {
    return hash(px ^ hash(py ^ hash(frame ^ hash(seed))));
}

const R2_A1: u32 = 3242174889u;
const R2_A2: u32 = 2447445414u;

fn r2_point(i: u32, key: u32) -> vec2<f32> {
    let x = 0x80000000u + i * R2_A1 + hash(key);
    let y = 0x80000000u + i * R2_A2 + hash(key ^ 0x68bc21ebu);
    return vec2<f32>(f32(x >> 8u), f32(y >> 8u)) * (1.0 / 16777216.0);
}

// Hash-based Owen scrambling (Laine-Karras permutation with Burley's 2020 constants on the
// bit-reversed coordinate) of the first two Sobol dimensions, with the index shuffled per pixel.
fn owen_permute(x0: u32, seed: u32) -> u32 {
    var x = x0 + seed;
    x ^= x * 0x6c50b47cu;
    x ^= x * 0xb82f1e52u;
    x ^= x * 0xc7afe638u;
    x ^= x * 0x8d22f6e6u;
    return x;
}

fn owen_scramble(x: u32, seed: u32) -> u32 {
    return reverseBits(owen_permute(reverseBits(x), seed));
}

// The first two Sobol dimensions of index i: (bit-reversed i, the second dimension), the twin
// of `sampling::sobol_2d`. The second dimension's direction numbers v_k = (1 + shift)^k of the top
// bit make its value reverseBits(the superset XOR (GF(2) Moebius) transform of i's bits): five
// masked shift-xors instead of a loop over 32 bits (no loop: lavapipe counts loop iterations
// against a budget, see `AoDispatches` in daemon/render/src/gpu/ao.rs).
fn sobol_2d(i: u32) -> vec2<u32> {
    var x = i;
    x ^= (x >> 1u) & 0x55555555u;
    x ^= (x >> 2u) & 0x33333333u;
    x ^= (x >> 4u) & 0x0f0f0f0fu;
    x ^= (x >> 8u) & 0x00ff00ffu;
    x ^= (x >> 16u) & 0x0000ffffu;
    return vec2<u32>(reverseBits(i), reverseBits(x));
}

fn sobol_point(i: u32, key: u32) -> vec2<f32> {
    let j = owen_scramble(i, hash(key));
    let s = sobol_2d(j);
    let x = owen_scramble(s.x, hash(key ^ 0x2c1b3c6du));
    let y = owen_scramble(s.y, hash(key ^ 0x297a2d39u));
    return vec2<f32>(f32(x >> 8u), f32(y >> 8u)) * (1.0 / 16777216.0);
}

// `AoSequence::code()` (the model's, checked by a test).
const AO_SEQUENCE_R2: u32 = 0u;
const AO_SEQUENCE_SOBOL: u32 = 1u;

fn ao_point(sequence: u32, i: u32, key: u32) -> vec2<f32> {
    if sequence == AO_SEQUENCE_SOBOL {
        return sobol_point(i, key);
    }
    return r2_point(i, key);
}

const QUARTER_PI: f32 = 0.78539816339744830962;
const HALF_PI: f32 = 1.57079632679489661923;

fn concentric_disk(uv: vec2<f32>) -> vec2<f32> {
    let a = 2.0 * uv.x - 1.0;
    let b = 2.0 * uv.y - 1.0;
    if a == 0.0 && b == 0.0 {
        return vec2<f32>(0.0);
    }
    var r: f32;
    var phi: f32;
    if abs(a) > abs(b) {
        r = a;
        phi = QUARTER_PI * (b / a);
    } else {
        r = b;
        phi = HALF_PI - QUARTER_PI * (a / b);
    }
    return vec2<f32>(r * cos(phi), r * sin(phi));
}

// (t, bt) completing the unit n to an orthonormal basis (Duff et al. 2017).
struct Onb {
    t: vec3<f32>,
    bt: vec3<f32>,
}

fn onb(n: vec3<f32>) -> Onb {
    let s = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    return Onb(vec3<f32>(1.0 + s * n.x * n.x * a, s * b, -s * n.x), vec3<f32>(b, s + n.y * n.y * a, -n.y));
}

fn cosine_direction(n: vec3<f32>, basis: Onb, uv: vec2<f32>) -> vec3<f32> {
    let d = concentric_disk(uv);
    let z = sqrt(max(0.0, 1.0 - d.x * d.x - d.y * d.y));
    return d.x * basis.t + d.y * basis.bt + z * n;
}
