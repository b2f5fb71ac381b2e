//! What the benchmarks share: medians, error statistics and the scene and sample lists of their
//! flags. It imports nothing of its sibling modules.

use anyhow::Result;

pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Splits `VOLUME[@ISO]`.
pub fn scene_spec(scene: &str) -> Result<(&str, Option<f64>)> {
    Ok(match scene.rsplit_once('@') {
        Some((s, i)) => {
            (s, Some(i.parse::<f64>().map_err(|_| anyhow::anyhow!("{scene}: iso '{i}' is not a number"))?))
        }
        None => (scene, None),
    })
}

/// RMSE and 99th percentile of |a - b| over pixels where `hit` holds.
pub fn error_stats(a: &[f32], b: &[f32], hit: &[bool]) -> (f64, f64) {
    let mut d: Vec<f64> =
        (0..a.len()).filter(|&i| hit[i]).map(|i| (a[i] as f64 - b[i] as f64).abs()).collect();
    if d.is_empty() {
        return (0.0, 0.0);
    }
    let rmse = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
    d.sort_by(f64::total_cmp);
    (rmse, d[(d.len() - 1) * 99 / 100])
}

/// A `--samples` list: whole numbers, comma-separated.
pub fn sample_list(list: &str) -> Result<Vec<u32>> {
    list.split(',')
        .map(|s| {
            s.trim().parse::<u32>().map_err(|_| anyhow::anyhow!("--samples: '{s}' is not a whole number"))
        })
        .collect()
}
