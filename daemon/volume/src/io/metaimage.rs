//! MetaImage reader (ITK's MetaIO: <https://itk.org/Wiki/ITK/MetaIO/Documentation>).
//!
//! Supported:
//! - `.mha` with the voxels after the header (`ElementDataFile = LOCAL`), and `.mhd` (or `.mha`)
//!   whose `ElementDataFile` names one file, relative to the header's folder and inside it (an
//!   absolute path or `..` is refused: see [`super`]);
//! - `NDims = 3`, `DimSize`, `ElementType` `MET_UCHAR`, `MET_CHAR`, `MET_USHORT`, `MET_SHORT`,
//!   `MET_UINT`, `MET_INT`, `MET_FLOAT`, `MET_DOUBLE`;
//! - spacing from `ElementSpacing`, else `ElementSize`, else 1 (with a warning); origin from `Offset`
//!   (or `Origin`, `Position`), else 0;
//! - `BinaryDataByteOrderMSB` / `ElementByteOrderMSB` (`True` = big endian);
//! - `CompressedData = True`: zlib (or gzip, recognised by its magic), as MetaIO writes it;
//!   `CompressedDataSize` is not needed and ignored;
//! - `HeaderSize` for a detached file: bytes to skip at its start (before decompression), `-1`
//!   for "the voxels are the last bytes of the file" (uncompressed only);
//! - `TransformMatrix` (also `Rotation`, `Orientation`) when diagonal: a negative entry mirrors
//!   the data, so every sample keeps its world position;
//! - other keys (`ObjectType`, `Comment`, `CenterOfRotation`, `AnatomicalOrientation`,
//!   `ElementMin`/`Max`, ...) are ignored; keys are matched case-insensitively.
//!
//! Refused with an error: `NDims` other than 3, `ElementNumberOfChannels` other than 1, other
//! element types (64-bit integers, arrays), `BinaryData = False` (ASCII data), a non-diagonal
//! `TransformMatrix`, `ElementDataFile = LIST` and file-name patterns, `HeaderSize` with `LOCAL`
//! data, a repeated key.

use super::{
    data_file_path, dims3, format_err, make_volume, numbers, open, spacing3, vec3, AxisSteps, DataSpec,
    Encoding, Files, HeaderLines, Layout, VolumeLimit, VoxelType,
};
use crate::{Volume, VolumeError};
use glam::DVec3;
use std::collections::HashMap;
use std::path::Path;

