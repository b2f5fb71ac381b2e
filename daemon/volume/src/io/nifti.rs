//! NIfTI-1 and NIfTI-2 reader (<https://nifti.nimh.nih.gov/nifti-1/>,
//! <https://nifti.nimh.nih.gov/nifti-2/>): NIfTI-2 is the same with a 540-byte header of 64-bit
//! fields (magic `n+2`/`ni2`).
//!
//! Supported:
//! - single files (`.nii`, magic `n+1`), gzip-compressed whole (`.nii.gz`; recognised by the gzip
//!   magic, whatever the name says), and header/image pairs (`.hdr` + `.img`, magic `ni1`: open
//!   the `.hdr`);
//! - either byte order, told by `sizeof_hdr` = 348;
//! - `datatype` 2 uint8, 4 int16, 8 int32, 16 float32, 64 float64, 256 int8, 512 uint16,
//!   768 uint32;
//! - `dim[0]` = 3, or 4 to 7 when the dimensions past the 4th are 1: `dim[4]` time steps, stacked
//!   along z in the file ([`super::load_step`] reads one step's voxels alone);
//! - spacing `|pixdim[1..=3]|`; voxels from `vox_offset`, so header extensions are skipped;
//! - `scl_slope`/`scl_inter`, applied when the slope is finite and not 0 and the pair is not
//!   (1, 0) (a non-finite intercept counts as 0, as nibabel does);
//! - origin `qoffset_x/y/z` when `qform_code` > 0, else the sform's translation when
//!   `sform_code` > 0, else 0.
//!
//! - patient orientation from the same transform (qform first, as for the origin): the grid
//!   stays axis-aligned, index axes along world x, y, z, and each axis is named by the RAS+
//!   direction its rotated column leans towards most ([`crate::Orientation`]); a rotation of 45
//!   degrees or more off the patient's axes keeps none (with a warning). Non-finite quaternion or
//!   `srow_*` values of the transform in use are refused.
//!
//! Not resampled: a qform or sform rotation (warned about). Units (`xyzt_units`)
//! are not converted. Refused with an error: Analyze 7.5 headers (no NIfTI magic), other
//! datatypes (complex, RGB, 64-bit), dimensions past the 4th above 1, zero or non-finite spacing, a
//! `vox_offset` inside the header.

use super::{
    check_raw_size, format_err, io_err, make_volume, open, read_data, read_full, read_voxels, DataSpec,
    Encoding, Files, Layout, Scale, VolumeLimit, VoxelType, MAX_VOXELS,
};
use crate::{Orientation, PatientFrame, Volume, VolumeError};
use glam::DVec3;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

/// The size of a NIfTI-1 header.
const HEADER_LEN: usize = 348;
/// The size of a NIfTI-2 header.
const HEADER2_LEN: usize = 540;

/// Reads the NIfTI file (`.nii`, `.nii.gz`, or the `.hdr` of a pair) at `path` within `limit`
/// (all its time steps together): the volume (a 4-D file's time steps stacked along z) and the
/// number of time steps.
pub(crate) fn read(path: &Path, limit: &VolumeLimit) -> Result<(Volume, usize), VolumeError> {
    let (mut r, file_len) = open(path)?;
    let gzipped = r.fill_buf().map_err(|e| io_err(path, e))?.starts_with(&[0x1f, 0x8b]);
    let files = Files::single(path);
    if gzipped {
        // The whole file is compressed: the header, any extensions, then the voxels.
        let mut r = BufReader::new(flate2::bufread::MultiGzDecoder::new(r));
        let header = Header::read(path, &mut r, Encoding::Gzip, limit)?;
        if !header.single_file {
            return Err(format_err(
                path,
                "magic 'ni1'/'ni2' (a .hdr/.img pair) in a gzip-compressed file is not supported",
            ));
        }
        let skip = header.vox_offset - header.len as u64;
        let data = read_voxels(files, &mut r, Encoding::Gzip, skip, &header.layout, header.scale)?;
        return header.volume(path, data);
    }

    let header = Header::read(path, &mut r, Encoding::Raw, limit)?;
    let is_hdr = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("hdr"));
    let data =
        match (header.single_file, is_hdr) {
            (true, false) => {
                let spec = DataSpec {
                    encoding: Encoding::Raw,
                    file_skip: Some(header.vox_offset - header.len as u64),
                    decoded_skip: 0,
                };
                read_data(files, r, header.len as u64, file_len, spec, &header.layout, header.scale)?
            }
            (false, true) => {
                let img = image_path(path);
                let (r, len) = open(&img)?;
                let spec =
                    DataSpec { encoding: Encoding::Raw, file_skip: Some(header.vox_offset), decoded_skip: 0 };
                read_data(Files { header: path, data: &img }, r, 0, len, spec, &header.layout, header.scale)?
            }
            (true, true) => {
                return Err(format_err(path, "the magic says a single .nii file, but the name ends in .hdr"))
            }
            (false, false) => return Err(format_err(
                path,
                "the magic ('ni1'/'ni2') says the voxels are in a separate .img file: open the matching .hdr",
            )),
        };
    header.volume(path, data)
}

