//! Where a volume comes from: `PATH`, `PATH?series=UID` (one series of a DICOM folder) or
//! `procedural:NAME[:N]`, as given on the command line and in wall configs.

use crate::io::RawSpec;
use crate::procedural::Procedural;
use crate::{Volume, VolumeError};
use std::path::PathBuf;
use std::str::FromStr;

#[derive(Clone, Debug, PartialEq)]
pub enum VolumeSource {
    /// A file; its format is chosen by its extension (raw needs a [`RawSpec`]).
    File(PathBuf),
    /// One series of a DICOM folder (or of the folder of the file named): `PATH?series=UID`.
    DicomSeries { path: PathBuf, series: String },
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
        } else if let Some((path, series)) = s.rsplit_once(SERIES_SELECTOR) {
            if path.is_empty() || series.is_empty() {
                return Err(VolumeError::Source(format!("{s}: expected PATH?series=UID")));
            }
            Ok(VolumeSource::DicomSeries { path: PathBuf::from(path), series: series.to_string() })
        } else {
            Ok(VolumeSource::File(PathBuf::from(s)))
        }
    }
}

/// What separates a DICOM folder from the series chosen in it: `PATH?series=UID`.
pub const SERIES_SELECTOR: &str = "?series=";

impl VolumeSource {
    /// This source with the DICOM series `uid` chosen (a file or folder source becomes
    /// [`VolumeSource::DicomSeries`]); `None` leaves it as it is.
    pub fn with_series(self, uid: Option<&str>) -> Result<VolumeSource, VolumeError> {
        match (self, uid) {
            (s, None) => Ok(s),
            (VolumeSource::File(path) | VolumeSource::DicomSeries { path, .. }, Some(uid)) => {
                Ok(VolumeSource::DicomSeries { path, series: uid.to_string() })
            }
            (s, Some(uid)) => Err(VolumeError::Source(format!(
                "{s}: a series ({uid}) can only be chosen in a DICOM folder or file"
            ))),
        }
    }

    /// The engine-like block at its default size: the embedded default.
    pub fn default_engine() -> VolumeSource {
        VolumeSource::Procedural { kind: Procedural::Engine, size: None }
    }

    /// Loads or generates the volume.
    pub fn load(&self, raw: Option<&RawSpec>) -> Result<Volume, VolumeError> {
        match self {
            VolumeSource::File(p) => crate::io::load(p, raw),
            VolumeSource::DicomSeries { path, series } => crate::io::dicom::read(path, Some(series)),
            VolumeSource::Procedural { kind, size } => Ok(kind.generate(*size)),
        }
    }

    /// The iso value to use when none is given: the procedural volume's own, else `None`.
    pub fn natural_iso(&self) -> Option<f64> {
        match self {
            VolumeSource::Procedural { kind, .. } => Some(kind.natural_iso()),
            VolumeSource::File(_) | VolumeSource::DicomSeries { .. } => None,
        }
    }
}

impl std::fmt::Display for VolumeSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VolumeSource::File(p) => write!(f, "{}", p.display()),
            VolumeSource::DicomSeries { path, series } => {
                write!(f, "{}{SERIES_SELECTOR}{series}", path.display())
            }
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
        let s: VolumeSource = "ct/?series=1.2.3".parse().unwrap();
        assert_eq!(s, VolumeSource::DicomSeries { path: "ct/".into(), series: "1.2.3".into() });
        assert_eq!(s.to_string(), "ct/?series=1.2.3");
        assert!("ct?series=".parse::<VolumeSource>().is_err());
        let chosen = VolumeSource::File("ct".into()).with_series(Some("9.8")).unwrap();
        assert_eq!(chosen.to_string(), "ct?series=9.8");
        assert!(VolumeSource::default_engine().with_series(Some("9.8")).is_err());
    }
}
