//! Where a volume comes from: `PATH`, `PATH?series=UID` (one series of a DICOM folder),
//! `DIR/step_*.nrrd` (time steps: the files matching a glob, sorted by name) or
//! `procedural:NAME[:N]`, as given on the command line and in wall configs.
//!
//! Time-varying volumes: a glob names one file per time step; a 4-D NIfTI or NRRD file holds its
//! steps itself. [`VolumeSource::time_steps`] counts them, [`VolumeSource::load_step`] reads one.

use crate::io::{RawSpec, VolumeLimit};
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
    /// Time steps: the files matching a glob pattern (`*`, `?`, `[...]`), sorted by name, one step
    /// each.
    Steps(String),
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
                    if !crate::procedural::SIZES.contains(&size) {
                        let sizes = crate::procedural::SIZES;
                        return Err(VolumeError::Source(format!("{s}: size {size} is outside {sizes:?}")));
                    }
                    (n, Some(size))
                }
                None => (rest, None),
            };
            let kind = name.parse::<Procedural>().map_err(|e| VolumeError::Source(format!("{s}: {e}")))?;
            Ok(VolumeSource::Procedural { kind, size })
        } else if s.is_empty() {
            Err(VolumeError::Source("empty volume source".into()))
        } else if s.contains('*') {
            Ok(VolumeSource::Steps(s.to_string()))
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

    /// Loads or generates the volume (its first time step), within the default [`VolumeLimit`].
    pub fn load(&self, raw: Option<&RawSpec>) -> Result<Volume, VolumeError> {
        self.load_within(raw, &VolumeLimit::default())
    }

    /// Loads or generates the volume (its first time step) if it fits `limit` (checked from a
    /// file's header, or from a procedural volume's size, before anything is allocated).
    pub fn load_within(&self, raw: Option<&RawSpec>, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
        self.load_step_within(raw, 0, limit)
    }

    /// [`VolumeSource::load_step_within`] within the default [`VolumeLimit`].
    pub fn load_step(&self, raw: Option<&RawSpec>, step: usize) -> Result<Volume, VolumeError> {
        self.load_step_within(raw, step, &VolumeLimit::default())
    }

    /// Loads time step `step` (see the module's notes) if it fits `limit`; a source without time
    /// steps has step 0.
    pub fn load_step_within(
        &self,
        raw: Option<&RawSpec>,
        step: usize,
        limit: &VolumeLimit,
    ) -> Result<Volume, VolumeError> {
        match self {
            VolumeSource::File(p) => crate::io::load_step_within(p, raw, step, limit),
            VolumeSource::DicomSeries { path, series } => {
                self.only_step_0(step)?;
                crate::io::dicom::read(path, Some(series), limit)
            }
            VolumeSource::Steps(_) => crate::io::load_within(&self.step_file(step)?, raw, limit),
            VolumeSource::Procedural { kind, size } => {
                self.only_step_0(step)?;
                let [nx, ny, nz] = kind.dims(*size);
                let voxels = (nx as u64) * (ny as u64) * (nz as u64);
                limit
                    .check(voxels, &format!("{nx}x{ny}x{nz}"))
                    .map_err(|e| VolumeError::Source(format!("{self}: {e}")))?;
                Ok(kind.generate(*size))
            }
        }
    }

    /// The number of time steps (1 for a volume that does not change).
    pub fn time_steps(&self) -> Result<usize, VolumeError> {
        match self {
            VolumeSource::File(p) => crate::io::time_steps(p),
            VolumeSource::Steps(_) => Ok(self.step_files()?.len()),
            VolumeSource::DicomSeries { .. } | VolumeSource::Procedural { .. } => Ok(1),
        }
    }

    /// The file of time step `step` of a [`VolumeSource::Steps`] glob.
    pub fn step_file(&self, step: usize) -> Result<PathBuf, VolumeError> {
        let mut files = self.step_files()?;
        if step >= files.len() {
            return Err(VolumeError::Source(format!(
                "{self} has no time step {step}: it matches {} files (steps 0 to {})",
                files.len(),
                files.len() - 1
            )));
        }
        Ok(files.swap_remove(step))
    }

    /// Refuses a step other than 0 of a source with one step.
    pub(crate) fn only_step_0(&self, step: usize) -> Result<(), VolumeError> {
        if step == 0 {
            Ok(())
        } else {
            Err(VolumeError::Source(format!("{self} has no time step {step}: it has one (0)")))
        }
    }

    /// The files of a [`VolumeSource::Steps`] glob, sorted by name (at least one).
    pub fn step_files(&self) -> Result<Vec<PathBuf>, VolumeError> {
        let VolumeSource::Steps(pattern) = self else { return Ok(Vec::new()) };
        let paths = glob::glob(pattern)
            .map_err(|e| VolumeError::Source(format!("{pattern}: not a valid file pattern: {e}")))?;
        let mut files = Vec::new();
        for p in paths {
            let p = p.map_err(|e| VolumeError::Io { path: e.path().to_path_buf(), error: e.into() })?;
            if p.is_file() {
                files.push(p);
            }
        }
        files.sort();
        if files.is_empty() {
            return Err(VolumeError::Source(format!("{pattern}: no file matches the pattern")));
        }
        Ok(files)
    }

    /// The iso value to use when none is given: the procedural volume's own, else `None`.
    pub fn natural_iso(&self) -> Option<f64> {
        match self {
            VolumeSource::Procedural { kind, .. } => Some(kind.natural_iso()),
            VolumeSource::File(_) | VolumeSource::DicomSeries { .. } | VolumeSource::Steps(_) => None,
        }
    }

    /// The iso value a render of this volume uses: the one `given`, else the volume's natural
    /// one ([`VolumeSource::natural_iso`]), else the middle of its data range `(lo, hi)`.
    pub fn iso_or_default(&self, given: Option<f64>, (lo, hi): (f32, f32)) -> f64 {
        given.or(self.natural_iso()).unwrap_or(0.5 * (f64::from(lo) + f64::from(hi)))
    }

    /// [`VolumeSource::iso_or_default`], with the iso `given` held to [`crate::check_iso`]
    /// against the data's range `(lo, hi)` (a chosen default lies within it).
    pub fn checked_iso(&self, given: Option<f64>, (lo, hi): (f32, f32)) -> Result<f64, crate::IsoError> {
        if let Some(iso) = given {
            crate::check_iso(iso, (f64::from(lo), f64::from(hi)))?;
        }
        Ok(self.iso_or_default(given, (lo, hi)))
    }
}

