//! NRRD reader (<http://teem.sourceforge.net/nrrd/format.html>), magic `NRRD0001` to `NRRD0005`.
//!
//! Supported:
//! - `.nrrd` with the data attached after the header's blank line, and detached headers (`.nhdr`,
//!   or any NRRD header) whose `data file:` names one file, relative to the header's folder and
//!   inside it (an absolute path or `..` is refused: see [`super`]);
//! - `encoding`: `raw`, `gzip` (also `gz`);
//! - `type`: every 8, 16 and 32-bit integer and `float`/`double`, under all of NRRD's names
//!   (`uchar`, `unsigned char`, `uint8`, `uint8_t`, `signed char`, `char`, `short`, `short int`,
//!   `signed short int`, `int16_t`, ... `float`, `double`);
//! - `endian` (required for multi-byte types), `line skip`, `byte skip` (`-1`, "the voxels are the
//!   last bytes of the file", with raw encoding only; for gzip the skip is in the decompressed data);
//! - geometry from `spacings`, or from `space directions` lying along the world axes (a negative
//!   direction mirrors the data, so every sample keeps its world position), and `space origin`;
//!   neither gives spacing 1 (with a warning); the origin defaults to 0;
//! - patient orientation from `space` (`right-anterior-superior`, `left-posterior-superior`,
//!   `RAS`, `LPS`, ...): the world axes are the space's (a mirrored direction keeps them), so
//!   `space` names them ([`crate::Orientation`]); `scanner-xyz` and `3D-*-handed` have none, an
//!   unknown space is refused;
//! - comments, `key:=value` pairs, CRLF line endings; fields Isowall does not use (`content`,
//!   `kinds`, `centers`, `axis mins`, `labels`, `units`, `measurement frame`, ...) are
//!   ignored, unknown fields warned about and ignored;
//! - `dimension: 4`: a series of 3-D time steps along the 4th (slowest) axis; the per-axis fields
//!   have a 4th entry, which is ignored (`spacings ... nan`, `space directions ... none`); the
//!   steps are stacked along z in the file ([`super::load_step`] reads one step's voxels alone); a negative z
//!   direction is refused there.
//!
//! Refused with an error: `dimension` other than 3 or 4, 64-bit integers and `block`, the `ascii`,
//! `hex` and `bzip2` encodings, `space directions` that are not along the world axes or `none`,
//! both `spacings` and `space directions`, `data file: LIST` and file-name patterns, a repeated field.

use super::{
    data_file_path, dims3, format_err, make_volume, open, skip_lines, spacing3, vec3, AxisSteps, DataSpec,
    Encoding, Files, HeaderLines, Layout, VolumeLimit, VoxelType,
};
use crate::{Orientation, PatientDir, Volume, VolumeError};
use glam::DVec3;
use std::collections::HashMap;
use std::io::BufRead;
use std::path::Path;

/// Reads the NRRD file (attached or detached header) at `path` within `limit` (all its time
/// steps together): the volume (a 4-D file's time steps stacked along z) and the number of time
/// steps.
pub(crate) fn read(path: &Path, limit: &VolumeLimit) -> Result<(Volume, usize), VolumeError> {
    let (r, file_len) = open(path)?;
    let mut lines = HeaderLines::new(r, path, "NRRD");
    let header = Header::read(path, &mut lines)?;
    let layout = Layout { dims: header.dims, voxel: header.voxel, big_endian: header.big_endian };
    layout
        .check_within(limit)
        .map_err(|e| format_err(path, format!("line {}: sizes: {e}", header.sizes_line)))?;

    let spec = match header.encoding {
        Encoding::Raw => DataSpec {
            encoding: Encoding::Raw,
            file_skip: u64::try_from(header.byte_skip).ok(),
            decoded_skip: 0,
        },
        // The header refuses byte skip -1 for compressed data.
        enc => DataSpec { encoding: enc, file_skip: Some(0), decoded_skip: header.byte_skip.max(0) as u64 },
    };
    let mut data = match &header.data_file {
        None => {
            if !header.blank_line {
                return Err(format_err(
                    path,
                    "the header ends without the blank line before the data and names no 'data file'",
                ));
            }
            let pos = lines.offset;
            let mut r = lines.into_inner();
            let files = Files::single(path);
            let pos = pos + skip_lines(files, &mut r, header.line_skip)?;
            super::read_data(files, r, pos, file_len, spec, &layout, None)?
        }
        Some(name) => {
            let data_path = data_file_path(path, "data file", name)?;
            let files = Files { header: path, data: &data_path };
            let (mut r, len) = open(&data_path)?;
            let pos = skip_lines(files, &mut r, header.line_skip)?;
            super::read_data(files, r, pos, len, spec, &layout, None)?
        }
    };

    let origin = header.origin.unwrap_or(DVec3::ZERO);
    let (spacing, origin) = match header.steps {
        Some(steps) => (steps.spacing(), steps.apply(origin, header.dims, &mut data)),
        None => (header.spacings.unwrap_or(DVec3::ONE), origin),
    };
    let volume = make_volume(path, header.dims, spacing, origin, data)?.with_orientation(header.orientation);
    Ok((volume, header.time_steps))
}

/// The number of time steps of the NRRD file at `path` (its header only).
pub(crate) fn time_steps(path: &Path) -> Result<usize, VolumeError> {
    let (r, _) = open(path)?;
    let mut lines = HeaderLines::new(r, path, "NRRD");
    Ok(Header::read(path, &mut lines)?.time_steps)
}

/// The patient orientation of the NRRD file at `path` (its header only), from `space`.
pub(crate) fn orientation(path: &Path) -> Result<Option<Orientation>, VolumeError> {
    let (r, _) = open(path)?;
    let mut lines = HeaderLines::new(r, path, "NRRD");
    Ok(Header::read(path, &mut lines)?.orientation)
}