/// The NIfTI file at `path` as time steps read one at a time ([`super::plan::StepFile`]; a 3-D
/// file is one step), its whole voxels within `limit`.
pub(crate) fn step_file(path: &Path, limit: &VolumeLimit) -> Result<super::plan::StepFile, VolumeError> {
    let (mut r, file_len) = open(path)?;
    let gzipped = r.fill_buf().map_err(|e| io_err(path, e))?.starts_with(&[0x1f, 0x8b]);
    let is_hdr = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("hdr"));
    let plan =
        |header: &Header, data: PathBuf, start: u64, encoding: Encoding, decoded_skip: u64| super::FilePlan {
            header: path.to_path_buf(),
            data,
            layout: header.layout,
            start,
            encoding,
            decoded_skip,
            trailing: false,
        };
    let (header, plan) = if gzipped {
        // The header is inside the compressed stream: the voxels start `vox_offset` bytes into it.
        let header = Header::read(path, &mut flate2::bufread::MultiGzDecoder::new(r), Encoding::Gzip, limit)?;
        if !header.single_file {
            return Err(format_err(
                path,
                "magic 'ni1'/'ni2' (a .hdr/.img pair) in a gzip-compressed file is not supported",
            ));
        }
        let plan = plan(&header, path.to_path_buf(), 0, Encoding::Gzip, header.vox_offset);
        (header, plan)
    } else {
        let header = Header::read(path, &mut r, Encoding::Raw, limit)?;
        let (data, len) = match (header.single_file, is_hdr) {
            (true, false) => (path.to_path_buf(), file_len),
            (false, true) => {
                let img = image_path(path);
                let len = open(&img)?.1;
                (img, len)
            }
            (true, true) => {
                return Err(format_err(path, "the magic says a single .nii file, but the name ends in .hdr"))
            }
            (false, false) => return Err(format_err(
                path,
                "the magic ('ni1'/'ni2') says the voxels are in a separate .img file: open the matching .hdr",
            )),
        };
        check_raw_size(Files { header: path, data: &data }, len, header.vox_offset, &header.layout)?;
        let plan = plan(&header, data, header.vox_offset, Encoding::Raw, 0);
        (header, plan)
    };
    Ok(super::plan::StepFile::new(plan, header.time_steps, header.spacing, header.origin, header.scale, None))
}

/// The number of time steps of the NIfTI file at `path` (its header only; the reader's limit is
/// checked when a step is read).
pub(crate) fn time_steps(path: &Path) -> Result<usize, VolumeError> {
    let limit = &VolumeLimit::new(u64::MAX, "none while counting time steps");
    let (mut r, _) = open(path)?;
    let gzipped = r.fill_buf().map_err(|e| io_err(path, e))?.starts_with(&[0x1f, 0x8b]);
    let header = if gzipped {
        Header::read(path, &mut flate2::bufread::MultiGzDecoder::new(r), Encoding::Gzip, limit)?
    } else {
        Header::read(path, &mut r, Encoding::Raw, limit)?
    };
    Ok(header.time_steps)
}

/// The `.img` of a `.hdr`, its extension in the same case.
fn image_path(hdr: &Path) -> PathBuf {
    let upper = hdr.extension().is_some_and(|e| e == "HDR");
    hdr.with_extension(if upper { "IMG" } else { "img" })
}

/// What Isowall takes from a NIfTI-1 header.
#[derive(Debug)]
struct Header {
    layout: Layout,
    spacing: DVec3,
    origin: DVec3,
    /// Where the voxels begin (in the `.nii`, or in the `.img` of a pair).
    vox_offset: u64,
    scale: Option<Scale>,
    /// Magic `n+1`/`n+2` (one file) rather than `ni1`/`ni2` (a pair).
    single_file: bool,
    /// The header's length: 348 (NIfTI-1) or 540 (NIfTI-2).
    len: usize,
    /// `dim[4]` of a 4-D file (1 otherwise); the steps are stacked along z in `layout`.
    time_steps: usize,
    /// The patient directions of the grid axes, from the qform or sform.
    orientation: Option<Orientation>,
}

/// A header's fields as both versions hold them (NIfTI-2 widens them to 64 bits).
struct Raw {
    magic: Vec<u8>,
    dim: Vec<i64>,
    datatype: i16,
    bitpix: i16,
    pixdim: Vec<f64>,
    vox_offset: f64,
    slope: f64,
    inter: f64,
    qform_code: i32,
    sform_code: i32,
    quatern: [f64; 3],
    qoffset: [f64; 3],
    srow: [[f64; 4]; 3],
}

