//! `Kernel::Denoise` (shaders/denoise.wgsl): the edge-aware spatial filter of the occlusion and
//! IBL terms on the GPU, [`crate::denoise::PASSES`] a-trous passes over the rectangle the AO kernel
//! ran on, between the AO kernel and compose, after a prepare dispatch that writes what the
//! passes' taps read (the raw signal and the guide: position and variance). Its definition and CPU twin are
//! [`crate::denoise`]; [`DenoiseParams`] is the twin of the WGSL struct, one per pass at a dynamic
//! offset. [`DenoiseBuffers`] are a rectangle's resources (made once per tile).

use super::{storage_entry, Aovs, FrameParams, GpuContext, GpuError};
use crate::denoise::{self, PASSES};
use crate::shaders::Kernel;
use bytemuck::{Pod, Zeroable};

/// Twin of WGSL `DenoiseParams`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct DenoiseParams {
    /// w: tan(fov_y / 2)
    pub forward: [f32; 4],
    pub right: [f32; 4],
    pub up: [f32; 4],
    pub full_size: [u32; 2],
    pub rect_origin: [u32; 2],
    pub rect_size: [u32; 2],
    pub step: u32,
    /// 1: the prepare dispatch.
    pub prepare: u32,
    pub last: u32,
    pub frames: u32,
    pub samples: f32,
    pub strength: f32,
    pub sigma_plane: f32,
    pub sigma_occlusion: f32,
    pub normal_squarings: u32,
    /// 1: each pixel's frames are its own weight (the E sum's w: a reprojected history), its
    /// samples `frame_samples` times that, its strength from them; 0: `frames`, `samples`,
    /// `strength` for every pixel.
    pub per_pixel: u32,
    /// AO samples per frame.
    pub frame_samples: f32,
    /// [`denoise::FULL_STRENGTH_SAMPLES`].
    pub full_strength: f32,
    pub _pad1: u32,
    pub _pad2: u32,
}

impl DenoiseParams {
    /// Pass `pass` over the rectangle of the frame `frame` (the AO kernel's parameters), with
    /// `frames` frames of `frame.ao_samples` samples in the running sums (`per_pixel`: each pixel's
    /// own weight instead, the output still in running-sum form over `frames`).
    pub fn new(frame: &FrameParams, frames: u32, pass: u32, per_pixel: bool) -> DenoiseParams {
        let samples = frame.ao_samples as u64 * frames as u64;
        DenoiseParams {
            forward: frame.forward,
            right: frame.right,
            up: frame.up,
            full_size: frame.full_size,
            rect_origin: frame.rect_origin,
            rect_size: frame.rect_size,
            step: 1 << pass,
            prepare: 0,
            last: u32::from(pass + 1 == PASSES),
            frames,
            samples: samples as f32,
            strength: denoise::strength(samples),
            sigma_plane: denoise::STOPS.sigma_plane,
            sigma_occlusion: denoise::STOPS.sigma_occlusion,
            normal_squarings: denoise::STOPS.normal_squarings,
            per_pixel: u32::from(per_pixel),
            frame_samples: frame.ao_samples as f32,
            full_strength: denoise::FULL_STRENGTH_SAMPLES as f32,
            _pad1: 0,
            _pad2: 0,
        }
    }

    /// The prepare dispatch before the passes.
    pub fn prepare(frame: &FrameParams, frames: u32, per_pixel: bool) -> DenoiseParams {
        DenoiseParams { step: 0, prepare: 1, last: 0, ..DenoiseParams::new(frame, frames, 0, per_pixel) }
    }
}

/// Dispatches of a frame's filter: the prepare one, then the passes.
const DISPATCHES: u32 = PASSES + 1;

/// Whether a frame of `settings` has anything to filter: AO samples (the filter is guided by the
/// occlusion estimate's variance; without samples the terms carry no noise).
pub fn applies(frame: &FrameParams) -> bool {
    frame.ao_samples > 0
}

/// The compiled kernel.
pub struct DenoiseKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    workgroup: (u32, u32),
    /// Bytes between the passes' parameters (the dynamic offset alignment).
    stride: u64,
}

