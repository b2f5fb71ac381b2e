//! Measures what a time-varying volume's step cache costs: writes a hostile 4-D file (a gzip
//! NRRD of N^3 x T uchar steps, or a `.nii.gz` of T one-voxel steps), plays every step through a
//! `StepCache` with the budget given, and prints the process's peak resident memory (VmHWM)
//! and the time taken.
//!
//! `cargo run --release -p isowall-volume --example step_cache_memory -- nrrd 32 128 16777216`
//! `cargo run --release -p isowall-volume --example step_cache_memory -- nii 1 32767 16777216`

use isowall_volume::io::VolumeLimit;
use isowall_volume::{StepCache, StepState, VolumeSource};
use std::io::Write;
use std::time::{Duration, Instant};

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

fn vm_hwm_kib() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [kind, n, steps, budget] = [0, 1, 2, 3].map(|i| args.get(i).cloned().unwrap_or_default());
    let (n, steps, budget): (usize, usize, usize) =
        (n.parse().unwrap_or(32), steps.parse().unwrap_or(128), budget.parse().unwrap_or(16 << 20));
    let dir = tempfile::tempdir().unwrap();
    let path = if kind == "nii" {
        let mut h = vec![0u8; 352];
        h[0..4].copy_from_slice(&348i32.to_le_bytes());
        for (i, d) in [4i16, 1, 1, 1, steps as i16, 1, 1, 1].iter().enumerate() {
            h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
        }
        h[70..72].copy_from_slice(&2i16.to_le_bytes());
        h[72..74].copy_from_slice(&8i16.to_le_bytes());
        for i in 0..8 {
            h[76 + 4 * i..80 + 4 * i].copy_from_slice(&1f32.to_le_bytes());
        }
        h[108..112].copy_from_slice(&352f32.to_le_bytes());
        h[344..348].copy_from_slice(b"n+1\0");
        h.extend(vec![7u8; steps]);
        let p = dir.path().join("tiny.nii.gz");
        std::fs::write(&p, gzip(&h)).unwrap();
        p
    } else {
        let voxels = vec![7u8; n * n * n * steps];
        let head =
            format!("NRRD0004\ntype: uchar\ndimension: 4\nsizes: {n} {n} {n} {steps}\nencoding: gzip\n\n");
        let p = dir.path().join("four.nrrd");
        std::fs::write(&p, [head.into_bytes(), gzip(&voxels)].concat()).unwrap();
        p
    };
    let file_bytes = std::fs::metadata(&path).unwrap().len();
    let before = vm_hwm_kib();
    let start = Instant::now();
    let c = StepCache::new(VolumeSource::File(path), None, budget, VolumeLimit::default()).unwrap();
    // Let the cache fill its budget ahead of step 0 (as it does while a wall shows a step), then
    // play every step in order, waiting for each.
    let _ = c.wait(0, Duration::from_secs(600));
    let mut last = (0, Instant::now());
    while last.1.elapsed() < Duration::from_millis(500) {
        std::thread::sleep(Duration::from_millis(20));
        let loads = c.counts().1;
        if loads != last.0 {
            last = (loads, Instant::now());
        }
    }
    for k in 0..steps {
        match c.wait(k, Duration::from_secs(600)) {
            StepState::Ready(_) => {}
            other => panic!("step {k}: {other:?}"),
        }
    }
    let (peak_steps, loads) = c.counts();
    println!(
        "{kind} {n}^3 x {steps} steps, {file_bytes} bytes on disk, cache_bytes {budget}: {loads} loads in {:.2?}, \
         {peak_steps} steps resident at most, VmHWM {:.1} MiB (before the cache {:.1} MiB)",
        start.elapsed(),
        vm_hwm_kib() as f64 / 1024.0,
        before as f64 / 1024.0
    );
}
