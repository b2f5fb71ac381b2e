//! Shared by the GPU integration tests.
#![allow(dead_code)]

use isowall_render::gpu::{GpuError, GpuRenderer};
use isowall_render::Frame;

/// The GPU renderer, or `None` (after a message) where no Vulkan adapter exists. Under `CI=true`
/// a missing adapter fails the test loudly instead: GPU tests never skip silently in CI.
pub fn gpu() -> Option<GpuRenderer> {
    match GpuRenderer::new() {
        Ok(g) => Some(g),
        // Only a missing adapter may skip, and never in CI; any other failure is a failure.
        Err(e @ GpuError::NoAdapter(_)) if std::env::var("CI").as_deref() != Ok("true") => {
            eprintln!("skipping GPU test: {e}");
            None
        }
        Err(e) => panic!("GPU set-up failed: {e}"),
    }
}

/// Agreement of a GPU frame with a reference frame.
#[derive(Debug)]
pub struct Agreement {
    /// Pixels whose hit flag differs, not counting silhouette pixels.
    pub mask_mismatches: usize,
    /// Pixels that differ on the silhouette (a reference pixel with a neighbour of the other kind).
    pub silhouette_mismatches: usize,
    pub both_hit: usize,
    /// Depth error in voxels (of the smallest spacing) over pixels both hit: median, max.
    pub depth_median: f64,
    pub depth_p99: f64,
    /// Normal error in degrees over pixels both hit: median, 99th percentile.
    pub normal_median_deg: f64,
    pub normal_p99_deg: f64,
}

fn quantile(mut v: Vec<f64>, q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

pub fn compare(gpu: &Frame, reference: &Frame, voxel: f64) -> Agreement {
    assert_eq!((gpu.width, gpu.height), (reference.width, reference.height));
    let (w, h) = (reference.width as i64, reference.height as i64);
    let at = |x: i64, y: i64| reference.hit[(y * w + x) as usize];
    let silhouette = |x: i64, y: i64| {
        let c = at(x, y);
        (-1..=1).any(|dy| {
            (-1..=1).any(|dx| {
                let (nx, ny) = (x + dx, y + dy);
                nx >= 0 && ny >= 0 && nx < w && ny < h && at(nx, ny) != c
            })
        })
    };
    let (mut mask_mismatches, mut silhouette_mismatches) = (0, 0);
    let (mut depth, mut normal) = (Vec::new(), Vec::new());
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            match (gpu.hit[i], reference.hit[i]) {
                (a, b) if a != b => {
                    if silhouette(x, y) {
                        silhouette_mismatches += 1
                    } else {
                        mask_mismatches += 1
                    }
                }
                (true, true) => {
                    depth.push((gpu.depth[i] as f64 - reference.depth[i] as f64).abs() / voxel);
                    let (a, b) = (gpu.normal[i], reference.normal[i]);
                    let dot: f64 = (0..3).map(|c| a[c] as f64 * b[c] as f64).sum();
                    let na: f64 = a.iter().map(|c| (*c as f64).powi(2)).sum::<f64>().sqrt();
                    let nb: f64 = b.iter().map(|c| (*c as f64).powi(2)).sum::<f64>().sqrt();
                    normal.push((dot / (na * nb)).clamp(-1.0, 1.0).acos().to_degrees());
                }
                _ => {}
            }
        }
    }
    Agreement {
        mask_mismatches,
        silhouette_mismatches,
        both_hit: depth.len(),
        depth_median: quantile(depth.clone(), 0.5),
        depth_p99: quantile(depth, 0.99),
        normal_median_deg: quantile(normal.clone(), 0.5),
        normal_p99_deg: quantile(normal, 0.99),
    }
}
