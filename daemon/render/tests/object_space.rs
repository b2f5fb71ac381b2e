//! Object space on the GPU: bricks with halos, each rendered alone and composited by depth, give
//! the single-node render (AO whose radius spans the cuts included); each brick reads only its
//! brick and halo.

mod common;

use glam::DVec3;
use isowall_model::bricks::{self, Occupancy};
use isowall_model::wire::Continuity;
use isowall_model::{AoRadius, Camera, RenderSettings, View};
use isowall_render::gpu::ObjectSpace;
use isowall_render::Frame;
use isowall_volume::{BlockMinMax, VolumeSource, VoxelRange};

/// The single render, the composite of the bricks, each brick's frame, and the bricks.
type Renders = (Frame, Frame, Vec<(Frame, ObjectSpace)>, Vec<bricks::Brick>);

/// A volume's stream and its split into bricks, as every node computes it.
struct Split {
    src: VolumeSource,
    stream: isowall_volume::region::VolumeStream,
    info: isowall_volume::VolumeInfo,
    blocks: BlockMinMax,
    split: Vec<bricks::Brick>,
    halo: [usize; 3],
}

/// `source` split into `n` bricks at `settings`' iso, with the halo of its AO radius.
fn split_of(source: &str, n: usize, settings: &RenderSettings) -> Split {
    let src: VolumeSource = source.parse().unwrap();
    let stream = src.stream(None).unwrap();
    let info = stream.info().clone();
    let blocks = stream.block_minmax(BlockMinMax::DEFAULT_BLOCK).unwrap();
    let occ = Occupancy::from_minmax(blocks.block, blocks.counts, &blocks.minmax, settings.iso);
    let split = bricks::split(&occ, info.dims, info.spacing, n).unwrap();
    let halo = bricks::halo_voxels(settings, info.spacing).unwrap();
    Split { src, stream, info, blocks, split, halo }
}

/// Renders `source` whole and as `n` bricks.
fn whole_and_bricks(
    source: &str,
    n: usize,
    settings: &RenderSettings,
    camera: Camera,
    size: (u32, u32),
) -> Option<Renders> {
    let gpu = common::gpu()?;
    let Split { src, stream, info, blocks, split, halo } = split_of(source, n, settings);
    let view = View::whole(camera, size.0, size.1);

    let whole = src.load(None).unwrap();
    let gv = gpu.upload(&whole).unwrap();
    let single = gpu.render(&gv, &view, settings, None).unwrap().frame;

    let mut composite = Frame::new(size.0, size.1);
    composite.color = single.color.iter().map(|_| settings.background.map(|c| c as f32)).collect();
    composite.depth = vec![f32::INFINITY; single.pixel_count()];
    let mut frames = Vec::new();
    for b in &split {
        let (lo, hi) = b.data_range(halo, info.dims);
        let region = stream.read_region(&VoxelRange { lo, hi }).unwrap();
        // Resident volume bytes: the brick and its halo, never the whole volume.
        assert_eq!(region.resident_bytes(), b.data_samples(halo, info.dims) * 4);
        assert!(region.resident_bytes() < whole.resident_bytes() || n == 1);
        let (owned_min, owned_max) = b.owned_planes(info.dims, info.origin, info.spacing);
        let object = ObjectSpace { data_offset: lo, owned_min, owned_max };
        let gb = gpu.upload_brick(&region, &info, &blocks, object.clone()).unwrap();
        let f = gpu.render(&gb, &view, settings, None).unwrap().frame;
        for i in 0..f.pixel_count() {
            if f.hit[i] && f.depth[i] < composite.depth[i] {
                composite.depth[i] = f.depth[i];
                composite.color[i] = f.color[i];
                composite.hit[i] = true;
                composite.normal[i] = f.normal[i];
                composite.occlusion[i] = f.occlusion[i];
            }
        }
        frames.push((f, object));
    }
    Some((single, composite, frames, split))
}

fn settings_with_ao(iso: f64, radius: f64) -> RenderSettings {
    let mut s = RenderSettings::new(iso);
    s.ao.samples = 8;
    s.ao.radius = AoRadius::World(radius);
    s
}

/// The largest colour difference and the number of pixels that differ at all.
fn colour_diff(a: &Frame, b: &Frame) -> (f32, usize) {
    let mut max = 0f32;
    let mut n = 0;
    for (x, y) in a.color.iter().zip(&b.color) {
        let d = (0..3).map(|c| (x[c] - y[c]).abs()).fold(0f32, f32::max);
        max = max.max(d);
        n += usize::from(d > 0.0);
    }
    (max, n)
}

