//! [`VoxelRange`]: an inclusive range of sample indices, what partial reads, regions and
//! procedural volumes are cut by; and cropping a volume to one.

use crate::{Volume, VolumeError};
use glam::DVec3;

/// An inclusive range of sample indices per axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct VoxelRange {
    pub lo: [usize; 3],
    pub hi: [usize; 3],
}

impl VoxelRange {
    /// Every sample of a volume of `dims`.
    pub fn whole(dims: [usize; 3]) -> VoxelRange {
        VoxelRange { lo: [0; 3], hi: dims.map(|n| n.max(1) - 1) }
    }

    /// Samples per axis.
    pub fn dims(&self) -> [usize; 3] {
        [0, 1, 2].map(|a| self.hi[a] + 1 - self.lo[a])
    }

    /// Number of samples.
    pub fn count(&self) -> usize {
        self.dims().iter().product()
    }

    /// Whether the range is non-empty and lies within a volume of `dims`.
    pub fn fits(&self, dims: [usize; 3]) -> bool {
        (0..3).all(|a| self.lo[a] <= self.hi[a] && self.hi[a] < dims[a])
    }
}

impl Volume {
    /// The samples of `range` as a volume of their own (origin at the range's first sample).
    pub fn crop(&self, range: &VoxelRange) -> Result<Volume, VolumeError> {
        if !range.fits(self.dims()) {
            return Err(VolumeError::Invalid(format!(
                "{}: region {range:?} does not fit dims {:?}",
                self.name,
                self.dims()
            )));
        }
        let [nx, ny, _] = range.dims();
        let mut data = Vec::with_capacity(range.count());
        for k in range.lo[2]..=range.hi[2] {
            for j in range.lo[1]..=range.hi[1] {
                let row = range.lo[0] + self.dims()[0] * (j + self.dims()[1] * k);
                data.extend_from_slice(&self.data()[row..row + nx]);
            }
        }
        debug_assert_eq!(data.len(), nx * ny * range.dims()[2]);
        Volume::new(self.name.clone(), range.dims(), self.spacing(), self.origin_of(range.lo), data)
    }

    /// World position of sample `index`.
    pub fn origin_of(&self, index: [usize; 3]) -> DVec3 {
        self.origin() + self.spacing() * DVec3::new(index[0] as f64, index[1] as f64, index[2] as f64)
    }
}
