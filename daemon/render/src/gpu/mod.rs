//! The wgpu renderer. One render thread owns the [`GpuRenderer`] (and so the device); the volume
//! ([`GpuVolume`]) and the environment ([`GpuEnvironment`]) are uploaded once.
//!
//! A frame is two kernels: [`Kernel::Isosurface`](crate::shaders::Kernel) (first hit, normal,
//! direct light) and, when AO or IBL is on, [`Kernel::Ao`](crate::shaders::Kernel) once per
//! accumulated frame (occlusion, bent normal, IBL term, added into accumulators). Colour is
//! composed exactly as the CPU reference does, `exposure * (direct + albedo * E)` with
//! `E = ambient` when neither AO nor IBL is on, and with `settings.denoise` on E (and A) first
//! filtered by [`Kernel::Denoise`](crate::shaders::Kernel) (`denoise.rs`; its CPU twin is
//! [`crate::denoise`]):
//! - a wall tile ([`TileTarget`], `tile.rs`): on the GPU by [`Kernel::Compose`](crate::shaders::Kernel)
//!   into the tile's presentable image, with resources made once and only what leaves the node
//!   read back ([`ReadbackRing`]);
//! - [`GpuRenderer::render_accumulated`] (files, AOVs, benchmarks): every AOV is read back into a
//!   [`Frame`] and the host composes.
//!
//! Every GPU allocation and transfer goes through [`GpuContext`]'s counting helpers
//! ([`GpuTraffic`]).

pub mod ao;
pub mod compose;
pub mod denoise;
pub mod frame_params;
pub mod isosurface;
pub mod perf;
pub mod present;
pub mod readback;
pub mod reproject;
pub mod tile;

use crate::environment::Environment;
use crate::shaders::{self, Kernel};
use crate::Frame;
use isowall_model::{IblMethod, RenderSettings, View};
use isowall_volume::{BlockMinMax, Volume, VoxelFormat};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use wgpu::util::DeviceExt;

pub use ao::AoKernel;
pub use compose::{ComposeKernel, ComposeParams};
pub use denoise::{DenoiseKernel, DenoiseParams};
pub use frame_params::FrameParams;
pub use isosurface::IsosurfaceKernel;
pub use perf::PerfOptions;
pub use readback::ReadbackRing;
pub use reproject::{ReprojectKernel, ReprojectParams};
pub use tile::{
    CanvasFrame, FrameCounters, FrameRead, ReadKind, TileFrame, TileOutput, TileSums, TileTarget,
};

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no Vulkan adapter found ({0}). On a machine without a GPU driver install Mesa's software driver lavapipe: `apt-get install mesa-vulkan-drivers` (as root)")]
    NoAdapter(String),
    #[error("the Vulkan adapter '{adapter}' refused a device: {source}")]
    Device { adapter: String, source: wgpu::RequestDeviceError },
    #[error(
        "{name} needs a {bytes}-byte buffer but the adapter allows at most {limit} bytes per storage binding"
    )]
    TooLarge { name: String, bytes: u64, limit: u64 },
    #[error("GPU validation failed in {stage}: {message}")]
    Validation { stage: &'static str, message: String },
    #[error("GPU readback failed: {0}")]
    Readback(String),
    #[error("invalid view: {0}")]
    View(String),
    #[error("invalid settings: {0}")]
    Settings(String),
    #[error("presentation: {0}")]
    Surface(String),
}

/// The device, its queue, and what adapter they came from. The instance and adapter are kept for
/// presentation: window surfaces are created from the same instance and configured for the adapter.
pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    /// What the renderer asked of the device so far (allocations, bytes each way).
    pub traffic: GpuTraffic,
}

/// Running totals of what the renderer asks of the device: GPU objects created (buffers,
/// textures, bind groups) and bytes uploaded and read back. Every creation and transfer of the
/// renderer goes through [`GpuContext`]'s helpers, which count it; a benchmark takes the
/// difference over a frame.
#[derive(Debug, Default)]
pub struct GpuTraffic {
    allocations: AtomicU64,
    uploaded: AtomicU64,
    read_back: AtomicU64,
}

/// A [`GpuTraffic`] reading.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TrafficCount {
    pub allocations: u64,
    pub uploaded: u64,
    pub read_back: u64,
}

impl GpuTraffic {
    pub fn now(&self) -> TrafficCount {
        TrafficCount {
            allocations: self.allocations.load(Ordering::Relaxed),
            uploaded: self.uploaded.load(Ordering::Relaxed),
            read_back: self.read_back.load(Ordering::Relaxed),
        }
    }

    pub(crate) fn read_back(&self, bytes: u64) {
        self.read_back.fetch_add(bytes, Ordering::Relaxed);
    }
}

impl std::ops::Sub for TrafficCount {
    type Output = TrafficCount;
    fn sub(self, o: TrafficCount) -> TrafficCount {
        TrafficCount {
            allocations: self.allocations - o.allocations,
            uploaded: self.uploaded - o.uploaded,
            read_back: self.read_back - o.read_back,
        }
    }
}

/// The largest storage buffer a kernel can bind under `limits`, in bytes.
pub fn storage_binding_limit(limits: &wgpu::Limits) -> u64 {
    limits.max_storage_buffer_binding_size.min(limits.max_buffer_size)
}

/// The adapter [`GpuContext::new`] would open, by name, and its [`storage_binding_limit`]: asked
/// without opening a device, so that a volume too large to bind is refused before it is read.
pub fn adapter_storage_limit() -> Result<(String, u64), GpuError> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        ..Default::default()
    }))
    .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
    Ok((adapter.get_info().name, storage_binding_limit(&adapter.limits())))
}

