//! DICOM series (dicom-rs: `dicom-object` reads the files, `dicom-pixeldata` decodes the pixels).
//!
//! A volume is one series: the single-frame image files of a folder that share a
//! SeriesInstanceUID (0020,000E). The source is the folder, or one file of the series (its folder's
//! files of the same series are read); a folder with several series needs the series chosen
//! (`DIR?series=UID`, `--series UID`, `series` in a wall config's `[volume]`), and the error lists
//! the series there. Files whose name starts with `.`, `DICOMDIR`, and files without DICOM's
//! `DICM` magic are not looked at (logged at debug); a file with the magic that cannot be read
//! is an error naming it.
//!
//! The grid:
//! - slices are ordered by ImagePositionPatient (0020,0032) along the slice normal, the cross
//!   product of ImageOrientationPatient's (0020,0037) row and column directions;
//! - x runs along the rows (the row direction), y down the columns, z along the normal; the
//!   volume lives in that frame, so for the usual axial orientation (`1\0\0\0\1\0`) world
//!   coordinates are the patient's (LPS) millimetres, and for any other orientation they are the
//!   patient's rotated into the grid (Isowall's grids are axis-aligned); the patient direction
//!   each of x, y, z leans towards most (LPS) is kept as the volume's [`crate::Orientation`]
//!   (none without ImageOrientationPatient, or for a grid 45 degrees off the patient's axes);
//! - the spacing is PixelSpacing (0028,0030) (row spacing, then column spacing: y first) and the
//!   step between slice positions (the median step, rounded to 1e-6); a series of one slice takes SpacingBetweenSlices (0018,0088),
//!   SliceThickness (0018,0050) or 1;
//! - refused, with the reason and the files: slices of different sizes, pixel spacings or
//!   orientations; two slices at one position (a duplicate); a gap (a step of about twice or more
//!   the usual one: a missing slice); uneven steps; slices that shift within their plane as they
//!   advance (a tilted gantry: Isowall does not resample); row and column directions that are not
//!   orthogonal; multi-frame files and colour images.
//! - voxel values are the stored values times RescaleSlope (0028,1053) plus RescaleIntercept
//!   (0028,1052), per slice (Hounsfield units for CT).
//!
//! Pixel data: the transfer syntaxes dicom-rs decodes in pure Rust: uncompressed (implicit and
//! explicit VR, little and big endian), deflate, RLE lossless, JPEG baseline, extended (8-bit; 12-bit
//! DCT data is refused by jpeg-decoder) and lossless (jpeg-decoder). JPEG-LS and JPEG 2000 would need C/C++ codecs (CharLS, OpenJPEG) and are refused
//! with the transfer syntax named.
//!
//! Sizes are checked from the headers before any pixel is decoded (the whole series against
//! [`super::MAX_VOXELS`] and the reader's [`VolumeLimit`] through [`super::Layout::check_within`]);
//! uncompressed pixel data must hold
//! the slice's bytes. Partial reads ([`crate::region`]) decode only the slices of a region.

use super::{format_err, Layout, VolumeLimit, VoxelType};
use crate::{Orientation, PatientAxes, PatientFrame, Volume, VolumeError};
use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::{InMemDicomObject, OpenFileOptions};
use dicom_pixeldata::{ConvertOptions, ModalityLutOption, PixelDecoder};
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};
use glam::DVec3;
use std::io::Read;
use std::path::{Path, PathBuf};

/// A DICOM header (the file up to its pixel data).
type Header = dicom_object::FileDicomObject<InMemDicomObject>;

/// Relative tolerance for slice steps: steps within 1% of the median are even.
const STEP_TOLERANCE: f64 = 0.01;

/// Whether `path` names DICOM data: a folder (not a Zarr store), a `.dcm`/`.dicom`/`.ima` file, or a file with the
/// `DICM` magic at byte 128.
pub fn is_dicom(path: &Path) -> bool {
    if path.is_dir() {
        return !super::ome_zarr::is_zarr(path);
    }
    let name = path.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    if [".dcm", ".dicom", ".ima"].iter().any(|e| name.ends_with(e)) {
        return true;
    }
    has_magic(path)
}

/// Whether the file has the DICOM magic `DICM` at byte 128.
fn has_magic(path: &Path) -> bool {
    let Ok(f) = std::fs::File::open(path) else { return false };
    let mut buf = [0u8; 132];
    let mut r = f.take(132);
    super::read_full(&mut r, &mut buf).map(|n| n == 132 && &buf[128..] == b"DICM").unwrap_or(false)
}

/// One series found in a folder, for listings.
#[derive(Clone, Debug, PartialEq)]
pub struct SeriesSummary {
    pub uid: String,
    pub modality: String,
    pub description: String,
    pub files: usize,
}

impl std::fmt::Display for SeriesSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({}, '{}', {} files)", self.uid, self.modality, self.description, self.files)
    }
}

/// One slice of a series: its file, the position along the normal and its rescaling.
#[derive(Clone, Debug)]
struct Slice {
    path: PathBuf,
    position: DVec3,
    depth: f64,
    slope: f64,
    intercept: f64,
}

/// A series, its grid known from the headers; voxels are decoded slice by slice on demand.
#[derive(Clone, Debug)]
pub struct Series {
    /// What the user named (the volume's name).
    name: PathBuf,
    pub uid: String,
    pub dims: [usize; 3],
    pub spacing: DVec3,
    pub origin: DVec3,
    /// The patient directions of x, y, z, where the files give ImageOrientationPatient.
    pub orientation: Option<Orientation>,
    /// Their exact directions (the row, the column and the normal), an oblique grid's included.
    pub patient_axes: Option<PatientAxes>,
    slices: Vec<Slice>,
}

/// Header facts one slice must share with the others.
#[derive(Clone, Debug, PartialEq)]
struct Shape {
    rows: usize,
    cols: usize,
    pixel_spacing: [f64; 2],
    row_dir: DVec3,
    col_dir: DVec3,
}

/// What a slice's header says.
struct SliceHeader {
    series: String,
    modality: String,
    description: String,
    shape: Shape,
    /// Whether ImageOrientationPatient is given (else rows along x, columns along y, unnamed).
    oriented: bool,
    position: Option<DVec3>,
    thickness: Option<f64>,
    slope: f64,
    intercept: f64,
}

fn tag_err(path: &Path, tag: Tag, name: &str, what: impl std::fmt::Display) -> VolumeError {
    format_err(path, format!("{name} {tag}: {what}"))
}

fn text(obj: &Header, tag: Tag) -> Option<String> {
    obj.get(tag).and_then(|e| e.to_str().ok()).map(|s| s.trim().trim_end_matches('\0').to_string())
}

