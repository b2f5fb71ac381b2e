//! Volume file readers. The format is chosen by the file name: `.nrrd`/`.nhdr` (NRRD), `.mhd`/`.mha`
//! (MetaImage), `.nii`/`.nii.gz`/`.hdr` (NIfTI-1 and NIfTI-2), a folder, `.dcm`/`.dicom`/`.ima` or a file with
//! DICOM's magic (a DICOM series, [`dicom`]); anything else is raw and needs a [`RawSpec`].
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

pub mod dicom;
pub mod dicom_write;
pub mod metaimage;
pub mod nifti;
pub mod nrrd;
mod plan;
pub mod raw;

use crate::{Volume, VolumeError};
use flate2::bufread::{MultiGzDecoder, ZlibDecoder};
use glam::DVec3;
pub(crate) use plan::FilePlan;
use std::fs::File;
use std::io::{self, BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

/// The largest volume Isowall reads: 2^30 voxels, 4 GiB as `f32`.
pub const MAX_VOXELS: u64 = 1 << 30;

/// The default [`VolumeLimit`]: 2 GiB of `f32` voxels (512 Mi voxels, e.g. 1024x1024x512).
pub const DEFAULT_MAX_BYTES: u64 = 2 << 30;

/// The most bytes a volume's voxels may take once read (as `f32`, 4 bytes a voxel), and where
/// that limit comes from (named in the error). Readers check it against the header's dims before
/// they allocate or inflate anything.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VolumeLimit {
    pub bytes: u64,
    /// E.g. "the GPU's largest storage binding" or "[volume] max_bytes".
    pub source: String,
}

impl Default for VolumeLimit {
    fn default() -> Self {
        VolumeLimit { bytes: DEFAULT_MAX_BYTES, source: "Isowall's default maximum".into() }
    }
}

impl VolumeLimit {
    pub fn new(bytes: u64, source: impl Into<String>) -> VolumeLimit {
        VolumeLimit { bytes, source: source.into() }
    }

    /// The tighter of two limits.
    pub fn min(self, other: VolumeLimit) -> VolumeLimit {
        if other.bytes < self.bytes {
            other
        } else {
            self
        }
    }

    /// Whether `voxels` voxels (of `what`, e.g. `1024x1024x1024 uint8`) fit.
    pub fn check(&self, voxels: u64, what: &str) -> Result<(), String> {
        let bytes = voxels.saturating_mul(4);
        if bytes > self.bytes {
            return Err(format!(
                "{what} is {bytes} bytes as float32, over the limit of {} bytes ({}): refused before reading \
                 its data",
                self.bytes, self.source
            ));
        }
        Ok(())
    }
}

/// The longest text header (NRRD, MetaImage) read before giving up on finding its end.
const HEADER_LIMIT: u64 = 1 << 20;

/// Voxel types found in files.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    F32,
    F64,
}

impl VoxelType {
    pub fn size(self) -> usize {
        match self {
            VoxelType::U8 | VoxelType::I8 => 1,
            VoxelType::U16 | VoxelType::I16 => 2,
            VoxelType::U32 | VoxelType::I32 | VoxelType::F32 => 4,
            VoxelType::F64 => 8,
        }
    }

    /// The canonical name, as `--type` takes it (`uint8` ... `float64`).
    pub fn name(self) -> &'static str {
        match self {
            VoxelType::U8 => "uint8",
            VoxelType::I8 => "int8",
            VoxelType::U16 => "uint16",
            VoxelType::I16 => "int16",
            VoxelType::U32 => "uint32",
            VoxelType::I32 => "int32",
            VoxelType::F32 => "float32",
            VoxelType::F64 => "float64",
        }
    }
}