impl GpuContext {
    /// Opens the best Vulkan adapter (a real GPU before a software one) with its full limits.
    /// `WGPU_ADAPTER_NAME` and the other wgpu environment variables are honoured.
    pub fn new() -> Result<GpuContext, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("isowall"),
            required_limits: adapter.limits(),
            // Per-pass GPU times of a tile's frame (`isowalld bench frame`), where the adapter has them.
            // The texture march samples an r32float volume with a linear filter where the adapter
            // can (`GpuContext::march_format`).
            required_features: adapter.features()
                & (wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::FLOAT32_FILTERABLE),
            ..Default::default()
        }))
        .map_err(|source| GpuError::Device { adapter: info.name.clone(), source })?;
        tracing::info!(adapter = %info.name, backend = ?info.backend, kind = ?info.device_type, "GPU device open");
        Ok(GpuContext { device, queue, info, instance, adapter, traffic: GpuTraffic::default() })
    }

    /// How many loop iterations one invocation of a kernel may make in all, where the driver
    /// ends its loops past a budget: Mesa's llvmpipe (lavapipe) does at 65535 (gallivm's
    /// `LP_MAX_TGSI_LOOP_ITERATIONS`, shared by every loop of the shader), silently. `None`: no
    /// such limit (every other driver: Vulkan requires loops to run to their end).
    pub fn loop_budget(&self) -> Option<u32> {
        let llvmpipe =
            self.info.driver.eq_ignore_ascii_case("llvmpipe") || self.info.name.starts_with("llvmpipe");
        llvmpipe.then_some(65535)
    }

    /// `device.create_buffer`, counted.
    pub fn create_buffer(&self, desc: &wgpu::BufferDescriptor) -> wgpu::Buffer {
        self.traffic.allocations.fetch_add(1, Ordering::Relaxed);
        self.device.create_buffer(desc)
    }

    /// A labelled buffer of `size` bytes for `usage`, not mapped at creation ([`Self::create_buffer`]).
    pub fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        })
    }

    /// `device.create_buffer_init`, counted (an allocation and its bytes uploaded).
    pub fn create_buffer_init(&self, desc: &wgpu::util::BufferInitDescriptor) -> wgpu::Buffer {
        self.traffic.allocations.fetch_add(1, Ordering::Relaxed);
        self.traffic.uploaded.fetch_add(desc.contents.len() as u64, Ordering::Relaxed);
        self.device.create_buffer_init(desc)
    }

    /// `device.create_texture`, counted.
    pub fn create_texture(&self, desc: &wgpu::TextureDescriptor) -> wgpu::Texture {
        self.traffic.allocations.fetch_add(1, Ordering::Relaxed);
        self.device.create_texture(desc)
    }

    /// `device.create_sampler`, counted.
    pub fn create_sampler(&self, desc: &wgpu::SamplerDescriptor) -> wgpu::Sampler {
        self.traffic.allocations.fetch_add(1, Ordering::Relaxed);
        self.device.create_sampler(desc)
    }

    /// The texel format of the texture march's copy of the volume (`PerfOptions::texture`):
    /// r32float where the device filters it linearly (`FLOAT32_FILTERABLE`: the voxels exactly),
    /// else r16float (always filterable; the march's values rounded to halves, the refinement
    /// still exact).
    pub fn march_format(&self) -> wgpu::TextureFormat {
        if self.device.features().contains(wgpu::Features::FLOAT32_FILTERABLE) {
            wgpu::TextureFormat::R32Float
        } else {
            wgpu::TextureFormat::R16Float
        }
    }

    /// `device.create_bind_group`, counted.
    pub fn create_bind_group(&self, desc: &wgpu::BindGroupDescriptor) -> wgpu::BindGroup {
        self.traffic.allocations.fetch_add(1, Ordering::Relaxed);
        self.device.create_bind_group(desc)
    }

    /// `queue.write_buffer`, counted.
    pub fn write_buffer(&self, buffer: &wgpu::Buffer, offset: u64, data: &[u8]) {
        self.traffic.uploaded.fetch_add(data.len() as u64, Ordering::Relaxed);
        self.queue.write_buffer(buffer, offset, data);
    }

    /// `queue.write_texture`, counted.
    pub fn write_texture(
        &self,
        texture: wgpu::TexelCopyTextureInfo,
        data: &[u8],
        layout: wgpu::TexelCopyBufferLayout,
        size: wgpu::Extent3d,
    ) {
        self.traffic.uploaded.fetch_add(data.len() as u64, Ordering::Relaxed);
        self.queue.write_texture(texture, data, layout, size);
    }

    /// Runs `f` inside a validation error scope and turns a captured error into [`GpuError`].
    pub(crate) fn validated<T>(&self, stage: &'static str, f: impl FnOnce() -> T) -> Result<T, GpuError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let out = f();
        match pollster::block_on(scope.pop()) {
            None => Ok(out),
            Some(e) => Err(GpuError::Validation { stage, message: e.to_string() }),
        }
    }

    /// Blocks until the queue is idle.
    pub(crate) fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Readback(e.to_string()))
    }

    /// A storage buffer initialised with `contents`, refused with a clear error past the limits.
    fn storage_init(&self, name: &str, contents: &[u8]) -> Result<wgpu::Buffer, GpuError> {
        let limit = storage_binding_limit(&self.device.limits());
        if contents.len() as u64 > limit {
            return Err(GpuError::TooLarge { name: name.to_string(), bytes: contents.len() as u64, limit });
        }
        self.validated("upload", || {
            self.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(name),
                contents,
                // COPY_DST: a brick's next time step is written into its buffers.
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            })
        })
    }

    /// A compute pipeline for `kernel` with one bind group of `entries`.
    /// `workgroup` is the kernel's workgroup shape (x, y), replacing the `@workgroup_size` the
    /// WGSL declares; `constants` the values of the pipeline constants (`override`s) the kernel
    /// declares, e.g. `VOXEL_FORMAT` (the voxel storage the volume kernels read).
    pub(crate) fn pipeline(
        &self,
        kernel: Kernel,
        entries: &[wgpu::BindGroupLayoutEntry],
        workgroup: (u32, u32),
        constants: &[(&str, f64)],
    ) -> Result<(wgpu::ComputePipeline, wgpu::BindGroupLayout), GpuError> {
        let layout = self.validated("pipeline", || {
            self.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(kernel.file_name()),
                entries,
            })
        })?;
        let pipeline = self.pipeline_for_layout(kernel, &layout, workgroup, constants)?;
        Ok((pipeline, layout))
    }

    /// Another compute pipeline of `kernel` (other `constants`) for the bind group `layout` of a
    /// first one, so that the same bind groups serve both.
    pub(crate) fn pipeline_for_layout(
        &self,
        kernel: Kernel,
        layout: &wgpu::BindGroupLayout,
        workgroup: (u32, u32),
        constants: &[(&str, f64)],
    ) -> Result<wgpu::ComputePipeline, GpuError> {
        self.validated("pipeline", || {
            let device = &self.device;
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(kernel.file_name()),
                source: wgpu::ShaderSource::Wgsl(shaders::source_with_workgroup(kernel, workgroup).into()),
            });
            let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(kernel.file_name()),
                bind_group_layouts: &[Some(layout)],
                immediate_size: 0,
            });
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(kernel.file_name()),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some("main"),
                compilation_options: wgpu::PipelineCompilationOptions { constants, ..Default::default() },
                cache: None,
            })
        })
    }
}

