//! `Kernel::Reproject` (shaders/reproject.wgsl): a tile's running sums carried from its previous
//! frame into a frame whose camera alone moved (temporal reprojection). The rule and its CPU twin
//! are [`crate::reproject`]; [`ReprojectParams`] is the twin of the WGSL struct.

use super::{buffer_entries, storage_entry, Aovs, FrameParams, GpuContext, GpuError};
use crate::reproject::{Rule, Spending};
use crate::shaders::Kernel;
use bytemuck::{Pod, Zeroable};

/// Twin of WGSL `ReprojectParams`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct ReprojectParams {
    pub eye: [f32; 4],
    /// w: tan(fov_y / 2)
    pub forward: [f32; 4],
    pub right: [f32; 4],
    pub up: [f32; 4],
    pub prev_eye: [f32; 4],
    /// w: tan(fov_y / 2)
    pub prev_forward: [f32; 4],
    pub prev_right: [f32; 4],
    pub prev_up: [f32; 4],
    pub full_size: [u32; 2],
    pub rect_origin: [u32; 2],
    pub rect_size: [u32; 2],
    pub prev_full_size: [u32; 2],
    pub prev_rect_origin: [u32; 2],
    pub prev_rect_size: [u32; 2],
    pub max_age: f32,
    pub plane_tolerance: f32,
    pub normal_agreement: f32,
    /// 1: the nearest previous pixel instead of the bilinear taps ([`Rule::nearest`]).
    pub nearest: u32,
    /// 1: the accepted taps' blend is not renormalized ([`Rule::accepted_share`]).
    pub accepted_share: u32,
    /// [`Rule::drift`] at the frame's AO samples, in footprints (infinite: no test).
    pub drift_tolerance: f32,
    /// The frame's AO samples a pixel (S), its index in the sample sequence and seed.
    pub samples: u32,
    pub frame: u32,
    pub seed: u32,
    /// [`Rule::spending`]'s code ([`Spending::code`]), and by history its three numbers.
    pub spending: u32,
    pub spend_target: f32,
    pub spend_least: f32,
    pub spend_most: f32,
    pub _pad1: u32,
    pub _pad2: u32,
    pub _pad3: u32,
}

impl ReprojectParams {
    /// From the frame `next` to be rendered and the previous frame `prev` (the kernels'
    /// parameters of each), under `rule`.
    pub fn new(next: &FrameParams, prev: &FrameParams, rule: &Rule) -> ReprojectParams {
        let (target, least, most) = match rule.spending {
            Spending::Uniform => (0.0, 0.0, 0.0),
            Spending::ByHistory { target, least, most } => (target, least, most),
        };
        ReprojectParams {
            eye: next.eye,
            forward: next.forward,
            right: next.right,
            up: next.up,
            prev_eye: prev.eye,
            prev_forward: prev.forward,
            prev_right: prev.right,
            prev_up: prev.up,
            full_size: next.full_size,
            rect_origin: next.rect_origin,
            rect_size: next.rect_size,
            prev_full_size: prev.full_size,
            prev_rect_origin: prev.rect_origin,
            prev_rect_size: prev.rect_size,
            max_age: rule.max_age,
            plane_tolerance: rule.plane_tolerance,
            normal_agreement: rule.normal_agreement,
            nearest: u32::from(rule.nearest),
            accepted_share: u32::from(rule.accepted_share),
            drift_tolerance: rule.drift.footprints(next.ao_samples),
            samples: next.ao_samples,
            frame: next.frame,
            seed: next.seed,
            spending: rule.spending.code(),
            spend_target: target,
            spend_least: least,
            spend_most: most,
            _pad1: 0,
            _pad2: 0,
            _pad3: 0,
        }
    }
}

/// The compiled kernel.
pub struct ReprojectKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    workgroup: (u32, u32),
}

impl ReprojectKernel {
    /// The bind group layout: parameters, this frame's hit flags and geometry, the previous
    /// frame's hit flags, geometry and sums, this frame's sums written, the previous frame's
    /// position sum, this frame's written (a test holds it to naga's reflection of the WGSL).
    pub(crate) fn entries() -> Vec<wgpu::BindGroupLayoutEntry> {
        let mut entries: Vec<_> = (0..=6).map(|b| storage_entry(b, true)).collect();
        entries.extend((7..=8).map(|b| storage_entry(b, false)));
        entries.push(storage_entry(9, true));
        entries.push(storage_entry(10, false));
        entries
    }

