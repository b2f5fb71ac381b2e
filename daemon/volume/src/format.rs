//! Voxel storage formats (performance): what precision the GPU could keep the voxels in, and what
//! that precision does to them. [`Volume::stored_as`] rounds every voxel as the format stores it
//! (unorm formats with a scale and offset mapping the volume's value range onto 0..=1), so the
//! error a format adds can be measured against the f32 volume with the f32 renderer.

use crate::Volume;

/// A voxel storage format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelFormat {
    /// 32-bit float: the voxels as loaded (no rounding).
    R32F,
    /// 16-bit float (IEEE half).
    R16F,
    /// 16-bit unsigned normalized, with scale and offset from the value range.
    R16,
    /// 8-bit unsigned normalized, with scale and offset from the value range.
    R8,
}

impl VoxelFormat {
    pub const ALL: [VoxelFormat; 4] =
        [VoxelFormat::R32F, VoxelFormat::R16F, VoxelFormat::R16, VoxelFormat::R8];

    pub fn name(self) -> &'static str {
        match self {
            VoxelFormat::R32F => "r32f",
            VoxelFormat::R16F => "r16f",
            VoxelFormat::R16 => "r16",
            VoxelFormat::R8 => "r8",
        }
    }

    /// Bytes per voxel.
    pub fn bytes(self) -> usize {
        match self {
            VoxelFormat::R32F => 4,
            VoxelFormat::R16F | VoxelFormat::R16 => 2,
            VoxelFormat::R8 => 1,
        }
    }
}

impl std::str::FromStr for VoxelFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        VoxelFormat::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| format!("unknown voxel format '{s}' (r32f, r16f, r16, r8)"))
    }
}

impl Volume {
    /// The volume with every voxel rounded as `format` stores it.
    pub fn stored_as(&self, format: VoxelFormat) -> Volume {
        let (lo, hi) = self.value_range();
        let (lo, range) = (lo as f64, (hi as f64 - lo as f64).max(f64::MIN_POSITIVE));
        let unorm = |levels: f64| {
            move |v: f32| (lo + ((v as f64 - lo) / range * levels).round() / levels * range) as f32
        };
        let data: Vec<f32> = match format {
            VoxelFormat::R32F => self.data().to_vec(),
            VoxelFormat::R16F => self.data().iter().map(|&v| half::f16::from_f32(v).to_f32()).collect(),
            VoxelFormat::R16 => self.data().iter().map(|&v| unorm(65535.0)(v)).collect(),
            VoxelFormat::R8 => self.data().iter().map(|&v| unorm(255.0)(v)).collect(),
        };
        let mut out = self.clone();
        out.data = data.into_iter().map(|v| if v.is_finite() { v } else { f32::MAX.copysign(v) }).collect();
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    fn ramp() -> Volume {
        let data: Vec<f32> = (0..1000).map(|i| -1024.0 + i as f32 * 3.0111).collect();
        Volume::new("ramp", [10, 10, 10], DVec3::ONE, DVec3::ZERO, data).unwrap()
    }

    #[test]
    fn each_format_rounds_within_its_step() {
        let v = ramp();
        let (lo, hi) = v.value_range();
        let range = (hi - lo) as f64;
        for (f, bound) in [
            (VoxelFormat::R32F, 0.0),
            (VoxelFormat::R16, 0.5 * range / 65535.0 + 1e-3),
            (VoxelFormat::R8, 0.5 * range / 255.0 + 1e-3),
            (VoxelFormat::R16F, 2048.0 * 2f64.powi(-11)),
        ] {
            let q = v.stored_as(f);
            let worst =
                v.data().iter().zip(q.data()).map(|(a, b)| (*a as f64 - *b as f64).abs()).fold(0.0, f64::max);
            assert!(worst <= bound, "{}: worst {worst} > {bound}", f.name());
            if f != VoxelFormat::R32F {
                assert!(worst > 0.0, "{}: rounded nothing", f.name());
            }
        }
    }

    #[test]
    fn unorm_keeps_the_range_ends_exactly_and_names_parse() {
        let v = ramp();
        for f in [VoxelFormat::R32F, VoxelFormat::R16, VoxelFormat::R8] {
            assert_eq!(v.stored_as(f).value_range(), v.value_range(), "{}", f.name());
        }
        for f in VoxelFormat::ALL {
            assert_eq!(f.name().parse::<VoxelFormat>(), Ok(f));
        }
        assert!("r4".parse::<VoxelFormat>().is_err());
    }
}
