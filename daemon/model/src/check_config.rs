//! `isowall check-config FILE` and `isowalld check-config FILE`, the one front end of both
//! binaries (the `cli` feature, which both enable): reads and validates a wall config
//! ([`WallConfig::check_report`]). Every problem is printed
//! to stderr as `FILE:LINE:COL: message` and the exit status is 1; a valid config prints a short
//! summary (the wall, its image size and the tiles of every node) to stdout. A DICOM volume's
//! headers are read too (no pixels): the series chosen, its grid, or why it cannot be read
//! (including a series over `[volume] max_bytes`, and a JPEG frame whose own header says another
//! size than the slice's). The wall's certificates, where keygen wrote
//! them, are checked by the caller's `certificates` (the network crate reads them): one that
//! expires within 30 days is a `warning:` line on stderr (the check still passes), one expired
//! fails the check.

use crate::WallConfig;
use std::path::PathBuf;

/// Why a config did not pass; every problem was printed to stderr first.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct CheckFailed(String);

#[derive(clap::Args, Debug)]
pub struct CheckConfigArgs {
    /// The wall config (TOML), e.g. wall-configs/local-2x2.toml
    #[arg(value_name = "FILE")]
    pub file: PathBuf,
}

/// What a certificate check says of a wall: warnings (each a line), or why it cannot work.
pub type CertificateCheck<'a> = &'a dyn Fn(&WallConfig) -> Result<Vec<String>, String>;

/// Prints the report of `a.file` to stdout (or its problems to stderr) and says whether it passed.
pub fn run(a: &CheckConfigArgs, certificates: CertificateCheck) -> Result<(), CheckFailed> {
    let (problems, last) = match WallConfig::check_report(&a.file) {
        Ok(report) => {
            let Ok(config) = WallConfig::load(&a.file) else {
                println!("{report}");
                return Ok(());
            };
            match check_dicom(&config) {
                Err(problem) => {
                    println!("{report}");
                    return Err(CheckFailed(format!("{}: [volume] source: {problem}", a.file.display())));
                }
                Ok(Some(series)) => println!("{report}\n  {series}"),
                Ok(None) => println!("{report}"),
            }
            return match certificates(&config) {
                Ok(warnings) => {
                    for w in warnings {
                        eprintln!("warning: {w}");
                    }
                    Ok(())
                }
                Err(problems) => {
                    eprintln!("{problems}");
                    Err(CheckFailed(problems.lines().last().unwrap_or_default().to_string()))
                }
            };
        }
        Err(e) => e,
    };
    eprintln!("{problems}");
    Err(CheckFailed(last))
}

/// A DICOM volume's series, from its headers: `Ok(None)` when the volume is not DICOM.
fn check_dicom(config: &WallConfig) -> Result<Option<String>, String> {
    use isowall_volume::io::dicom::{is_dicom, Series};
    use isowall_volume::VolumeSource;
    let (path, series) = match config.volume_source().parse::<VolumeSource>() {
        Ok(VolumeSource::DicomSeries { path, series }) => (path, Some(series)),
        Ok(VolumeSource::File(path)) if is_dicom(&path) => (path, None),
        _ => return Ok(None),
    };
    let s = Series::open(&path, series.as_deref()).map_err(|e| e.to_string())?;
    // What a read refuses before decoding: a compressed frame whose own header says another size.
    s.check_frames().map_err(|e| e.to_string())?;
    if let Some(bytes) = config.volume.max_bytes {
        let limit = isowall_volume::io::VolumeLimit::new(bytes, "[volume] max_bytes");
        s.check_within(&limit).map_err(|e| e.to_string())?;
    }
    let [nx, ny, nz] = s.dims;
    Ok(Some(format!(
        "volume: DICOM series {} of {nx}x{ny}x{nz} slices, spacing {} {} {}",
        s.uid, s.spacing.x, s.spacing.y, s.spacing.z
    )))
}