impl Header {
    /// Reads and checks the header (348 bytes NIfTI-1, 540 NIfTI-2) from `r` (data decoded from
    /// `enc`), and its dims against `limit`.
    fn read(
        path: &Path,
        r: &mut dyn Read,
        enc: Encoding,
        limit: &VolumeLimit,
    ) -> Result<Header, VolumeError> {
        let files = Files::single(path);
        let mut h = vec![0u8; HEADER_LEN];
        let n = read_full(r, &mut h).map_err(|e| files.read_error(enc, e))?;
        if n < 4 {
            return Err(
                files.format(format!("header is truncated: {n} bytes, a NIfTI-1 header has {HEADER_LEN}"))
            );
        }
        let err = |what: String| format_err(path, what);

        let sizeof_le = i32::from_le_bytes([h[0], h[1], h[2], h[3]]);
        let sizeof_be = i32::from_be_bytes([h[0], h[1], h[2], h[3]]);
        let (big, v2) = match (sizeof_le, sizeof_be) {
            (348, _) => (false, false),
            (_, 348) => (true, false),
            (540, _) => (false, true),
            (_, 540) => (true, true),
            _ => {
                return Err(err(format!(
                    "not a NIfTI file: sizeof_hdr is {sizeof_le} (or {sizeof_be} big-endian), not 348 (NIfTI-1) or 540 (NIfTI-2)"
                )))
            }
        };
        let len = if v2 { HEADER2_LEN } else { HEADER_LEN };
        if v2 && n == HEADER_LEN {
            h.resize(HEADER2_LEN, 0);
            let more = read_full(r, &mut h[HEADER_LEN..]).map_err(|e| files.read_error(enc, e))?;
            h.truncate(HEADER_LEN + more);
        }
        let got = if v2 && n == HEADER_LEN { h.len() } else { n };
        if got < len {
            let version = if v2 { "NIfTI-2" } else { "NIfTI-1" };
            return Err(
                files.format(format!("header is truncated: {got} bytes, a {version} header has {len}"))
            );
        }
        let bytes = |o: usize, n: usize| {
            let mut b = h[o..o + n].to_vec();
            if big {
                b.reverse();
            }
            b
        };
        let i16_at = |o: usize| i16::from_le_bytes(bytes(o, 2).try_into().unwrap());
        let i32_at = |o: usize| i32::from_le_bytes(bytes(o, 4).try_into().unwrap());
        let i64_at = |o: usize| i64::from_le_bytes(bytes(o, 8).try_into().unwrap());
        let f32_at = |o: usize| f64::from(f32::from_le_bytes(bytes(o, 4).try_into().unwrap()));
        let f64_at = |o: usize| f64::from_le_bytes(bytes(o, 8).try_into().unwrap());
        // The fields of both versions, by the specifications' offsets.
        let f = if v2 {
            Raw {
                magic: h[4..12].to_vec(),
                dim: (0..8).map(|i| i64_at(16 + 8 * i)).collect(),
                datatype: i16_at(12),
                bitpix: i16_at(14),
                pixdim: (0..8).map(|i| f64_at(104 + 8 * i)).collect(),
                vox_offset: i64_at(168) as f64,
                slope: f64_at(176),
                inter: f64_at(184),
                qform_code: i32_at(344),
                sform_code: i32_at(348),
                quatern: [f64_at(352), f64_at(360), f64_at(368)],
                qoffset: [f64_at(376), f64_at(384), f64_at(392)],
                srow: [0, 1, 2].map(|r| [0, 1, 2, 3].map(|c| f64_at(400 + 32 * r + 8 * c))),
            }
        } else {
            Raw {
                magic: h[344..348].to_vec(),
                dim: (0..8).map(|i| i64::from(i16_at(40 + 2 * i))).collect(),
                datatype: i16_at(70),
                bitpix: i16_at(72),
                pixdim: (0..8).map(|i| f32_at(76 + 4 * i)).collect(),
                vox_offset: f32_at(108),
                slope: f32_at(112),
                inter: f32_at(116),
                qform_code: i32::from(i16_at(252)),
                sform_code: i32::from(i16_at(254)),
                quatern: [f32_at(256), f32_at(260), f32_at(264)],
                qoffset: [f32_at(268), f32_at(272), f32_at(276)],
                srow: [0, 1, 2].map(|r| [0, 1, 2, 3].map(|c| f32_at(280 + 16 * r + 4 * c))),
            }
        };

        let single_file = match (v2, f.magic.as_slice()) {
            (false, b"n+1\0") | (true, b"n+2\0\r\n\x1a\n") => true,
            (false, b"ni1\0") | (true, b"ni2\0\r\n\x1a\n") => false,
            (_, m) => {
                let want = if v2 {
                    "\"n+2\" (or \"ni2\" for a .hdr/.img pair)"
                } else {
                    "\"n+1\" (or \"ni1\" for a .hdr/.img pair)"
                };
                return Err(err(format!(
                    "magic is {:?}, not {want}; Analyze 7.5 files are not supported",
                    String::from_utf8_lossy(m)
                )));
            }
        };

        let dim = &f.dim;
        let rank = dim[0];
        if !(3..=7).contains(&rank) || (5..=rank as usize).any(|i| dim[i] != 1) {
            let shown: Vec<String> =
                dim.iter().take((rank.clamp(0, 7) + 1) as usize).map(|d| d.to_string()).collect();
            return Err(err(format!(
                "dim is [{}]; Isowall reads 3-dimensional volumes and 4-dimensional series of them \
                 (dim[0] = 3 or 4, or more with the extra sizes 1)",
                shown.join(", ")
            )));
        }
        if dim[1..4].iter().any(|&d| d < 1) || (rank >= 4 && dim[4] < 1) {
            return Err(err(format!(
                "dim[1..4] = {} {} {} {}: every size must be at least 1",
                dim[1],
                dim[2],
                dim[3],
                if rank >= 4 { dim[4] } else { 1 }
            )));
        }
        let too_big = |d: i64| usize::try_from(d).ok().filter(|&d| d as u64 <= MAX_VOXELS);
        let (Some(nx), Some(ny), Some(nz), Some(nt)) =
            (too_big(dim[1]), too_big(dim[2]), too_big(dim[3]), too_big(if rank >= 4 { dim[4] } else { 1 }))
        else {
            return Err(err(format!(
                "dim: {} {} {} {} is over Isowall's limit of {MAX_VOXELS} voxels",
                dim[1], dim[2], dim[3], dim[4]
            )));
        };
        let time_steps = nt;
        // Time steps are stacked along z: the file's voxels are one volume of nz * nt slices.
        let dims = [nx, ny, nz.saturating_mul(nt)];

        let datatype = f.datatype;
        let voxel = match datatype {
            2 => VoxelType::U8,
            4 => VoxelType::I16,
            8 => VoxelType::I32,
            16 => VoxelType::F32,
            64 => VoxelType::F64,
            256 => VoxelType::I8,
            512 => VoxelType::U16,
            768 => VoxelType::U32,
            d => {
                let name = match d {
                    1 => " (binary)",
                    32 => " (complex64)",
                    128 => " (rgb24)",
                    1024 => " (int64)",
                    1280 => " (uint64)",
                    1536 => " (float128)",
                    1792 => " (complex128)",
                    2048 => " (complex256)",
                    2304 => " (rgba32)",
                    _ => "",
                };
                return Err(err(format!(
                    "datatype {d}{name} is not supported (2 uint8, 4 int16, 8 int32, 16 float32, 64 float64, \
                     256 int8, 512 uint16, 768 uint32 are)"
                )));
            }
        };
        let bitpix = f.bitpix;
        if i64::from(bitpix) != 8 * voxel.size() as i64 {
            tracing::warn!(
                "{}: bitpix is {bitpix} but datatype {datatype} has {} bits; going by datatype",
                path.display(),
                8 * voxel.size()
            );
        }
        let layout = Layout { dims, voxel, big_endian: big };
        layout.check_within(limit).map_err(|e| err(format!("dim (all {nt} time steps): {e}")))?;

        let mut spacing = DVec3::ZERO;
        for a in 0..3 {
            let p = f.pixdim[a + 1];
            if !(p.is_finite() && p != 0.0) {
                return Err(err(format!("pixdim[{}] is {p}: voxel spacing must be finite and not 0", a + 1)));
            }
            spacing[a] = p.abs();
        }

        let vox_offset = f.vox_offset;
        let min_offset = if single_file { len as f64 } else { 0.0 };
        if !(vox_offset.is_finite() && vox_offset >= min_offset && vox_offset.fract() == 0.0) {
            return Err(err(format!(
                "vox_offset is {vox_offset}: it must be a whole number of bytes, at least {min_offset}"
            )));
        }

        let (slope, inter) = (f.slope, f.inter);
        let inter = if inter.is_finite() { inter } else { 0.0 };
        let scale = (slope.is_finite() && slope != 0.0 && !(slope == 1.0 && inter == 0.0))
            .then_some(Scale { slope, inter });

        let (qform_code, sform_code) = (f.qform_code, f.sform_code);
        // The grid stays axis-aligned (index axes along world x, y, z); the rotation names the
        // axes' patient directions ([`Orientation`], NIfTI's world is RAS+).
        let (origin, columns) = if qform_code > 0 {
            let columns = qform_columns(f.quatern, f.pixdim[0]).map_err(err)?;
            (DVec3::from_array(f.qoffset), Some(columns))
        } else if sform_code > 0 {
            let [x, y, z] = f.srow;
            for (name, row) in [("srow_x", x), ("srow_y", y), ("srow_z", z)] {
                if row.iter().any(|v| !v.is_finite()) {
                    return Err(err(format!("{name} {row:?} is not finite (sform_code {sform_code})")));
                }
            }
            let columns = [0, 1, 2].map(|c| DVec3::new(x[c], y[c], z[c]));
            (DVec3::new(x[3], y[3], z[3]), Some(columns))
        } else {
            (DVec3::ZERO, None)
        };
        let orientation = columns.and_then(|columns| {
            let o = Orientation::from_directions(columns, PatientFrame::Ras);
            let axis_aligned = columns.iter().enumerate().all(|(a, c)| {
                (0..3).filter(|&b| b != a).all(|b| c[b].abs() <= 1e-6 * c.length()) && c[a] > 0.0
            });
            if o.is_none() {
                tracing::warn!(
                    "{}: the {} turns the grid's axes 45 degrees or more off the patient's: no orientation is \
                     kept (views are named by the world axes)",
                    path.display(),
                    if qform_code > 0 { "qform" } else { "sform" }
                );
            } else if !axis_aligned {
                tracing::warn!(
                    "{}: the {} rotates or flips the grid; Isowall keeps the grid axis-aligned and names its \
                     axes {} (the nearest patient directions)",
                    path.display(),
                    if qform_code > 0 { "qform" } else { "sform" },
                    o.map(|o| o.code()).unwrap_or_default()
                );
            }
            o
        });
        if !origin.is_finite() {
            return Err(err(format!("the origin ({}, {}, {}) is not finite", origin.x, origin.y, origin.z)));
        }

        Ok(Header {
            layout,
            spacing,
            origin,
            orientation,
            vox_offset: vox_offset as u64,
            scale,
            single_file,
            len,
            time_steps,
        })
    }

