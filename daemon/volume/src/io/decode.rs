//! The data path shared by the readers: where the voxels are in a file (layout, encoding, skips),
//! reading exactly the bytes they take (no more than one past, however compressed), and
//! converting them to `f32`.

use super::{format_err, io_err, VolumeLimit, MAX_VOXELS};
use crate::VolumeError;
use flate2::bufread::{MultiGzDecoder, ZlibDecoder};
use std::io::{self, BufRead, Read};
use std::path::Path;

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
    pub fn read_error(&self, enc: Encoding, e: io::Error) -> VolumeError {
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
    pub(crate) fn name(self) -> &'static str {
        match self {
            Encoding::Raw => "raw",
            Encoding::Gzip => "gzip",
            Encoding::Zlib => "zlib",
        }
    }

    /// `r` wrapped in this encoding's decoder.
    pub fn decoder<'a, R: BufRead + Send + 'a>(self, mut r: R) -> io::Result<Box<dyn Read + Send + 'a>> {
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
pub(crate) fn read_data<R: BufRead + Send>(
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
