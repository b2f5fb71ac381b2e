//! Text headers (NRRD, MetaImage): reading them line by line within a size limit, parsing their
//! number fields, and the axis-aligned grid their per-axis steps describe (mirrored where a step
//! is negative).

use super::{format_err, io_err};
use crate::VolumeError;
use glam::DVec3;
use std::io::{BufRead, Read};
use std::path::Path;

/// The longest text header (NRRD, MetaImage) read before giving up on finding its end.
const HEADER_LIMIT: u64 = 1 << 20;
/// Reads a text header (NRRD, MetaImage) line by line, keeping count of the bytes read, so the
/// data's offset is known when the header ends, and refusing headers longer than 1 MiB.
pub(crate) struct HeaderLines<'a, R> {
    r: R,
    path: &'a Path,
    format: &'static str,
    /// Bytes read so far: where the next line (or the attached data) begins.
    pub offset: u64,
    /// The number of the last line read (1-based).
    pub line_no: usize,
}

impl<'a, R: BufRead> HeaderLines<'a, R> {
    pub fn new(r: R, path: &'a Path, format: &'static str) -> Self {
        HeaderLines { r, path, format, offset: 0, line_no: 0 }
    }

    /// The next line without its line ending (`\n` or `\r\n`), or `None` at the end of the file.
    pub fn next_line(&mut self) -> Result<Option<String>, VolumeError> {
        let left = HEADER_LIMIT.saturating_sub(self.offset);
        let mut buf = Vec::new();
        let n = (&mut self.r).take(left).read_until(b'\n', &mut buf).map_err(|e| io_err(self.path, e))?;
        if n == 0 && left > 0 {
            return Ok(None);
        }
        if !buf.ends_with(b"\n") && n as u64 == left {
            return Err(format_err(
                self.path,
                format!(
                    "the header does not end within its first {HEADER_LIMIT} bytes: is this a {} file?",
                    self.format
                ),
            ));
        }
        self.offset += n as u64;
        self.line_no += 1;
        if buf.ends_with(b"\n") {
            buf.pop();
        }
        if buf.ends_with(b"\r") {
            buf.pop();
        }
        Ok(Some(String::from_utf8_lossy(&buf).into_owned()))
    }

    /// The reader, positioned just after the last line read.
    pub fn into_inner(self) -> R {
        self.r
    }
}

/// Parses exactly `n` numbers separated by whitespace (or commas) from a header field.
pub(crate) fn numbers<T: std::str::FromStr>(
    field: &str,
    value: &str,
    n: usize,
    noun: &str,
) -> Result<Vec<T>, String> {
    let tokens: Vec<&str> =
        value.split(|c: char| c.is_whitespace() || c == ',').filter(|t| !t.is_empty()).collect();
    if tokens.len() != n {
        return Err(format!("{field}: expected {n} numbers, got {}", tokens.len()));
    }
    tokens.iter().map(|t| t.parse().map_err(|_| format!("{field}: '{t}' is not a {noun}"))).collect()
}

/// Three sizes, each at least 1.
pub(crate) fn dims3(field: &str, value: &str) -> Result<[usize; 3], String> {
    let v = numbers::<usize>(field, value, 3, "whole number")?;
    if v.contains(&0) {
        return Err(format!("{field}: every size must be at least 1, got {} {} {}", v[0], v[1], v[2]));
    }
    Ok([v[0], v[1], v[2]])
}

/// Three finite numbers.
pub(crate) fn vec3(field: &str, value: &str) -> Result<DVec3, String> {
    let v = numbers::<f64>(field, value, 3, "number")?;
    let v = DVec3::new(v[0], v[1], v[2]);
    if !v.is_finite() {
        return Err(format!("{field}: {value} is not three finite numbers"));
    }
    Ok(v)
}

/// Three finite, positive spacings.
pub(crate) fn spacing3(field: &str, value: &str) -> Result<DVec3, String> {
    let s = vec3(field, value)?;
    if s.min_element() <= 0.0 {
        return Err(format!("{field}: spacings must be positive, got {} {} {}", s.x, s.y, s.z));
    }
    spacing_in_range(field, s)?;
    Ok(s)
}