/// Where the voxels of the NRRD file at `path` are, for partial reads; `None` where a `space
/// directions` mirrors an axis (such files are read whole).
pub(crate) fn plan(path: &Path) -> Result<Option<(super::FilePlan, DVec3, DVec3)>, VolumeError> {
    let limit = VolumeLimit::new(u64::MAX, "none while planning a partial read");
    let steps = step_file(path, &limit)?;
    if steps.mirror.is_some() {
        return Ok(None);
    }
    Ok(Some((steps.plan, steps.spacing, steps.origin)))
}

/// The NRRD file at `path` as time steps read one at a time ([`super::plan::StepFile`]; a 3-D
/// file is one step), its whole voxels within `limit`.
pub(crate) fn step_file(path: &Path, limit: &VolumeLimit) -> Result<super::plan::StepFile, VolumeError> {
    let (r, file_len) = open(path)?;
    let mut lines = HeaderLines::new(r, path, "NRRD");
    let header = Header::read(path, &mut lines)?;
    let layout = Layout { dims: header.dims, voxel: header.voxel, big_endian: header.big_endian };
    layout
        .check_within(limit)
        .map_err(|e| format_err(path, format!("line {}: sizes: {e}", header.sizes_line)))?;
    let mirror = header.steps.filter(|s| s.mirrors());
    let origin = header.origin.unwrap_or(DVec3::ZERO);
    let spacing = match &header.steps {
        Some(steps) => steps.spacing(),
        None => header.spacings.unwrap_or(DVec3::ONE),
    };
    let (data_path, pos, len) = match &header.data_file {
        None => {
            if !header.blank_line {
                return Err(format_err(
                    path,
                    "the header ends without the blank line before the data and names no 'data file'",
                ));
            }
            let pos = lines.offset;
            let mut r = lines.into_inner();
            let pos = pos + skip_lines(Files::single(path), &mut r, header.line_skip)?;
            (path.to_path_buf(), pos, file_len)
        }
        Some(name) => {
            let data_path = data_file_path(path, "data file", name)?;
            let files = Files { header: path, data: &data_path };
            let (mut r, len) = open(&data_path)?;
            let pos = skip_lines(files, &mut r, header.line_skip)?;
            (data_path, pos, len)
        }
    };
    let files = Files { header: path, data: &data_path };
    let (start, decoded_skip) = match header.encoding {
        Encoding::Raw => {
            let start = match u64::try_from(header.byte_skip) {
                Ok(skip) => pos.saturating_add(skip),
                Err(_) => pos.max(len.saturating_sub(layout.byte_len())),
            };
            super::check_raw_size(files, len, start, &layout)?;
            (start, 0)
        }
        _ => (pos, header.byte_skip.max(0) as u64),
    };
    let plan = super::FilePlan {
        header: path.to_path_buf(),
        data: data_path.clone(),
        layout,
        start,
        encoding: header.encoding,
        decoded_skip,
        trailing: false,
    };
    Ok(super::plan::StepFile::new(plan, header.time_steps, spacing, origin, None, mirror))
}

/// What Isowall takes from a NRRD header.
#[derive(Debug)]
struct Header {
    voxel: VoxelType,
    dims: [usize; 3],
    sizes_line: usize,
    big_endian: bool,
    encoding: Encoding,
    spacings: Option<DVec3>,
    steps: Option<AxisSteps>,
    origin: Option<DVec3>,
    data_file: Option<String>,
    line_skip: u64,
    /// `-1` (raw only: the voxels end the file) or the bytes to skip.
    byte_skip: i64,
    /// Whether the header ended with a blank line (rather than the end of the file).
    blank_line: bool,
    /// The 4th size of a 4-D file (1 otherwise); the steps are stacked along z in `dims`.
    time_steps: usize,
    /// The patient directions of the world axes, from `space`.
    orientation: Option<Orientation>,
}

/// Fields Isowall reads or knowingly ignores, with their alternative spellings.
const FIELDS: &[(&str, &[&str])] = &[
    ("type", &[]),
    ("dimension", &[]),
    ("sizes", &[]),
    ("endian", &[]),
    ("encoding", &[]),
    ("spacings", &[]),
    ("space directions", &[]),
    ("space origin", &[]),
    ("space dimension", &[]),
    ("space", &[]),
    ("data file", &["datafile"]),
    ("line skip", &["lineskip"]),
    ("byte skip", &["byteskip"]),
    // Ignored: they do not change where samples are or what they hold.
    ("content", &[]),
    ("number", &[]),
    ("block size", &["blocksize"]),
    ("min", &[]),
    ("max", &[]),
    ("old min", &["oldmin"]),
    ("old max", &["oldmax"]),
    ("axis mins", &["axismins"]),
    ("axis maxs", &["axismaxs"]),
    ("centers", &["centerings"]),
    ("labels", &[]),
    ("units", &[]),
    ("kinds", &[]),
    ("thicknesses", &[]),
    ("space units", &[]),
    ("measurement frame", &[]),
    ("sample units", &["sampleunits"]),
];

