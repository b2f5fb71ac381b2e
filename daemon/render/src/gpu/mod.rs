//! The wgpu renderer. One render thread owns the [`GpuRenderer`] (and so the device); the volume is
//! uploaded once ([`GpuVolume`]) and frames are rendered from it, read back into a [`Frame`].

pub mod isosurface;

use crate::Frame;
use isowall_volume::{BlockMinMax, Volume};
use isowall_wall::{RenderSettings, View};
use std::time::Duration;

pub use isosurface::{GpuVolume, IsoParams, IsosurfaceKernel};

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no Vulkan adapter found ({0}). On a machine without a GPU driver install Mesa's software driver lavapipe: `apt-get install mesa-vulkan-drivers` (as root)")]
    NoAdapter(String),
    #[error("the Vulkan adapter '{adapter}' refused a device: {source}")]
    Device { adapter: String, source: wgpu::RequestDeviceError },
    #[error("volume {name} needs a {bytes}-byte buffer but the adapter allows at most {limit} bytes per storage binding")]
    VolumeTooLarge { name: String, bytes: u64, limit: u64 },
    #[error("GPU validation failed in {stage}: {message}")]
    Validation { stage: &'static str, message: String },
    #[error("GPU readback failed: {0}")]
    Readback(String),
    #[error("invalid view: {0}")]
    View(String),
}

/// The device, its queue, and what adapter they came from.
pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
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
            ..Default::default()
        }))
        .map_err(|source| GpuError::Device { adapter: info.name.clone(), source })?;
        tracing::info!(adapter = %info.name, backend = ?info.backend, kind = ?info.device_type, "GPU device open");
        Ok(GpuContext { device, queue, info })
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
}

/// The GPU renderer: device plus compiled kernels.
pub struct GpuRenderer {
    pub ctx: GpuContext,
    isosurface: IsosurfaceKernel,
}

/// A rendered frame and the time the GPU took for it (submit to done, readback excluded).
pub struct Rendered {
    pub frame: Frame,
    pub gpu_time: Duration,
}

impl GpuRenderer {
    pub fn new() -> Result<GpuRenderer, GpuError> {
        let ctx = GpuContext::new()?;
        let isosurface = IsosurfaceKernel::new(&ctx)?;
        Ok(GpuRenderer { ctx, isosurface })
    }

    pub fn adapter_name(&self) -> &str {
        &self.ctx.info.name
    }

    /// Uploads a volume and its block min/max for rendering.
    pub fn upload(&self, volume: &Volume) -> Result<GpuVolume, GpuError> {
        let blocks = BlockMinMax::new(volume, BlockMinMax::DEFAULT_BLOCK);
        GpuVolume::upload(&self.ctx, volume, &blocks)
    }

    /// Renders one frame of `view` and reads every AOV back.
    pub fn render(
        &self,
        volume: &GpuVolume,
        view: &View,
        settings: &RenderSettings,
    ) -> Result<Rendered, GpuError> {
        self.isosurface.render(&self.ctx, volume, view, settings)
    }
}