fn required_text(path: &Path, obj: &Header, tag: Tag, name: &str) -> Result<String, VolumeError> {
    match text(obj, tag) {
        Some(s) if !s.is_empty() => Ok(s),
        _ => Err(tag_err(path, tag, name, "is missing or empty")),
    }
}

fn floats(
    path: &Path,
    obj: &Header,
    tag: Tag,
    name: &str,
    n: usize,
) -> Result<Option<Vec<f64>>, VolumeError> {
    let Some(e) = obj.get(tag) else { return Ok(None) };
    let v = e.to_multi_float64().map_err(|err| tag_err(path, tag, name, format!("not numbers ({err})")))?;
    if v.len() != n || v.iter().any(|x| !x.is_finite()) {
        return Err(tag_err(path, tag, name, format!("expected {n} finite numbers, got {v:?}")));
    }
    Ok(Some(v))
}

fn float(path: &Path, obj: &Header, tag: Tag, name: &str) -> Result<Option<f64>, VolumeError> {
    Ok(floats(path, obj, tag, name, 1)?.map(|v| v[0]))
}

fn uint(path: &Path, obj: &Header, tag: Tag, name: &str) -> Result<Option<u32>, VolumeError> {
    let Some(e) = obj.get(tag) else { return Ok(None) };
    e.to_int::<u32>().map(Some).map_err(|err| tag_err(path, tag, name, format!("not a whole number ({err})")))
}

/// Reads a file's header (up to the pixel data).
fn read_header(path: &Path) -> Result<Header, VolumeError> {
    OpenFileOptions::new()
        .read_until(tags::PIXEL_DATA)
        .open_file(path)
        .map_err(|e| format_err(path, format!("not a readable DICOM file: {}", report(&e))))
}

/// An error and its causes on one line.
fn report(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut src = e.source();
    while let Some(cause) = src {
        let c = cause.to_string();
        if !s.contains(&c) {
            s.push_str(": ");
            s.push_str(&c);
        }
        src = cause.source();
    }
    s
}

fn slice_header(path: &Path, obj: &Header) -> Result<SliceHeader, VolumeError> {
    let series = required_text(path, obj, tags::SERIES_INSTANCE_UID, "SeriesInstanceUID")?;
    let rows = uint(path, obj, tags::ROWS, "Rows")?
        .ok_or_else(|| tag_err(path, tags::ROWS, "Rows", "is missing"))?;
    let cols = uint(path, obj, tags::COLUMNS, "Columns")?
        .ok_or_else(|| tag_err(path, tags::COLUMNS, "Columns", "is missing"))?;
    if rows == 0 || cols == 0 {
        return Err(format_err(
            path,
            format!("Rows/Columns (0028,0010)/(0028,0011): {rows}x{cols} is an empty image"),
        ));
    }
    if let Some(frames) = text(obj, tags::NUMBER_OF_FRAMES).and_then(|s| s.parse::<u32>().ok()) {
        if frames > 1 {
            return Err(tag_err(
                path,
                tags::NUMBER_OF_FRAMES,
                "NumberOfFrames",
                format!("{frames} frames: multi-frame (enhanced) images are not read; Isowall reads a series of single-frame slices"),
            ));
        }
    }
    let spp = uint(path, obj, tags::SAMPLES_PER_PIXEL, "SamplesPerPixel")?.unwrap_or(1);
    if spp != 1 {
        return Err(tag_err(
            path,
            tags::SAMPLES_PER_PIXEL,
            "SamplesPerPixel",
            format!("{spp} samples per pixel (a colour image); Isowall reads one scalar per voxel"),
        ));
    }
    let pixel_spacing = match floats(path, obj, tags::PIXEL_SPACING, "PixelSpacing", 2)? {
        Some(v) if v[0] > 0.0 && v[1] > 0.0 => [v[0], v[1]],
        Some(v) => {
            return Err(tag_err(path, tags::PIXEL_SPACING, "PixelSpacing", format!("{v:?} must be positive")))
        }
        None => {
            tracing::warn!("{}: PixelSpacing (0028,0030) is missing; using 1 1", path.display());
            [1.0, 1.0]
        }
    };
    let (row_dir, col_dir, oriented) =
        match floats(path, obj, tags::IMAGE_ORIENTATION_PATIENT, "ImageOrientationPatient", 6)? {
            Some(v) => (DVec3::new(v[0], v[1], v[2]), DVec3::new(v[3], v[4], v[5]), true),
            None => (DVec3::X, DVec3::Y, false),
        };
    let (lr, lc) = (row_dir.length(), col_dir.length());
    if (lr - 1.0).abs() > 1e-3 || (lc - 1.0).abs() > 1e-3 {
        return Err(tag_err(
            path,
            tags::IMAGE_ORIENTATION_PATIENT,
            "ImageOrientationPatient",
            "the row and column directions must be unit vectors",
        ));
    }
    if row_dir.dot(col_dir).abs() > 1e-3 {
        return Err(tag_err(
            path,
            tags::IMAGE_ORIENTATION_PATIENT,
            "ImageOrientationPatient",
            format!(
                "rows and columns are not orthogonal (cosine {:.4}): a sheared grid, which Isowall does not resample",
                row_dir.dot(col_dir)
            ),
        ));
    }
    let position = floats(path, obj, tags::IMAGE_POSITION_PATIENT, "ImagePositionPatient", 3)?
        .map(|v| DVec3::new(v[0], v[1], v[2]));
    let thickness = match float(path, obj, tags::SPACING_BETWEEN_SLICES, "SpacingBetweenSlices")? {
        Some(t) if t > 0.0 => Some(t),
        _ => float(path, obj, tags::SLICE_THICKNESS, "SliceThickness")?.filter(|&t| t > 0.0),
    };
    let slope = float(path, obj, tags::RESCALE_SLOPE, "RescaleSlope")?.unwrap_or(1.0);
    let intercept = float(path, obj, tags::RESCALE_INTERCEPT, "RescaleIntercept")?.unwrap_or(0.0);
    Ok(SliceHeader {
        series,
        modality: text(obj, tags::MODALITY).unwrap_or_default(),
        description: text(obj, tags::SERIES_DESCRIPTION).unwrap_or_default(),
        shape: Shape {
            rows: rows as usize,
            cols: cols as usize,
            pixel_spacing,
            row_dir: row_dir / lr,
            col_dir: col_dir / lc,
        },
        oriented,
        position,
        thickness,
        slope,
        intercept,
    })
}