impl std::str::FromStr for VoxelType {
    type Err = String;
    /// Names accepted by `--type`: uint8 int8 uint16 int16 uint32 int32 float32 float64 (and the
    /// short forms u8 i8 u16 i16 u32 i32 f32 f64).
    fn from_str(s: &str) -> Result<Self, String> {
        Ok(match s {
            "uint8" | "u8" | "uchar" => VoxelType::U8,
            "int8" | "i8" | "char" => VoxelType::I8,
            "uint16" | "u16" | "ushort" => VoxelType::U16,
            "int16" | "i16" | "short" => VoxelType::I16,
            "uint32" | "u32" | "uint" => VoxelType::U32,
            "int32" | "i32" | "int" => VoxelType::I32,
            "float32" | "f32" | "float" => VoxelType::F32,
            "float64" | "f64" | "double" => VoxelType::F64,
            _ => {
                return Err(format!(
                    "unknown voxel type '{s}' (uint8, int8, uint16, int16, uint32, int32, float32, float64)"
                ))
            }
        })
    }
}

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
}

impl FileFormat {
    /// The format a file name says (case-insensitive); a folder or a file with DICOM's magic is
    /// DICOM; anything else unknown is raw.
    fn of(path: &Path) -> FileFormat {
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
/// steps (read whole, then the step cut out, so the limit applies to the whole file), every
/// other file one (step 0).
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
    let (volume, steps) = match format {
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

/// The number of time steps of a volume file, from its header: `dim[4]` of a 4-D NIfTI, the 4th
/// size of a 4-D NRRD, 1 for every other file.
pub fn time_steps(path: &Path) -> Result<usize, VolumeError> {
    match FileFormat::of(path) {
        FileFormat::Nrrd => nrrd::time_steps(path),
        FileFormat::Nifti => nifti::time_steps(path),
        _ => Ok(1),
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
    let mut data = v.data;
    data.truncate(nx * ny * nz * (step + 1));
    data.drain(..nx * ny * nz * step);
    Volume::new(v.name, [nx, ny, nz], v.spacing, v.origin, data)
}

/// Where the voxels of a file are, for partial reads ([`crate::region`]): raw files and NRRD
/// (unless a `space directions` mirrors an axis). `None`: the format is read whole.
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
        FileFormat::MetaImage | FileFormat::Nifti => Ok(None),
        // Read slice by slice through `Series` (crate::region), not through a file plan.
        FileFormat::Dicom => Ok(None),
    }
}

// ---------------------------------------------------------------------------------------------
// Shared by the readers.

/// A [`VolumeError::Format`] for `path`.
pub(crate) fn format_err(path: &Path, what: impl Into<String>) -> VolumeError {
    VolumeError::Format { path: path.to_path_buf(), what: what.into() }
}

/// A [`VolumeError::Io`] for `path`.
pub(crate) fn io_err(path: &Path, source: io::Error) -> VolumeError {
    VolumeError::Io { path: path.to_path_buf(), source }
}

/// Opens a regular file for buffered reading and returns it with its length. Anything else (a
/// FIFO, a device, a socket, a directory) is refused before it is opened; the file is opened
/// without blocking (a FIFO swapped in meanwhile cannot hold the reader) and checked again.
pub(crate) fn open(path: &Path) -> Result<(BufReader<File>, u64), VolumeError> {
    use std::os::unix::fs::OpenOptionsExt;
    let not_regular = |t: std::fs::FileType| {
        use std::os::unix::fs::FileTypeExt;
        let kind = if t.is_fifo() {
            "a FIFO (named pipe)"
        } else if t.is_dir() {
            "a directory"
        } else if t.is_char_device() || t.is_block_device() {
            "a device"
        } else if t.is_socket() {
            "a socket"
        } else {
            "not a regular file"
        };
        format_err(path, format!("is {kind}, not a regular file: volumes are read from regular files only"))
    };
    let kind = std::fs::metadata(path).map_err(|e| io_err(path, e))?.file_type();
    if !kind.is_file() {
        return Err(not_regular(kind));
    }
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
        .map_err(|e| io_err(path, e))?;
    let meta = file.metadata().map_err(|e| io_err(path, e))?;
    if !meta.file_type().is_file() {
        return Err(not_regular(meta.file_type()));
    }
    Ok((BufReader::new(file), meta.len()))
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
    Ok(header.parent().unwrap_or(Path::new("")).join(p))
}

/// The files a volume's voxels are read from, for error messages: `header` is the file the user
/// named (and the volume's name), `data` the file holding the voxels (the same unless detached).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Files<'a> {
    pub header: &'a Path,
    pub data: &'a Path,
}

impl<'a> Files<'a> {
    pub fn single(path: &'a Path) -> Files<'a> {
        Files { header: path, data: path }
    }

    /// A format error about the data, on the header's path, naming the data file when detached.
    pub fn format(&self, what: impl Into<String>) -> VolumeError {
        let what = what.into();
        if self.header == self.data {
            format_err(self.header, what)
        } else {
            format_err(self.header, format!("data file {}: {what}", self.data.display()))
        }
    }

    /// An I/O error reading the data, on the data file's path.
    pub fn io(&self, source: io::Error) -> VolumeError {
        io_err(self.data, source)
    }

    /// An error from reading data decoded from `enc`: the decoder's complaints (kinds
    /// `InvalidInput`, `InvalidData`, `UnexpectedEof`) are format errors, the rest I/O errors.
    fn read_error(&self, enc: Encoding, e: io::Error) -> VolumeError {
        let decoder_complaint = matches!(
            e.kind(),
            io::ErrorKind::InvalidInput | io::ErrorKind::InvalidData | io::ErrorKind::UnexpectedEof
        );
        if enc != Encoding::Raw && decoder_complaint {
            self.format(format!("{} data is corrupt: {e}", enc.name()))
        } else {
            self.io(e)
        }
    }
}

/// How the voxels are laid out: dims (x fastest), type and byte order.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Layout {
    pub dims: [usize; 3],
    pub voxel: VoxelType,
    pub big_endian: bool,
}

impl Layout {
    /// The number of voxels; `Err` says why the dims are unusable (a zero, an overflow, or more
    /// than [`MAX_VOXELS`]). Readers call this before reading any data.
    pub fn voxel_count(&self) -> Result<usize, String> {
        let [nx, ny, nz] = self.dims;
        if self.dims.contains(&0) {
            return Err(format!("{nx}x{ny}x{nz}: every size must be at least 1"));
        }
        let count = self.dims.iter().try_fold(1u64, |acc, &n| acc.checked_mul(n as u64));
        match count {
            Some(c) if c <= MAX_VOXELS => {
                usize::try_from(c).map_err(|_| format!("{nx}x{ny}x{nz} does not fit in memory"))
            }
            Some(c) => Err(format!(
                "{nx}x{ny}x{nz} is {c} voxels, over Isowall's limit of {MAX_VOXELS} (4 GiB as float32)"
            )),
            None => Err(format!("{nx}x{ny}x{nz} voxels overflow a 64-bit count")),
        }
    }

