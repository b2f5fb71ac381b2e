//! The edge-aware spatial filter of the occlusion and IBL terms, and its CPU twin [`filter`]: the
//! definition `Kernel::Denoise` (shaders/denoise.wgsl, gpu/denoise.rs) follows.
//!
//! [`PASSES`] a-trous wavelet passes (SVGF-style) with steps 1, 2, 4, 8, 16 pixels and the 5x5
//! B3-spline weights (1/16, 1/4, 3/8, 1/4, 1/16 per axis) filter each hit pixel's (A, E): the
//! accumulated occlusion and IBL terms divided by the frame count. A neighbour q of p counts with
//! the B3 weight times three edge stops ([`STOPS`]):
//! - plane: `exp(-|n_p . (P_q - P_p)| / (sigma_plane * footprint_p * |offset| ))`, the distance of
//!   q's hit from p's tangent plane against the world size of the pixel offset at p's depth
//!   (`footprint_p` = depth_p * 2 tan(fov_y / 2) / H): a plane keeps its neighbours at any angle
//!   (grazing views), a step in depth (silhouettes, a plate's other side) does not;
//! - normal: `max(n_p . n_q, 0)^32` (five squarings: the same bits on both sides);
//! - occlusion: `exp(-|A_p - A_q| / (sigma_occlusion * sqrt(max(var_p, var_q)) + 1e-6))` with
//!   var_p the variance of p's occlusion estimate (the larger of the two: an open pixel, whose
//!   estimate of a small A has a small variance, would otherwise refuse its occluded neighbours
//!   while they take its value, and occlusion would leak out of creases: a bias low against the
//!   independent estimate): before the first pass the binomial variance of a mean of
//!   n = samples x frames visibility samples, `p (1 - p) / n` with p = (n A + 1) / (n + 2) (never 0
//!   where a pixel saw no occluder yet); each pass carries it on as `sum w^2 var_q / (sum w)^2`.
//!
//! Pixels without a hit, and pixels outside the filtered rectangle, are no one's neighbour. So a
//! pixel's output depends on the inputs within [`reach`] pixels of it only: a tile rendered with a
//! guard band that wide around it filters its own pixels exactly as the whole image does.
//!
//! Still frames: the output is `raw + strength (filtered - raw)` with `strength(n)` =
//! min(1, sqrt([`FULL_STRENGTH_SAMPLES`] / n)) for n samples per pixel in all: full up to 4
//! samples, a half at 16, 1/8 at 256, 1/32 at 4096; and as n grows, var_p shrinks and the occlusion stop
//! holds neighbours that differ by more than the remaining noise. A converged image stays (a test
//! bounds the change).
//!
//! A reprojected history ([`crate::reproject`]) gives each pixel its own count, n = AO samples per
//! frame times its weight ([`Input::pixel_samples`]): its variance and strength follow that count.

use isowall_model::View;

/// The a-trous passes (steps 1, 2, 4, ..., 2^(PASSES-1) pixels).
pub const PASSES: u32 = 5;
/// B3-spline weights of offsets 0, 1, 2 (times the step) along one axis.
pub const B3: [f32; 3] = [3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0];
/// The edge stops' parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stops {
    /// Scale of the plane distance against a pixel offset's world size.
    pub sigma_plane: f32,
    /// Scale of the occlusion difference against its standard deviation.
    pub sigma_occlusion: f32,
    /// The normal stop is `max(n_p . n_q, 0)^(2^normal_squarings)`.
    pub normal_squarings: u32,
}

