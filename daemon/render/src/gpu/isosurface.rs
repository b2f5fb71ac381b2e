//! `Kernel::Isosurface` (shaders/isosurface.wgsl): primary rays, first hit, normal, direct light.
//! Outputs per pixel: direct light + hit flag, N + depth, trilinear fetches.

use super::{
    buffer_entries, frame_entries, marks_entry, storage_entry, Aovs, GpuContext, GpuError, GpuVolume,
    PerfOptions,
};
use crate::shaders::Kernel;

/// The compiled kernel.
pub struct IsosurfaceKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    workgroup: (u32, u32),
}

impl IsosurfaceKernel {
    /// The bind group layout: the frame's inputs (0-2, 11), the three outputs, then the texture
    /// march's volume and sampler (a test holds it to naga's reflection of the WGSL).
    pub(crate) fn entries() -> Vec<wgpu::BindGroupLayoutEntry> {
        let [e0, e1, e2, marks] = frame_entries();
        vec![
            e0,
            e1,
            e2,
            marks,
            storage_entry(3, false),
            storage_entry(4, false),
            storage_entry(5, false),
            wgpu::BindGroupLayoutEntry {
                binding: 6,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Texture {
                    sample_type: wgpu::TextureSampleType::Float { filterable: true },
                    view_dimension: wgpu::TextureViewDimension::D3,
                    multisampled: false,
                },
                count: None,
            },
            wgpu::BindGroupLayoutEntry {
                binding: 7,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                count: None,
            },
        ]
    }

    /// The kernel compiled for `perf`'s workgroup shape, voxel format and block levels, its march
    /// sampling the volume's texture where `perf.texture` (`TEXTURE_MARCH`), for volumes held
    /// whole or `bricked`.
    pub fn new(ctx: &GpuContext, perf: &PerfOptions, bricked: bool) -> Result<IsosurfaceKernel, GpuError> {
        let [format, pow2, bricks] = perf.volume_constants(bricked);
        let constants =
            [format, pow2, bricks, ("TEXTURE_MARCH", f64::from(u8::from(perf.texture && !bricked)))];
        let workgroup = perf.workgroup;
        let (pipeline, layout) = ctx.pipeline(Kernel::Isosurface, &Self::entries(), workgroup, &constants)?;
        Ok(IsosurfaceKernel { pipeline, layout, workgroup })
    }

    /// The bind group of the kernel's inputs and its outputs in `aovs` (direct + hit, N + depth,
    /// fetches), made once per tile and volume ([`TileTarget`](super::tile::TileTarget)).
    pub(crate) fn bind(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        volume: &GpuVolume,
        aovs: &Aovs,
    ) -> wgpu::BindGroup {
        let io = [params, &volume.voxels, &volume.block_minmax, &aovs.direct, &aovs.geometry, &aovs.fetches];
        let mut entries = buffer_entries(&io);
        entries.push(marks_entry(volume));
        entries.push(wgpu::BindGroupEntry {
            binding: 6,
            resource: wgpu::BindingResource::TextureView(&volume.march.view),
        });
        entries.push(wgpu::BindGroupEntry {
            binding: 7,
            resource: wgpu::BindingResource::Sampler(&volume.march.sampler),
        });
        ctx.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("isosurface"),
            layout: &self.layout,
            entries: &entries,
        })
    }

    /// Records the kernel over a `size` rectangle with a bind group from
    /// [`IsosurfaceKernel::bind`].
    pub(crate) fn pass(
        &self,
        enc: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        size: (u32, u32),
        timestamps: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        super::pass(enc, &self.pipeline, bind_group, "isosurface", size, self.workgroup, timestamps);
    }
}
