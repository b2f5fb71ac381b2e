//! Scalar volumes and the field they define (DESIGN.md "Volume"):
//!
//! - dims (nx, ny, nz), x fastest in memory; sample (i, j, k) sits at world position
//!   `origin + (i*sx, j*sy, k*sz)`;
//! - the field f is the trilinear interpolant of the samples inside the box
//!   `[origin, origin + (n-1)*s]`; outside the box it is empty (below any iso), so a surface cut by
//!   the box is closed by a cap on the box face.
//!
//! Voxels are held as `f32` in the data's own units (Hounsfield for CT), whatever the file's type.
//! Non-finite voxels are rejected when a volume is made ([`VolumeError::NonFinite`]): the policy
//! is "refuse with a clear error", so no NaN or Inf can reach a renderer.
//!
//! Modules: [`io`] reads files (raw, NRRD, MetaImage, NIfTI-1), [`procedural`] makes the built-in
//! volumes, [`blocks`] holds the per-block min/max used for empty-space skipping, [`source`] parses
//! `PATH | procedural:NAME[:N]`, [`iso`] is the rule an iso value meets against the data's range.
//! [`env_files`] names and sizes the image files of a lighting environment from their headers
//! (for the renderer's loader and for `check-config`).

pub mod blocks;
pub mod brick_cache;
pub mod env_files;
pub mod format;
pub mod io;
pub mod iso;
pub mod orientation;
pub mod procedural;
pub mod region;
pub mod source;
pub mod steps;
pub mod value_stats;
mod voxel_range;

use glam::DVec3;
use std::path::PathBuf;

pub use blocks::BlockMinMax;
pub use format::VoxelFormat;
pub use iso::{check_iso, IsoError};
pub use orientation::{Orientation, PatientAxes, PatientDir, PatientFrame};
pub use region::{Pass, Progress, VolumeInfo, VolumeStream};
pub use source::VolumeSource;
pub use steps::{StepCache, StepState};
pub use voxel_range::VoxelRange;

/// Everything that can go wrong making or reading a volume. File errors carry the path.
#[derive(Debug, thiserror::Error)]
pub enum VolumeError {
    #[error("{path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
    /// A malformed header or an inconsistent file: `what` says which field and why.
    #[error("{path}: {what}")]
    Format { path: PathBuf, what: String },
    #[error("{path}: {count} non-finite voxel(s) (NaN or Inf), the first at index ({i}, {j}, {k}); Isowall refuses volumes with NaN/Inf voxels: clean the data or choose another file")]
    NonFinite { path: PathBuf, count: usize, i: usize, j: usize, k: usize },
    #[error("invalid volume: {0}")]
    Invalid(String),
    #[error("{0}")]
    Source(String),
}

/// The voxel sizes a volume may have, in world units on each axis: from a nanometre to a
/// kilometre when the unit is the millimetre. Beyond them no camera can frame it (its box would
/// be a point, or reach past the camera's coordinates).
pub const SPACING_RANGE: (f64, f64) = (1e-6, 1e6);
/// How far from the world's origin any point of a volume's box may lie, on each axis.
pub const MAX_WORLD_COORD: f64 = 1e6;

/// Checks that a grid of `dims` samples `spacing` apart from `origin` can be framed: its spacing
/// within [`SPACING_RANGE`] and its box within [`MAX_WORLD_COORD`] of the origin. (Finite and
/// positive spacing and a finite origin are the caller's checks.)
pub fn check_geometry(
    name: &str,
    dims: [usize; 3],
    spacing: DVec3,
    origin: DVec3,
) -> Result<(), VolumeError> {
    let (lo, hi) = SPACING_RANGE;
    if spacing.min_element() < lo || spacing.max_element() > hi {
        return Err(VolumeError::Invalid(format!(
            "{name}: spacing {:?} {:?} {:?} is outside {lo:e}..={hi:e} world units on some axis",
            spacing.x, spacing.y, spacing.z
        )));
    }
    let far = origin.abs() + DVec3::new(dims[0] as f64, dims[1] as f64, dims[2] as f64) * spacing;
    if far.max_element() > MAX_WORLD_COORD {
        return Err(VolumeError::Invalid(format!(
            "{name}: its box reaches {:e} world units from the origin (origin {} {} {}), beyond {MAX_WORLD_COORD:e}",
            far.max_element(),
            origin.x,
            origin.y,
            origin.z
        )));
    }
    Ok(())
}