    fn volume(&self, path: &Path, data: Vec<f32>) -> Result<(Volume, usize), VolumeError> {
        let volume = make_volume(path, self.layout.dims, self.spacing, self.origin, data)?
            .with_orientation(self.orientation);
        Ok((volume, self.time_steps))
    }
}

/// The qform's rotation as the world directions of the three grid axes (unit columns): the
/// quaternion (b, c, d) with a = sqrt(1 - b^2 - c^2 - d^2), and the third column times `qfac`
/// (`pixdim[0]`, -1 where negative, else 1). As the NIfTI reference does, a quaternion whose
/// b^2 + c^2 + d^2 reaches 1 is normalised with a = 0.
fn qform_columns(quatern: [f64; 3], qfac: f64) -> Result<[DVec3; 3], String> {
    let [mut b, mut c, mut d] = quatern;
    if !(b.is_finite() && c.is_finite() && d.is_finite()) {
        return Err(format!("quatern_b/c/d ({b}, {c}, {d}) are not finite (qform_code > 0)"));
    }
    let sum = b * b + c * c + d * d;
    let a = if 1.0 - sum < 1e-7 {
        let n = sum.sqrt();
        (b, c, d) = (b / n, c / n, d / n);
        0.0
    } else {
        (1.0 - sum).sqrt()
    };
    let flip = if qfac < 0.0 { -1.0 } else { 1.0 };
    Ok([
        DVec3::new(a * a + b * b - c * c - d * d, 2.0 * (b * c + a * d), 2.0 * (b * d - a * c)),
        DVec3::new(2.0 * (b * c - a * d), a * a + c * c - b * b - d * d, 2.0 * (c * d + a * b)),
        flip * DVec3::new(2.0 * (b * d + a * c), 2.0 * (c * d - a * b), a * a + d * d - c * c - b * b),
    ])
}

