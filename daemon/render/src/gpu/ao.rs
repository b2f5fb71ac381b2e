//! `Kernel::Ao` (shaders/ao.wgsl): ambient occlusion (ours, or the 2008 `seed` baseline), bent
//! normal and the IBL term of one frame at every hit, added into accumulators.

use super::{frame_entries, storage_entry, GpuContext, GpuError, GpuVolume};
use crate::shaders::Kernel;
use isowall_volume::VoxelFormat;

/// The compiled kernel.
pub struct AoKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    workgroup: (u32, u32),
}

impl AoKernel {
    pub fn new(ctx: &GpuContext, workgroup: (u32, u32), format: VoxelFormat) -> Result<AoKernel, GpuError> {
        let [e0, e1, e2] = frame_entries();
        let entries = [
            e0,
            e1,
            e2,
            storage_entry(3, true),
            storage_entry(4, true),
            storage_entry(5, true),
            storage_entry(6, false),
            storage_entry(7, false),
            storage_entry(8, false),
        ];
        let (pipeline, layout) = ctx.pipeline(Kernel::Ao, &entries, workgroup, format)?;
        Ok(AoKernel { pipeline, layout, workgroup })
    }

    /// The bind group of the kernel's inputs and `io` (as [`AoKernel::encode`] takes them), made
    /// once per tile, volume and environment ([`TileTarget`](super::tile::TileTarget)).
    pub(crate) fn bind(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        volume: &GpuVolume,
        env: &wgpu::Buffer,
        io: [&wgpu::Buffer; 5],
    ) -> wgpu::BindGroup {
        let buffers = [params, &volume.voxels, &volume.block_minmax, io[0], io[1], env, io[2], io[3], io[4]];
        super::bind_buffers(ctx, &self.layout, "ao", &buffers)
    }

    /// Records one frame of the kernel over a `size` window with a bind group from [`AoKernel::bind`].
    pub(crate) fn pass(
        &self,
        enc: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        size: (u32, u32),
        timestamps: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        super::pass(enc, &self.pipeline, bind_group, "ao", size, self.workgroup, timestamps);
    }

    /// Records one frame of the kernel over a `size` window. `io` is (direct + hit, N + depth,
    /// accumulated bent + A, accumulated E, fetches).
    #[allow(clippy::too_many_arguments)]
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        volume: &GpuVolume,
        env: &wgpu::Buffer,
        io: [&wgpu::Buffer; 5],
        size: (u32, u32),
    ) {
        let bind_group = self.bind(ctx, params, volume, env, io);
        self.pass(enc, &bind_group, size, None);
    }
}
