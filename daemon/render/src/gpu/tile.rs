//! A wall tile's GPU resources, made once (at start, on a resize, on a change of internal scale)
//! and reused every frame: the AOV and accumulation buffers of its (low-resolution) rectangle, the
//! parameters (written in place), [`IMAGES`] presentable images (the one on show, one waiting for
//! its swap, the one being rendered), depth, counters, and the bind groups that tie them to the kernels.
//!
//! A frame ([`GpuRenderer::render_tile`]) stays on the GPU: the isosurface kernel (only when the
//! accumulation restarts: the primary hits do not change while the frame state does not), the AO
//! kernel adding one frame into the running sums, and [`Kernel::Compose`](crate::shaders::Kernel)
//! writing the presentable image, depth and the frame's counters; with `settings.denoise` on,
//! [`Kernel::Denoise`](crate::shaders::Kernel) filters the occlusion and IBL terms between AO and
//! compose (its buffers made on the first denoised frame and kept), over the rectangle grown by
//! the tile's guard band ([`work_view`]; the counters count the tile's own pixels only). With
//! `temporal` on, a frame whose state differs from the last only by the camera keeps the history:
//! after the isosurface kernel, [`Kernel::Reproject`](crate::shaders::Kernel) carries each pixel's
//! sums over from the previous frame's pixel that saw the same point ([`crate::reproject`]; the
//! previous frame's hits and sums are copied into buffers made on the first such frame and kept),
//! and compose and the filter divide by each pixel's weight. Only what leaves the node is
//! read back, through a [`ReadbackRing`]: the counters (and kernel timestamps) every frame, colour
//! and depth where the tile's pixels travel (object space), the image when a snapshot is asked
//! for ([`GpuRenderer::read_tile_image`]).

use super::compose::ComposeParams;
use super::denoise::DenoiseBuffers;
use super::readback::{Read, ReadbackRing, Source};
use super::reproject::ReprojectParams;
use super::{Aovs, FrameParams, GpuEnvironment, GpuError, GpuRenderer, GpuVolume};
use crate::frame_plan::{Continuity, FramePlan, Start, Sums};
use crate::reproject::{Rule, Spending, RULE};
use isowall_model::composite::PixelForm;
use isowall_model::{lowres, IblMethod, RenderSettings, View};

/// A presentable image of a tile: 8-bit sRGB values in an RGBA8 texture the size of the tile's
/// window, drawn by presentation (`present.rs`) and copied for snapshots.
pub struct TileImage {
    pub texture: wgpu::Texture,
    /// The frame it holds, once rendered.
    pub frame_id: Option<u64>,
    storage: wgpu::TextureView,
}

/// The bind groups of a tile for one volume and environment.
struct Bound {
    volume: u64,
    env: u64,
    isosurface: wgpu::BindGroup,
    ao: wgpu::BindGroup,
}

/// A tile's filter resources ([`Kernel::Denoise`](crate::shaders::Kernel)), made on its first
/// denoised frame and kept: the passes' buffers and compose's bind groups reading their output.
struct TileDenoise {
    buffers: DenoiseBuffers,
    compose: [wgpu::BindGroup; IMAGES],
}

/// A tile's previous frame, kept for temporal reprojection ([`Kernel::Reproject`](crate::shaders::Kernel)):
/// copies of its hit flags, geometry and running sums, the kernel's parameters and bind group,
/// made on the tile's first reprojected frame and kept.
struct TileHistory {
    /// direct + hit, N + depth, summed bent + A, summed E (+ weight), of the previous frame.
    prev: [wgpu::Buffer; 4],
    /// The previous frame's summed sample positions.
    prev_pos: wgpu::Buffer,
    params: wgpu::Buffer,
    bind: wgpu::BindGroup,
}

/// The timestamp queries of a tile's frame (where the adapter has them): begin and end of the
/// isosurface, AO and compose passes.
struct Timestamps {
    set: wgpu::QuerySet,
    resolved: wgpu::Buffer,
}

const QUERIES: u32 = 6;

/// Presentable images per tile: the one on show, one rendered and waiting for its swap, and the
/// one being rendered.
pub const IMAGES: usize = 3;