#[test]
fn two_and_four_bricks_composite_to_the_single_render_bit_for_bit() {
    // The sphere over a plane: the plane and the sphere are cut, and the AO radius (12 voxels)
    // spans every cut (the plane is occluded by the sphere across them).
    for n in [2, 4] {
        let s = settings_with_ao(0.0, 12.0);
        let cam = Camera {
            eye: DVec3::new(-30.0, -60.0, 70.0),
            target: DVec3::new(24.0, 24.0, 16.0),
            up: DVec3::Z,
            fov_y_deg: 40.0,
        };
        let Some((single, composite, frames, split)) =
            whole_and_bricks("procedural:sphere-over-plane:48", n, &s, cam, (96, 72))
        else {
            return;
        };
        assert_eq!(split.len(), n);
        let hits = single.hit_count();
        assert!(hits > 1000, "{hits}");
        // Every brick contributes: the cuts are in view.
        for (f, o) in &frames {
            assert!(f.hit_count() > 50, "brick at {:?} has {} hits", o.data_offset, f.hit_count());
        }
        // Tolerance: exact. The bricks march the single render's steps (t, samples, hits and the
        // AO rays' cells are the same f32 arithmetic), so the composite is the same image.
        assert_eq!(composite.hit, single.hit, "{n} bricks: hit masks differ");
        let depth_diff = single
            .depth
            .iter()
            .zip(&composite.depth)
            .zip(&single.hit)
            .filter(|(_, &h)| h)
            .map(|((a, b), _)| (a - b).abs())
            .fold(0f32, f32::max);
        assert_eq!(depth_diff, 0.0, "{n} bricks: depth differs");
        let (max, count) = colour_diff(&single, &composite);
        assert_eq!((max, count), (0.0, 0), "{n} bricks: colour differs at {count} pixels, by up to {max}");
        // (With the AO origin on the surface the plane under the sphere is a little less occluded
        // than from half a voxel above it: about 200 pixels have A > 0.1.)
        let occluded = single.occlusion.iter().filter(|&&a| a > 0.1).count();
        assert!(occluded > 150, "AO is visible: {occluded} pixels with A > 0.1");
    }
}

#[test]
fn pixels_along_the_cut_agree_and_a_brick_without_halo_would_differ() {
    // The sphere over a plane cut in two: look at the pixels whose hit lies within the AO radius
    // of the cut plane; they match the single render. Then the control: bricks read with a halo
    // of one sample (less than the stencil and the AO reach) shade those pixels differently (the
    // test can fail).
    let s = settings_with_ao(0.0, 12.0);
    let cam = Camera {
        eye: DVec3::new(-30.0, -60.0, 70.0),
        target: DVec3::new(24.0, 24.0, 16.0),
        up: DVec3::Z,
        fov_y_deg: 40.0,
    };
    let Some((single, composite, _frames, split)) =
        whole_and_bricks("procedural:sphere-over-plane:48", 2, &s, cam, (96, 72))
    else {
        return;
    };
    let b = &split[0];
    let axis = (0..3).find(|&a| b.hi[a] < 47).expect("a cut");
    let cut = b.hi[axis] as f64;
    let basis = cam.basis();
    let view = View::whole(cam, 96, 72);
    let mut near_cut = Vec::new();
    for i in 0..single.pixel_count() {
        if !single.hit[i] {
            continue;
        }
        let (x, y) = ((i % 96) as u32, (i / 96) as u32);
        let p = cam.eye + view.ray_dir(&basis, x, y) * single.depth[i] as f64;
        if (p[axis] - cut).abs() <= 12.0 {
            near_cut.push(i);
        }
    }
    assert!(near_cut.len() > 200, "{} pixels near the cut", near_cut.len());
    for &i in &near_cut {
        assert_eq!(composite.color[i], single.color[i], "pixel {i} near the cut");
    }

    // Control: the same brick with a halo of 1 sample (less than the stencil and the AO reach).
    let gpu = common::gpu().unwrap();
    let src: VolumeSource = "procedural:sphere-over-plane:48".parse().unwrap();
    let stream = src.stream(None).unwrap();
    let info = stream.info().clone();
    let blocks = stream.block_minmax(BlockMinMax::DEFAULT_BLOCK).unwrap();
    let mut nearest = vec![(f32::INFINITY, [0f32; 3]); single.pixel_count()];
    for brick in &split {
        let (lo, hi) = brick.data_range([1, 1, 1], info.dims);
        let region = stream.read_region(&VoxelRange { lo, hi }).unwrap();
        let (owned_min, owned_max) = brick.owned_planes(info.dims, info.origin, info.spacing);
        let gb = gpu
            .upload_brick(&region, &info, &blocks, ObjectSpace { data_offset: lo, owned_min, owned_max })
            .unwrap();
        let f = gpu.render(&gb, &view, &s, None).unwrap().frame;
        for (i, n) in nearest.iter_mut().enumerate() {
            if f.hit[i] && f.depth[i] < n.0 {
                *n = (f.depth[i], f.color[i]);
            }
        }
    }
    let differ = near_cut.iter().filter(|&&i| nearest[i].1 != single.color[i]).count();
    assert!(differ >= 10, "without a halo only {differ} of {} pixels near the cut differ", near_cut.len());
}