impl Header {
    fn read<R: BufRead>(path: &Path, lines: &mut HeaderLines<R>) -> Result<Header, VolumeError> {
        let err = |line: usize, what: String| format_err(path, format!("line {line}: {what}"));
        let magic = lines.next_line()?.unwrap_or_default();
        let version = magic.strip_prefix("NRRD000").and_then(|v| v.trim_end().parse::<u32>().ok());
        match version {
            Some(1..=5) => {}
            Some(v) => return Err(err(1, format!("NRRD version {v} is not supported (1 to 5 are)"))),
            None => {
                let shown: String = magic.chars().take(16).collect();
                return Err(err(1, format!("not a NRRD file: it starts with {shown:?}, not \"NRRD0004\"")));
            }
        }

        // Field name -> (line, value); `None` marks the end of the header by a blank line.
        let mut fields: HashMap<&'static str, (usize, String)> = HashMap::new();
        let mut blank_line = false;
        while let Some(line) = lines.next_line()? {
            let n = lines.line_no;
            if line.is_empty() {
                blank_line = true;
                break;
            }
            if line.starts_with('#') {
                continue;
            }
            if let Some((key, _)) = line.split_once(":=") {
                if !key.contains(": ") {
                    continue; // a key/value pair
                }
            }
            let Some((name, value)) = line.split_once(':') else {
                return Err(err(n, format!("expected 'field: value', got {line:?}")));
            };
            let name = name.trim().to_ascii_lowercase();
            let value = value.trim();
            match FIELDS.iter().find(|(f, alt)| *f == name || alt.contains(&name.as_str())) {
                Some((field, _)) => {
                    if let Some((first, _)) = fields.insert(field, (n, value.to_string())) {
                        return Err(err(n, format!("'{field}' is given again (first in line {first})")));
                    }
                }
                None => tracing::warn!("{}: line {n}: ignoring unknown NRRD field '{name}'", path.display()),
            }
        }

        let get = |f: &str| fields.get(f).map(|(n, v)| (*n, v.as_str()));
        let required =
            |f: &str| get(f).ok_or_else(|| format_err(path, format!("missing required field '{f}'")));

        let (n, t) = required("type")?;
        let voxel = voxel_type(t).map_err(|e| err(n, e))?;
        let (n, d) = required("dimension")?;
        let rank = match d.parse::<usize>() {
            Ok(r @ (3 | 4)) => r,
            Ok(d) => {
                return Err(err(
                    n,
                    format!(
                    "dimension is {d}; Isowall reads 3-dimensional volumes and 4-dimensional series of them"
                ),
                ))
            }
            Err(_) => return Err(err(n, format!("dimension: '{d}' is not a whole number"))),
        };
        // A 4-D file is a series of 3-D time steps (its last axis, the slowest): its per-axis
        // fields have a fourth entry, which is set aside here.
        let (sizes_line, s) = required("sizes")?;
        let (s, t) = split_fourth(s, rank);
        let dims = dims3("sizes", s).map_err(|e| err(sizes_line, e))?;
        let time_steps = match t {
            None => 1,
            Some(t) => match t.parse::<usize>() {
                Ok(t) if t >= 1 => t,
                _ => {
                    return Err(err(
                        sizes_line,
                        format!("sizes: the time steps '{t}' are not a whole number >= 1"),
                    ))
                }
            },
        };
        // Time steps are stacked along z: the file's voxels are one volume of nz * nt slices.
        let dims = [dims[0], dims[1], dims[2].saturating_mul(time_steps)];
        let (n, e) = required("encoding")?;
        let encoding = match e.to_ascii_lowercase().as_str() {
            "raw" => Encoding::Raw,
            "gzip" | "gz" => Encoding::Gzip,
            "ascii" | "text" | "txt" | "hex" | "bzip2" | "bz2" => {
                return Err(err(n, format!("encoding '{e}' is not supported (raw and gzip are)")))
            }
            _ => return Err(err(n, format!("unknown encoding '{e}' (raw and gzip are supported)"))),
        };
        let big_endian = match get("endian") {
            Some((_, e)) if e.eq_ignore_ascii_case("little") => false,
            Some((_, e)) if e.eq_ignore_ascii_case("big") => true,
            Some((n, e)) => return Err(err(n, format!("endian: '{e}' is neither 'little' nor 'big'"))),
            None if voxel.size() == 1 => false,
            None => {
                return Err(format_err(
                    path,
                    format!("missing field 'endian', required for {}-byte voxels", voxel.size()),
                ))
            }
        };

        let spacings = match get("spacings") {
            Some((n, s)) => Some(spacing3("spacings", split_fourth(s, rank).0).map_err(|e| err(n, e))?),
            None => None,
        };
        if let Some((n, sd)) = get("space dimension") {
            if sd.parse::<usize>() != Ok(3) {
                return Err(err(n, format!("space dimension is {sd}; Isowall needs a 3-dimensional space")));
            }
        }
        let steps = match get("space directions") {
            Some((n, _)) if spacings.is_some() => {
                return Err(err(
                    n,
                    "both 'spacings' and 'space directions' are given; NRRD allows only one".into(),
                ))
            }
            Some((n, sd)) => {
                let sd = if rank == 4 { sd.trim_end().strip_suffix("none").unwrap_or(sd) } else { sd };
                let steps = space_directions(sd).map_err(|e| err(n, e))?;
                if time_steps > 1 && steps.mirrors_z() {
                    return Err(err(
                        n,
                        "space directions: a negative z step in a 4-D series is not supported".into(),
                    ));
                }
                Some(steps)
            }
            None => None,
        };
        if spacings.is_none() && steps.is_none() {
            tracing::warn!("{}: no 'spacings' or 'space directions': assuming spacing 1", path.display());
        }
        let orientation = match get("space") {
            Some((n, name)) => space_orientation(name).map_err(|e| err(n, e))?,
            None => None,
        };
        let origin = match get("space origin") {
            Some((n, o)) => Some(vector(o).and_then(|v| vec3("space origin", &v)).map_err(|e| err(n, e))?),
            None => None,
        };

        let data_file = match get("data file") {
            Some((n, f)) => {
                let tokens: Vec<&str> = f.split_whitespace().collect();
                if tokens.first() == Some(&"LIST") {
                    return Err(err(n, "data file: LIST (several data files) is not supported".into()));
                }
                if tokens.len() >= 4 && tokens[0].contains('%') {
                    return Err(err(n, format!("data file: the file name pattern '{f}' is not supported")));
                }
                if f.is_empty() {
                    return Err(err(n, "data file: no file name".into()));
                }
                Some(f.to_string())
            }
            None => None,
        };
        let line_skip = match get("line skip") {
            Some((n, s)) => {
                s.parse::<u64>().map_err(|_| err(n, format!("line skip: '{s}' is not a whole number")))?
            }
            None => 0,
        };
        let byte_skip = match get("byte skip") {
            Some((n, s)) => match s.parse::<i64>() {
                Ok(-1) if encoding != Encoding::Raw => {
                    return Err(err(n, "byte skip: -1 is only allowed with raw encoding".into()))
                }
                Ok(b) if b >= -1 => b,
                _ => return Err(err(n, format!("byte skip: '{s}' is neither -1 nor a whole number"))),
            },
            None => 0,
        };

        Ok(Header {
            voxel,
            dims,
            sizes_line,
            big_endian,
            encoding,
            spacings,
            steps,
            origin,
            data_file,
            line_skip,
            byte_skip,
            blank_line,
            time_steps,
            orientation,
        })
    }
}

