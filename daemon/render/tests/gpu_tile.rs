//! A wall tile's frame on the GPU (`TileTarget`, `Kernel::Compose`): the compose kernel against
//! the host's compose of the same AOVs and against the CPU reference's colour, progressive
//! accumulation against `render_accumulated`, the restart on a change of frame state, and the
//! counts that make a steady frame cheap: no allocation, only the counters read back (colour and
//! depth for a share).

mod common;

use isowall_model::composite::PixelForm;
use isowall_model::wire::Continuity;
use isowall_model::{Camera, RenderSettings, View};
use isowall_render::gpu::{
    FrameRead, GpuRenderer, GpuVolume, ReadbackRing, TileFrame, TileOutput, TileTarget,
};
use isowall_render::output::srgb8;
use isowall_render::reference;
use isowall_volume::procedural::Procedural;
use isowall_volume::{Volume, VolumeSource};

const W: u32 = 64;
const H: u32 = 48;

fn scene() -> (Volume, View, RenderSettings) {
    let src = VolumeSource::Procedural { kind: Procedural::SphereOverPlane, size: Some(40) };
    let volume = src.load(None).unwrap();
    let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), W, H), W, H);
    let settings = RenderSettings::new(Procedural::SphereOverPlane.natural_iso());
    (volume, view, settings)
}

/// Renders one frame of the tile and waits for its read.
fn frame(
    gpu: &GpuRenderer,
    tile: &mut TileTarget,
    ring: &mut ReadbackRing<FrameRead>,
    gv: &GpuVolume,
    view: &View,
    s: &RenderSettings,
    continuity: Continuity,
) -> TileOutput {
    let f = TileFrame {
        frame_id: 1,
        volume: gv,
        view,
        settings: s,
        env: None,
        continuity,
        temporal: false,
        share: Some(PixelForm::Colour),
    };
    common::render_tile_and_read(gpu, tile, ring, &f)
}

/// (channel values that differ, the largest difference in levels).
fn differences(a: &[u8], b: &[u8]) -> (usize, u8) {
    assert_eq!(a.len(), b.len());
    let d: Vec<u8> = a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).collect();
    (d.iter().filter(|&&x| x > 0).count(), d.iter().copied().max().unwrap_or(0))
}

#[test]
fn the_compose_kernel_is_the_host_compose_and_follows_the_reference() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, mut s) = scene();
    let gv = gpu.upload(&volume).unwrap();
    let mut ring = ReadbackRing::new(2);
    for samples in [0, 8] {
        s.ao.samples = samples;
        s.exposure = 1.3;
        let mut tile = TileTarget::new(&gpu, "t", &view, 1).unwrap();
        let out = frame(&gpu, &mut tile, &mut ring, &gv, &view, &s, Continuity::Changed);
        let host = gpu.render(&gv, &view, &s, None).unwrap().frame;
        let (n, max) = differences(out.rgb8.as_ref().unwrap(), &srgb8(&host));
        eprintln!("{samples} samples: {n} channel values differ from the host's compose, by at most {max}");
        assert!(max <= 1 && n * 200 <= host.pixel_count() * 3, "{n} values differ, by up to {max} levels");
        // Depth: the frame's where it hits, +inf elsewhere.
        let depth = out.depth.as_ref().unwrap();
        assert_eq!(depth.len(), host.pixel_count());
        for (i, &d) in depth.iter().enumerate() {
            let want = if host.hit[i] { host.depth[i] } else { f32::INFINITY };
            assert_eq!(d, want, "pixel {i}");
        }
        assert_eq!(out.counters.hits, host.hit_count() as u64);
        assert_eq!(out.counters.fetches, host.fetches);
        assert_eq!(out.counters.pixels, (W * H) as u64);
    }
    // Against the CPU reference's own compose (no AO: E = ambient): the colour of pixels both hit.
    s.ao.samples = 0;
    let mut tile = TileTarget::new(&gpu, "t", &view, 1).unwrap();
    let out = frame(&gpu, &mut tile, &mut ring, &gv, &view, &s, Continuity::Changed);
    let r = reference::render(&volume, &view, &s);
    let rgb = out.rgb8.unwrap();
    let want = srgb8(&r);
    let depth = out.depth.unwrap();
    let mut diffs: Vec<u8> = (0..r.pixel_count())
        .filter(|&i| r.hit[i] && depth[i].is_finite())
        .map(|i| (0..3).map(|c| rgb[3 * i + c].abs_diff(want[3 * i + c])).max().unwrap())
        .collect();
    diffs.sort();
    assert!(diffs.len() > 500, "too few hits ({})", diffs.len());
    assert!(
        diffs[diffs.len() / 2] <= 1,
        "median difference {} levels from the reference",
        diffs[diffs.len() / 2]
    );
    assert!(diffs[diffs.len() * 9 / 10] <= 3, "90th percentile {} levels", diffs[diffs.len() * 9 / 10]);
    // Background pixels are the background exactly.
    let bg = srgb8(&r);
    for i in (0..r.pixel_count()).filter(|&i| !r.hit[i] && !depth[i].is_finite()) {
        assert_eq!(rgb[3 * i..3 * i + 3], bg[3 * i..3 * i + 3], "background pixel {i}");
    }
}