/// A rectangle's filter resources: two signal and guide buffers the dispatches alternate between,
/// the output (running-sum form, what compose reads), the passes' parameters and the two bind
/// groups. Made once (per tile, or per `render_accumulated`).
pub struct DenoiseBuffers {
    /// E * frames (rgb), A * frames (w), per pixel of the rectangle.
    pub out: wgpu::Buffer,
    params: wgpu::Buffer,
    bind: [wgpu::BindGroup; 2],
    _signal: [wgpu::Buffer; 2],
    _guide: [wgpu::Buffer; 2],
    pixels: u64,
}

impl DenoiseBuffers {
    /// Bytes the buffers of an `n`-pixel rectangle take.
    pub fn bytes(n: u64) -> u64 {
        n * (16 + 16 + 16 + 16 + 16)
    }
}

impl DenoiseKernel {
    /// The bind group layout: the passes' parameters (dynamic offset), the isosurface and AO
    /// kernels' outputs, the previous and this pass's signal and guide, the output (a test holds
    /// it to naga's reflection of the WGSL).
    pub(crate) fn entries() -> Vec<wgpu::BindGroupLayoutEntry> {
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only: true },
                has_dynamic_offset: true,
                min_binding_size: wgpu::BufferSize::new(std::mem::size_of::<DenoiseParams>() as u64),
            },
            count: None,
        }];
        entries.extend((1..=6).map(|b| storage_entry(b, true)));
        entries.extend((7..=9).map(|b| storage_entry(b, false)));
        entries
    }

    pub fn new(ctx: &GpuContext, workgroup: (u32, u32)) -> Result<DenoiseKernel, GpuError> {
        let entries = Self::entries();
        // The voxel format is a constant of the volume kernels only.
        let (pipeline, layout) = ctx.pipeline(Kernel::Denoise, &entries, workgroup, &[])?;
        let align = ctx.device.limits().min_storage_buffer_offset_alignment.max(16) as u64;
        let stride = (std::mem::size_of::<DenoiseParams>() as u64).div_ceil(align) * align;
        Ok(DenoiseKernel { pipeline, layout, workgroup, stride })
    }

    /// The resources of an `n`-pixel rectangle whose isosurface and AO outputs are `aovs`.
    pub(crate) fn buffers(&self, ctx: &GpuContext, n: u64, aovs: &Aovs) -> DenoiseBuffers {
        let inputs = aovs.shading();
        let storage = wgpu::BufferUsages::STORAGE;
        let signal = [
            ctx.buffer("denoise signal 0", n * 16, storage),
            ctx.buffer("denoise signal 1", n * 16, storage),
        ];
        let guide =
            [ctx.buffer("denoise guide 0", n * 16, storage), ctx.buffer("denoise guide 1", n * 16, storage)];
        let out = ctx.buffer("denoised", n * 16, storage | wgpu::BufferUsages::COPY_SRC);
        let params = ctx.buffer(
            "denoise params",
            self.stride * DISPATCHES as u64,
            storage | wgpu::BufferUsages::COPY_DST,
        );
        fn b(binding: u32, buf: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry { binding, resource: buf.as_entire_binding() }
        }
        // Bind group j reads signal/guide 1 - j and writes j.
        let bind = [0usize, 1].map(|j| {
            ctx.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("denoise"),
                layout: &self.layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                            buffer: &params,
                            offset: 0,
                            size: wgpu::BufferSize::new(std::mem::size_of::<DenoiseParams>() as u64),
                        }),
                    },
                    b(1, inputs[0]),
                    b(2, inputs[1]),
                    b(3, inputs[2]),
                    b(4, inputs[3]),
                    b(5, &signal[1 - j]),
                    b(6, &guide[1 - j]),
                    b(7, &signal[j]),
                    b(8, &guide[j]),
                    b(9, &out),
                ],
            })
        });
        DenoiseBuffers { out, params, bind, _signal: signal, _guide: guide, pixels: n }
    }

    /// Writes the passes' parameters for a frame of `frame` (the AO kernel's parameters) with
    /// `frames` frames in the running sums (`per_pixel`: each pixel's own weight), and records the
    /// prepare dispatch and the passes over its rectangle.
    pub(crate) fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        buffers: &DenoiseBuffers,
        frame: &FrameParams,
        frames: u32,
        per_pixel: bool,
    ) {
        let size = (frame.rect_size[0], frame.rect_size[1]);
        debug_assert_eq!(size.0 as u64 * size.1 as u64, buffers.pixels);
        // One write per dispatch at its offset: no host buffer per frame.
        for k in 0..DISPATCHES {
            let p = match k {
                0 => DenoiseParams::prepare(frame, frames, per_pixel),
                _ => DenoiseParams::new(frame, frames, k - 1, per_pixel),
            };
            ctx.write_buffer(&buffers.params, k as u64 * self.stride, bytemuck::bytes_of(&p));
        }
        for k in 0..DISPATCHES {
            let mut cpass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("denoise"),
                timestamp_writes: None,
            });
            cpass.set_pipeline(&self.pipeline);
            cpass.set_bind_group(0, &buffers.bind[(k % 2) as usize], &[(k as u64 * self.stride) as u32]);
            cpass.dispatch_workgroups(
                size.0.div_ceil(self.workgroup.0),
                size.1.div_ceil(self.workgroup.1),
                1,
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::offset_of;

    #[test]
    fn denoise_params_layout_matches_the_wgsl() {
        crate::shaders::tests::check_layout(
            Kernel::Denoise,
            "DenoiseParams",
            std::mem::size_of::<DenoiseParams>(),
            &[
                ("forward", offset_of!(DenoiseParams, forward)),
                ("right", offset_of!(DenoiseParams, right)),
                ("up", offset_of!(DenoiseParams, up)),
                ("full_size", offset_of!(DenoiseParams, full_size)),
                ("rect_origin", offset_of!(DenoiseParams, rect_origin)),
                ("rect_size", offset_of!(DenoiseParams, rect_size)),
                ("step", offset_of!(DenoiseParams, step)),
                ("prepare", offset_of!(DenoiseParams, prepare)),
                ("last", offset_of!(DenoiseParams, last)),
                ("frames", offset_of!(DenoiseParams, frames)),
                ("samples", offset_of!(DenoiseParams, samples)),
                ("strength", offset_of!(DenoiseParams, strength)),
                ("sigma_plane", offset_of!(DenoiseParams, sigma_plane)),
                ("sigma_occlusion", offset_of!(DenoiseParams, sigma_occlusion)),
                ("normal_squarings", offset_of!(DenoiseParams, normal_squarings)),
                ("per_pixel", offset_of!(DenoiseParams, per_pixel)),
                ("frame_samples", offset_of!(DenoiseParams, frame_samples)),
                ("full_strength", offset_of!(DenoiseParams, full_strength)),
                ("_pad1", offset_of!(DenoiseParams, _pad1)),
                ("_pad2", offset_of!(DenoiseParams, _pad2)),
            ],
        );
    }

    #[test]
    fn passes_double_their_step_after_the_prepare_dispatch() {
        let mut f: FrameParams = Zeroable::zeroed();
        f.ao_samples = 4;
        let p: Vec<DenoiseParams> = (0..PASSES).map(|k| DenoiseParams::new(&f, 4, k, false)).collect();
        assert_eq!(p.iter().map(|p| p.step).collect::<Vec<_>>(), vec![1, 2, 4, 8, 16]);
        assert_eq!(p.iter().map(|p| p.prepare).sum::<u32>(), 0);
        let prep = DenoiseParams::prepare(&f, 4, false);
        assert_eq!((prep.prepare, prep.last, prep.samples, prep.per_pixel), (1, 0, 16.0, 0));
        assert_eq!(p.iter().map(|p| p.last).sum::<u32>(), 1);
        assert_eq!(p[PASSES as usize - 1].last, 1);
        assert_eq!(p[0].samples, 16.0);
        assert_eq!(p[0].strength, 0.5);
    }
}
