//! The outside answers of `../shared/conventions/ao-known-answers.json` (AO on the two real scans
//! from an independent renderer), read into types: the one reader of that file, for the AO tests
//! and `isowalld bench denoise`.

use serde::Deserialize;
use std::path::Path;

/// The file: one case per scan.
#[derive(Clone, Debug, Deserialize)]
pub struct KnownAnswers {
    pub cases: Vec<KnownCase>,
}

/// A scan: its volume (a path relative to the checkout, `../shared/data/...`), iso, camera and
/// pixels.
#[derive(Clone, Debug, Deserialize)]
pub struct KnownCase {
    pub volume: String,
    pub iso: f64,
    pub camera: KnownCamera,
    pub pixels: Vec<KnownPixel>,
}

/// A pinhole camera, pixel-centre rays as DESIGN.md defines them.
#[derive(Clone, Copy, Debug, Deserialize)]
pub struct KnownCamera {
    pub eye: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub fov_y_deg: f64,
    pub width: u32,
    pub height: u32,
}

/// A hit pixel (py = 0 the top row): the hit position (world), the normal, and the occlusion for
/// AO radius 8 world units and unbounded.
#[derive(Clone, Copy, Debug, Deserialize)]
pub struct KnownPixel {
    pub px: u32,
    pub py: u32,
    pub pos: [f64; 3],
    pub normal: [f64; 3],
    #[serde(rename = "A_r8")]
    pub a_r8: f64,
    #[serde(rename = "A_unbounded")]
    pub a_unbounded: f64,
}

impl KnownAnswers {
    /// Reads the file; the error names it and says what is wrong.
    pub fn read(path: &Path) -> Result<KnownAnswers, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))
    }
}

impl KnownCase {
    /// The volume's file name (what a scene given by another path is matched by).
    pub fn file_name(&self) -> &str {
        Path::new(&self.volume).file_name().and_then(|f| f.to_str()).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_case_reads_into_its_fields_and_a_bad_file_is_named() {
        let dir = std::env::temp_dir().join(format!("isowall-known-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good = dir.join("good.json");
        std::fs::write(
            &good,
            r#"{"note": "x", "cases": [{"volume": "../shared/data/ct.nrrd", "iso": 300.0, "mean_A_r8_over_all_hits": 0.01,
                "camera": {"eye": [1, 2, 3], "target": [0, 0, 0], "up": [0, 0, 1], "fov_y_deg": 35.0, "width": 128, "height": 96},
                "pixels": [{"px": 4, "py": 5, "pos": [0.5, 0.25, 1.0], "normal": [0, 0, 1], "A_r8": 0.125, "A_unbounded": 0.5}]}]}"#,
        )
        .unwrap();
        let k = KnownAnswers::read(&good).unwrap();
        let c = &k.cases[0];
        assert_eq!((c.file_name(), c.iso, c.camera.width, c.camera.height), ("ct.nrrd", 300.0, 128, 96));
        assert_eq!(c.camera.eye, [1.0, 2.0, 3.0]);
        let p = c.pixels[0];
        assert_eq!((p.px, p.py, p.pos, p.a_r8, p.a_unbounded), (4, 5, [0.5, 0.25, 1.0], 0.125, 0.5));
        let bad = dir.join("bad.json");
        std::fs::write(&bad, r#"{"cases": [{"volume": "v"}]}"#).unwrap();
        let e = KnownAnswers::read(&bad).unwrap_err();
        assert!(e.contains("bad.json") && e.contains("missing field"), "{e}");
        let e = KnownAnswers::read(&dir.join("absent.json")).unwrap_err();
        assert!(e.contains("absent.json"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
