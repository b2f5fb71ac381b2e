//! Loads a volume source (any `--volume` form) once and prints how long it took, for load-time
//! and peak-memory measurements (run it under `/usr/bin/time -v`):
//!
//! ```text
//! cargo run --release -p isowall-volume --example load_volume -- /tmp/ct-dicom [STEP]
//! ```

use isowall_volume::VolumeSource;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(source) = args.first() else { return Err("usage: load_volume SOURCE [STEP]".into()) };
    let step = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(0);
    let start = Instant::now();
    let v = source.parse::<VolumeSource>()?.load_step(None, step)?;
    let ms = start.elapsed().as_secs_f64() * 1e3;
    let (lo, hi) = v.value_range();
    println!("{source}: {:?} voxels, range [{lo}, {hi}], loaded in {ms:.1} ms", v.dims());
    Ok(())
}
