//! `Kernel::Present` (shaders/present.wgsl): showing tiles in windows. A [`TileSurface`] is one
//! tile's window surface, created from the render thread's own instance (so the device that
//! renders the tiles also presents them). It draws from the tile's own presentable images (a
//! [`Presentable`]: a [`TileTarget`](super::tile::TileTarget) holds a few: the one on show, the
//! next, the one being rendered), which the compose kernel wrote on the GPU: nothing is copied or
//! uploaded. (In object space a tile composited on the CPU has its images uploaded:
//! [`ShownImages`](super::tile::ShownImages).) Presenting at the swap is a draw of a full-window
//! triangle from the image holding the frame, and the present itself.
//!
//! One path for every surface: a render pass samples the image (nearest) into the surface, so any
//! surface format works (BGRA or RGBA, sRGB or not: see present.wgsl) and a window of another size
//! than the tile (a monitor that does not match the config) is filled by stretching.

use super::tile::Presentable;
use super::{GpuContext, GpuError};
use crate::shaders::{self, Kernel};

/// The bind groups of a tile target's two images, made once per target.
struct Bound {
    target: u64,
    groups: [wgpu::BindGroup; super::tile::IMAGES],
}

/// What presenting did to one surface.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Presented {
    /// The frame asked for was rendered and is now on show.
    Frame,
    /// The tile holds no image of the frame asked for: the image already on show (or black) was
    /// presented.
    Previous,
    /// Nothing was presented (the window is occluded or the surface timed out).
    Skipped,
}

/// The bind group layout of `present.wgsl`: the tile's image and its sampler, for the fragment
/// stage.
pub(crate) fn entries() -> Vec<wgpu::BindGroupLayoutEntry> {
    vec![
        wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: true },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
            count: None,
        },
        wgpu::BindGroupLayoutEntry {
            binding: 1,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
            count: None,
        },
    ]
}

/// One tile's window surface.
pub struct TileSurface {
    pub name: String,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    bound: Option<Bound>,
    /// The image on show (of `bound`'s target) and its frame.
    shown: Option<(usize, u64)>,
}