#[cfg(test)]
mod tests {
    use super::super::load;
    use super::super::testutil::{check, encode, gzip, values, ALL_TYPES};
    use super::*;
    use std::fs;

    const DIMS: [usize; 3] = [3, 2, 4];

    fn datatype(voxel: VoxelType) -> i16 {
        match voxel {
            VoxelType::U8 => 2,
            VoxelType::I16 => 4,
            VoxelType::I32 => 8,
            VoxelType::F32 => 16,
            VoxelType::F64 => 64,
            VoxelType::I8 => 256,
            VoxelType::U16 => 512,
            VoxelType::U32 => 768,
        }
    }

    /// The fields a test sets; the rest of the header is zero.
    #[derive(Clone)]
    struct Fields {
        big: bool,
        dim: [i16; 8],
        datatype: i16,
        bitpix: i16,
        pixdim: [f32; 8],
        vox_offset: f32,
        slope: f32,
        inter: f32,
        qform_code: i16,
        sform_code: i16,
        quatern: [f32; 3],
        qoffset: [f32; 3],
        srow: [[f32; 4]; 3],
        magic: &'static [u8; 4],
    }

    fn fields(voxel: VoxelType, big: bool) -> Fields {
        Fields {
            big,
            dim: [3, 3, 2, 4, 1, 1, 1, 1],
            datatype: datatype(voxel),
            bitpix: 8 * voxel.size() as i16,
            pixdim: [1.0, 0.5, 2.0, -1.25, 1.0, 0.0, 0.0, 0.0],
            vox_offset: 352.0,
            slope: 0.0,
            inter: 0.0,
            qform_code: 0,
            sform_code: 0,
            quatern: [0.0; 3],
            qoffset: [0.0; 3],
            srow: [[0.0; 4]; 3],
            magic: b"n+1\0",
        }
    }