/// The DICOM files of a folder, sorted by name (see the module's notes).
fn folder_files(dir: &Path) -> Result<Vec<PathBuf>, VolumeError> {
    let entries = std::fs::read_dir(dir).map_err(|e| super::io_err(dir, e))?;
    let mut files = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| super::io_err(dir, e))?;
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') || name.eq_ignore_ascii_case("DICOMDIR") || !path.is_file() {
            continue;
        }
        if has_magic(&path) {
            files.push(path);
        } else {
            tracing::debug!("{}: no DICOM magic (DICM at byte 128); not part of the series", path.display());
        }
    }
    files.sort();
    Ok(files)
}

impl Series {
    /// Opens the series `path` names (a folder or one of its files), `series` choosing among
    /// several; reads every header, checks the grid and sizes, decodes no pixels.
    pub fn open(path: &Path, series: Option<&str>) -> Result<Series, VolumeError> {
        let (dir, named_file) = if path.is_dir() {
            (path.to_path_buf(), None)
        } else {
            if !path.exists() {
                return Err(super::io_err(
                    path,
                    std::io::Error::new(std::io::ErrorKind::NotFound, "no such file or folder"),
                ));
            }
            (
                path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).to_path_buf(),
                Some(path),
            )
        };
        let mut files = folder_files(&dir)?;
        let wanted: Option<String> = match (series, named_file) {
            (Some(uid), _) => Some(uid.to_string()),
            (None, Some(f)) => {
                let h = read_header(f)?;
                let uid = required_text(f, &h, tags::SERIES_INSTANCE_UID, "SeriesInstanceUID")?;
                if !files.iter().any(|p| p == f) {
                    files.push(f.to_path_buf());
                }
                Some(uid)
            }
            (None, None) => None,
        };
        if files.is_empty() {
            return Err(format_err(path, "holds no DICOM files (none with DICM at byte 128)"));
        }
        let mut headers: Vec<(PathBuf, SliceHeader)> = Vec::with_capacity(files.len());
        let mut found: Vec<SeriesSummary> = Vec::new();
        for f in files {
            let h = slice_header(&f, &read_header(&f)?);
            // A file of another series that does not parse as an image does not stop this one.
            let h = match (h, &wanted) {
                (Ok(h), _) => h,
                (Err(e), Some(_)) => {
                    let h = read_header(&f)?;
                    if text(&h, tags::SERIES_INSTANCE_UID).as_deref() != wanted.as_deref() {
                        continue;
                    }
                    return Err(e);
                }
                (Err(e), None) => return Err(e),
            };
            match found.iter_mut().find(|s| s.uid == h.series) {
                Some(s) => s.files += 1,
                None => found.push(SeriesSummary {
                    uid: h.series.clone(),
                    modality: h.modality.clone(),
                    description: h.description.clone(),
                    files: 1,
                }),
            }
            headers.push((f, h));
        }
        let listing = || found.iter().map(|s| format!("  {s}")).collect::<Vec<_>>().join("\n");
        let uid = match wanted {
            Some(uid) => {
                if !found.iter().any(|s| s.uid == uid) {
                    return Err(format_err(path, format!("holds no series {uid}; it holds:\n{}", listing())));
                }
                uid
            }
            None if found.len() == 1 => found[0].uid.clone(),
            None => {
                return Err(format_err(
                    path,
                    format!(
                        "holds {} series; choose one with --series UID (or `series` in the config's [volume]):\n{}",
                        found.len(),
                        listing()
                    ),
                ))
            }
        };
        headers.retain(|(_, h)| h.series == uid);
        Series::from_headers(path, uid, headers)
    }

    fn from_headers(
        path: &Path,
        uid: String,
        headers: Vec<(PathBuf, SliceHeader)>,
    ) -> Result<Series, VolumeError> {
        let (first_path, first) = &headers[0];
        let shape = first.shape.clone();
        for (p, h) in &headers[1..] {
            let s = &h.shape;
            let what = if (s.rows, s.cols) != (shape.rows, shape.cols) {
                Some(format!(
                    "{}x{} (columns x rows) where {} is {}x{}",
                    s.cols,
                    s.rows,
                    first_path.display(),
                    shape.cols,
                    shape.rows
                ))
            } else if (0..2)
                .any(|a| (s.pixel_spacing[a] - shape.pixel_spacing[a]).abs() > 1e-4 * shape.pixel_spacing[a])
            {
                Some(format!(
                    "PixelSpacing (0028,0030) {:?} where {} has {:?}",
                    s.pixel_spacing,
                    first_path.display(),
                    shape.pixel_spacing
                ))
            } else if (s.row_dir - shape.row_dir).length() > 1e-4
                || (s.col_dir - shape.col_dir).length() > 1e-4
            {
                Some(format!("ImageOrientationPatient (0020,0037) differs from {}'s", first_path.display()))
            } else {
                None
            };
            if let Some(what) = what {
                return Err(format_err(p, format!("series {uid} mixes slice sizes or grids: {what}")));
            }
        }
        let normal = shape.row_dir.cross(shape.col_dir).normalize();
        let mut slices = Vec::with_capacity(headers.len());
        for (p, h) in &headers {
            let position = match h.position {
                Some(pos) => pos,
                None if headers.len() == 1 => DVec3::ZERO,
                None => {
                    return Err(tag_err(
                        p,
                        tags::IMAGE_POSITION_PATIENT,
                        "ImagePositionPatient",
                        "is missing; slices cannot be ordered",
                    ))
                }
            };
            slices.push(Slice {
                path: p.clone(),
                position,
                depth: position.dot(normal),
                slope: h.slope,
                intercept: h.intercept,
            });
        }
        slices.sort_by(|a, b| a.depth.total_cmp(&b.depth));
        let dz = if slices.len() == 1 {
            first.thickness.unwrap_or(1.0)
        } else {
            check_steps(path, &uid, &slices, normal)?
        };
        let (nx, ny, nz) = (shape.cols, shape.rows, slices.len());
        let layout = Layout { dims: [nx, ny, nz], voxel: VoxelType::F32, big_endian: false };
        layout.voxel_count().map_err(|e| format_err(path, format!("series {uid}: {e}")))?;
        let p0 = slices[0].position;
        // PixelSpacing is (between rows, between columns): y first.
        let spacing = DVec3::new(shape.pixel_spacing[1], shape.pixel_spacing[0], dz);
        let origin = DVec3::new(p0.dot(shape.row_dir), p0.dot(shape.col_dir), p0.dot(normal));
        // x along the rows, y down the columns, z along the normal (slices in increasing depth).
        let patient_axes = first
            .oriented
            .then(|| PatientAxes::new([shape.row_dir, shape.col_dir, normal], PatientFrame::Lps))
            .flatten();
        let orientation = if first.oriented {
            let o = Orientation::from_directions([shape.row_dir, shape.col_dir, normal], PatientFrame::Lps);
            if o.is_none() {
                tracing::warn!(
                    "{}: ImageOrientationPatient turns the grid 45 degrees off the patient's axes: no \
                     orientation is kept (views are named by the world axes)",
                    first_path.display()
                );
            }
            o
        } else {
            None
        };
        Ok(Series {
            name: path.to_path_buf(),
            uid,
            dims: [nx, ny, nz],
            spacing,
            origin,
            orientation,
            patient_axes,
            slices,
        })
    }

    /// The files of the slices, in z order.
    pub fn files(&self) -> impl Iterator<Item = &Path> {
        self.slices.iter().map(|s| s.path.as_path())
    }

    /// Decodes slice `k` (x fastest, `nx * ny` values, rescaled) and appends it to `out`.
    pub fn read_slice(&self, k: usize, out: &mut Vec<f32>) -> Result<(), VolumeError> {
        let s = &self.slices[k];
        let [nx, ny, _] = self.dims;
        let values = decode_slice(&s.path, nx, ny)?;
        out.extend(values.iter().map(|&v| (v * s.slope + s.intercept) as f32));
        Ok(())
    }

    /// Whether the series, as `f32` voxels, fits `limit` (from its headers).
    pub fn check_within(&self, limit: &VolumeLimit) -> Result<(), VolumeError> {
        let layout = Layout { dims: self.dims, voxel: VoxelType::F32, big_endian: false };
        layout
            .check_within(limit)
            .map_err(|e| format_err(&self.name, format!("series {}: {e}", self.uid)))?;
        Ok(())
    }

    /// Reads every slice's compressed frame header (no pixel is decoded) and checks it says the
    /// series' slice size: what a read refuses before decoding, for `check-config`.
    pub fn check_frames(&self) -> Result<(), VolumeError> {
        let [nx, ny, _] = self.dims;
        for s in &self.slices {
            let obj = dicom_object::open_file(&s.path)
                .map_err(|e| format_err(&s.path, format!("cannot read the DICOM file: {}", report(&e))))?;
            check_frame(&s.path, &obj, nx, ny)?;
        }
        Ok(())
    }

    /// Reads the whole series if it fits `limit` (checked from the headers, before any pixel is
    /// decoded).
    pub fn read(&self, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
        let [nx, ny, nz] = self.dims;
        self.check_within(limit)?;
        let mut data = Vec::with_capacity(nx * ny * nz);
        for k in 0..nz {
            self.read_slice(k, &mut data)?;
        }
        Ok(super::make_volume(&self.name, self.dims, self.spacing, self.origin, data)?
            .with_orientation(self.orientation)
            .with_patient_axes(self.patient_axes))
    }
}