impl TileSurface {
    /// Creates the surface of a window (`target`, e.g. an `Arc` of a winit window) and configures
    /// it at the window's size in pixels.
    pub fn new(
        ctx: &GpuContext,
        name: &str,
        target: impl Into<wgpu::SurfaceTarget<'static>>,
        size: (u32, u32),
    ) -> Result<TileSurface, GpuError> {
        let surface = ctx
            .instance
            .create_surface(target)
            .map_err(|e| GpuError::Surface(format!("tile {name}: cannot create a surface: {e}")))?;
        let caps = surface.get_capabilities(&ctx.adapter);
        if caps.formats.is_empty() {
            return Err(GpuError::Surface(format!(
                "tile {name}: the adapter '{}' cannot present to this window",
                ctx.info.name
            )));
        }
        // 8-bit formats first, non-sRGB before sRGB (the image is sRGB-encoded already).
        let preference = [
            wgpu::TextureFormat::Bgra8Unorm,
            wgpu::TextureFormat::Rgba8Unorm,
            wgpu::TextureFormat::Bgra8UnormSrgb,
            wgpu::TextureFormat::Rgba8UnormSrgb,
        ];
        let format = preference.into_iter().find(|f| caps.formats.contains(f)).unwrap_or(caps.formats[0]);
        let alpha_mode = if caps.alpha_modes.contains(&wgpu::CompositeAlphaMode::Opaque) {
            wgpu::CompositeAlphaMode::Opaque
        } else {
            caps.alpha_modes.first().copied().unwrap_or(wgpu::CompositeAlphaMode::Auto)
        };
        let config = wgpu::SurfaceConfiguration {
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            format,
            color_space: wgpu::SurfaceColorSpace::Auto,
            width: size.0.max(1),
            height: size.1.max(1),
            // Vsync: the swap shows at the next refresh (the only mode every surface has).
            present_mode: wgpu::PresentMode::Fifo,
            desired_maximum_frame_latency: 2,
            alpha_mode,
            view_formats: Vec::new(),
        };
        // The images hold sRGB values: an sRGB surface encodes again, so the shader decodes.
        let decode: &[(&str, f64)] = &[("SRGB_SURFACE", if format.is_srgb() { 1.0 } else { 0.0 })];
        let device = &ctx.device;
        let (pipeline, layout, sampler) = ctx.validated("present pipeline", || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(Kernel::Present.file_name()),
                source: wgpu::ShaderSource::Wgsl(shaders::source(Kernel::Present).into()),
            });
            let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("present"),
                entries: &entries(),
            });
            let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("present"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
            let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("present"),
                layout: Some(&pipeline_layout),
                vertex: wgpu::VertexState {
                    module: &module,
                    entry_point: Some("vs_main"),
                    compilation_options: Default::default(),
                    buffers: &[],
                },
                primitive: wgpu::PrimitiveState::default(),
                depth_stencil: None,
                multisample: wgpu::MultisampleState::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &module,
                    entry_point: Some("fs_main"),
                    compilation_options: wgpu::PipelineCompilationOptions {
                        constants: decode,
                        ..Default::default()
                    },
                    targets: &[Some(wgpu::ColorTargetState {
                        format,
                        blend: None,
                        write_mask: wgpu::ColorWrites::ALL,
                    })],
                }),
                multiview_mask: None,
                cache: None,
            });
            let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
                label: Some("present"),
                mag_filter: wgpu::FilterMode::Nearest,
                min_filter: wgpu::FilterMode::Nearest,
                ..Default::default()
            });
            (pipeline, layout, sampler)
        })?;
        let tile = TileSurface {
            name: name.to_string(),
            surface,
            config,
            pipeline,
            layout,
            sampler,
            bound: None,
            shown: None,
        };
        tile.configure(ctx)?;
        tracing::info!(
            tile = name,
            width = tile.config.width,
            height = tile.config.height,
            format = ?format,
            present_mode = ?tile.config.present_mode,
            "window surface ready"
        );
        Ok(tile)
    }

    /// The surface's pixel format.
    pub fn format(&self) -> wgpu::TextureFormat {
        self.config.format
    }

    /// The surface's size in pixels.
    pub fn size(&self) -> (u32, u32) {
        (self.config.width, self.config.height)
    }

    fn configure(&self, ctx: &GpuContext) -> Result<(), GpuError> {
        ctx.validated("configure surface", || self.surface.configure(&ctx.device, &self.config))
    }

    /// Follows the window to a new size in pixels (a zero size, a minimised window, is ignored).
    pub fn resize(&mut self, ctx: &GpuContext, width: u32, height: u32) -> Result<(), GpuError> {
        if width == 0 || height == 0 || (width, height) == self.size() {
            return Ok(());
        }
        self.config.width = width;
        self.config.height = height;
        tracing::debug!(tile = %self.name, width, height, "surface resized");
        self.configure(ctx)
    }

    /// Bind groups for `target`'s images, made when the target is new to this surface.
    fn bind(&mut self, ctx: &GpuContext, target: &dyn Presentable) -> Result<(), GpuError> {
        if self.bound.as_ref().is_some_and(|b| b.target == target.id()) {
            return Ok(());
        }
        self.shown = None;
        let groups = ctx.validated("tile bind groups", || {
            target.images().each_ref().map(|image| {
                let view = image.texture.create_view(&wgpu::TextureViewDescriptor::default());
                ctx.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some(&self.name),
                    layout: &self.layout,
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: wgpu::BindingResource::TextureView(&view),
                        },
                        wgpu::BindGroupEntry {
                            binding: 1,
                            resource: wgpu::BindingResource::Sampler(&self.sampler),
                        },
                    ],
                })
            })
        })?;
        self.bound = Some(Bound { target: target.id(), groups });
        Ok(())
    }

    /// The swap: puts `target`'s image of `frame_id` on show (where it holds that frame), then
    /// draws the image on show (black before the first) and presents it.
    pub fn present(
        &mut self,
        ctx: &GpuContext,
        target: Option<&dyn Presentable>,
        frame_id: u64,
    ) -> Result<Presented, GpuError> {
        let mut fresh = false;
        if let Some(t) = target {
            self.bind(ctx, t)?;
            if let Some(i) = t.images().iter().position(|im| im.frame_id == Some(frame_id)) {
                self.shown = Some((i, frame_id));
                fresh = true;
            }
        }
        Ok(match self.draw(ctx, target)? {
            false => Presented::Skipped,
            true if fresh => Presented::Frame,
            true => Presented::Previous,
        })
    }

    /// Draws the image on show again (the window was exposed or resized).
    pub fn redraw(&mut self, ctx: &GpuContext, target: Option<&dyn Presentable>) -> Result<bool, GpuError> {
        self.draw(ctx, target)
    }

    /// Acquires the surface's next texture, draws the image on show into it and presents it;
    /// `false` where the surface gave no texture (occluded, timed out).
    fn draw(&mut self, ctx: &GpuContext, target: Option<&dyn Presentable>) -> Result<bool, GpuError> {
        // The image on show, if the target still holds its frame (else black).
        let shown = match (&self.bound, self.shown, target) {
            (Some(b), Some((i, id)), Some(t)) if b.target == t.id() && t.images()[i].frame_id == Some(id) => {
                Some(&b.groups[i])
            }
            _ => None,
        };
        let mut retried = false;
        let (frame, suboptimal) = loop {
            match self.surface.get_current_texture() {
                wgpu::CurrentSurfaceTexture::Success(t) => break (t, false),
                // Present this one; configure again before the next.
                wgpu::CurrentSurfaceTexture::Suboptimal(t) => break (t, true),
                wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {
                    return Ok(false)
                }
                wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost if !retried => {
                    retried = true;
                    self.configure(ctx)?;
                }
                other => {
                    return Err(GpuError::Surface(format!(
                        "tile {}: cannot acquire the window's next image: {other:?}",
                        self.name
                    )))
                }
            }
        };
        let view = frame.texture.create_view(&wgpu::TextureViewDescriptor::default());
        let mut enc =
            ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("present") });
        ctx.validated("present", || {
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("present"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            if let Some(group) = shown {
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, group, &[]);
                pass.draw(0..3, 0..1);
            }
        })?;
        ctx.queue.submit([enc.finish()]);
        ctx.queue.present(frame);
        if suboptimal {
            self.configure(ctx)?;
        }
        Ok(true)
    }
}
