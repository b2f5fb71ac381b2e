//! Sample patterns for ambient occlusion (DESIGN.md "AO"): the contract the WGSL twin
//! (`shaders/sampling.wgsl`) follows bit for bit wherever it is integer arithmetic.
//!
//! All integer arithmetic is on `u32` and wraps (WGSL's `u32` arithmetic wraps too).
//!
//! ```text
//! hash(x)            "lowbias32" (Chris Wellons):
//!                    x ^= x >> 16; x *= 0x7feb352d; x ^= x >> 15; x *= 0x846ca68b; x ^= x >> 16
//! pixel_key(px, py, frame, seed) = hash(px ^ hash(py ^ hash(frame ^ hash(seed))))
//!                    px, py: the pixel in the FULL image (the wall), never the rectangle, so a tile
//!                    of a wall draws exactly what the same pixel of one big render draws
//! R2_A1 = 3242174889 = round(2^32 / g), R2_A2 = 2447445414 = round(2^32 / g^2),
//!                    g = 1.32471795724474602596 (the plastic number)
//! r2_point(i, key):  x = 0x80000000 + i * R2_A1 + hash(key)
//!                    y = 0x80000000 + i * R2_A2 + hash(key ^ 0x68bc21eb)
//!                    (u, v) = ((x >> 8) * 2^-24, (y >> 8) * 2^-24) as f32: in [0, 1), exact in f32
//!                    (the R2 sequence in 0.32 fixed point, Cranley-Patterson shifted per pixel)
//! concentric_disk(u, v) (Shirley & Chiu 1997), in f32:
//!                    a = 2u - 1, b = 2v - 1; (0, 0) when a = b = 0;
//!                    |a| > |b|: r = a, phi = (pi/4) (b / a); else r = b, phi = pi/2 - (pi/4) (a / b);
//!                    (r cos phi, r sin phi)
//! onb(n) (Duff et al. 2017, "Building an Orthonormal Basis, Revisited"), n unit:
//!                    s = 1 if n.z >= 0 else -1; a = -1 / (s + n.z); b = n.x n.y a;
//!                    t = (1 + s n.x^2 a, s b, -s n.x); bt = (b, s + n.y^2 a, -n.y)
//! cosine_direction(n, u, v): (x, y) = concentric_disk(u, v) (f32), then in f64 (f32 on the GPU):
//!                    z = sqrt(max(0, 1 - x^2 - y^2)); w = x t + y bt + z n   (Malley's method)
//! owen_permute(x, s) (Laine & Karras 2011, Burley's 2020 constants), each output bit depending
//!                    only on itself and the lower bits:
//!                    x += s; x ^= x * 0x6c50b47c; x ^= x * 0xb82f1e52; x ^= x * 0xc7afe638;
//!                    x ^= x * 0x8d22f6e6
//! owen_scramble(x, s) = reverse_bits(owen_permute(reverse_bits(x), s)): hash-based nested
//!                    uniform (Owen) scrambling of a 0.32 fixed-point coordinate
//! sobol_2d(i):       (reverse_bits(i), XOR of SOBOL_Y[k] over the set bits k of i), SOBOL_Y[0] =
//!                    0x80000000, SOBOL_Y[k] = SOBOL_Y[k-1] ^ (SOBOL_Y[k-1] >> 1) (the first two
//!                    Sobol dimensions, primitive polynomials 1 and x + 1)
//! sobol_point(i, key): j = owen_scramble(i, hash(key))                    (index shuffle)
//!                    (x, y) = sobol_2d(j)
//!                    x = owen_scramble(x, hash(key ^ 0x2c1b3c6d)); y = owen_scramble(y, hash(key ^ 0x297a2d39))
//!                    (u, v) = ((x >> 8) * 2^-24, (y >> 8) * 2^-24) as f32
//!                    (Burley 2020, "Practical Hash-based Owen Scrambling": the first 2^k samples
//!                    of a pixel are an aligned block of the sequence, a (0, k, 2)-net, scrambled)
//! ```
//!
//! The 2D set is chosen per frame by [`AoSequence`](isowall_model::AoSequence) ([`ao_point`]):
//! sample `i` of a pixel is `cosine_direction(n, ao_point(sequence, i, pixel_key(px, py, frame, seed)))`:
//! cosine-weighted over the hemisphere around `n`, so the mean of the occlusion indicator over the
//! samples estimates A(p) = (1/pi) ∫ V cos. The frame index decorrelates successive frames of a
//! progressive accumulation; nothing depends on the wall clock.
//!
//! [`seed_directions`] is the 2008 shader's direction set (see its documentation), kept only for
//! the `seed` baseline.

