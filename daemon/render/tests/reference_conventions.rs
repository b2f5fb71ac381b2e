//! The reference renderer against the convention vectors of `../shared/conventions/`: the camera
//! of `camera-and-hits.json` on `sphere32` at iso 0, for every listed pixel: hit or miss, the depth
//! within 2e-4 and the normal within 0.2 degrees of the independently computed answers.

use glam::DVec3;
use isowall_model::{Camera, RenderSettings, View};
use isowall_render::reference::{render, trace};
use isowall_volume::Volume;
use std::path::{Path, PathBuf};

fn conventions_dir() -> Option<PathBuf> {
    let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared/conventions"));
    if dir.join("camera-and-hits.json").is_file() {
        return Some(dir.to_owned());
    }
    assert!(std::env::var("CI").as_deref() != Ok("true"), "{} missing under CI=true", dir.display());
    eprintln!(
        "skipping: {} not found (the shared/ folder is beside the checkout only in CI and for developers)",
        dir.display()
    );
    None
}

/// sphere32 from its formula in the conventions README: 32^3, value = 10 - |p - (15.5, 14, 16)| at
/// voxel index p, spacing 1, origin 0, x fastest.
fn sphere32_from_formula() -> Volume {
    let c = DVec3::new(15.5, 14.0, 16.0);
    let mut data = Vec::with_capacity(32 * 32 * 32);
    for k in 0..32 {
        for j in 0..32 {
            for i in 0..32 {
                data.push((10.0 - (DVec3::new(i as f64, j as f64, k as f64) - c).length()) as f32);
            }
        }
    }
    Volume::new("sphere32 (formula)", [32; 3], DVec3::ONE, DVec3::ZERO, data).unwrap()
}

/// The voxels of sphere32.nrrd read directly (raw little-endian f32 after the header's blank line),
/// without the project's NRRD reader, to check that the formula matches the file.
fn sphere32_file_voxels(dir: &Path) -> Vec<f32> {
    let bytes = std::fs::read(dir.join("sphere32.nrrd")).unwrap();
    let start = bytes.windows(2).position(|w| w == b"\n\n").expect("NRRD header end") + 2;
    let header = String::from_utf8_lossy(&bytes[..start]);
    assert!(header.contains("type: float") && header.contains("sizes: 32 32 32"), "{header}");
    assert!(header.contains("encoding: raw") && header.contains("endian: little"), "{header}");
    bytes[start..].chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn v3(v: &serde_json::Value) -> DVec3 {
    DVec3::new(v[0].as_f64().unwrap(), v[1].as_f64().unwrap(), v[2].as_f64().unwrap())
}

#[test]
fn reference_hits_match_the_convention_vectors() {
    let Some(dir) = conventions_dir() else { return };
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("camera-and-hits.json")).unwrap()).unwrap();
    assert_eq!(j["volume"], "sphere32.nrrd");
    let iso = j["iso"].as_f64().unwrap();
    let cam = &j["camera"];
    let camera = Camera {
        eye: v3(&cam["eye"]),
        target: v3(&cam["target"]),
        up: v3(&cam["up"]),
        fov_y_deg: cam["fov_y_deg"].as_f64().unwrap(),
    };
    camera.validate().unwrap();
    let (w, h) = (cam["width"].as_u64().unwrap() as u32, cam["height"].as_u64().unwrap() as u32);
    let view = View::whole(camera, w, h);

    let formula = sphere32_from_formula();
    assert_eq!(sphere32_file_voxels(&dir), formula.data(), "sphere32.nrrd differs from its formula");
    // The project's NRRD reader must give the same volume; both are rendered.
    let loaded = isowall_volume::io::load(&dir.join("sphere32.nrrd"), None).unwrap();
    assert_eq!(loaded.dims(), [32; 3]);
    assert_eq!((loaded.spacing(), loaded.origin()), (DVec3::ONE, DVec3::ZERO));
    assert_eq!(loaded.data(), formula.data());
    for volume in [formula, loaded] {
        check_volume(&volume, &j, &view, iso);
    }
}

fn check_volume(volume: &Volume, j: &serde_json::Value, view: &View, iso: f64) {
    let (camera, w) = (view.camera, view.full.0);
    let frame = render(volume, view, &RenderSettings::new(iso));
    let (mut max_depth_err, mut max_normal_deg) = (0f64, 0f64);
    let pixels = j["pixels"].as_array().unwrap();
    assert!(pixels.len() >= 5);
    let (mut hits, mut misses) = (0, 0);
    for p in pixels {
        let (px, py) = (p["px"].as_u64().unwrap() as u32, p["py"].as_u64().unwrap() as u32);
        let dir = v3(&p["dir"]);
        let i = py as usize * w as usize + px as usize;
        let traced = trace(volume, camera.eye, dir, iso);
        if !p["hit"].as_bool().unwrap() {
            misses += 1;
            assert!(traced.is_none(), "pixel ({px},{py}) should miss: {traced:?}");
            assert!(!frame.hit[i] && frame.depth[i] == 0.0, "pixel ({px},{py}) should miss in the frame");
            continue;
        }
        hits += 1;
        let want_depth = p["depth"].as_f64().unwrap();
        let want_n = v3(&p["normal"]).normalize();
        let hit = traced.unwrap_or_else(|| panic!("pixel ({px},{py}) should hit at depth {want_depth}"));
        assert!(!hit.cap);
        let depth_err = (hit.t - want_depth).abs();
        let normal_deg = hit.normal.dot(want_n).clamp(-1.0, 1.0).acos().to_degrees();
        eprintln!(
            "pixel ({px},{py}): depth {:.6} (want {want_depth}), normal error {normal_deg:.4} deg",
            hit.t
        );
        assert!(depth_err < 2e-4, "pixel ({px},{py}): depth {} want {want_depth}", hit.t);
        assert!(
            normal_deg < 0.2,
            "pixel ({px},{py}): normal {:?} want {want_n:?} ({normal_deg} deg)",
            hit.normal
        );
        // The frame holds the same answer (its ray is View::ray_dir, equal to the listed direction).
        assert!(frame.hit[i], "pixel ({px},{py}) should hit in the frame");
        assert!(
            (frame.depth[i] as f64 - want_depth).abs() < 2e-4,
            "frame depth {} at ({px},{py})",
            frame.depth[i]
        );
        let fnorm = DVec3::from_array(frame.normal[i].map(f64::from));
        assert!(fnorm.dot(want_n) > (0.2f64).to_radians().cos(), "frame normal {fnorm:?} at ({px},{py})");
        max_depth_err = max_depth_err.max(depth_err);
        max_normal_deg = max_normal_deg.max(normal_deg);
    }
    assert!(hits > 0 && misses > 0);
    eprintln!(
        "{}: max depth error {max_depth_err:.3e}, max normal error {max_normal_deg:.4} degrees",
        volume.name
    );
}
