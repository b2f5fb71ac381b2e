//! The brick cache on the GPU (`BrickPool`, shaders/volume.wgsl `BRICKED`): a still frame whose
//! wanted bricks are all resident at level 0 is the whole volume's frame bit for bit (depth,
//! normals, shading, AO); before that, every lookup reads the finest resident coarser level, so
//! the picture is never black; budgets hold; a pool smaller than the view's set evicts and says
//! that the set is over the pool, and a still frame through it is finished in passes over screen
//! regions, still the whole volume's frame bit for bit.

mod common;

use isowall_model::{AoSettings, Camera, RenderSettings, View};
use isowall_render::gpu::{footprint, BrickPool, GpuRenderer, GpuVolume};
use isowall_render::Frame;
use isowall_volume::brick_cache::{wanted_bricks, BrickSource, HostBrickCache, InCorePyramid, ViewFootprint};
use isowall_volume::procedural::Procedural;
use isowall_volume::VolumeSource;

const W: u32 = 64;
const H: u32 = 48;
/// Bricks of 8 cells: 8^3 at level 0 of the 64^3 torus, one at level 3.
const CELLS: usize = 8;

fn scene() -> (InCorePyramid, View, RenderSettings) {
    let kind = Procedural::Torus;
    let volume = VolumeSource::Procedural { kind, size: Some(64) }.load(None).unwrap();
    let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), W, H), W, H);
    let mut settings = RenderSettings::new(kind.natural_iso());
    settings.ao = AoSettings { samples: 4, ..settings.ao };
    (InCorePyramid::new(volume, CELLS).unwrap(), view, settings)
}

/// What a still view wants (with the default kernels): the procedural volumes' voxels are 1 unit.
fn still(view: &View, s: &RenderSettings) -> ViewFootprint {
    footprint(view, s, &isowall_render::gpu::PerfOptions::default(), glam::DVec3::ONE, true)
}

fn render(gpu: &GpuRenderer, v: &GpuVolume, view: &View, s: &RenderSettings) -> Frame {
    gpu.render(v, view, s, None).unwrap().frame
}

/// Pixels whose depth, normal, colour or occlusion differ in any bit.
fn differing(a: &Frame, b: &Frame) -> usize {
    (0..a.hit.len())
        .filter(|&i| {
            a.hit[i] != b.hit[i]
                || a.depth[i].to_bits() != b.depth[i].to_bits()
                || a.normal[i].map(f32::to_bits) != b.normal[i].map(f32::to_bits)
                || a.color[i].map(f32::to_bits) != b.color[i].map(f32::to_bits)
                || a.occlusion[i].to_bits() != b.occlusion[i].to_bits()
        })
        .count()
}

fn hits(f: &Frame) -> usize {
    f.hit.iter().filter(|&&h| h).count()
}

#[test]
fn a_refined_still_frame_is_the_whole_volumes_frame_bit_for_bit() {
    let Some(gpu) = common::gpu() else { return };
    let (pyramid, view, s) = scene();
    let whole = gpu.upload(pyramid.level(0)).unwrap();
    let layout = pyramid.layout().clone();
    let mut cache = HostBrickCache::new(64 << 20, &layout).unwrap();
    let mut pool = BrickPool::new(&gpu.ctx, &gpu.perf(), &pyramid, &mut cache, 64 << 20).unwrap();
    let wanted = wanted_bricks(&pyramid, s.iso as f32, &still(&view, &s));
    assert!(
        !wanted.is_empty() && wanted.len() < layout.bricks(0),
        "{} of {}",
        wanted.len(),
        layout.bricks(0)
    );

    for method_exact in [false, true] {
        let mut s = s;
        s.ao.exact = method_exact;
        let reference = render(&gpu, &whole, &view, &s);
        assert!(hits(&reference) > 200, "the scene shows the torus");
        // Refine two bricks a round, as a capped upload would, rendering between the rounds.
        let mut rounds = 0;
        loop {
            let r = pool.refine(&gpu.ctx, &pyramid, &mut cache, &wanted, 2 * layout.brick_bytes()).unwrap();
            let f = render(&gpu, pool.volume(), &view, &s);
            assert!(
                hits(&f) * 10 >= hits(&reference) * 7,
                "round {rounds}: {} hits of {}",
                hits(&f),
                hits(&reference)
            );
            if r.complete() {
                let d = differing(&reference, &f);
                assert_eq!(
                    d, 0,
                    "exact AO walk {method_exact}: {d} pixels differ from the whole volume's frame"
                );
                break;
            }
            assert!(r.uploaded <= 2 && r.over_pool == 0, "{r:?}");
            rounds += 1;
            assert!(rounds <= wanted.len(), "refinement does not end");
        }
    }
    assert!(pool.gpu_bytes() <= 64 << 20);
    assert_eq!(pool.stats().evictions, 0, "the pool holds the whole set");
}

