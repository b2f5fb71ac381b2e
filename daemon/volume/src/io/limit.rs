//! How big a volume may be: the voxel count Isowall reads at most and the byte limit readers
//! check against a header's dims before they allocate or inflate anything.

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
