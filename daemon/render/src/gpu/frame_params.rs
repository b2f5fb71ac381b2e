//! [`FrameParams`]: the `bytemuck` twin of WGSL `FrameParams` (shaders/frame.wgsl), bound at 0 by
//! every kernel. A test checks its layout against the shader with naga.

use super::{GpuEnvironment, GpuVolume};
use bytemuck::{Pod, Zeroable};
use isowall_model::{RenderSettings, View};

/// Bisection steps after the bracketing march step (then one secant step): h / 4096.
pub const REFINE_STEPS: u32 = 12;
const FLAG_EMPTY_SPACE_SKIPPING: u32 = 1;

/// Twin of WGSL `FrameParams`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct FrameParams {
    pub eye: [f32; 4],
    /// w: tan(fov_y / 2)
    pub forward: [f32; 4],
    pub right: [f32; 4],
    pub up: [f32; 4],
    pub light_dir: [f32; 4],
    pub light_color: [f32; 4],
    pub ambient: [f32; 4],
    /// w: specular
    pub albedo: [f32; 4],
    /// w: exposure
    pub background: [f32; 4],
    pub box_min: [f32; 4],
    pub box_max: [f32; 4],
    /// w: primary march step in world units
    pub spacing: [f32; 4],
    /// w: cells per block edge
    pub dims: [u32; 4],
    /// w: flags
    pub block_counts: [u32; 4],
    pub full_size: [u32; 2],
    pub rect_origin: [u32; 2],
    pub rect_size: [u32; 2],
    pub shading: u32,
    pub iso: f32,
    pub shininess: f32,
    pub refine_steps: u32,
    pub max_steps: u32,
    pub ao_samples: u32,
    pub ao_method: u32,
    pub ibl: u32,
    pub frame: u32,
    pub seed: u32,
    /// < 0: unbounded
    pub ao_radius: f32,
    /// eps: the AO rays start at p + eps Ng (world units)
    pub ao_offset: f32,
    pub ao_step: f32,
    pub env_width: u32,
    pub env_height: u32,
    /// 1: ours tests each cell exactly; 0: marches with `ao_step`
    pub ao_exact: u32,
    /// Ours' 2D set: [`AoSequence::code`].
    pub ao_sequence: u32,
    /// 1: the AO kernel sums the positions its samples were taken at (`acc_pos`): a temporal
    /// tile's drift test needs them; elsewhere the buffer is a placeholder and is not written.
    pub positions: u32,
    pub sh: [[f32; 4]; 9],
    // object space
    /// xyz: global sample index of the volume buffer's first sample; w: 1 in object space
    pub data_offset: [f32; 4],
    /// The brick owns a (box-clamped) point q when `owned_min <= q < owned_max`.
    pub owned_min: [f32; 4],
    pub owned_max: [f32; 4],
    // performance
    /// The AO rays' block level: counts (xyz), cells per edge (w; 0: the primary level).
    pub ao_blocks: [u32; 4],
    /// The coarse level of AO rays: counts (xyz), cells per edge (w; 0: none).
    pub coarse: [u32; 4],
    /// x: performance flags (`PERF_*`); y, z: offsets of the AO and coarse levels in the block
    /// min/max buffer; w: 1 where the kernels mark the bricks their rays read (`brick_marks`,
    /// [`GpuVolume::marking`]), else 0.
    pub perf: [u32; 4],
    /// xy: the value range the unorm voxel formats span (lo, hi); zw: 0.
    pub voxel_range: [f32; 4],
    /// AO dispatches ([`super::ao::AoDispatches`]): x: samples per dispatch (the frame's
    /// `ao_samples` are split over `ceil(ao_samples / x)` dispatches); y: the exact walk's
    /// iteration cap per ray; z: 0, or where a reprojected frame's samples are spent by history
    /// ([`crate::reproject::Spending`]) the most a pixel takes, each pixel taking the number the
    /// reprojection wrote into its position sum's w; w: 0.
    pub ao_pass: [u32; 4],
}

/// Performance flag: an AO ray that enters a block whose min >= iso is occluded at once (exact).
pub const PERF_BLOCK_MIN_EXIT: u32 = 1;

