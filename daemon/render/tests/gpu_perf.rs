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
