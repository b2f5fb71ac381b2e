//! Where a temporal history's error comes from (`bench orbit`): per frame, the error of repeated
//! runs split into bias and noise ([`split`]), and the error of pixels grouped by how long a history
//! they carry ([`Buckets`]).
//!
//! The split: the same orbit run R times with disjoint sample patterns gives, per pixel i,
//! estimates a_1..a_R of one truth t. With m the mean over the repeats and v the spread
//! (sum of (a_r - m)^2 over R - 1, unbiased), the mean squared error over repeats is
//! (m - t)^2 + v (R - 1) / R; (m - t)^2 itself holds the squared bias plus the mean's own noise
//! v / R. So over the pixels: RMS std = sqrt(mean v), RMS bias = sqrt(mean (m - t)^2 - mean v / R)
//! (0 where noise alone explains it), and RMSE^2 = bias^2 + std^2. The truth is itself an estimate
//! (the converged reference): its noise counts as bias here, the part no repeat can average out.
//!
//! How much of the bias is a blur: the same split against the reference blurred in screen space
//! ([`blurred`], a Gaussian of [`BLUR_SIGMAS`] pixels over the neighbours on the same surface as
//! the reprojection would accept them): where the history is the truth seen through a blur of
//! about that width, its bias against the blurred reference is small. (Blurring also averages away
//! some of the reference's own noise.)

/// A frame's error over repeated runs: RMSE, its RMS bias and RMS std, over the pixels every
/// run and the truth hit.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Split {
    pub rmse: f64,
    pub rms_bias: f64,
    pub rms_std: f64,
    pub pixels: usize,
}

/// The bias and noise of `repeats` (per run, per pixel; NaN: no hit) against `truth` (at least
/// two runs, else the spread is unknown and std is NaN).
pub fn split(repeats: &[Vec<f32>], truth: &[f32]) -> Split {
    let r = repeats.len() as f64;
    let (mut bias2, mut spread, mut n) = (0.0, 0.0, 0usize);
    for (i, &t) in truth.iter().enumerate() {
        let a: Option<Vec<f64>> =
            repeats.iter().map(|run| run.get(i).filter(|x| x.is_finite()).map(|&x| x as f64)).collect();
        let Some(a) = a.filter(|_| t.is_finite() && !repeats.is_empty()) else { continue };
        let m = a.iter().sum::<f64>() / r;
        bias2 += (m - t as f64).powi(2);
        spread += a.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (r - 1.0);
        n += 1;
    }
    if n == 0 {
        return Split::default();
    }
    let (bias2, var) = (bias2 / n as f64, spread / n as f64);
    Split {
        rmse: (bias2 + var * (r - 1.0) / r).sqrt(),
        rms_bias: (bias2 - var / r).max(0.0).sqrt(),
        rms_std: var.sqrt(),
        pixels: n,
    }
}

/// The widths (Gaussian sigma, pixels) the reference is blurred by to compare the bias with.
pub const BLUR_SIGMAS: [f64; 4] = [0.5, 1.0, 1.5, 2.0];

/// `image` (rows of `width` pixels; NaN: no hit) blurred by a Gaussian of `sigma` pixels over
/// the hit pixels `q` with `same(i, q)` for pixel `i`, renormalized; a pixel without a hit stays NaN.
pub fn blurred(image: &[f32], width: usize, sigma: f64, same: &dyn Fn(usize, usize) -> bool) -> Vec<f32> {
    let r = (3.0 * sigma).ceil() as i64;
    let kernel: Vec<f64> = (-r..=r).map(|d| (-((d * d) as f64) / (2.0 * sigma * sigma)).exp()).collect();
    let (w, h) = (width as i64, (image.len() / width.max(1)) as i64);
    let at = |x: i64, y: i64| (x >= 0 && y >= 0 && x < w && y < h).then_some((x + y * w) as usize);
    (0..image.len())
        .map(|i| {
            if !image[i].is_finite() {
                return f32::NAN;
            }
            let (x, y) = (i as i64 % w, i as i64 / w);
            let (mut sum, mut norm) = (0.0, 0.0);
            for dy in -r..=r {
                for dx in -r..=r {
                    if let Some(q) = at(x + dx, y + dy).filter(|&q| image[q].is_finite() && same(i, q)) {
                        let k = kernel[(dx + r) as usize] * kernel[(dy + r) as usize];
                        sum += k * image[q] as f64;
                        norm += k;
                    }
                }
            }
            (sum / norm) as f32
        })
        .collect()
}

