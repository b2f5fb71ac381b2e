//! Plays a time series through a [`StepCache`] as a wall node would, one step per frame: writes
//! `STEPS` NRRD files of a moving sphere at `N`^3 (float32) to a temporary folder, then asks for
//! step `frame % STEPS` every `FRAME_MS` (0: as fast as the steps arrive) and counts the frames
//! whose step was not loaded yet (the node would report them and show the step it has). Prints
//! steps per second, frames that waited, loads and the most steps resident at once.
//!
//! With `--dir DIR` the steps are written to `DIR/step_KKKK.nrrd` and kept (for a wall config's
//! `source = "DIR/step_*.nrrd"`, iso 0: the sphere's surface); FRAMES 0 only writes them.
//!
//! ```text
//! cargo run --release -p isowall-volume --example play_steps -- N STEPS FRAMES CACHE_MB [FRAME_MS] [--dir DIR]
//! cargo run --release -p isowall-volume --example play_steps -- 64 16 64 64
//! cargo run --release -p isowall-volume --example play_steps -- 256 16 64 512 40
//! cargo run --release -p isowall-volume --example play_steps -- 256 16 0 0 --dir /tmp/steps-256
//! ```

use isowall_volume::{StepCache, StepState, VolumeSource};
use std::io::Write;
use std::time::{Duration, Instant};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let usage = "usage: play_steps N STEPS FRAMES CACHE_MB [FRAME_MS] [--dir DIR]";
    let mut words: Vec<String> = std::env::args().skip(1).collect();
    let kept = match words.iter().position(|w| w == "--dir") {
        Some(i) => {
            let d = words.get(i + 1).ok_or(usage)?.clone();
            words.drain(i..i + 2);
            Some(std::path::PathBuf::from(d))
        }
        None => None,
    };
    let args: Vec<usize> = words.iter().map(|a| a.parse()).collect::<Result<_, _>>()?;
    let [n, steps, frames, cache_mb, rest @ ..] = args.as_slice() else {
        return Err(usage.into());
    };
    let frame_ms = rest.first().copied().unwrap_or(0);
    let temporary = tempfile::tempdir()?;
    let dir = match &kept {
        Some(d) => {
            std::fs::create_dir_all(d)?;
            d.as_path()
        }
        None => temporary.path(),
    };
    for k in 0..*steps {
        let path = dir.join(format!("step_{k:04}.nrrd"));
        let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
        write!(
            f,
            "NRRD0004\ntype: float\ndimension: 3\nsizes: {n} {n} {n}\nendian: little\nencoding: raw\n\n"
        )?;
        let c = *n as f64 * (0.3 + 0.4 * k as f64 / *steps as f64);
        for z in 0..*n {
            for y in 0..*n {
                for x in 0..*n {
                    let d = ((x as f64 - c).powi(2)
                        + (y as f64 - *n as f64 / 2.0).powi(2)
                        + (z as f64 - *n as f64 / 2.0).powi(2))
                    .sqrt();
                    f.write_all(&((*n as f64 / 4.0 - d) as f32).to_le_bytes())?;
                }
            }
        }
    }
    if *frames == 0 {
        println!("wrote {steps} steps of {n}^3 to {}", dir.display());
        return Ok(());
    }
    let source: VolumeSource = format!("{}/step_*.nrrd", dir.display()).parse()?;
    let cache = StepCache::new(source, None, cache_mb << 20, isowall_volume::io::VolumeLimit::default())?;
    let _ = cache.wait(0, Duration::from_secs(60));
    let start = Instant::now();
    let mut waited = 0;
    for frame in 0..*frames {
        let t = Instant::now();
        let step = frame % steps;
        match cache.get(step) {
            StepState::Ready(_) => {}
            StepState::Loading => {
                waited += 1;
                if let StepState::Failed(e) = cache.wait(step, Duration::from_secs(60)) {
                    return Err(e.into());
                }
            }
            StepState::Failed(e) => return Err(e.into()),
        }
        let spent = t.elapsed();
        if let Some(rest) = Duration::from_millis(frame_ms as u64).checked_sub(spent) {
            std::thread::sleep(rest);
        }
    }
    let secs = start.elapsed().as_secs_f64();
    let (peak, loads) = cache.counts();
    println!(
        "{n}^3 x {steps} steps, cache {cache_mb} MiB, frame {frame_ms} ms: {:.1} steps/s over {frames} frames, \
         {waited} frames waited, {loads} loads, at most {peak} steps resident",
        *frames as f64 / secs
    );
    Ok(())
}
