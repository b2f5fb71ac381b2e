//! Writes a volume as a DICOM series (dicom-object's writer): one CT slice per file, the voxels
//! stored as 16-bit integers with RescaleSlope 1 and a RescaleIntercept, positions and spacing
//! from the volume's grid. For tests and benchmarks (a real-looking series from any volume,
//! checked voxel for voxel against its source) and `examples/dicom_series.rs`; not a clinical
//! export.
//!
//! The patient stays where the volume's file put it: ImageOrientationPatient holds the patient
//! directions of the volume's +x and +y ([`Volume::patient_axes`]: an oblique DICOM grid's exact
//! directions, or the orientation's axes; LPS axial for a volume without one, which is how views
//! read such a volume), and slice k's ImagePositionPatient is voxel (0, 0, k)'s world position
//! turned onto those directions, so the DICOM reader gives back the volume's origin, grid and
//! orientation. A mirrored (left-handed) grid, whose +z is against the slice normal (row x
//! column), reads back with its slices in the normal's order: the same patient, z reversed.

use crate::{Orientation, PatientAxes, Volume, VolumeError};
use dicom_core::{DataElement, PrimitiveValue, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use std::path::{Path, PathBuf};

/// How to write a series.
#[derive(Clone, Debug)]
pub struct SeriesWriter {
    pub series_uid: String,
    pub description: String,
    /// Stored value = voxel - intercept (rounded); voxels must be whole numbers in range.
    pub intercept: f64,
    /// The slice positions along z (default: the volume's grid); lets tests write broken series.
    pub z_positions: Option<Vec<f64>>,
    /// In-plane shift of slice k's position: `k * shift` (a tilted gantry when not zero).
    pub shift_per_slice: [f64; 2],
    /// First file name number (`slice_NNNN.dcm`).
    pub first_number: usize,
    /// The patient directions of the volume's x, y and z (LPS); x and y are written as
    /// ImageOrientationPatient's row and column, and positions are `x a0 + y a1 + z a2`. `None`
    /// (the default): the volume's own ([`Volume::patient_axes`]), else LPS axial.
    pub axes: Option<PatientAxes>,
}

impl SeriesWriter {
    pub fn new(series_uid: impl Into<String>) -> SeriesWriter {
        SeriesWriter {
            series_uid: series_uid.into(),
            description: "isowall".into(),
            intercept: -1024.0,
            z_positions: None,
            shift_per_slice: [0.0; 2],
            first_number: 0,
            axes: None,
        }
    }

    /// A writer whose grid lies along ImageOrientationPatient `iop` (the row's and the
    /// column's LPS directions; z along their cross product), whatever the volume says.
    pub fn with_image_orientation(self, iop: [f64; 6]) -> Result<SeriesWriter, VolumeError> {
        let [rx, ry, rz, cx, cy, cz] = iop;
        let (row, col) = (glam::DVec3::new(rx, ry, rz), glam::DVec3::new(cx, cy, cz));
        let axes =
            PatientAxes::new([row, col, row.cross(col)], crate::PatientFrame::Lps).ok_or_else(|| {
                VolumeError::Invalid(format!(
                    "ImageOrientationPatient {iop:?}: not two orthogonal directions"
                ))
            })?;
        Ok(SeriesWriter { axes: Some(axes), ..self })
    }

    /// Writes every z-slice of `v` to `dir` (created if absent); returns the files in z order.
    pub fn write(&self, v: &Volume, dir: &Path) -> Result<Vec<PathBuf>, VolumeError> {
        std::fs::create_dir_all(dir).map_err(|e| super::io_err(dir, e))?;
        let [nx, ny, nz] = v.dims();
        let (s, o) = (v.spacing(), v.origin());
        let mut files = Vec::with_capacity(nz);
        let axes = self.axes.or(v.patient_axes()).unwrap_or(PatientAxes::of(Orientation::ASSUMED));
        let [row, col, along_z] = axes.lps();
        let iop = [row.x, row.y, row.z, col.x, col.y, col.z];
        for k in 0..nz {
            let z = self.z_positions.as_ref().map_or(o.z + k as f64 * s.z, |p| p[k]);
            let shift = self.shift_per_slice.map(|d| d * k as f64);
            let mut pixels = Vec::with_capacity(nx * ny);
            for &x in &v.data()[nx * ny * k..nx * ny * (k + 1)] {
                let stored = f64::from(x) - self.intercept;
                if stored.fract() != 0.0 || !(0.0..=65535.0).contains(&stored) {
                    return Err(VolumeError::Invalid(format!(
                        "{}: voxel {x} is not a whole number in 16 bits above the intercept {}",
                        v.name, self.intercept
                    )));
                }
                pixels.push(stored as u16);
            }
            let sop = format!("{}.{}", self.series_uid, k + 1);
            let ds = |x: f64| format!("{x}");
            let el = |tag, vr, value: PrimitiveValue| DataElement::new(tag, vr, value);
            let str_ = |s: &str| PrimitiveValue::from(s.to_string());
            let obj = InMemDicomObject::from_element_iter([
                el(tags::SOP_CLASS_UID, VR::UI, str_(uids::CT_IMAGE_STORAGE)),
                el(tags::SOP_INSTANCE_UID, VR::UI, str_(&sop)),
                el(tags::MODALITY, VR::CS, str_("CT")),
                el(tags::SERIES_DESCRIPTION, VR::LO, str_(&self.description)),
                el(tags::STUDY_INSTANCE_UID, VR::UI, str_(&format!("{}.0", self.series_uid))),
                el(tags::SERIES_INSTANCE_UID, VR::UI, str_(&self.series_uid)),
                el(tags::INSTANCE_NUMBER, VR::IS, str_(&(k + 1).to_string())),
                el(
                    tags::IMAGE_POSITION_PATIENT,
                    VR::DS,
                    PrimitiveValue::Strs({
                        let p = (o.x + shift[0]) * row + (o.y + shift[1]) * col + z * along_z;
                        [ds(p.x), ds(p.y), ds(p.z)].into_iter().collect()
                    }),
                ),
                el(
                    tags::IMAGE_ORIENTATION_PATIENT,
                    VR::DS,
                    PrimitiveValue::Strs(iop.map(ds).into_iter().collect()),
                ),
                el(tags::SLICE_THICKNESS, VR::DS, str_(&ds(s.z))),
                el(tags::SAMPLES_PER_PIXEL, VR::US, PrimitiveValue::from(1u16)),
                el(tags::PHOTOMETRIC_INTERPRETATION, VR::CS, str_("MONOCHROME2")),
                el(tags::ROWS, VR::US, PrimitiveValue::from(ny as u16)),
                el(tags::COLUMNS, VR::US, PrimitiveValue::from(nx as u16)),
                el(
                    tags::PIXEL_SPACING,
                    VR::DS,
                    PrimitiveValue::Strs([ds(s.y), ds(s.x)].into_iter().collect()),
                ),
                el(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(16u16)),
                el(tags::BITS_STORED, VR::US, PrimitiveValue::from(16u16)),
                el(tags::HIGH_BIT, VR::US, PrimitiveValue::from(15u16)),
                el(tags::PIXEL_REPRESENTATION, VR::US, PrimitiveValue::from(0u16)),
                el(tags::RESCALE_INTERCEPT, VR::DS, str_(&ds(self.intercept))),
                el(tags::RESCALE_SLOPE, VR::DS, str_("1")),
                el(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(pixels.into_iter().collect())),
            ]);
            let meta = FileMetaTableBuilder::new()
                .transfer_syntax(uids::EXPLICIT_VR_LITTLE_ENDIAN)
                .media_storage_sop_class_uid(uids::CT_IMAGE_STORAGE);
            let file = obj
                .with_meta(meta)
                .map_err(|e| VolumeError::Invalid(format!("DICOM file meta for slice {k}: {e}")))?;
            let path = dir.join(format!("slice_{:04}.dcm", self.first_number + k));
            file.write_to_file(&path)
                .map_err(|e| super::format_err(&path, format!("cannot write DICOM: {e}")))?;
            files.push(path);
        }
        Ok(files)
    }
}