    /// [`Layout::voxel_count`], also within `limit` (as `f32`): what readers check from a header.
    pub fn check_within(&self, limit: &VolumeLimit) -> Result<usize, String> {
        let count = self.voxel_count()?;
        limit.check(count as u64, &self.describe())?;
        Ok(count)
    }

    /// Bytes the voxels take in the file (valid once [`Layout::voxel_count`] succeeded).
    pub fn byte_len(&self) -> u64 {
        self.dims.iter().map(|&n| n as u64).product::<u64>() * self.voxel.size() as u64
    }

    /// E.g. `256x256x108 int16`, for messages.
    pub fn describe(&self) -> String {
        let [nx, ny, nz] = self.dims;
        format!("{nx}x{ny}x{nz} {}", self.voxel.name())
    }
}

/// How the voxel bytes are stored in a file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Encoding {
    Raw,
    /// gzip (RFC 1952); several members are read as one stream.
    Gzip,
    /// zlib (RFC 1950), or gzip when the data starts with gzip's magic (as MetaIO reads it).
    Zlib,
}

impl Encoding {
    fn name(self) -> &'static str {
        match self {
            Encoding::Raw => "raw",
            Encoding::Gzip => "gzip",
            Encoding::Zlib => "zlib",
        }
    }

    /// `r` wrapped in this encoding's decoder.
    pub fn decoder<'a, R: BufRead + 'a>(self, mut r: R) -> io::Result<Box<dyn Read + 'a>> {
        Ok(match self {
            Encoding::Raw => Box::new(r),
            Encoding::Gzip => Box::new(MultiGzDecoder::new(r)),
            Encoding::Zlib => {
                if r.fill_buf()?.starts_with(&[0x1f, 0x8b]) {
                    Box::new(MultiGzDecoder::new(r))
                } else {
                    Box::new(ZlibDecoder::new(r))
                }
            }
        })
    }
}

