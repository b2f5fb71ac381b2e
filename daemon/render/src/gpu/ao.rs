//! `Kernel::Ao` (shaders/ao.wgsl): ambient occlusion (ours, or the 2008 `seed` baseline), bent
//! normal and the IBL term of one frame at every hit, added into accumulators.

use super::{frame_entries, storage_entry, GpuContext, GpuError, GpuVolume, WORKGROUP};
use crate::shaders::Kernel;

/// The compiled kernel.
pub struct AoKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

impl AoKernel {
    pub fn new(ctx: &GpuContext) -> Result<AoKernel, GpuError> {
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
        let (pipeline, layout) = ctx.pipeline(Kernel::Ao, &entries)?;
        Ok(AoKernel { pipeline, layout })
    }

    /// Records one frame of the kernel over a `size` window. `io` is (direct + hit, N + depth,
    /// accumulated bent + A, accumulated E, fetches).
    #[allow(clippy::too_many_arguments)]
    pub fn encode(
        &self,
        device: &wgpu::Device,
        enc: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        volume: &GpuVolume,
        env: &wgpu::Buffer,
        io: [&wgpu::Buffer; 5],
        size: (u32, u32),
    ) {
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("ao"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: params.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: volume.voxels.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: volume.block_minmax.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: io[0].as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: io[1].as_entire_binding() },
                wgpu::BindGroupEntry { binding: 5, resource: env.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 6, resource: io[2].as_entire_binding() },
                wgpu::BindGroupEntry { binding: 7, resource: io[3].as_entire_binding() },
                wgpu::BindGroupEntry { binding: 8, resource: io[4].as_entire_binding() },
            ],
        });
        let mut pass = enc
            .begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("ao"), timestamp_writes: None });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(size.0.div_ceil(WORKGROUP), size.1.div_ceil(WORKGROUP), 1);
    }
}
