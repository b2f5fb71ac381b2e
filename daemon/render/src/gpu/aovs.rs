//! The AOV buffers of a rectangle of pixels, the kernels' shared working set, by name: the
//! isosurface kernel writes `direct`, `geometry` and `fetches`; the AO kernel adds into `ao_sum`,
//! `ibl_sum`, `pos_sum` and `fetches`; reprojection, the filter and compose read them.

use super::GpuContext;

/// Bytes of one pixel of the four-vector AOVs.
pub const VEC4_BYTES: u64 = 16;

/// The AOVs of an `n`-pixel rectangle, rows top to bottom.
pub struct Aovs {
    /// Direct light (rgb) and the hit flag (w = 1 on a hit).
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
    /// ([`crate::reproject::Rule::drift`]).
    pub pos_sum: wgpu::Buffer,
}

impl Aovs {
    /// The buffers of an `n`-pixel rectangle with `usage` (beside STORAGE).
    pub(crate) fn new(ctx: &GpuContext, n: u64, usage: wgpu::BufferUsages) -> Aovs {
        let usage = usage | wgpu::BufferUsages::STORAGE;
        Aovs {
            direct: ctx.buffer("direct", n * VEC4_BYTES, usage),
            geometry: ctx.buffer("geometry", n * VEC4_BYTES, usage),
            fetches: ctx.buffer("fetches", n * 4, usage),
            ao_sum: ctx.buffer("acc ao", n * VEC4_BYTES, usage),
            ibl_sum: ctx.buffer("acc ibl", n * VEC4_BYTES, usage),
            pos_sum: ctx.buffer("acc pos", n * VEC4_BYTES, usage),
        }
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
