//! Writers and checks shared by the readers' tests.

use super::VoxelType;
use crate::Volume;
use glam::DVec3;
use std::io::Write;
use std::path::PathBuf;

pub const ALL_TYPES: [VoxelType; 8] = [
    VoxelType::U8,
    VoxelType::I8,
    VoxelType::U16,
    VoxelType::I16,
    VoxelType::U32,
    VoxelType::I32,
    VoxelType::F32,
    VoxelType::F64,
];

/// Values of `voxel` type worth a round trip: its extremes, zero, small values; all exact in
/// `f32` except two `f64`s that test the rounding to `f32`.
pub fn type_values(voxel: VoxelType) -> Vec<f64> {
    match voxel {
        VoxelType::U8 => vec![0.0, 1.0, 127.0, 128.0, 255.0, 42.0],
        VoxelType::I8 => vec![-128.0, -1.0, 0.0, 1.0, 127.0, -42.0],
        VoxelType::U16 => vec![0.0, 1.0, 255.0, 256.0, 65535.0, 1000.0],
        VoxelType::I16 => vec![-32768.0, -1.0, 0.0, 1.0, 32767.0, -1024.0, 2986.0],
        VoxelType::U32 => vec![0.0, 1.0, 65536.0, 16777216.0, 4294967040.0],
        VoxelType::I32 => vec![-2147483648.0, -1.0, 0.0, 1.0, 16777216.0, 2147483520.0],
        VoxelType::F32 => vec![-1.5, 0.0, 3.25, f64::from(1e-3f32), -1e30f32 as f64, f64::from(f32::MAX)],
        VoxelType::F64 => vec![-2.5, 0.0, 1e10, 0.1, -1e-300, 123456789.123],
    }
}

/// `n` values of `voxel` type, cycling through [`type_values`] in a scrambled order.
pub fn values(voxel: VoxelType, n: usize) -> Vec<f64> {
    let t = type_values(voxel);
    (0..n).map(|i| t[(i * 7 + i / 3) % t.len()]).collect()
}

/// `values` stored as `voxel` in the given byte order, written out independently of the readers.
pub fn encode(values: &[f64], voxel: VoxelType, big_endian: bool) -> Vec<u8> {
    let mut out = Vec::new();
    for &v in values {
        let mut b: Vec<u8> = match voxel {
            VoxelType::U8 => vec![v as u8],
            VoxelType::I8 => vec![v as i8 as u8],
            VoxelType::U16 => (v as u16).to_le_bytes().to_vec(),
            VoxelType::I16 => (v as i16).to_le_bytes().to_vec(),
            VoxelType::U32 => (v as u32).to_le_bytes().to_vec(),
            VoxelType::I32 => (v as i32).to_le_bytes().to_vec(),
            VoxelType::F32 => (v as f32).to_le_bytes().to_vec(),
            VoxelType::F64 => v.to_le_bytes().to_vec(),
        };
        if big_endian {
            b.reverse();
        }
        out.extend(b);
    }
    out
}

pub fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

pub fn zlib(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// Checks a volume against what was written: dims, spacing, origin and every voxel (as `f32`).
pub fn check(v: &Volume, dims: [usize; 3], spacing: DVec3, origin: DVec3, values: &[f64]) {
    assert_eq!(v.dims(), dims, "{}", v.name);
    assert!((v.spacing() - spacing).abs().max_element() < 1e-12, "{}: spacing {}", v.name, v.spacing());
    assert!((v.origin() - origin).abs().max_element() < 1e-12, "{}: origin {}", v.name, v.origin());
    assert_eq!(v.data().len(), values.len());
    for (i, (&got, &want)) in v.data().iter().zip(values).enumerate() {
        assert_eq!(got, want as f32, "{}: voxel {i}", v.name);
    }
}

/// A file of the shared test data (`/work/shared`, seen from this crate): `None`, with a
/// message, when absent; absent in CI (`CI=true`) is a failure.
pub fn shared_file(path: &str) -> Option<PathBuf> {
    let p = PathBuf::from(path);
    if p.exists() {
        return Some(p);
    }
    assert!(std::env::var("CI").as_deref() != Ok("true"), "{} is missing in CI", p.display());
    eprintln!("skipped: {} is absent", p.display());
    None
}

/// A FIFO at `path` (by the `mkfifo` command: no unsafe code here).
pub(crate) fn mkfifo(path: &std::path::Path) {
    let ok = std::process::Command::new("mkfifo").arg(path).status().unwrap().success();
    assert!(ok, "mkfifo {}", path.display());
}