#[test]
fn accumulation_on_the_gpu_averages_the_frames_and_restarts_when_the_state_changes() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, mut s) = scene();
    let gv = gpu.upload(&volume).unwrap();
    let mut ring = ReadbackRing::new(2);
    let mut tile = TileTarget::new(&gpu, "t", &view, 1).unwrap();
    s.ao.samples = 2;
    let frames = 6;
    let mut out = TileOutput::default();
    for k in 0..frames {
        let mut f = s;
        f.ao.frame = s.ao.frame + k;
        let c = common::continuity((k > 0).then_some((&view, &s)), &view, &f);
        out = frame(&gpu, &mut tile, &mut ring, &gv, &view, &f, c);
    }
    assert_eq!(tile.frames(), frames);
    let want = gpu.render_accumulated(&gv, &view, &s, None, frames).unwrap().frame;
    let (n, max) = differences(out.rgb8.as_ref().unwrap(), &srgb8(&want));
    eprintln!("{frames} frames: {n} channel values differ from render_accumulated, by at most {max}");
    assert!(max <= 1 && n * 100 <= want.pixel_count() * 3, "{n} values differ, by up to {max} levels");
    // And it is not the single first frame: the frames were averaged.
    let single = gpu.render(&gv, &view, &s, None).unwrap().frame;
    let (n, _) = differences(out.rgb8.as_ref().unwrap(), &srgb8(&single));
    assert!(n > 100, "only {n} values differ from a single frame");

    // A change of state restarts the sums: the model's rule says so, and the frame plan follows.
    let mut moved = s;
    moved.iso += 0.05;
    moved.ao.frame = s.ao.frame + frames;
    let c = common::continuity(Some((&view, &s)), &view, &moved);
    assert_eq!(c, Continuity::Changed);
    let out = frame(&gpu, &mut tile, &mut ring, &gv, &view, &moved, c);
    assert_eq!(tile.frames(), 1);
    let want = gpu.render(&gv, &view, &moved, None).unwrap().frame;
    let (n, max) = differences(out.rgb8.as_ref().unwrap(), &srgb8(&want));
    assert!(max <= 1 && n * 100 <= want.pixel_count() * 3, "after the change: {n} values differ");
}

#[test]
fn a_steady_tile_allocates_nothing_and_reads_back_only_what_leaves_the_node() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, mut s) = scene();
    s.ao.samples = 2;
    let gv = gpu.upload(&volume).unwrap();
    let mut ring = ReadbackRing::new(3);
    let mut tile = TileTarget::new(&gpu, "t", &view, 2).unwrap();
    let timestamps = if gpu.ctx.device.features().contains(wgpu::Features::TIMESTAMP_QUERY) { 48 } else { 0 };
    let params = (std::mem::size_of::<isowall_render::gpu::FrameParams>()
        + std::mem::size_of::<isowall_render::gpu::ComposeParams>()) as u64;
    for share in [false, true] {
        let run = |ring: &mut ReadbackRing<FrameRead>, tile: &mut TileTarget, k: u32| {
            let mut f = s;
            f.ao.frame = k;
            let tf = TileFrame {
                frame_id: k as u64,
                volume: &gv,
                view: &view,
                settings: &f,
                env: None,
                continuity: if k > 0 { Continuity::Same } else { Continuity::Changed },
                // A still camera never reprojects: temporal on changes nothing.
                temporal: true,
                share: share.then_some(PixelForm::Colour),
            };
            gpu.render_tile(tile, &tf, ring).unwrap();
        };
        // Warm: the ring's staging buffers are made as first needed.
        for k in 0..3 {
            run(&mut ring, &mut tile, k);
        }
        while ring.in_flight() > 0 {
            ring.wait_oldest(&gpu.ctx).unwrap();
        }
        ring.take_ready();
        let before = gpu.ctx.traffic.now();
        let n = 6u64;
        for k in 3..3 + n as u32 {
            if !ring.has_free_slot() {
                ring.wait_oldest(&gpu.ctx).unwrap();
            }
            run(&mut ring, &mut tile, k);
        }
        while ring.in_flight() > 0 {
            ring.wait_oldest(&gpu.ctx).unwrap();
        }
        let reads = ring.take_ready();
        let t = gpu.ctx.traffic.now() - before;
        assert_eq!(reads.len() as u64, n);
        assert_eq!(t.allocations, 0, "share {share}: {} GPU allocations in {n} steady frames", t.allocations);
        assert_eq!(t.uploaded, n * params, "share {share}: bytes uploaded");
        let pixels = (W * H) as u64;
        let per_frame = isowall_render::gpu::tile::COUNTER_BYTES
            + timestamps
            + if share { pixels * 4 + pixels * 4 } else { 0 };
        assert_eq!(t.read_back, n * per_frame, "share {share}: bytes read back");
    }
    // A resize (another tile size) needs new resources, which the tile says.
    let small = View::whole(view.camera, W / 2, H / 2);
    assert!(!tile.fits(&small, 2) && !tile.fits(&view, 1) && tile.fits(&view, 2));
}

