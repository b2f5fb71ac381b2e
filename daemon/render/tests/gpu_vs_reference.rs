//! The GPU renderer against the exact CPU reference: hit masks agree except on
//! silhouette pixels, median depth error under 0.05 voxel, median normal error under 1 degree.
//! Also: empty-space skipping changes nothing but the work done; a tile renders exactly the pixels
//! of the whole image; every AOV is 0 where there is no hit.

mod common;

use glam::DVec3;
use isowall_model::{Camera, Rect, RenderSettings, Shading, View};
use isowall_render::reference;
use isowall_volume::procedural::Procedural;
use isowall_volume::VolumeSource;

const SIZE: u32 = 96;

fn scene(kind: Procedural, size: usize) -> (isowall_volume::Volume, f64) {
    let src = VolumeSource::Procedural { kind, size: Some(size) };
    (src.load(None).unwrap(), kind.natural_iso())
}

#[test]
fn gpu_agrees_with_the_exact_reference_on_procedural_volumes() {
    let Some(gpu) = common::gpu() else { return };
    let cases = [
        (Procedural::Sphere, 48),
        (Procedural::Torus, 48),
        (Procedural::MarschnerLobb, 41),
        (Procedural::Gyroid, 48),
        (Procedural::SphereOverPlane, 48),
        (Procedural::Engine, 64),
    ];
    for (kind, n) in cases {
        let (volume, iso) = scene(kind, n);
        let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), SIZE, SIZE), SIZE, SIZE);
        let settings = RenderSettings::new(iso);
        let gv = gpu.upload(&volume).unwrap();
        let g = gpu.render(&gv, &view, &settings, None).unwrap().frame;
        let r = reference::render(&volume, &view, &settings);
        let a = common::compare(&g, &r, volume.spacing().min_element());
        eprintln!("{}: {a:?}", kind.name());
        assert!(a.both_hit > 300, "{}: too few hits to judge ({})", kind.name(), a.both_hit);
        assert_eq!(a.mask_mismatches, 0, "{}: hit masks differ off the silhouette: {a:?}", kind.name());
        assert!(a.depth_median < 0.05, "{}: median depth error {} voxel", kind.name(), a.depth_median);
        assert!(
            a.normal_median_deg < 1.0,
            "{}: median normal error {} deg",
            kind.name(),
            a.normal_median_deg
        );
        // Colour follows from the same shading formula: close where both hit.
        let mut diffs: Vec<f32> = (0..g.pixel_count())
            .filter(|&i| g.hit[i] && r.hit[i])
            .map(|i| (0..3).map(|c| (g.color[i][c] - r.color[i][c]).abs()).fold(0.0, f32::max))
            .collect();
        diffs.sort_by(f32::total_cmp);
        assert!(
            diffs[diffs.len() / 2] < 0.01,
            "{}: median colour difference {}",
            kind.name(),
            diffs[diffs.len() / 2]
        );
    }
}

#[test]
fn empty_space_skipping_saves_fetches_and_changes_nothing_else() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, iso) = scene(Procedural::Engine, 64);
    let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), SIZE, SIZE), SIZE, SIZE);
    let gv = gpu.upload(&volume).unwrap();
    let mut s = RenderSettings::new(iso);
    s.empty_space_skipping = false;
    let off = gpu.render(&gv, &view, &s, None).unwrap().frame;
    s.empty_space_skipping = true;
    let on = gpu.render(&gv, &view, &s, None).unwrap().frame;
    // A march may step over a thin grazing crossing (the reference cannot), and steps restart at
    // block exits, so the two marches may each miss a different such crossing: rare pixels, all on
    // a silhouette. Everywhere else both give the reference's surface.
    let r = reference::render(&volume, &view, &s);
    for (name, f) in [("skipping", &on), ("plain", &off)] {
        let wrong = (0..f.pixel_count())
            .filter(|&i| f.hit[i] != r.hit[i] || (f.hit[i] && (f.depth[i] - r.depth[i]).abs() > 0.05))
            .count();
        eprintln!("{name} march: {wrong} of {} pixels differ from the reference", f.pixel_count());
        assert!(wrong * 200 <= f.pixel_count(), "{name} march: {wrong} pixels differ from the reference");
        assert_eq!(
            common::compare(f, &r, 1.0).mask_mismatches,
            0,
            "{name}: hit mask differs off the silhouette"
        );
    }
    let mut diff: Vec<f32> = (0..on.pixel_count())
        .filter(|&i| on.hit[i] && off.hit[i])
        .map(|i| (on.depth[i] - off.depth[i]).abs())
        .collect();
    diff.sort_by(f32::total_cmp);
    assert!(diff[diff.len() / 2] < 1e-3, "median depth difference {}", diff[diff.len() / 2]);
    assert!(
        (on.fetches as f64) < 0.8 * off.fetches as f64,
        "skipping saved too little: {} vs {} fetches",
        on.fetches,
        off.fetches
    );
}

#[test]
fn a_tile_renders_exactly_the_pixels_of_the_whole_image() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, iso) = scene(Procedural::Torus, 48);
    let cam = Camera::framing(volume.box_min(), volume.box_max(), SIZE, SIZE);
    let whole = View::whole(cam, SIZE, SIZE);
    let tile = View { rect: Rect { x: 40, y: 24, width: 33, height: 41 }, ..whole };
    let gv = gpu.upload(&volume).unwrap();
    let s = RenderSettings::new(iso);
    let w = gpu.render(&gv, &whole, &s, None).unwrap().frame;
    let t = gpu.render(&gv, &tile, &s, None).unwrap().frame;
    assert!(t.hit_count() > 50);
    for y in 0..41 {
        for x in 0..33 {
            let i = (y * 33 + x) as usize;
            let j = ((y + 24) * SIZE + x + 40) as usize;
            assert_eq!(
                (t.hit[i], t.depth[i], t.color[i]),
                (w.hit[j], w.depth[j], w.color[j]),
                "pixel ({x},{y})"
            );
        }
    }
}

#[test]
fn misses_are_zero_in_every_aov_and_caps_use_the_face_normal() {
    let Some(gpu) = common::gpu() else { return };
    // A solid block: every ray that enters the box hits its face (a cap).
    let volume =
        isowall_volume::Volume::new("solid", [8, 8, 8], DVec3::ONE, DVec3::ZERO, vec![1.0; 512]).unwrap();
    let cam = Camera {
        eye: DVec3::new(3.5, 3.5, 40.0),
        target: DVec3::new(3.5, 3.5, 0.0),
        up: DVec3::Y,
        fov_y_deg: 30.0,
    };
    let view = View::whole(cam, 64, 64);
    let mut s = RenderSettings::new(0.5);
    s.shading = Shading::Lambert;
    let gv = gpu.upload(&volume).unwrap();
    let f = gpu.render(&gv, &view, &s, None).unwrap().frame;
    let r = reference::render(&volume, &view, &s);
    assert!(f.hit_count() > 100 && f.hit_count() < 64 * 64);
    for i in 0..f.pixel_count() {
        if f.hit[i] {
            assert_eq!(f.normal[i], [0.0, 0.0, 1.0], "cap normal at {i}");
            assert!((f.depth[i] - r.depth[i]).abs() < 1e-3);
        } else {
            assert_eq!((f.depth[i], f.normal[i]), (0.0, [0.0; 3]), "miss {i} not zero");
        }
    }
    assert_eq!(common::compare(&f, &r, 1.0).mask_mismatches, 0);
}