/// Orders are sorted; checks duplicates, gaps, uneven steps and in-plane shifts (tilt) and returns
/// the step.
fn check_steps(path: &Path, uid: &str, slices: &[Slice], normal: DVec3) -> Result<f64, VolumeError> {
    let steps: Vec<f64> = slices.windows(2).map(|w| w[1].depth - w[0].depth).collect();
    let mut sorted = steps.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    for (i, &d) in steps.iter().enumerate() {
        let (a, b) = (&slices[i], &slices[i + 1]);
        if d <= 1e-6 * median.abs().max(1e-3) {
            return Err(format_err(
                path,
                format!(
                    "series {uid}: {} and {} are at the same position ({:.4} along the slice normal): a duplicate slice",
                    a.path.display(),
                    b.path.display(),
                    a.depth
                ),
            ));
        }
    }
    for (i, &d) in steps.iter().enumerate() {
        let (a, b) = (&slices[i], &slices[i + 1]);
        if (d - median).abs() > STEP_TOLERANCE * median {
            let kind = if d > 1.5 * median {
                format!("a gap: about {} missing slice(s)", (d / median).round() as i64 - 1)
            } else {
                "uneven slice steps".to_string()
            };
            return Err(format_err(
                path,
                format!(
                    "series {uid}: {kind} between {} and {} (step {d:.4} where the usual step is {median:.4}); \
                     Isowall needs evenly spaced slices (it does not resample)",
                    a.path.display(),
                    b.path.display()
                ),
            ));
        }
    }
    let p0 = slices[0].position;
    for s in &slices[1..] {
        let along = (s.position - p0).dot(normal);
        let shift = ((s.position - p0) - along * normal).length();
        if shift > STEP_TOLERANCE * median {
            let tilt = shift.atan2(along).to_degrees();
            return Err(format_err(
                path,
                format!(
                    "series {uid}: {} is shifted {shift:.3} within the slice plane from the first slice: slices step \
                     at {tilt:.1} degrees off the normal (a tilted gantry), which Isowall does not resample",
                    s.path.display()
                ),
            ));
        }
    }
    // Positions are decimal strings (at most 16 characters): the step is known to about 1e-6 mm,
    // and rounding it there gives back the exact step a series was written with.
    Ok((median * 1e6).round() / 1e6)
}