#[test]
fn before_level_0_the_coarser_levels_draw_the_surface_and_a_small_pool_evicts_within_its_budget() {
    let Some(gpu) = common::gpu() else { return };
    let (pyramid, view, s) = scene();
    let layout = pyramid.layout().clone();
    let whole = gpu.upload(pyramid.level(0)).unwrap();
    let reference = render(&gpu, &whole, &view, &s);
    // The coarsest level (one brick) and 6 more slots, past the page tables and min/max.
    let brick = layout.brick_bytes();
    let budget = 8 * brick - 1;
    let mut cache = HostBrickCache::new(3 * brick, &layout).unwrap();
    let mut pool = BrickPool::new(&gpu.ctx, &gpu.perf(), &pyramid, &mut cache, budget).unwrap();
    assert!(pool.gpu_bytes() <= budget);
    assert!(pool.slots() < 8, "{} slots", pool.slots());
    // Only the coarsest level (16^3 samples): the torus is there, blurred.
    let coarse = render(&gpu, pool.volume(), &view, &s);
    assert!(hits(&coarse) * 10 >= hits(&reference) * 7, "{} hits of {}", hits(&coarse), hits(&reference));
    assert!(differing(&reference, &coarse) > 0);
    // The still set is larger than the pool: it fills, says so, and stays within its budget.
    let wanted = wanted_bricks(&pyramid, s.iso as f32, &still(&view, &s));
    let r = pool.refine(&gpu.ctx, &pyramid, &mut cache, &wanted, u64::MAX).unwrap();
    assert!(!r.complete() && r.over_pool > 0 && r.resident == pool.slots() - 1, "{r:?}");
    let partial = render(&gpu, pool.volume(), &view, &s);
    assert!(hits(&partial) * 10 >= hits(&reference) * 7);
    // Another round wanting three bricks that are not resident: the bricks it does not want make
    // room, and those three are then resident.
    let last = &wanted[wanted.len() - 3..];
    assert!(last.iter().all(|k| !pool.holds(*k)));
    let before = pool.stats().evictions;
    let r = pool.refine(&gpu.ctx, &pyramid, &mut cache, last, u64::MAX).unwrap();
    assert!(r.complete() && pool.stats().evictions == before + 3, "{r:?} {:?}", pool.stats());
    assert!(cache.stats().peak_bytes <= 3 * brick && cache.stats().evictions > 0, "{:?}", cache.stats());
    // A budget that cannot hold the coarsest level and one more brick is refused, saying why.
    let e = BrickPool::new(&gpu.ctx, &gpu.perf(), &pyramid, &mut cache, brick).err().unwrap().to_string();
    assert!(e.contains("GPU budget") && e.contains("coarsest level"), "{e}");
}