impl TileImage {
    fn new(gpu: &GpuRenderer, name: &str, size: (u32, u32)) -> TileImage {
        let texture = gpu.ctx.create_texture(&wgpu::TextureDescriptor {
            label: Some(name),
            size: wgpu::Extent3d { width: size.0, height: size.1, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8Unorm,
            // COPY_DST: an object-space tile composited on the CPU is uploaded ([`ShownImages`]).
            usage: wgpu::TextureUsages::STORAGE_BINDING
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let storage = texture.create_view(&wgpu::TextureViewDescriptor::default());
        TileImage { texture, frame_id: None, storage }
    }
}

/// What a window shows of a tile (`present.rs`): its presentable images, and an identity under
/// which presentation binds them once.
pub trait Presentable {
    fn id(&self) -> u64;
    fn images(&self) -> &[TileImage; IMAGES];
}

impl Presentable for TileTarget {
    fn id(&self) -> u64 {
        self.id
    }

    fn images(&self) -> &[TileImage; IMAGES] {
        &self.images
    }
}

/// The presentable images of a tile whose frames come whole from the CPU (object space, the
/// colour form: the tile's owner composites its peers' pixels on the CPU), with nothing that
/// renders: each frame's image is uploaded ([`GpuRenderer::show_image`]) for its windows.
pub struct ShownImages {
    pub name: String,
    id: u64,
    size: (u32, u32),
    images: [TileImage; IMAGES],
    latest: usize,
    /// The upload's RGBA8 bytes, kept between frames.
    staging: Vec<u8>,
}

impl ShownImages {
    pub fn new(gpu: &GpuRenderer, name: &str, size: (u32, u32)) -> Result<ShownImages, GpuError> {
        let max = gpu.ctx.device.limits().max_texture_dimension_2d;
        if size.0 == 0 || size.1 == 0 || size.0.max(size.1) > max {
            return Err(GpuError::View(format!(
                "tile {name}: an image of {}x{} (each side 1 to {max})",
                size.0, size.1
            )));
        }
        let images =
            gpu.ctx.validated("tile images", || [0; IMAGES].map(|_| TileImage::new(gpu, name, size)))?;
        Ok(ShownImages {
            name: name.to_string(),
            id: super::resources::next_resource_id(),
            size,
            images,
            latest: 0,
            staging: Vec::new(),
        })
    }

    /// The images' size in pixels.
    pub fn size(&self) -> (u32, u32) {
        self.size
    }
}

impl Presentable for ShownImages {
    fn id(&self) -> u64 {
        self.id
    }

    fn images(&self) -> &[TileImage; IMAGES] {
        &self.images
    }
}

/// Of `images`, the one a new frame goes into: not the `latest`, and of the others the one
/// holding the oldest frame (or none).
fn oldest_other(images: &[TileImage; IMAGES], latest: usize) -> usize {
    (0..IMAGES)
        .filter(|&i| i != latest)
        .min_by_key(|&i| images[i].frame_id.map_or(0, |f| f + 1))
        .expect("more than one image")
}

/// Bytes of the counters buffer: fetches (low, high word), hits, pixels, hits at level 0.
pub const COUNTER_BYTES: u64 = 20;

/// A tile's resources.
pub struct TileTarget {
    pub name: String,
    /// Identifies these resources (presentation binds a target's images once).
    id: u64,
    size: (u32, u32),
    scale: u32,
    /// Low pixels rendered beyond the rectangle on each side (within the full image): the
    /// filter's guard band, so that a tile filters its edge pixels as the whole image does.
    guard: u32,
    low_size: (u32, u32),
    /// The low rectangle's AOVs.
    aovs: Aovs,
    params: wgpu::Buffer,
    compose_params: wgpu::Buffer,
    depth: wgpu::Buffer,
    counters: wgpu::Buffer,
    images: [TileImage; IMAGES],
    compose: [wgpu::BindGroup; IMAGES],
    denoise: Option<TileDenoise>,
    history: Option<TileHistory>,
    /// The reprojection's acceptance and ageing rule ([`RULE`] unless set).
    rule: Rule,
    bound: Option<Bound>,
    timestamps: Option<Timestamps>,
    /// What the running sums hold ([`FramePlan`]).
    sums: Sums,
    /// The last frame's parameters (a reprojection's previous camera); `None` where the next
    /// frame must start over (a new tile, or a composited canvas shown instead).
    previous: Option<FrameParams>,
    /// The last frame was denoised.
    filtered: bool,
    /// The image the last frame was rendered into.
    latest: usize,
    /// Host bytes a composited canvas is staged in per AOV ([`GpuRenderer::compose_canvas`]):
    /// made on the first canvas and kept.
    staging: Vec<u8>,
}

/// What a tile's frame reads back (the tag of its slot in the ring).
#[derive(Clone, Debug)]
pub struct FrameRead {
    pub frame_id: u64,
    pub tile: String,
    pub width: u32,
    pub height: u32,
    /// The passes the frame ran (isosurface, AO, compose) where they were timed.
    pub timed: Option<[bool; 3]>,
    /// The share read (object space): colour and depth, or depth and the shading AOVs.
    pub share: Option<PixelForm>,
    /// What the read is for.
    pub kind: ReadKind,
}

/// What a tile's read is for (where the render thread delivers it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReadKind {
    /// A rendered frame: its counters (timestamps), and its share in object space.
    Frame,
    /// Only the image of a frame already rendered (a snapshot).
    Snapshot,
    /// A composited canvas's counters, colour and depth ([`GpuRenderer::compose_canvas`]).
    Canvas,
}

/// The frame's counters over the tile's low rectangle.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameCounters {
    pub fetches: u64,
    pub hits: u64,
    pub pixels: u64,
    /// Hits drawn with level 0 where they lie (all of them for a volume held whole; bricked,
    /// the rest were drawn from a coarser level: DESIGN.md "Large volumes").
    pub level0_hits: u64,
}

/// A tile's read, decoded.
#[derive(Clone, Debug, Default)]
pub struct TileOutput {
    pub counters: FrameCounters,
    /// GPU milliseconds of the isosurface, AO and compose passes (timestamp queries), where the
    /// adapter has them and the pass ran.
    pub kernel_ms: [Option<f64>; 3],
    /// 8-bit sRGB RGB, rows top to bottom (shares and snapshots).
    pub rgb8: Option<Vec<u8>>,
    /// Distance along the ray per pixel, +inf without a hit (shares).
    pub depth: Option<Vec<f32>>,
    /// Shading shares: per pixel of the rectangle, the AOVs compose and the filter read (direct +
    /// hit, N + depth, summed bent + A, summed E + weight), rows top to bottom.
    pub shading: Option<Vec<[[f32; 4]; 4]>>,
}

/// The rectangle the kernels of a tile showing `view` at `scale` run over: the low-resolution
/// rectangle grown by `guard` pixels on each side, within the (low) full image
/// ([`isowall_model::Rect::grown`], the rule object space's tile canvases follow too).
pub fn work_view(view: &View, scale: u32, guard: u32) -> View {
    let mut low = lowres::scaled_view(view, scale.max(1));
    low.rect = low.rect.grown(guard, low.full);
    low
}

impl TileTarget {
    /// The resources of a tile showing `view`'s rectangle, rendered at internal scale `scale`.
    pub fn new(gpu: &GpuRenderer, name: &str, view: &View, scale: u32) -> Result<TileTarget, GpuError> {
        TileTarget::with_guard(gpu, name, view, scale, 0)
    }

