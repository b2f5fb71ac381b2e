//! `Kernel::Compose` (shaders/compose.wgsl): a tile's presentable image from the isosurface and AO
//! kernels' outputs: the colour `exposure * (direct + albedo * E)` with E averaged over the
//! accumulated frames, the sRGB encoding, the low-resolution upsample, depth per pixel and the
//! frame's counters. [`ComposeParams`] is the twin of the WGSL struct.

use super::{storage_entry, Aovs, GpuContext, GpuError};
use crate::shaders::Kernel;
use bytemuck::{Pod, Zeroable};
use isowall_model::{RenderSettings, View};

/// Twin of WGSL `ComposeParams`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct ComposeParams {
    /// rgb: linear background; w: exposure
    pub background: [f32; 4],
    pub albedo: [f32; 4],
    /// E where neither AO nor IBL is on
    pub ambient: [f32; 4],
    pub low_origin: [u32; 2],
    pub low_size: [u32; 2],
    pub origin: [u32; 2],
    pub size: [u32; 2],
    pub scale: u32,
    /// Frames in the running sums; 0: no AO or IBL.
    pub frames: u32,
    /// 1: divide each pixel's E sum by its own weight (the sum's w: a reprojected history) instead
    /// of `frames`.
    pub per_pixel: u32,
    pub _pad1: u32,
    /// The tile's own low rectangle within the low rectangle the kernels ran over (which a guard
    /// band grows): the pixels the counters count.
    pub counted_origin: [u32; 2],
    pub counted_size: [u32; 2],
}

impl ComposeParams {
    /// The parameters of a tile of `view` rendered over `low` (`lowres::scaled_view(view, scale)`)
    /// with `frames` frames in the running sums (0 where neither AO nor IBL is on).
    pub fn new(view: &View, low: &View, scale: u32, s: &RenderSettings, frames: u32) -> ComposeParams {
        let c = |v: [f64; 3], w: f64| [v[0] as f32, v[1] as f32, v[2] as f32, w as f32];
        let own = isowall_model::lowres::scaled_view(view, scale.max(1)).rect;
        ComposeParams {
            background: c(s.background, s.exposure),
            albedo: c(s.material.albedo, 0.0),
            ambient: c(s.light.ambient, 0.0),
            low_origin: [low.rect.x, low.rect.y],
            low_size: [low.rect.width, low.rect.height],
            origin: [view.rect.x, view.rect.y],
            size: [view.rect.width, view.rect.height],
            scale: scale.max(1),
            frames,
            per_pixel: 0,
            _pad1: 0,
            counted_origin: [own.x.saturating_sub(low.rect.x), own.y.saturating_sub(low.rect.y)],
            counted_size: [own.width, own.height],
        }
    }
}

/// The compiled kernel.
pub struct ComposeKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    workgroup: (u32, u32),
}

impl ComposeKernel {
    /// The bind group layout: the low rectangle's inputs, the image written, depth and counters (a
    /// test holds it to naga's reflection of the WGSL).
    pub(crate) fn entries() -> Vec<wgpu::BindGroupLayoutEntry> {
        vec![
            storage_entry(0, true),
            storage_entry(1, true),
            storage_entry(2, true),
            storage_entry(3, true),
            storage_entry(4, true),
            wgpu::BindGroupLayoutEntry {
                binding: 5,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::StorageTexture {
                    access: wgpu::StorageTextureAccess::WriteOnly,
                    format: wgpu::TextureFormat::Rgba8Unorm,
                    view_dimension: wgpu::TextureViewDimension::D2,
                },
                count: None,
            },
            storage_entry(6, false),
            storage_entry(7, false),
        ]
    }

    pub fn new(ctx: &GpuContext, workgroup: (u32, u32)) -> Result<ComposeKernel, GpuError> {
        let entries = Self::entries();
        // The voxel format is a constant of the volume kernels only.
        let (pipeline, layout) = ctx.pipeline(Kernel::Compose, &entries, workgroup, &[])?;
        Ok(ComposeKernel { pipeline, layout, workgroup })
    }

    /// The bind group of a tile: parameters, the low rectangle's `aovs` (direct + hit, N + depth,
    /// fetches) with `ambient` the E it composes (the IBL sum, or the filter's output), the image
    /// written, depth and counters.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn bind(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        aovs: &Aovs,
        ambient: &wgpu::Buffer,
        image: &wgpu::TextureView,
        depth: &wgpu::Buffer,
        counters: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        fn b(binding: u32, buf: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry { binding, resource: buf.as_entire_binding() }
        }
        ctx.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("compose"),
            layout: &self.layout,
            entries: &[
                b(0, params),
                b(1, &aovs.direct),
                b(2, &aovs.geometry),
                b(3, ambient),
                b(4, &aovs.fetches),
                wgpu::BindGroupEntry { binding: 5, resource: wgpu::BindingResource::TextureView(image) },
                b(6, depth),
                b(7, counters),
            ],
        })
    }

    /// Records the kernel over the tile's (full-resolution) rectangle of `size`.
    pub(crate) fn pass(
        &self,
        enc: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        size: (u32, u32),
        timestamps: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        super::pass(enc, &self.pipeline, bind_group, "compose", size, self.workgroup, timestamps);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::offset_of;

    #[test]
    fn compose_params_layout_matches_the_wgsl() {
        crate::shaders::tests::check_layout(
            Kernel::Compose,
            "ComposeParams",
            std::mem::size_of::<ComposeParams>(),
            &[
                ("background", offset_of!(ComposeParams, background)),
                ("albedo", offset_of!(ComposeParams, albedo)),
                ("ambient", offset_of!(ComposeParams, ambient)),
                ("low_origin", offset_of!(ComposeParams, low_origin)),
                ("low_size", offset_of!(ComposeParams, low_size)),
                ("origin", offset_of!(ComposeParams, origin)),
                ("size", offset_of!(ComposeParams, size)),
                ("scale", offset_of!(ComposeParams, scale)),
                ("frames", offset_of!(ComposeParams, frames)),
                ("per_pixel", offset_of!(ComposeParams, per_pixel)),
                ("_pad1", offset_of!(ComposeParams, _pad1)),
                ("counted_origin", offset_of!(ComposeParams, counted_origin)),
                ("counted_size", offset_of!(ComposeParams, counted_size)),
            ],
        );
    }
}