/// Reads the MetaImage file (`.mha` or `.mhd`) at `path`.
pub(crate) fn read(path: &Path, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
    let (r, file_len) = open(path)?;
    let mut lines = HeaderLines::new(r, path, "MetaImage");
    let err = |line: usize, what: String| format_err(path, format!("line {line}: {what}"));

    // Key (lower case) -> (line, value), up to ElementDataFile, which ends the header.
    let mut keys: HashMap<String, (usize, String)> = HashMap::new();
    let (data_line, data_file) = loop {
        let Some(line) = lines.next_line()? else {
            return Err(format_err(path, "no ElementDataFile: it must be the header's last line"));
        };
        let n = lines.line_no;
        if line.trim().is_empty() {
            continue;
        }
        let Some((key, value)) = line.split_once('=') else {
            let shown: String = line.chars().take(40).collect();
            return Err(err(n, format!("expected 'Key = Value', got {shown:?}")));
        };
        let (key, value) = (key.trim(), value.trim());
        if key.eq_ignore_ascii_case("ElementDataFile") {
            break (n, value.to_string());
        }
        if let Some((first, _)) = keys.insert(key.to_ascii_lowercase(), (n, value.to_string())) {
            return Err(err(n, format!("{key} is given again (first in line {first})")));
        }
    };
    let get = |k: &str| keys.get(&k.to_ascii_lowercase()).map(|(n, v)| (*n, v.as_str()));
    let required = |k: &str| get(k).ok_or_else(|| format_err(path, format!("missing required key {k}")));
    let boolean = |k: &str| -> Result<Option<bool>, VolumeError> {
        match get(k) {
            None => Ok(None),
            Some((_, v)) if v.eq_ignore_ascii_case("true") || v == "1" => Ok(Some(true)),
            Some((_, v)) if v.eq_ignore_ascii_case("false") || v == "0" => Ok(Some(false)),
            Some((n, v)) => Err(err(n, format!("{k}: expected True or False, got '{v}'"))),
        }
    };

    if let Some((n, t)) = get("ObjectType") {
        if !t.eq_ignore_ascii_case("Image") {
            return Err(err(n, format!("ObjectType is '{t}'; Isowall reads images only")));
        }
    }
    let (n, nd) = required("NDims")?;
    if nd.parse::<usize>() != Ok(3) {
        return Err(err(n, format!("NDims is {nd}; Isowall reads 3-dimensional volumes only")));
    }
    let (dims_line, d) = required("DimSize")?;
    let dims = dims3("DimSize", d).map_err(|e| err(dims_line, e))?;
    if let Some((n, c)) = get("ElementNumberOfChannels") {
        if c.parse::<usize>() != Ok(1) {
            return Err(err(n, format!("ElementNumberOfChannels is {c}; Isowall reads one value per voxel")));
        }
    }
    let (n, t) = required("ElementType")?;
    let voxel = element_type(t).map_err(|e| err(n, e))?;
    if boolean("BinaryData")? == Some(false) {
        return Err(format_err(path, "BinaryData = False (ASCII voxels) is not supported"));
    }
    let big_endian = match (boolean("BinaryDataByteOrderMSB")?, boolean("ElementByteOrderMSB")?) {
        (Some(a), Some(b)) if a != b => {
            return Err(format_err(path, "BinaryDataByteOrderMSB and ElementByteOrderMSB disagree"))
        }
        (a, b) => a.or(b).unwrap_or(false),
    };
    let encoding = if boolean("CompressedData")? == Some(true) { Encoding::Zlib } else { Encoding::Raw };

    let spacing_key = ["ElementSpacing", "ElementSize"].into_iter().find_map(|k| get(k).map(|v| (k, v)));
    let spacing = match spacing_key {
        Some((key, (n, s))) => spacing3(key, s).map_err(|e| err(n, e))?,
        None => {
            tracing::warn!("{}: no ElementSpacing or ElementSize: assuming spacing 1", path.display());
            DVec3::ONE
        }
    };
    let mut origin = None;
    for key in ["Offset", "Origin", "Position"] {
        if let Some((n, o)) = get(key) {
            let o = vec3(key, o).map_err(|e| err(n, e))?;
            if origin.is_some_and(|first| first != o) {
                return Err(err(n, format!("{key} disagrees with Offset/Origin/Position given before")));
            }
            origin = Some(o);
        }
    }
    let origin = origin.unwrap_or(DVec3::ZERO);
    let steps =
        match ["TransformMatrix", "Rotation", "Orientation"].iter().find_map(|k| get(k).map(|v| (k, v))) {
            Some((key, (n, m))) => {
                let m = numbers::<f64>(key, m, 9, "number").map_err(|e| err(n, e))?;
                // Column a of the matrix is axis a's direction; MetaIO lists the columns one after another.
                let axis = |a: usize| DVec3::new(m[3 * a], m[3 * a + 1], m[3 * a + 2]) * spacing[a];
                Some(AxisSteps::new(key, [axis(0), axis(1), axis(2)]).map_err(|e| err(n, e))?)
            }
            None => None,
        };

    let header_size = match get("HeaderSize") {
        Some((n, h)) => match h.parse::<i64>() {
            Ok(-1) if encoding != Encoding::Raw => {
                return Err(err(n, "HeaderSize = -1 is only supported for uncompressed data".into()))
            }
            Ok(h) if h >= -1 => Some(h),
            _ => return Err(err(n, format!("HeaderSize: '{h}' is neither -1 nor a whole number"))),
        },
        None => None,
    };
    let layout = Layout { dims, voxel, big_endian };
    layout.check_within(limit).map_err(|e| err(dims_line, format!("DimSize: {e}")))?;

    let tokens: Vec<&str> = data_file.split_whitespace().collect();
    let mut data = if data_file.eq_ignore_ascii_case("LOCAL") {
        if header_size.is_some_and(|h| h != 0) {
            return Err(err(
                data_line,
                "HeaderSize is only supported with a detached ElementDataFile".into(),
            ));
        }
        let spec = DataSpec { encoding, file_skip: Some(0), decoded_skip: 0 };
        let pos = lines.offset;
        super::read_data(Files::single(path), lines.into_inner(), pos, file_len, spec, &layout, None)?
    } else if tokens.first().is_some_and(|t| t.eq_ignore_ascii_case("LIST")) {
        return Err(err(data_line, "ElementDataFile = LIST (one file per slice) is not supported".into()));
    } else if tokens.len() >= 4 && tokens[0].contains('%') {
        return Err(err(
            data_line,
            format!("ElementDataFile: the file name pattern '{data_file}' is not supported"),
        ));
    } else if data_file.is_empty() {
        return Err(err(data_line, "ElementDataFile: no file name".into()));
    } else {
        let data_path = data_file_path(path, &format!("line {data_line}: ElementDataFile"), &data_file)?;
        let (r, len) = open(&data_path)?;
        let file_skip = u64::try_from(header_size.unwrap_or(0)).ok();
        let spec = DataSpec { encoding, file_skip, decoded_skip: 0 };
        super::read_data(Files { header: path, data: &data_path }, r, 0, len, spec, &layout, None)?
    };
    let origin = match steps {
        Some(steps) => steps.apply(origin, dims, &mut data),
        None => origin,
    };
    make_volume(path, dims, spacing, origin, data)
}

