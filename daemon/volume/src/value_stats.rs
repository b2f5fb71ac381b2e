//! What a volume's values look like, for choosing an iso value (`isowalld info`): the range,
//! percentiles, a histogram, and thresholds found from it by Otsu's method (the value that best
//! splits the voxels into two classes, or three, by their between-class variance): the surface
//! of a scan lies between the classes of its values (air and tissue, tissue and bone).

/// Bins of the histogram the thresholds are found on.
pub const BINS: usize = 256;

/// A volume's values summarized (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct ValueStats {
    pub min: f32,
    pub max: f32,
    /// (percent, value) for 1, 5, 25, 50, 75, 95 and 99 percent.
    pub percentiles: Vec<(u32, f32)>,
    /// [`BINS`] equal bins over `min..=max`: voxel counts.
    pub histogram: Vec<u64>,
    /// The two-class threshold (Otsu).
    pub two_class: f64,
    /// The two thresholds of three classes (Otsu's method with two thresholds), lower first.
    pub three_class: (f64, f64),
}

impl ValueStats {
    /// The statistics of `values` (at least one).
    pub fn of(values: &[f32]) -> Option<ValueStats> {
        let (mut min, mut max) = (f32::INFINITY, f32::NEG_INFINITY);
        for &v in values {
            min = min.min(v);
            max = max.max(v);
        }
        if values.is_empty() || !(min.is_finite() && max.is_finite()) {
            return None;
        }
        let width = (f64::from(max) - f64::from(min)) / BINS as f64;
        let bin = |v: f32| {
            if width > 0.0 {
                (((f64::from(v) - f64::from(min)) / width) as usize).min(BINS - 1)
            } else {
                0
            }
        };
        let mut histogram = vec![0u64; BINS];
        for &v in values {
            histogram[bin(v)] += 1;
        }
        let mut sorted = values.to_vec();
        sorted.sort_unstable_by(f32::total_cmp);
        let percentiles = [1, 5, 25, 50, 75, 95, 99]
            .iter()
            .map(|&p| (p, sorted[((sorted.len() - 1) * p as usize) / 100]))
            .collect();
        // A bin's threshold is its upper edge: the classes are the bins at and below, and above.
        let edge = |k: usize| f64::from(min) + width * (k + 1) as f64;
        let (k2, (k3a, k3b)) = (otsu_two(&histogram), otsu_three(&histogram));
        Some(ValueStats {
            min,
            max,
            percentiles,
            histogram,
            two_class: edge(k2),
            three_class: (edge(k3a), edge(k3b)),
        })
    }

    /// The histogram in `n` bars of at most `width` characters (log scale: a scan's background
    /// would flatten everything else), each `value_from..value_to  count  ###`.
    pub fn bars(&self, n: usize, width: usize) -> Vec<String> {
        let n = n.clamp(1, BINS);
        let per = BINS.div_ceil(n);
        let counts: Vec<u64> = self.histogram.chunks(per).map(|c| c.iter().sum()).collect();
        let top = counts.iter().copied().max().unwrap_or(0).max(1) as f64;
        let step = (f64::from(self.max) - f64::from(self.min)) / counts.len() as f64;
        counts
            .iter()
            .enumerate()
            .map(|(i, &c)| {
                let len = if c == 0 {
                    0
                } else {
                    (((c as f64).ln_1p() / top.ln_1p()) * width as f64).ceil() as usize
                };
                let from = f64::from(self.min) + step * i as f64;
                format!("{:>10.4} ..{:>10.4} {c:>10} {}", from, from + step, "#".repeat(len.min(width)))
            })
            .collect()
    }
}

/// The bin whose upper edge best splits `h` into two classes (Otsu: the largest between-class
/// variance).
fn otsu_two(h: &[u64]) -> usize {
    let total: f64 = h.iter().map(|&c| c as f64).sum();
    let sum: f64 = h.iter().enumerate().map(|(i, &c)| i as f64 * c as f64).sum();
    let (mut w0, mut s0, mut best, mut at) = (0.0, 0.0, -1.0, 0);
    for (k, &c) in h.iter().enumerate().take(h.len() - 1) {
        w0 += c as f64;
        s0 += k as f64 * c as f64;
        let w1 = total - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let (m0, m1) = (s0 / w0, (sum - s0) / w1);
        let between = w0 * w1 * (m0 - m1) * (m0 - m1);
        if between > best {
            (best, at) = (between, k);
        }
    }
    at
}

/// The two bins whose upper edges best split `h` into three classes (Otsu with two thresholds:
/// the largest sum of the classes' weighted squared means).
fn otsu_three(h: &[u64]) -> (usize, usize) {
    let n = h.len();
    // Prefix sums of counts and of index times count.
    let mut w = vec![0.0f64; n + 1];
    let mut s = vec![0.0f64; n + 1];
    for (i, &c) in h.iter().enumerate() {
        w[i + 1] = w[i] + c as f64;
        s[i + 1] = s[i] + i as f64 * c as f64;
    }
    let class = |a: usize, b: usize| {
        let (wc, sc) = (w[b] - w[a], s[b] - s[a]);
        if wc > 0.0 {
            sc * sc / wc
        } else {
            0.0
        }
    };
    let (mut best, mut at) = (-1.0, (0, n.saturating_sub(2)));
    for k1 in 0..n.saturating_sub(2) {
        for k2 in k1 + 1..n - 1 {
            let v = class(0, k1 + 1) + class(k1 + 1, k2 + 1) + class(k2 + 1, n);
            if v > best {
                (best, at) = (v, (k1, k2));
            }
        }
    }
    at
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_and_three_classes_are_split_between_their_values() {
        // Air at -1000, tissue at 40, bone at 1200, in unequal shares, with a little spread.
        let mut v = Vec::new();
        for i in 0..6000 {
            v.push(-1000.0 + (i % 7) as f32);
        }
        for i in 0..3000 {
            v.push(40.0 + (i % 11) as f32);
        }
        for i in 0..600 {
            v.push(1200.0 + (i % 5) as f32);
        }
        let s = ValueStats::of(&v).unwrap();
        assert_eq!((s.min, s.max), (-1000.0, 1204.0));
        assert!(s.two_class > -994.0 && s.two_class < 40.0, "{}", s.two_class);
        let (a, b) = s.three_class;
        assert!(a > -994.0 && a < 40.0 && b > 50.0 && b < 1200.0, "{a} {b}");
        assert_eq!(s.histogram.iter().sum::<u64>(), v.len() as u64);
        let (p, median) = s.percentiles[3];
        assert!(p == 50 && (-1000.0..=-994.0).contains(&median), "the median is air's: {median}");
        assert!(
            (1200.0..=1204.0).contains(&s.percentiles[6].1),
            "the 99th percentile is bone's: {:?}",
            s.percentiles[6]
        );
        let bars = s.bars(16, 20);
        assert_eq!(bars.len(), 16);
        assert!(bars[0].ends_with(&"#".repeat(20)), "{}", bars[0]);
    }

    #[test]
    fn a_constant_or_empty_volume_has_no_split() {
        let s = ValueStats::of(&[3.0; 10]).unwrap();
        assert_eq!((s.min, s.max, s.histogram[0]), (3.0, 3.0, 10));
        assert!(ValueStats::of(&[]).is_none());
    }
}