    /// The resources of a tile whose kernels also render `guard` (low) pixels beyond its
    /// rectangle on each side ([`work_view`]): with `guard >= denoise::reach()` its denoised pixels
    /// are the whole image's.
    pub fn with_guard(
        gpu: &GpuRenderer,
        name: &str,
        view: &View,
        scale: u32,
        guard: u32,
    ) -> Result<TileTarget, GpuError> {
        let ctx = &gpu.ctx;
        let scale = scale.max(1);
        let low = work_view(view, scale, guard);
        let size = (view.rect.width, view.rect.height);
        let low_size = (low.rect.width, low.rect.height);
        if size.0 == 0 || size.1 == 0 {
            return Err(GpuError::View(format!("tile {name}: empty rectangle {}x{}", size.0, size.1)));
        }
        let limits = ctx.device.limits();
        if size.0.max(size.1) > limits.max_texture_dimension_2d {
            return Err(GpuError::TooLarge {
                name: format!("tile {name}'s image"),
                bytes: 4 * size.0 as u64 * size.1 as u64,
                limit: limits.max_texture_dimension_2d as u64,
            });
        }
        let n = low_size.0 as u64 * low_size.1 as u64;
        let limit = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        if n * 16 > limit {
            return Err(GpuError::TooLarge { name: format!("tile {name}'s AOVs"), bytes: n * 16, limit });
        }
        ctx.validated("tile resources", || {
            let storage =
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC;
            let aovs = Aovs::new(ctx, n, storage);
            let params_usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
            let params = ctx.buffer("frame params", std::mem::size_of::<FrameParams>() as u64, params_usage);
            let compose_params =
                ctx.buffer("compose params", std::mem::size_of::<ComposeParams>() as u64, params_usage);
            let depth = ctx.buffer("depth", size.0 as u64 * size.1 as u64 * 4, storage);
            let counters = ctx.buffer("counters", COUNTER_BYTES, storage);
            let images = [0; IMAGES].map(|_| TileImage::new(gpu, name, size));
            let compose = [0, 1, 2].map(|i| {
                gpu.compose.bind(
                    ctx,
                    &compose_params,
                    &aovs,
                    &aovs.ibl_sum,
                    &images[i].storage,
                    &depth,
                    &counters,
                )
            });
            let timestamps =
                ctx.device.features().contains(wgpu::Features::TIMESTAMP_QUERY).then(|| Timestamps {
                    set: ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
                        label: Some("tile passes"),
                        ty: wgpu::QueryType::Timestamp,
                        count: QUERIES,
                    }),
                    resolved: ctx.buffer(
                        "timestamps",
                        8 * QUERIES as u64,
                        wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                    ),
                });
            TileTarget {
                name: name.to_string(),
                id: super::resources::next_resource_id(),
                size,
                scale,
                guard,
                low_size,
                aovs,
                params,
                compose_params,
                depth,
                counters,
                images,
                compose,
                denoise: None,
                history: None,
                rule: RULE,
                bound: None,
                timestamps,
                sums: Sums::default(),
                filtered: false,
                previous: None,
                latest: 0,
                staging: Vec::new(),
            }
        })
    }

    /// Whether the resources fit `view`'s rectangle at `scale` (else make new ones), without a
    /// guard band.
    pub fn fits(&self, view: &View, scale: u32) -> bool {
        self.fits_with_guard(view, scale, 0)
    }

    /// Whether the resources fit `view`'s rectangle at `scale` with a `guard` band.
    pub fn fits_with_guard(&self, view: &View, scale: u32, guard: u32) -> bool {
        let low = work_view(view, scale.max(1), guard);
        self.size == (view.rect.width, view.rect.height)
            && self.scale == scale.max(1)
            && self.guard == guard
            && self.low_size == (low.rect.width, low.rect.height)
    }

    /// The guard band, low pixels each way.
    pub fn guard(&self) -> u32 {
        self.guard
    }

    /// The rectangle's size in pixels.
    pub fn size(&self) -> (u32, u32) {
        self.size
    }

    /// Frames in the running sums after the last frame.
    pub fn frames(&self) -> u32 {
        self.sums.frames
    }

    /// The rule the tile's reprojection follows from its next frame on (measurements compare
    /// rules; the renderer's is [`RULE`]).
    pub fn set_reproject_rule(&mut self, rule: Rule) {
        self.rule = rule;
    }

    /// Whether the running sums hold a reprojected history (since they were last cleared).
    pub fn reprojected(&self) -> bool {
        self.sums.per_pixel
    }

    /// The image holding `frame_id`, if it is still held.
    pub fn image(&self, frame_id: u64) -> Option<&TileImage> {
        self.images.iter().find(|i| i.frame_id == Some(frame_id))
    }

    /// The image a new frame is rendered into: the one holding the oldest frame (or none).
    fn back(&self) -> usize {
        oldest_other(&self.images, self.latest)
    }
}