/// Bind group layout entries shared by every kernel: the frame parameters (0), the voxels (1) and
/// the block min/max (2), as declared in shaders/frame.wgsl (the parameters in a read-only storage
/// buffer: see there why not a uniform).
pub(crate) fn frame_entries() -> [wgpu::BindGroupLayoutEntry; 3] {
    [
        wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only: true },
                has_dynamic_offset: false,
                min_binding_size: wgpu::BufferSize::new(std::mem::size_of::<FrameParams>() as u64),
            },
            count: None,
        },
        storage_entry(1, true),
        storage_entry(2, true),
    ]
}

/// Bind group entries binding `buffers` whole at bindings 0, 1, 2, ... in order.
pub(crate) fn buffer_entries<'a>(buffers: &[&'a wgpu::Buffer]) -> Vec<wgpu::BindGroupEntry<'a>> {
    buffers
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupEntry { binding: i as u32, resource: b.as_entire_binding() })
        .collect()
}

pub(crate) fn storage_entry(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
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

/// Records one compute pass of `pipeline` (compiled with workgroup shape `workgroup`) over a `size`
/// rectangle with `bind_group` at group 0; `timestamps` where the pass is timed.
pub(crate) fn pass(
    enc: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::ComputePipeline,
    bind_group: &wgpu::BindGroup,
    label: &str,
    size: (u32, u32),
    workgroup: (u32, u32),
    timestamps: Option<wgpu::ComputePassTimestampWrites>,
) {
    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
        label: Some(label),
        timestamp_writes: timestamps,
    });
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bind_group, &[]);
    pass.dispatch_workgroups(size.0.div_ceil(workgroup.0), size.1.div_ceil(workgroup.1), 1);
}

/// A number no other volume or environment upload of this process has.
fn next_resource_id() -> u64 {
    static NEXT: AtomicU64 = AtomicU64::new(1);
    NEXT.fetch_add(1, Ordering::Relaxed)
}

/// A volume on the GPU: voxels (packed as `format`) and per-block min/max (the fine level, then the
/// coarse one).
pub struct GpuVolume {
    /// Identifies this upload (a tile's bind groups are made once per volume they bind).
    pub id: u64,
    voxels: wgpu::Buffer,
    block_minmax: wgpu::Buffer,
    /// The texture march's copy of the voxels (`PerfOptions::texture`), or one texel.
    pub march: MarchTexture,
    /// How the voxels are stored; the kernels that read them must be compiled for it.
    pub format: VoxelFormat,
    /// The value range the unorm formats span (the whole volume's).
    pub value_range: (f32, f32),
    /// Bytes resident on the GPU: the packed voxels, and every block level's min/max.
    pub voxel_bytes: u64,
    pub minmax_bytes: u64,
    pub dims: [u32; 3],
    pub block: u32,
    pub counts: [u32; 3],
    /// The AO rays' own block level (performance), if uploaded.
    pub ao_level: Option<BlockLevel>,
    /// The coarse level of AO rays, if uploaded.
    pub coarse_level: Option<BlockLevel>,
    pub spacing: glam::DVec3,
    pub box_min: glam::DVec3,
    pub box_max: glam::DVec3,
    pub name: String,
    // object space
    /// Where the buffer holds a brick and its halo, not the whole volume.
    pub object: Option<ObjectSpace>,
}