/// Object space's images of a tile composited on the CPU (`ShownImages`, what its windows show):
/// made once, then each frame is one upload into the image holding the oldest frame, with no
/// allocation; an image of the wrong size is refused, and what is on show stays.
#[test]
fn a_tile_composited_on_the_cpu_is_uploaded_into_its_images_without_allocating() {
    use isowall_render::gpu::tile::{Presentable, ShownImages, IMAGES};
    let Some(gpu) = common::gpu() else { return };
    let mut shown = ShownImages::new(&gpu, "t", (W, H)).unwrap();
    assert!(ShownImages::new(&gpu, "t", (0, H)).is_err());
    let rgb8 = vec![7u8; (3 * W * H) as usize];
    gpu.show_image(&mut shown, 0, &rgb8).unwrap();
    let before = gpu.ctx.traffic.now();
    for frame_id in 1..=5u64 {
        gpu.show_image(&mut shown, frame_id, &rgb8).unwrap();
        // The last IMAGES frames are held, each in its own image.
        let mut held: Vec<u64> = shown.images().iter().filter_map(|i| i.frame_id).collect();
        held.sort_unstable();
        let first = (frame_id + 1).saturating_sub(IMAGES as u64);
        assert_eq!(held, (first..=frame_id).collect::<Vec<_>>(), "after frame {frame_id}");
    }
    let t = gpu.ctx.traffic.now() - before;
    assert_eq!(t.allocations, 0, "{t:?}");
    assert_eq!(t.uploaded, 5 * 4 * (W * H) as u64, "{t:?}");
    let e = gpu.show_image(&mut shown, 6, &rgb8[3..]).unwrap_err().to_string();
    assert!(e.contains("tile t") && e.contains(&format!("{W}x{H}")), "{e}");
    assert!(shown.images().iter().all(|i| i.frame_id != Some(6)));
}

/// A balanced wall renders a tile as bands of rows, each its own view and target, on whichever
/// node the split names: each band must be the tile's own pixels there, bit for bit, filtered or
/// not (a band renders the filter's guard band as a tile does), on its first frame and as it
/// accumulates.
#[test]
fn a_tile_cut_into_bands_renders_the_tiles_own_pixels_filtered_or_not() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, mut s) = common::ambient_sphere_scene(W, H);
    let gv = gpu.upload(&volume).unwrap();
    for denoise in [isowall_model::Denoise::Off, isowall_model::Denoise::On] {
        s.denoise = denoise;
        let guard = if denoise.is_on() { isowall_render::denoise::reach() } else { 0 };
        let mut ring = ReadbackRing::new(2);
        let mut whole = TileTarget::with_guard(&gpu, "t", &view, 1, guard).unwrap();
        // Cuts through the surface, at rows that are no multiple of anything (without the guard
        // band, the filtered frames differ there by up to 8 levels).
        let bands: Vec<View> = [(0, 11), (11, 12), (23, 9), (32, H - 32)]
            .into_iter()
            .map(|(y, h)| {
                let mut v = view;
                v.rect.y = y;
                v.rect.height = h;
                v
            })
            .collect();
        let mut targets: Vec<TileTarget> =
            bands.iter().map(|b| TileTarget::with_guard(&gpu, "band", b, 1, guard).unwrap()).collect();
        for (k, continuity) in
            [Continuity::Changed, Continuity::Same, Continuity::Same].into_iter().enumerate()
        {
            let mut f = s;
            f.ao.frame = k as u32;
            fn tf<'a>(
                k: usize,
                gv: &'a GpuVolume,
                v: &'a View,
                f: &'a RenderSettings,
                continuity: Continuity,
            ) -> TileFrame<'a> {
                TileFrame {
                    frame_id: k as u64 + 1,
                    volume: gv,
                    view: v,
                    settings: f,
                    env: None,
                    continuity,
                    temporal: true,
                    share: Some(PixelForm::Colour),
                }
            }
            let want =
                common::render_tile_and_read(&gpu, &mut whole, &mut ring, &tf(k, &gv, &view, &f, continuity));
            let (mut rgb8, mut depth) = (Vec::new(), Vec::new());
            for (t, b) in targets.iter_mut().zip(&bands) {
                let got = common::render_tile_and_read(&gpu, t, &mut ring, &tf(k, &gv, b, &f, continuity));
                rgb8.extend(got.rgb8.unwrap());
                depth.extend(got.depth.unwrap());
            }
            let want_rgb8 = want.rgb8.unwrap();
            assert_eq!(differences(&rgb8, &want_rgb8), (0, 0), "{denoise:?}, frame {k}: the bands' colour");
            assert_eq!(depth, want.depth.unwrap(), "{denoise:?}, frame {k}: the bands' depth");
            // The scene is in view and its occlusion varies: the comparison sees something.
            assert!(want_rgb8.chunks(3).any(|p| p != &want_rgb8[..3]));
        }
    }
}