    /// The 348-byte header, laid out by the NIfTI-1 specification's offsets.
    fn header(f: &Fields) -> Vec<u8> {
        let mut h = vec![0u8; 348];
        let mut put = |o: usize, b: &[u8]| {
            let mut b = b.to_vec();
            if f.big {
                b.reverse();
            }
            h[o..o + b.len()].copy_from_slice(&b);
        };
        put(0, &348i32.to_le_bytes());
        for (i, d) in f.dim.iter().enumerate() {
            put(40 + 2 * i, &d.to_le_bytes());
        }
        put(70, &f.datatype.to_le_bytes());
        put(72, &f.bitpix.to_le_bytes());
        for (i, p) in f.pixdim.iter().enumerate() {
            put(76 + 4 * i, &p.to_le_bytes());
        }
        put(108, &f.vox_offset.to_le_bytes());
        put(112, &f.slope.to_le_bytes());
        put(116, &f.inter.to_le_bytes());
        put(252, &f.qform_code.to_le_bytes());
        put(254, &f.sform_code.to_le_bytes());
        for (i, q) in f.quatern.iter().enumerate() {
            put(256 + 4 * i, &q.to_le_bytes());
        }
        for (i, q) in f.qoffset.iter().enumerate() {
            put(268 + 4 * i, &q.to_le_bytes());
        }
        for (r, row) in f.srow.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                put(280 + 16 * r + 4 * c, &v.to_le_bytes());
            }
        }
        h[344..348].copy_from_slice(f.magic);
        h
    }

    /// A .nii: the header, zeros up to `vox_offset` (the extension flag "none" and any padding), voxels.
    fn nii(f: &Fields, data: &[u8]) -> Vec<u8> {
        let mut b = header(f);
        if f.vox_offset as usize > b.len() {
            b.resize(f.vox_offset as usize, 0);
        }
        b.extend_from_slice(data);
        b
    }

    const SPACING: DVec3 = DVec3::new(0.5, 2.0, 1.25);

    #[test]
    fn single_gzip_and_pair_files_of_every_type_read_back() {
        let dir = tempfile::tempdir().unwrap();
        for voxel in ALL_TYPES {
            for big in [false, true] {
                let vals = values(voxel, 24);
                let raw = encode(&vals, voxel, big);
                let f = fields(voxel, big);
                let stem = format!("{}-{big}", voxel.name());
                let p = dir.path().join(format!("{stem}.nii"));
                fs::write(&p, nii(&f, &raw)).unwrap();
                check(&load(&p, None).unwrap(), DIMS, SPACING, DVec3::ZERO, &vals);
                let p = dir.path().join(format!("{stem}.nii.gz"));
                fs::write(&p, gzip(&nii(&f, &raw))).unwrap();
                check(&load(&p, None).unwrap(), DIMS, SPACING, DVec3::ZERO, &vals);

                let pair = Fields { vox_offset: 0.0, magic: b"ni1\0", ..f.clone() };
                let h = dir.path().join(format!("{stem}.hdr"));
                fs::write(&h, header(&pair)).unwrap();
                fs::write(dir.path().join(format!("{stem}.img")), &raw).unwrap();
                check(&load(&h, None).unwrap(), DIMS, SPACING, DVec3::ZERO, &vals);
            }
        }
    }

    #[test]
    fn scaling_origin_extensions_and_a_single_time_point() {
        let dir = tempfile::tempdir().unwrap();
        let vals = values(VoxelType::I16, 24);
        let raw = encode(&vals, VoxelType::I16, false);
        let p = dir.path().join("s.nii");
        let base = fields(VoxelType::I16, false);

        let f = Fields { slope: 0.5, inter: -10.0, ..base.clone() };
        fs::write(&p, nii(&f, &raw)).unwrap();
        let scaled: Vec<f64> = vals.iter().map(|v| v * 0.5 - 10.0).collect();
        check(&load(&p, None).unwrap(), DIMS, SPACING, DVec3::ZERO, &scaled);

        // qform origin; a 4-D file with one time point; 48 bytes of extensions before the voxels.
        let f = Fields {
            dim: [4, 3, 2, 4, 1, 1, 1, 1],
            qform_code: 1,
            qoffset: [-90.0, 126.0, -72.5],
            vox_offset: 400.0,
            ..base.clone()
        };
        fs::write(&p, nii(&f, &raw)).unwrap();
        check(&load(&p, None).unwrap(), DIMS, SPACING, DVec3::new(-90.0, 126.0, -72.5), &vals);

        // sform origin when there is no qform.
        let f = Fields {
            sform_code: 2,
            srow: [[0.5, 0.0, 0.0, 1.0], [0.0, 2.0, 0.0, 2.0], [0.0, 0.0, 1.25, 3.0]],
            ..base
        };
        fs::write(&p, nii(&f, &raw)).unwrap();
        check(&load(&p, None).unwrap(), DIMS, SPACING, DVec3::new(1.0, 2.0, 3.0), &vals);
    }

    #[test]
    fn qform_and_sform_name_the_patient_directions_of_the_axes() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("o.nii");
        let vals = values(VoxelType::U8, 24);
        let raw = encode(&vals, VoxelType::U8, false);
        let base = fields(VoxelType::U8, false);
        let code = |f: &Fields| {
            fs::write(&p, nii(f, &raw)).unwrap();
            load(&p, None).unwrap().orientation().map(|o| o.code())
        };
        let h = std::f32::consts::FRAC_1_SQRT_2;
        for (quatern, qfac, want) in [
            ([0.0, 0.0, 0.0], 1.0, "RAS"),
            // qfac -1 flips the third axis.
            ([0.0, 0.0, 0.0], -1.0, "RAI"),
            // 180 degrees about z: x left, y posterior (a = 0, b^2 + c^2 + d^2 = 1).
            ([0.0, 0.0, 1.0], 1.0, "LPS"),
            // 90 degrees about x: y superior, z posterior (a coronal grid).
            ([h, 0.0, 0.0], 1.0, "RSP"),
        ] {
            let mut pixdim = base.pixdim;
            pixdim[0] = qfac;
            let f = Fields { qform_code: 1, quatern, pixdim, ..base.clone() };
            assert_eq!(code(&f).as_deref(), Some(want), "quatern {quatern:?} qfac {qfac}");
        }
        // The sform when there is no qform: columns x anterior, y left, z inferior.
        let srow = [[0.0, -2.0, 0.0, 1.0], [0.5, 0.0, 0.0, 2.0], [0.0, 0.0, -1.25, 3.0]];
        assert_eq!(code(&Fields { sform_code: 1, srow, ..base.clone() }).as_deref(), Some("ALI"));
        // 45 degrees about z: no nearest patient axis, no orientation; neither code: none.
        let f = Fields {
            qform_code: 1,
            quatern: [0.0, 0.0, (0.125f32 * std::f32::consts::PI).sin()],
            ..base.clone()
        };
        assert_eq!(code(&f), None);
        assert_eq!(code(&base), None);
        // Hostile values of the transform in use are refused, naming the field.
        let f = Fields { qform_code: 1, quatern: [f32::NAN, 0.0, 0.0], ..base.clone() };
        let m = error_of(dir.path(), "q.nii", &nii(&f, &raw)).to_string();
        assert!(m.contains("quatern_b/c/d") && m.contains("not finite"), "{m}");
        let mut srow = srow;
        srow[1][1] = f32::INFINITY;
        let m =
            error_of(dir.path(), "s.nii", &nii(&Fields { sform_code: 1, srow, ..base }, &raw)).to_string();
        assert!(m.contains("srow_y") && m.contains("not finite"), "{m}");
    }

    fn error_of(dir: &Path, name: &str, bytes: &[u8]) -> VolumeError {
        let p = dir.join(name);
        fs::write(&p, bytes).unwrap();
        let e = load(&p, None).unwrap_err();
        assert!(e.to_string().starts_with(&p.display().to_string()), "{e}");
        e
    }

    #[test]
    fn bad_headers_and_data_are_refused_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let raw = encode(&values(VoxelType::U8, 24), VoxelType::U8, false);
        let base = fields(VoxelType::U8, false);
        let m = |f: Fields| error_of(d, "e.nii", &nii(&f, &raw)).to_string();

        let s = m(Fields { dim: [5, 3, 2, 4, 2, 2, 1, 1], ..base.clone() });
        assert!(s.contains("dim is [5, 3, 2, 4, 2, 2]"), "{s}");
        let s = m(Fields { dim: [2, 3, 8, 1, 1, 1, 1, 1], ..base.clone() });
        assert!(s.contains("3-dimensional"), "{s}");
        let s = m(Fields { dim: [3, 3, 0, 4, 1, 1, 1, 1], ..base.clone() });
        assert!(s.contains("at least 1"), "{s}");
        let s = m(Fields { datatype: 128, ..base.clone() });
        assert!(s.contains("datatype 128 (rgb24) is not supported"), "{s}");
        let s = m(Fields { pixdim: [1.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0], ..base.clone() });
        assert!(s.contains("pixdim[2] is 0"), "{s}");
        let s = m(Fields { vox_offset: 100.0, ..base.clone() });
        assert!(s.contains("vox_offset is 100"), "{s}");
        let s = m(Fields { magic: b"abcd", ..base.clone() });
        assert!(s.contains("magic"), "{s}");
        let s = m(Fields { magic: b"ni1\0", ..base.clone() });
        assert!(s.contains("open the matching .hdr"), "{s}");
        let mut bytes = nii(&base, &raw);
        bytes[0..4].copy_from_slice(&540i32.to_le_bytes());
        let s = error_of(d, "e.nii", &bytes).to_string();
        assert!(s.contains("header is truncated: 376 bytes, a NIfTI-2 header has 540"), "{s}");
        bytes[0..4].copy_from_slice(&1234i32.to_le_bytes());
        let s = error_of(d, "e.nii", &bytes).to_string();
        assert!(s.contains("sizeof_hdr is 1234"), "{s}");
        let s = error_of(d, "e.nii", &header(&base)[..200]).to_string();
        assert!(s.contains("header is truncated: 200 bytes"), "{s}");

        let s = error_of(d, "e.nii", &nii(&base, &raw[..20])).to_string();
        assert!(s.contains("data is truncated: 20 bytes from byte 352 on, 3x2x4 uint8 needs 24"), "{s}");
        let s = error_of(d, "e.nii", &nii(&base, &[raw.as_slice(), &[0; 3]].concat())).to_string();
        assert!(s.contains("extra data: file has 3 bytes more"), "{s}");
        let s = error_of(d, "e.nii.gz", &gzip(&nii(&base, &raw[..20]))).to_string();
        assert!(s.contains("decompresses to 20 bytes"), "{s}");
        let s = error_of(d, "e.nii.gz", &gzip(&nii(&base, &[raw.as_slice(), &[0; 3]].concat()))).to_string();
        assert!(s.contains("extra data"), "{s}");
        let mut garbage = gzip(&nii(&base, &raw));
        // A valid gzip header, then a deflate block of the reserved type 3.
        garbage[10..].fill(0xFF);
        let s = error_of(d, "e.nii.gz", &garbage).to_string();
        assert!(s.contains("gzip data is corrupt"), "{s}");
        let s = error_of(d, "e.nii.gz", &gzip(&header(&base)[..100])).to_string();
        assert!(s.contains("header is truncated: 100 bytes"), "{s}");
        let s = error_of(d, "e.nii.gz", b"not a nifti at all").to_string();
        assert!(s.contains("truncated") || s.contains("sizeof_hdr"), "{s}");
    }

    /// A NIfTI-2 header (540 bytes) for `f`, by the NIfTI-2 specification's offsets.
    fn header2(f: &Fields) -> Vec<u8> {
        let mut h = vec![0u8; 540];
        let mut put = |o: usize, b: &[u8]| {
            let mut b = b.to_vec();
            if f.big {
                b.reverse();
            }
            h[o..o + b.len()].copy_from_slice(&b);
        };
        put(0, &540i32.to_le_bytes());
        put(12, &f.datatype.to_le_bytes());
        put(14, &f.bitpix.to_le_bytes());
        for (i, d) in f.dim.iter().enumerate() {
            put(16 + 8 * i, &i64::from(*d).to_le_bytes());
        }
        for (i, p) in f.pixdim.iter().enumerate() {
            put(104 + 8 * i, &f64::from(*p).to_le_bytes());
        }
        put(168, &(f.vox_offset as i64).to_le_bytes());
        put(176, &f64::from(f.slope).to_le_bytes());
        put(184, &f64::from(f.inter).to_le_bytes());
        put(344, &i32::from(f.qform_code).to_le_bytes());
        put(348, &i32::from(f.sform_code).to_le_bytes());
        for (i, q) in f.qoffset.iter().enumerate() {
            put(376 + 8 * i, &f64::from(*q).to_le_bytes());
        }
        h[4..12].copy_from_slice(b"n+2\0\r\n\x1a\n");
        h
    }

    #[test]
    fn nifti2_and_4d_files_read_as_time_steps() {
        let dir = tempfile::tempdir().unwrap();
        for big in [false, true] {
            let vals = values(VoxelType::I16, 48);
            let raw = encode(&vals, VoxelType::I16, big);
            let f = Fields {
                dim: [4, 3, 2, 4, 2, 1, 1, 1],
                vox_offset: 544.0,
                qform_code: 1,
                qoffset: [1.0, 2.0, 3.0],
                slope: 2.0,
                inter: 1.0,
                ..fields(VoxelType::I16, big)
            };
            let mut bytes = header2(&f);
            bytes.resize(544, 0);
            bytes.extend_from_slice(&raw);
            let scaled: Vec<f64> = vals.iter().map(|v| v * 2.0 + 1.0).collect();
            for name in ["four.nii", "four.nii.gz"] {
                let p = dir.path().join(name);
                fs::write(&p, if name.ends_with(".gz") { gzip(&bytes) } else { bytes.clone() }).unwrap();
                assert_eq!(super::super::time_steps(&p).unwrap(), 2);
                let origin = DVec3::new(1.0, 2.0, 3.0);
                check(&load(&p, None).unwrap(), DIMS, SPACING, origin, &scaled[..24]);
                check(&super::super::load_step(&p, None, 1).unwrap(), DIMS, SPACING, origin, &scaled[24..]);
                let e = super::super::load_step(&p, None, 2).unwrap_err().to_string();
                assert!(e.contains("has no time step 2: it holds 2 (0 to 1)"), "{e}");
            }
            // NIfTI-1 4-D too; a file one step short is truncated.
            let p = dir.path().join("four1.nii");
            let f1 = Fields { vox_offset: 352.0, ..f.clone() };
            fs::write(&p, nii(&f1, &raw)).unwrap();
            check(
                &super::super::load_step(&p, None, 1).unwrap(),
                DIMS,
                SPACING,
                DVec3::new(1.0, 2.0, 3.0),
                &scaled[24..],
            );
            let s = error_of(dir.path(), "short.nii", &nii(&f1, &raw[..raw.len() - 2 * 24])).to_string();
            assert!(s.contains("data is truncated"), "{s}");
        }
    }

    #[test]
    fn nibabels_nifti2_example_reads_both_steps() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/nifti/example_nifti2.nii.gz");
        assert_eq!(super::super::time_steps(&p).unwrap(), 2);
        let s0 = load(&p, None).unwrap();
        let s1 = super::super::load_step(&p, None, 1).unwrap();
        assert_eq!(s0.dims(), [32, 20, 12]);
        assert!((s0.spacing() - DVec3::new(2.0, 2.0, 2.2)).abs().max_element() < 1e-5, "{}", s0.spacing());
        assert!((s0.origin() - DVec3::new(117.8551, -35.72294, -7.2487984)).abs().max_element() < 1e-3);
        assert_eq!(&s0.data()[..4], &[424.0, 428.0, 408.0, 403.0]);
        assert_eq!(&s1.data()[..4], &[439.0, 421.0, 414.0, 404.0]);
        assert_eq!(&s1.data()[s1.data().len() - 3..], &[452.0, 448.0, 457.0]);
        let sum = |v: &Volume| v.data().iter().map(|&x| x as f64).sum::<f64>();
        assert_eq!((sum(&s0), sum(&s1)), (3461748.0, 3465054.0));
    }

    #[test]
    fn nan_voxels_and_missing_image_files_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut vals = values(VoxelType::F32, 24);
        vals[3] = f64::NAN;
        let f = fields(VoxelType::F32, true);
        let e = error_of(dir.path(), "nan.nii.gz", &gzip(&nii(&f, &encode(&vals, VoxelType::F32, true))));
        assert!(matches!(e, VolumeError::NonFinite { count: 1, i: 0, j: 1, k: 0, .. }), "{e}");

        let h = dir.path().join("lonely.hdr");
        fs::write(&h, header(&Fields { vox_offset: 0.0, magic: b"ni1\0", ..f })).unwrap();
        let e = load(&h, None).unwrap_err();
        assert!(matches!(&e, VolumeError::Io { path, .. } if path == &dir.path().join("lonely.img")), "{e}");
    }
}
