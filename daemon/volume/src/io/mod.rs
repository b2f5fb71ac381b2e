//! Volume file readers. The format is chosen by the file name: `.nrrd`/`.nhdr` (NRRD), `.mhd`/`.mha`
//! (MetaImage), `.nii`/`.nii.gz`/`.hdr` (NIfTI-1 and NIfTI-2), a folder, `.dcm`/`.dicom`/`.ima` or a file with
//! DICOM's magic (a DICOM series, [`dicom`]), a Zarr store (`*.zarr`, or a folder with `zarr.json` or
//! `.zattrs`: an OME-Zarr pyramid, [`ome_zarr`]); anything else is raw and needs a [`RawSpec`].
//! Every error names the file and what is wrong with it; nothing here panics on bad input.
//! Voxel values are kept in the data's own units (no rescaling except NIfTI's scl_slope/inter),
//! converted to `f32`: 32-bit integers beyond 2^24 and doubles lose precision, doubles beyond the
//! `f32` range become infinite and are refused like NaN.
//!
//! What each reader supports and refuses is in its module: [`raw`], [`nrrd`], [`metaimage`],
//! [`nifti`]. Common to all of them:
//!
//! - three dimensions (a 4-D NIfTI or NRRD is a series of 3-D time steps, [`load_step_within`]),
//!   one scalar per voxel, x fastest; the grid must be axis-aligned (a negative
//!   axis direction, where a format has one, is undone by mirroring the data, so every sample keeps
//!   its world position);
//! - at most [`MAX_VOXELS`] voxels, and at most a [`VolumeLimit`] of bytes as Isowall holds them
//!   (`f32`, 4 bytes a voxel; by default [`DEFAULT_MAX_BYTES`], the daemon passes the GPU's
//!   largest storage binding and the wall's `[volume] max_bytes`): both checked from the header,
//!   before anything is allocated or inflated, with an error naming the file and the limit;
//! - only regular files are read: a volume, or a data file a header names, that is a FIFO, a
//!   device, a socket or a directory is refused (its type is checked before it is opened, it is
//!   opened without blocking and checked again), so no header can make a reader wait forever;
//! - a detached header names its data file relative to its own folder, never above it: absolute
//!   paths and `..` are refused (a header cannot be used to read, or learn the size of, any
//!   other file); symbolic links inside the folder are followed;
//! - uncompressed data must fill the file exactly (after its header and skips): fewer bytes are
//!   "truncated", more are "extra data"; compressed data must decompress to exactly the voxels'
//!   bytes and is read through a bounded reader (never more than one byte past what the volume
//!   needs, memory growing only as data arrives), so a small file that claims a huge volume or a
//!   compression bomb costs no more than the data really there;
//! - NaN and Inf voxels are refused ([`VolumeError::NonFinite`], naming the file).

mod decode;
pub mod dicom;
pub mod dicom_write;
mod header;
mod limit;
pub mod metaimage;
pub mod nifti;
pub mod nrrd;
pub mod ome_zarr;
pub mod ome_zarr_write;
mod plan;
pub mod raw;
pub mod regular;
#[cfg(test)]
pub(crate) mod testutil;
pub mod zarr_codecs;

pub use decode::VoxelType;
pub(crate) use decode::{
    check_raw_size, decode_into, read_data, read_full, read_voxels, skip_bytes, skip_lines, DataSpec,
    Encoding, Files, Layout, Scale,
};
pub(crate) use header::{dims3, numbers, spacing3, vec3, AxisSteps, HeaderLines};
pub use limit::{VolumeLimit, DEFAULT_MAX_BYTES, MAX_VOXELS};
pub(crate) use plan::{FilePlan, StepFile};

use crate::{Volume, VolumeError};
use glam::DVec3;
use std::fs::File;
use std::io::{self, BufReader};
use std::path::{Path, PathBuf};

/// What a raw file does not say about itself.
#[derive(Clone, Debug, PartialEq)]
pub struct RawSpec {
    pub dims: [usize; 3],
    pub voxel: VoxelType,
    pub spacing: DVec3,
    pub big_endian: bool,
    /// Bytes to skip at the start of the file.
    pub header_bytes: u64,
}