/// NIfTI's linear rescaling of stored values: `value * slope + inter`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Scale {
    pub slope: f64,
    pub inter: f64,
}

/// Where the voxels are in a file and how they are encoded.
#[derive(Clone, Copy, Debug)]
pub(crate) struct DataSpec {
    pub encoding: Encoding,
    /// Bytes of the file to skip (from the reader's position) before the (encoded) data; `None`:
    /// the voxels are the last bytes of the file (raw encoding only).
    pub file_skip: Option<u64>,
    /// Decoded bytes to skip before the voxels (compressed encodings only).
    pub decoded_skip: u64,
}

/// Reads the voxels of `layout` from `r`, which is at byte `pos` of the data file of `file_len`
/// bytes, as `spec` says. Raw data must fill the file exactly; compressed data must decode to
/// exactly the voxels' bytes.
pub(crate) fn read_data<R: BufRead>(
    files: Files,
    mut r: R,
    pos: u64,
    file_len: u64,
    spec: DataSpec,
    layout: &Layout,
    scale: Option<Scale>,
) -> Result<Vec<f32>, VolumeError> {
    layout.voxel_count().map_err(|e| files.format(e))?;
    match spec.encoding {
        Encoding::Raw => {
            let start = match spec.file_skip {
                Some(skip) => pos.saturating_add(skip),
                None => pos.max(file_len.saturating_sub(layout.byte_len())),
            };
            check_raw_size(files, file_len, start, layout)?;
            read_voxels(files, &mut r, Encoding::Raw, start - pos, layout, scale)
        }
        enc => {
            let Some(skip) = spec.file_skip else {
                return Err(files.format("data at the end of the file (skip -1) needs raw encoding"));
            };
            skip_bytes(files, &mut r, Encoding::Raw, skip)?;
            let mut dec = enc.decoder(r).map_err(|e| files.io(e))?;
            read_voxels(files, &mut *dec, enc, spec.decoded_skip, layout, scale)
        }
    }
}

/// Checks that the raw voxels starting at byte `start` fill a file of `file_len` bytes exactly.
pub(crate) fn check_raw_size(
    files: Files,
    file_len: u64,
    start: u64,
    layout: &Layout,
) -> Result<(), VolumeError> {
    let need = layout.byte_len();
    let desc = layout.describe();
    if start > file_len {
        return Err(files.format(format!(
            "data is truncated: the voxels would start at byte {start} but the file has {file_len} bytes"
        )));
    }
    let have = file_len - start;
    let from = if start > 0 { format!(" from byte {start} on") } else { String::new() };
    if have < need {
        Err(files.format(format!("data is truncated: {have} bytes{from}, {desc} needs {need}")))
    } else if have > need {
        Err(files.format(format!(
            "extra data: file has {} bytes more than {desc} needs ({need} bytes{from})",
            have - need
        )))
    } else {
        Ok(())
    }
}

/// Reads and drops `n` bytes of `r`.
pub(crate) fn skip_bytes(files: Files, r: &mut dyn Read, enc: Encoding, n: u64) -> Result<(), VolumeError> {
    let skipped = io::copy(&mut r.take(n), &mut io::sink()).map_err(|e| files.read_error(enc, e))?;
    if skipped < n {
        let decoded =
            if enc == Encoding::Raw { String::new() } else { format!(" of decoded {} data", enc.name()) };
        return Err(files.format(format!(
            "data is truncated: only {skipped} bytes{decoded}, fewer than the {n} to skip before the voxels"
        )));
    }
    Ok(())
}

/// Skips `n` text lines of `r` (a NRRD `line skip`); returns the bytes skipped.
pub(crate) fn skip_lines<R: BufRead>(files: Files, r: &mut R, n: u64) -> Result<u64, VolumeError> {
    let mut bytes = 0u64;
    for line in 0..n {
        loop {
            let buf = r.fill_buf().map_err(|e| files.io(e))?;
            if buf.is_empty() {
                return Err(
                    files.format(format!("data is truncated: the file ends in line {line} of {n} to skip"))
                );
            }
            match buf.iter().position(|&b| b == b'\n') {
                Some(i) => {
                    r.consume(i + 1);
                    bytes += i as u64 + 1;
                    break;
                }
                None => {
                    let len = buf.len();
                    r.consume(len);
                    bytes += len as u64;
                }
            }
        }
    }
    Ok(bytes)
}

