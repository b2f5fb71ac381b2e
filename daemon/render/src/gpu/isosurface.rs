//! `Kernel::Isosurface` (shaders/isosurface.wgsl): primary rays, first hit, normal, direct shading,
//! AOVs. [`IsoParams`] is the `bytemuck` twin of the WGSL struct of the same name; a test checks
//! its layout against the shader with naga.

use super::{GpuContext, GpuError, Rendered};
use crate::shaders::{self, Kernel};
use crate::Frame;
use bytemuck::{Pod, Zeroable};
use isowall_volume::{BlockMinMax, Volume};
use isowall_wall::{RenderSettings, Shading, View};
use std::time::Instant;
use wgpu::util::DeviceExt;

/// Workgroup edge of the kernel (`@workgroup_size(8, 8, 1)`).
const WORKGROUP: u32 = 8;
/// Bisection steps after the bracketing march step (then one secant step): h / 4096.
const REFINE_STEPS: u32 = 12;
const FLAG_EMPTY_SPACE_SKIPPING: u32 = 1;

/// Twin of WGSL `IsoParams`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct IsoParams {
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
    /// w: march step in world units
    pub spacing: [f32; 4],
    /// w: cells per block edge
    pub dims: [u32; 4],
    /// w: flags
    pub block_counts: [u32; 4],
    pub full_size: [u32; 2],
    pub window_origin: [u32; 2],
    pub window_size: [u32; 2],
    pub shading: u32,
    pub iso: f32,
    pub shininess: f32,
    pub refine_steps: u32,
    pub max_steps: u32,
    pub _pad: u32,
}

fn v4(v: glam::DVec3, w: f64) -> [f32; 4] {
    [v.x as f32, v.y as f32, v.z as f32, w as f32]
}

fn rgb4(c: [f64; 3], w: f64) -> [f32; 4] {
    [c[0] as f32, c[1] as f32, c[2] as f32, w as f32]
}

impl IsoParams {
    /// Converts the model's view and settings (f64) into the kernel's parameters (f32).
    pub fn new(volume: &GpuVolume, view: &View, s: &RenderSettings) -> IsoParams {
        let b = view.camera.basis();
        let light = s.light.world_direction(b.forward, b.right, b.up);
        let step = s.step_voxels * volume.spacing.min_element();
        // Enough steps to cross the box diagonal, plus one per block crossed, plus slack.
        let diag = (volume.box_max - volume.box_min).length();
        let max_steps =
            (diag / step).ceil() as u64 + volume.counts.iter().map(|&c| c as u64).sum::<u64>() * 2 + 64;
        IsoParams {
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
            window_origin: [view.window.x, view.window.y],
            window_size: [view.window.width, view.window.height],
            shading: match s.shading {
                Shading::Lambert => 0,
                Shading::BlinnPhong => 1,
            },
            iso: s.iso as f32,
            shininess: s.material.shininess as f32,
            refine_steps: REFINE_STEPS,
            max_steps: max_steps.min(u32::MAX as u64) as u32,
            _pad: 0,
        }
    }
}

/// A volume on the GPU: voxels (f32) and per-block min/max.
pub struct GpuVolume {
    voxels: wgpu::Buffer,
    block_minmax: wgpu::Buffer,
    pub dims: [u32; 3],
    pub block: u32,
    pub counts: [u32; 3],
    pub spacing: glam::DVec3,
    pub box_min: glam::DVec3,
    pub box_max: glam::DVec3,
    pub name: String,
}