/// A spacing within [`crate::SPACING_RANGE`] on every axis, or the field named.
pub(crate) fn spacing_in_range(field: &str, s: DVec3) -> Result<(), String> {
    let (lo, hi) = crate::SPACING_RANGE;
    if s.min_element() < lo || s.max_element() > hi {
        return Err(format!(
            "{field}: a voxel of {:?} x {:?} x {:?} world units is outside {lo:e}..={hi:e} on some axis",
            s.x, s.y, s.z
        ));
    }
    Ok(())
}

/// An axis-aligned grid made from per-axis steps in world space (a NRRD `space directions`, a
/// MetaImage `TransformMatrix` times the spacing).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct AxisSteps {
    /// `steps[a]`: the world step between neighbours along axis a; it lies along world axis a.
    steps: [DVec3; 3],
}

impl AxisSteps {
    /// Checks that axis a steps along world axis a (off-axis parts at most 1e-6 of the step, for
    /// rounding noise); a negative step is allowed (see [`AxisSteps::apply`]).
    pub fn new(field: &str, steps: [DVec3; 3]) -> Result<AxisSteps, String> {
        const AXES: [&str; 3] = ["x", "y", "z"];
        for (a, d) in steps.iter().enumerate() {
            let len = d.length();
            let off = (0..3).filter(|&b| b != a).map(|b| d[b].abs()).fold(0.0, f64::max);
            if !d.is_finite() || len == 0.0 || off > 1e-6 * len {
                return Err(format!(
                    "{field}: axis {a} steps by ({}, {}, {}), not along world {}; Isowall needs an \
                     axis-aligned grid (resample the volume)",
                    d.x, d.y, d.z, AXES[a]
                ));
            }
        }
        spacing_in_range(field, DVec3::new(steps[0].x.abs(), steps[1].y.abs(), steps[2].z.abs()))?;
        Ok(AxisSteps { steps })
    }

    /// Whether the z step is negative.
    pub fn mirrors_z(&self) -> bool {
        self.steps[2][2] < 0.0
    }

    /// Whether a step is negative (the data is mirrored along that axis when read).
    pub fn mirrors(&self) -> bool {
        (0..3).any(|a| self.steps[a][a] < 0.0)
    }

    /// The steps along the world axes (all positive).
    pub fn spacing(&self) -> DVec3 {
        DVec3::new(self.steps[0].x.abs(), self.steps[1].y.abs(), self.steps[2].z.abs())
    }

    /// Undoes negative steps: mirrors `data` along each such axis and moves `origin` (the first
    /// sample's world position) to the far end, so every sample keeps its world position.
    /// Returns the new origin.
    pub fn apply(&self, origin: DVec3, dims: [usize; 3], data: &mut [f32]) -> DVec3 {
        let mut origin = origin;
        for a in 0..3 {
            let step = self.steps[a][a];
            if step < 0.0 {
                origin[a] += (dims[a] - 1) as f64 * step;
                mirror(data, dims, a);
            }
        }
        origin
    }
}

/// Mirrors x-fastest `data` of `dims` along `axis`.
fn mirror(data: &mut [f32], dims: [usize; 3], axis: usize) {
    let [nx, ny, nz] = dims;
    // Runs of `run` values that swap as units, in blocks of `n` runs.
    let (run, n) = match axis {
        0 => (1, nx),
        1 => (nx, ny),
        _ => (nx * ny, nz),
    };
    for block in data.chunks_exact_mut(run * n) {
        for i in 0..n / 2 {
            let (lo, hi) = block.split_at_mut((n - 1 - i) * run);
            lo[i * run..(i + 1) * run].swap_with_slice(&mut hi[..run]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirroring_reverses_one_axis_only() {
        let data: Vec<f32> = (0..24).map(|v| v as f32).collect();
        let dims = [4, 3, 2];
        for axis in 0..3 {
            let mut m = data.clone();
            mirror(&mut m, dims, axis);
            for k in 0..2 {
                for j in 0..3 {
                    for i in 0..4 {
                        let mut src = [i, j, k];
                        src[axis] = dims[axis] - 1 - src[axis];
                        let at = |p: [usize; 3]| p[0] + 4 * (p[1] + 3 * p[2]);
                        assert_eq!(m[at([i, j, k])], data[at(src)], "axis {axis} ({i},{j},{k})");
                    }
                }
            }
        }
    }
}