/// The voxel type of a MetaImage `ElementType`.
fn element_type(t: &str) -> Result<VoxelType, String> {
    Ok(match t.to_ascii_uppercase().as_str() {
        "MET_UCHAR" => VoxelType::U8,
        "MET_CHAR" => VoxelType::I8,
        "MET_USHORT" => VoxelType::U16,
        "MET_SHORT" => VoxelType::I16,
        "MET_UINT" => VoxelType::U32,
        "MET_INT" => VoxelType::I32,
        "MET_FLOAT" => VoxelType::F32,
        "MET_DOUBLE" => VoxelType::F64,
        u if u.ends_with("_ARRAY") => {
            return Err(format!("ElementType {t}: vector voxels are not supported"))
        }
        "MET_LONG" | "MET_ULONG" | "MET_LONG_LONG" | "MET_ULONG_LONG" => {
            return Err(format!("ElementType {t} is not supported (convert to MET_INT or MET_FLOAT)"))
        }
        _ => {
            return Err(format!(
                "unknown ElementType '{t}' (MET_UCHAR, MET_CHAR, MET_USHORT, MET_SHORT, MET_UINT, MET_INT, \
                 MET_FLOAT, MET_DOUBLE are supported)"
            ))
        }
    })
}

#[cfg(test)]
mod tests {
    use super::super::load;
    use super::super::testutil::{check, encode, gzip, values, zlib, ALL_TYPES};
    use super::*;
    use std::fs;

    const DIMS: [usize; 3] = [2, 3, 4];