impl GpuVolume {
    pub fn upload(ctx: &GpuContext, v: &Volume, blocks: &BlockMinMax) -> Result<GpuVolume, GpuError> {
        let bytes = v.resident_bytes() as u64;
        let limit =
            ctx.device.limits().max_storage_buffer_binding_size.min(ctx.device.limits().max_buffer_size);
        if bytes > limit {
            return Err(GpuError::VolumeTooLarge { name: v.name.clone(), bytes, limit });
        }
        let (voxels, block_minmax) = ctx.validated("volume upload", || {
            let voxels = ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("volume voxels"),
                contents: bytemuck::cast_slice(v.data()),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let block_minmax = ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("block min/max"),
                contents: bytemuck::cast_slice(&blocks.minmax),
                usage: wgpu::BufferUsages::STORAGE,
            });
            (voxels, block_minmax)
        })?;
        let d = v.dims();
        Ok(GpuVolume {
            voxels,
            block_minmax,
            dims: [d[0] as u32, d[1] as u32, d[2] as u32],
            block: blocks.block as u32,
            counts: blocks.counts.map(|c| c as u32),
            spacing: v.spacing(),
            box_min: v.box_min(),
            box_max: v.box_max(),
            name: v.name.clone(),
        })
    }
}

/// The compiled kernel.
pub struct IsosurfaceKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

fn storage_entry(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

impl IsosurfaceKernel {
    pub fn new(ctx: &GpuContext) -> Result<IsosurfaceKernel, GpuError> {
        ctx.validated("isosurface pipeline", || {
            let device = &ctx.device;
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(Kernel::Isosurface.file_name()),
                source: wgpu::ShaderSource::Wgsl(shaders::source(Kernel::Isosurface).into()),
            });
            let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("isosurface"),
                entries: &[
                    wgpu::BindGroupLayoutEntry {
                        binding: 0,
                        visibility: wgpu::ShaderStages::COMPUTE,
                        ty: wgpu::BindingType::Buffer {
                            ty: wgpu::BufferBindingType::Uniform,
                            has_dynamic_offset: false,
                            min_binding_size: wgpu::BufferSize::new(std::mem::size_of::<IsoParams>() as u64),
                        },
                        count: None,
                    },
                    storage_entry(1, true),
                    storage_entry(2, true),
                    storage_entry(3, false),
                    storage_entry(4, false),
                    storage_entry(5, false),
                ],
            });
            let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("isosurface"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
            let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("isosurface"),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some("main"),
                compilation_options: Default::default(),
                cache: None,
            });
            IsosurfaceKernel { pipeline, layout }
        })
    }

    pub fn render(
        &self,
        ctx: &GpuContext,
        volume: &GpuVolume,
        view: &View,
        settings: &RenderSettings,
    ) -> Result<Rendered, GpuError> {
        let (w, h) = (view.window.width, view.window.height);
        if w == 0 || h == 0 || view.full.0 == 0 || view.full.1 == 0 {
            return Err(GpuError::View(format!("empty window {w}x{h} of {}x{}", view.full.0, view.full.1)));
        }
        view.camera.validate().map_err(|e| GpuError::View(e.to_string()))?;
        let n = w as u64 * h as u64;
        let params = IsoParams::new(volume, view, settings);
        let device = &ctx.device;
        let out_size = [n * 16, n * 16, n * 4];
        let (bind_group, outputs, staging) = ctx.validated("isosurface buffers", || {
            let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("iso params"),
                contents: bytemuck::bytes_of(&params),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let outputs: Vec<wgpu::Buffer> = ["out color", "out geometry", "out fetches"]
                .iter()
                .zip(out_size)
                .map(|(label, size)| {
                    device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some(label),
                        size,
                        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                        mapped_at_creation: false,
                    })
                })
                .collect();
            let staging: Vec<wgpu::Buffer> = out_size
                .iter()
                .map(|&size| {
                    device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("readback"),
                        size,
                        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                        mapped_at_creation: false,
                    })
                })
                .collect();
            let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("isosurface"),
                layout: &self.layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: uniform.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: volume.voxels.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 2, resource: volume.block_minmax.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 3, resource: outputs[0].as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 4, resource: outputs[1].as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 5, resource: outputs[2].as_entire_binding() },
                ],
            });
            (bind_group, outputs, staging)
        })?;

        // The kernel alone, timed from submit to done.
        let mut enc =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("isosurface") });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("isosurface"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(w.div_ceil(WORKGROUP), h.div_ceil(WORKGROUP), 1);
        }
        let start = Instant::now();
        ctx.queue.submit([enc.finish()]);
        ctx.wait()?;
        let gpu_time = start.elapsed();

        let mut enc =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("readback") });
        for (src, dst) in outputs.iter().zip(&staging) {
            enc.copy_buffer_to_buffer(src, 0, dst, 0, None);
        }
        ctx.queue.submit([enc.finish()]);
        let bytes = read_buffers(ctx, &staging)?;

        let color: &[[f32; 4]] = bytemuck::cast_slice(&bytes[0]);
        let geometry: &[[f32; 4]] = bytemuck::cast_slice(&bytes[1]);
        let fetches: &[u32] = bytemuck::cast_slice(&bytes[2]);
        let mut frame = Frame::new(w, h);
        for i in 0..n as usize {
            let c = color[i];
            let g = geometry[i];
            frame.color[i] = [c[0], c[1], c[2]];
            frame.hit[i] = c[3] > 0.5;
            frame.normal[i] = [g[0], g[1], g[2]];
            frame.depth[i] = g[3];
        }
        frame.fetches = fetches.iter().map(|&f| f as u64).sum();
        tracing::debug!(
            width = w,
            height = h,
            hits = frame.hit_count(),
            fetches_per_pixel = frame.fetches_per_pixel(),
            gpu_ms = gpu_time.as_secs_f64() * 1e3,
            "isosurface frame"
        );
        Ok(Rendered { frame, gpu_time })
    }
}