impl FrameRead {
    /// Decodes a delivered read of this tag.
    pub fn decode(
        read: Read<FrameRead>,
        timestamp_period_ns: f32,
    ) -> Result<(FrameRead, TileOutput), GpuError> {
        let tag = read.tag;
        let mut parts = read.parts?.into_iter();
        let mut out = TileOutput::default();
        let mut next = |what: &str| {
            parts
                .next()
                .ok_or_else(|| GpuError::Readback(format!("tile {}: the read lacks its {what}", tag.tile)))
        };
        if tag.kind != ReadKind::Snapshot {
            let c: Vec<u32> = bytemuck::pod_collect_to_vec(next("counters")?.as_slice());
            out.counters = FrameCounters {
                fetches: c[0] as u64 | (c[1] as u64) << 32,
                hits: c[2] as u64,
                pixels: c[3] as u64,
                level0_hits: c[4] as u64,
            };
            if let Some(ran) = tag.timed {
                let t: Vec<u64> = bytemuck::pod_collect_to_vec(next("timestamps")?.as_slice());
                for k in 0..3 {
                    if ran[k] && t[2 * k + 1] >= t[2 * k] {
                        out.kernel_ms[k] =
                            Some((t[2 * k + 1] - t[2 * k]) as f64 * timestamp_period_ns as f64 * 1e-6);
                    }
                }
            }
        }
        if tag.kind == ReadKind::Snapshot || tag.share == Some(PixelForm::Colour) {
            let rgba = next("image")?;
            out.rgb8 = Some(rgba.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect());
        }
        if tag.share.is_some() {
            out.depth = Some(bytemuck::pod_collect_to_vec(next("depth")?.as_slice()));
        }
        if tag.share == Some(PixelForm::Shading) {
            let planes: Vec<Vec<[f32; 4]>> = ["direct", "geometry", "ao sums", "ibl sums"]
                .into_iter()
                .map(|what| next(what).map(|b| bytemuck::pod_collect_to_vec(b.as_slice())))
                .collect::<Result<_, _>>()?;
            out.shading = Some((0..planes[0].len()).map(|i| [0, 1, 2, 3].map(|k| planes[k][i])).collect());
        }
        Ok((tag, out))
    }
}

/// A tile's low rectangle read back ([`GpuRenderer::read_tile_sums`]): per pixel of the work
/// rectangle ([`work_view`]), rows top to bottom.
#[derive(Clone, Debug, Default)]
pub struct TileSums {
    /// Direct light (rgb) and hit flag (w, `shaders/hit.wgsl`: at least 0.5 on a hit).
    pub color: Vec<[f32; 4]>,
    /// N (outward) and depth (w).
    pub geometry: Vec<[f32; 4]>,
    /// Summed bent normal (xyz) and occlusion (w).
    pub ao: Vec<[f32; 4]>,
    /// Summed E (rgb) and the pixel's weight (w: frames' worth of samples).
    pub ibl: Vec<[f32; 4]>,
    /// Summed sample positions (xyz), weighted as `ibl`'s w; empty unless read
    /// ([`GpuRenderer::read_tile_sums_with_positions`]).
    pub pos: Vec<[f32; 4]>,
    /// Where the last frame was denoised, the filter's output in running-sum form over
    /// [`TileTarget::frames`]: E * frames (rgb), A * frames (w).
    pub denoised: Option<Vec<[f32; 4]>>,
}

/// One frame of a tile ([`GpuRenderer::render_tile`]).
pub struct TileFrame<'a> {
    pub frame_id: u64,
    pub volume: &'a GpuVolume,
    /// The tile's view at full resolution (the resources' rectangle).
    pub view: &'a View,
    /// `settings.ao.frame` is this frame's index in the sample sequence.
    pub settings: &'a RenderSettings,
    pub env: Option<&'a GpuEnvironment>,
    /// How the frame relates to the tile's last one (the model's rule, `FrameState::continuity`):
    /// the same image accumulates, a moved view may reproject, a change restarts.
    pub continuity: Continuity,
    /// Temporal reprojection: where the view moved (`continuity`), carry the running sums over ([`crate::reproject`]) instead of restarting. A tile
    /// whose sums hold a reprojected history draws its samples with index `settings.ao.frame +
    /// frame_id` (new samples every frame, the same on every node).
    pub temporal: bool,
    /// What of the frame leaves the node (object space shares): colour and depth, or depth and
    /// the shading AOVs the tile's owner filters and composes ([`GpuRenderer::compose_canvas`];
    /// only at scale 1 without a guard band, where the AOVs' rectangle is the tile's).
    pub share: Option<PixelForm>,
}

/// A composited canvas's frame ([`GpuRenderer::compose_canvas`]).
pub struct CanvasFrame<'a> {
    pub frame_id: u64,
    /// Any volume of the node's (the frame's parameters take its box; the canvas's pixels do
    /// not depend on it).
    pub volume: &'a GpuVolume,
    /// The tile's view (its own rectangle; the canvas is that grown by the tile's guard band).
    pub view: &'a View,
    pub settings: &'a RenderSettings,
    pub env: Option<&'a GpuEnvironment>,
}

