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
pub mod aovs;
pub mod brick_pool;
pub mod compose;
pub mod denoise;
pub mod frame_params;
pub mod isosurface;
pub mod perf;
pub mod present;
pub mod readback;
pub mod reproject;
pub mod resources;
pub mod tile;

use crate::environment::Environment;
use crate::frame_plan::Continuity;
use crate::shaders::{self, Kernel};
use crate::Frame;
use isowall_model::{IblMethod, RenderSettings, View};
use isowall_volume::{BlockMinMax, Volume, VoxelFormat};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use wgpu::util::DeviceExt;

pub use ao::AoKernel;
pub use aovs::Aovs;
pub use brick_pool::{footprint, wanted_by_views, BrickPool, Converged, PoolStats, Refinement};
pub use compose::{ComposeKernel, ComposeParams};
pub use denoise::{DenoiseKernel, DenoiseParams};
pub use frame_params::FrameParams;
pub use isosurface::IsosurfaceKernel;
pub use perf::PerfOptions;
pub use readback::ReadbackRing;
pub use reproject::{ReprojectKernel, ReprojectParams};
pub use resources::{BlockLevel, GpuEnvironment, GpuVolume, MarchTexture, ObjectSpace};
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
/// textures, bind groups), the bytes of the buffers and textures among them, and bytes uploaded
/// and read back. Every creation and transfer of the renderer goes through [`GpuContext`]'s
/// helpers, which count it; a benchmark takes the difference over a frame.
#[derive(Debug, Default)]
pub struct GpuTraffic {
    allocations: AtomicU64,
    allocated_bytes: AtomicU64,
    uploaded: AtomicU64,
    read_back: AtomicU64,
}

/// A [`GpuTraffic`] reading.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TrafficCount {
    pub allocations: u64,
    /// The sizes of the buffers and textures created (a texture's texels at its format's size,
    /// every mip level and sample: what the device is asked to hold, before any padding of its own).
    pub allocated_bytes: u64,
    pub uploaded: u64,
    pub read_back: u64,
}

impl GpuTraffic {
    pub fn now(&self) -> TrafficCount {
        TrafficCount {
            allocations: self.allocations.load(Ordering::Relaxed),
            allocated_bytes: self.allocated_bytes.load(Ordering::Relaxed),
            uploaded: self.uploaded.load(Ordering::Relaxed),
            read_back: self.read_back.load(Ordering::Relaxed),
        }
    }

    fn allocated(&self, bytes: u64) {
        self.allocations.fetch_add(1, Ordering::Relaxed);
        self.allocated_bytes.fetch_add(bytes, Ordering::Relaxed);
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
            allocated_bytes: self.allocated_bytes - o.allocated_bytes,
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
        self.traffic.allocated(desc.size);
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
        self.traffic.allocated(desc.contents.len() as u64);
        self.traffic.uploaded.fetch_add(desc.contents.len() as u64, Ordering::Relaxed);
        self.device.create_buffer_init(desc)
    }