/// A scalar volume on a regular grid, voxels as `f32` in the data's units.
#[derive(Clone, Debug)]
pub struct Volume {
    dims: [usize; 3],
    spacing: DVec3,
    origin: DVec3,
    data: Vec<f32>,
    /// Where it came from, for messages: a path or `procedural:NAME:N`.
    pub name: String,
    /// Which patient direction each world axis points to, where the file says so.
    orientation: Option<Orientation>,
    /// The exact patient directions of the world axes, where the file gives more than the
    /// [`Orientation`] keeps (an oblique DICOM grid).
    patient_axes: Option<PatientAxes>,
}

impl Volume {
    /// Makes a volume, checking that dims are >= 1, data has nx*ny*nz voxels, spacing is finite and
    /// positive, the origin finite and no voxel NaN or Inf.
    pub fn new(
        name: impl Into<String>,
        dims: [usize; 3],
        spacing: DVec3,
        origin: DVec3,
        data: Vec<f32>,
    ) -> Result<Volume, VolumeError> {
        let name = name.into();
        if dims.contains(&0) {
            return Err(VolumeError::Invalid(format!("{name}: dims {dims:?} must all be at least 1")));
        }
        let count = dims.iter().try_fold(1usize, |acc, &n| acc.checked_mul(n));
        if count != Some(data.len()) {
            return Err(VolumeError::Invalid(format!(
                "{name}: dims {dims:?} need {} voxels but {} were given",
                count.map_or("too many".to_string(), |c| c.to_string()),
                data.len()
            )));
        }
        if !(spacing.is_finite() && spacing.min_element() > 0.0) {
            return Err(VolumeError::Invalid(format!(
                "{name}: spacing {spacing:?} must be finite and positive"
            )));
        }
        if !origin.is_finite() {
            return Err(VolumeError::Invalid(format!("{name}: origin {origin:?} is not finite")));
        }
        check_geometry(&name, dims, spacing, origin)?;
        if let Some(first) = data.iter().position(|v| !v.is_finite()) {
            let count = data.iter().filter(|v| !v.is_finite()).count();
            let (i, j, k) = (first % dims[0], (first / dims[0]) % dims[1], first / (dims[0] * dims[1]));
            return Err(VolumeError::NonFinite { path: PathBuf::from(&name), count, i, j, k });
        }
        Ok(Volume { dims, spacing, origin, data, name, orientation: None, patient_axes: None })
    }

    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }
    pub fn spacing(&self) -> DVec3 {
        self.spacing
    }
    pub fn origin(&self) -> DVec3 {
        self.origin
    }
    pub fn data(&self) -> &[f32] {
        &self.data
    }
    /// The patient orientation the file gave, if any ([`Orientation`]).
    pub fn orientation(&self) -> Option<Orientation> {
        self.orientation
    }
    /// The volume with `orientation` as its patient orientation.
    pub fn with_orientation(self, orientation: Option<Orientation>) -> Volume {
        Volume { orientation, ..self }
    }
    /// The exact patient directions of the world axes: the file's where it gave them
    /// ([`Volume::with_patient_axes`]), else the orientation's axes, else none.
    pub fn patient_axes(&self) -> Option<PatientAxes> {
        self.patient_axes.or(self.orientation.map(PatientAxes::of))
    }
    /// The volume with `axes` as the exact patient directions of its world axes.
    pub fn with_patient_axes(self, axes: Option<PatientAxes>) -> Volume {
        Volume { patient_axes: axes, ..self }
    }
    /// Bytes the voxel buffer holds in memory: as allocated (capacity, not length).
    pub fn resident_bytes(&self) -> usize {
        self.data.capacity() * std::mem::size_of::<f32>()
    }

    /// The voxel at (i, j, k); panics when out of range (callers clamp).
    #[inline]
    pub fn at(&self, i: usize, j: usize, k: usize) -> f32 {
        self.data[i + self.dims[0] * (j + self.dims[1] * k)]
    }

    /// The box the field lives in: `[origin, origin + (n-1)*s]`.
    pub fn box_min(&self) -> DVec3 {
        self.origin
    }
    pub fn box_max(&self) -> DVec3 {
        self.origin
            + self.spacing
                * DVec3::new((self.dims[0] - 1) as f64, (self.dims[1] - 1) as f64, (self.dims[2] - 1) as f64)
    }

    /// Smallest and largest voxel value.
    pub fn value_range(&self) -> (f32, f32) {
        self.data.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| (lo.min(v), hi.max(v)))
    }

    /// Continuous voxel coordinates of a world position.
    #[inline]
    pub fn to_voxel(&self, p: DVec3) -> DVec3 {
        (p - self.origin) / self.spacing
    }

    /// Whether a world point lies in the closed box.
    pub fn contains(&self, p: DVec3) -> bool {
        let (lo, hi) = (self.box_min(), self.box_max());
        p.cmpge(lo).all() && p.cmple(hi).all()
    }

    /// The cell that holds continuous voxel coordinates `u` (clamped to the box): its lowest
    /// corner and the fraction along each axis; an axis with a single sample has cell 0, fraction 0.
    #[inline]
    fn cell_of(&self, u: DVec3) -> ([usize; 3], [f64; 3]) {
        let mut i0 = [0usize; 3];
        let mut fr = [0f64; 3];
        for a in 0..3 {
            let n = self.dims[a];
            if n == 1 {
                continue;
            }
            let x = u[a].clamp(0.0, (n - 1) as f64);
            let i = (x.floor() as usize).min(n - 2);
            i0[a] = i;
            fr[a] = x - i as f64;
        }
        (i0, fr)
    }

    /// The trilinear interpolant at continuous voxel coordinates `u`, clamped to the box.
    /// An axis with a single sample is constant along that axis.
    #[inline]
    pub fn trilinear_voxel(&self, u: DVec3) -> f64 {
        let (i0, fr) = self.cell_of(u);
        let step = |a: usize| usize::from(self.dims[a] > 1);
        let (i, j, k) = (i0[0], i0[1], i0[2]);
        let (di, dj, dk) = (step(0), step(1), step(2));
        let c = |a, b, c| self.at(a, b, c) as f64;
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let x00 = lerp(c(i, j, k), c(i + di, j, k), fr[0]);
        let x10 = lerp(c(i, j + dj, k), c(i + di, j + dj, k), fr[0]);
        let x01 = lerp(c(i, j, k + dk), c(i + di, j, k + dk), fr[0]);
        let x11 = lerp(c(i, j + dj, k + dk), c(i + di, j + dj, k + dk), fr[0]);
        lerp(lerp(x00, x10, fr[1]), lerp(x01, x11, fr[1]), fr[2])
    }

    /// The field at a world point: the trilinear interpolant inside the box, `None` (empty) outside.
    pub fn sample(&self, p: DVec3) -> Option<f64> {
        self.contains(p).then(|| self.trilinear_voxel(self.to_voxel(p)))
    }

    /// The field at a world point with the position clamped to the box (for gradient stencils).
    pub fn sample_clamped(&self, p: DVec3) -> f64 {
        self.trilinear_voxel(self.to_voxel(p))
    }

    /// Central differences of the trilinear field at `p` with h = one voxel spacing per axis,
    /// stencil positions clamped to the box (DESIGN.md "Normal").
    pub fn gradient(&self, p: DVec3) -> DVec3 {
        let s = self.spacing;
        let d =
            |e: DVec3, h: f64| (self.sample_clamped(p + e * h) - self.sample_clamped(p - e * h)) / (2.0 * h);
        DVec3::new(d(DVec3::X, s.x), d(DVec3::Y, s.y), d(DVec3::Z, s.z))
    }

    /// The trilinear interpolant's own gradient at `p`, inside the cell [`Volume::trilinear_voxel`]
    /// evaluates `p` in (position clamped to the box; an axis with a single sample has 0), in
    /// world units: DESIGN.md "AO"'s geometric normal is `-` this, normalized. The WGSL twin is
    /// `cell_gradient` in shaders/volume.wgsl.
    pub fn cell_gradient(&self, p: DVec3) -> DVec3 {
        let u = self.to_voxel(p);
        let (i0, fr) = self.cell_of(u);
        let step = |a: usize| usize::from(self.dims[a] > 1);
        let (d, (i, j, k)) = ([step(0), step(1), step(2)], (i0[0], i0[1], i0[2]));
        // Corner c[dx + 2 dy + 4 dz].
        let c: [f64; 8] = std::array::from_fn(|m| {
            let (x, y, z) = (m & 1, (m >> 1) & 1, (m >> 2) & 1);
            self.at(i + x * d[0], j + y * d[1], k + z * d[2]) as f64
        });
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let (x, y, z) = (fr[0], fr[1], fr[2]);
        // d/dx: the x differences blended over y and z; likewise for y and z.
        let gx = lerp(lerp(c[1] - c[0], c[3] - c[2], y), lerp(c[5] - c[4], c[7] - c[6], y), z);
        let gy = lerp(lerp(c[2] - c[0], c[3] - c[1], x), lerp(c[6] - c[4], c[7] - c[5], x), z);
        let gz = lerp(lerp(c[4] - c[0], c[5] - c[1], x), lerp(c[6] - c[2], c[7] - c[3], x), y);
        let g = DVec3::new(gx, gy, gz) / self.spacing;
        DVec3::select(glam::BVec3::new(d[0] == 0, d[1] == 0, d[2] == 0), DVec3::ZERO, g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cell_gradient_is_the_trilinear_cells_own() {
        // f = x y z + 3 x on a 4x3x3 grid, spacing (1, 2, 0.5): trilinear inside each cell is
        // exact for it, so the gradient is analytic at a point of the cell.
        let (dims, s) = ([4, 3, 3], DVec3::new(1.0, 2.0, 0.5));
        let f = |p: DVec3| p.x * p.y * p.z + 3.0 * p.x;
        let mut data = Vec::new();
        for k in 0..3 {
            for j in 0..3 {
                for i in 0..4 {
                    data.push(f(s * DVec3::new(i as f64, j as f64, k as f64)) as f32);
                }
            }
        }
        let v = Volume::new("xyz", dims, s, DVec3::ZERO, data).unwrap();
        let p = DVec3::new(1.3, 2.5, 0.7);
        let g = v.cell_gradient(p);
        let want = DVec3::new(p.y * p.z + 3.0, p.x * p.z, p.x * p.y);
        assert!((g - want).length() < 1e-5, "{g:?} {want:?}");
        // A flat axis has no gradient along it.
        let flat = Volume::new("flat", [2, 2, 1], DVec3::ONE, DVec3::ZERO, vec![0.0, 1.0, 0.0, 1.0]).unwrap();
        assert_eq!(flat.cell_gradient(DVec3::new(0.5, 0.5, 0.0)), DVec3::X);
    }

    fn ramp() -> Volume {
        // f = i + 10 j + 100 k on a 3x3x3 grid with spacing (1, 2, 4): trilinear reproduces it exactly.
        let mut d = Vec::new();
        for k in 0..3 {
            for j in 0..3 {
                for i in 0..3 {
                    d.push((i + 10 * j + 100 * k) as f32);
                }
            }
        }
        Volume::new("ramp", [3, 3, 3], DVec3::new(1.0, 2.0, 4.0), DVec3::new(-1.0, 0.0, 0.0), d).unwrap()
    }

    #[test]
    fn trilinear_reproduces_a_linear_field_and_outside_is_empty() {
        let v = ramp();
        let p = DVec3::new(-1.0 + 1.25, 2.0 * 0.5, 4.0 * 1.75);
        assert!((v.sample(p).unwrap() - (1.25 + 5.0 + 175.0)).abs() < 1e-12);
        assert_eq!(v.box_max(), DVec3::new(1.0, 4.0, 8.0));
        assert!(v.sample(DVec3::new(1.0001, 1.0, 1.0)).is_none());
        assert!(v.sample(v.box_max()).is_some());
        let g = v.gradient(DVec3::new(0.0, 2.0, 4.0));
        assert!((g - DVec3::new(1.0, 5.0, 25.0)).length() < 1e-12, "{g:?}");
    }

    #[test]
    fn invalid_volumes_are_refused_with_the_reason() {
        let e = Volume::new("v", [2, 2, 2], DVec3::ONE, DVec3::ZERO, vec![0.0; 7]).unwrap_err();
        assert!(e.to_string().contains("need 8 voxels but 7"), "{e}");
        let mut d = vec![0.0; 8];
        d[5] = f32::NAN;
        let e = Volume::new("v.raw", [2, 2, 2], DVec3::ONE, DVec3::ZERO, d).unwrap_err();
        assert!(matches!(e, VolumeError::NonFinite { count: 1, i: 1, j: 0, k: 1, .. }), "{e}");
        assert!(e.to_string().starts_with("v.raw:"));
        assert!(Volume::new("v", [2, 2, 2], DVec3::new(1.0, 0.0, 1.0), DVec3::ZERO, vec![0.0; 8]).is_err());
        assert!(Volume::new("v", [0, 2, 2], DVec3::ONE, DVec3::ZERO, vec![]).is_err());
        // A grid no camera can frame: a voxel of 1e300 or 1e-40, or a box past 1e6.
        for (s, o) in [(1e300, 0.0), (1e-40, 0.0), (1.0, 2e6)] {
            let e =
                Volume::new("v.nrrd", [2, 2, 2], DVec3::splat(s), DVec3::splat(o), vec![0.0; 8]).unwrap_err();
            let e = e.to_string();
            assert!(
                (e.contains("v.nrrd: spacing") || e.contains("v.nrrd: its box")) && !e.contains("camera"),
                "{e}"
            );
        }
    }

    #[test]
    fn single_sample_axes_are_constant() {
        let v = Volume::new("one", [1, 1, 1], DVec3::ONE, DVec3::ZERO, vec![3.0]).unwrap();
        assert_eq!(v.sample(DVec3::ZERO), Some(3.0));
        assert_eq!(v.sample(DVec3::new(0.1, 0.0, 0.0)), None);
        assert_eq!(v.gradient(DVec3::ZERO), DVec3::ZERO);
    }
}