/// Bytes converted per step: a multiple of every voxel size.
const CHUNK: usize = 1 << 20;

/// Reads the voxels of `layout` from `r` (decoded from `enc`; used for messages) after dropping
/// `skip` bytes, converting them to `f32` (through `scale` when given). The stream must then end:
/// fewer bytes are "truncated", more "extra data". Reads at most one byte past what the volume
/// needs; for compressed data the output grows only as data arrives.
pub(crate) fn read_voxels(
    files: Files,
    r: &mut dyn Read,
    enc: Encoding,
    skip: u64,
    layout: &Layout,
    scale: Option<Scale>,
) -> Result<Vec<f32>, VolumeError> {
    let count = layout.voxel_count().map_err(|e| files.format(e))?;
    skip_bytes(files, r, enc, skip)?;
    let size = layout.voxel.size();
    let need = layout.byte_len();
    let desc = layout.describe();
    // Raw data was checked against the file's length, so it is there: allocate it at once.
    let mut out = if enc == Encoding::Raw { Vec::with_capacity(count) } else { Vec::new() };
    let mut buf = vec![0u8; (CHUNK as u64).min(need) as usize];
    let mut got = 0u64;
    while got < need {
        let want = ((need - got) as usize).min(buf.len());
        let n = read_full(r, &mut buf[..want]).map_err(|e| files.read_error(enc, e))?;
        got += n as u64;
        let whole = n - n % size;
        reserve_up_to(&mut out, whole / size, count);
        decode_into(&buf[..whole], layout.voxel, layout.big_endian, scale, &mut out);
        if n < want {
            let what = match enc {
                Encoding::Raw => format!("data is truncated: {got} bytes, {desc} needs {need}"),
                _ => format!(
                    "data is truncated: the {} data decompresses to {got} bytes, {desc} needs {need}",
                    enc.name()
                ),
            };
            return Err(files.format(what));
        }
    }
    let mut probe = [0u8; 1];
    if read_full(r, &mut probe).map_err(|e| files.read_error(enc, e))? > 0 {
        let what = match enc {
            Encoding::Raw => {
                format!("extra data: the file holds more than the {need} bytes {desc} needs")
            }
            _ => format!(
                "extra data: the {} data decompresses to more than the {need} bytes {desc} needs",
                enc.name()
            ),
        };
        return Err(files.format(what));
    }
    Ok(out)
}

/// Reads until `buf` is full or the stream ends; returns the bytes read.
pub(crate) fn read_full(r: &mut dyn Read, buf: &mut [u8]) -> io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// Makes room for `more` values, growing geometrically but never past `cap` values.
fn reserve_up_to(out: &mut Vec<f32>, more: usize, cap: usize) {
    let need = out.len() + more;
    if need > out.capacity() {
        let target = out.capacity().saturating_mul(2).max(need).min(cap.max(need));
        out.reserve_exact(target - out.len());
    }
}

/// Converts whole voxels of `voxel` type in `bytes` to `f32` and appends them to `out`.
pub(crate) fn decode_into(
    bytes: &[u8],
    voxel: VoxelType,
    big_endian: bool,
    scale: Option<Scale>,
    out: &mut Vec<f32>,
) {
    macro_rules! decode {
        ($t:ty) => {{
            const N: usize = std::mem::size_of::<$t>();
            let value = |c: &[u8]| -> f64 {
                let mut a = [0u8; N];
                a.copy_from_slice(c);
                let v = if big_endian { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) };
                v as f64
            };
            let chunks = bytes.chunks_exact(N);
            match scale {
                None => out.extend(chunks.map(|c| value(c) as f32)),
                Some(s) => out.extend(chunks.map(|c| (value(c) * s.slope + s.inter) as f32)),
            }
        }};
    }
    match voxel {
        VoxelType::U8 => decode!(u8),
        VoxelType::I8 => decode!(i8),
        VoxelType::U16 => decode!(u16),
        VoxelType::I16 => decode!(i16),
        VoxelType::U32 => decode!(u32),
        VoxelType::I32 => decode!(i32),
        VoxelType::F32 => decode!(f32),
        VoxelType::F64 => decode!(f64),
    }
}