    fn met_name(voxel: VoxelType) -> &'static str {
        match voxel {
            VoxelType::U8 => "MET_UCHAR",
            VoxelType::I8 => "MET_CHAR",
            VoxelType::U16 => "MET_USHORT",
            VoxelType::I16 => "MET_SHORT",
            VoxelType::U32 => "MET_UINT",
            VoxelType::I32 => "MET_INT",
            VoxelType::F32 => "MET_FLOAT",
            VoxelType::F64 => "MET_DOUBLE",
        }
    }

    /// A header for a 2x3x4 volume; `extra` lines come before ElementDataFile.
    fn header(voxel: VoxelType, big: bool, compressed: bool, extra: &str, data_file: &str) -> String {
        let tf = |b: bool| if b { "True" } else { "False" };
        format!(
            "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = {}\nCompressedData = {}\n\
             TransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = -1 2.5 3\nElementSpacing = 0.25 1 3\nDimSize = 2 3 4\n\
             ElementType = {}\n{extra}ElementDataFile = {data_file}\n",
            tf(big),
            tf(compressed),
            met_name(voxel)
        )
    }

    fn write(path: &Path, header: &str, data: &[u8]) {
        fs::write(path, [header.as_bytes(), data].concat()).unwrap();
    }

    const SPACING: DVec3 = DVec3::new(0.25, 1.0, 3.0);
    const ORIGIN: DVec3 = DVec3::new(-1.0, 2.5, 3.0);

    #[test]
    fn local_and_detached_raw_and_compressed_of_every_type_read_back() {
        let dir = tempfile::tempdir().unwrap();
        for voxel in ALL_TYPES {
            for big in [false, true] {
                let vals = values(voxel, 24);
                let raw = encode(&vals, voxel, big);
                let stem = format!("{}-{big}", voxel.name());
                let mha = dir.path().join(format!("{stem}.mha"));
                write(&mha, &header(voxel, big, false, "", "LOCAL"), &raw);
                check(&load(&mha, None).unwrap(), DIMS, SPACING, ORIGIN, &vals);
                write(&mha, &header(voxel, big, true, "", "LOCAL"), &zlib(&raw));
                check(&load(&mha, None).unwrap(), DIMS, SPACING, ORIGIN, &vals);

                let mhd = dir.path().join(format!("{stem}.mhd"));
                fs::write(dir.path().join(format!("{stem}.raw")), &raw).unwrap();
                write(&mhd, &header(voxel, big, false, "", &format!("{stem}.raw")), &[]);
                check(&load(&mhd, None).unwrap(), DIMS, SPACING, ORIGIN, &vals);
                fs::write(dir.path().join(format!("{stem}.zraw")), zlib(&raw)).unwrap();
                write(&mhd, &header(voxel, big, true, "", &format!("{stem}.zraw")), &[]);
                check(&load(&mhd, None).unwrap(), DIMS, SPACING, ORIGIN, &vals);
            }
        }
    }

    #[test]
    fn header_size_gzip_element_size_and_key_variants() {
        let dir = tempfile::tempdir().unwrap();
        let vals = values(VoxelType::U16, 24);
        let raw = encode(&vals, VoxelType::U16, true);
        let d = dir.path().join("v.raw");
        let h = dir.path().join("v.mhd");
        fs::write(&d, [[1u8; 10].as_slice(), &raw].concat()).unwrap();
        write(&h, &header(VoxelType::U16, true, false, "HeaderSize = 10\n", "v.raw"), &[]);
        check(&load(&h, None).unwrap(), DIMS, SPACING, ORIGIN, &vals);
        write(&h, &header(VoxelType::U16, true, false, "HeaderSize = -1\n", "v.raw"), &[]);
        check(&load(&h, None).unwrap(), DIMS, SPACING, ORIGIN, &vals);
        // Gzip where zlib is expected (recognised by its magic).
        fs::write(&d, gzip(&raw)).unwrap();
        write(&h, &header(VoxelType::U16, true, true, "", "v.raw"), &[]);
        check(&load(&h, None).unwrap(), DIMS, SPACING, ORIGIN, &vals);
        // ElementSize when there is no ElementSpacing; Origin; ElementByteOrderMSB; CRLF; no
        // TransformMatrix.
        let text = "NDims = 3\r\nDimSize = 2 3 4\r\nElementSize = 2 2 5\r\nOrigin = 1 1 1\r\n\
                    ElementByteOrderMSB = True\r\nElementType = MET_USHORT\r\nElementDataFile = LOCAL\r\n";
        let mha = dir.path().join("v.mha");
        write(&mha, text, &raw);
        check(&load(&mha, None).unwrap(), DIMS, DVec3::new(2.0, 2.0, 5.0), DVec3::ONE, &vals);
    }

    #[test]
    fn a_mirroring_transform_keeps_world_positions() {
        let dir = tempfile::tempdir().unwrap();
        let vals: Vec<f64> = (0..24).map(|v| v as f64 * 1.5).collect();
        let p = dir.path().join("m.mha");
        let h = header(VoxelType::F32, false, false, "", "LOCAL")
            .replace("1 0 0 0 1 0 0 0 1", "1 0 0 0 -1 0 0 0 -1");
        write(&p, &h, &encode(&vals, VoxelType::F32, false));
        let v = load(&p, None).unwrap();
        assert_eq!(v.spacing(), SPACING);
        let axes = [DVec3::X * SPACING.x, -DVec3::Y * SPACING.y, -DVec3::Z * SPACING.z];
        for k in 0..4 {
            for j in 0..3 {
                for i in 0..2 {
                    let world = ORIGIN + axes[0] * i as f64 + axes[1] * j as f64 + axes[2] * k as f64;
                    assert_eq!(v.sample(world), Some(vals[i + 2 * (j + 3 * k)]), "({i},{j},{k})");
                }
            }
        }
    }

    fn error_of(dir: &Path, name: &str, header: &str, data: &[u8]) -> VolumeError {
        let p = dir.join(name);
        write(&p, header, data);
        let e = load(&p, None).unwrap_err();
        assert!(e.to_string().starts_with(&p.display().to_string()), "{e}");
        e
    }

    #[test]
    fn broken_headers_and_data_are_refused_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let raw = encode(&values(VoxelType::I16, 24), VoxelType::I16, false);
        let h = |extra: &str| header(VoxelType::I16, false, false, extra, "LOCAL");
        let m = error_of(d, "a.mha", &h("").replace("MET_SHORT", "MET_SHROT"), &raw).to_string();
        assert!(m.contains("line 10: unknown ElementType 'MET_SHROT'"), "{m}");
        let m = error_of(d, "a.mha", &h("").replace("NDims = 3", "NDims = 2"), &raw).to_string();
        assert!(m.contains("NDims is 2"), "{m}");
        let m = error_of(d, "a.mha", &h("").replace("DimSize = 2 3 4\n", ""), &raw).to_string();
        assert!(m.contains("missing required key DimSize"), "{m}");
        let m = error_of(d, "a.mha", &h("").replace("2 3 4", "2 3 four"), &raw).to_string();
        assert!(m.contains("DimSize: 'four' is not a whole number"), "{m}");
        let m = error_of(d, "a.mha", &h("ElementNumberOfChannels = 3\n"), &raw).to_string();
        assert!(m.contains("ElementNumberOfChannels is 3"), "{m}");
        let m =
            error_of(d, "a.mha", &h("").replace("1 0 0 0 1 0 0 0 1", "0 1 0 1 0 0 0 0 1"), &raw).to_string();
        assert!(m.contains("TransformMatrix: axis 0") && m.contains("axis-aligned"), "{m}");
        let m = error_of(d, "a.mha", &h("").replace("ElementDataFile = LOCAL\n", ""), &[]).to_string();
        assert!(m.contains("no ElementDataFile"), "{m}");
        let m = error_of(d, "a.mha", &h("BinaryData = False\n"), &raw).to_string();
        assert!(m.contains("line 11: BinaryData is given again (first in line 3)"), "{m}");
        let m =
            error_of(d, "a.mha", &h("").replace("BinaryData = True", "BinaryData = False"), &raw).to_string();
        assert!(m.contains("ASCII"), "{m}");
        let m =
            error_of(d, "a.mha", &h("").replace("BinaryData = True", "BinaryData = Maybe"), &raw).to_string();
        assert!(m.contains("BinaryData: expected True or False, got 'Maybe'"), "{m}");
        let m =
            error_of(d, "a.mha", &h("").replace("ElementSpacing = 0.25 1 3", "ElementSize = 1 -1 1"), &raw)
                .to_string();
        assert!(m.contains("line 8: ElementSize: spacings must be positive"), "{m}");
        let m = error_of(d, "a.mha", "this is not a header\n", &raw).to_string();
        assert!(m.contains("line 1: expected 'Key = Value'"), "{m}");

        let m = error_of(d, "a.mha", &h(""), &raw[..47]).to_string();
        let want = format!("data is truncated: 47 bytes from byte {} on, 2x3x4 int16 needs 48", h("").len());
        assert!(m.contains(&want), "{m}");
        let m = error_of(d, "a.mha", &h(""), &[raw.as_slice(), &[1, 2]].concat()).to_string();
        assert!(m.contains("extra data: file has 2 bytes more"), "{m}");
        let hz = header(VoxelType::I16, false, true, "", "LOCAL");
        let m = error_of(d, "a.mha", &hz, b"definitely not zlib data").to_string();
        assert!(m.contains("zlib data is corrupt"), "{m}");
        let m = error_of(d, "a.mha", &hz, &zlib(&raw[..30])).to_string();
        assert!(m.contains("decompresses to 30 bytes"), "{m}");
        let m = error_of(d, "a.mha", &hz, &zlib(&vec![0; 1 << 22])).to_string();
        assert!(m.contains("extra data"), "{m}");
    }

    #[test]
    fn nan_voxels_and_missing_data_files_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut vals = values(VoxelType::F64, 24);
        vals[23] = f64::INFINITY;
        let e = error_of(
            dir.path(),
            "nan.mha",
            &header(VoxelType::F64, true, true, "", "LOCAL"),
            &zlib(&encode(&vals, VoxelType::F64, true)),
        );
        assert!(matches!(e, VolumeError::NonFinite { count: 1, i: 1, j: 2, k: 3, .. }), "{e}");

        let h = dir.path().join("v.mhd");
        write(&h, &header(VoxelType::U8, false, false, "", "missing.raw"), &[]);
        let e = load(&h, None).unwrap_err();
        assert!(matches!(&e, VolumeError::Io { path, .. } if path == &dir.path().join("missing.raw")), "{e}");
    }
}
