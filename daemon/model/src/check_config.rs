//! `isowall check-config FILE` and `isowalld check-config FILE`, the one front end of both
//! binaries (the `cli` feature, which both enable): reads and validates a wall config
//! ([`WallConfig::check_report`]). Every problem is printed
//! to stderr as `FILE:LINE:COL: message` and the exit status is 1; a valid config prints a short
//! summary (the wall, its image size and the tiles of every node) to stdout. Headers are read
//! too, never pixels or voxels, and each is checked as the node's own reader checks it:
//! - a DICOM volume's: the series chosen, its grid, or why it cannot be read (including a series
//!   over `[volume] max_bytes`, and a JPEG frame whose own header says another size than the
//!   slice's);
//! - a NRRD's or NIfTI's (every step file's of a glob), where the file is on this machine (sizes
//!   within `[volume] max_bytes`);
//! - the environment's images (`[render] env`: a `.hdr`, or a cube map's six faces), where they
//!   are on this machine, by the rule of `isowall_volume::env_files` the node's loader applies
//!   (a size over the limits, a missing, doubled, non-square or odd-sized face, a file that is
//!   not regular), naming the file and why.
//!
//! The wall's certificates, where keygen wrote them, are checked by the caller's `certificates`
//! (the network crate reads them): one that expires within 30 days is a `warning:` line on
//! stderr (the check still passes), one expired fails the check.

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
            match check_volume_files(&config).and_then(|()| check_dicom(&config)) {
                Err(problem) => {
                    println!("{report}");
                    return Err(CheckFailed(format!("{}: [volume] source: {problem}", a.file.display())));
                }
                Ok(Some(series)) => println!("{report}\n  {series}"),
                Ok(None) => println!("{report}"),
            }
            if let Err(problem) = check_environment(&config) {
                return Err(CheckFailed(format!("{}: [render] env: {problem}", a.file.display())));
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

/// The headers of a volume file, or of every file of a time-step glob, that are on this
/// machine (a controller may have none): what a node's reader refuses from them
/// ([`isowall_volume::io::check_header`]), within `[volume] max_bytes` or the readers' default.
fn check_volume_files(config: &WallConfig) -> Result<(), String> {
    use isowall_volume::io::{check_header, dicom::is_dicom, VolumeLimit};
    use isowall_volume::VolumeSource;
    let limit = config
        .volume
        .max_bytes
        .map_or_else(VolumeLimit::default, |b| VolumeLimit::new(b, "[volume] max_bytes"));
    let files = match config.volume_source().parse::<VolumeSource>() {
        Ok(VolumeSource::File(path)) if !is_dicom(&path) => vec![path],
        Ok(source @ VolumeSource::Steps(_)) => source.step_files().unwrap_or_default(),
        _ => Vec::new(),
    };
    for path in files.iter().filter(|p| p.is_file()) {
        check_header(path, &limit).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// The files of `[render] env` where they are on this machine (a controller may have none): what
/// the node's loader refuses from their headers ([`EnvSource::check_headers`]: a `.hdr` or cube
/// face whose header says a size over the limits, a missing, doubled, non-square or odd-sized
/// face, a path that is not a regular file), no pixel decoded. A FILE.hdr or DIR not here is left
/// to the node; a path here that is neither is refused as the node refuses it.
///
/// [`EnvSource::check_headers`]: isowall_volume::env_files::EnvSource::check_headers
fn check_environment(config: &WallConfig) -> Result<(), String> {
    use isowall_volume::env_files::EnvSource;
    let value = config.env_source();
    let here = || std::path::Path::new(&value).exists();
    match value.parse::<EnvSource>() {
        Ok(EnvSource::Hdr(_)) if !here() => Ok(()),
        Ok(source) => source.check_headers().map_err(|e| e.to_string()),
        Err(e) if here() => Err(e.to_string()),
        Err(_) => Ok(()),
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_volume_header_the_node_would_refuse_fails_the_check_naming_file_and_field() {
        let dir = std::env::temp_dir().join(format!("isowall-check-volume-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let wall = |source: &str, extra: &str| {
            format!(
                "[wall]\nname = \"w\"\n[volume]\nsource = \"{source}\"\n{extra}\n[[tiles]]\nname = \"t\"\nx = 0\ny = 0\n\
                 width = 160\nheight = 120\n[[nodes]]\nname = \"n0\"\naddress = \"127.0.0.1:7401\"\ntiles = [\"t\"]\n"
            )
        };
        let config = dir.join("w.toml");
        let check = |text: String| {
            std::fs::write(&config, text).unwrap();
            run(&CheckConfigArgs { file: config.clone() }, &|_| Ok(Vec::new()))
        };
        // A gzip NRRD whose header claims 1024x1024x256 x 2 steps (2 GiB as float32): no data.
        let head = "NRRD0004\ntype: uchar\ndimension: 4\nsizes: 1024 1024 256 2\nencoding: gzip\n\n";
        std::fs::write(dir.join("bomb.nrrd"), head).unwrap();
        let e = check(wall("bomb.nrrd", "max_bytes = 1073741824")).unwrap_err().to_string();
        assert!(
            e.contains("w.toml: [volume] source:")
                && e.contains("bomb.nrrd: line 4: sizes:")
                && e.contains("over the limit of 1073741824 bytes ([volume] max_bytes)"),
            "{e}"
        );
        // A volume file not on this machine is left to the node; a good one passes.
        check(wall("elsewhere.nrrd", "")).unwrap();
        let ok = "NRRD0004\ntype: uchar\ndimension: 4\nsizes: 2 1 1 2\nencoding: raw\n\n";
        std::fs::write(dir.join("ok.nrrd"), [ok.as_bytes(), &[1, 2, 3, 4]].concat()).unwrap();
        check(wall("ok.nrrd", "")).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn environment_files_the_node_would_refuse_fail_the_check_naming_file_and_why() {
        let dir = std::env::temp_dir().join(format!("isowall-check-env-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("faces")).unwrap();
        let config = dir.join("w.toml");
        let check = |env: &str| {
            let text = format!(
                "[wall]\nname = \"w\"\n[volume]\nsource = \"procedural:sphere:16\"\n[render]\nenv = \"{env}\"\n\
                 [[tiles]]\nname = \"t\"\nx = 0\ny = 0\nwidth = 160\nheight = 120\n[[nodes]]\nname = \"n0\"\n\
                 address = \"127.0.0.1:7401\"\ntiles = [\"t\"]\n"
            );
            std::fs::write(&config, text).unwrap();
            run(&CheckConfigArgs { file: config.clone() }, &|_| Ok(Vec::new())).map_err(|e| e.to_string())
        };
        // An equirectangular .hdr whose header says 16384x8192 (2^27 pixels): no pixel data.
        let hdr = |w: u32, h: u32| format!("#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n");
        std::fs::write(dir.join("big.hdr"), hdr(16384, 8192)).unwrap();
        let e = check("big.hdr").unwrap_err();
        assert!(
            e.contains("w.toml: [render] env: ")
                && e.contains("big.hdr: the HDR header says 16384x8192 (134217728 pixels), over the limit")
                && e.contains("refused before decoding"),
            "{e}"
        );
        // Within the limit, the header passes: its pixels are not read.
        std::fs::write(dir.join("ok.hdr"), hdr(8192, 4096)).unwrap();
        check("ok.hdr").unwrap();
        // A cube map here whose faces the loader would refuse: a missing face, a face too big.
        let e = check("faces").unwrap_err();
        assert!(e.contains("faces: missing face px (.png or .hdr)"), "{e}");
        for face in ["px", "nx", "py", "ny", "pz", "nz"] {
            std::fs::write(dir.join(format!("faces/{face}.hdr")), hdr(8, 8)).unwrap();
        }
        check("faces").unwrap();
        std::fs::write(dir.join("faces/pz.hdr"), hdr(4096, 4096)).unwrap();
        let e = check("faces").unwrap_err();
        assert!(
            e.contains("pz.hdr: the HDR header says 4096x4096, over the largest cube face of 2048x2048"),
            "{e}"
        );
        // A .hdr that is a FIFO is refused at once, not read; a path here that is no environment
        // is refused as the node refuses it.
        assert!(std::process::Command::new("mkfifo").arg(dir.join("fifo.hdr")).status().unwrap().success());
        let e = check("fifo.hdr").unwrap_err();
        assert!(e.contains("fifo.hdr: it is a FIFO (named pipe), not a regular file"), "{e}");
        std::fs::write(dir.join("sky.png"), b"").unwrap();
        let e = check("sky.png").unwrap_err();
        assert!(e.contains("sky.png\" is not an environment"), "{e}");
        // Files that are not on this machine are left to the nodes; the sky has none.
        for elsewhere in ["elsewhere.hdr", "elsewhere-faces", "sky"] {
            check(elsewhere).unwrap();
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