/// Reads a text header (NRRD, MetaImage) line by line, keeping count of the bytes read, so the
/// data's offset is known when the header ends, and refusing headers longer than 1 MiB.
pub(crate) struct HeaderLines<'a, R> {
    r: R,
    path: &'a Path,
    format: &'static str,
    /// Bytes read so far: where the next line (or the attached data) begins.
    pub offset: u64,
    /// The number of the last line read (1-based).
    pub line_no: usize,
}

impl<'a, R: BufRead> HeaderLines<'a, R> {
    pub fn new(r: R, path: &'a Path, format: &'static str) -> Self {
        HeaderLines { r, path, format, offset: 0, line_no: 0 }
    }

    /// The next line without its line ending (`\n` or `\r\n`), or `None` at the end of the file.
    pub fn next_line(&mut self) -> Result<Option<String>, VolumeError> {
        let left = HEADER_LIMIT.saturating_sub(self.offset);
        let mut buf = Vec::new();
        let n = (&mut self.r).take(left).read_until(b'\n', &mut buf).map_err(|e| io_err(self.path, e))?;
        if n == 0 && left > 0 {
            return Ok(None);
        }
        if !buf.ends_with(b"\n") && n as u64 == left {
            return Err(format_err(
                self.path,
                format!(
                    "the header does not end within its first {HEADER_LIMIT} bytes: is this a {} file?",
                    self.format
                ),
            ));
        }
        self.offset += n as u64;
        self.line_no += 1;
        if buf.ends_with(b"\n") {
            buf.pop();
        }
        if buf.ends_with(b"\r") {
            buf.pop();
        }
        Ok(Some(String::from_utf8_lossy(&buf).into_owned()))
    }

    /// The reader, positioned just after the last line read.
    pub fn into_inner(self) -> R {
        self.r
    }
}

/// Parses exactly `n` numbers separated by whitespace (or commas) from a header field.
pub(crate) fn numbers<T: std::str::FromStr>(
    field: &str,
    value: &str,
    n: usize,
    noun: &str,
) -> Result<Vec<T>, String> {
    let tokens: Vec<&str> =
        value.split(|c: char| c.is_whitespace() || c == ',').filter(|t| !t.is_empty()).collect();
    if tokens.len() != n {
        return Err(format!("{field}: expected {n} numbers, got {}", tokens.len()));
    }
    tokens.iter().map(|t| t.parse().map_err(|_| format!("{field}: '{t}' is not a {noun}"))).collect()
}

/// Three sizes, each at least 1.
pub(crate) fn dims3(field: &str, value: &str) -> Result<[usize; 3], String> {
    let v = numbers::<usize>(field, value, 3, "whole number")?;
    if v.contains(&0) {
        return Err(format!("{field}: every size must be at least 1, got {} {} {}", v[0], v[1], v[2]));
    }
    Ok([v[0], v[1], v[2]])
}

/// Three finite numbers.
pub(crate) fn vec3(field: &str, value: &str) -> Result<DVec3, String> {
    let v = numbers::<f64>(field, value, 3, "number")?;
    let v = DVec3::new(v[0], v[1], v[2]);
    if !v.is_finite() {
        return Err(format!("{field}: {value} is not three finite numbers"));
    }
    Ok(v)
}

/// Three finite, positive spacings.
pub(crate) fn spacing3(field: &str, value: &str) -> Result<DVec3, String> {
    let s = vec3(field, value)?;
    if s.min_element() <= 0.0 {
        return Err(format!("{field}: spacings must be positive, got {} {} {}", s.x, s.y, s.z));
    }
    Ok(s)
}

/// An axis-aligned grid made from per-axis steps in world space (a NRRD `space directions`, a
/// MetaImage `TransformMatrix` times the spacing).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct AxisSteps {
    /// `steps[a]`: the world step between neighbours along axis a; it lies along world axis a.
    steps: [DVec3; 3],
}