impl std::fmt::Display for VolumeSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VolumeSource::File(p) => write!(f, "{}", p.display()),
            VolumeSource::Steps(pattern) => write!(f, "{pattern}"),
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

    #[test]
    fn a_glob_names_time_steps_in_file_name_order() {
        let dir = tempfile::tempdir().unwrap();
        for (name, value) in
            [("step_0010.nrrd", 3u8), ("step_0002.nrrd", 1), ("step_0003.nrrd", 2), ("other.nrrd", 9)]
        {
            let text = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 1 1\nencoding: raw\n\n".to_string();
            let mut bytes = text.into_bytes();
            bytes.extend([value, value]);
            std::fs::write(dir.path().join(name), bytes).unwrap();
        }
        let pattern = format!("{}/step_*.nrrd", dir.path().display());
        let s: VolumeSource = pattern.parse().unwrap();
        assert_eq!(s, VolumeSource::Steps(pattern.clone()));
        assert_eq!(s.time_steps().unwrap(), 3);
        let firsts: Vec<f32> = (0..3).map(|k| s.load_step(None, k).unwrap().data()[0]).collect();
        assert_eq!(firsts, [1.0, 2.0, 3.0]);
        let e = s.load_step(None, 3).unwrap_err().to_string();
        assert!(e.contains("no time step 3: it matches 3 files"), "{e}");
        // Every step is read within the limit: 2 voxels are 8 bytes as float32.
        let e =
            s.load_step_within(None, 1, &VolumeLimit::new(7, "[volume] max_bytes")).unwrap_err().to_string();
        assert!(
            e.contains("step_0003.nrrd") && e.contains("over the limit of 7 bytes ([volume] max_bytes)"),
            "{e}"
        );
        assert_eq!(s.load_step_within(None, 1, &VolumeLimit::new(8, "test")).unwrap().data(), [2.0, 2.0]);
        // A 4-D file is limited as a whole (from its header), though a step reads its voxels only.
        let four = dir.path().join("four.nrrd");
        let text = "NRRD0004\ntype: uchar\ndimension: 4\nsizes: 2 1 1 3\nencoding: raw\n\n";
        std::fs::write(&four, [text.as_bytes(), &[1, 1, 2, 2, 3, 3]].concat()).unwrap();
        let f = VolumeSource::File(four);
        assert_eq!(f.load_step_within(None, 2, &VolumeLimit::new(24, "test")).unwrap().data(), [3.0, 3.0]);
        let e = f.load_step_within(None, 2, &VolumeLimit::new(23, "test")).unwrap_err().to_string();
        assert!(e.contains("over the limit of 23 bytes"), "{e}");
        let none: VolumeSource = format!("{}/nothing_*.nrrd", dir.path().display()).parse().unwrap();
        assert!(none.time_steps().unwrap_err().to_string().contains("no file matches"));
        let e = VolumeSource::default_engine().load_step(None, 1).unwrap_err().to_string();
        assert!(e.contains("has no time step 1"), "{e}");
    }
}