/// Decodes one slice's stored values (no rescaling) as `f64`, `nx * ny` of them.
fn decode_slice(path: &Path, nx: usize, ny: usize) -> Result<Vec<f64>, VolumeError> {
    let obj = dicom_object::open_file(path)
        .map_err(|e| format_err(path, format!("cannot read the DICOM file: {}", report(&e))))?;
    let ts_uid = obj.meta().transfer_syntax().trim_end_matches('\0').to_string();
    let ts = TransferSyntaxRegistry.get(&ts_uid);
    let ts_name = ts.map(|t| t.name()).unwrap_or("unknown");
    match ts {
        None => {
            return Err(format_err(path, format!("transfer syntax {ts_uid} is unknown to Isowall's DICOM reader")))
        }
        Some(t) if !t.can_decode_all() => {
            return Err(format_err(
                path,
                format!(
                    "transfer syntax {ts_uid} ({ts_name}) cannot be decoded: Isowall reads uncompressed, deflate, RLE \
                     and JPEG baseline/extended/lossless pixel data (convert the series, e.g. with dcmdjpeg or gdcmconv --raw)"
                ),
            ))
        }
        Some(_) => {}
    }
    let pixel = obj
        .get(tags::PIXEL_DATA)
        .ok_or_else(|| tag_err(path, tags::PIXEL_DATA, "PixelData", "is missing"))?;
    let bits = uint(path, &obj, tags::BITS_ALLOCATED, "BitsAllocated")?
        .ok_or_else(|| tag_err(path, tags::BITS_ALLOCATED, "BitsAllocated", "is missing"))?;
    if ![8, 16, 32].contains(&bits) {
        return Err(tag_err(
            path,
            tags::BITS_ALLOCATED,
            "BitsAllocated",
            format!("{bits} bits; Isowall reads 8, 16 or 32"),
        ));
    }
    if !ts.is_some_and(|t| t.is_encapsulated_pixel_data()) {
        let need = nx * ny * (bits as usize / 8);
        let have = pixel.value().to_bytes().map(|b| b.len()).unwrap_or(0);
        if have < need {
            return Err(tag_err(
                path,
                tags::PIXEL_DATA,
                "PixelData",
                format!("is truncated: {have} bytes where a {nx}x{ny} slice of {bits} bits needs {need}"),
            ));
        }
    }
    check_frame(path, &obj, nx, ny)?;
    // A decoder panic on hostile data must not take the daemon down: it is this file's error.
    let decoded = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let px = obj.decode_pixel_data()?;
        px.to_vec_frame_with_options::<f64>(
            0,
            &ConvertOptions::new().with_modality_lut(ModalityLutOption::None),
        )
    }));
    let values = match decoded {
        Ok(Ok(v)) => v,
        Ok(Err(e)) => {
            return Err(tag_err(
                path,
                tags::PIXEL_DATA,
                "PixelData",
                format!("cannot decode {ts_name} data: {}", report(&e)),
            ))
        }
        Err(_) => {
            return Err(tag_err(
                path,
                tags::PIXEL_DATA,
                "PixelData",
                format!("the {ts_name} decoder failed on this data"),
            ))
        }
    };
    if values.len() != nx * ny {
        return Err(tag_err(
            path,
            tags::PIXEL_DATA,
            "PixelData",
            format!("decoded to {} values where a {nx}x{ny} slice has {}", values.len(), nx * ny),
        ));
    }
    Ok(values)
}

/// Checks that a JPEG frame's own header says the slice's size (`nx` columns by `ny` rows, one
/// component) before anything is decoded: the decoder allocates what the frame header says, not
/// what the DICOM header says, so a frame claiming 45000x45000 in a file whose Rows/Columns say
/// 8x8 would cost gigabytes before the size check after decoding. Only the markers up to the
/// frame header are read (jpeg-decoder's `read_info`); other pixel data passes unchanged (native
/// and RLE data are decoded to the DICOM header's size).
fn check_frame(path: &Path, obj: &Header, nx: usize, ny: usize) -> Result<(), VolumeError> {
    let Some(fragments) = obj.get(tags::PIXEL_DATA).and_then(|p| p.value().fragments()) else {
        return Ok(());
    };
    let jpeg = fragments.iter().find(|f| !f.is_empty()).is_some_and(|f| f.starts_with(&[0xFF, 0xD8]));
    if !jpeg {
        return Ok(());
    }
    let ts_uid = obj.meta().transfer_syntax().trim_end_matches('\0').to_string();
    let ts_name = TransferSyntaxRegistry.get(&ts_uid).map(|t| t.name()).unwrap_or("JPEG");
    let err = |what: String| tag_err(path, tags::PIXEL_DATA, "PixelData", what);
    let reader = Fragments { rest: fragments, at: 0 };
    let info = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let mut d = jpeg_decoder::Decoder::new(reader);
        d.read_info().map(|()| d.info())
    }));
    let info = match info {
        Ok(Ok(Some(info))) => info,
        Ok(Ok(None)) => return Err(err("the JPEG data has no frame header".into())),
        Ok(Err(e)) => return Err(err(format!("cannot read the {ts_name} frame header: {e}"))),
        Err(_) => return Err(err("the JPEG frame header cannot be read".into())),
    };
    let (w, h) = (usize::from(info.width), usize::from(info.height));
    if (w, h) != (nx, ny) {
        return Err(err(format!(
            "the JPEG frame header says {w}x{h} (columns x rows) where Rows/Columns (0028,0010)/(0028,0011) say {nx}x{ny}: refused before decoding"
        )));
    }
    let components = match info.pixel_format {
        jpeg_decoder::PixelFormat::L8 | jpeg_decoder::PixelFormat::L16 => 1,
        jpeg_decoder::PixelFormat::RGB24 => 3,
        jpeg_decoder::PixelFormat::CMYK32 => 4,
    };
    if components != 1 {
        return Err(err(format!(
            "the JPEG frame has {components} components where a greyscale slice has 1: refused before decoding"
        )));
    }
    Ok(())
}

/// The fragments of encapsulated pixel data read as one stream (a frame may span several).
struct Fragments<'a, P> {
    rest: &'a [P],
    at: usize,
}

impl<P: AsRef<[u8]>> Read for Fragments<'_, P> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        while let Some(first) = self.rest.first() {
            let left = &first.as_ref()[self.at..];
            if left.is_empty() {
                self.rest = &self.rest[1..];
                self.at = 0;
                continue;
            }
            let n = left.len().min(buf.len());
            buf[..n].copy_from_slice(&left[..n]);
            self.at += n;
            return Ok(n);
        }
        Ok(0)
    }
}

