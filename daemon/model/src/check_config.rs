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
//!   within `[volume] max_bytes`). A volume file that is not there fails the check on a node
//!   (`isowalld`), and on a controller (`isowall`) where its folder is there (a misspelt name); a
//!   controller machine without the folder gets a `warning:` line (its drive commands read the
//!   volume too);
//! - the environment's images (`[render] env`: a `.hdr`, or a cube map's six faces), where they
//!   are on this machine, by the rule of `isowall_volume::env_files` the node's loader applies
//!   (a size over the limits, a missing, doubled, non-square or odd-sized face, a file that is
//!   not regular), naming the file and why.
//!
//! The wall's certificates, where keygen wrote them, are checked by the caller's `certificates`
//! (the network crate reads them): one that expires within 30 days is a `warning:` line on
//! stderr (the check still passes), one expired fails the check.

use crate::WallConfig;
use std::path::{Path, PathBuf};

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

/// Where a config is checked: on a node (`isowalld check-config`), which loads the volume and so
/// must hold its file, or on a controller machine (`isowall check-config`), which may not.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CheckedOn {
    Node,
    Controller,
}

/// Prints the report of `a.file` to stdout (or its problems to stderr) and says whether it passed.
pub fn run(a: &CheckConfigArgs, on: CheckedOn, certificates: CertificateCheck) -> Result<(), CheckFailed> {
    let (problems, last) = match WallConfig::check_report(&a.file) {
        Ok(report) => {
            let Ok(config) = WallConfig::load(&a.file) else {
                println!("{report}");
                return Ok(());
            };
            // The summary is printed either way; `FILE: ok` only when every check passed.
            let problem = |p: String| CheckFailed(format!("{}: [volume] source: {p}", a.file.display()));
            let checked = check_volume_files(&config, on).map_err(problem).and_then(|volume_warnings| {
                let series = check_dicom(&config).map_err(problem)?;
                check_iso_range(&config)
                    .map_err(|p| CheckFailed(format!("{}: [volume] iso: {p}", a.file.display())))?;
                check_environment(&config, on)
                    .map_err(|p| CheckFailed(format!("{}: [render] env: {p}", a.file.display())))?;
                Ok((volume_warnings, series))
            });
            let (volume_warnings, series) = match checked {
                Ok(c) => c,
                Err(e) => {
                    println!("{}", config.summary());
                    return Err(e);
                }
            };
            for w in volume_warnings {
                eprintln!("warning: {}: [volume] source: {w}", a.file.display());
            }
            let report = match series {
                Some(series) => format!("{report}\n  {series}"),
                None => report,
            };
            return match certificates(&config) {
                Ok(warnings) => {
                    println!("{report}");
                    for w in warnings {
                        eprintln!("warning: {w}");
                    }
                    Ok(())
                }
                Err(problems) => {
                    println!("{}", config.summary());
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

/// The headers of a volume file, or of every file of a time-step glob: what a node's reader
/// refuses from them ([`isowall_volume::io::check_header`]), within `[volume] max_bytes` or the
/// readers' default (a store read through the brick cache: its metadata only). A file (or a glob's every file) not there: see [`missing_volume`]. `Ok`
/// holds warnings.
fn check_volume_files(config: &WallConfig, on: CheckedOn) -> Result<Vec<String>, String> {
    use isowall_volume::io::{check_header, dicom::is_dicom, VolumeLimit};
    use isowall_volume::VolumeSource;
    let limit = config
        .volume
        .max_bytes
        .map_or_else(VolumeLimit::default, |b| VolumeLimit::new(b, "[volume] max_bytes"));
    let files = match config.volume_source().parse::<VolumeSource>() {
        Ok(VolumeSource::File(path)) if !path.exists() => return missing_volume(&path, "no such file", on),
        Ok(VolumeSource::File(path)) if !is_dicom(&path) => vec![path],
        Ok(source @ VolumeSource::Steps(_)) => match source.step_files() {
            Ok(files) => files,
            Err(_) => {
                return missing_volume(Path::new(&source.to_string()), "no file matches the pattern", on)
            }
        },
        _ => Vec::new(),
    };
    for path in files.iter().filter(|p| p.is_file() || isowall_volume::io::ome_zarr::is_zarr(p)) {
        // A store read through the brick cache is never loaded whole: `max_bytes` is not its
        // bound; its metadata must still open.
        if config.volume.gpu_budget_mb.is_some() && isowall_volume::io::ome_zarr::is_zarr(path) {
            isowall_volume::io::ome_zarr::OmeZarr::open(path).map_err(|e| e.to_string())?;
            continue;
        }
        check_header(path, &limit).map_err(|e| e.to_string())?;
    }
    Ok(Vec::new())
}

/// `[volume] iso` within the volume's value range, where the volume is on this machine: it is
/// read (within `[volume] max_bytes`) for its range, or for a store `convert` wrote its per-brick
/// min/max only, and the iso held to the rule `up` and the nodes apply
/// ([`isowall_volume::check_iso`]). A volume not here, or no iso set: nothing to check.
fn check_iso_range(config: &WallConfig) -> Result<(), String> {
    use isowall_volume::io::VolumeLimit;
    use isowall_volume::VolumeSource;
    let Some(iso) = config.volume.iso else { return Ok(()) };
    let Ok(source) = config.volume_source().parse::<VolumeSource>() else { return Ok(()) };
    let here = match &source {
        VolumeSource::File(p) | VolumeSource::DicomSeries { path: p, .. } => p.exists(),
        VolumeSource::Steps(_) => source.step_files().is_ok(),
        VolumeSource::Procedural { .. } => true,
    };
    if !here {
        return Ok(());
    }
    let limit = config
        .volume
        .max_bytes
        .map_or_else(VolumeLimit::default, |b| VolumeLimit::new(b, "[volume] max_bytes"));
    // A store `convert` wrote holds level 0's range in its per-brick min/max: nothing is read.
    let store_range = match &source {
        VolumeSource::File(p) if isowall_volume::io::ome_zarr::is_zarr(p) => {
            use isowall_volume::brick_cache::BrickSource;
            let store = isowall_volume::io::ome_zarr::OmeZarr::open(p).map_err(|e| e.to_string())?;
            let bricks = store.into_bricks(0).map_err(|e| e.to_string())?;
            bricks.value_range()
        }
        _ => None,
    };
    let (lo, hi) = match store_range {
        Some(range) => range,
        None => {
            let raw = config.raw_spec().map_err(|e| e.to_string())?;
            let volume = source.load_step_within(raw.as_ref(), 0, &limit).map_err(|e| e.to_string())?;
            volume.value_range()
        }
    };
    isowall_volume::check_iso(iso, (f64::from(lo), f64::from(hi))).map_err(|e| format!("{e} ({source})"))
}

/// A volume `path` that is not on this machine (`why`: no such file, no file matching a glob): a
/// problem on a node, which would fail to load it, and on a controller where the path's folder is
/// there (a misspelt name, most likely); else a warning, since a controller machine may not hold
/// the nodes' files, but its drive commands read the volume too (its box and value range).
fn missing_volume(path: &Path, why: &str, on: CheckedOn) -> Result<Vec<String>, String> {
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if on == CheckedOn::Node {
        return Err(format!("{}: {why} on this node: the node could not load the volume", path.display()));
    }
    if folder.is_dir() {
        return Err(format!(
            "{}: {why} (its folder {} is here): the nodes and `isowall up` could not load the volume",
            path.display(),
            folder.display()
        ));
    }
    Ok(vec![format!(
        "{} is not on this machine ({} is not here): every node must hold it, and `isowall up`, `orbit`, \
         `session`, `demo` and `console` read it here too (the volume's box and value range)",
        path.display(),
        folder.display()
    )])
}

/// The files of `[render] env` where they are on this machine (a controller may have none): what
/// the node's loader refuses from their headers ([`EnvSource::check_headers`]: a `.hdr` or cube
/// face whose header says a size over the limits, a missing, doubled, non-square or odd-sized
/// face, a path that is not a regular file), no pixel decoded. A FILE.hdr or DIR not here fails
/// the check on a node and is left to the nodes on a controller; a path here that is neither is
/// refused as the node refuses it.
///
/// [`EnvSource::check_headers`]: isowall_volume::env_files::EnvSource::check_headers
fn check_environment(config: &WallConfig, on: CheckedOn) -> Result<(), String> {
    use isowall_volume::env_files::EnvSource;
    let value = config.env_source();
    let here = Path::new(&value).exists();
    match value.parse::<EnvSource>() {
        Ok(EnvSource::Sky) => Ok(()),
        Ok(source) if here => source.check_headers().map_err(|e| e.to_string()),
        Err(e) if here => Err(e.to_string()),
        _ if on == CheckedOn::Node => Err(format!(
            "{value}: no such file or folder on this node: the node could not load its environment"
        )),
        _ => Ok(()),
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
            run(&CheckConfigArgs { file: config.clone() }, CheckedOn::Controller, &|_| Ok(Vec::new()))
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
        // A good one passes.
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
            run(&CheckConfigArgs { file: config.clone() }, CheckedOn::Node, &|_| Ok(Vec::new()))
                .map_err(|e| e.to_string())
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
        // Files that are not on this machine: a node could not load them; a controller leaves
        // them to the nodes. The sky has none.
        check("sky").unwrap();
        for elsewhere in ["elsewhere.hdr", "elsewhere-faces"] {
            let e = check(elsewhere).unwrap_err();
            assert!(e.contains("no such file or folder on this node"), "{e}");
            let on_controller =
                run(&CheckConfigArgs { file: config.clone() }, CheckedOn::Controller, &|_| Ok(Vec::new()));
            assert!(on_controller.is_ok(), "{elsewhere}: {on_controller:?}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_iso_outside_the_volumes_range_fails_the_check_where_the_volume_is_here() {
        let config = |source: &str, iso: &str| {
            let text = format!(
                "[wall]\nname = \"w\"\n[volume]\nsource = \"{source}\"\niso = {iso}\n[[tiles]]\nname = \"t\"\nx = 0\ny = 0\n\
                 width = 64\nheight = 48\n[[nodes]]\nname = \"n\"\naddress = \"127.0.0.1:7999\"\ntiles = [\"t\"]\n"
            );
            WallConfig::parse(&text, Path::new("w.toml")).unwrap()
        };
        // procedural:sphere:16 holds values from about -7.7 to 4.4.
        let e = check_iso_range(&config("procedural:sphere:16", "100")).unwrap_err();
        assert!(e.contains("100") && e.contains("outside") && e.contains("procedural:sphere:16"), "{e}");
        assert_eq!(check_iso_range(&config("procedural:sphere:16", "0")), Ok(()));
        // A file not on this machine: the node checks it.
        assert_eq!(check_iso_range(&config("/nowhere/scan.nrrd", "100")), Ok(()));
    }

    #[test]
    fn a_volume_file_that_is_not_there_fails_on_a_node_and_where_its_folder_is_else_warns() {
        let dir = std::env::temp_dir().join(format!("isowall-check-missing-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let config = |source: &str| {
            let text = format!(
                "[wall]\nname = \"w\"\n[volume]\nsource = \"{source}\"\n[[tiles]]\nname = \"t\"\nx = 0\ny = 0\n\
                 width = 160\nheight = 120\n[[nodes]]\nname = \"n0\"\naddress = \"127.0.0.1:7401\"\ntiles = [\"t\"]\n"
            );
            WallConfig::parse(&text, &dir.join("w.toml")).unwrap()
        };
        // The folder is here, the file is not (a misspelt name): a problem on both.
        let here = config("ct-cranum.nrrd");
        let file = dir.join("ct-cranum.nrrd").display().to_string();
        for on in [CheckedOn::Node, CheckedOn::Controller] {
            let e = check_volume_files(&here, on).unwrap_err();
            assert!(e.starts_with(&format!("{file}: no such file")), "{on:?}: {e}");
        }
        let glob = config("steps/step_*.nrrd");
        std::fs::create_dir_all(dir.join("steps")).unwrap();
        let e = check_volume_files(&glob, CheckedOn::Controller).unwrap_err();
        assert!(e.contains("step_*.nrrd: no file matches the pattern"), "{e}");
        // Nor its folder: a warning on a controller machine, a problem on a node.
        let elsewhere = config("data/ct.nrrd");
        let file = dir.join("data/ct.nrrd").display().to_string();
        let w = check_volume_files(&elsewhere, CheckedOn::Controller).unwrap();
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(w[0].starts_with(&format!("{file} is not on this machine")), "{w:?}");
        let e = check_volume_files(&elsewhere, CheckedOn::Node).unwrap_err();
        assert!(e.starts_with(&format!("{file}: no such file on this node")), "{e}");
        // A procedural volume has no file.
        assert_eq!(check_volume_files(&config("procedural:sphere"), CheckedOn::Node), Ok(Vec::new()));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