use glam::DVec3;
use isowall_model::AoSequence;

/// "lowbias32" integer hash (Chris Wellons' hash-prospector), a bijection on `u32`.
#[inline]
pub fn hash(x: u32) -> u32 {
    let mut x = x;
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// The per-pixel, per-frame key of the sample pattern. `px, py` are the pixel in the full image
/// (the wall), not in the rendered rectangle.
#[inline]
pub fn pixel_key(px: u32, py: u32, frame: u32, seed: u32) -> u32 {
    hash(px ^ hash(py ^ hash(frame ^ hash(seed))))
}

/// round(2^32 / g), g the plastic number 1.32471795724474602596.
pub const R2_A1: u32 = 3_242_174_889;
/// round(2^32 / g^2).
pub const R2_A2: u32 = 2_447_445_414;

/// Point `i` of the R2 sequence (Roberts 2018) in 0.32 fixed point, shifted by a hash of `key`
/// (Cranley-Patterson rotation): both coordinates in [0, 1), multiples of 2^-24, exact in `f32`.
#[inline]
pub fn r2_point(i: u32, key: u32) -> (f32, f32) {
    let x = 0x8000_0000u32.wrapping_add(i.wrapping_mul(R2_A1)).wrapping_add(hash(key));
    let y = 0x8000_0000u32.wrapping_add(i.wrapping_mul(R2_A2)).wrapping_add(hash(key ^ 0x68bc_21eb));
    ((x >> 8) as f32 * (1.0 / 16_777_216.0), (y >> 8) as f32 * (1.0 / 16_777_216.0))
}

/// Laine-Karras style permutation of `x` keyed by `seed` (Burley 2020): each output bit depends
/// only on the same and lower input bits, so on bit-reversed input it is a nested scramble.
#[inline]
pub fn owen_permute(x: u32, seed: u32) -> u32 {
    let mut x = x.wrapping_add(seed);
    x ^= x.wrapping_mul(0x6c50_b47c);
    x ^= x.wrapping_mul(0xb82f_1e52);
    x ^= x.wrapping_mul(0xc7af_e638);
    x ^= x.wrapping_mul(0x8d22_f6e6);
    x
}

/// Hash-based nested uniform (Owen) scrambling of a 0.32 fixed-point coordinate.
#[inline]
pub fn owen_scramble(x: u32, seed: u32) -> u32 {
    owen_permute(x.reverse_bits(), seed).reverse_bits()
}

/// The first two dimensions of the Sobol sequence at index `i`, in 0.32 fixed point.
#[inline]
pub fn sobol_2d(i: u32) -> (u32, u32) {
    // The second dimension is the sum of v_k = (1 + shift)^k (top bit) over i's set bits k, i.e.
    // I(1 + shift) (top bit) for I(z) = the polynomial of i's bits: over GF(2) the coefficient of
    // shift^j is the XOR of i's bits k with j a bit-subset of k (Lucas), a superset-XOR transform
    // in five masked steps; shift^j of the top bit is bit 31 - j, hence the final reversal.
    let mut x = i;
    x ^= (x >> 1) & 0x5555_5555;
    x ^= (x >> 2) & 0x3333_3333;
    x ^= (x >> 4) & 0x0f0f_0f0f;
    x ^= (x >> 8) & 0x00ff_00ff;
    x ^= (x >> 16) & 0x0000_ffff;
    (i.reverse_bits(), x.reverse_bits())
}

/// Point `i` of the Owen-scrambled Sobol set of a pixel `key` (module documentation): both
/// coordinates in [0, 1), multiples of 2^-24, exact in `f32`.
#[inline]
pub fn sobol_point(i: u32, key: u32) -> (f32, f32) {
    let j = owen_scramble(i, hash(key));
    let (x, y) = sobol_2d(j);
    let x = owen_scramble(x, hash(key ^ 0x2c1b_3c6d));
    let y = owen_scramble(y, hash(key ^ 0x297a_2d39));
    ((x >> 8) as f32 * (1.0 / 16_777_216.0), (y >> 8) as f32 * (1.0 / 16_777_216.0))
}

/// Point `i` of the pixel `key`'s 2D set of `sequence`.
#[inline]
pub fn ao_point(sequence: AoSequence, i: u32, key: u32) -> (f32, f32) {
    match sequence {
        AoSequence::R2 => r2_point(i, key),
        AoSequence::Sobol => sobol_point(i, key),
    }
}

/// Shirley-Chiu concentric mapping of the unit square onto the unit disk (area-preserving), in f32.
#[inline]
pub fn concentric_disk(u: f32, v: f32) -> (f32, f32) {
    let a = 2.0 * u - 1.0;
    let b = 2.0 * v - 1.0;
    if a == 0.0 && b == 0.0 {
        return (0.0, 0.0);
    }
    let (r, phi) = if a.abs() > b.abs() {
        (a, std::f32::consts::FRAC_PI_4 * (b / a))
    } else {
        (b, std::f32::consts::FRAC_PI_2 - std::f32::consts::FRAC_PI_4 * (a / b))
    };
    (r * phi.cos(), r * phi.sin())
}

/// Two unit vectors `(t, bt)` completing the unit `n` to an orthonormal basis (t, bt, n) (Duff et
/// al. 2017); branch on the sign of `n.z`, with `n.z = 0` taking the `+` branch.
#[inline]
pub fn onb(n: DVec3) -> (DVec3, DVec3) {
    let s = if n.z >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    let t = DVec3::new(1.0 + s * n.x * n.x * a, s * b, -s * n.x);
    let bt = DVec3::new(b, s + n.y * n.y * a, -n.y);
    (t, bt)
}

/// The cosine-weighted direction around the unit `n` for the square point (u, v): the concentric
/// disk point (in f32) lifted onto the hemisphere (Malley's method, in f64).
#[inline]
pub fn cosine_direction(n: DVec3, u: f32, v: f32) -> DVec3 {
    let (x, y) = concentric_disk(u, v);
    let (x, y) = (x as f64, y as f64);
    let z = (1.0 - x * x - y * y).max(0.0).sqrt();
    let (t, bt) = onb(n);
    x * t + y * bt + z * n
}

/// The direction set of the 2008 RTPara shader, for the `seed` baseline only: for i in 0..N,
/// `u = v = -1 + 2i/N`, `x0 = 2u - 1`, `y0 = 2v - 1` (so every point lies on the disk's diagonal
/// x0 = y0, and most of them outside it). `None` where `x0^2 + y0^2 > 1`: the shader skips that
/// sample but still counts it in the denominator. A `Some((x0, y0))` is lifted to
/// `x0 t + y0 bt + sqrt(1 - x0^2 - y0^2) n` with the same [`onb`] (see [`seed_lift`]).
pub fn seed_directions(n_samples: u32) -> impl Iterator<Item = Option<(f64, f64)>> {
    let n = n_samples as f64;
    (0..n_samples).map(move |i| {
        let u = -1.0 + 2.0 * i as f64 / n;
        let x0 = 2.0 * u - 1.0;
        let y0 = x0;
        (x0 * x0 + y0 * y0 <= 1.0).then_some((x0, y0))
    })
}

/// Lifts a point of [`seed_directions`] onto the hemisphere around the unit `n`.
#[inline]
pub fn seed_lift(n: DVec3, (x0, y0): (f64, f64)) -> DVec3 {
    let (t, bt) = onb(n);
    x0 * t + y0 * bt + (1.0 - x0 * x0 - y0 * y0).max(0.0).sqrt() * n
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hash_known_answers() {
        // Computed outside this code with Python:
        //   M = 0xffffffff
        //   def h(x): x ^= x >> 16; x = (x * 0x7feb352d) & M; x ^= x >> 15
        //             x = (x * 0x846ca68b) & M; x ^= x >> 16; return x
        assert_eq!(hash(0), 0);
        assert_eq!(hash(1), 1_753_845_952); // 0x688990c0
        assert_eq!(hash(0xdead_beef), 3_861_431_939); // 0xe628c683
        assert_eq!(hash(12_345), 2_435_775_735); // 0x912efcf7
                                                 // pixel_key(3, 5, 0, 0) = h(3 ^ h(5 ^ h(0 ^ h(0)))) with the same Python.
        assert_eq!(pixel_key(3, 5, 0, 0), 4_225_011_718);
        // r2 with that key, same Python: (x >> 8, y >> 8) of the 32-bit sums, over 2^24.
        let p = |x: u32, y: u32| (x as f32 / 16_777_216.0, y as f32 / 16_777_216.0);
        assert_eq!(r2_point(0, 4_225_011_718), p(5_444_844, 1_372_129));
        assert_eq!(r2_point(7, 4_225_011_718), p(10_211_983, 1_185_600));
    }

    #[test]
    fn sobol_known_answers() {
        // Computed outside this code with Python (the module documentation's formulas, with
        // reverse_bits(x) = int(format(x, '032b')[::-1], 2) and h as in hash_known_answers).
        assert_eq!(sobol_2d(0), (0, 0));
        assert_eq!(sobol_2d(1), (0x8000_0000, 0x8000_0000));
        assert_eq!(sobol_2d(2), (0x4000_0000, 0xc000_0000));
        assert_eq!(sobol_2d(3), (0xc000_0000, 0x4000_0000));
        assert_eq!(sobol_2d(5), (0xa000_0000, 0x2000_0000));
        assert_eq!(owen_scramble(0x1234_5678, 0xdead_beef), 0xc90c_b9f0);
        let p = |x: u32, y: u32| (x as f32 / 16_777_216.0, y as f32 / 16_777_216.0);
        assert_eq!(sobol_point(0, 4_225_011_718), p(1_423_546, 2_168_656));
        assert_eq!(sobol_point(1, 4_225_011_718), p(13_079_559, 14_870_759));
        assert_eq!(sobol_point(7, 4_225_011_718), p(10_949_349, 12_418_055));
        assert_eq!(ao_point(AoSequence::Sobol, 7, 4_225_011_718), sobol_point(7, 4_225_011_718));
        assert_eq!(ao_point(AoSequence::R2, 7, 4_225_011_718), r2_point(7, 4_225_011_718));
    }

    #[test]
    fn sobol_2d_is_the_direction_number_definition() {
        // The module documentation's XOR of SOBOL_Y[k] over the set bits k, at every index of
        // 16 bits and at spread-out larger ones.
        let by_definition = |i: u32| {
            let (mut v, mut y) = (0x8000_0000u32, 0u32);
            for k in 0..32 {
                if (i >> k) & 1 != 0 {
                    y ^= v;
                }
                v ^= v >> 1;
            }
            y
        };
        for i in (0..=0xffffu32).chain((0..4096u32).map(|k| k.wrapping_mul(0x9e37_79b9))) {
            assert_eq!(sobol_2d(i), (i.reverse_bits(), by_definition(i)), "index {i}");
        }
    }

    #[test]
    fn owen_scrambled_sobol_prefixes_are_nets_in_every_pixel() {
        // The first 2^k points of any pixel: exactly one point in every elementary interval
        // [a/2^i, (a+1)/2^i) x [b/2^j, (b+1)/2^j) with i + j = k (a (0, k, 2)-net in base 2).
        for key in [0, 1, pixel_key(17, 4, 2, 9), pixel_key(500, 300, 7, 0)] {
            for k in [2u32, 4, 6] {
                let n = 1u32 << k;
                let pts: Vec<(f32, f32)> = (0..n).map(|i| sobol_point(i, key)).collect();
                for i in 0..=k {
                    let j = k - i;
                    let mut cells = vec![0u32; n as usize];
                    for &(u, v) in &pts {
                        assert!((0.0..1.0).contains(&u) && (0.0..1.0).contains(&v));
                        let (a, b) = ((u * (1 << i) as f32) as u32, (v * (1 << j) as f32) as u32);
                        cells[(a + (b << i)) as usize] += 1;
                    }
                    assert!(cells.iter().all(|&c| c == 1), "key {key} k {k} i {i}: {cells:?}");
                }
            }
        }
        // Pixels and frames get different scramblings.
        assert_ne!(sobol_point(0, pixel_key(1, 2, 0, 0)), sobol_point(0, pixel_key(1, 2, 1, 0)));
        assert_ne!(sobol_point(3, pixel_key(1, 2, 0, 0)), sobol_point(3, pixel_key(2, 1, 0, 0)));
    }

    #[test]
    fn r2_constants_are_the_plastic_number_fractions() {
        let g = 1.324_717_957_244_746_f64;
        assert_eq!((2f64.powi(32) / g).round() as u32, R2_A1);
        assert_eq!((2f64.powi(32) / (g * g)).round() as u32, R2_A2);
    }

    #[test]
    fn r2_points_lie_in_the_unit_square_and_fill_it_evenly() {
        let key = pixel_key(17, 4, 2, 9);
        let n = 4096;
        let mut cells = [0u32; 16];
        for i in 0..n {
            let (u, v) = r2_point(i, key);
            assert!((0.0..1.0).contains(&u) && (0.0..1.0).contains(&v), "{i}: {u} {v}");
            cells[(u * 4.0) as usize + 4 * (v * 4.0) as usize] += 1;
        }
        // Low discrepancy: each of the 16 cells holds 256 +- a few, far tighter than random (+-16).
        for c in cells {
            assert!((c as i32 - 256).abs() <= 4, "{cells:?}");
        }
        assert_ne!(r2_point(0, key), r2_point(0, key ^ 1));
        assert_eq!(r2_point(u32::MAX, 0), r2_point(u32::MAX, 0));
    }

    #[test]
    fn concentric_disk_is_an_area_preserving_map_onto_the_disk() {
        let m = 64;
        let mut mean_r2 = 0.0;
        let mut quadrants = [0; 4];
        for j in 0..m {
            for i in 0..m {
                let (u, v) = ((i as f32 + 0.5) / m as f32, (j as f32 + 0.5) / m as f32);
                let (x, y) = concentric_disk(u, v);
                let r2 = (x * x + y * y) as f64;
                assert!(r2 <= 1.0 + 1e-6, "{u} {v} -> {x} {y}");
                mean_r2 += r2;
                quadrants[usize::from(x > 0.0) + 2 * usize::from(y > 0.0)] += 1;
            }
        }
        mean_r2 /= (m * m) as f64;
        // Uniform on the disk: E[r^2] = 1/2.
        assert!((mean_r2 - 0.5).abs() < 2e-3, "{mean_r2}");
        assert_eq!(quadrants, [1024; 4]);
        assert_eq!(concentric_disk(0.5, 0.5), (0.0, 0.0));
        // Square corners go to the circle at 45 degrees, edge midpoints to the axes.
        let (x, y) = concentric_disk(1.0, 1.0);
        assert!((x - 0.5f32.sqrt()).abs() < 1e-6 && (y - 0.5f32.sqrt()).abs() < 1e-6);
        let (x, y) = concentric_disk(1.0, 0.5);
        assert!((x - 1.0).abs() < 1e-7 && y.abs() < 1e-7);
        let (x, y) = concentric_disk(0.5, 0.0);
        assert!(x.abs() < 1e-7 && (y + 1.0).abs() < 1e-7);
    }

    #[test]
    fn onb_is_orthonormal_on_both_branches() {
        for n in [
            DVec3::Z,
            -DVec3::Z,
            DVec3::X,
            DVec3::new(0.3, -0.4, 0.5).normalize(),
            DVec3::new(0.3, -0.4, -0.5).normalize(),
            DVec3::new(1e-9, 0.0, -1.0).normalize(),
        ] {
            let (t, b) = onb(n);
            for (x, y) in [(t, b), (t, n), (b, n)] {
                assert!(x.dot(y).abs() < 1e-12, "{n:?}");
            }
            assert!((t.length() - 1.0).abs() < 1e-12 && (b.length() - 1.0).abs() < 1e-12);
            // Right-handed: t x bt = n.
            assert!((t.cross(b) - n).length() < 1e-12, "{n:?}");
        }
    }

    #[test]
    fn cosine_directions_are_cosine_weighted_over_the_hemisphere() {
        for n in [
            DVec3::Z,
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(0.6, -0.48, 0.64),
            DVec3::new(-0.2, 0.9, -0.3).normalize(),
        ] {
            let key = pixel_key(5, 6, 0, 1);
            let count = 2048;
            let (mut mean_cos, mut mean_cos2, mut mean) = (0.0, 0.0, DVec3::ZERO);
            for i in 0..count {
                let (u, v) = r2_point(i, key);
                let w = cosine_direction(n, u, v);
                assert!((w.length() - 1.0).abs() < 1e-6, "{w:?}");
                let c = w.dot(n);
                assert!(c >= -1e-7, "{n:?} {w:?}");
                mean_cos += c;
                mean_cos2 += c * c;
                mean += w;
            }
            let k = count as f64;
            // p(w) = cos / pi: E[cos] = 2/3, E[cos^2] = 1/2, and the mean direction is (2/3) n.
            assert!((mean_cos / k - 2.0 / 3.0).abs() < 2e-3, "{n:?}: {}", mean_cos / k);
            assert!((mean_cos2 / k - 0.5).abs() < 2e-3, "{n:?}: {}", mean_cos2 / k);
            assert!((mean / k - 2.0 / 3.0 * n).length() < 4e-3, "{n:?}: {:?}", mean / k);
        }
    }

    #[test]
    fn seed_directions_lie_on_one_diagonal_and_most_are_skipped() {
        let n = 64;
        let dirs: Vec<_> = seed_directions(n).collect();
        assert_eq!(dirs.len(), 64);
        // x0 = 4i/N - 3 lies in [-1/sqrt2, 1/sqrt2] for i/N in [0.573, 0.927]: i = 37..=59.
        let kept: Vec<usize> = (0..64).filter(|&i| dirs[i].is_some()).collect();
        assert_eq!(kept, (37..=59).collect::<Vec<_>>());
        for (x0, y0) in dirs.iter().flatten() {
            assert_eq!(x0, y0);
            let w = seed_lift(DVec3::Z, (*x0, *y0));
            assert!((w.length() - 1.0).abs() < 1e-12 && w.z >= 0.0);
        }
        assert_eq!(seed_directions(0).count(), 0);
    }
}