/// The stops the renderer uses.
///
/// Tuned with `isowalld bench suite --scenes procedural:engine,CT@300 --sizes 256x256 --samples
/// 4,32 --variants default,denoise=on` (occlusion RMSE, engine 4 / 32 spp, CT 4 / 32 spp; raw
/// 0.089 / 0.019, 0.049 / 0.014): these 0.058 / 0.018, 0.014 / 0.011; the occlusion stop at 4
/// 0.065 / 0.021, 0.013 / 0.011 (it blurs the engine's fine detail); the normal stop at 128
/// (SVGF's) 0.059 / 0.018, 0.016 / 0.011. The ignored test `sweep_the_stops` of
/// tests/gpu_denoise.rs sweeps them with the CPU twin on the sphere over a plane.
pub const STOPS: Stops = Stops { sigma_plane: 1.0, sigma_occlusion: 2.0, normal_squarings: 5 };
/// Samples per pixel up to which the filter applies in full.
pub const FULL_STRENGTH_SAMPLES: u64 = 4;

/// Pixels a filtered pixel depends on, each way: 2 (1 + 2 + ... + 2^(PASSES-1)). A tile's guard
/// band must be this wide.
pub const fn reach() -> u32 {
    2 * ((1 << PASSES) - 1)
}

/// The share of the filtered value in the output, for `samples` visibility samples per pixel in
/// all (AO samples per frame times frames); 0 without samples (nothing to filter).
pub fn strength(samples: u64) -> f32 {
    pixel_strength(samples as f32)
}

/// [`strength`] of a pixel's own sample count (a reprojected history's, not a whole number).
pub fn pixel_strength(samples: f32) -> f32 {
    if samples <= 0.0 {
        return 0.0;
    }
    (FULL_STRENGTH_SAMPLES as f32 / samples).sqrt().min(1.0)
}

/// The variance of an occlusion estimate `a` over `n` samples (binomial, with the rule of
/// succession for p so that 0 and 1 keep a variance).
pub fn occlusion_variance(a: f32, n: f32) -> f32 {
    let p = (n * a + 1.0) / (n + 2.0);
    p * (1.0 - p) / n
}

/// `x^(2^squarings)` by squarings.
pub fn power_of_two_power(x: f32, squarings: u32) -> f32 {
    let mut y = x;
    for _ in 0..squarings {
        y *= y;
    }
    y
}

/// What the filter reads of a rectangle: per pixel, rows top to bottom.
pub struct Input<'a> {
    /// The rectangle and its camera (positions come from depth along the full image's pixel rays).
    pub view: &'a View,
    pub hit: &'a [bool],
    pub depth: &'a [f32],
    pub normal: &'a [[f32; 3]],
    pub occlusion: &'a [f32],
    pub ibl: &'a [[f32; 3]],
    /// Visibility samples per pixel in all (AO samples per frame times frames).
    pub samples: u64,
    /// Where each pixel has its own count (a reprojected history: AO samples per frame times the
    /// pixel's weight), those counts, in place of `samples` for its variance and strength.
    pub pixel_samples: Option<&'a [f32]>,
}

/// The camera as the kernels hold it, in f32.
pub(crate) struct Rays {
    pub(crate) forward: [f32; 3],
    pub(crate) right: [f32; 3],
    pub(crate) up: [f32; 3],
    pub(crate) tan_half: f32,
    pub(crate) full: (f32, f32),
}

pub(crate) fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Rays {
    pub(crate) fn new(view: &View) -> Rays {
        let b = view.camera.basis();
        let f = |v: glam::DVec3| [v.x as f32, v.y as f32, v.z as f32];
        Rays {
            forward: f(b.forward),
            right: f(b.right),
            up: f(b.up),
            tan_half: b.tan_half_fov as f32,
            full: (view.full.0 as f32, view.full.1 as f32),
        }
    }

    /// shaders/frame.wgsl's `pixel_dir` in f32.
    pub(crate) fn dir(&self, px: u32, py: u32) -> [f32; 3] {
        let (w, h) = self.full;
        let sx = ((px as f32 + 0.5) / w * 2.0 - 1.0) * self.tan_half * w / h;
        let sy = (1.0 - (py as f32 + 0.5) / h * 2.0) * self.tan_half;
        let d: [f32; 3] = std::array::from_fn(|c| self.forward[c] + sx * self.right[c] + sy * self.up[c]);
        let l = dot(d, d).sqrt();
        d.map(|x| x / l)
    }
}