/// An enum's code in the kernels' parameters: the model's (`code()`, the wire's too), widened.
pub fn gpu_code(code: u8) -> u32 {
    u32::from(code)
}

fn v4(v: glam::DVec3, w: f64) -> [f32; 4] {
    [v.x as f32, v.y as f32, v.z as f32, w as f32]
}

fn rgb4(c: [f64; 3], w: f64) -> [f32; 4] {
    [c[0] as f32, c[1] as f32, c[2] as f32, w as f32]
}

/// The iteration cap of the exact AO walk (`exact_occluded` in shaders/ao.wgsl) for one ray: each
/// iteration enters a new cell or leaves an empty block (plus the odd empty segment where two cell
/// planes are crossed a rounding error apart, hence the factor 2). The whole box bounds it; a
/// radius R bounds it tighter: a segment of length R crosses at most ceil(R / s) + 1 planes of an
/// axis of spacing s, of cells and of blocks alike.
pub fn exact_walk_cap(volume: &GpuVolume, s: &RenderSettings) -> u32 {
    let level_cells = volume.ao_level.map_or(volume.block, |l| l.cells).max(1);
    let counts = volume.ao_level.map_or(volume.counts, |l| l.counts);
    let n: u64 = volume.dims.iter().map(|&d| d as u64).sum();
    let nb: u64 = counts.iter().map(|&c| c.max(1) as u64).sum();
    let whole_box = 2 * (n + 4 * nb) + 16;
    let cap = match s.ao.radius_world(volume.spacing) {
        Some(r) if r.is_finite() && r >= 0.0 => {
            let planes = |cells: f64| -> u64 {
                (0..3).map(|a| (r / (volume.spacing[a] * cells)).ceil() as u64 + 2).sum()
            };
            whole_box.min(2 * (planes(1.0) + 4 * planes(level_cells as f64)) + 16)
        }
        _ => whole_box,
    };
    cap.min(u32::MAX as u64) as u32
}