impl AxisSteps {
    /// Checks that axis a steps along world axis a (off-axis parts at most 1e-6 of the step, for
    /// rounding noise); a negative step is allowed (see [`AxisSteps::apply`]).
    pub fn new(field: &str, steps: [DVec3; 3]) -> Result<AxisSteps, String> {
        const AXES: [&str; 3] = ["x", "y", "z"];
        for (a, d) in steps.iter().enumerate() {
            let len = d.length();
            let off = (0..3).filter(|&b| b != a).map(|b| d[b].abs()).fold(0.0, f64::max);
            if !d.is_finite() || len == 0.0 || off > 1e-6 * len {
                return Err(format!(
                    "{field}: axis {a} steps by ({}, {}, {}), not along world {}; Isowall needs an \
                     axis-aligned grid (resample the volume)",
                    d.x, d.y, d.z, AXES[a]
                ));
            }
        }
        Ok(AxisSteps { steps })
    }

    /// Whether the z step is negative.
    pub fn mirrors_z(&self) -> bool {
        self.steps[2][2] < 0.0
    }

    /// Whether a step is negative (the data is mirrored along that axis when read).
    pub fn mirrors(&self) -> bool {
        (0..3).any(|a| self.steps[a][a] < 0.0)
    }

    /// The steps along the world axes (all positive).
    pub fn spacing(&self) -> DVec3 {
        DVec3::new(self.steps[0].x.abs(), self.steps[1].y.abs(), self.steps[2].z.abs())
    }

    /// Undoes negative steps: mirrors `data` along each such axis and moves `origin` (the first
    /// sample's world position) to the far end, so every sample keeps its world position.
    /// Returns the new origin.
    pub fn apply(&self, origin: DVec3, dims: [usize; 3], data: &mut [f32]) -> DVec3 {
        let mut origin = origin;
        for a in 0..3 {
            let step = self.steps[a][a];
            if step < 0.0 {
                origin[a] += (dims[a] - 1) as f64 * step;
                mirror(data, dims, a);
            }
        }
        origin
    }
}