/// File formats, as recognised by the file name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FileFormat {
    Raw,
    Nrrd,
    MetaImage,
    Nifti,
    Dicom,
    OmeZarr,
}

/// The name of the format a file is read as ("NRRD", "MetaImage", "NIfTI", "DICOM", "raw").
pub fn format_name(path: &Path) -> &'static str {
    match FileFormat::of(path) {
        FileFormat::Raw => "raw",
        FileFormat::Nrrd => "NRRD",
        FileFormat::MetaImage => "MetaImage",
        FileFormat::Nifti => "NIfTI",
        FileFormat::Dicom => "DICOM",
        FileFormat::OmeZarr => "OME-Zarr",
    }
}

impl FileFormat {
    /// The format a file name says (case-insensitive); a folder or a file with DICOM's magic is
    /// DICOM; anything else unknown is raw.
    fn of(path: &Path) -> FileFormat {
        if ome_zarr::is_zarr(path) {
            return FileFormat::OmeZarr;
        }
        match FileFormat::by_name(path) {
            FileFormat::Raw if dicom::is_dicom(path) => FileFormat::Dicom,
            f => f,
        }
    }

    fn by_name(path: &Path) -> FileFormat {
        let name = path.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
        let ends = |exts: &[&str]| exts.iter().any(|e| name.ends_with(e));
        if ends(&[".nrrd", ".nhdr"]) {
            FileFormat::Nrrd
        } else if ends(&[".mhd", ".mha"]) {
            FileFormat::MetaImage
        } else if ends(&[".nii", ".nii.gz", ".hdr"]) {
            FileFormat::Nifti
        } else if ends(&[".dcm", ".dicom", ".ima"]) {
            FileFormat::Dicom
        } else {
            FileFormat::Raw
        }
    }
}

/// Reads a volume file, choosing the reader by the file name, within the default
/// [`VolumeLimit`]. `raw` is needed for raw files and ignored (with a warning) for the
/// self-describing formats. A 4-D file gives its first time step.
pub fn load(path: &Path, raw: Option<&RawSpec>) -> Result<Volume, VolumeError> {
    load_within(path, raw, &VolumeLimit::default())
}

/// [`load`] within `limit`, checked from the header before any voxel is read.
pub fn load_within(path: &Path, raw: Option<&RawSpec>, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
    load_step_within(path, raw, 0, limit)
}

/// [`load_step_within`] within the default [`VolumeLimit`].
pub fn load_step(path: &Path, raw: Option<&RawSpec>, step: usize) -> Result<Volume, VolumeError> {
    load_step_within(path, raw, step, &VolumeLimit::default())
}

/// Reads time step `step` of a volume file within `limit`: a 4-D NIfTI or NRRD holds `dim[4]`
/// steps (the limit applies to the whole file, checked from its header; only the step's voxels
/// are read and held, [`StepFile`]), every other file one (step 0).
pub fn load_step_within(
    path: &Path,
    raw: Option<&RawSpec>,
    step: usize,
    limit: &VolumeLimit,
) -> Result<Volume, VolumeError> {
    let format = FileFormat::of(path);
    if format != FileFormat::Raw && raw.is_some() {
        tracing::warn!(
            "{}: is a {format:?} file, which describes itself; ignoring the raw volume options (--dims, --type, --spacing)",
            path.display()
        );
    }
    if let Some(mut steps) = step_file(path, limit)?.filter(|f| f.steps > 1) {
        return steps.read(step);
    }
    let (volume, steps) = match format {
        FileFormat::OmeZarr => return ome_zarr::read(path, step, limit),
        FileFormat::Nrrd => nrrd::read(path, limit)?,
        FileFormat::MetaImage => (metaimage::read(path, limit)?, 1),
        FileFormat::Nifti => nifti::read(path, limit)?,
        FileFormat::Dicom => (dicom::read(path, None, limit)?, 1),
        FileFormat::Raw => match raw {
            Some(spec) => (raw::read(path, spec, limit)?, 1),
            None => {
                return Err(format_err(
                    path,
                    "not a known volume format (.nrrd, .nhdr, .mhd, .mha, .nii, .nii.gz, .hdr, DICOM), so it is read as \
                     raw voxels; a raw volume needs --dims NX,NY,NZ, --type and --spacing SX,SY,SZ",
                ))
            }
        },
    };
    time_step(path, volume, steps, step)
}