#[test]
fn the_covered_rect_holds_every_hit_of_a_brick() {
    let s = settings_with_ao(0.0, 8.0);
    let cam = Camera {
        eye: DVec3::new(-40.0, -50.0, 60.0),
        target: DVec3::new(20.0, 20.0, 20.0),
        up: DVec3::Z,
        fov_y_deg: 40.0,
    };
    let Some((_single, _c, frames, split)) = whole_and_bricks("procedural:gyroid:40", 4, &s, cam, (80, 64))
    else {
        return;
    };
    let view = View::whole(cam, 80, 64);
    for ((f, _), b) in frames.iter().zip(&split) {
        let (lo, hi) = b.owned_box(DVec3::ZERO, DVec3::ONE);
        let r = bricks::covered_rect(&view, lo, hi).expect("each brick shows");
        for i in 0..f.pixel_count() {
            let (x, y) = ((i % 80) as u32, (i / 80) as u32);
            if f.hit[i] {
                assert!(
                    x >= r.x && x < r.x + r.width && y >= r.y && y < r.y + r.height,
                    "hit ({x},{y}) outside {r:?}"
                );
            }
        }
    }
}

/// Object space, a time-varying volume: a brick's next step written into its buffers
/// (`GpuVolume::rewrite_brick`) renders exactly as that step uploaded afresh, and not as the
/// step before; a region of another size is refused.
#[test]
fn a_bricks_next_time_step_written_in_place_renders_as_a_fresh_upload() {
    let Some(gpu) = common::gpu() else { return };
    // Two steps of the torus at 32^3, the second moved 3 voxels along x.
    let torus = "procedural:torus:32".parse::<VolumeSource>().unwrap().load(None).unwrap();
    let [nx, ny, nz] = torus.dims();
    let dir = tempfile::tempdir().unwrap();
    for (k, shift) in [(0usize, 0usize), (1, 3)] {
        let mut bytes = format!(
            "NRRD0004\ntype: float\ndimension: 3\nsizes: {nx} {ny} {nz}\nendian: little\nencoding: raw\n\n"
        )
        .into_bytes();
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    bytes.extend(torus.at((x + shift).min(nx - 1), y, z).to_le_bytes());
                }
            }
        }
        std::fs::write(dir.path().join(format!("step_{k}.nrrd")), bytes).unwrap();
    }
    let src: VolumeSource = format!("{}/step_*.nrrd", dir.path().display()).parse().unwrap();
    let settings = settings_with_ao(0.0, 6.0);
    let stream = src.stream(None).unwrap();
    let info = stream.info().clone();
    let blocks = stream.block_minmax(BlockMinMax::DEFAULT_BLOCK).unwrap();
    let occ = Occupancy::from_minmax(blocks.block, blocks.counts, &blocks.minmax, settings.iso);
    let split = bricks::split(&occ, info.dims, info.spacing, 2).unwrap();
    let halo = bricks::halo_voxels(&settings, info.spacing).unwrap();
    let (lo, hi) = split[0].data_range(halo, info.dims);
    let range = VoxelRange { lo, hi };
    let (owned_min, owned_max) = split[0].owned_planes(info.dims, info.origin, info.spacing);
    let object = ObjectSpace { data_offset: lo, owned_min, owned_max };
    let camera = Camera {
        eye: DVec3::new(40.0, -45.0, 30.0),
        target: DVec3::splat(15.5),
        up: DVec3::Z,
        fov_y_deg: 40.0,
    };
    let view = View::whole(camera, 96, 72);
    let step = |k| src.read_step_region(None, k, &range, BlockMinMax::DEFAULT_BLOCK, &info).unwrap();
    let (s0, s1) = (step(0), step(1));

    let mut gv = gpu.upload_brick(&s0.region, &info, &s0.blocks, object.clone()).unwrap();
    let first = gpu.render(&gv, &view, &settings, None).unwrap().frame;
    let id = gv.id;
    gv.rewrite_brick(&gpu.ctx, &s1.region, &s1.blocks).unwrap();
    assert_eq!(gv.id, id, "the buffers (and the tiles' bind groups) are kept");
    let rewritten = gpu.render(&gv, &view, &settings, None).unwrap().frame;
    let fresh = gpu.upload_brick(&s1.region, &info, &s1.blocks, object.clone()).unwrap();
    let fresh = gpu.render(&fresh, &view, &settings, None).unwrap().frame;
    let (max, n) = colour_diff(&rewritten, &fresh);
    assert_eq!((max, n), (0.0, 0), "the rewritten brick renders differently from a fresh upload");
    assert_eq!(rewritten.depth, fresh.depth);
    let lit = fresh.hit.iter().filter(|&&h| h).count();
    assert!(lit > 200, "the brick is hardly in view ({lit} pixels)");
    let (_, n) = colour_diff(&first, &fresh);
    assert!(n > 100, "the two steps differ in only {n} pixels");
    // Another size does not fit the buffers.
    let smaller = VoxelRange { lo, hi: [hi[0] - 1, hi[1], hi[2]] };
    let other = src.read_step_region(None, 1, &smaller, BlockMinMax::DEFAULT_BLOCK, &info).unwrap();
    let e = gv.rewrite_brick(&gpu.ctx, &other.region, &other.blocks).unwrap_err().to_string();
    assert!(e.contains("does not fit the buffers"), "{e}");
}

