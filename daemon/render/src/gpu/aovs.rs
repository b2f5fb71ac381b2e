//! The AOV buffers of a rectangle of pixels, the kernels' shared working set, by name: the
//! isosurface kernel writes `direct`, `geometry` and `fetches`; the AO kernel adds into `ao_sum`,
//! `ibl_sum`, `pos_sum` and `fetches`; reprojection, the filter and compose read them.

use super::GpuContext;

/// Bytes of one pixel of the four-vector AOVs.
pub const VEC4_BYTES: u64 = 16;

/// The AOVs of an `n`-pixel rectangle, rows top to bottom.
pub struct Aovs {
    /// Direct light (rgb) and the hit flag (w, `shaders/hit.wgsl`: at least 0.5 on a hit).
    pub direct: wgpu::Buffer,
    /// N (xyz, outward) and depth (w).
    pub geometry: wgpu::Buffer,
    /// Trilinear fetches per pixel (u32).
    pub fetches: wgpu::Buffer,
    /// Summed bent normal (xyz) and summed occlusion (w).
    pub ao_sum: wgpu::Buffer,
    /// Summed E (rgb) and the pixel's weight (w: frames' worth of samples).
    pub ibl_sum: wgpu::Buffer,
    /// Summed hit position (xyz, world) the samples were taken at, weighted as the other sums
    /// (w: 0): divided by the weight, where a reprojected history stands on the surface
    /// ([`crate::reproject::Rule::drift`]). Only a temporal tile needs it: elsewhere it is one
    /// pixel's placeholder, bound and never written ([`Aovs::with_positions`]).
    pub pos_sum: wgpu::Buffer,
    /// Whether `pos_sum` holds every pixel.
    pub positions: bool,
}

impl Aovs {
    /// The buffers of an `n`-pixel rectangle with `usage` (beside STORAGE), the positions'
    /// a placeholder.
    pub(crate) fn new(ctx: &GpuContext, n: u64, usage: wgpu::BufferUsages) -> Aovs {
        let usage = usage | wgpu::BufferUsages::STORAGE;
        Aovs {
            direct: ctx.buffer("direct", n * VEC4_BYTES, usage),
            geometry: ctx.buffer("geometry", n * VEC4_BYTES, usage),
            fetches: ctx.buffer("fetches", n * 4, usage),
            ao_sum: ctx.buffer("acc ao", n * VEC4_BYTES, usage),
            ibl_sum: ctx.buffer("acc ibl", n * VEC4_BYTES, usage),
            pos_sum: ctx.buffer("acc pos placeholder", VEC4_BYTES, usage),
            positions: false,
        }
    }

    /// The positions' buffer for all `n` pixels, made on a temporal tile's first frame (the
    /// buffers' bind groups must be made again). Returns whether it was made now.
    pub(crate) fn with_positions(&mut self, ctx: &GpuContext, n: u64) -> bool {
        if self.positions {
            return false;
        }
        self.pos_sum = ctx.buffer("acc pos", n * VEC4_BYTES, self.pos_sum.usage());
        self.positions = true;
        true
    }

    /// The four planes of a pixel's shading, in the order a shading share, a canvas and
    /// [`super::tile::TileSums`] carry them: direct, geometry, the AO sum, the IBL sum.
    pub(crate) fn shading(&self) -> [&wgpu::Buffer; 4] {
        [&self.direct, &self.geometry, &self.ao_sum, &self.ibl_sum]
    }

    /// The running sums the AO kernel adds into (cleared when accumulation restarts).
    pub(crate) fn sums(&self) -> [&wgpu::Buffer; 3] {
        [&self.ao_sum, &self.ibl_sum, &self.pos_sum]
    }
}