/// Filters the occlusion and IBL terms of `input` (the CPU twin of `Kernel::Denoise`): the
/// output's (occlusion, ibl) per pixel; pixels without a hit keep theirs.
pub fn filter(input: &Input) -> (Vec<f32>, Vec<[f32; 3]>) {
    filter_with(input, &STOPS)
}

/// [`filter`] with other edge stops (for tuning them).
pub fn filter_with(input: &Input, stops: &Stops) -> (Vec<f32>, Vec<[f32; 3]>) {
    let (w, h) = (input.view.rect.width as usize, input.view.rect.height as usize);
    let n = w * h;
    let rays = Rays::new(input.view);
    let (ox, oy) = (input.view.rect.x, input.view.rect.y);
    let pos: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            let d = rays.dir(ox + (i % w) as u32, oy + (i / w) as u32);
            d.map(|c| c * input.depth[i])
        })
        .collect();
    let pixel_size = 2.0 * rays.tan_half / rays.full.1;
    let count = |i: usize| input.pixel_samples.map_or(input.samples as f32, |p| p[i]);
    let raw: Vec<[f32; 4]> = (0..n)
        .map(|i| {
            let e = input.ibl[i];
            [input.occlusion[i], e[0], e[1], e[2]]
        })
        .collect();
    let mut signal = raw.clone();
    let mut variance: Vec<f32> =
        raw.iter().enumerate().map(|(i, s)| occlusion_variance(s[0], count(i))).collect();
    for pass in 0..PASSES {
        let step = 1i64 << pass;
        let mut next_signal = signal.clone();
        let mut next_variance = variance.clone();
        for i in 0..n {
            if !input.hit[i] {
                continue;
            }
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            let np = input.normal[i];
            let pp = pos[i];
            let ap = signal[i][0];
            let footprint = stops.sigma_plane * input.depth[i] * pixel_size;
            let mut sum = [0.0f32; 4];
            let mut wsum = 0.0f32;
            let mut vsum = 0.0f32;
            for dy in -2i64..=2 {
                for dx in -2i64..=2 {
                    let (qx, qy) = (x + dx * step, y + dy * step);
                    if qx < 0 || qy < 0 || qx >= w as i64 || qy >= h as i64 {
                        continue;
                    }
                    let q = qx as usize + qy as usize * w;
                    if !input.hit[q] {
                        continue;
                    }
                    let k = B3[dx.unsigned_abs() as usize] * B3[dy.unsigned_abs() as usize];
                    let offset = (((dx * dx + dy * dy) * step * step) as f32).sqrt();
                    let pq = pos[q];
                    let plane = dot(np, [pq[0] - pp[0], pq[1] - pp[1], pq[2] - pp[2]]).abs();
                    let w_plane = (-plane / (footprint * offset).max(1e-20)).exp();
                    let w_normal =
                        power_of_two_power(dot(np, input.normal[q]).max(0.0), stops.normal_squarings);
                    // Symmetric: the larger of the two estimates' variances.
                    let sigma_a = stops.sigma_occlusion * variance[i].max(variance[q]).max(0.0).sqrt() + 1e-6;
                    let w_occ = (-(ap - signal[q][0]).abs() / sigma_a).exp();
                    let wq = k * w_plane * w_normal * w_occ;
                    for c in 0..4 {
                        sum[c] += wq * signal[q][c];
                    }
                    wsum += wq;
                    vsum += wq * wq * variance[q];
                }
            }
            if wsum > 0.0 {
                next_signal[i] = sum.map(|s| s / wsum);
                next_variance[i] = vsum / (wsum * wsum);
            }
        }
        signal = next_signal;
        variance = next_variance;
    }
    let uniform = strength(input.samples);
    let mut occlusion = input.occlusion.to_vec();
    let mut ibl = input.ibl.to_vec();
    for i in 0..n {
        if input.hit[i] {
            let s = input.pixel_samples.map_or(uniform, |p| pixel_strength(p[i]));
            let out: [f32; 4] = std::array::from_fn(|c| raw[i][c] + s * (signal[i][c] - raw[i][c]));
            occlusion[i] = out[0];
            ibl[i] = [out[1], out[2], out[3]];
        }
    }
    (occlusion, ibl)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reach_covers_every_pass() {
        let steps: u32 = (0..PASSES).map(|p| 2 * (1 << p)).sum();
        assert_eq!(reach(), steps);
        assert_eq!(reach(), 62);
    }

    #[test]
    fn strength_is_full_for_few_samples_and_falls_with_more() {
        assert_eq!(strength(0), 0.0);
        assert_eq!(strength(1), 1.0);
        assert_eq!(strength(4), 1.0);
        assert!((strength(16) - 0.5).abs() < 1e-6);
        assert!((strength(256) - 0.125).abs() < 1e-6);
        assert!(strength(4096) < strength(1024) && strength(1024) < strength(64));
    }

    /// A plane facing the camera whose true occlusion is a band of 0.3 across open surface (a
    /// crease's shadow), estimated with 4 samples per pixel: the filtered image keeps the mean
    /// occlusion (the raw estimate's is unbiased). A stop that scales with the centre pixel's
    /// variance alone (open pixels refuse the band, band pixels take the open ones) takes the
    /// band's occlusion away: -0.0052 here, against -0.0018 with the larger of the two variances.
    #[test]
    fn the_filter_keeps_the_mean_occlusion_of_a_shadow_band() {
        let (w, h) = (96u32, 64u32);
        let camera = isowall_model::Camera {
            eye: glam::DVec3::ZERO,
            target: glam::DVec3::Y,
            up: glam::DVec3::Z,
            fov_y_deg: 40.0,
        };
        let view = View::whole(camera, w, h);
        let rays = Rays::new(&view);
        let n = (w * h) as usize;
        let samples = 4u32;
        let mut depth = Vec::with_capacity(n);
        let mut truth = Vec::with_capacity(n);
        let mut occlusion = Vec::with_capacity(n);
        for i in 0..n as u32 {
            let (x, y) = (i % w, i / w);
            // On the plane y = 10 (its normal towards the camera).
            depth.push(10.0 / rays.dir(x, y)[1]);
            let a = if (36..60).contains(&x) { 0.3f32 } else { 0.0 };
            truth.push(a);
            let hits = (0..samples)
                .filter(|&k| {
                    let u = crate::sampling::hash(i.wrapping_mul(9781).wrapping_add(k * 6271 + 1)) as f32;
                    u / 4294967296.0 < a
                })
                .count();
            occlusion.push(hits as f32 / samples as f32);
        }
        let input = Input {
            view: &view,
            hit: &vec![true; n],
            depth: &depth,
            normal: &vec![[0.0, -1.0, 0.0]; n],
            occlusion: &occlusion,
            ibl: &vec![[0.0; 3]; n],
            samples: samples as u64,
            pixel_samples: None,
        };
        let (filtered, _) = filter(&input);
        let mean = |v: &[f32]| v.iter().map(|&x| x as f64).sum::<f64>() / n as f64;
        let (raw_bias, bias) = (mean(&occlusion) - mean(&truth), mean(&filtered) - mean(&truth));
        assert!(raw_bias.abs() < 0.004, "the test's raw estimate is biased: {raw_bias}");
        assert!(bias.abs() < 0.004, "the filter moved the mean occlusion by {bias} (raw {raw_bias})");
    }

    #[test]
    fn variance_is_never_zero_and_falls_with_samples() {
        assert!(occlusion_variance(0.0, 4.0) > 0.0 && occlusion_variance(1.0, 4.0) > 0.0);
        assert!(occlusion_variance(0.5, 1024.0) < occlusion_variance(0.5, 4.0) / 100.0);
        assert_eq!(power_of_two_power(1.0, 7), 1.0);
        assert!((power_of_two_power(0.99, 7) - 0.99f32.powi(128)).abs() < 1e-5);
        assert!((power_of_two_power(0.99, 5) - 0.99f32.powi(32)).abs() < 1e-5);
    }
}
