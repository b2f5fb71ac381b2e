//! The edge-aware spatial filter (`Kernel::Denoise`): the GPU against its CPU twin
//! (`isowall_render::denoise::filter`) on the same inputs; what it is for (a few samples closer to
//! the converged occlusion than raw); what it must not do (change a converged image, blur across a
//! silhouette); and wall consistency: tiles rendered with a guard band of the filter's reach
//! compose the whole image's pixels, the edges included, and a narrower band does not; a steady
//! denoised tile allocates nothing and counts its own pixels, not its guard band's.

mod common;

use isowall_model::composite::PixelForm;
use isowall_model::wire::Continuity;
use isowall_model::{Denoise, Rect, RenderSettings, View};
use isowall_render::denoise::{self, Input};
use isowall_render::gpu::{FrameRead, GpuRenderer, GpuVolume, ReadbackRing, TileFrame, TileTarget};
use isowall_render::Frame;

fn render(
    gpu: &GpuRenderer,
    gv: &GpuVolume,
    view: &View,
    s: &RenderSettings,
    frames: u32,
    on: bool,
) -> Frame {
    let mut s = *s;
    s.denoise = if on { Denoise::On } else { Denoise::Off };
    gpu.render_accumulated(gv, view, &s, None, frames).unwrap().frame
}

fn cpu_filter(view: &View, raw: &Frame, samples: u64) -> (Vec<f32>, Vec<[f32; 3]>) {
    denoise::filter(&Input {
        view,
        hit: &raw.hit,
        depth: &raw.depth,
        normal: &raw.normal,
        occlusion: &raw.occlusion,
        ibl: &raw.ibl,
        samples,
        pixel_samples: None,
    })
}

#[test]
fn the_gpu_filter_is_its_cpu_twin() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, s) = common::ambient_sphere_scene(64, 48);
    let gv = gpu.upload(&volume).unwrap();
    for frames in [1, 3] {
        let raw = render(&gpu, &gv, &view, &s, frames, false);
        let gpu_den = render(&gpu, &gv, &view, &s, frames, true);
        let (occ, ibl) = cpu_filter(&view, &raw, s.ao.samples as u64 * frames as u64);
        let (mut max, mut changed) = (0.0f32, 0.0f64);
        for i in 0..raw.pixel_count() {
            assert_eq!(gpu_den.hit[i], raw.hit[i]);
            max = max.max((gpu_den.occlusion[i] - occ[i]).abs());
            for (g, c) in gpu_den.ibl[i].iter().zip(&ibl[i]) {
                max = max.max((g - c).abs());
            }
            changed += (gpu_den.occlusion[i] - raw.occlusion[i]).abs() as f64;
        }
        let changed = changed / raw.hit_count() as f64;
        eprintln!(
            "{frames} frames: GPU vs CPU twin max |diff| {max:.2e}; mean change by the filter {changed:.4}"
        );
        // The filter does something (so the comparison means something) ...
        assert!(changed > 0.003, "the filter changed the occlusion by {changed} on average");
        // ... and the GPU does what the CPU twin does (f32 exp on both; rounding only).
        assert!(max < 1e-3, "GPU and CPU twin differ by up to {max}");
    }
}

#[test]
fn four_samples_denoised_are_closer_to_the_converged_occlusion_than_raw() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, s) = common::ambient_sphere_scene(192, 144);
    let gv = gpu.upload(&volume).unwrap();
    // 4 x 128 samples per pixel: the converged occlusion of the same estimator.
    let converged = render(&gpu, &gv, &view, &s, 128, false);
    let raw = render(&gpu, &gv, &view, &s, 1, false);
    let den = render(&gpu, &gv, &view, &s, 1, true);
    let error =
        |f: &Frame| common::rmse(&f.occlusion, &converged.occlusion, |i| converged.hit[i] && f.hit[i]);
    let (e_raw, e_den) = (error(&raw), error(&den));
    eprintln!("occlusion RMSE against 512 spp: raw 4 spp {e_raw:.4}, denoised 4 spp {e_den:.4}");
    assert!(e_den < 0.5 * e_raw, "denoised {e_den} against raw {e_raw}");
}