/// What a node's reader refuses of a volume file from its header alone, without reading a voxel
/// (for `check-config`): a NRRD's or NIfTI's sizes (all its time steps) over `limit`, or
/// uncompressed data that does not fill its file. Other formats pass here (a DICOM series has
/// [`dicom::Series`]'s checks; the rest are checked when read).
pub fn check_header(path: &Path, limit: &VolumeLimit) -> Result<(), VolumeError> {
    if FileFormat::of(path) == FileFormat::OmeZarr {
        let store = ome_zarr::OmeZarr::open(path)?;
        if store.finest_within(limit).is_none() {
            return Err(store.none_within(limit));
        }
        return Ok(());
    }
    step_file(path, limit).map(|_| ())
}

/// The number of time steps of a volume file, from its header: `dim[4]` of a 4-D NIfTI, the 4th
/// size of a 4-D NRRD, 1 for every other file.
pub fn time_steps(path: &Path) -> Result<usize, VolumeError> {
    match FileFormat::of(path) {
        FileFormat::Nrrd => nrrd::time_steps(path),
        FileFormat::Nifti => nifti::time_steps(path),
        FileFormat::OmeZarr => Ok(ome_zarr::OmeZarr::open(path)?.steps()),
        _ => Ok(1),
    }
}

/// A NRRD or NIfTI file as time steps read one at a time, within `limit` (its whole voxels,
/// from the header); `None` for the other formats (one step each).
pub(crate) fn step_file(path: &Path, limit: &VolumeLimit) -> Result<Option<StepFile>, VolumeError> {
    match FileFormat::of(path) {
        FileFormat::Nrrd => nrrd::step_file(path, limit).map(Some),
        FileFormat::Nifti => nifti::step_file(path, limit).map(Some),
        _ => Ok(None),
    }
}

/// Step `step` of `steps` stacked along z in `v`.
fn time_step(path: &Path, v: Volume, steps: usize, step: usize) -> Result<Volume, VolumeError> {
    if step >= steps {
        return Err(format_err(
            path,
            format!("has no time step {step}: it holds {steps} (0 to {})", steps - 1),
        ));
    }
    if steps == 1 {
        return Ok(v);
    }
    let [nx, ny, nzt] = v.dims;
    let nz = nzt / steps;
    // Copied out, so the step holds its own voxels only, not the whole file's buffer.
    let data = v.data[nx * ny * nz * step..nx * ny * nz * (step + 1)].to_vec();
    Volume::new(v.name, [nx, ny, nz], v.spacing, v.origin, data)
}

/// Where the voxels of a file are, for partial reads ([`crate::region`]): raw files and NRRD
/// (unless a `space directions` mirrors an axis). `None`: the format is read whole.
/// The patient orientation of a file read by a [`plan`] (from its header): a NRRD's `space`;
/// raw files have none.
pub(crate) fn plan_orientation(path: &Path) -> Result<Option<crate::Orientation>, VolumeError> {
    match FileFormat::of(path) {
        FileFormat::Nrrd => nrrd::orientation(path),
        _ => Ok(None),
    }
}

pub(crate) fn plan(
    path: &Path,
    raw: Option<&RawSpec>,
) -> Result<Option<(FilePlan, DVec3, DVec3)>, VolumeError> {
    match FileFormat::of(path) {
        FileFormat::Nrrd => nrrd::plan(path),
        FileFormat::Raw => {
            let Some(spec) = raw else {
                return load_within(path, raw, &VolumeLimit::default()).map(|_| None);
            };
            let layout = Layout { dims: spec.dims, voxel: spec.voxel, big_endian: spec.big_endian };
            layout.voxel_count().map_err(|e| format_err(path, format!("--dims {e}")))?;
            let s = spec.spacing;
            if !(s.is_finite() && s.min_element() > 0.0) {
                return Err(format_err(
                    path,
                    format!("--spacing {},{},{}: spacings must be finite and positive", s.x, s.y, s.z),
                ));
            }
            let (_, len) = open(path)?;
            check_raw_size(Files::single(path), len, spec.header_bytes, &layout)?;
            let plan = FilePlan {
                header: path.to_path_buf(),
                data: path.to_path_buf(),
                layout,
                start: spec.header_bytes,
                encoding: Encoding::Raw,
                decoded_skip: 0,
                trailing: false,
            };
            Ok(Some((plan, spec.spacing, DVec3::ZERO)))
        }
        FileFormat::MetaImage | FileFormat::Nifti | FileFormat::OmeZarr => Ok(None),
        // Read slice by slice through `Series` (crate::region), not through a file plan.
        FileFormat::Dicom => Ok(None),
    }
}

