//! `Kernel::Isosurface` (shaders/isosurface.wgsl): primary rays, first hit, normal, direct light.
//! Outputs per pixel: direct light + hit flag, N + depth, trilinear fetches.

use super::{frame_entries, storage_entry, GpuContext, GpuError, GpuVolume};
use crate::shaders::Kernel;
use isowall_volume::VoxelFormat;

/// The compiled kernel.
pub struct IsosurfaceKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    workgroup: (u32, u32),
}

impl IsosurfaceKernel {
    /// The bind group layout: the frame's inputs (0-2), then the three outputs (a test holds it
    /// to naga's reflection of the WGSL).
    pub(crate) fn entries() -> Vec<wgpu::BindGroupLayoutEntry> {
        let [e0, e1, e2] = frame_entries();
        vec![e0, e1, e2, storage_entry(3, false), storage_entry(4, false), storage_entry(5, false)]
    }

    pub fn new(
        ctx: &GpuContext,
        workgroup: (u32, u32),
        format: VoxelFormat,
    ) -> Result<IsosurfaceKernel, GpuError> {
        let (pipeline, layout) = ctx.pipeline(Kernel::Isosurface, &Self::entries(), workgroup, format)?;
        Ok(IsosurfaceKernel { pipeline, layout, workgroup })
    }

    /// The bind group of the kernel's inputs and `outputs` (direct + hit, N + depth, fetches),
    /// made once per tile and volume ([`TileTarget`](super::tile::TileTarget)).
    pub(crate) fn bind(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        volume: &GpuVolume,
        outputs: [&wgpu::Buffer; 3],
    ) -> wgpu::BindGroup {
        let io = [params, &volume.voxels, &volume.block_minmax, outputs[0], outputs[1], outputs[2]];
        super::bind_buffers(ctx, &self.layout, "isosurface", &io)
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

    /// Records the kernel over a `size` rectangle: `outputs` are (direct + hit, N + depth,
    /// fetches).
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        volume: &GpuVolume,
        outputs: [&wgpu::Buffer; 3],
        size: (u32, u32),
    ) {
        let bind_group = self.bind(ctx, params, volume, outputs);
        self.pass(enc, &bind_group, size, None);
    }
}
