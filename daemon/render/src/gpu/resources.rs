//! The resources a frame binds besides its own buffers, in one place: a volume on the GPU (its
//! packed voxels, block levels and the texture march's copy, made by one builder for a whole
//! volume and for object space's bricks) and an environment.

use super::{GpuContext, GpuError};
use crate::environment::Environment;
use isowall_volume::{BlockMinMax, Volume, VoxelFormat};
use std::sync::atomic::{AtomicU64, Ordering};

/// The block levels a volume is uploaded with.
struct Levels<'a> {
    primary: &'a BlockMinMax,
    ao: Option<BlockLevel>,
    coarse: Option<BlockLevel>,
}

/// Where a volume sits in the world, and its name.
struct Geometry<'a> {
    spacing: glam::DVec3,
    box_min: glam::DVec3,
    box_max: glam::DVec3,
    name: &'a str,
}

/// A number no other volume or environment upload of this process has.
pub(crate) fn next_resource_id() -> u64 {
    static NEXT: AtomicU64 = AtomicU64::new(1);
    NEXT.fetch_add(1, Ordering::Relaxed)
}

/// The buffer of a volume's brick marks, `words` 32-bit words (zeroed).
pub(crate) fn brick_marks(ctx: &GpuContext, words: usize) -> Result<wgpu::Buffer, GpuError> {
    ctx.validated("upload", || {
        ctx.buffer(
            "brick marks",
            4 * words.max(1) as u64,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC,
        )
    })
}

/// A volume on the GPU: voxels (packed as `format`) and per-block min/max (the fine level, then the
/// coarse one).
pub struct GpuVolume {
    /// Identifies this upload (a tile's bind groups are made once per volume they bind).
    pub id: u64,
    pub(crate) voxels: wgpu::Buffer,
    pub(crate) block_minmax: wgpu::Buffer,
    /// One bit per level-0 brick the kernels set where a ray read it (a bricked volume's; one
    /// unused word for a volume held whole): shaders/frame.wgsl, `brick_marks`.
    pub(crate) brick_marks: wgpu::Buffer,
    /// Whether the kernels set `brick_marks` (a bricked volume's ray-guided rounds; the check
    /// costs a lookup one comparison where off, the marks themselves about a fifth of a bricked
    /// frame on lavapipe).
    pub marking: bool,
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
    /// The buffer is a [`BrickPool`](super::brick_pool::BrickPool)'s: page tables and bricks of a
    /// pyramid, read by the kernels compiled `BRICKED`.
    pub bricked: bool,
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
    pub(crate) fn new(
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
        let texels = texture.then(|| (v.data(), v.dims()));
        let geometry =
            Geometry { spacing: v.spacing(), box_min: v.box_min(), box_max: v.box_max(), name: &v.name };
        let levels = Levels { primary: blocks, ao: ao_level, coarse: coarse_level };
        GpuVolume::build(
            ctx,
            &format!("volume {}", v.name),
            (&words, v.dims()),
            minmax,
            texels,
            format,
            value_range,
            levels,
            geometry,
            None,
        )
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
        let minmax = stored_minmax(format, blocks, value_range);
        // The texture holds the voxels as stored (r16f rounds them).
        let stored = (format != VoxelFormat::R32F).then(|| region.stored_as(format));
        let texels = texture.then(|| (stored.as_ref().unwrap_or(region).data(), d));
        let geometry = Geometry {
            spacing: whole.spacing,
            box_min: whole.box_min(),
            box_max: whole.box_max(),
            name: &whole.name,
        };
        // A brick's AO rays use the primary block level (the whole volume's grid): the extra
        // levels are built from a whole volume's voxels, which a brick node does not hold.
        let levels = Levels { primary: blocks, ao: None, coarse: None };
        let label = format!("brick of {}", whole.name);
        GpuVolume::build(
            ctx,
            &label,
            (&words, d),
            minmax,
            texels,
            format,
            value_range,
            levels,
            geometry,
            Some(object),
        )
    }

    /// The one builder of a volume's resources: the packed voxels of `dims` samples, every block
    /// level's min/max,
    /// the texture march's texture (`texels`, or one texel), and what the kernels' parameters
    /// read of them.
    #[allow(clippy::too_many_arguments)]
    fn build(
        ctx: &GpuContext,
        label: &str,
        (words, dims): (&[u32], [usize; 3]),
        minmax: Vec<[f32; 2]>,
        texels: Option<(&[f32], [usize; 3])>,
        format: VoxelFormat,
        value_range: (f32, f32),
        levels: Levels,
        geometry: Geometry,
        object: Option<ObjectSpace>,
    ) -> Result<GpuVolume, GpuError> {
        let voxels = ctx.storage_init(label, bytemuck::cast_slice(words))?;
        let block_minmax = ctx.storage_init("block min/max", bytemuck::cast_slice(&minmax))?;
        let march = MarchTexture::new(ctx, geometry.name, texels)?;
        Ok(GpuVolume {
            id: next_resource_id(),
            voxels,
            block_minmax,
            brick_marks: brick_marks(ctx, 1)?,
            marking: false,
            march,
            format,
            value_range,
            voxel_bytes: words.len() as u64 * 4,
            minmax_bytes: minmax.len() as u64 * 8,
            dims: dims.map(|d| d as u32),
            block: levels.primary.block as u32,
            counts: levels.primary.counts.map(|c| c as u32),
            ao_level: levels.ao,
            coarse_level: levels.coarse,
            spacing: geometry.spacing,
            box_min: geometry.box_min,
            box_max: geometry.box_max,
            name: geometry.name.to_string(),
            object,
            bricked: false,
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
    pub(crate) texels: wgpu::Buffer,
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