// ---------------------------------------------------------------------------------------------
// Shared by the readers: errors naming the file, opening regular files only, data files inside
// the header's folder, and the volume they make.

/// A [`VolumeError::Format`] for `path`.
pub(crate) fn format_err(path: &Path, what: impl Into<String>) -> VolumeError {
    VolumeError::Format { path: path.to_path_buf(), what: what.into() }
}

/// A [`VolumeError::Io`] for `path`.
pub(crate) fn io_err(path: &Path, source: io::Error) -> VolumeError {
    VolumeError::Io { path: path.to_path_buf(), error: source }
}

/// Opens a regular file for buffered reading and returns it with its length. Anything else (a
/// FIFO, a device, a socket, a directory) is refused before it is opened; the file is opened
/// without blocking (a FIFO swapped in meanwhile cannot hold the reader) and checked again.
pub(crate) fn open(path: &Path) -> Result<(BufReader<File>, u64), VolumeError> {
    let (file, len) = regular::open_regular(path).map_err(|e| match e {
        regular::RegularError::NotRegular(kind) => format_err(
            path,
            format!("is {kind}, not a regular file: volumes are read from regular files only"),
        ),
        regular::RegularError::Io(e) => io_err(path, e),
        e => format_err(path, e.to_string()),
    })?;
    Ok((BufReader::new(file), len))
}

/// The data file a header names: relative to the header's folder, and inside it. An absolute
/// path or a `..` is refused (naming the header and the field), so a header cannot point a
/// reader at any other file.
pub(crate) fn data_file_path(header: &Path, field: &str, name: &str) -> Result<PathBuf, VolumeError> {
    use std::path::Component;
    let p = Path::new(name);
    let inside = p.components().all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    if !inside {
        return Err(format_err(
            header,
            format!(
                "{field}: '{name}' is not a file in the header's folder: a data file is named relative to \
                 the header, without '..' or an absolute path"
            ),
        ));
    }
    let folder = header.parent().unwrap_or(Path::new(""));
    let data = folder.join(p);
    // Links resolved first: a data file (or a folder on its way) that is a link must still lead
    // into the header's folder. One that does not exist yet is reported when it is opened.
    let real_folder =
        std::fs::canonicalize(if folder.as_os_str().is_empty() { Path::new(".") } else { folder });
    if let (Ok(real_folder), Ok(real)) = (real_folder, std::fs::canonicalize(&data)) {
        if !real.starts_with(&real_folder) {
            return Err(format_err(
                header,
                format!(
                    "{field}: '{name}' is a link to {}, outside the header's folder {}: a data file must lie \
                     in the header's folder, links resolved",
                    real.display(),
                    real_folder.display()
                ),
            ));
        }
    }
    Ok(data)
}