#[test]
fn a_still_frame_larger_than_the_pool_is_finished_in_passes_and_is_the_whole_volumes_frame() {
    let Some(gpu) = common::gpu() else { return };
    let (pyramid, view, mut s) = scene();
    // A short AO reach (2 voxels): a pixel's rays then read a thin tube of bricks of 8 cells.
    // (With the filter on, a pass carries the filter's guard band of 62 pixels, the way a wall
    // tile does: at this size that is the whole view.)
    s.ao.radius = isowall_model::AoRadius::World(2.0);
    let layout = pyramid.layout().clone();
    let whole = gpu.upload(pyramid.level(0)).unwrap();
    let brick = layout.brick_bytes();
    let wanted = wanted_bricks(&pyramid, s.iso as f32, &still(&view, &s));
    for exact in [false, true] {
        s.ao.exact = exact;
        let reference = gpu.render_accumulated(&whole, &view, &s, None, 2).unwrap().frame;
        // Half the view's bricks (and the page tables, min/max and coarsest level): a
        // pixel's ray reads the bricks along it to the far side of the volume.
        let mut cache = HostBrickCache::new(16 * brick, &layout).unwrap();
        let budget = 64 * 1024 + (wanted.len() as u64 / 2 + 1) * brick;
        let mut pool = BrickPool::new(&gpu.ctx, &gpu.perf(), &pyramid, &mut cache, budget).unwrap();
        assert!(pool.slots() < wanted.len(), "{} slots for {} bricks", pool.slots(), wanted.len());
        let c = gpu.render_converged(&mut pool, &pyramid, &mut cache, &view, &s, None, 2).unwrap();
        eprintln!(
            "exact AO walk {exact}: {} passes in {} rounds, at most {} of the view's {} bricks in one, {} slots, {} uploads, {} evictions",
            c.passes,
            c.rounds,
            c.most_wanted,
            wanted.len(),
            pool.slots(),
            pool.stats().uploads,
            pool.stats().evictions
        );
        assert!(c.passes > 1 && pool.stats().evictions > 0);
        let d = differing(&reference, &c.frame);
        assert_eq!(d, 0, "exact AO walk {exact}: {d} pixels differ from the whole volume's frame");
        assert!(pool.gpu_bytes() <= budget);
    }
}

#[test]
fn ray_guided_rounds_load_only_what_rays_read_and_the_frame_is_still_exact() {
    let Some(gpu) = common::gpu() else { return };
    // A solid ball of radius 44 in 128^3: most of its bricks of 8 are wholly inside.
    let kind = Procedural::Sphere;
    let volume = VolumeSource::Procedural { kind, size: Some(128) }.load(None).unwrap();
    let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), W, H), W, H);
    let mut s = RenderSettings::new(kind.natural_iso());
    s.ao = AoSettings { samples: 4, ..s.ao };
    let pyramid = InCorePyramid::new(volume, CELLS).unwrap();
    let whole = gpu.upload(pyramid.level(0)).unwrap();
    let mut fp = still(&view, &s);
    let inside_too = wanted_bricks(&pyramid, s.iso as f32, &ViewFootprint { interior_exit: false, ..fp });
    fp.interior_exit = true;
    let wanted = wanted_bricks(&pyramid, s.iso as f32, &fp);
    eprintln!("{} bricks wanted, {} with those wholly inside", wanted.len(), inside_too.len());
    assert!(wanted.len() < inside_too.len(), "{} of {}", wanted.len(), inside_too.len());
    let layout = pyramid.layout().clone();
    let mut cache = HostBrickCache::new(64 << 20, &layout).unwrap();
    let inside: Vec<_> = inside_too.iter().filter(|k| !wanted.contains(k)).collect();
    for exact in [false, true] {
        s.ao.exact = exact;
        let mut pool = BrickPool::new(&gpu.ctx, &gpu.perf(), &pyramid, &mut cache, 64 << 20).unwrap();
        let reference = render(&gpu, &whole, &view, &s);
        let c = gpu.render_converged(&mut pool, &pyramid, &mut cache, &view, &s, None, 1).unwrap();
        assert_eq!(c.passes, 1);
        let d = differing(&reference, &c.frame);
        assert_eq!(d, 0, "exact AO walk {exact}: {d} pixels differ");
        // Ray-guided: only what the rays read is loaded, fewer than the view's cone holds (the
        // ball's far side is never read), and not every brick wholly inside (the rounds before
        // level 0 march through the coarser levels' surface into some).
        let loaded = pool.stats().uploads as usize - 1;
        eprintln!(
            "exact AO walk {exact}: {} rounds read {} bricks, {loaded} loaded",
            c.rounds, c.most_wanted
        );
        assert!(c.rounds > 1 && loaded >= c.most_wanted, "{} rounds, {loaded} loaded", c.rounds);
        assert!(loaded < wanted.len(), "{loaded} bricks loaded, {} in the view's cone", wanted.len());
        assert!(inside.iter().any(|k| !pool.holds(**k)), "every brick wholly inside was read");
    }
}