/// The right half (`x0 .. x0 + w`) of a `full`-pixel image as a tile's view.
fn tile_view(camera: Camera, full: (u32, u32), x0: u32, w: u32) -> View {
    View {
        rect: isowall_model::Rect { x: x0, y: 0, width: w, height: full.1 },
        ..View::whole(camera, full.0, full.1)
    }
}

/// Object space with the filter on the composited tile: every brick renders the tile's canvas
/// (its rectangle grown by the guard band) and reads back its shading share, the nearest hit of
/// the bricks is kept per pixel, and the owner filters and composes the canvas
/// (`GpuRenderer::compose_canvas`). Returns the owner's tile image (sRGB8).
fn composited_canvas(
    gpu: &isowall_render::gpu::GpuRenderer,
    source: &str,
    n: usize,
    settings: &RenderSettings,
    view: &View,
    guard: u32,
) -> Vec<u8> {
    use isowall_model::composite::PixelForm;
    use isowall_render::gpu::tile::work_view;
    use isowall_render::gpu::{CanvasFrame, ReadbackRing, TileFrame, TileTarget};
    let Split { stream, info, blocks, split, halo, .. } = split_of(source, n, settings);
    let canvas_view = work_view(view, 1, guard);
    let pixels = canvas_view.rect.width as usize * canvas_view.rect.height as usize;
    let mut canvas = vec![[[0f32; 4]; 4]; pixels];
    let mut nearest = vec![f32::INFINITY; pixels];
    let mut ring = ReadbackRing::new(2);
    let mut raw = *settings;
    raw.denoise = isowall_model::Denoise::Off;
    let mut volumes = Vec::new();
    for b in &split {
        let (lo, hi) = b.data_range(halo, info.dims);
        let region = stream.read_region(&VoxelRange { lo, hi }).unwrap();
        let (owned_min, owned_max) = b.owned_planes(info.dims, info.origin, info.spacing);
        let gb = gpu
            .upload_brick(&region, &info, &blocks, ObjectSpace { data_offset: lo, owned_min, owned_max })
            .unwrap();
        let mut share = TileTarget::new(gpu, "brick", &canvas_view, 1).unwrap();
        let frame = TileFrame {
            frame_id: 1,
            volume: &gb,
            view: &canvas_view,
            settings: &raw,
            env: None,
            continuity: Continuity::Changed,
            temporal: false,
            share: Some(PixelForm::Shading),
        };
        let out = common::render_tile_and_read(gpu, &mut share, &mut ring, &frame);
        let (depth, shading) = (out.depth.unwrap(), out.shading.unwrap());
        assert_eq!((depth.len(), shading.len()), (pixels, pixels));
        for i in 0..pixels {
            if depth[i] < nearest[i] {
                nearest[i] = depth[i];
                canvas[i] = shading[i];
            }
        }
        volumes.push(gb);
    }
    let mut owner = TileTarget::with_guard(gpu, "tile", view, 1, guard).unwrap();
    let frame = CanvasFrame { frame_id: 1, volume: &volumes[0], view, settings, env: None };
    gpu.compose_canvas(&mut owner, &frame, &canvas, &mut ring).unwrap();
    ring.wait_oldest(&gpu.ctx).unwrap();
    let mut reads = ring.take_ready();
    let out = isowall_render::gpu::FrameRead::decode(reads.remove(0), 1.0).unwrap().1;
    out.rgb8.unwrap()
}

