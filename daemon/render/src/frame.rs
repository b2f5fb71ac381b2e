//! A rendered frame: every AOV of a rectangle of pixels, rows top to bottom.

use isowall_model::Aov;

/// All AOVs of one rendered rectangle. Pixels without a hit hold 0 in every AOV but `color`,
/// which holds the background.
#[derive(Clone, Debug, Default)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Linear RGB after exposure, before the sRGB transfer.
    pub color: Vec<[f32; 3]>,
    /// Distance from the eye to the hit along the ray, world units.
    pub depth: Vec<f32>,
    /// N = -grad f / |grad f| (outward), not flipped towards the viewer.
    pub normal: Vec<[f32; 3]>,
    pub hit: Vec<bool>,
    /// A in [0, 1], 0 = fully open (0 where AO is off).
    pub occlusion: Vec<f32>,
    /// Normalized mean of the unoccluded AO directions (N where none is, or AO is off).
    pub bent_normal: Vec<[f32; 3]>,
    /// E(p) for albedo 1 before exposure, linear RGB.
    pub ibl: Vec<[f32; 3]>,
    /// Trilinear field evaluations made for the frame (each is 8 voxel reads), all pixels together.
    pub fetches: u64,
}

impl Frame {
    /// A frame of `width x height` pixels, all without a hit.
    pub fn new(width: u32, height: u32) -> Frame {
        let n = width as usize * height as usize;
        Frame {
            width,
            height,
            color: vec![[0.0; 3]; n],
            depth: vec![0.0; n],
            normal: vec![[0.0; 3]; n],
            hit: vec![false; n],
            occlusion: vec![0.0; n],
            bent_normal: vec![[0.0; 3]; n],
            ibl: vec![[0.0; 3]; n],
            fetches: 0,
        }
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Trilinear fetches per pixel of the frame.
    pub fn fetches_per_pixel(&self) -> f64 {
        self.fetches as f64 / self.pixel_count().max(1) as f64
    }

    /// One AOV as interleaved floats, rows top to bottom, `aov.channels()` per pixel.
    pub fn aov(&self, aov: Aov) -> Vec<f32> {
        match aov {
            Aov::Color => self.color.iter().flatten().copied().collect(),
            Aov::Depth => self.depth.clone(),
            Aov::Normal => self.normal.iter().flatten().copied().collect(),
            Aov::Hit => self.hit.iter().map(|&h| if h { 1.0 } else { 0.0 }).collect(),
            Aov::Occlusion => self.occlusion.clone(),
            Aov::BentNormal => self.bent_normal.iter().flatten().copied().collect(),
            Aov::Ibl => self.ibl.iter().flatten().copied().collect(),
        }
    }

    /// Number of pixels with a hit.
    pub fn hit_count(&self) -> usize {
        self.hit.iter().filter(|&&h| h).count()
    }
}