/// The volume as a `texture_3d` the primary march samples through the hardware's trilinear filter
/// (`PerfOptions::texture`, `TEXTURE_MARCH` in shaders/isosurface.wgsl), texel i holding sample i,
/// with its linear, clamp-to-edge sampler. Where the march reads the storage volume it is a single
/// texel, bound (the kernel's layout has it) and never sampled.
pub struct MarchTexture {
    texture: wgpu::Texture,
    pub(crate) view: wgpu::TextureView,
    pub(crate) sampler: wgpu::Sampler,
    /// Whether it holds the volume.
    pub enabled: bool,
    /// Bytes resident on the GPU.
    pub bytes: u64,
}

impl MarchTexture {
    /// The texture of `voxels` (x fastest, `dims`) in [`GpuContext::march_format`], or one texel
    /// where `voxels` is `None`.
    fn new(
        ctx: &GpuContext,
        name: &str,
        voxels: Option<(&[f32], [usize; 3])>,
    ) -> Result<MarchTexture, GpuError> {
        let dims = voxels.map_or([1, 1, 1], |(_, d)| d);
        let max = ctx.device.limits().max_texture_dimension_3d as usize;
        if dims.iter().any(|&d| d > max) {
            return Err(GpuError::Settings(format!(
                "texture march: {name} is {dims:?} samples but the adapter's 3D textures hold at most {max} per axis"
            )));
        }
        let format = ctx.march_format();
        let texture = ctx.validated("upload", || {
            ctx.create_texture(&wgpu::TextureDescriptor {
                label: Some(name),
                size: wgpu::Extent3d {
                    width: dims[0] as u32,
                    height: dims[1] as u32,
                    depth_or_array_layers: dims[2] as u32,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D3,
                format,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            })
        })?;
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let sampler = ctx.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("march"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            address_mode_w: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        let texel = format.block_copy_size(None).unwrap_or(4) as u64;
        let bytes = texel * dims.iter().map(|&d| d as u64).product::<u64>();
        let march = MarchTexture { texture, view, sampler, enabled: voxels.is_some(), bytes };
        if let Some((data, _)) = voxels {
            march.write(ctx, data, dims);
        }
        Ok(march)
    }

    /// Writes `voxels` (x fastest, `dims`: the texture's own) into the texture.
    fn write(&self, ctx: &GpuContext, voxels: &[f32], dims: [usize; 3]) {
        let bytes: Vec<u8> = if self.texture.format() == wgpu::TextureFormat::R32Float {
            bytemuck::cast_slice(voxels).to_vec()
        } else {
            // r16float: IEEE halves, as the r16f voxel format packs them (first in the low bits).
            let words = VoxelFormat::R16F.pack(voxels, (0.0, 0.0));
            bytemuck::cast_slice::<u32, u8>(&words)[..voxels.len() * 2].to_vec()
        };
        let texel = bytes.len() / voxels.len().max(1);
        ctx.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            &bytes,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some((dims[0] * texel) as u32),
                rows_per_image: Some(dims[1] as u32),
            },
            self.texture.size(),
        );
    }
}

/// Object space: the GPU volume holds a brick and its halo (`isowall_model::bricks`). The box,
/// spacing and block grid stay the whole volume's; the voxels are the region starting at
/// `data_offset`.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectSpace {
    /// Global sample index of the buffer's first sample.
    pub data_offset: [usize; 3],
    /// The brick owns a (box-clamped) point q when `owned_min <= q < owned_max` (the brick's
    /// `owned_planes`).
    pub owned_min: glam::DVec3,
    pub owned_max: glam::DVec3,
}

impl GpuVolume {
    /// Uploads the voxels packed as `format` and the block min/max of the primary rays (`blocks`),
    /// then of AO rays' own levels where given: `ao` (their fine level) and `coarse`
    /// (hierarchical skipping). The block levels must be those of the voxels as `format` stores
    /// them (`Volume::stored_as`), so that skipping stays conservative. With `texture` the voxels
    /// also go into the texture march's texture ([`MarchTexture`]).
    pub fn upload(
        ctx: &GpuContext,
        v: &Volume,
        format: VoxelFormat,
        blocks: &BlockMinMax,
        ao: Option<&BlockMinMax>,
        coarse: Option<&BlockMinMax>,
        texture: bool,
    ) -> Result<GpuVolume, GpuError> {
        let value_range = v.value_range();
        let words = format.pack(v.data(), value_range);
        let voxels = ctx.storage_init(&format!("volume {}", v.name), bytemuck::cast_slice(&words))?;
        let march = MarchTexture::new(ctx, &v.name, texture.then(|| (v.data(), v.dims())))?;
        let mut minmax = blocks.minmax.clone();
        let mut append = |b: Option<&BlockMinMax>| {
            b.map(|b| {
                let level = BlockLevel {
                    counts: b.counts.map(|c| c as u32),
                    cells: b.block as u32,
                    offset: minmax.len() as u32,
                };
                minmax.extend_from_slice(&b.minmax);
                level
            })
        };
        let ao_level = append(ao);
        let coarse_level = append(coarse);
        let block_minmax = ctx.storage_init("block min/max", bytemuck::cast_slice(&minmax))?;
        let d = v.dims();
        Ok(GpuVolume {
            id: next_resource_id(),
            voxels,
            block_minmax,
            march,
            format,
            value_range,
            voxel_bytes: words.len() as u64 * 4,
            minmax_bytes: minmax.len() as u64 * 8,
            dims: [d[0] as u32, d[1] as u32, d[2] as u32],
            block: blocks.block as u32,
            counts: blocks.counts.map(|c| c as u32),
            ao_level,
            coarse_level,
            spacing: v.spacing(),
            box_min: v.box_min(),
            box_max: v.box_max(),
            name: v.name.clone(),
            object: None,
        })
    }