impl FrameParams {
    /// Converts the model's view and settings (f64) into the kernels' parameters (f32).
    pub fn new(volume: &GpuVolume, view: &View, s: &RenderSettings, env: &GpuEnvironment) -> FrameParams {
        let b = view.camera.basis();
        let light = s.light.world_direction(b.forward, b.right, b.up);
        let voxel = volume.spacing.min_element();
        let step = s.step_voxels * voxel;
        let ao_step = s.ao.step_voxels * voxel;
        // Enough steps to cross the box diagonal, plus two per block crossed, plus slack.
        let diag = (volume.box_max - volume.box_min).length();
        let blocks: u64 = volume.counts.iter().map(|&c| c as u64).sum::<u64>() * 2 + 64;
        let max_steps = (diag / step.min(ao_step)).ceil() as u64 + blocks;
        let mut sh = [[0.0; 4]; 9];
        for (dst, src) in sh.iter_mut().zip(&env.sh) {
            *dst = [src[0], src[1], src[2], 0.0];
        }
        FrameParams {
            eye: v4(view.camera.eye, 0.0),
            forward: v4(b.forward, b.tan_half_fov),
            right: v4(b.right, 0.0),
            up: v4(b.up, 0.0),
            light_dir: v4(light, 0.0),
            light_color: rgb4(s.light.color, 0.0),
            ambient: rgb4(s.light.ambient, 0.0),
            albedo: rgb4(s.material.albedo, s.material.specular),
            background: rgb4(s.background, s.exposure),
            box_min: v4(volume.box_min, 0.0),
            box_max: v4(volume.box_max, 0.0),
            spacing: v4(volume.spacing, step),
            dims: [volume.dims[0], volume.dims[1], volume.dims[2], volume.block],
            block_counts: [
                volume.counts[0],
                volume.counts[1],
                volume.counts[2],
                if s.empty_space_skipping { FLAG_EMPTY_SPACE_SKIPPING } else { 0 },
            ],
            full_size: [view.full.0, view.full.1],
            rect_origin: [view.rect.x, view.rect.y],
            rect_size: [view.rect.width, view.rect.height],
            shading: gpu_code(s.shading.code()),
            iso: s.iso as f32,
            shininess: s.material.shininess as f32,
            refine_steps: REFINE_STEPS,
            max_steps: max_steps.min(u32::MAX as u64) as u32,
            ao_samples: s.ao.samples,
            ao_method: gpu_code(s.ao.method.code()),
            ibl: gpu_code(s.ao.ibl.code()),
            frame: s.ao.frame,
            seed: s.ao.seed,
            ao_radius: s.ao.radius_world(volume.spacing).map_or(-1.0, |r| r as f32),
            ao_offset: (s.ao.offset_voxels * voxel) as f32,
            ao_step: ao_step as f32,
            env_width: env.width,
            env_height: env.height,
            ao_exact: u32::from(s.ao.exact),
            ao_sequence: gpu_code(s.ao.sequence.code()),
            positions: 0,
            sh,
            data_offset: match &volume.object {
                Some(o) => [o.data_offset[0] as f32, o.data_offset[1] as f32, o.data_offset[2] as f32, 1.0],
                None => [0.0; 4],
            },
            owned_min: volume.object.as_ref().map_or([0.0; 4], |o| v4(o.owned_min, 0.0)),
            owned_max: volume.object.as_ref().map_or([0.0; 4], |o| v4(o.owned_max, 0.0)),
            ao_blocks: volume.ao_level.map_or([0; 4], |l| l.params()),
            coarse: volume.coarse_level.map_or([0; 4], |l| l.params()),
            perf: [
                0,
                volume.ao_level.map_or(0, |l| l.offset),
                volume.coarse_level.map_or(0, |l| l.offset),
                u32::from(volume.marking),
            ],
            voxel_range: [volume.value_range.0, volume.value_range.1, 0.0, 0.0],
            ao_pass: [s.ao.samples.max(1), exact_walk_cap(volume, s), 0, 0],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shaders::Kernel;
    use isowall_model::{AoMethod, AoSequence, IblMethod, Shading};
    use std::mem::offset_of;

    #[test]
    fn each_enum_has_one_code_on_the_wire_in_the_parameters_and_in_the_wgsl() {
        use crate::shaders::tests::wgsl_constants;
        use isowall_model::wire::WireSettings;
        let ao = wgsl_constants(Kernel::Ao);
        let iso = wgsl_constants(Kernel::Isosurface);
        let sampling = &ao; // sampling.wgsl is included by the AO kernel
                            // (WGSL constant, the kernel's constants, the variant's code, its code on the wire, its
                            // code in the kernels' parameters).
        type Row<'a> = (&'a str, &'a std::collections::BTreeMap<String, u32>, u8, u8, u32);
        let mut rows: Vec<Row> = Vec::new();
        let settings = |f: &dyn Fn(&mut RenderSettings)| {
            let mut s = RenderSettings::new(0.0);
            f(&mut s);
            s
        };
        for (name, m) in [("AO_OURS", AoMethod::Ours), ("AO_SEED", AoMethod::Seed)] {
            let s = settings(&|s| s.ao.method = m);
            rows.push((name, &ao, m.code(), WireSettings::from(&s).ao.method, gpu_code(s.ao.method.code())));
        }
        for (name, m) in [
            ("IBL_NONE", IblMethod::None),
            ("IBL_SEED", IblMethod::Seed),
            ("IBL_BENT", IblMethod::Bent),
            ("IBL_RAYS", IblMethod::Rays),
        ] {
            let s = settings(&|s| s.ao.ibl = m);
            rows.push((name, &ao, m.code(), WireSettings::from(&s).ao.ibl, gpu_code(s.ao.ibl.code())));
        }
        for (name, q) in [("AO_SEQUENCE_R2", AoSequence::R2), ("AO_SEQUENCE_SOBOL", AoSequence::Sobol)] {
            let s = settings(&|s| s.ao.sequence = q);
            rows.push((
                name,
                sampling,
                q.code(),
                WireSettings::from(&s).ao.sequence,
                gpu_code(s.ao.sequence.code()),
            ));
        }
        for (name, sh) in
            [("SHADING_LAMBERT", Shading::Lambert), ("SHADING_BLINN_PHONG", Shading::BlinnPhong)]
        {
            let s = settings(&|s| s.shading = sh);
            rows.push((name, &iso, sh.code(), WireSettings::from(&s).shading, gpu_code(s.shading.code())));
        }
        assert_eq!(rows.len(), 10, "every variant of every enum the kernels read");
        for (name, constants, code, wire, gpu) in rows {
            assert_eq!(u32::from(wire), u32::from(code), "{name} on the wire");
            assert_eq!(gpu, u32::from(code), "{name} in the parameters");
            assert_eq!(constants.get(name), Some(&u32::from(code)), "{name} in the WGSL");
        }
        assert_eq!(ao.get("PERF_BLOCK_MIN_EXIT"), Some(&PERF_BLOCK_MIN_EXIT));
        assert_eq!(iso.get("FLAG_EMPTY_SPACE_SKIPPING"), Some(&FLAG_EMPTY_SPACE_SKIPPING));
    }

    #[test]
    fn frame_params_layout_matches_the_wgsl_of_every_kernel() {
        for kernel in Kernel::FRAME {
            crate::shaders::tests::check_layout(
                kernel,
                "FrameParams",
                std::mem::size_of::<FrameParams>(),
                &[
                    ("eye", offset_of!(FrameParams, eye)),
                    ("forward", offset_of!(FrameParams, forward)),
                    ("right", offset_of!(FrameParams, right)),
                    ("up", offset_of!(FrameParams, up)),
                    ("light_dir", offset_of!(FrameParams, light_dir)),
                    ("light_color", offset_of!(FrameParams, light_color)),
                    ("ambient", offset_of!(FrameParams, ambient)),
                    ("albedo", offset_of!(FrameParams, albedo)),
                    ("background", offset_of!(FrameParams, background)),
                    ("box_min", offset_of!(FrameParams, box_min)),
                    ("box_max", offset_of!(FrameParams, box_max)),
                    ("spacing", offset_of!(FrameParams, spacing)),
                    ("dims", offset_of!(FrameParams, dims)),
                    ("block_counts", offset_of!(FrameParams, block_counts)),
                    ("full_size", offset_of!(FrameParams, full_size)),
                    ("rect_origin", offset_of!(FrameParams, rect_origin)),
                    ("rect_size", offset_of!(FrameParams, rect_size)),
                    ("shading", offset_of!(FrameParams, shading)),
                    ("iso", offset_of!(FrameParams, iso)),
                    ("shininess", offset_of!(FrameParams, shininess)),
                    ("refine_steps", offset_of!(FrameParams, refine_steps)),
                    ("max_steps", offset_of!(FrameParams, max_steps)),
                    ("ao_samples", offset_of!(FrameParams, ao_samples)),
                    ("ao_method", offset_of!(FrameParams, ao_method)),
                    ("ibl", offset_of!(FrameParams, ibl)),
                    ("frame", offset_of!(FrameParams, frame)),
                    ("seed", offset_of!(FrameParams, seed)),
                    ("ao_radius", offset_of!(FrameParams, ao_radius)),
                    ("ao_offset", offset_of!(FrameParams, ao_offset)),
                    ("ao_step", offset_of!(FrameParams, ao_step)),
                    ("env_width", offset_of!(FrameParams, env_width)),
                    ("env_height", offset_of!(FrameParams, env_height)),
                    ("ao_exact", offset_of!(FrameParams, ao_exact)),
                    ("ao_sequence", offset_of!(FrameParams, ao_sequence)),
                    ("positions", offset_of!(FrameParams, positions)),
                    ("sh", offset_of!(FrameParams, sh)),
                    ("data_offset", offset_of!(FrameParams, data_offset)),
                    ("owned_min", offset_of!(FrameParams, owned_min)),
                    ("owned_max", offset_of!(FrameParams, owned_max)),
                    ("ao_blocks", offset_of!(FrameParams, ao_blocks)),
                    ("coarse", offset_of!(FrameParams, coarse)),
                    ("perf", offset_of!(FrameParams, perf)),
                    ("voxel_range", offset_of!(FrameParams, voxel_range)),
                    ("ao_pass", offset_of!(FrameParams, ao_pass)),
                ],
            );
        }
    }
}