    pub fn new(ctx: &GpuContext, workgroup: (u32, u32)) -> Result<ReprojectKernel, GpuError> {
        let (pipeline, layout) = ctx.pipeline(Kernel::Reproject, &Self::entries(), workgroup, &[])?;
        Ok(ReprojectKernel { pipeline, layout, workgroup })
    }

    /// The bind group of a tile: `params`, this frame's `aovs` (direct + hit, N + depth read, the
    /// sums written) and the previous frame's shading planes (direct + hit, N + depth, summed
    /// bent + A, summed E: [`Aovs::shading`]'s order) and position sum.
    pub(crate) fn bind(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        aovs: &Aovs,
        prev: [&wgpu::Buffer; 4],
        prev_pos: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        let a = aovs;
        let all = [
            params,
            &a.direct,
            &a.geometry,
            prev[0],
            prev[1],
            prev[2],
            prev[3],
            &a.ao_sum,
            &a.ibl_sum,
            prev_pos,
            &a.pos_sum,
        ];
        let entries = buffer_entries(&all);
        ctx.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("reproject"),
            layout: &self.layout,
            entries: &entries,
        })
    }

    /// Records the kernel over a `size` rectangle.
    pub(crate) fn pass(
        &self,
        enc: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        size: (u32, u32),
    ) {
        super::pass(enc, &self.pipeline, bind_group, "reproject", size, self.workgroup, None);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::offset_of;

    #[test]
    fn spending_codes_and_the_draws_salt_are_the_wgsls() {
        let constants = crate::shaders::tests::wgsl_constants(Kernel::Reproject);
        let rule = crate::reproject::SPENDING;
        let Spending::ByHistory { .. } = rule else { panic!("the renderer spends by history") };
        for (name, spending) in [("SPENDING_UNIFORM", Spending::Uniform), ("SPENDING_BY_HISTORY", rule)] {
            assert_eq!(constants.get(name), Some(&spending.code()), "{name}");
        }
        assert_eq!(constants.get("SPEND_SALT"), Some(&crate::reproject::SPEND_SALT));
    }

    #[test]
    fn reproject_params_layout_matches_the_wgsl() {
        crate::shaders::tests::check_layout(
            Kernel::Reproject,
            "ReprojectParams",
            std::mem::size_of::<ReprojectParams>(),
            &[
                ("eye", offset_of!(ReprojectParams, eye)),
                ("forward", offset_of!(ReprojectParams, forward)),
                ("right", offset_of!(ReprojectParams, right)),
                ("up", offset_of!(ReprojectParams, up)),
                ("prev_eye", offset_of!(ReprojectParams, prev_eye)),
                ("prev_forward", offset_of!(ReprojectParams, prev_forward)),
                ("prev_right", offset_of!(ReprojectParams, prev_right)),
                ("prev_up", offset_of!(ReprojectParams, prev_up)),
                ("full_size", offset_of!(ReprojectParams, full_size)),
                ("rect_origin", offset_of!(ReprojectParams, rect_origin)),
                ("rect_size", offset_of!(ReprojectParams, rect_size)),
                ("prev_full_size", offset_of!(ReprojectParams, prev_full_size)),
                ("prev_rect_origin", offset_of!(ReprojectParams, prev_rect_origin)),
                ("prev_rect_size", offset_of!(ReprojectParams, prev_rect_size)),
                ("max_age", offset_of!(ReprojectParams, max_age)),
                ("plane_tolerance", offset_of!(ReprojectParams, plane_tolerance)),
                ("normal_agreement", offset_of!(ReprojectParams, normal_agreement)),
                ("nearest", offset_of!(ReprojectParams, nearest)),
                ("accepted_share", offset_of!(ReprojectParams, accepted_share)),
                ("drift_tolerance", offset_of!(ReprojectParams, drift_tolerance)),
                ("samples", offset_of!(ReprojectParams, samples)),
                ("frame", offset_of!(ReprojectParams, frame)),
                ("seed", offset_of!(ReprojectParams, seed)),
                ("spending", offset_of!(ReprojectParams, spending)),
                ("spend_target", offset_of!(ReprojectParams, spend_target)),
                ("spend_least", offset_of!(ReprojectParams, spend_least)),
                ("spend_most", offset_of!(ReprojectParams, spend_most)),
                ("_pad1", offset_of!(ReprojectParams, _pad1)),
                ("_pad2", offset_of!(ReprojectParams, _pad2)),
                ("_pad3", offset_of!(ReprojectParams, _pad3)),
            ],
        );
    }
}