    /// Object space: uploads `region` (a brick and its halo, the samples from `object.data_offset`
    /// on) of the volume `whole` describes, with the whole volume's block min/max `blocks`, the
    /// voxels packed as `format`. The unorm formats are refused: they span the whole volume's
    /// value range, which a brick node does not know, and bricks rounding alike is what keeps
    /// their seams invisible. With `texture` the region also goes into the texture march's
    /// texture.
    pub fn upload_brick(
        ctx: &GpuContext,
        region: &Volume,
        whole: &isowall_volume::VolumeInfo,
        blocks: &BlockMinMax,
        object: ObjectSpace,
        format: VoxelFormat,
        texture: bool,
    ) -> Result<GpuVolume, GpuError> {
        if format.is_unorm() {
            return Err(GpuError::Settings(format!(
                "object space: voxel format {} spans the whole volume's value range, which a brick does not know (use r32f or r16f)",
                format.name()
            )));
        }
        let o = object.data_offset;
        let d = region.dims();
        if (0..3).any(|a| o[a] + d[a] > whole.dims[a]) {
            return Err(GpuError::Settings(format!(
                "brick region {d:?} at {o:?} does not fit the volume's {:?}",
                whole.dims
            )));
        }
        let value_range = (0.0, 0.0); // r32f and r16f need none
        let words = format.pack(region.data(), value_range);
        let voxels = ctx.storage_init(&format!("brick of {}", whole.name), bytemuck::cast_slice(&words))?;
        let minmax = stored_minmax(format, blocks, value_range);
        let block_minmax = ctx.storage_init("block min/max", bytemuck::cast_slice(&minmax))?;
        // The texture holds the voxels as stored (r16f rounds them).
        let stored = (format != VoxelFormat::R32F).then(|| region.stored_as(format));
        let texels = stored.as_ref().unwrap_or(region);
        let march = MarchTexture::new(ctx, &whole.name, texture.then(|| (texels.data(), d)))?;
        Ok(GpuVolume {
            id: next_resource_id(),
            voxels,
            block_minmax,
            march,
            format,
            value_range,
            voxel_bytes: words.len() as u64 * 4,
            minmax_bytes: minmax.len() as u64 * 8,
            dims: [d[0] as u32, d[1] as u32, d[2] as u32],
            block: blocks.block as u32,
            counts: blocks.counts.map(|c| c as u32),
            spacing: whole.spacing,
            box_min: whole.box_min(),
            box_max: whole.box_max(),
            name: whole.name.clone(),
            // A brick's AO rays use the primary block level (the whole volume's grid): the extra
            // levels are built from a whole volume's voxels, which a brick node does not hold.
            ao_level: None,
            coarse_level: None,
            object: Some(object),
        })
    }

    /// Whether every block level's cells per edge is a power of two (what kernels compiled for
    /// `PerfOptions::pow2_levels` need: they find a cell's block by a shift).
    pub fn pow2_levels(&self) -> bool {
        let levels = [self.ao_level, self.coarse_level];
        self.block.is_power_of_two() && levels.iter().flatten().all(|l| l.cells.is_power_of_two())
    }

    /// Object space, a time-varying volume: puts another step of the same brick in this
    /// volume's buffers, `region` (its brick and halo) and `blocks` (the step's block min/max of
    /// the whole volume), written in place (the buffers, and the tiles' bind groups made for
    /// them, are kept). Frames submitted before read the old step, later ones the new. Refused
    /// where the sizes differ from what the buffers hold (upload a new volume then).
    pub fn rewrite_brick(
        &mut self,
        ctx: &GpuContext,
        region: &Volume,
        blocks: &BlockMinMax,
    ) -> Result<(), GpuError> {
        let d = region.dims();
        let dims = [d[0] as u32, d[1] as u32, d[2] as u32];
        if self.object.is_none()
            || dims != self.dims
            || blocks.block as u32 != self.block
            || blocks.counts.map(|c| c as u32) != self.counts
        {
            return Err(GpuError::Settings(format!(
                "brick region {d:?} with blocks {:?} does not fit the buffers of {} ({:?}, blocks {:?})",
                blocks.counts, self.name, self.dims, self.counts
            )));
        }
        let words = self.format.pack(region.data(), self.value_range);
        let minmax = stored_minmax(self.format, blocks, self.value_range);
        ctx.queue.write_buffer(&self.voxels, 0, bytemuck::cast_slice(&words));
        ctx.queue.write_buffer(&self.block_minmax, 0, bytemuck::cast_slice(&minmax));
        if self.march.enabled {
            let stored = (self.format != VoxelFormat::R32F).then(|| region.stored_as(self.format));
            self.march.write(ctx, stored.as_ref().unwrap_or(region).data(), d);
        }
        Ok(())
    }
}

/// A brick's block min/max as its voxels are stored: rounding is monotone, so the stored voxels'
/// block min/max are the rounded min/max.
fn stored_minmax(format: VoxelFormat, blocks: &BlockMinMax, value_range: (f32, f32)) -> Vec<[f32; 2]> {
    let round = |v: f32| format.decode(format.encode(v, value_range), value_range);
    blocks.minmax.iter().map(|m| [round(m[0]), round(m[1])]).collect()
}

/// A block level uploaded after the primary rays' one: its counts, cells per edge and where its
/// min/max start in the buffer (in blocks).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BlockLevel {
    pub counts: [u32; 3],
    pub cells: u32,
    pub offset: u32,
}

impl BlockLevel {
    /// (counts, cells) as `FrameParams` carries a level.
    pub fn params(&self) -> [u32; 4] {
        [self.counts[0], self.counts[1], self.counts[2], self.cells]
    }
}