/// The history buckets: a pixel's weight (frames' worth of samples, the E sum's w) in
/// [floor, next floor).
pub const BUCKET_FLOORS: [f32; 5] = [0.0, 2.0, 4.0, 8.0, 16.0];

/// The buckets' names, in frames of history.
pub const BUCKET_NAMES: [&str; 5] = ["1-2", "2-4", "4-8", "8-16", "16+"];

/// The bucket of a pixel of `weight`.
fn bucket(weight: f32) -> usize {
    BUCKET_FLOORS.iter().rposition(|&lo| weight >= lo).unwrap_or(0)
}

/// Squared errors pooled per history bucket over frames.
#[derive(Clone, Debug, Default)]
pub struct Buckets {
    count: [usize; 5],
    squared: [f64; 5],
}

/// A bucket's share of the pooled pixels and its RMSE (NaN where empty).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BucketError {
    pub name: &'static str,
    pub fraction: f64,
    pub rmse: f64,
}

impl Buckets {
    /// Adds a frame: estimate `a` against `truth` per pixel (both finite), with the pixel's
    /// history `weight`.
    pub fn add(&mut self, a: &[f32], truth: &[f32], weight: &[f32]) {
        for ((&a, &t), &w) in a.iter().zip(truth).zip(weight) {
            if a.is_finite() && t.is_finite() {
                let b = bucket(w);
                self.count[b] += 1;
                self.squared[b] += (a as f64 - t as f64).powi(2);
            }
        }
    }

