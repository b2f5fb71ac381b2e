//! `Kernel::Isosurface` (shaders/isosurface.wgsl): primary rays, first hit, normal, direct light.
//! Outputs per pixel: direct light + hit flag, N + depth, trilinear fetches.

use super::{frame_entries, storage_entry, GpuContext, GpuError, GpuVolume, WORKGROUP};
use crate::shaders::Kernel;

/// The compiled kernel.
pub struct IsosurfaceKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

impl IsosurfaceKernel {
    pub fn new(ctx: &GpuContext) -> Result<IsosurfaceKernel, GpuError> {
        let [e0, e1, e2] = frame_entries();
        let entries = [e0, e1, e2, storage_entry(3, false), storage_entry(4, false), storage_entry(5, false)];
        let (pipeline, layout) = ctx.pipeline(Kernel::Isosurface, &entries)?;
        Ok(IsosurfaceKernel { pipeline, layout })
    }

    /// Records the kernel over a `size` window: `outputs` are (direct + hit, N + depth, fetches).
    pub fn encode(
        &self,
        device: &wgpu::Device,
        enc: &mut wgpu::CommandEncoder,
        params: &wgpu::Buffer,
        volume: &GpuVolume,
        outputs: [&wgpu::Buffer; 3],
        size: (u32, u32),
    ) {
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("isosurface"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: params.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: volume.voxels.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: volume.block_minmax.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: outputs[0].as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: outputs[1].as_entire_binding() },
                wgpu::BindGroupEntry { binding: 5, resource: outputs[2].as_entire_binding() },
            ],
        });
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("isosurface"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(size.0.div_ceil(WORKGROUP), size.1.div_ceil(WORKGROUP), 1);
    }
}