/// Makes the volume, named by the path as given.
pub(crate) fn make_volume(
    path: &Path,
    dims: [usize; 3],
    spacing: DVec3,
    origin: DVec3,
    data: Vec<f32>,
) -> Result<Volume, VolumeError> {
    Volume::new(path.display().to_string(), dims, spacing, origin, data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_format_comes_from_the_file_name_in_any_case() {
        let of = |n: &str| FileFormat::of(Path::new(n));
        assert_eq!(of("a/b/head.NRRD"), FileFormat::Nrrd);
        assert_eq!(of("head.nhdr"), FileFormat::Nrrd);
        assert_eq!(of("x.mha"), FileFormat::MetaImage);
        assert_eq!(of("x.MHD"), FileFormat::MetaImage);
        assert_eq!(of("brain.nii.gz"), FileFormat::Nifti);
        assert_eq!(of("brain.Nii"), FileFormat::Nifti);
        assert_eq!(of("brain.hdr"), FileFormat::Nifti);
        assert_eq!(of("engine.raw"), FileFormat::Raw);
        assert_eq!(of("nrrd"), FileFormat::Raw);
        assert_eq!(of("x.nii.gz.bak"), FileFormat::Raw);
        assert_eq!(of("ct/IM0001.DCM"), FileFormat::Dicom);
    }

    #[test]
    fn a_raw_spec_is_ignored_for_self_describing_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("tiny.nrrd");
        std::fs::write(&p, b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 1 1\nencoding: raw\n\n\x07\x09")
            .unwrap();
        let spec = RawSpec {
            dims: [9, 9, 9],
            voxel: VoxelType::F64,
            spacing: DVec3::splat(3.0),
            big_endian: true,
            header_bytes: 0,
        };
        let v = load(&p, Some(&spec)).unwrap();
        assert_eq!((v.dims(), v.spacing(), v.data()), ([2, 1, 1], DVec3::ONE, [7.0, 9.0].as_slice()));
    }

    #[test]
    fn only_regular_files_are_read_and_none_blocks() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe.nrrd");
        testutil::mkfifo(&fifo);
        let header = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 1 1\nencoding: raw\n";
        let nhdr = dir.path().join("v.nhdr");
        std::fs::write(&nhdr, format!("{header}data file: pipe.nrrd\n")).unwrap();
        let mha = dir.path().join("v.mhd");
        std::fs::write(
            &mha,
            "NDims = 3\nDimSize = 2 1 1\nElementType = MET_UCHAR\nElementDataFile = pipe.nrrd\n",
        )
        .unwrap();
        let sub = dir.path().join("sub.nrrd");
        std::fs::create_dir(&sub).unwrap();
        let spec = RawSpec {
            dims: [2, 1, 1],
            voxel: VoxelType::U8,
            spacing: DVec3::ONE,
            big_endian: false,
            header_bytes: 0,
        };
        // No writer ever opens the FIFO: a reader that opened it blocking would wait forever.
        let cases: [(&Path, Option<&RawSpec>, &str); 6] = [
            (&fifo, None, "a FIFO"),
            (&nhdr, None, "a FIFO"),
            (&mha, None, "a FIFO"),
            (&sub, None, "a directory"),
            (Path::new("/dev/zero"), Some(&spec), "a device"),
            (Path::new("/dev/null"), Some(&spec), "a device"),
        ];
        for (path, raw, kind) in cases {
            let m = load(path, raw).unwrap_err().to_string();
            assert!(
                m.contains(&format!("is {kind}")) && m.contains("not a regular file"),
                "{}: {m}",
                path.display()
            );
        }
    }

    #[test]
    fn the_limit_is_checked_from_the_header_before_inflating() {
        let dir = tempfile::tempdir().unwrap();
        // Claims 1024^3 voxels: 4 GiB as float32, over the default 2 GiB. Its data would be a
        // gzip bomb; a reader that inflated before checking would allocate gigabytes.
        let p = dir.path().join("bomb.nrrd");
        let header = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 1024 1024 1024\nencoding: gzip\n\n";
        std::fs::write(&p, [header.as_bytes(), &testutil::gzip(&[0u8; 4096])].concat()).unwrap();
        let m = load(&p, None).unwrap_err().to_string();
        assert!(m.starts_with(&p.display().to_string()), "{m}");
        assert!(m.contains("line 4: sizes: 1024x1024x1024 uint8 is 4294967296 bytes as float32"), "{m}");
        assert!(m.contains("over the limit of 2147483648 bytes (Isowall's default maximum)"), "{m}");
        // A tighter limit names where it comes from; a small volume within it reads.
        let tiny = dir.path().join("tiny.nrrd");
        let header = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: gzip\n\n";
        std::fs::write(&tiny, [header.as_bytes(), &testutil::gzip(&[1u8; 64])].concat()).unwrap();
        let limit = VolumeLimit::new(255, "the GPU's largest storage binding");
        let m = load_within(&tiny, None, &limit).unwrap_err().to_string();
        assert!(m.contains("256 bytes as float32, over the limit of 255 bytes (the GPU's"), "{m}");
        assert_eq!(load_within(&tiny, None, &VolumeLimit::new(256, "x")).unwrap().data().len(), 64);
        assert_eq!(limit.clone().min(VolumeLimit::default()), limit);
    }
}