    /// Per bucket: its share of the pixels added and its RMSE.
    pub fn errors(&self) -> Vec<BucketError> {
        let total = self.count.iter().sum::<usize>().max(1) as f64;
        (0..BUCKET_NAMES.len())
            .map(|b| BucketError {
                name: BUCKET_NAMES[b],
                fraction: self.count[b] as f64 / total,
                rmse: if self.count[b] == 0 {
                    f64::NAN
                } else {
                    (self.squared[b] / self.count[b] as f64).sqrt()
                },
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_constant_offset_is_bias_and_a_spread_about_the_truth_is_noise() {
        let truth = vec![0.5f32, 0.2, f32::NAN, 0.7];
        // Runs that agree, 0.1 above the truth: all bias.
        let biased: Vec<Vec<f32>> = (0..4).map(|_| truth.iter().map(|t| t + 0.1).collect()).collect();
        let s = split(&biased, &truth);
        assert_eq!(s.pixels, 3);
        assert!((s.rms_bias - 0.1).abs() < 1e-6 && s.rms_std < 1e-6, "{s:?}");
        // Runs of +-0.2 about the truth, averaging to it: no bias; the spread (sample std of
        // +0.2, -0.2, +0.2, -0.2) is 0.2 * sqrt(4 / 3); the RMSE is 0.2.
        let noisy: Vec<Vec<f32>> =
            (0..4).map(|r| truth.iter().map(|t| t + if r % 2 == 0 { 0.2 } else { -0.2 }).collect()).collect();
        let s = split(&noisy, &truth);
        assert!(s.rms_bias < 1e-6, "{s:?}");
        assert!((s.rms_std - 0.2 * (4.0f64 / 3.0).sqrt()).abs() < 1e-6, "{s:?}");
        assert!((s.rmse - 0.2).abs() < 1e-6, "{s:?}");
        // Both, with independent noise: an offset of 0.1 plus uniform noise in [-0.3, 0.3] (std
        // 0.3 / sqrt(3)) over many pixels; the mean's own noise is not counted as bias.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut noise = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 11) as f64 / (1u64 << 53) as f64 * 0.6 - 0.3) as f32
        };
        let many: Vec<f32> = (0..20_000).map(|i| (i % 100) as f32 / 100.0).collect();
        let both: Vec<Vec<f32>> = (0..4).map(|_| many.iter().map(|t| t + 0.1 + noise()).collect()).collect();
        let s = split(&both, &many);
        assert!((s.rms_bias - 0.1).abs() < 0.005, "{s:?}");
        assert!((s.rms_std - 0.3 / 3f64.sqrt()).abs() < 0.005, "{s:?}");
        assert!((s.rmse.powi(2) - s.rms_bias.powi(2) - s.rms_std.powi(2)).abs() < 1e-9);
        // A pixel one run missed is left out.
        let mut missed = noisy.clone();
        missed[2][0] = f32::NAN;
        assert_eq!(split(&missed, &truth).pixels, 2);
    }

    #[test]
    fn a_blur_spreads_an_edge_over_hit_pixels_only() {
        // Rows of 8: a step from 0 to 1 between columns 3 and 4; column 7 has no hit.
        let image: Vec<f32> = (0..8 * 5)
            .map(|i| {
                if i % 8 == 7 {
                    f32::NAN
                } else if i % 8 >= 4 {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        let b = blurred(&image, 8, 1.0, &|_, _| true);
        let row = &b[16..24];
        assert!(row[7].is_nan());
        assert!(row[3] > 0.1 && row[3] < 0.5 && row[4] > 0.5 && row[4] < 0.9, "{row:?}");
        assert!(row[0] < 0.01, "{row:?}");
        // Column 6 sees no hit to its right: only the ones of columns 4-5 and the edge's zeros.
        assert!(row[6] > row[4], "{row:?}");
        // A constant stays constant.
        let flat = blurred(&[0.3f32; 64], 8, 2.0, &|_, _| true);
        assert!(flat.iter().all(|v| (v - 0.3).abs() < 1e-6));
        // Pixels on another surface (here: the other side of the step) are left out.
        let sides = blurred(&image, 8, 1.0, &|i, q| (i % 8 >= 4) == (q % 8 >= 4));
        assert!(sides[16..23].iter().zip(&image[16..23]).all(|(b, a)| (b - a).abs() < 1e-6), "{sides:?}");
    }

    #[test]
    fn pixels_are_bucketed_by_their_history_length() {
        assert_eq!([1.0, 1.9, 2.0, 3.5, 4.0, 15.9, 16.0, 17.0].map(bucket), [0, 0, 1, 1, 2, 3, 4, 4]);
        let mut b = Buckets::default();
        let truth = [0.5f32; 5];
        // Two short histories off by 0.3 and 0.4, one long one exact, one no-hit, one 8-16 off by 0.1.
        b.add(&[0.8, 0.1, 0.5, f32::NAN, 0.6], &truth, &[1.0, 1.5, 17.0, 1.0, 9.0]);
        let e = b.errors();
        assert_eq!(e.len(), 5);
        assert_eq!(e[0].name, "1-2");
        assert!((e[0].fraction - 0.5).abs() < 1e-12 && (e[0].rmse - 0.125f64.sqrt()).abs() < 1e-6, "{e:?}");
        assert!(e[1].fraction == 0.0 && e[1].rmse.is_nan());
        assert!((e[3].rmse - 0.1).abs() < 1e-6 && (e[3].fraction - 0.25).abs() < 1e-12);
        assert!(e[4].rmse < 1e-6 && (e[4].fraction - 0.25).abs() < 1e-12);
    }
}