impl GpuRenderer {
    /// Renders a frame of a tile into its next image, on the GPU, and records its read (counters;
    /// colour and depth for a share) into `ring`, which must have a free slot. Submits and
    /// returns without waiting.
    pub fn render_tile(
        &self,
        tile: &mut TileTarget,
        frame: &TileFrame,
        ring: &mut ReadbackRing<FrameRead>,
    ) -> Result<(), GpuError> {
        let ctx = &self.ctx;
        let scale = tile.scale;
        check_fits(tile, frame)?;
        let low = work_view(frame.view, scale, tile.guard);
        let env = self.check_frame(frame.volume, &low, frame.settings, frame.env, 1)?;
        let (isosurface, ao) = self.volume_kernels(frame.volume)?;
        let s = frame.settings;
        let with_ao = s.ao.samples > 0 || s.ao.ibl != IblMethod::None;
        let mut params = FrameParams::new(frame.volume, &low, s, env);
        params.perf[0] = self.perf.flags();
        let n = low.rect.width as u64 * low.rect.height as u64;
        if frame.temporal && tile.aovs.with_positions(ctx, n) {
            // Every bind group holding the placeholder is made again below.
            tile.bound = None;
            tile.history = None;
            // Sums taken without their positions start over.
            tile.previous = None;
        }
        params.positions = u32::from(tile.aovs.positions);
        // The tile's own knowledge: without a last frame, with other resources bound, or over other
        // pixels, the sums belong to something else.
        let resources_held =
            tile.bound.as_ref().is_some_and(|b| (b.volume, b.env) == (frame.volume.id, env.id));
        let same_pixels = tile.previous.is_some_and(|p| {
            (p.full_size, p.rect_origin, p.rect_size)
                == (params.full_size, params.rect_origin, params.rect_size)
        });
        let continuity = if same_pixels && resources_held { frame.continuity } else { Continuity::Changed };
        let plan = FramePlan::new(continuity, tile.sums, frame.temporal, with_ao);
        let (restart, reproject) = (plan.start == Start::Restart, plan.start == Start::Reproject);
        params.frame = plan.sample_index(s.ao.frame, frame.frame_id);
        // A reprojected frame of ours spends its samples by history where the rule says so: the
        // reprojection writes each pixel's number, the AO kernel takes it.
        let ours = s.ao.method == isowall_model::AoMethod::Ours;
        if reproject && ours && params.ao_samples > 0 && tile.rule.spending != Spending::Uniform {
            params.ao_pass[2] = tile.rule.spending.most(params.ao_samples);
        }
        let dispatches = super::ao::AoDispatches::split(&mut params, ctx.loop_budget());
        let prev = tile.previous.replace(params);
        if reproject {
            self.make_history(tile, &low)?;
        }
        if tile.bound.as_ref().is_none_or(|b| (b.volume, b.env) != (frame.volume.id, env.id)) {
            tile.bound = Some(Bound {
                volume: frame.volume.id,
                env: env.id,
                isosurface: isosurface.bind(ctx, &tile.params, frame.volume, &tile.aovs),
                ao: ao.bind(ctx, &tile.params, frame.volume, &env.texels, &tile.aovs),
            });
        }
        let denoised = with_ao && s.denoise.is_on() && super::denoise::applies(&params);
        if denoised {
            self.make_denoise(tile)?;
        }
        let bound = tile.bound.as_ref().expect("bound above");
        let Sums { frames, per_pixel } = plan.sums;
        let back = tile.back();
        let mut compose = ComposeParams::new(frame.view, &low, scale, s, frames);
        // The filter's output is in running-sum form over `frames` whatever the pixel's weight.
        compose.per_pixel = u32::from(per_pixel && !denoised);
        let low_size = (low.rect.width, low.rect.height);
        let timed = tile.timestamps.as_ref().map(|_| [restart || reproject, with_ao, true]);
        let share = frame.share;
        let slot = ctx.validated("tile frame", || -> Result<(usize, wgpu::CommandBuffer), GpuError> {
            ctx.write_buffer(&tile.params, 0, bytemuck::bytes_of(&params));
            ctx.write_buffer(&tile.compose_params, 0, bytemuck::bytes_of(&compose));
            let mut enc =
                ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("tile") });
            let ts = |k: u32| {
                tile.timestamps.as_ref().map(|t| wgpu::ComputePassTimestampWrites {
                    query_set: &t.set,
                    beginning_of_pass_write_index: Some(2 * k),
                    end_of_pass_write_index: Some(2 * k + 1),
                })
            };
            if let (true, Some(h), Some(prev)) = (reproject, &tile.history, &prev) {
                // The previous frame's hits and sums, before this frame's isosurface kernel
                // overwrites them; then the sums carried over onto this frame's hits.
                for (src, dst) in tile.aovs.shading().into_iter().zip(&h.prev) {
                    enc.copy_buffer_to_buffer(src, 0, dst, 0, None);
                }
                enc.copy_buffer_to_buffer(&tile.aovs.pos_sum, 0, &h.prev_pos, 0, None);
                let rp = ReprojectParams::new(&params, prev, &tile.rule);
                ctx.write_buffer(&h.params, 0, bytemuck::bytes_of(&rp));
                isosurface.pass(&mut enc, &bound.isosurface, low_size, ts(0));
                self.reproject.pass(&mut enc, &h.bind, low_size);
            } else if restart {
                for sum in tile.aovs.sums() {
                    enc.clear_buffer(sum, 0, None);
                }
                isosurface.pass(&mut enc, &bound.isosurface, low_size, ts(0));
            } else {
                // The fetches of this frame only (the isosurface kernel's were counted when it ran).
                enc.clear_buffer(&tile.aovs.fetches, 0, None);
            }
            if with_ao {
                ao.pass(&mut enc, &bound.ao, low_size, dispatches, ts(1));
            }
            if let (true, Some(d)) = (denoised, &tile.denoise) {
                self.denoise.encode(ctx, &mut enc, &d.buffers, &params, frames, per_pixel);
            }
            let tag = FrameRead {
                frame_id: frame.frame_id,
                tile: tile.name.clone(),
                width: tile.size.0,
                height: tile.size.1,
                timed,
                share,
                kind: ReadKind::Frame,
            };
            let slot = self.compose_and_read(tile, &mut enc, back, denoised, ts(2), tag, ring)?;
            Ok((slot, enc.finish()))
        })??;
        let (slot, commands) = slot;
        let submission = ctx.queue.submit([commands]);
        ring.submitted(slot, submission);
        tile.sums = plan.sums;
        tile.filtered = denoised;
        tile.latest = back;
        tile.images[back].frame_id = Some(frame.frame_id);
        Ok(())
    }

    /// The reprojection's resources of `tile` (the previous frame's shading AOVs), made on its
    /// first reprojected frame and kept.
    fn make_history(&self, tile: &mut TileTarget, low: &View) -> Result<(), GpuError> {
        if tile.history.is_some() {
            return Ok(());
        }
        let ctx = &self.ctx;
        let n = low.rect.width as u64 * low.rect.height as u64;
        let made = ctx.validated("tile history resources", || {
            let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
            let prev = [
                ctx.buffer("previous direct", n * 16, storage),
                ctx.buffer("previous geometry", n * 16, storage),
                ctx.buffer("previous acc ao", n * 16, storage),
                ctx.buffer("previous acc ibl", n * 16, storage),
            ];
            let prev_pos = ctx.buffer("previous acc pos", n * 16, storage);
            let params =
                ctx.buffer("reproject params", std::mem::size_of::<ReprojectParams>() as u64, storage);
            let prev_planes = [&prev[0], &prev[1], &prev[2], &prev[3]];
            let bind = self.reproject.bind(ctx, &params, &tile.aovs, prev_planes, &prev_pos);
            TileHistory { prev, prev_pos, params, bind }
        })?;
        tile.history = Some(made);
        Ok(())
    }

    /// The filter's resources of `tile`, made on its first denoised frame and kept.
    fn make_denoise(&self, tile: &mut TileTarget) -> Result<(), GpuError> {
        if tile.denoise.is_some() {
            return Ok(());
        }
        let ctx = &self.ctx;
        let n = tile.low_size.0 as u64 * tile.low_size.1 as u64;
        let made = ctx.validated("tile denoise resources", || {
            let buffers = self.denoise.buffers(ctx, n, &tile.aovs);
            let compose = [0, 1, 2].map(|i| {
                self.compose.bind(
                    ctx,
                    &tile.compose_params,
                    &tile.aovs,
                    &buffers.out,
                    &tile.images[i].storage,
                    &tile.depth,
                    &tile.counters,
                )
            });
            TileDenoise { buffers, compose }
        })?;
        tile.denoise = Some(made);
        Ok(())
    }

    /// Records compose into image `back` (reading the filter's output where `filtered`) and the
    /// frame's read into `ring` as `tag` says (counters, timestamps where `tag.timed`, the share);
    /// returns the ring's slot.
    #[expect(clippy::too_many_arguments, reason = "the frame's choices for one encoder, each used once")]
    fn compose_and_read(
        &self,
        tile: &TileTarget,
        enc: &mut wgpu::CommandEncoder,
        back: usize,
        filtered: bool,
        timestamp: Option<wgpu::ComputePassTimestampWrites>,
        tag: FrameRead,
        ring: &mut ReadbackRing<FrameRead>,
    ) -> Result<usize, GpuError> {
        let compose_group = match (filtered, &tile.denoise) {
            (true, Some(d)) => &d.compose[back],
            _ => &tile.compose[back],
        };
        enc.clear_buffer(&tile.counters, 0, None);
        self.compose.pass(enc, compose_group, tile.size, timestamp);
        let mut sources = vec![Source::Buffer(&tile.counters, COUNTER_BYTES)];
        if let (Some(t), Some(_)) = (&tile.timestamps, tag.timed) {
            enc.resolve_query_set(&t.set, 0..QUERIES, &t.resolved, 0);
            sources.push(Source::Buffer(&t.resolved, 8 * QUERIES as u64));
        }
        let depth = Source::Buffer(&tile.depth, tile.size.0 as u64 * tile.size.1 as u64 * 4);
        let aov_bytes = tile.low_size.0 as u64 * tile.low_size.1 as u64 * 16;
        match tag.share {
            Some(PixelForm::Colour) => sources.extend([Source::Texture(&tile.images[back].texture), depth]),
            Some(PixelForm::Shading) => {
                sources.push(depth);
                sources.extend(tile.aovs.shading().map(|b| Source::Buffer(b, aov_bytes)));
            }
            None => {}
        }
        ring.record(&self.ctx, enc, tag, &sources)
    }

    /// Filters and composes a composited canvas into `tile`'s next image (object space, on the
    /// tile's owner): `shading` holds, per pixel of the tile's rectangle grown by its guard band
    /// ([`work_view`] at scale 1), the AOVs of the nearest brick's hit as their shading shares
    /// carried them (running sums: each pixel is divided by its own weight, the IBL sum's w).
    /// With `settings.denoise` on the filter runs over the whole canvas, so with a guard band of
    /// [`crate::denoise::reach`] the tile's pixels are the single render's. Records the read of
    /// its colour and depth into `ring` (which must have a free slot) and submits; the tile's
    /// accumulation restarts at its next [`GpuRenderer::render_tile`].
    pub fn compose_canvas(
        &self,
        tile: &mut TileTarget,
        frame: &CanvasFrame,
        shading: &[[[f32; 4]; 4]],
        ring: &mut ReadbackRing<FrameRead>,
    ) -> Result<(), GpuError> {
        let ctx = &self.ctx;
        if tile.scale != 1 || !tile.fits_with_guard(frame.view, 1, tile.guard) {
            return Err(GpuError::View(format!(
                "tile {}: its resources are {}x{} at scale {}, the canvas's view is {}x{} at scale 1",
                tile.name,
                tile.size.0,
                tile.size.1,
                tile.scale,
                frame.view.rect.width,
                frame.view.rect.height
            )));
        }
        let low = work_view(frame.view, 1, tile.guard);
        let n = low.rect.width as usize * low.rect.height as usize;
        if shading.len() != n {
            return Err(GpuError::View(format!(
                "tile {}: the canvas has {} pixels, its rectangle grown by the guard band {}x{}",
                tile.name,
                shading.len(),
                low.rect.width,
                low.rect.height
            )));
        }
        let s = frame.settings;
        let env = self.check_frame(frame.volume, &low, s, frame.env, 1)?;
        let with_ao = s.ao.samples > 0 || s.ao.ibl != IblMethod::None;
        let params = FrameParams::new(frame.volume, &low, s, env);
        let denoised = with_ao && s.denoise.is_on() && super::denoise::applies(&params);
        if denoised {
            self.make_denoise(tile)?;
        }
        // The canvas is not this tile's own accumulation: its next frame restarts.
        tile.previous = None;
        tile.sums = Sums::default();
        // Each pixel's sums are divided by its own weight (the filter's output is in running-sum
        // form over one frame).
        let frames = u32::from(with_ao);
        let back = tile.back();
        let mut compose = ComposeParams::new(frame.view, &low, 1, s, frames);
        compose.per_pixel = u32::from(!denoised);
        let slot =
            ctx.validated("canvas frame", || -> Result<(usize, wgpu::CommandBuffer), GpuError> {
                tile.staging.resize(n * 16, 0);
                for (k, plane) in tile.aovs.shading().into_iter().enumerate() {
                    for (dst, px) in tile.staging.chunks_exact_mut(16).zip(shading) {
                        dst.copy_from_slice(bytemuck::bytes_of(&px[k]));
                    }
                    ctx.write_buffer(plane, 0, &tile.staging);
                }
                ctx.write_buffer(&tile.compose_params, 0, bytemuck::bytes_of(&compose));
                let mut enc = ctx
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("canvas") });
                // The fetches were counted where the bricks were rendered.
                enc.clear_buffer(&tile.aovs.fetches, 0, None);
                if let (true, Some(d)) = (denoised, &tile.denoise) {
                    self.denoise.encode(ctx, &mut enc, &d.buffers, &params, frames, true);
                }
                let tag = FrameRead {
                    frame_id: frame.frame_id,
                    tile: tile.name.clone(),
                    width: tile.size.0,
                    height: tile.size.1,
                    timed: None,
                    share: Some(PixelForm::Colour),
                    kind: ReadKind::Canvas,
                };
                let slot = self.compose_and_read(tile, &mut enc, back, denoised, None, tag, ring)?;
                Ok((slot, enc.finish()))
            })??;
        let (slot, commands) = slot;
        let submission = ctx.queue.submit([commands]);
        ring.submitted(slot, submission);
        tile.filtered = denoised;
        tile.latest = back;
        tile.images[back].frame_id = Some(frame.frame_id);
        Ok(())
    }

    /// Writes `rgba` (8-bit RGBA, `size` pixels, rows top to bottom) over the top-left corner of
    /// the tile's latest image (the frame just rendered), cut to the image: the operator's
    /// identify label. The write reaches the image before anything submitted after it (a
    /// presentation, a snapshot's read).
    pub fn stamp(&self, tile: &TileTarget, rgba: &[u8], size: (u32, u32)) -> Result<(), GpuError> {
        let (w, h) = (size.0.min(tile.size.0), size.1.min(tile.size.1));
        if w == 0 || h == 0 || rgba.len() as u64 != 4 * u64::from(size.0) * u64::from(size.1) {
            return Ok(());
        }
        let ctx = &self.ctx;
        ctx.validated("tile label", || {
            ctx.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &tile.images[tile.latest].texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                rgba,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * size.0),
                    rows_per_image: Some(size.1),
                },
                wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
            )
        })
    }

    /// Uploads frame `frame_id`'s image of a tile composited on the CPU (`rgb8`: 8-bit sRGB,
    /// rows top to bottom, the images' size) into `shown`'s next image, for its windows.
    pub fn show_image(&self, shown: &mut ShownImages, frame_id: u64, rgb8: &[u8]) -> Result<(), GpuError> {
        let (w, h) = shown.size;
        let n = w as usize * h as usize;
        if rgb8.len() != 3 * n {
            return Err(GpuError::View(format!(
                "tile {}: an image of {} bytes for {w}x{h} pixels (3 a pixel)",
                shown.name,
                rgb8.len()
            )));
        }
        shown.staging.clear();
        shown.staging.extend(rgb8.chunks_exact(3).flat_map(|p| [p[0], p[1], p[2], 255]));
        let back = oldest_other(&shown.images, shown.latest);
        let ctx = &self.ctx;
        ctx.validated("tile image upload", || {
            ctx.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &shown.images[back].texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                &shown.staging,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * w),
                    rows_per_image: Some(h),
                },
                wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
            )
        })?;
        shown.images[back].frame_id = Some(frame_id);
        shown.latest = back;
        Ok(())
    }

    /// Reads back the tile's low rectangle as its last frame left it (hit flags, geometry, running
    /// sums), waiting for the GPU: for tests and benchmarks, not the frame path (it allocates).
    pub fn read_tile_sums(&self, tile: &TileTarget) -> Result<TileSums, GpuError> {
        self.read_sums(tile, false)
    }

    /// [`GpuRenderer::read_tile_sums`] with the summed sample positions too (the drift test's).
    pub fn read_tile_sums_with_positions(&self, tile: &TileTarget) -> Result<TileSums, GpuError> {
        self.read_sums(tile, true)
    }

    fn read_sums(&self, tile: &TileTarget, positions: bool) -> Result<TileSums, GpuError> {
        let ctx = &self.ctx;
        let mut picked = tile.aovs.shading().to_vec();
        if positions && !tile.aovs.positions {
            return Err(GpuError::View(format!(
                "tile {}: no sample positions are summed where frames are not temporal",
                tile.name
            )));
        }
        if positions {
            picked.push(&tile.aovs.pos_sum);
        }
        if let (true, Some(d)) = (tile.filtered, &tile.denoise) {
            picked.push(&d.buffers.out);
        }
        let staging = ctx.validated("tile sums readback", || {
            picked
                .iter()
                .map(|b| {
                    ctx.buffer(
                        "tile sums",
                        b.size(),
                        wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    )
                })
                .collect::<Vec<_>>()
        })?;
        let mut enc =
            ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("tile sums") });
        for (src, dst) in picked.iter().zip(&staging) {
            enc.copy_buffer_to_buffer(src, 0, dst, 0, None);
        }
        ctx.queue.submit([enc.finish()]);
        let (bytes, _) = super::read_buffers(ctx, &staging)?;
        let v = |k: usize| bytemuck::pod_collect_to_vec::<u8, [f32; 4]>(&bytes[k]);
        let planes = if positions { 5 } else { 4 };
        let denoised = (bytes.len() > planes).then(|| v(planes));
        let pos = if positions { v(4) } else { Vec::new() };
        Ok(TileSums { color: v(0), geometry: v(1), ao: v(2), ibl: v(3), pos, denoised })
    }

    /// Records a read of the image holding `frame_id` (a snapshot) into `ring` and submits it;
    /// an error where the tile no longer holds that frame.
    pub fn read_tile_image(
        &self,
        tile: &TileTarget,
        frame_id: u64,
        ring: &mut ReadbackRing<FrameRead>,
    ) -> Result<(), GpuError> {
        let ctx = &self.ctx;
        let image = tile.image(frame_id).ok_or_else(|| {
            GpuError::Readback(format!("tile {}: frame {frame_id} is no longer held", tile.name))
        })?;
        let mut enc =
            ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("snapshot") });
        let tag = FrameRead {
            frame_id,
            tile: tile.name.clone(),
            width: tile.size.0,
            height: tile.size.1,
            timed: None,
            share: None,
            kind: ReadKind::Snapshot,
        };
        let slot = ring.record(ctx, &mut enc, tag, &[Source::Texture(&image.texture)])?;
        let submission = ctx.queue.submit([enc.finish()]);
        ring.submitted(slot, submission);
        Ok(())
    }
}
/// `frame` fits `tile`'s resources: its view's rectangle at the tile's scale and guard band, and
/// a shading share only at scale 1 without a guard band.
fn check_fits(tile: &TileTarget, frame: &TileFrame) -> Result<(), GpuError> {
    let scale = tile.scale;
    if !tile.fits_with_guard(frame.view, scale, tile.guard) {
        return Err(GpuError::View(format!(
            "tile {}: its resources are {}x{} at scale {scale}, the view's rectangle is {}x{}",
            tile.name, tile.size.0, tile.size.1, frame.view.rect.width, frame.view.rect.height
        )));
    }
    if frame.share == Some(PixelForm::Shading) && (scale != 1 || tile.guard != 0) {
        return Err(GpuError::View(format!(
            "tile {}: a shading share needs scale 1 and no guard band (scale {scale}, guard {})",
            tile.name, tile.guard
        )));
    }
    Ok(())
}