/// A per-axis field's first three entries and, in a 4-D header, the fourth.
fn split_fourth(value: &str, rank: usize) -> (&str, Option<&str>) {
    if rank != 4 {
        return (value, None);
    }
    let v = value.trim_end();
    match v.rfind(|c: char| c.is_whitespace()) {
        Some(i) => (&v[..i], Some(v[i..].trim())),
        None => (v, None),
    }
}

/// The voxel type a NRRD `type` names (any of NRRD's spellings, case-insensitive).
fn voxel_type(t: &str) -> Result<VoxelType, String> {
    let name = t.split_whitespace().collect::<Vec<_>>().join(" ").to_ascii_lowercase();
    Ok(match name.as_str() {
        "signed char" | "char" | "int8" | "int8_t" => VoxelType::I8,
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => VoxelType::U8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => VoxelType::I16,
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => VoxelType::U16,
        "int" | "signed int" | "int32" | "int32_t" => VoxelType::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => VoxelType::U32,
        "float" => VoxelType::F32,
        "double" => VoxelType::F64,
        "longlong"
        | "long long"
        | "long long int"
        | "signed long long"
        | "signed long long int"
        | "int64"
        | "int64_t"
        | "ulonglong"
        | "unsigned long long"
        | "unsigned long long int"
        | "uint64"
        | "uint64_t" => {
            return Err(format!(
                "type '{t}': 64-bit integer voxels are not supported (convert to int32 or float)"
            ))
        }
        "block" => return Err("type 'block' is not supported".into()),
        _ => return Err(format!("unknown type '{t}'")),
    })
}

/// The inside of one `(x,y,z)` vector, or an error naming what was found instead.
fn vector(s: &str) -> Result<String, String> {
    let s = s.trim();
    match s.strip_prefix('(').and_then(|s| s.strip_suffix(')')) {
        Some(inner) if !inner.contains(['(', ')']) => Ok(inner.to_string()),
        _ => Err(format!("expected a vector '(x,y,z)', got '{s}'")),
    }
}

/// `space`: the patient directions of the space's axes, which are the world axes (`space
/// directions` must lie along them, a negative one mirrors the data, so +x, +y, +z stay the
/// space's). `None` for the spaces without anatomy (`scanner-xyz`, `3D-right-handed`,
/// `3D-left-handed`); a `-time` space's first three axes are its spatial ones.
fn space_orientation(value: &str) -> Result<Option<Orientation>, String> {
    use PatientDir::*;
    let name = value.trim().to_ascii_lowercase();
    let spatial = name.strip_suffix("-time").unwrap_or(&name);
    let axes = match spatial {
        "right-anterior-superior" | "ras" | "rast" => [Right, Anterior, Superior],
        "left-anterior-superior" | "las" | "last" => [Left, Anterior, Superior],
        "left-posterior-superior" | "lps" | "lpst" => [Left, Posterior, Superior],
        "scanner-xyz" | "3d-right-handed" | "3d-left-handed" => return Ok(None),
        _ => {
            return Err(format!(
                "space: '{value}' is not a NRRD space (right-anterior-superior, left-anterior-superior, \
                 left-posterior-superior, their -time forms, RAS, LAS, LPS, RAST, LAST, LPST, scanner-xyz, \
                 3D-right-handed, 3D-left-handed)"
            ))
        }
    };
    Ok(Orientation::new(axes))
}

/// `space directions`: three vectors `(x,y,z)`, each along its own world axis.
fn space_directions(value: &str) -> Result<AxisSteps, String> {
    let mut steps = Vec::new();
    let mut rest = value.trim();
    while !rest.is_empty() {
        if rest.starts_with("none") {
            return Err(format!(
                "space directions: axis {} is 'none' (not spatial); Isowall needs three spatial axes",
                steps.len()
            ));
        }
        let Some(end) = rest.find(')') else {
            return Err(format!("space directions: expected vectors '(x,y,z)', got '{rest}'"));
        };
        let inner = vector(&rest[..=end]).map_err(|e| format!("space directions: {e}"))?;
        steps.push(vec3("space directions", &inner).map_err(|_| {
            format!(
                "space directions: '{}' is not three finite numbers (Isowall needs a 3-D space)",
                &rest[..=end]
            )
        })?);
        rest = rest[end + 1..].trim_start();
    }
    if steps.len() != 3 {
        return Err(format!("space directions: expected 3 vectors, got {}", steps.len()));
    }
    AxisSteps::new("space directions", [steps[0], steps[1], steps[2]])
}

#[cfg(test)]
mod tests {
    use super::super::load;
    use super::super::testutil::{check, encode, gzip, shared_file, values, ALL_TYPES};
    use super::*;
    use std::fs;

    const DIMS: [usize; 3] = [4, 3, 2];