/// An environment on the GPU: the equirectangular texels and their SH9 projection.
pub struct GpuEnvironment {
    /// Identifies this upload (see [`GpuVolume::id`]).
    pub id: u64,
    texels: wgpu::Buffer,
    pub width: u32,
    pub height: u32,
    pub sh: [[f32; 3]; 9],
}

impl GpuEnvironment {
    pub fn upload(ctx: &GpuContext, env: &Environment) -> Result<GpuEnvironment, GpuError> {
        let texels = ctx.storage_init(
            &format!("environment {}", env.name),
            bytemuck::cast_slice(&env.equirect_f32x4()),
        )?;
        Ok(GpuEnvironment {
            id: next_resource_id(),
            texels,
            width: env.width,
            height: env.height,
            sh: env.sh9(),
        })
    }
}

/// The GPU renderer: device plus compiled kernels.
pub struct GpuRenderer {
    pub ctx: GpuContext,
    isosurface: IsosurfaceKernel,
    ao: AoKernel,
    compose: ComposeKernel,
    denoise: DenoiseKernel,
    reproject: ReprojectKernel,
    perf: PerfOptions,
    /// Bound where no environment is given (IBL off): one black texel.
    no_env: GpuEnvironment,
}

/// A rendered frame and the time the GPU took for it (submit to done, readback excluded).
pub struct Rendered {
    pub frame: Frame,
    pub gpu_time: Duration,
    /// All the time the host waited for the GPU: the frame and its readback.
    pub wait_time: Duration,
}

/// The most frames one `render` accumulates.
pub const MAX_FRAMES: u32 = 4096;

impl GpuRenderer {
    pub fn new() -> Result<GpuRenderer, GpuError> {
        let ctx = GpuContext::new()?;
        let perf = PerfOptions::default();
        let isosurface = IsosurfaceKernel::new(&ctx, &perf)?;
        let ao = AoKernel::new(&ctx, &perf)?;
        let compose = ComposeKernel::new(&ctx, perf.workgroup)?;
        let denoise = DenoiseKernel::new(&ctx, perf.workgroup)?;
        let reproject = ReprojectKernel::new(&ctx, perf.workgroup)?;
        let no_env = GpuEnvironment::upload(&ctx, &Environment::constant([0.0; 3]))?;
        Ok(GpuRenderer { ctx, isosurface, ao, compose, denoise, reproject, perf, no_env })
    }

    /// The performance options in use.
    pub fn perf(&self) -> PerfOptions {
        self.perf
    }

    /// Changes the performance options (for benchmarks: the defaults are the measured best). A new
    /// workgroup shape, voxel format, march or power-of-two-ness of the block levels recompiles
    /// the kernels; block sizes, the format and
    /// the march's texture apply to volumes uploaded afterwards (a volume stored in another format than the kernels read is
    /// refused at render).
    pub fn set_perf(&mut self, perf: PerfOptions) -> Result<(), GpuError> {
        perf.validate().map_err(GpuError::Settings)?;
        let compiled = |p: &PerfOptions| (p.workgroup, p.format, p.texture, p.pow2_levels());
        if compiled(&perf) != compiled(&self.perf) {
            self.isosurface = IsosurfaceKernel::new(&self.ctx, &perf)?;
            self.ao = AoKernel::new(&self.ctx, &perf)?;
            self.compose = ComposeKernel::new(&self.ctx, perf.workgroup)?;
            self.denoise = DenoiseKernel::new(&self.ctx, perf.workgroup)?;
            self.reproject = ReprojectKernel::new(&self.ctx, perf.workgroup)?;
        }
        self.perf = perf;
        Ok(())
    }

    pub fn adapter_name(&self) -> &str {
        &self.ctx.info.name
    }