/// The GPU bytes a tile holds per pixel once every resource a frame may make is made (its AOVs,
/// the sample positions of a temporal tile, the history of a reprojected frame, the filter's
/// buffers, depth and its presentable images), counted from the allocations the renderer makes
/// (`GpuTraffic`), are the model's `GPU_BYTES_PER_TILE_PIXEL`, by which `check-config` refuses a
/// node given more tiles than its GPU holds. A buffer added to the tile, or one made larger,
/// fails here until the bound says so.
#[test]
fn a_tiles_gpu_bytes_per_pixel_are_the_models_bound() {
    use isowall_model::config::GPU_BYTES_PER_TILE_PIXEL;
    use isowall_model::Denoise;
    let Some(gpu) = common::gpu() else { return };
    let (volume, _, mut s) = scene();
    s.ao.samples = 2;
    s.denoise = Denoise::On;
    let gv = gpu.upload(&volume).unwrap();
    // The bytes allocated for a tile of `w`x`h` and its frames: a still one, then the camera
    // panning (reprojected, denoised). What does not grow with the tile (parameters, counters,
    // the ring's staging, whatever the renderer makes once) cancels in the difference of two sizes.
    let bytes = |w: u32, h: u32| {
        let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), w, h), w, h);
        let mut ring = ReadbackRing::new(4);
        let before = gpu.ctx.traffic.now();
        let mut tile = TileTarget::new(&gpu, "t", &view, 1).unwrap();
        let mut previous: Option<View> = None;
        for k in 0..4u32 {
            let c = view.camera;
            let by = glam::DVec3::new(0.05 * k as f64, 0.0, 0.0);
            let moved = View { camera: Camera { eye: c.eye + by, target: c.target + by, ..c }, ..view };
            let mut f = s;
            f.ao.frame = k;
            let tf = TileFrame {
                frame_id: k as u64,
                volume: &gv,
                view: &moved,
                settings: &f,
                env: None,
                continuity: common::continuity(previous.as_ref().map(|p| (p, &s)), &moved, &s),
                temporal: true,
                share: None,
            };
            if !ring.has_free_slot() {
                ring.wait_oldest(&gpu.ctx).unwrap();
            }
            gpu.render_tile(&mut tile, &tf, &mut ring).unwrap();
            previous = Some(moved);
        }
        while ring.in_flight() > 0 {
            ring.wait_oldest(&gpu.ctx).unwrap();
        }
        (gpu.ctx.traffic.now() - before).allocated_bytes
    };
    // The renderer's own first-use objects are made before the sizes are compared.
    bytes(8, 6);
    let (small, large) = ((W, H), (2 * W, 2 * H));
    let (a, b) = (bytes(small.0, small.1), bytes(large.0, large.1));
    let pixels = |(w, h): (u32, u32)| u64::from(w) * u64::from(h);
    let grown = pixels(large) - pixels(small);
    eprintln!("tile {}x{}: {a} bytes; {}x{}: {b} bytes", small.0, small.1, large.0, large.1);
    assert_eq!((b - a) % grown, 0, "{} bytes more for {grown} pixels more", b - a);
    assert_eq!(
        (b - a) / grown,
        GPU_BYTES_PER_TILE_PIXEL,
        "the bytes a tile pixel takes on the GPU (left) against the model's GPU_BYTES_PER_TILE_PIXEL"
    );
}