/// Reads the series `path` names (see [`Series::open`]) within `limit`.
pub fn read(path: &Path, series: Option<&str>, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
    Series::open(path, series)?.read(limit)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::dicom_write::SeriesWriter;
    use crate::io::testutil::shared_file;

    fn data(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/dicom").join(name)
    }

    /// Reads one of the test files on its own: the folder holds several copies of one series
    /// (which, together, are duplicate slices).
    fn read_alone(name: &str) -> Result<Volume, VolumeError> {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join(name);
        std::fs::copy(data(name), &p).unwrap();
        read(&p, None, &VolumeLimit::default())
    }

    /// A small CT-like volume: whole Hounsfield values from -1024 up, distinct per voxel.
    fn ct_like(dims: [usize; 3]) -> Volume {
        let n: usize = dims.iter().product();
        let values = (0..n).map(|i| ((i * 37) % 3000) as f32 - 1024.0).collect();
        Volume::new("ct-like", dims, DVec3::new(0.5, 0.75, 1.25), DVec3::new(-10.0, 4.5, 3.0), values)
            .unwrap()
    }

    fn err_of(path: &Path, series: Option<&str>) -> String {
        read(path, series, &VolumeLimit::default()).unwrap_err().to_string()
    }

    #[test]
    fn a_written_series_reads_back_voxel_for_voxel_from_the_folder_or_one_file() {
        let dir = tempfile::tempdir().unwrap();
        let v = ct_like([5, 4, 6]);
        let files = SeriesWriter::new("1.2.826.0.1.3680043.10.1").write(&v, dir.path()).unwrap();
        for source in [dir.path().to_path_buf(), files[3].clone()] {
            let r = read(&source, None, &VolumeLimit::default()).unwrap();
            assert_eq!(r.dims(), v.dims());
            assert!((r.spacing() - v.spacing()).abs().max_element() < 1e-9, "{}", r.spacing());
            assert!((r.origin() - v.origin()).abs().max_element() < 1e-9, "{}", r.origin());
            assert_eq!(r.data(), v.data());
        }
    }

    #[test]
    fn image_orientation_names_the_patient_directions_of_the_axes() {
        let v = ct_like([4, 3, 5]);
        for (orientation, want) in [
            // Axial: rows towards the patient's left, columns posterior, slices superior.
            ([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], Some("LPS")),
            // Coronal: rows left, columns inferior, the normal (row x column) posterior.
            ([1.0, 0.0, 0.0, 0.0, 0.0, -1.0], Some("LIP")),
            // Sagittal, 37 degrees oblique: rows posterior, columns superior, the normal left.
            ([0.0, 0.8, 0.6, 0.0, -0.6, 0.8], Some("PSL")),
            // 45 degrees between left and posterior: no nearest axis.
            ([0.5f64.sqrt(), 0.5f64.sqrt(), 0.0, -(0.5f64.sqrt()), 0.5f64.sqrt(), 0.0], None),
        ] {
            let dir = tempfile::tempdir().unwrap();
            let writer =
                SeriesWriter::new("1.2.826.0.1.3680043.10.9").with_image_orientation(orientation).unwrap();
            writer.write(&v, dir.path()).unwrap();
            let read = read(dir.path(), None, &VolumeLimit::default()).unwrap();
            assert_eq!(read.orientation().map(|o| o.code()).as_deref(), want, "{orientation:?}");
            assert_eq!(read.data(), v.data(), "{orientation:?}: the grid is the written one");
        }
    }

    /// ImageOrientationPatient and ImagePositionPatient of each file, as written.
    fn geometry_of(files: &[PathBuf]) -> Vec<Vec<f64>> {
        files
            .iter()
            .map(|f| {
                let obj = read_header(f).unwrap();
                let mut g = floats(f, &obj, tags::IMAGE_ORIENTATION_PATIENT, "IOP", 6).unwrap().unwrap();
                g.extend(floats(f, &obj, tags::IMAGE_POSITION_PATIENT, "IPP", 3).unwrap().unwrap());
                g
            })
            .collect()
    }

    #[test]
    fn an_oriented_volume_is_written_where_its_patient_is_and_reads_back_the_same() {
        use crate::PatientDir::*;
        let v = ct_like([4, 3, 5]);
        let (o, s) = (v.origin(), v.spacing());
        // RAS (a NRRD's or a NIfTI's world): +x right and +y anterior are LPS's -x and -y.
        let ras = v.clone().with_orientation(Orientation::new([Right, Anterior, Superior]));
        let dir = tempfile::tempdir().unwrap();
        let files = SeriesWriter::new("1.2.826.0.1.3680043.10.30").write(&ras, dir.path()).unwrap();
        for (k, g) in geometry_of(&files).iter().enumerate() {
            assert_eq!(g[..6], [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0], "slice {k}: rows right, columns anterior");
            let want = [-o.x, -o.y, o.z + k as f64 * s.z];
            assert!(g[6..].iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-9), "slice {k}: {g:?}");
        }
        let r = read(dir.path(), None, &VolumeLimit::default()).unwrap();
        assert_eq!(r.orientation().map(|o| o.code()).as_deref(), Some("RAS"));
        assert!((r.origin() - o).abs().max_element() < 1e-9, "{}", r.origin());
        assert_eq!((r.dims(), r.data()), (v.dims(), v.data()));

        // An oblique series (sagittal, 37 degrees): read, written again from the volume alone,
        // it is the same files' geometry and reads back the same volume.
        let dir = tempfile::tempdir().unwrap();
        let first = SeriesWriter::new("1.2.826.0.1.3680043.10.31")
            .with_image_orientation([0.0, 0.8, 0.6, 0.0, -0.6, 0.8])
            .unwrap()
            .write(&v, &dir.path().join("a"))
            .unwrap();
        let oblique = read(&dir.path().join("a"), None, &VolumeLimit::default()).unwrap();
        assert_eq!(oblique.orientation().map(|o| o.code()).as_deref(), Some("PSL"));
        let again =
            SeriesWriter::new("1.2.826.0.1.3680043.10.32").write(&oblique, &dir.path().join("b")).unwrap();
        let (g1, g2) = (geometry_of(&first), geometry_of(&again));
        for (k, (a, b)) in g1.iter().zip(&g2).enumerate() {
            assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9), "slice {k}: {a:?} then {b:?}");
        }
        let back = read(&dir.path().join("b"), None, &VolumeLimit::default()).unwrap();
        assert_eq!(back.patient_axes(), oblique.patient_axes());
        assert!((back.origin() - oblique.origin()).abs().max_element() < 1e-9);
        assert_eq!(back.data(), v.data());

        // A mirrored grid (+z inferior): the same patient, its slices in the normal's order.
        let lpi = v.clone().with_orientation(Orientation::new([Left, Posterior, Inferior]));
        assert!(!lpi.patient_axes().unwrap().right_handed());
        let dir = tempfile::tempdir().unwrap();
        SeriesWriter::new("1.2.826.0.1.3680043.10.33").write(&lpi, dir.path()).unwrap();
        let r = read(dir.path(), None, &VolumeLimit::default()).unwrap();
        assert_eq!(r.orientation().map(|o| o.code()).as_deref(), Some("LPS"));
        let [nx, ny, nz] = v.dims();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    assert_eq!(r.at(i, j, nz - 1 - k), v.at(i, j, k), "voxel {i} {j} {k}");
                }
            }
        }
        // Voxel k at z = o.z + k s.z inferior is at -(o.z + k s.z) superior.
        assert!((r.origin().z + o.z + (nz - 1) as f64 * s.z).abs() < 1e-9, "{}", r.origin());
    }

    #[test]
    fn slices_are_ordered_by_position_not_by_file_name() {
        let dir = tempfile::tempdir().unwrap();
        let v = ct_like([3, 2, 5]);
        let (o, s) = (v.origin(), v.spacing());
        // File k holds slice k of `v` but sits at the mirrored position.
        let mut w = SeriesWriter::new("1.2.826.0.1.3680043.10.2");
        w.z_positions = Some((0..5).map(|k| o.z + (4 - k) as f64 * s.z).collect());
        w.write(&v, dir.path()).unwrap();
        let r = read(dir.path(), None, &VolumeLimit::default()).unwrap();
        for k in 0..5 {
            for i in 0..6 {
                assert_eq!(r.data()[6 * k + i], v.data()[6 * (4 - k) + i], "slice {k}");
            }
        }
        assert!((r.origin().z - o.z).abs() < 1e-9);
    }

    #[test]
    fn a_folder_of_several_series_lists_them_and_reads_the_chosen_one() {
        let dir = tempfile::tempdir().unwrap();
        let a = ct_like([3, 3, 4]);
        let b = Volume::new("b", [2, 2, 3], DVec3::ONE, DVec3::ZERO, (0..12).map(|x| x as f32).collect())
            .unwrap();
        let mut wa = SeriesWriter::new("1.2.3.100");
        wa.description = "head".into();
        wa.write(&a, dir.path()).unwrap();
        let mut wb = SeriesWriter::new("1.2.3.200");
        wb.first_number = 100;
        let files_b = wb.write(&b, dir.path()).unwrap();
        let e = err_of(dir.path(), None);
        assert!(e.contains("holds 2 series") && e.contains("--series"), "{e}");
        assert!(e.contains("1.2.3.100 (CT, 'head', 4 files)") && e.contains("1.2.3.200"), "{e}");
        assert_eq!(read(dir.path(), Some("1.2.3.100"), &VolumeLimit::default()).unwrap().data(), a.data());
        assert_eq!(read(dir.path(), Some("1.2.3.200"), &VolumeLimit::default()).unwrap().data(), b.data());
        // One file names its own series.
        assert_eq!(read(&files_b[1], None, &VolumeLimit::default()).unwrap().dims(), [2, 2, 3]);
        let e = err_of(dir.path(), Some("9.9"));
        assert!(e.contains("no series 9.9") && e.contains("1.2.3.100"), "{e}");
    }

    #[test]
    fn broken_series_are_refused_with_the_reason_and_the_files() {
        let v = ct_like([3, 3, 6]);
        let (o, s) = (v.origin(), v.spacing());
        // A missing slice.
        let dir = tempfile::tempdir().unwrap();
        let files = SeriesWriter::new("1.5.1").write(&v, dir.path()).unwrap();
        std::fs::remove_file(&files[2]).unwrap();
        let e = err_of(dir.path(), None);
        assert!(e.contains("a gap: about 1 missing slice") && e.contains("slice_0001.dcm"), "{e}");
        // A duplicate.
        let dir = tempfile::tempdir().unwrap();
        let files = SeriesWriter::new("1.5.2").write(&v, dir.path()).unwrap();
        std::fs::copy(&files[4], dir.path().join("copy.dcm")).unwrap();
        let e = err_of(dir.path(), None);
        assert!(e.contains("duplicate slice") && e.contains("copy.dcm"), "{e}");
        // An uneven step.
        let dir = tempfile::tempdir().unwrap();
        let mut w = SeriesWriter::new("1.5.3");
        w.z_positions = Some((0..6).map(|k| o.z + k as f64 * s.z + if k >= 3 { 0.3 } else { 0.0 }).collect());
        w.write(&v, dir.path()).unwrap();
        let e = err_of(dir.path(), None);
        assert!(
            e.contains("uneven slice steps") && e.contains("slice_0002.dcm") && e.contains("slice_0003.dcm"),
            "{e}"
        );
        // A tilted gantry: each slice shifted along y as it advances.
        let dir = tempfile::tempdir().unwrap();
        let mut w = SeriesWriter::new("1.5.4");
        w.shift_per_slice = [0.0, 0.2];
        w.write(&v, dir.path()).unwrap();
        let e = err_of(dir.path(), None);
        assert!(e.contains("tilted gantry") && e.contains("9.1 degrees"), "{e}");
        // Mixed sizes in one series.
        let dir = tempfile::tempdir().unwrap();
        SeriesWriter::new("1.5.5").write(&v, dir.path()).unwrap();
        let small = Volume::new("s", [2, 3, 1], s, o + DVec3::Z * 6.0 * s.z, vec![0.0; 6]).unwrap();
        let mut w = SeriesWriter::new("1.5.5");
        w.first_number = 6;
        w.write(&small, dir.path()).unwrap();
        let e = err_of(dir.path(), None);
        assert!(e.contains("mixes slice sizes") && e.contains("slice_0006.dcm") && e.contains("2x3"), "{e}");
    }

    #[test]
    fn bad_files_name_the_file_and_the_tag() {
        let e = read_alone("MR_truncated.dcm").unwrap_err().to_string();
        assert!(e.contains("MR_truncated.dcm") && e.contains("(7FE0,0010)"), "{e}");
        // A slice cut short inside its pixel data.
        let dir = tempfile::tempdir().unwrap();
        let files = SeriesWriter::new("1.6.1").write(&ct_like([8, 8, 3]), dir.path()).unwrap();
        let bytes = std::fs::read(&files[1]).unwrap();
        std::fs::write(&files[1], &bytes[..bytes.len() - 40]).unwrap();
        let e = err_of(dir.path(), None);
        assert!(e.contains("slice_0001.dcm") && e.contains("(7FE0,0010)"), "{e}");
        // A header cut short: the series cannot be read, the file is named.
        std::fs::write(&files[2], &bytes[..300]).unwrap();
        let e = err_of(dir.path(), None);
        assert!(e.contains("slice_0002.dcm"), "{e}");
        // Colour and unsupported codecs.
        let e = read_alone("SC_rgb_rle.dcm").unwrap_err().to_string();
        assert!(e.contains("SamplesPerPixel (0028,0002)") && e.contains("colour"), "{e}");
        for (f, ts) in [
            ("MR_small_jpeg_ls_lossless.dcm", "1.2.840.10008.1.2.4.80"),
            ("MR_small_jp2klossless.dcm", "1.2.840.10008.1.2.4.90"),
        ] {
            let e = read_alone(f).unwrap_err().to_string();
            assert!(e.contains(f) && e.contains(ts) && e.contains("cannot be decoded"), "{e}");
        }
    }

    #[test]
    fn real_slices_decode_with_their_rescaling() {
        // CT_small: stored 175 180 166 143 in the first row (pydicom), RescaleIntercept -1024.
        let ct = read_alone("CT_small.dcm").unwrap();
        assert_eq!(ct.dims(), [128, 128, 1]);
        assert_eq!(&ct.data()[..4], &[175.0 - 1024.0, 180.0 - 1024.0, 166.0 - 1024.0, 143.0 - 1024.0]);
        assert!((ct.spacing().x - 0.661468).abs() < 1e-9);
        assert!((ct.origin() - DVec3::new(-158.135803, -179.035797, -75.699997)).length() < 1e-9);
        // MR_small in four encodings: the same voxels (905 1019 1227 1259 first).
        let mr = read_alone("MR_small.dcm").unwrap();
        assert_eq!(&mr.data()[..4], &[905.0, 1019.0, 1227.0, 1259.0]);
        for f in ["MR_small_RLE.dcm", "MR_small_bigendian.dcm", "MR_small_implicit.dcm"] {
            assert_eq!(read_alone(f).unwrap().data(), mr.data(), "{f}");
        }
        // JPEG extended at 12 bits: jpeg-decoder does not decode 12-bit DCT data; refused, named.
        let e = read_alone("JPGExtended.dcm").unwrap_err().to_string();
        assert!(
            e.contains("JPGExtended.dcm") && e.contains("(7FE0,0010)") && e.contains("JPEG Extended"),
            "{e}"
        );
    }

    /// The pure-Rust JPEG decoders of this build: lossless (process 14) decodes to exactly the
    /// RLE copy's pixels, baseline to within its loss.
    #[test]
    fn jpeg_lossless_and_baseline_decode_in_this_build() {
        let pixels = |f: &str| {
            let obj = dicom_object::open_file(data(f)).unwrap();
            obj.decode_pixel_data().unwrap().to_vec_frame::<u8>(0).unwrap()
        };
        let rle = pixels("SC_rgb_rle.dcm");
        assert_eq!(rle.len(), 100 * 100 * 3);
        assert_eq!(pixels("SC_rgb_jpeg_gdcm.dcm"), rle);
        let baseline = pixels("SC_rgb_dcmtk_+eb+cr.dcm");
        let worst = baseline.iter().zip(&rle).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        assert!(worst < 40 && baseline != rle, "baseline differs from the lossless pixels by up to {worst}");
    }

    #[test]
    fn the_shared_ct_as_a_series_equals_the_nrrd_voxel_for_voxel() {
        let Some(nrrd) = shared_file("../../../shared/data/ct-cranium.nrrd") else { return };
        let ct = crate::io::load(&nrrd, None).unwrap();
        let dir = tempfile::tempdir().unwrap();
        SeriesWriter::new("1.2.826.0.1.3680043.10.9").write(&ct, dir.path()).unwrap();
        let series = read(dir.path(), None, &VolumeLimit::default()).unwrap();
        assert_eq!(series.dims(), ct.dims());
        assert!((series.spacing() - ct.spacing()).abs().max_element() < 1e-9, "{}", series.spacing());
        assert!((series.origin() - ct.origin()).abs().max_element() < 1e-9, "{}", series.origin());
        assert_eq!(
            series.orientation(),
            ct.orientation(),
            "the series is the patient the NRRD's header says"
        );
        assert_eq!(series.data(), ct.data());
    }

    #[test]
    fn partial_reads_decode_only_the_slices_of_the_region() {
        let dir = tempfile::tempdir().unwrap();
        let v = ct_like([6, 5, 7]);
        let files = SeriesWriter::new("1.7.1").write(&v, dir.path()).unwrap();
        // Slice 0 is unreadable: a region that does not touch it never decodes it.
        let bytes = std::fs::read(&files[0]).unwrap();
        std::fs::write(&files[0], &bytes[..bytes.len() - 10]).unwrap();
        let s = crate::VolumeSource::File(dir.path().to_path_buf()).stream(None).unwrap();
        assert!(s.partial());
        let range = crate::VoxelRange { lo: [1, 2, 3], hi: [4, 4, 6] };
        let r = s.read_region(&range).unwrap();
        let mut whole = v.data().to_vec();
        whole[..30].fill(0.0);
        let want = Volume::new("w", v.dims(), v.spacing(), v.origin(), whole).unwrap().crop(&range).unwrap();
        assert_eq!(r.data(), want.data());
        assert!((r.origin() - want.origin()).length() < 1e-9);
        let e = s.block_minmax(4).unwrap_err().to_string();
        assert!(e.contains("slice_0000.dcm"), "{e}");
    }

    #[test]
    fn a_series_too_large_is_refused_before_decoding() {
        let dir = tempfile::tempdir().unwrap();
        // 1 x 1 slices: the headers claim 65535 x 65535, which with 300 slices passes 2^30 voxels.
        let v = Volume::new("v", [1, 1, 1], DVec3::ONE, DVec3::ZERO, vec![0.0]).unwrap();
        let f = SeriesWriter::new("1.8.1").write(&v, dir.path()).unwrap();
        let mut obj = dicom_object::open_file(&f[0]).unwrap();
        for k in 0..300 {
            obj.put(dicom_core::DataElement::new(
                tags::ROWS,
                dicom_core::VR::US,
                dicom_core::PrimitiveValue::from(65535u16),
            ));
            obj.put(dicom_core::DataElement::new(
                tags::COLUMNS,
                dicom_core::VR::US,
                dicom_core::PrimitiveValue::from(65535u16),
            ));
            obj.put(dicom_core::DataElement::new(
                tags::IMAGE_POSITION_PATIENT,
                dicom_core::VR::DS,
                dicom_core::PrimitiveValue::Strs(
                    ["0".to_string(), "0".to_string(), k.to_string()].into_iter().collect(),
                ),
            ));
            obj.write_to_file(dir.path().join(format!("big_{k:03}.dcm"))).unwrap();
        }
        std::fs::remove_file(&f[0]).unwrap();
        let e = err_of(dir.path(), None);
        assert!(e.contains("over Isowall's limit"), "{e}");
    }

    #[test]
    fn a_series_over_the_reader_limit_is_refused_naming_the_limit() {
        // 5x4x6 float32 is 480 bytes: a 400-byte limit refuses it naming the limit's source;
        // a limit of exactly its size reads it.
        let dir = tempfile::tempdir().unwrap();
        let v = ct_like([5, 4, 6]);
        SeriesWriter::new("1.8.2").write(&v, dir.path()).unwrap();
        let limit = VolumeLimit::new(400, "[volume] max_bytes");
        let e = read(dir.path(), None, &limit).unwrap_err().to_string();
        assert!(e.contains("480 bytes as float32, over the limit of 400 bytes ([volume] max_bytes)"), "{e}");
        assert!(e.contains("series 1.8.2"), "{e}");
        let r = read(dir.path(), None, &VolumeLimit::new(480, "test")).unwrap();
        assert_eq!(r.data(), v.data());
    }
}