    /// What wgpu says of the adapter: name, backend, driver and its description.
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.ctx.info
    }

    /// Uploads a volume (voxels packed as the options' format) and its block min/max for rendering.
    pub fn upload(&self, volume: &Volume) -> Result<GpuVolume, GpuError> {
        let p = self.perf;
        // The block levels of the voxels as stored, so that skipping stays conservative.
        let stored;
        let volume = if p.format == VoxelFormat::R32F {
            volume
        } else {
            stored = volume.stored_as(p.format);
            &stored
        };
        let blocks = BlockMinMax::new(volume, p.block as usize);
        let level = |cells: u32| {
            (cells > 0 && cells != p.block).then(|| {
                if cells.is_multiple_of(p.block) {
                    blocks.coarsen((cells / p.block) as usize)
                } else {
                    BlockMinMax::new(volume, cells as usize)
                }
            })
        };
        let ao = level(p.ao_block);
        let coarse = (p.coarse > 0).then(|| BlockMinMax::new(volume, p.coarse as usize));
        GpuVolume::upload(&self.ctx, volume, p.format, &blocks, ao.as_ref(), coarse.as_ref(), p.texture)
    }

    /// Object space: uploads a brick and its halo ([`GpuVolume::upload_brick`]).
    pub fn upload_brick(
        &self,
        region: &Volume,
        whole: &isowall_volume::VolumeInfo,
        blocks: &BlockMinMax,
        object: ObjectSpace,
    ) -> Result<GpuVolume, GpuError> {
        GpuVolume::upload_brick(&self.ctx, region, whole, blocks, object, self.perf.format, self.perf.texture)
    }

    /// Uploads an environment for IBL.
    pub fn upload_environment(&self, env: &Environment) -> Result<GpuEnvironment, GpuError> {
        GpuEnvironment::upload(&self.ctx, env)
    }

    /// Checks a frame's view, settings and volume before any GPU work; the environment to bind.
    fn check_frame<'a>(
        &'a self,
        volume: &GpuVolume,
        view: &View,
        settings: &RenderSettings,
        env: Option<&'a GpuEnvironment>,
        frames: u32,
    ) -> Result<&'a GpuEnvironment, GpuError> {
        let (w, h) = (view.rect.width, view.rect.height);
        if w == 0 || h == 0 || view.full.0 == 0 || view.full.1 == 0 {
            return Err(GpuError::View(format!(
                "empty rectangle {w}x{h} of {}x{}",
                view.full.0, view.full.1
            )));
        }
        if view.rect.x.checked_add(w).is_none_or(|r| r > view.full.0)
            || view.rect.y.checked_add(h).is_none_or(|b| b > view.full.1)
        {
            return Err(GpuError::View(format!(
                "rectangle {:?} lies outside the {}x{} image",
                view.rect, view.full.0, view.full.1
            )));
        }
        view.camera.validate().map_err(|e| GpuError::View(e.to_string()))?;
        if !(1..=MAX_FRAMES).contains(&frames) {
            return Err(GpuError::Settings(format!("frames {frames} is outside 1..={MAX_FRAMES}")));
        }
        if volume.format != self.perf.format {
            return Err(GpuError::Settings(format!(
                "volume {} is stored as {} but the kernels read {} (upload it after set_perf)",
                volume.name,
                volume.format.name(),
                self.perf.format.name()
            )));
        }
        if self.perf.pow2_levels() && !volume.pow2_levels() {
            return Err(GpuError::Settings(format!(
                "volume {} has block levels that are not powers of two but the kernels were compiled for them (upload it after set_perf)",
                volume.name
            )));
        }
        if self.perf.texture && !volume.march.enabled {
            return Err(GpuError::Settings(format!(
                "the texture march needs volume {} uploaded with its texture (upload it after set_perf)",
                volume.name
            )));
        }
        if settings.ibl_needs_environment() && env.is_none() {
            return Err(GpuError::Settings(format!("IBL method {:?} needs an environment", settings.ao.ibl)));
        }
        Ok(env.unwrap_or(&self.no_env))
    }

    /// Renders one frame of `view` and reads every AOV back.
    pub fn render(
        &self,
        volume: &GpuVolume,
        view: &View,
        settings: &RenderSettings,
        env: Option<&GpuEnvironment>,
    ) -> Result<Rendered, GpuError> {
        self.render_accumulated(volume, view, settings, env, 1)
    }

    /// Renders `frames` frames with frame indices `settings.ao.frame ..` (fresh decorrelation each)
    /// and averages their AO and IBL (progressive accumulation); reads every AOV back. With
    /// `settings.denoise` on (and AO samples), the occlusion and IBL terms are the filter's
    /// ([`Kernel::Denoise`](crate::shaders::Kernel) over the view's rectangle).
    pub fn render_accumulated(
        &self,
        volume: &GpuVolume,
        view: &View,
        settings: &RenderSettings,
        env: Option<&GpuEnvironment>,
        frames: u32,
    ) -> Result<Rendered, GpuError> {
        self.render_accumulated_reporting(volume, view, settings, env, frames, None)
    }

    /// [`GpuRenderer::render_accumulated`], calling `on_frame(k)` as each of the `frames` AO frames
    /// is done (k from 1): each frame is then submitted and waited for on its own, where without
    /// `on_frame` all go in one submission. Without AO nothing accumulates and it is not called.
    pub fn render_accumulated_reporting(
        &self,
        volume: &GpuVolume,
        view: &View,
        settings: &RenderSettings,
        env: Option<&GpuEnvironment>,
        frames: u32,
        mut on_frame: Option<&mut dyn FnMut(u32)>,
    ) -> Result<Rendered, GpuError> {
        let env = self.check_frame(volume, view, settings, env, frames)?;
        let (w, h) = (view.rect.width, view.rect.height);
        let n = w as u64 * h as u64;
        let device = &self.ctx.device;
        let with_ao = settings.ao.samples > 0 || settings.ao.ibl != IblMethod::None;
        let denoised = with_ao && settings.denoise.is_on() && settings.ao.samples > 0;

        let sizes = [n * 16, n * 16, n * 4, n * 16, n * 16];
        let (buffers, staging) = self.ctx.validated("frame buffers", || {
            let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
            let read = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
            let labels = ["direct", "geometry", "fetches", "acc ao", "acc ibl"];
            let buffers: Vec<_> =
                labels.iter().zip(sizes).map(|(l, s)| self.ctx.buffer(l, s, storage)).collect();
            let mut staging: Vec<_> =
                labels.iter().zip(sizes).map(|(l, s)| self.ctx.buffer(l, s, read)).collect();
            if denoised {
                staging.push(self.ctx.buffer("denoised", n * 16, read));
            }
            (buffers, staging)
        })?;
        let denoise = denoised.then(|| {
            self.denoise.buffers(&self.ctx, n, [&buffers[0], &buffers[1], &buffers[3], &buffers[4]])
        });

        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        let mut uniforms = Vec::new();
        let mut params = FrameParams::new(volume, view, settings, env);
        params.perf[0] = self.perf.flags();
        let uniform = |p: &FrameParams| {
            self.ctx.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("frame params"),
                contents: bytemuck::bytes_of(p),
                usage: wgpu::BufferUsages::STORAGE,
            })
        };
        let new_encoder =
            || device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        let mut gpu_time = Duration::ZERO;
        self.ctx.validated("encode", || -> Result<(), GpuError> {
            uniforms.push(uniform(&params));
            self.isosurface.encode(
                &self.ctx,
                &mut enc,
                &uniforms[0],
                volume,
                [&buffers[0], &buffers[1], &buffers[2]],
                (w, h),
            );
            if with_ao {
                for k in 0..frames {
                    params.frame = settings.ao.frame.wrapping_add(k);
                    let dispatches = ao::AoDispatches::split(&mut params, self.ctx.loop_budget());
                    uniforms.push(uniform(&params));
                    let u = uniforms.last().expect("just pushed");
                    self.ao.encode(
                        &self.ctx,
                        &mut enc,
                        u,
                        volume,
                        &env.texels,
                        [&buffers[0], &buffers[1], &buffers[3], &buffers[4], &buffers[2]],
                        (w, h),
                        dispatches,
                    );
                    if let Some(report) = on_frame.as_mut() {
                        let start = Instant::now();
                        self.ctx.queue.submit([std::mem::replace(&mut enc, new_encoder()).finish()]);
                        self.ctx.wait()?;
                        gpu_time += start.elapsed();
                        report(k + 1);
                    }
                }
                if let Some(d) = &denoise {
                    self.denoise.encode(&self.ctx, &mut enc, d, &params, frames, false);
                }
            }
            Ok(())
        })??;
        let start = Instant::now();
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.wait()?;
        gpu_time += start.elapsed();

        let mut enc =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("readback") });
        let sources = buffers.iter().chain(denoise.as_ref().map(|d| &d.out));
        for (src, dst) in sources.zip(&staging) {
            enc.copy_buffer_to_buffer(src, 0, dst, 0, None);
        }
        self.ctx.queue.submit([enc.finish()]);
        let (bytes, readback_wait) = read_buffers(&self.ctx, &staging)?;

        let direct: &[[f32; 4]] = bytemuck::cast_slice(&bytes[0]);
        let geometry: &[[f32; 4]] = bytemuck::cast_slice(&bytes[1]);
        let fetches: &[u32] = bytemuck::cast_slice(&bytes[2]);
        let acc_ao: &[[f32; 4]] = bytemuck::cast_slice(&bytes[3]);
        let acc_ibl: &[[f32; 4]] = bytemuck::cast_slice(&bytes[4]);
        // Denoised: E * frames (rgb) and A * frames (w) of the filter, in place of the sums'.
        let filtered: Option<&[[f32; 4]]> = bytes.get(5).map(|b| bytemuck::cast_slice(b));
        let mut frame = Frame::new(w, h);
        let k = if with_ao { frames as f32 } else { 1.0 };
        let exposure = settings.exposure as f32;
        let albedo = settings.material.albedo.map(|a| a as f32);
        let basis = view.camera.basis();
        for i in 0..n as usize {
            let g = geometry[i];
            if direct[i][3] < 0.5 {
                frame.color[i] = settings.background.map(|c| c as f32);
                continue;
            }
            frame.hit[i] = true;
            frame.normal[i] = [g[0], g[1], g[2]];
            frame.depth[i] = g[3];
            let (a, bent, e) = if with_ao {
                let b = glam::Vec3::new(acc_ao[i][0], acc_ao[i][1], acc_ao[i][2]).normalize_or_zero();
                match filtered {
                    Some(f) => (f[i][3] / k, b, [0, 1, 2].map(|c| f[i][c] / k)),
                    None => (acc_ao[i][3] / k, b, [0, 1, 2].map(|c| acc_ibl[i][c] / k)),
                }
            } else {
                let nv = glam::Vec3::from_array(frame.normal[i]);
                let d = view.ray_dir(&basis, (i % w as usize) as u32, (i / w as usize) as u32);
                let facing = if nv.dot(-d.as_vec3()) >= 0.0 { nv } else { -nv };
                (0.0, facing, settings.light.ambient.map(|c| c as f32))
            };
            frame.occlusion[i] = a;
            frame.bent_normal[i] = bent.to_array();
            frame.ibl[i] = e;
            frame.color[i] = std::array::from_fn(|c| exposure * (direct[i][c] + albedo[c] * e[c]));
        }
        frame.fetches = fetches.iter().map(|&f| f as u64).sum();
        tracing::debug!(
            width = w,
            height = h,
            frames,
            hits = frame.hit_count(),
            fetches_per_pixel = frame.fetches_per_pixel(),
            gpu_ms = gpu_time.as_secs_f64() * 1e3,
            "frame rendered"
        );
        Ok(Rendered { frame, gpu_time, wait_time: gpu_time + readback_wait })
    }
}

/// Maps every buffer for reading, waits, and copies their contents out; also the time waited.
fn read_buffers(ctx: &GpuContext, buffers: &[wgpu::Buffer]) -> Result<(Vec<Vec<u8>>, Duration), GpuError> {
    let (tx, rx) = std::sync::mpsc::channel();
    for (i, b) in buffers.iter().enumerate() {
        let tx = tx.clone();
        b.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send((i, r));
        });
    }
    drop(tx);
    let waited = Instant::now();
    ctx.wait()?;
    let waited = waited.elapsed();
    for (i, r) in rx.iter() {
        r.map_err(|e| GpuError::Readback(format!("buffer {i}: {e}")))?;
    }
    let mut out = Vec::with_capacity(buffers.len());
    for b in buffers {
        let view = b.get_mapped_range(..).map_err(|e| GpuError::Readback(e.to_string()))?;
        out.push(view.to_vec());
        ctx.traffic.read_back(b.size());
        drop(view);
        b.unmap();
    }
    Ok((out, waited))
}