#[test]
fn a_converged_image_barely_changes() {
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, s) = common::ambient_sphere_scene(64, 48);
    let gv = gpu.upload(&volume).unwrap();
    let change = |frames: u32| {
        let raw = render(&gpu, &gv, &view, &s, frames, false);
        let den = render(&gpu, &gv, &view, &s, frames, true);
        let d: Vec<f32> = (0..raw.pixel_count())
            .filter(|&i| raw.hit[i])
            .map(|i| (den.occlusion[i] - raw.occlusion[i]).abs())
            .collect();
        let mean = d.iter().sum::<f32>() / d.len() as f32;
        (mean, d.iter().copied().fold(0.0f32, f32::max))
    };
    let (few_mean, _) = change(1);
    let (many_mean, many_max) = change(256);
    eprintln!("mean |denoised - raw|: 4 spp {few_mean:.4}; 1024 spp {many_mean:.5} (max {many_max:.4})");
    assert!(many_mean < 0.002 && many_max < 0.03, "1024 spp: mean {many_mean}, max {many_max}");
    assert!(few_mean > 10.0 * many_mean, "4 spp {few_mean}, 1024 spp {many_mean}");
}

#[test]
fn silhouettes_keep_their_edges() {
    // The sphere's outline over the plane: a pixel on the sphere next to plane pixels far behind
    // it (a depth step) takes nothing from them, so a converged-enough image keeps the occlusion
    // step at the outline: the filter changes outline pixels no more than it changes others.
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, s) = common::ambient_sphere_scene(64, 48);
    let gv = gpu.upload(&volume).unwrap();
    let converged = render(&gpu, &gv, &view, &s, 256, false);
    let raw = render(&gpu, &gv, &view, &s, 4, false);
    let den = render(&gpu, &gv, &view, &s, 4, true);
    let w = view.rect.width as usize;
    let (mut edge, mut inner) = (Vec::new(), Vec::new());
    for i in 0..raw.pixel_count() {
        if !raw.hit[i] || !converged.hit[i] {
            continue;
        }
        let (x, y) = (i % w, i / w);
        let step = [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)].iter().any(|&(dx, dy)| {
            let (qx, qy) = (x as i64 + dx, y as i64 + dy);
            if qx < 0 || qy < 0 || qx >= w as i64 || qy >= view.rect.height as i64 {
                return false;
            }
            let q = qx as usize + qy as usize * w;
            raw.hit[q] && (raw.depth[q] - raw.depth[i]).abs() > 0.05 * raw.depth[i]
        });
        let err = (den.occlusion[i] - converged.occlusion[i]).abs();
        if step {
            edge.push(err);
        } else {
            inner.push(err);
        }
    }
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len().max(1) as f32;
    eprintln!(
        "denoised 16 spp error against 1024 spp: {} outline pixels {:.4}, {} others {:.4}",
        edge.len(),
        mean(&edge),
        inner.len(),
        mean(&inner)
    );
    assert!(edge.len() >= 10, "the scene has {} outline pixels", edge.len());
    assert!(mean(&edge) < 2.0 * mean(&inner) + 0.01, "outline {} others {}", mean(&edge), mean(&inner));
}

/// The tile showing `rect` of `view`'s whole image, one denoised frame, its 8-bit image.
fn tile_image(
    gpu: &GpuRenderer,
    gv: &GpuVolume,
    view: &View,
    rect: Rect,
    s: &RenderSettings,
    guard: u32,
) -> Vec<u8> {
    let tile_view = View { rect, ..*view };
    let mut tile = TileTarget::with_guard(gpu, "t", &tile_view, 1, guard).unwrap();
    let mut ring = ReadbackRing::new(2);
    let f = TileFrame {
        frame_id: 1,
        volume: gv,
        view: &tile_view,
        settings: s,
        env: None,
        continuity: Continuity::Changed,
        temporal: false,
        share: Some(PixelForm::Colour),
    };
    common::render_tile_and_read(gpu, &mut tile, &mut ring, &f).rgb8.unwrap()
}

/// The 2x2 wall's tiles with `guard`, against the whole image: (largest difference in levels, mean
/// difference over the pixels within 2 of a tile edge).
fn seam_error(gpu: &GpuRenderer, gv: &GpuVolume, view: &View, s: &RenderSettings, guard: u32) -> (u8, f64) {
    let (w, h) = view.full;
    let whole = tile_image(gpu, gv, view, view.rect, s, 0);
    let (hw, hh) = (w / 2, h / 2);
    let (mut max, mut edge_sum, mut edge_n) = (0u8, 0u64, 0u64);
    for (x0, y0) in [(0, 0), (hw, 0), (0, hh), (hw, hh)] {
        let rect = Rect {
            x: x0,
            y: y0,
            width: if x0 == 0 { hw } else { w - hw },
            height: if y0 == 0 { hh } else { h - hh },
        };
        let img = tile_image(gpu, gv, view, rect, s, guard);
        for y in 0..rect.height {
            for x in 0..rect.width {
                let (fx, fy) = (x0 + x, y0 + y);
                let near_seam = fx.abs_diff(hw) <= 2 || fy.abs_diff(hh) <= 2;
                for c in 0..3 {
                    let a = img[((x + y * rect.width) * 3 + c) as usize];
                    let b = whole[((fx + fy * w) * 3 + c) as usize];
                    let d = a.abs_diff(b);
                    max = max.max(d);
                    if near_seam {
                        edge_sum += d as u64;
                        edge_n += 1;
                    }
                }
            }
        }
    }
    (max, edge_sum as f64 / edge_n.max(1) as f64)
}

