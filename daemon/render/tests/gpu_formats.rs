//! Packed voxel formats: kernels compiled for r16f, r16 or r8 read the packed voxels as
//! the CPU twin `Volume::stored_as` rounds them. The packed GPU render equals the f32 kernels on the
//! rounded volume, agrees with the exact CPU reference on the rounded volume, and a volume stored
//! in another format than the kernels read is refused.

mod common;

use isowall_model::{Camera, RenderSettings, View};
use isowall_render::gpu::{ObjectSpace, PerfOptions};
use isowall_render::reference;
use isowall_volume::procedural::Procedural;
use isowall_volume::{VolumeSource, VoxelFormat};

const PACKED: [VoxelFormat; 3] = [VoxelFormat::R16F, VoxelFormat::R16, VoxelFormat::R8];

#[test]
fn packed_voxels_render_as_the_rounded_volume() {
    let Some(mut gpu) = common::gpu() else { return };
    for (kind, volume, view, s) in common::perf_scenes() {
        gpu.set_perf(PerfOptions::default()).unwrap();
        let gv = gpu.upload(&volume).unwrap();
        let full = gpu.render(&gv, &view, &s, None).unwrap().frame;
        for format in PACKED {
            let rounded = volume.stored_as(format);
            gpu.set_perf(PerfOptions::default()).unwrap();
            let twin = gpu.upload(&rounded).unwrap();
            let twin = gpu.render(&twin, &view, &s, None).unwrap().frame;
            gpu.set_perf(PerfOptions { format, ..Default::default() }).unwrap();
            let gv = gpu.upload(&volume).unwrap();
            assert_eq!(gv.voxel_bytes, (volume.data().len().div_ceil(format.per_word()) * 4) as u64);
            let packed = gpu.render(&gv, &view, &s, None).unwrap().frame;
            let name = format!("{kind} {}", format.name());
            // The same voxel values (up to the last bit of the GPU's unpacking): the same hits, the
            // same depth within a hair, occlusion within one ray on at most 1% of the pixels.
            let hits = (0..packed.pixel_count()).filter(|&i| packed.hit[i] != twin.hit[i]).count();
            assert_eq!(hits, 0, "{name}: hits differ from the f32 kernels on the rounded volume");
            let worst = (0..packed.pixel_count())
                .filter(|&i| packed.hit[i])
                .map(|i| (packed.depth[i] - twin.depth[i]).abs() as f64)
                .fold(0.0, f64::max);
            assert!(worst < 1e-3 * volume.spacing().min_element(), "{name}: depth differs by {worst}");
            let ao = (0..packed.pixel_count())
                .filter(|&i| packed.hit[i] && (packed.occlusion[i] - twin.occlusion[i]).abs() > 0.5 / 16.0)
                .count();
            assert!(ao * 100 <= packed.hit_count(), "{name}: occlusion differs at {ao} pixels");
            // The exact CPU reference on the rounded volume (the cross-check of "First light").
            let r = reference::render(&rounded, &view, &s);
            let a = common::compare(&packed, &r, volume.spacing().min_element());
            assert_eq!(a.mask_mismatches, 0, "{name}: hit masks differ off the silhouette: {a:?}");
            assert!(a.depth_median < 0.05, "{name}: median depth error {} voxel", a.depth_median);
            assert!(a.normal_median_deg < 1.0, "{name}: median normal error {} deg", a.normal_median_deg);
            // r8 rounds the field visibly: the packed path is really the one rendered.
            if format == VoxelFormat::R8 && kind == Procedural::Engine.name() {
                let moved = (0..packed.pixel_count())
                    .filter(|&i| packed.hit[i] && full.hit[i] && packed.depth[i] != full.depth[i])
                    .count();
                assert!(moved * 2 > packed.hit_count(), "{name}: only {moved} depths moved from f32");
            }
        }
    }
}

#[test]
fn a_volume_stored_in_another_format_is_refused() {
    let Some(mut gpu) = common::gpu() else { return };
    let volume = VolumeSource::Procedural { kind: Procedural::Sphere, size: Some(16) }.load(None).unwrap();
    let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), 16, 16), 16, 16);
    let s = RenderSettings::new(Procedural::Sphere.natural_iso());
    gpu.set_perf(PerfOptions { format: VoxelFormat::R16, ..Default::default() }).unwrap();
    let packed = gpu.upload(&volume).unwrap();
    gpu.set_perf(PerfOptions::default()).unwrap();
    let e = gpu.render(&packed, &view, &s, None).err().expect("a r16 volume under r32f kernels");
    assert!(e.to_string().contains("r16") && e.to_string().contains("r32f"), "{e}");
    // Uploaded again for the kernels in use, it renders.
    let f32_volume = gpu.upload(&volume).unwrap();
    assert!(gpu.render(&f32_volume, &view, &s, None).unwrap().frame.hit_count() > 0);
}

#[test]
fn a_brick_packs_r16f_and_refuses_the_unorm_formats() {
    let Some(mut gpu) = common::gpu() else { return };
    let volume = VolumeSource::Procedural { kind: Procedural::Engine, size: Some(48) }.load(None).unwrap();
    let info = isowall_volume::VolumeInfo {
        name: volume.name.clone(),
        dims: volume.dims(),
        spacing: volume.spacing(),
        origin: volume.box_min(),
    };
    let blocks = isowall_volume::BlockMinMax::new(&volume, 8);
    // One brick holding the whole volume: its render is the whole volume's in the same format.
    let object = ObjectSpace {
        data_offset: [0, 0, 0],
        owned_min: volume.box_min() - 1.0,
        owned_max: volume.box_max() + 1.0,
    };
    let view = View::whole(Camera::framing(volume.box_min(), volume.box_max(), 48, 48), 48, 48);
    let s = RenderSettings::new(Procedural::Engine.natural_iso());
    for format in [VoxelFormat::R16, VoxelFormat::R8] {
        gpu.set_perf(PerfOptions { format, ..Default::default() }).unwrap();
        let e = gpu.upload_brick(&volume, &info, &blocks, object.clone()).err().expect("refused");
        assert!(e.to_string().contains(format.name()), "{e}");
    }
    gpu.set_perf(PerfOptions { format: VoxelFormat::R16F, ..PerfOptions::PLAIN }).unwrap();
    let brick = gpu.upload_brick(&volume, &info, &blocks, object).unwrap();
    assert_eq!(brick.voxel_bytes, (volume.data().len().div_ceil(2) * 4) as u64);
    let whole = gpu.upload(&volume).unwrap();
    let a = gpu.render(&brick, &view, &s, None).unwrap().frame;
    let b = gpu.render(&whole, &view, &s, None).unwrap().frame;
    assert!(b.hit_count() > 300);
    assert_eq!(a.hit, b.hit);
    assert_eq!(a.depth, b.depth);
}
