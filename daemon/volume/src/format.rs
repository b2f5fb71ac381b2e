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

impl VoxelFormat {
    /// The code the kernels' `VOXEL_FORMAT` constant takes for this format (shaders/volume.wgsl).
    pub fn code(self) -> u32 {
        match self {
            VoxelFormat::R32F => 0,
            VoxelFormat::R16F => 1,
            VoxelFormat::R16 => 2,
            VoxelFormat::R8 => 3,
        }
    }

    /// Voxels per 32-bit word of the packed storage.
    pub fn per_word(self) -> usize {
        4 / self.bytes()
    }

    /// Whether the format maps a value range onto 0..=1 (and so needs the whole volume's range:
    /// two bricks of one volume must round alike).
    pub fn is_unorm(self) -> bool {
        matches!(self, VoxelFormat::R16 | VoxelFormat::R8)
    }

    fn levels(self) -> f64 {
        match self {
            VoxelFormat::R16 => 65535.0,
            VoxelFormat::R8 => 255.0,
            _ => 1.0,
        }
    }

    /// The stored code of value `v` (`range`: the volume's value range, for the unorm formats).
    pub fn encode(self, v: f32, range: (f32, f32)) -> u32 {
        match self {
            VoxelFormat::R32F => v.to_bits(),
            VoxelFormat::R16F => half::f16::from_f32(v.clamp(-65504.0, 65504.0)).to_bits() as u32,
            VoxelFormat::R16 | VoxelFormat::R8 => {
                let (lo, hi) = (range.0 as f64, range.1 as f64);
                let levels = self.levels();
                let t = if hi > lo { (v as f64 - lo) / (hi - lo) } else { 0.0 };
                (t * levels).round().clamp(0.0, levels) as u32
            }
        }
    }

    /// The value a code stands for, as the kernels decode it (the bits of a half,
    /// `unpack2x16unorm`/`unpack4x8unorm` then `lo * (1 - t) + hi * t`): the CPU twin of
    /// `voxel()` in shaders/volume.wgsl.
    pub fn decode(self, code: u32, range: (f32, f32)) -> f32 {
        match self {
            VoxelFormat::R32F => f32::from_bits(code),
            VoxelFormat::R16F => half::f16::from_bits(code as u16).to_f32(),
            VoxelFormat::R16 | VoxelFormat::R8 => {
                let t = code as f32 / self.levels() as f32;
                range.0 * (1.0 - t) + range.1 * t
            }
        }
    }

    /// `data` packed as the GPU stores it: [`Self::per_word`] codes per little-endian u32, the
    /// first voxel in the lowest bits; the last word padded with zeros.
    pub fn pack(self, data: &[f32], range: (f32, f32)) -> Vec<u32> {
        let per = self.per_word();
        let bits = 32 / per as u32;
        data.chunks(per)
            .map(|c| {
                c.iter().enumerate().fold(0u32, |w, (k, &v)| w | self.encode(v, range) << (bits * k as u32))
            })
            .collect()
    }

    /// The value of voxel `i` of words made by [`Self::pack`].
    pub fn unpack(self, words: &[u32], i: usize, range: (f32, f32)) -> f32 {
        let per = self.per_word();
        let bits = 32 / per;
        let w = words[i / per] >> (bits * (i % per));
        let mask = if bits == 32 { u32::MAX } else { (1u32 << bits) - 1 };
        self.decode(w & mask, range)
    }
}

impl Volume {
    /// The volume with every voxel rounded as `format` stores it and decoded as the kernels decode
    /// it (unorm formats over this volume's value range): the CPU twin of the GPU's packed volume.
    pub fn stored_as(&self, format: VoxelFormat) -> Volume {
        let range = self.value_range();
        let mut out = self.clone();
        if format != VoxelFormat::R32F {
            out.data = self.data().iter().map(|&v| format.decode(format.encode(v, range), range)).collect();
        }
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

    #[test]
    fn packed_words_unpack_to_the_stored_volume() {
        // 1000 voxels: not a multiple of 3 bytes' worth, and odd counts per word are padded.
        let v = ramp();
        let range = v.value_range();
        for f in VoxelFormat::ALL {
            let words = f.pack(v.data(), range);
            assert_eq!(words.len(), v.data().len().div_ceil(f.per_word()), "{}", f.name());
            let stored = v.stored_as(f);
            for i in 0..v.data().len() {
                assert_eq!(
                    f.unpack(&words, i, range).to_bits(),
                    stored.data()[i].to_bits(),
                    "{} voxel {i}",
                    f.name()
                );
            }
        }
        // The first voxel sits in the lowest bits; the range ends are the extreme codes.
        let (lo, hi) = range;
        assert_eq!(VoxelFormat::R16.pack(&[lo, hi], range), vec![0xFFFF_0000]);
        assert_eq!(VoxelFormat::R8.pack(&[hi, lo, lo], range), vec![0x0000_00FF]);
        assert_eq!(VoxelFormat::R16F.pack(&[1.0, -2.0], range), vec![0xC000_3C00]);
        // Values beyond half's range stay finite.
        assert_eq!(VoxelFormat::R16F.decode(VoxelFormat::R16F.encode(1e6, range), range), 65504.0);
    }
}