#[test]
fn bricks_filtered_on_the_composited_canvas_give_the_single_denoised_render() {
    use isowall_model::composite::PixelForm;
    use isowall_render::denoise::reach;
    use isowall_render::gpu::{ReadbackRing, TileFrame, TileTarget};
    let Some(gpu) = common::gpu() else { return };
    let source = "procedural:sphere-over-plane:48";
    // Ambient light only: the colour is albedo * ambient * (1 - A), the occlusion made visible.
    let mut s = settings_with_ao(0.0, 12.0);
    s.ao.samples = 4;
    s.light.color = [0.0; 3];
    s.light.ambient = [1.0; 3];
    s.denoise = isowall_model::Denoise::On;
    let cam = Camera {
        eye: DVec3::new(-30.0, -60.0, 70.0),
        target: DVec3::new(24.0, 24.0, 16.0),
        up: DVec3::Z,
        fov_y_deg: 40.0,
    };
    let full = (192, 144);
    // The right half of the image: its left edge is inside the image, so its guard band matters.
    let view = tile_view(cam, full, 96, 96);
    let whole = gpu.upload(&src_load(source)).unwrap();
    let mut ring = ReadbackRing::new(2);
    let mut single_image = |settings: &RenderSettings| {
        let mut t = TileTarget::with_guard(&gpu, "single", &view, 1, reach()).unwrap();
        let frame = TileFrame {
            frame_id: 1,
            volume: &whole,
            view: &view,
            settings,
            env: None,
            continuity: Continuity::Changed,
            temporal: false,
            share: Some(PixelForm::Colour),
        };
        common::render_tile_and_read(&gpu, &mut t, &mut ring, &frame).rgb8.unwrap()
    };
    let single = single_image(&s);
    let mut raw_settings = s;
    raw_settings.denoise = isowall_model::Denoise::Off;
    let raw = single_image(&raw_settings);
    let max_diff = |a: &[u8], b: &[u8]| a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max().unwrap_or(0);
    let filtered_by = max_diff(&single, &raw);
    assert!(filtered_by >= 8, "the filter hardly changed the image ({filtered_by} levels)");

    for n in [2, 4] {
        let composited = composited_canvas(&gpu, source, n, &s, &view, reach());
        let d = max_diff(&composited, &single);
        let differ = composited.iter().zip(&single).filter(|(a, b)| a != b).count();
        eprintln!("{n} bricks, guard {}: max {d} levels, {differ} values differ; the filter moved the image by up to {filtered_by} levels", reach());
        // The stated tolerance: within one level (in practice the same f32 arithmetic).
        assert!(
            d <= 1,
            "{n} bricks: the composited canvas is {d} levels off the single render ({differ} values differ)"
        );
    }
    // A frame whose `denoise` is off, from the same shares, is the unfiltered single render.
    let unfiltered = composited_canvas(&gpu, source, 2, &raw_settings, &view, reach());
    let d = max_diff(&unfiltered, &raw);
    assert!(d <= 1, "the unfiltered canvas is {d} levels off the single raw render");
    // Control: a guard band of 4 pixels filters the tile's edge without most of its neighbours.
    let narrow = composited_canvas(&gpu, source, 2, &s, &view, 4);
    let d = max_diff(&narrow, &single);
    let differ = narrow.iter().zip(&single).filter(|(a, b)| a != b).count();
    eprintln!("2 bricks, guard 4: max {d} levels, {differ} values differ");
    assert!(d > 1, "with a too-narrow guard band the canvas still matches (max {d} levels)");
}

fn src_load(source: &str) -> isowall_volume::Volume {
    source.parse::<VolumeSource>().unwrap().load(None).unwrap()
}
