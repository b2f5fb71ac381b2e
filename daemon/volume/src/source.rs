//! Where a volume comes from: `PATH` or `procedural:NAME[:N]`, as given on the command line and in
//! wall configs.

use crate::io::{RawSpec, VolumeLimit};
use crate::procedural::Procedural;
use crate::{Volume, VolumeError};
use std::path::PathBuf;
use std::str::FromStr;

#[derive(Clone, Debug, PartialEq)]
pub enum VolumeSource {
    /// A file; its format is chosen by its extension (raw needs a [`RawSpec`]).
    File(PathBuf),
    /// A built-in volume, with an optional size (the largest dimension; default per volume).
    Procedural { kind: Procedural, size: Option<usize> },
}

impl FromStr for VolumeSource {
    type Err = VolumeError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if let Some(rest) = s.strip_prefix("procedural:") {
            let (name, size) = match rest.split_once(':') {
                Some((n, sz)) => {
                    let size: usize = sz.parse().map_err(|_| {
                        VolumeError::Source(format!("{s}: size '{sz}' is not a whole number"))
                    })?;
                    if !(2..=1024).contains(&size) {
                        return Err(VolumeError::Source(format!("{s}: size {size} is outside 2..=1024")));
                    }
                    (n, Some(size))
                }
                None => (rest, None),
            };
            let kind = name.parse::<Procedural>().map_err(|e| VolumeError::Source(format!("{s}: {e}")))?;
            Ok(VolumeSource::Procedural { kind, size })
        } else if s.is_empty() {
            Err(VolumeError::Source("empty volume source".into()))
        } else {
            Ok(VolumeSource::File(PathBuf::from(s)))
        }
    }
}

impl VolumeSource {
    /// The engine-like block at its default size: the embedded default.
    pub fn default_engine() -> VolumeSource {
        VolumeSource::Procedural { kind: Procedural::Engine, size: None }
    }

    /// Loads or generates the volume, within the default [`VolumeLimit`].
    pub fn load(&self, raw: Option<&RawSpec>) -> Result<Volume, VolumeError> {
        self.load_within(raw, &VolumeLimit::default())
    }

    /// Loads or generates the volume if it fits `limit` (checked from a file's header, or from a
    /// procedural volume's size, before anything is allocated).
    pub fn load_within(&self, raw: Option<&RawSpec>, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
        match self {
            VolumeSource::File(p) => crate::io::load_within(p, raw, limit),
            VolumeSource::Procedural { kind, size } => {
                let [nx, ny, nz] = kind.dims(*size);
                let voxels = (nx as u64) * (ny as u64) * (nz as u64);
                limit
                    .check(voxels, &format!("{nx}x{ny}x{nz}"))
                    .map_err(|e| VolumeError::Source(format!("{self}: {e}")))?;
                Ok(kind.generate(*size))
            }
        }
    }

    /// The iso value to use when none is given: the procedural volume's own, else `None`.
    pub fn natural_iso(&self) -> Option<f64> {
        match self {
            VolumeSource::Procedural { kind, .. } => Some(kind.natural_iso()),
            VolumeSource::File(_) => None,
        }
    }

    /// The iso value a render of this volume uses: the one `given`, else the volume's natural
    /// one ([`VolumeSource::natural_iso`]), else the middle of its data range `(lo, hi)`.
    pub fn iso_or_default(&self, given: Option<f64>, (lo, hi): (f32, f32)) -> f64 {
        given.or(self.natural_iso()).unwrap_or(0.5 * (f64::from(lo) + f64::from(hi)))
    }
}

impl std::fmt::Display for VolumeSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VolumeSource::File(p) => write!(f, "{}", p.display()),
            VolumeSource::Procedural { kind, size: None } => {
                write!(f, "procedural:{}", kind.name())
            }
            VolumeSource::Procedural { kind, size: Some(n) } => write!(f, "procedural:{}:{n}", kind.name()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_files_and_procedurals() {
        assert_eq!("a/b.nrrd".parse::<VolumeSource>().unwrap(), VolumeSource::File("a/b.nrrd".into()));
        assert_eq!(
            "procedural:torus:48".parse::<VolumeSource>().unwrap(),
            VolumeSource::Procedural { kind: Procedural::Torus, size: Some(48) }
        );
        assert_eq!("procedural:engine".parse::<VolumeSource>().unwrap().to_string(), "procedural:engine");
        for bad in ["procedural:teapot", "procedural:sphere:x", "procedural:sphere:1", ""] {
            let e = bad.parse::<VolumeSource>().unwrap_err().to_string();
            assert!(!e.is_empty(), "{bad}");
        }
        assert!("procedural:teapot".parse::<VolumeSource>().unwrap_err().to_string().contains("teapot"));
    }
}
