//! Raw volumes: bare voxels, described by a [`RawSpec`] (the CLI's `--dims NX,NY,NZ`, `--type`,
//! `--spacing SX,SY,SZ`, or a wall config).
//!
//! Supported: every [`VoxelType`](super::VoxelType), either byte order, a header of
//! `header_bytes` to skip. The origin is 0. The file must hold exactly `header_bytes` plus the
//! voxels: a size mismatch either way is an error (it almost always means wrong dims or type).
//! Compressed raw files are not supported.

use super::{
    check_raw_size, format_err, make_volume, open, read_voxels, Encoding, Files, Layout, RawSpec, VolumeLimit,
};
use crate::{Volume, VolumeError};
use glam::DVec3;
use std::path::Path;

/// Reads the raw volume at `path` as `spec` describes it.
pub(crate) fn read(path: &Path, spec: &RawSpec, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
    let layout = Layout { dims: spec.dims, voxel: spec.voxel, big_endian: spec.big_endian };
    layout.check_within(limit).map_err(|e| format_err(path, format!("--dims {e}")))?;
    let s = spec.spacing;
    if !(s.is_finite() && s.min_element() > 0.0) {
        return Err(format_err(
            path,
            format!("--spacing {},{},{}: spacings must be finite and positive", s.x, s.y, s.z),
        ));
    }
    let files = Files::single(path);
    let (mut r, len) = open(path)?;
    check_raw_size(files, len, spec.header_bytes, &layout)?;
    let data = read_voxels(files, &mut r, Encoding::Raw, spec.header_bytes, &layout, None)?;
    make_volume(path, spec.dims, spec.spacing, DVec3::ZERO, data)
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{check, encode, values, ALL_TYPES};
    use super::super::{load, VoxelType};
    use super::*;
    use std::fs;

    fn spec(dims: [usize; 3], voxel: VoxelType, big_endian: bool, header_bytes: u64) -> RawSpec {
        RawSpec { dims, voxel, spacing: DVec3::new(0.5, 1.0, 2.5), big_endian, header_bytes }
    }

    #[test]
    fn every_type_and_byte_order_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [3, 4, 5];
        for voxel in ALL_TYPES {
            for big in [false, true] {
                for header in [0u64, 13] {
                    let vals = values(voxel, 60);
                    let mut bytes = vec![0xAB; header as usize];
                    bytes.extend(encode(&vals, voxel, big));
                    let p = dir.path().join(format!("v-{}-{big}-{header}.raw", voxel.name()));
                    fs::write(&p, bytes).unwrap();
                    let v = load(&p, Some(&spec(dims, voxel, big, header))).unwrap();
                    check(&v, dims, DVec3::new(0.5, 1.0, 2.5), DVec3::ZERO, &vals);
                    assert_eq!(v.name, p.display().to_string());
                }
            }
        }
    }

    #[test]
    fn bytes_written_by_hand_decode_as_expected() {
        // int16 258 = 0x0102 and -2 = 0xFFFE; x fastest: (0,0,0), (1,0,0).
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("hand.bin");
        fs::write(&p, [0x01, 0x02, 0xFF, 0xFE]).unwrap();
        let v = load(&p, Some(&spec([2, 1, 1], VoxelType::I16, true, 0))).unwrap();
        assert_eq!(v.data(), &[258.0, -2.0]);
        let v = load(&p, Some(&spec([1, 2, 1], VoxelType::I16, false, 0))).unwrap();
        assert_eq!(v.data(), &[513.0, -257.0]);
        assert_eq!(v.at(0, 1, 0), -257.0);
        // float32 1.0 little endian is 00 00 80 3F.
        fs::write(&p, [0x00, 0x00, 0x80, 0x3F]).unwrap();
        let v = load(&p, Some(&spec([1, 1, 1], VoxelType::F32, false, 0))).unwrap();
        assert_eq!(v.data(), &[1.0]);
    }

    #[test]
    fn size_mismatch_either_way_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("short.raw");
        fs::write(&p, vec![0u8; 1000]).unwrap();
        let e = load(&p, Some(&spec([10, 10, 10], VoxelType::I16, false, 0))).unwrap_err();
        let m = e.to_string();
        assert!(m.contains("truncated") && m.contains("1000 bytes") && m.contains("2000"), "{m}");
        assert!(m.starts_with(&p.display().to_string()), "{m}");
        let e = load(&p, Some(&spec([10, 10, 5], VoxelType::U8, false, 0))).unwrap_err();
        assert!(e.to_string().contains("extra data: file has 500 bytes more"), "{e}");
        let e = load(&p, Some(&spec([10, 10, 10], VoxelType::U8, false, 1))).unwrap_err();
        assert!(e.to_string().contains("truncated: 999 bytes from byte 1 on"), "{e}");
        let e = load(&p, Some(&spec([1, 1, 1], VoxelType::U8, false, 5000))).unwrap_err();
        assert!(e.to_string().contains("start at byte 5000"), "{e}");
    }

    #[test]
    fn huge_or_zero_dims_are_refused_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("small.raw");
        fs::write(&p, [0u8; 8]).unwrap();
        let e = load(&p, Some(&spec([2048, 2048, 2048], VoxelType::U8, false, 0))).unwrap_err();
        assert!(e.to_string().contains("over Isowall's limit"), "{e}");
        let e = load(&p, Some(&spec([usize::MAX, 3, 1], VoxelType::U8, false, 0))).unwrap_err();
        assert!(e.to_string().contains("overflow"), "{e}");
        let e = load(&p, Some(&spec([0, 3, 1], VoxelType::U8, false, 0))).unwrap_err();
        assert!(e.to_string().contains("at least 1"), "{e}");
        let mut s = spec([2, 2, 2], VoxelType::U8, false, 0);
        s.spacing = DVec3::new(1.0, 0.0, 1.0);
        assert!(load(&p, Some(&s)).unwrap_err().to_string().contains("--spacing"));
    }

    #[test]
    fn nan_voxels_are_refused_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("nan.f32");
        fs::write(&p, encode(&[1.0, f64::NAN, 2.0, 3.0], VoxelType::F32, false)).unwrap();
        let e = load(&p, Some(&spec([2, 2, 1], VoxelType::F32, false, 0))).unwrap_err();
        assert!(matches!(e, VolumeError::NonFinite { count: 1, i: 1, j: 0, k: 0, .. }), "{e}");
        assert!(e.to_string().starts_with(&p.display().to_string()), "{e}");
    }

    #[test]
    fn missing_file_and_missing_spec_are_explained() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("nothing.raw");
        let e = load(&p, Some(&spec([1, 1, 1], VoxelType::U8, false, 0))).unwrap_err();
        assert!(matches!(&e, VolumeError::Io { path, .. } if path == &p), "{e}");
        fs::write(&p, [0u8]).unwrap();
        let e = load(&p, None).unwrap_err();
        assert!(e.to_string().contains("needs --dims NX,NY,NZ, --type and --spacing"), "{e}");
    }
}