/// Maps every buffer for reading, waits, and copies their contents out.
fn read_buffers(ctx: &GpuContext, buffers: &[wgpu::Buffer]) -> Result<Vec<Vec<u8>>, GpuError> {
    let (tx, rx) = std::sync::mpsc::channel();
    for (i, b) in buffers.iter().enumerate() {
        let tx = tx.clone();
        b.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send((i, r));
        });
    }
    drop(tx);
    ctx.wait()?;
    for (i, r) in rx.iter() {
        r.map_err(|e| GpuError::Readback(format!("buffer {i}: {e}")))?;
    }
    let mut out = Vec::with_capacity(buffers.len());
    for b in buffers {
        let view = b.get_mapped_range(..).map_err(|e| GpuError::Readback(e.to_string()))?;
        out.push(view.to_vec());
        drop(view);
        b.unmap();
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::offset_of;

    #[test]
    fn iso_params_layout_matches_the_wgsl() {
        crate::shaders::tests::check_layout(
            Kernel::Isosurface,
            "IsoParams",
            std::mem::size_of::<IsoParams>(),
            &[
                ("eye", offset_of!(IsoParams, eye)),
                ("forward", offset_of!(IsoParams, forward)),
                ("right", offset_of!(IsoParams, right)),
                ("up", offset_of!(IsoParams, up)),
                ("light_dir", offset_of!(IsoParams, light_dir)),
                ("light_color", offset_of!(IsoParams, light_color)),
                ("ambient", offset_of!(IsoParams, ambient)),
                ("albedo", offset_of!(IsoParams, albedo)),
                ("background", offset_of!(IsoParams, background)),
                ("box_min", offset_of!(IsoParams, box_min)),
                ("box_max", offset_of!(IsoParams, box_max)),
                ("spacing", offset_of!(IsoParams, spacing)),
                ("dims", offset_of!(IsoParams, dims)),
                ("block_counts", offset_of!(IsoParams, block_counts)),
                ("full_size", offset_of!(IsoParams, full_size)),
                ("window_origin", offset_of!(IsoParams, window_origin)),
                ("window_size", offset_of!(IsoParams, window_size)),
                ("shading", offset_of!(IsoParams, shading)),
                ("iso", offset_of!(IsoParams, iso)),
                ("shininess", offset_of!(IsoParams, shininess)),
                ("refine_steps", offset_of!(IsoParams, refine_steps)),
                ("max_steps", offset_of!(IsoParams, max_steps)),
                ("_pad", offset_of!(IsoParams, _pad)),
            ],
        );
    }
}