/// Mirrors x-fastest `data` of `dims` along `axis`.
fn mirror(data: &mut [f32], dims: [usize; 3], axis: usize) {
    let [nx, ny, nz] = dims;
    // Runs of `run` values that swap as units, in blocks of `n` runs.
    let (run, n) = match axis {
        0 => (1, nx),
        1 => (nx, ny),
        _ => (nx * ny, nz),
    };
    for block in data.chunks_exact_mut(run * n) {
        for i in 0..n / 2 {
            let (lo, hi) = block.split_at_mut((n - 1 - i) * run);
            lo[i * run..(i + 1) * run].swap_with_slice(&mut hi[..run]);
        }
    }
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
pub(crate) mod testutil {
    //! Writers and checks shared by the readers' tests.

    use super::VoxelType;
    use crate::Volume;
    use glam::DVec3;
    use std::io::Write;
    use std::path::PathBuf;

    pub const ALL_TYPES: [VoxelType; 8] = [
        VoxelType::U8,
        VoxelType::I8,
        VoxelType::U16,
        VoxelType::I16,
        VoxelType::U32,
        VoxelType::I32,
        VoxelType::F32,
        VoxelType::F64,
    ];

    /// Values of `voxel` type worth a round trip: its extremes, zero, small values; all exact in
    /// `f32` except two `f64`s that test the rounding to `f32`.
    pub fn type_values(voxel: VoxelType) -> Vec<f64> {
        match voxel {
            VoxelType::U8 => vec![0.0, 1.0, 127.0, 128.0, 255.0, 42.0],
            VoxelType::I8 => vec![-128.0, -1.0, 0.0, 1.0, 127.0, -42.0],
            VoxelType::U16 => vec![0.0, 1.0, 255.0, 256.0, 65535.0, 1000.0],
            VoxelType::I16 => vec![-32768.0, -1.0, 0.0, 1.0, 32767.0, -1024.0, 2986.0],
            VoxelType::U32 => vec![0.0, 1.0, 65536.0, 16777216.0, 4294967040.0],
            VoxelType::I32 => vec![-2147483648.0, -1.0, 0.0, 1.0, 16777216.0, 2147483520.0],
            VoxelType::F32 => vec![-1.5, 0.0, 3.25, f64::from(1e-3f32), -1e30f32 as f64, f64::from(f32::MAX)],
            VoxelType::F64 => vec![-2.5, 0.0, 1e10, 0.1, -1e-300, 123456789.123],
        }
    }

    /// `n` values of `voxel` type, cycling through [`type_values`] in a scrambled order.
    pub fn values(voxel: VoxelType, n: usize) -> Vec<f64> {
        let t = type_values(voxel);
        (0..n).map(|i| t[(i * 7 + i / 3) % t.len()]).collect()
    }

    /// `values` stored as `voxel` in the given byte order, written out independently of the readers.
    pub fn encode(values: &[f64], voxel: VoxelType, big_endian: bool) -> Vec<u8> {
        let mut out = Vec::new();
        for &v in values {
            let mut b: Vec<u8> = match voxel {
                VoxelType::U8 => vec![v as u8],
                VoxelType::I8 => vec![v as i8 as u8],
                VoxelType::U16 => (v as u16).to_le_bytes().to_vec(),
                VoxelType::I16 => (v as i16).to_le_bytes().to_vec(),
                VoxelType::U32 => (v as u32).to_le_bytes().to_vec(),
                VoxelType::I32 => (v as i32).to_le_bytes().to_vec(),
                VoxelType::F32 => (v as f32).to_le_bytes().to_vec(),
                VoxelType::F64 => v.to_le_bytes().to_vec(),
            };
            if big_endian {
                b.reverse();
            }
            out.extend(b);
        }
        out
    }

    pub fn gzip(bytes: &[u8]) -> Vec<u8> {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(bytes).unwrap();
        e.finish().unwrap()
    }

    pub fn zlib(bytes: &[u8]) -> Vec<u8> {
        let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(bytes).unwrap();
        e.finish().unwrap()
    }

    /// Checks a volume against what was written: dims, spacing, origin and every voxel (as `f32`).
    pub fn check(v: &Volume, dims: [usize; 3], spacing: DVec3, origin: DVec3, values: &[f64]) {
        assert_eq!(v.dims(), dims, "{}", v.name);
        assert!((v.spacing() - spacing).abs().max_element() < 1e-12, "{}: spacing {}", v.name, v.spacing());
        assert!((v.origin() - origin).abs().max_element() < 1e-12, "{}: origin {}", v.name, v.origin());
        assert_eq!(v.data().len(), values.len());
        for (i, (&got, &want)) in v.data().iter().zip(values).enumerate() {
            assert_eq!(got, want as f32, "{}: voxel {i}", v.name);
        }
    }

    /// A file of the shared test data (`/work/shared`, seen from this crate): `None`, with a
    /// message, when absent; absent in CI (`CI=true`) is a failure.
    pub fn shared_file(path: &str) -> Option<PathBuf> {
        let p = PathBuf::from(path);
        if p.exists() {
            return Some(p);
        }
        assert!(std::env::var("CI").as_deref() != Ok("true"), "{} is missing in CI", p.display());
        eprintln!("skipped: {} is absent", p.display());
        None
    }
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

    /// A FIFO at `path` (by the `mkfifo` command: no unsafe code here).
    fn mkfifo(path: &Path) {
        let ok = std::process::Command::new("mkfifo").arg(path).status().unwrap().success();
        assert!(ok, "mkfifo {}", path.display());
    }

    #[test]
    fn only_regular_files_are_read_and_none_blocks() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe.nrrd");
        mkfifo(&fifo);
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

    #[test]
    fn mirroring_reverses_one_axis_only() {
        let data: Vec<f32> = (0..24).map(|v| v as f32).collect();
        let dims = [4, 3, 2];
        for axis in 0..3 {
            let mut m = data.clone();
            mirror(&mut m, dims, axis);
            for k in 0..2 {
                for j in 0..3 {
                    for i in 0..4 {
                        let mut src = [i, j, k];
                        src[axis] = dims[axis] - 1 - src[axis];
                        let at = |p: [usize; 3]| p[0] + 4 * (p[1] + 3 * p[2]);
                        assert_eq!(m[at([i, j, k])], data[at(src)], "axis {axis} ({i},{j},{k})");
                    }
                }
            }
        }
    }
}