    /// `device.create_texture`, counted.
    pub fn create_texture(&self, desc: &wgpu::TextureDescriptor) -> wgpu::Texture {
        let texels: u64 = (0..desc.mip_level_count)
            .filter_map(|level| desc.mip_level_size(level))
            .map(|size| desc.format.theoretical_memory_footprint(size))
            .sum();
        self.traffic.allocated(texels * u64::from(desc.sample_count));
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
pub(crate) fn frame_entries() -> [wgpu::BindGroupLayoutEntry; 4] {
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
        storage_entry(MARKS_BINDING, false),
    ]
}

/// Where the volume kernels bind a volume's `brick_marks` (shaders/frame.wgsl).
pub(crate) const MARKS_BINDING: u32 = 11;

/// The bind group entry of `volume`'s brick marks.
pub(crate) fn marks_entry(volume: &GpuVolume) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry { binding: MARKS_BINDING, resource: volume.brick_marks.as_entire_binding() }
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

/// The GPU renderer: device plus compiled kernels.
pub struct GpuRenderer {
    pub ctx: GpuContext,
    isosurface: IsosurfaceKernel,
    ao: AoKernel,
    /// The volume kernels compiled for bricked volumes, made at the first one's frame.
    bricked: std::sync::OnceLock<(IsosurfaceKernel, AoKernel)>,
    compose: ComposeKernel,
    denoise: DenoiseKernel,
    reproject: ReprojectKernel,
    perf: PerfOptions,
    /// Bound where no environment is given (IBL off): one black texel.
    no_env: GpuEnvironment,
}

/// A rendered frame and the time its frames took (from the first's recording to the last's end,
/// the AOVs' readback excluded).
pub struct Rendered {
    pub frame: Frame,
    pub gpu_time: Duration,
    /// All the time the host waited for the GPU: the frame and its readback.
    pub wait_time: Duration,
}

pub use crate::frame_plan::MAX_FRAMES;

impl GpuRenderer {
    pub fn new() -> Result<GpuRenderer, GpuError> {
        let ctx = GpuContext::new()?;
        let perf = PerfOptions::default();
        let isosurface = IsosurfaceKernel::new(&ctx, &perf, false)?;
        let ao = AoKernel::new(&ctx, &perf, false)?;
        let compose = ComposeKernel::new(&ctx, perf.workgroup)?;
        let denoise = DenoiseKernel::new(&ctx, perf.workgroup)?;
        let reproject = ReprojectKernel::new(&ctx, perf.workgroup)?;
        let no_env = GpuEnvironment::upload(&ctx, &Environment::constant([0.0; 3]))?;
        let bricked = std::sync::OnceLock::new();
        Ok(GpuRenderer { ctx, isosurface, ao, bricked, compose, denoise, reproject, perf, no_env })
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
            self.isosurface = IsosurfaceKernel::new(&self.ctx, &perf, false)?;
            self.ao = AoKernel::new(&self.ctx, &perf, false)?;
            self.bricked = std::sync::OnceLock::new();
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

    /// Compiles the kernels `volume` needs, where not done yet (a bricked volume's are compiled at
    /// its first frame otherwise, and that frame's time would hold their compilation).
    pub fn prepare(&self, volume: &GpuVolume) -> Result<(), GpuError> {
        self.volume_kernels(volume).map(|_| ())
    }

    /// Compiles the kernels of bricked volumes now, before any is opened.
    pub fn prepare_bricked(&self) -> Result<(), GpuError> {
        self.bricked_kernels().map(|_| ())
    }

    /// The isosurface and AO kernels that read `volume`: the bricked ones (compiled at the first
    /// bricked volume's frame) or the whole volume's.
    pub(crate) fn volume_kernels(
        &self,
        volume: &GpuVolume,
    ) -> Result<(&IsosurfaceKernel, &AoKernel), GpuError> {
        if !volume.bricked {
            return Ok((&self.isosurface, &self.ao));
        }
        self.bricked_kernels()
    }

    /// The kernels of bricked volumes, compiled at the first call.
    fn bricked_kernels(&self) -> Result<(&IsosurfaceKernel, &AoKernel), GpuError> {
        if self.bricked.get().is_none() {
            let kernels = (
                IsosurfaceKernel::new(&self.ctx, &self.perf, true)?,
                AoKernel::new(&self.ctx, &self.perf, true)?,
            );
            let _ = self.bricked.set(kernels);
        }
        let (i, a) = self.bricked.get().expect("set above");
        Ok((i, a))
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
    /// is done (k from 1). Without AO nothing accumulates and it is not called.
    ///
    /// The frames go through the wall tile's own frame path ([`GpuRenderer::render_tile`]: one
    /// recording of a frame's kernels for both), over a tile of the whole view: the first frame
    /// starts over, the others are the same image (the filter, where on, runs on the last); then
    /// every AOV is read back and composed on the host.
    pub fn render_accumulated_reporting(
        &self,
        volume: &GpuVolume,
        view: &View,
        settings: &RenderSettings,
        env: Option<&GpuEnvironment>,
        frames: u32,
        mut on_frame: Option<&mut dyn FnMut(u32)>,
    ) -> Result<Rendered, GpuError> {
        let bound_env = self.check_frame(volume, view, settings, env, frames)?;
        let (w, h) = (view.rect.width, view.rect.height);
        let n = w as u64 * h as u64;
        let with_ao = settings.ao.samples > 0 || settings.ao.ibl != IblMethod::None;
        let runs = if with_ao { frames } else { 1 };
        let mut tile = TileTarget::new(self, "render", view, 1)?;
        let mut ring = ReadbackRing::<FrameRead>::new(2);
        let mut fetches = 0u64;
        let mut collect = |ring: &mut ReadbackRing<FrameRead>| -> Result<(), GpuError> {
            for read in ring.take_ready() {
                let (_, out) = FrameRead::decode(read, self.ctx.queue.get_timestamp_period())?;
                fetches += out.counters.fetches;
            }
            Ok(())
        };
        let start = Instant::now();
        for k in 0..runs {
            let mut s = *settings;
            s.ao.frame = settings.ao.frame.wrapping_add(k);
            if k + 1 < runs {
                s.denoise = isowall_model::Denoise::Off;
            }
            let frame = TileFrame {
                frame_id: u64::from(k),
                volume,
                view,
                settings: &s,
                env: Some(bound_env),
                continuity: if k == 0 { Continuity::Changed } else { Continuity::Same },
                temporal: false,
                share: None,
            };
            while !ring.has_free_slot() {
                ring.wait_oldest(&self.ctx)?;
                collect(&mut ring)?;
            }
            self.render_tile(&mut tile, &frame, &mut ring)?;
            if let (true, Some(report)) = (with_ao, on_frame.as_mut()) {
                ring.wait_oldest(&self.ctx)?;
                collect(&mut ring)?;
                report(k + 1);
            }
        }
        while ring.in_flight() > 0 {
            ring.wait_oldest(&self.ctx)?;
            collect(&mut ring)?;
        }
        collect(&mut ring)?;
        let gpu_time = start.elapsed();
        let readback = Instant::now();
        let sums = self.read_tile_sums(&tile)?;
        let readback_wait = readback.elapsed();
        let mut frame = Frame::new(w, h);
        let k = if with_ao { frames as f32 } else { 1.0 };
        let exposure = settings.exposure as f32;
        let albedo = settings.material.albedo.map(|a| a as f32);
        let basis = view.camera.basis();
        for i in 0..n as usize {
            let (direct, g) = (sums.color[i], sums.geometry[i]);
            if direct[3] < 0.5 {
                frame.color[i] = settings.background.map(|c| c as f32);
                continue;
            }
            frame.hit[i] = true;
            frame.normal[i] = [g[0], g[1], g[2]];
            frame.depth[i] = g[3];
            let (a, bent, e) = if with_ao {
                let acc = sums.ao[i];
                let b = glam::Vec3::new(acc[0], acc[1], acc[2]).normalize_or_zero();
                match &sums.denoised {
                    // Denoised: E * frames (rgb) and A * frames (w) of the filter, in place of the sums'.
                    Some(f) => (f[i][3] / k, b, [0, 1, 2].map(|c| f[i][c] / k)),
                    None => (acc[3] / k, b, [0, 1, 2].map(|c| sums.ibl[i][c] / k)),
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
            frame.color[i] = std::array::from_fn(|c| exposure * (direct[c] + albedo[c] * e[c]));
        }
        frame.fetches = fetches;
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
