//! `Kernel::Present` (shaders/present.wgsl): showing tiles in windows. A [`TileSurface`] is one
//! tile's window surface, created from the render thread's own instance (so the device that
//! renders the tiles also presents them), with two textures: the image staged for the next swap
//! and the image on show. Staging (upload) happens when a frame has rendered; presenting at the
//! swap is then only a draw of a full-window triangle and the present itself.
//!
//! One path for every surface: a render pass samples the image (nearest) into the surface, so any
//! surface format works (BGRA or RGBA, sRGB or not: see present.wgsl) and a window of another size
//! than the tile (a monitor that does not match the config) is filled by stretching.

use super::{GpuContext, GpuError};
use crate::shaders::{self, Kernel};

/// An image of a tile on the GPU, bound for drawing.
struct TileTexture {
    texture: wgpu::Texture,
    bind_group: wgpu::BindGroup,
    frame_id: u64,
}

/// What presenting did to one surface.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Presented {
    /// The frame asked for was staged and is now on show.
    Frame,
    /// The frame asked for was not staged: the image already on show (or black) was presented.
    Previous,
    /// Nothing was presented (the window is occluded or the surface timed out).
    Skipped,
}

/// One tile's window surface.
pub struct TileSurface {
    pub name: String,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    /// The view format of the tile textures: sRGB where the surface format is (see present.wgsl).
    view_format: wgpu::TextureFormat,
    staged: Option<TileTexture>,
    shown: Option<TileTexture>,
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
        let view_format = if format.is_srgb() {
            wgpu::TextureFormat::Rgba8UnormSrgb
        } else {
            wgpu::TextureFormat::Rgba8Unorm
        };
        let device = &ctx.device;
        let (pipeline, layout, sampler) = ctx.validated("present pipeline", || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(Kernel::Present.file_name()),
                source: wgpu::ShaderSource::Wgsl(shaders::source(Kernel::Present).into()),
            });
            let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("present"),
                entries: &[
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
                ],
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
                    compilation_options: Default::default(),
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
            view_format,
            staged: None,
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

    /// Uploads a frame's image of the tile (8-bit sRGB RGB, rows top to bottom) for the next
    /// [`TileSurface::present`] of `frame_id`.
    pub fn stage(
        &mut self,
        ctx: &GpuContext,
        frame_id: u64,
        width: u32,
        height: u32,
        rgb8: &[u8],
    ) -> Result<(), GpuError> {
        let n = width as usize * height as usize;
        if width == 0 || height == 0 || rgb8.len() != 3 * n {
            return Err(GpuError::View(format!(
                "tile {}: a {width}x{height} image needs {} bytes, not {}",
                self.name,
                3 * n,
                rgb8.len()
            )));
        }
        let reuse = self.staged.take().filter(|t| {
            let s = t.texture.size();
            (s.width, s.height) == (width, height)
        });
        let mut staged = match reuse {
            Some(t) => t,
            None => self.texture(ctx, width, height)?,
        };
        let mut rgba = vec![255u8; 4 * n];
        for (d, s) in rgba.chunks_exact_mut(4).zip(rgb8.chunks_exact(3)) {
            d[..3].copy_from_slice(s);
        }
        ctx.validated("stage tile", || {
            ctx.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &staged.texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                &rgba,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * width),
                    rows_per_image: Some(height),
                },
                wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
            )
        })?;
        staged.frame_id = frame_id;
        self.staged = Some(staged);
        Ok(())
    }

    /// A texture for the tile's image with its bind group.
    fn texture(&self, ctx: &GpuContext, width: u32, height: u32) -> Result<TileTexture, GpuError> {
        ctx.validated("tile texture", || {
            let texture = ctx.device.create_texture(&wgpu::TextureDescriptor {
                label: Some(&self.name),
                size: wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8Unorm,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[wgpu::TextureFormat::Rgba8UnormSrgb],
            });
            let view = texture.create_view(&wgpu::TextureViewDescriptor {
                format: Some(self.view_format),
                ..Default::default()
            });
            let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(&self.name),
                layout: &self.layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&view) },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: wgpu::BindingResource::Sampler(&self.sampler),
                    },
                ],
            });
            TileTexture { texture, bind_group, frame_id: 0 }
        })
    }

    /// The swap: puts the staged image of `frame_id` on show (if that is what is staged), then
    /// draws the image on show (black before the first) and presents it.
    pub fn present(&mut self, ctx: &GpuContext, frame_id: u64) -> Result<Presented, GpuError> {
        let fresh = self.staged.as_ref().is_some_and(|t| t.frame_id == frame_id);
        if fresh {
            std::mem::swap(&mut self.staged, &mut self.shown);
        }
        Ok(match self.draw(ctx)? {
            false => Presented::Skipped,
            true if fresh => Presented::Frame,
            true => Presented::Previous,
        })
    }

    /// Draws the image on show again (the window was exposed or resized).
    pub fn redraw(&mut self, ctx: &GpuContext) -> Result<bool, GpuError> {
        self.draw(ctx)
    }

    /// Acquires the surface's next texture, draws the image on show into it and presents it;
    /// `false` where the surface gave no texture (occluded, timed out).
    fn draw(&mut self, ctx: &GpuContext) -> Result<bool, GpuError> {
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
            if let Some(shown) = &self.shown {
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, &shown.bind_group, &[]);
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
