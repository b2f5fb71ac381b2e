//! Performance options change how the kernels work, never what they compute: AO block
//! levels (an AO level of its own, a coarse level), the block-min early exit and the workgroup
//! shape all give the occlusion and the primary hits of the build before them (`PerfOptions::PLAIN`),
//! and the finer AO levels load fewer cells.

mod common;

use isowall_render::gpu::PerfOptions;
use isowall_render::Frame;

/// Pixels whose hit differs, and pixels both hit whose occlusion differs by more than `tol`.
fn differences(a: &Frame, b: &Frame, tol: f32) -> (usize, usize) {
    let hits = (0..a.pixel_count()).filter(|&i| a.hit[i] != b.hit[i]).count();
    let ao = (0..a.pixel_count())
        .filter(|&i| a.hit[i] && b.hit[i] && (a.occlusion[i] - b.occlusion[i]).abs() > tol)
        .count();
    (hits, ao)
}

#[test]
fn performance_options_leave_the_image_unchanged() {
    let Some(mut gpu) = common::gpu() else { return };
    for (name, volume, view, s) in common::perf_scenes() {
        gpu.set_perf(PerfOptions::PLAIN).unwrap();
        let gv = gpu.upload(&volume).unwrap();
        let before = gpu.render(&gv, &view, &s, None).unwrap().frame;
        assert!(before.hit_count() > 500, "{}: too few hits", name);
        for o in [
            PerfOptions::default(),
            PerfOptions { ao_block: 4, ..PerfOptions::PLAIN },
            PerfOptions { ao_block: 2, coarse: 16, ..PerfOptions::default() },
            PerfOptions { coarse: 32, ..PerfOptions::PLAIN },
            PerfOptions { block_min_exit: true, ..PerfOptions::PLAIN },
            PerfOptions { workgroup: (16, 4), ..PerfOptions::PLAIN },
            PerfOptions { workgroup: (16, 16), ..PerfOptions::default() },
            // Levels that are not powers of two: blocks found by integer division, not a shift.
            PerfOptions { ao_block: 3, coarse: 12, ..PerfOptions::default() },
        ] {
            gpu.set_perf(o).unwrap();
            let gv = gpu.upload(&volume).unwrap();
            let f = gpu.render(&gv, &view, &s, None).unwrap().frame;
            let (hits, ao) = differences(&f, &before, 0.5 / 16.0);
            // Primary rays are untouched by every option: the same hits, the same depth.
            assert_eq!(hits, 0, "{} {o:?}: hits differ", name);
            assert_eq!(f.depth, before.depth, "{} {o:?}: depth differs", name);
            // The AO tests are exact either way; a ray grazing a cell corner may flip within f32
            // rounding where a DDA restarts at a block face: at most 1% of pixels by one ray.
            assert!(ao * 100 <= f.hit_count(), "{} {o:?}: occlusion differs at {ao} pixels", name);
            let (_, ao2) = differences(&f, &before, 1.5 / 16.0);
            assert_eq!(ao2, 0, "{} {o:?}: occlusion differs by more than one ray", name);
            if o.ao_block > 0 && o.ao_block < 8 {
                assert!(
                    f.fetches < before.fetches,
                    "{} {o:?}: a finer AO level should load fewer cells ({} >= {})",
                    name,
                    f.fetches,
                    before.fetches
                );
            }
        }
    }
}

/// The texture march (`PerfOptions::texture`: the primary march samples a hardware-filtered
/// `texture_3d`, the bracketing step refined exactly from the storage volume) finds the storage
/// march's surface: the hit masks agree off the silhouette, the median depth error is under 0.05
/// voxel and the median normal error under 1 degree (the tolerances the GPU is held to against
/// the reference); and the texture is what the march read (it checks each bracket on the exact
/// field: one fetch more per hit than the storage march).
#[test]
fn the_texture_march_finds_the_storage_marchs_surface() {
    let Some(mut gpu) = common::gpu() else { return };
    for (name, volume, view, mut s) in common::perf_scenes() {
        s.ao.samples = 0;
        gpu.set_perf(PerfOptions::default()).unwrap();
        let gv = gpu.upload(&volume).unwrap();
        let storage = gpu.render(&gv, &view, &s, None).unwrap().frame;
        // The kernels refuse a volume uploaded without its texture.
        gpu.set_perf(PerfOptions { texture: true, ..Default::default() }).unwrap();
        let e = gpu.render(&gv, &view, &s, None).err().expect("a volume without its texture");
        assert!(e.to_string().contains("texture"), "{e}");
        let gv = gpu.upload(&volume).unwrap();
        assert!(gv.march.enabled && gv.march.bytes >= volume.data().len() as u64 * 2);
        let texture = gpu.render(&gv, &view, &s, None).unwrap().frame;
        assert!(texture.hit_count() > 500, "{name}: too few hits");
        let a = common::compare(&texture, &storage, volume.spacing().min_element());
        assert_eq!(a.mask_mismatches, 0, "{name}: hit masks differ off the silhouette: {a:?}");
        assert!(a.depth_median < 0.05, "{name}: median depth error {} voxel", a.depth_median);
        assert!(a.normal_median_deg < 1.0, "{name}: median normal error {} deg", a.normal_median_deg);
        assert!(
            texture.fetches >= storage.fetches + texture.hit_count() as u64 / 2,
            "{name}: the march did not sample the texture ({} fetches, storage {})",
            texture.fetches,
            storage.fetches
        );
    }
}

/// Kernels compiled for block levels that are powers of two (a cell's block by a shift) refuse a
/// volume whose levels are not, instead of skipping the wrong blocks.
#[test]
fn shift_kernels_refuse_levels_that_are_not_powers_of_two() {
    let Some(mut gpu) = common::gpu() else { return };
    let (_, volume, view, s) = common::perf_scenes().remove(0);
    gpu.set_perf(PerfOptions { ao_block: 3, ..Default::default() }).unwrap();
    let odd = gpu.upload(&volume).unwrap();
    assert!(!odd.pow2_levels());
    gpu.set_perf(PerfOptions::default()).unwrap();
    let e = gpu.render(&odd, &view, &s, None).err().expect("levels of 3 under shift kernels");
    assert!(e.to_string().contains("powers of two"), "{e}");
    assert!(gpu.render(&gpu.upload(&volume).unwrap(), &view, &s, None).is_ok());
}