#[test]
fn a_2x2_wall_with_the_guard_band_is_the_whole_denoised_image() {
    let Some(gpu) = common::gpu() else { return };
    // Larger than twice the reach, so that a tile's band does not cover the whole image.
    let (volume, view, mut s) = common::ambient_sphere_scene(256, 192);
    s.denoise = Denoise::On;
    let gv = gpu.upload(&volume).unwrap();
    let (max, edge) = seam_error(&gpu, &gv, &view, &s, denoise::reach());
    let (narrow_max, narrow_edge) = seam_error(&gpu, &gv, &view, &s, 4);
    eprintln!(
        "2x2 wall vs whole, denoised: guard {} max {max} levels, mean at the seams {edge:.4}; \
         guard 4: max {narrow_max}, mean at the seams {narrow_edge:.4}",
        denoise::reach()
    );
    // The stated tolerance: the tiles' pixels are the whole image's, within one level.
    assert!(max <= 1, "full band: up to {max} levels");
    // A too-narrow band shows at the seams.
    assert!(
        narrow_max > max && narrow_edge > edge + 0.01,
        "narrow {narrow_max}/{narrow_edge} vs {max}/{edge}"
    );
}

#[test]
fn a_steady_denoised_tile_allocates_nothing() {
    // The filter's buffers are made on the tile's first denoised frame and kept; a steady frame
    // uploads only the parameters (the frame's, compose's and the passes').
    let Some(gpu) = common::gpu() else { return };
    let (volume, view, mut s) = common::ambient_sphere_scene(64, 48);
    s.denoise = Denoise::On;
    let gv = gpu.upload(&volume).unwrap();
    let rect = Rect { x: 0, y: 0, width: 32, height: 24 };
    let tile_view = View { rect, ..view };
    let mut tile = TileTarget::with_guard(&gpu, "t", &tile_view, 1, denoise::reach()).unwrap();
    assert!(tile.fits_with_guard(&tile_view, 1, denoise::reach()) && !tile.fits(&tile_view, 1));
    let mut ring = ReadbackRing::new(3);
    let mut run = |ring: &mut ReadbackRing<FrameRead>, k: u32| {
        let mut f = s;
        f.ao.frame = k;
        let tf = TileFrame {
            frame_id: k as u64,
            volume: &gv,
            view: &tile_view,
            settings: &f,
            env: None,
            continuity: if k > 0 { Continuity::Same } else { Continuity::Changed },
            // A still camera never reprojects: temporal on changes nothing.
            temporal: true,
            share: None,
        };
        if !ring.has_free_slot() {
            ring.wait_oldest(&gpu.ctx).unwrap();
        }
        gpu.render_tile(&mut tile, &tf, ring).unwrap();
    };
    for k in 0..3 {
        run(&mut ring, k);
    }
    while ring.in_flight() > 0 {
        ring.wait_oldest(&gpu.ctx).unwrap();
    }
    ring.take_ready();
    let before = gpu.ctx.traffic.now();
    for k in 3..9 {
        run(&mut ring, k);
    }
    while ring.in_flight() > 0 {
        ring.wait_oldest(&gpu.ctx).unwrap();
    }
    let t = gpu.ctx.traffic.now() - before;
    assert_eq!(t.allocations, 0, "{} GPU allocations in 6 steady denoised frames", t.allocations);
    // The frame's counters count the tile's own pixels, not its guard band's.
    let reads = ring.take_ready();
    assert_eq!(reads.len(), 6);
    for read in reads {
        let (tag, out) = FrameRead::decode(read, gpu.ctx.queue.get_timestamp_period()).unwrap();
        assert_eq!(out.counters.pixels, 32 * 24, "frame {}: pixels counted", tag.frame_id);
        assert!(out.counters.hits <= 32 * 24, "frame {}: {} hits", tag.frame_id, out.counters.hits);
    }
}