    /// NRRD names for each type: Isowall must read all of them.
    fn type_names(voxel: VoxelType) -> &'static [&'static str] {
        match voxel {
            VoxelType::U8 => &["uchar", "unsigned char", "uint8", "uint8_t"],
            VoxelType::I8 => &["signed char", "char", "int8", "int8_t"],
            VoxelType::U16 => &["ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"],
            VoxelType::I16 => &["short", "short int", "signed short", "signed short int", "int16", "int16_t"],
            VoxelType::U32 => &["uint", "unsigned int", "uint32", "uint32_t"],
            VoxelType::I32 => &["int", "signed int", "int32", "int32_t"],
            VoxelType::F32 => &["float"],
            VoxelType::F64 => &["double"],
        }
    }

    fn header(type_name: &str, big: bool, encoding: &str, extra: &str) -> String {
        let endian = if big { "big" } else { "little" };
        format!(
            "NRRD0004\n# a comment\ntype: {type_name}\ndimension: 3\nsizes: 4 3 2\nendian: {endian}\n\
             encoding: {encoding}\nspacings: 0.5 1 2\nkey:=value: ignored\n{extra}"
        )
    }

    fn write(path: &Path, header: &str, data: &[u8]) {
        let mut bytes = header.as_bytes().to_vec();
        bytes.extend_from_slice(data);
        fs::write(path, bytes).unwrap();
    }

    #[test]
    fn four_dimensional_files_are_time_steps() {
        let dir = tempfile::tempdir().unwrap();
        let vals = values(VoxelType::I16, 48);
        let raw = encode(&vals, VoxelType::I16, false);
        let four = |encoding: &str, geometry: &str| {
            format!(
                "NRRD0004\ntype: short\ndimension: 4\nsizes: 4 3 2 2\nendian: little\nencoding: {encoding}\n\
                 {geometry}\nspace origin: (1,2,3)\nkinds: domain domain domain time\n\n"
            )
        };
        let spacing = DVec3::new(0.5, 1.0, 2.0);
        for (name, enc, data) in [("r.nrrd", "raw", raw.clone()), ("g.nrrd", "gzip", gzip(&raw))] {
            for geometry in ["spacings: 0.5 1 2 nan", "space directions: (0.5,0,0) (0,1,0) (0,0,2) none"] {
                let p = dir.path().join(name);
                let text = four(enc, geometry);
                let text = if geometry.starts_with("spacings") {
                    text.replace("space origin: (1,2,3)\n", "")
                } else {
                    text
                };
                write(&p, &text, &data);
                let origin =
                    if geometry.starts_with("spacings") { DVec3::ZERO } else { DVec3::new(1.0, 2.0, 3.0) };
                assert_eq!(super::super::time_steps(&p).unwrap(), 2);
                check(&load(&p, None).unwrap(), [4, 3, 2], spacing, origin, &vals[..24]);
                check(
                    &super::super::load_step(&p, None, 1).unwrap(),
                    [4, 3, 2],
                    spacing,
                    origin,
                    &vals[24..],
                );
            }
        }
        // One step short.
        let p = dir.path().join("short.nrrd");
        write(&p, &four("raw", "spacings: 0.5 1 2 nan"), &raw[..24 * 2]);
        let e = load(&p, None).unwrap_err().to_string();
        assert!(e.contains("data is truncated"), "{e}");
        // Object space reads a step's slices alone: step 1 of the 4-D file is its second half.
        let p = dir.path().join("r.nrrd");
        let s = crate::VolumeSource::File(p).stream_step(None, 1).unwrap();
        assert_eq!(s.info().dims, [4, 3, 2]);
        let whole = crate::VoxelRange::whole([4, 3, 2]);
        check(&s.read_region(&whole).unwrap(), [4, 3, 2], spacing, DVec3::new(1.0, 2.0, 3.0), &vals[24..]);
    }

    #[test]
    fn attached_and_detached_raw_and_gzip_of_every_type_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let spacing = DVec3::new(0.5, 1.0, 2.0);
        for voxel in ALL_TYPES {
            for (t, &name) in type_names(voxel).iter().enumerate() {
                let big = t % 2 == 1;
                let vals = values(voxel, 24);
                let raw = encode(&vals, voxel, big);
                let stem = format!("{}-{t}", voxel.name());
                // Attached, raw and gzip.
                let p = dir.path().join(format!("{stem}.nrrd"));
                write(&p, &header(name, big, "raw", "\n"), &raw);
                check(&load(&p, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
                write(&p, &header(name, big, "gzip", "\n"), &gzip(&raw));
                check(&load(&p, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
                // Detached: raw and "gz" data files, the header ending at the end of the file.
                let h = dir.path().join(format!("{stem}.nhdr"));
                fs::write(dir.path().join(format!("{stem}.raw")), &raw).unwrap();
                write(&h, &header(name, big, "raw", &format!("data file: {stem}.raw\n")), &[]);
                check(&load(&h, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
                fs::write(dir.path().join(format!("{stem}.raw.gz")), gzip(&raw)).unwrap();
                write(&h, &header(name, big, "gz", &format!("datafile: ./{stem}.raw.gz\n\n")), &[]);
                check(&load(&h, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
            }
        }
    }

    #[test]
    fn skips_crlf_and_detached_data_beside_the_header() {
        let dir = tempfile::tempdir().unwrap();
        let vals = values(VoxelType::I16, 24);
        let raw = encode(&vals, VoxelType::I16, false);
        let spacing = DVec3::new(0.5, 1.0, 2.0);
        let p = dir.path().join("skip.nrrd");
        // byte skip N (raw): N bytes of junk before the voxels.
        write(&p, &header("short", false, "raw", "byte skip: 5\n\n"), &[[9u8; 5].as_slice(), &raw].concat());
        check(&load(&p, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
        // byte skip -1: the voxels are the last bytes, whatever comes before.
        write(
            &p,
            &header("short", false, "raw", "byte skip: -1\n\n"),
            &[[9u8; 77].as_slice(), &raw].concat(),
        );
        check(&load(&p, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
        // byte skip with gzip counts decompressed bytes.
        let skipped = gzip(&[[7u8; 3].as_slice(), &raw].concat());
        write(&p, &header("short", false, "gzip", "byte skip: 3\n\n"), &skipped);
        check(&load(&p, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
        // line skip, then byte skip, in a detached file in a folder beside the header.
        fs::create_dir(dir.path().join("sub")).unwrap();
        let d = dir.path().join("sub/data with lines.bin");
        fs::write(&d, [b"first line\nsecond\n".as_slice(), b"xy", &raw].concat()).unwrap();
        let h = dir.path().join("lines.nhdr");
        let fields = "line skip: 2\nbyte skip: 2\ndata file: ./sub/data with lines.bin\n";
        write(&h, &header("short", false, "raw", fields), &[]);
        check(&load(&h, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
        // The same file by its absolute path, or from above the header's folder, is refused,
        // and its size is not told.
        let inner = dir.path().join("sub/up.nhdr");
        for (header_path, name) in
            [(&h, d.display().to_string()), (&inner, "../sub/data with lines.bin".into())]
        {
            write(header_path, &header("short", false, "raw", &format!("data file: {name}\n")), &[]);
            let m = load(header_path, None).unwrap_err().to_string();
            assert!(m.contains("is not a file in the header's folder"), "{m}");
            assert!(!m.contains("bytes"), "{m}");
        }
        // A data file named inside the folder that is a link out of it (or a link to a folder
        // out of it) is refused too, links resolved first; a link that stays inside is read.
        let outside = tempfile::tempdir().unwrap();
        let secret = outside.path().join("secret.bin");
        fs::write(&secret, &raw).unwrap();
        std::os::unix::fs::symlink(&secret, dir.path().join("link.bin")).unwrap();
        std::os::unix::fs::symlink(outside.path(), dir.path().join("away")).unwrap();
        for name in ["link.bin", "away/secret.bin"] {
            write(&h, &header("short", false, "raw", &format!("data file: {name}\n")), &[]);
            let m = load(&h, None).unwrap_err().to_string();
            assert!(m.contains(&format!("data file: '{name}' is a link to")), "{m}");
            assert!(m.contains("outside the header's folder"), "{m}");
        }
        std::os::unix::fs::symlink(&d, dir.path().join("inside.bin")).unwrap();
        let fields = "line skip: 2\nbyte skip: 2\ndata file: inside.bin\n";
        write(&h, &header("short", false, "raw", fields), &[]);
        check(&load(&h, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
        // CRLF line endings.
        let crlf = header("short", false, "raw", "\n").replace('\n', "\r\n");
        write(&p, &crlf, &raw);
        check(&load(&p, None).unwrap(), DIMS, spacing, DVec3::ZERO, &vals);
    }

    #[test]
    fn space_names_the_patient_directions_of_the_world_axes() {
        let dir = tempfile::tempdir().unwrap();
        let vals: Vec<f64> = (0..24).map(|v| v as f64).collect();
        let raw = encode(&vals, VoxelType::F32, false);
        let p = dir.path().join("oriented.nrrd");
        let with = |space: &str, geometry: &str| {
            format!(
                "NRRD0005\ntype: float\ndimension: 3\nspace: {space}\nsizes: 4 3 2\n{geometry}\n\
                 endian: little\nencoding: raw\n\n"
            )
        };
        let axial = "space directions: (0.5,0,0) (0,1,0) (0,0,2)";
        // A mirrored direction keeps the world axes the space's: the orientation is the space's.
        let mirrored = "space directions: (-0.5,0,0) (0,1,0) (0,0,-2)";
        for (space, geometry, code) in [
            ("left-posterior-superior", axial, Some("LPS")),
            ("LPS", mirrored, Some("LPS")),
            ("right-anterior-superior", axial, Some("RAS")),
            ("RAS", "spacings: 1 1 1", Some("RAS")),
            ("left-anterior-superior", mirrored, Some("LAS")),
            ("scanner-xyz", axial, None),
            ("3D-right-handed", axial, None),
        ] {
            write(&p, &with(space, geometry), &raw);
            let v = load(&p, None).unwrap();
            assert_eq!(v.orientation().map(|o| o.code()).as_deref(), code, "space {space}");
        }
        write(&p, &header("float", false, "raw", "\n"), &raw);
        assert_eq!(load(&p, None).unwrap().orientation(), None, "no space, no orientation");
        let m = error_of(dir.path(), "bogus.nrrd", &with("sideways", axial), &raw);
        assert!(
            m.contains("bogus.nrrd") && m.contains("line 4: space: 'sideways' is not a NRRD space"),
            "{m}"
        );
        // A voxel no camera can frame is refused by the field that gives it.
        for (geometry, field) in [
            ("space directions: (1e300,0,0) (0,1,0) (0,0,2)", "line 6: space directions: a voxel of 1e300"),
            ("space directions: (1e-40,0,0) (0,1,0) (0,0,2)", "line 6: space directions: a voxel of 1e-40"),
            ("spacings: 1 1e300 1", "line 6: spacings: a voxel of 1.0 x 1e300"),
        ] {
            let m = error_of(dir.path(), "far.nrrd", &with("RAS", geometry), &raw);
            assert!(m.contains("far.nrrd") && m.contains(field) && !m.contains("camera"), "{m}");
        }
    }

    #[test]
    fn space_directions_and_origin_place_every_sample() {
        let dir = tempfile::tempdir().unwrap();
        let vals: Vec<f64> = (0..24).map(|v| v as f64).collect();
        let raw = encode(&vals, VoxelType::F32, false);
        let p = dir.path().join("space.nrrd");
        let text = "NRRD0005\ntype: float\ndimension: 3\nspace: left-posterior-superior\nsizes: 4 3 2\n\
                    space directions: (0.5,0,0) (0, 1, 0) (0,0,2)\nspace origin: (10,-20,30.5)\nendian: little\n\
                    encoding: raw\n\n";
        write(&p, text, &raw);
        check(
            &load(&p, None).unwrap(),
            DIMS,
            DVec3::new(0.5, 1.0, 2.0),
            DVec3::new(10.0, -20.0, 30.5),
            &vals,
        );

        // Negative directions: the data is mirrored, every sample keeps its world position.
        let (o, d) = (
            DVec3::new(10.0, -20.0, 30.5),
            [DVec3::new(-0.5, 0.0, 0.0), DVec3::Y, DVec3::new(0.0, 0.0, -2.0)],
        );
        let text = "NRRD0004\ntype: float\ndimension: 3\nsizes: 4 3 2\n\
                    space directions: (-0.5,0,0) (0,1,0) (0,0,-2)\nspace origin: (10,-20,30.5)\nendian: little\n\
                    encoding: raw\n\n";
        write(&p, text, &raw);
        let v = load(&p, None).unwrap();
        assert_eq!(v.spacing(), DVec3::new(0.5, 1.0, 2.0));
        for k in 0..2 {
            for j in 0..3 {
                for i in 0..4 {
                    let world = o + d[0] * i as f64 + d[1] * j as f64 + d[2] * k as f64;
                    let want = vals[i + 4 * (j + 3 * k)];
                    assert_eq!(v.sample(world), Some(want), "sample ({i},{j},{k}) at {world}");
                }
            }
        }
    }

    fn error_of(dir: &Path, name: &str, header: &str, data: &[u8]) -> String {
        let p = dir.join(name);
        write(&p, header, data);
        let e = load(&p, None).unwrap_err();
        let m = e.to_string();
        assert!(m.starts_with(&p.display().to_string()), "{m}");
        m
    }

    #[test]
    fn broken_headers_say_which_line_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let raw = [0u8; 24];
        let m = error_of(d, "t.nrrd", &header("flaot", false, "raw", "\n"), &raw);
        assert!(m.contains("line 3: unknown type 'flaot'"), "{m}");
        let m = error_of(d, "t.nrrd", &header("int64", false, "raw", "\n"), &raw);
        assert!(m.contains("64-bit"), "{m}");
        let m =
            error_of(d, "t.nrrd", &header("uchar", false, "raw", "\n").replace("sizes: 4 3 2\n", ""), &raw);
        assert!(m.contains("missing required field 'sizes'"), "{m}");
        let m = error_of(d, "t.nrrd", &header("uchar", false, "raw", "\n").replace("4 3 2", "4 3"), &raw);
        assert!(m.contains("line 5: sizes: expected 3 numbers, got 2"), "{m}");
        let m = error_of(d, "t.nrrd", &header("uchar", false, "raw", "\n").replace("4 3 2", "4 x 2"), &raw);
        assert!(m.contains("sizes: 'x' is not a whole number"), "{m}");
        let m =
            error_of(d, "t.nrrd", &header("uchar", false, "raw", "\n").replace("0.5 1 2", "0.5 1 nan"), &raw);
        assert!(m.contains("spacings"), "{m}");
        let m = error_of(
            d,
            "t.nrrd",
            &header("uchar", false, "raw", "\n").replace("dimension: 3", "dimension: 5"),
            &raw,
        );
        assert!(m.contains("dimension is 5"), "{m}");
        let m =
            error_of(d, "t.nrrd", &header("short", false, "raw", "\n").replace("endian: little\n", ""), &raw);
        assert!(m.contains("'endian'"), "{m}");
        let m = error_of(d, "t.nrrd", &header("uchar", false, "bzip2", "\n"), &raw);
        assert!(m.contains("encoding 'bzip2' is not supported"), "{m}");
        let m = error_of(d, "t.nrrd", &header("uchar", false, "gzip", "byte skip: -1\n\n"), &raw);
        assert!(m.contains("byte skip: -1 is only allowed with raw"), "{m}");
        let m = error_of(d, "t.nrrd", &header("uchar", false, "raw", "sizes: 4 3 2\n\n"), &raw);
        assert!(m.contains("'sizes' is given again"), "{m}");
        let m = error_of(d, "t.nrrd", "P5\n4 3\n255\n", &raw);
        assert!(m.contains("not a NRRD file"), "{m}");
        let m = error_of(d, "t.nrrd", &header("uchar", false, "raw", ""), &[]);
        assert!(m.contains("without the blank line"), "{m}");
        let m = error_of(d, "t.nrrd", &header("uchar", false, "raw", "data file: LIST\n\n"), &[]);
        assert!(m.contains("LIST"), "{m}");
    }

    #[test]
    fn non_axis_aligned_or_none_directions_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let base = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 3 2\nencoding: raw\n";
        let m = error_of(
            dir.path(),
            "d.nrrd",
            &format!("{base}space directions: (1,0,0) (0,0.7,0.7) (0,0,1)\n\n"),
            &[0; 24],
        );
        assert!(m.contains("line 6: space directions: axis 1 steps by (0, 0.7, 0.7)"), "{m}");
        assert!(m.contains("axis-aligned"), "{m}");
        let m = error_of(
            dir.path(),
            "d.nrrd",
            &format!("{base}space directions: (0,1,0) (1,0,0) (0,0,1)\n\n"),
            &[0; 24],
        );
        assert!(m.contains("axis 0"), "{m}");
        let m = error_of(
            dir.path(),
            "d.nrrd",
            &format!("{base}space directions: none (0,1,0) (0,0,1)\n\n"),
            &[0; 24],
        );
        assert!(m.contains("'none'"), "{m}");
        let m = error_of(
            dir.path(),
            "d.nrrd",
            &format!("{base}space directions: (1,0) (0,1) (0,0)\n\n"),
            &[0; 24],
        );
        assert!(m.contains("3-D space"), "{m}");
        let m = error_of(
            dir.path(),
            "d.nrrd",
            &format!("{base}spacings: 1 1 1\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n\n"),
            &[0; 24],
        );
        assert!(m.contains("only one"), "{m}");
    }

    #[test]
    fn bad_data_is_refused_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let raw = encode(&values(VoxelType::I16, 24), VoxelType::I16, false);
        let m = error_of(d, "t.nrrd", &header("short", false, "raw", "\n"), &raw[..40]);
        assert!(m.contains("data is truncated: 40 bytes"), "{m}");
        assert!(m.contains("4x3x2 int16 needs 48"), "{m}");
        let m =
            error_of(d, "t.nrrd", &header("short", false, "raw", "\n"), &[raw.as_slice(), &[0; 6]].concat());
        assert!(m.contains("extra data: file has 6 bytes more"), "{m}");
        let m = error_of(d, "t.nrrd", &header("short", false, "gzip", "\n"), &gzip(&raw[..40]));
        assert!(m.contains("truncated") && m.contains("decompresses to 40 bytes"), "{m}");
        let m = error_of(
            d,
            "t.nrrd",
            &header("short", false, "gzip", "\n"),
            &gzip(&[raw.as_slice(), &[0]].concat()),
        );
        assert!(m.contains("extra data"), "{m}");
        let m = error_of(
            d,
            "t.nrrd",
            &header("short", false, "gzip", "\n"),
            b"this is not gzip at all, not at all",
        );
        assert!(m.contains("gzip data is corrupt"), "{m}");
        // A valid gzip header, then a deflate block of the reserved type 3.
        let mut bad = gzip(&raw);
        bad[10..].fill(0xFF);
        let m = error_of(d, "t.nrrd", &header("short", false, "gzip", "\n"), &bad);
        assert!(m.contains("gzip data is corrupt"), "{m}");
        let mut cut = gzip(&raw);
        cut.truncate(cut.len() / 2);
        let m = error_of(d, "t.nrrd", &header("short", false, "gzip", "\n"), &cut);
        assert!(m.contains("corrupt") || m.contains("truncated"), "{m}");
        // A gzip bomb: 10 MB of zeros for a 24-byte volume is refused after reading 49 bytes.
        let m = error_of(d, "t.nrrd", &header("short", false, "gzip", "\n"), &gzip(&vec![0; 10_000_000]));
        assert!(m.contains("extra data"), "{m}");
        // A huge volume claimed by a tiny file is refused without allocating it: over the limit
        // from its header, or (within the limit) at the end of the data really there.
        let m = error_of(
            d,
            "t.nrrd",
            &header("short", false, "gzip", "\n").replace("4 3 2", "1024 1024 1000"),
            &gzip(&raw),
        );
        assert!(
            m.contains("line 5: sizes: 1024x1024x1000 int16 is 4194304000 bytes as float32, over the limit"),
            "{m}"
        );
        let m = error_of(
            d,
            "t.nrrd",
            &header("short", false, "gzip", "\n").replace("4 3 2", "1024 1024 500"),
            &gzip(&raw),
        );
        assert!(m.contains("truncated"), "{m}");
        let m = error_of(
            d,
            "t.nrrd",
            &header("short", false, "gzip", "\n").replace("4 3 2", "2048 2048 2048"),
            &gzip(&raw),
        );
        assert!(m.contains("line 5: sizes:") && m.contains("limit"), "{m}");
    }

    #[test]
    fn nan_voxels_and_missing_data_files_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut vals = values(VoxelType::F32, 24);
        vals[5] = f64::NAN;
        let p = dir.path().join("nan.nrrd");
        write(&p, &header("float", false, "gzip", "\n"), &gzip(&encode(&vals, VoxelType::F32, false)));
        let e = load(&p, None).unwrap_err();
        assert!(matches!(e, VolumeError::NonFinite { i: 1, j: 1, k: 0, .. }), "{e}");
        assert!(e.to_string().starts_with(&p.display().to_string()), "{e}");

        let h = dir.path().join("gone.nhdr");
        write(&h, &header("float", false, "raw", "data file: gone.raw\n"), &[]);
        let e = load(&h, None).unwrap_err();
        assert!(matches!(&e, VolumeError::Io { path, .. } if path == &dir.path().join("gone.raw")), "{e}");
        // Errors in a detached data file name both files.
        fs::write(dir.path().join("gone.raw"), [0u8; 10]).unwrap();
        let m = load(&h, None).unwrap_err().to_string();
        assert!(m.starts_with(&h.display().to_string()) && m.contains("gone.raw: data is truncated"), "{m}");
    }

    const SHARED: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared/");

    #[test]
    fn reads_the_shared_ct_and_mri_scans() {
        if let Some(p) = shared_file(&format!("{SHARED}data/ct-cranium.nrrd")) {
            let v = load(&p, None).unwrap();
            assert_eq!(v.dims(), [256, 256, 108]);
            assert!((v.spacing() - DVec3::new(0.9570312, 0.9570312, 1.5)).abs().max_element() < 1e-9);
            assert_eq!(v.origin(), DVec3::ZERO);
            // The header's space: it opens on the face.
            assert_eq!(v.orientation().map(|o| o.code()).as_deref(), Some("RAS"));
            // The header's comment: Hounsfield units, -1024..2986.
            let (lo, hi) = v.value_range();
            assert!(lo >= -1024.0 && hi <= 2986.0 && hi > 300.0, "{lo}..{hi}");
            assert!(v.data().iter().all(|x| x.fract() == 0.0));
        }
        if let Some(p) = shared_file(&format!("{SHARED}data/mri-brainsmall.nrrd")) {
            let v = load(&p, None).unwrap();
            assert_eq!(v.dims(), [128, 128, 84]);
            assert_eq!(v.spacing(), DVec3::ONE);
            // The header's comment: values 0..202.
            let (lo, hi) = v.value_range();
            assert!(lo >= 0.0 && hi <= 202.0 && hi > 40.0, "{lo}..{hi}");
        }
    }

    #[test]
    fn reads_the_sphere32_convention_volume() {
        let Some(p) = shared_file(&format!("{SHARED}conventions/sphere32.nrrd")) else {
            return;
        };
        let v = load(&p, None).unwrap();
        assert_eq!(v.dims(), [32, 32, 32]);
        assert_eq!(v.spacing(), DVec3::ONE);
        let centre = DVec3::new(15.5, 14.0, 16.0);
        for (i, j, k) in [
            (0, 0, 0),
            (31, 0, 0),
            (0, 31, 0),
            (0, 0, 31),
            (15, 14, 16),
            (16, 14, 16),
            (3, 20, 29),
            (31, 31, 31),
        ] {
            let want = 10.0 - (DVec3::new(i as f64, j as f64, k as f64) - centre).length();
            assert!((v.at(i, j, k) as f64 - want).abs() < 1e-5, "({i},{j},{k}): {} vs {want}", v.at(i, j, k));
        }
    }
}
