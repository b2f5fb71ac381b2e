//! What a frame is rendered with, apart from the camera: iso value, march step, shading model,
//! light and material, and which AOV to output. Plain data shared by the CLI, the controller's frame
//! state and both renderers; the GPU copy of it is a separate `bytemuck` type in the renderer.

use glam::DVec3;
use serde::{Deserialize, Serialize};

/// The direct-light shading model of DESIGN.md's final colour.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Shading {
    Lambert,
    #[default]
    BlinnPhong,
}

impl Shading {
    /// Every shading model.
    pub const ALL: [Shading; 2] = [Shading::Lambert, Shading::BlinnPhong];

    /// The variant's code: on the wire (`wire.rs`), in the kernels' parameters and in the WGSL's
    /// constants, one number everywhere (append only: a code never changes meaning).
    pub const fn code(self) -> u8 {
        match self {
            Shading::Lambert => 0,
            Shading::BlinnPhong => 1,
        }
    }
}

/// The edge-aware spatial filter of the occlusion and IBL terms before compose (`--denoise`,
/// `[render] denoise`): off shows the running sums as they are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Denoise {
    #[default]
    Off,
    On,
}

impl Denoise {
    /// Every setting.
    pub const ALL: [Denoise; 2] = [Denoise::Off, Denoise::On];

    /// The variant's code: on the wire (`wire.rs`), in the kernels' parameters and in the WGSL's
    /// constants, one number everywhere (append only: a code never changes meaning).
    pub const fn code(self) -> u8 {
        match self {
            Denoise::Off => 0,
            Denoise::On => 1,
        }
    }

    pub fn is_on(self) -> bool {
        self == Denoise::On
    }
}

/// The exposure where none is given: with the default light (and with the built-in sky, whose
/// irradiance is of the same order as the constant ambient) the surface's mean shown luminance is
/// about 0.6-0.7, as it was before the light was rebalanced (`isowalld bench look`).
pub const DEFAULT_EXPOSURE: f64 = 0.6;

/// A directional light. `direction` points *towards* the light. When `camera_relative` is set,
/// `direction` is given in the camera frame (x right, y up, z towards the viewer), so the light
/// follows the camera: the default, a key light above-left of the viewer.
///
/// The default balance (key 0.5, ambient 0.8) is chosen so AO shows shape: in the default AO
/// render a surface point with A >= 0.3 is at least 30% darker (linear luminance) than an open one
/// at the same N.L, on the CT, the MRI and the engine (`isowalld bench look`; with the earlier key
/// 0.9 and ambient 0.15 the ambient term that AO darkens was a sixth of the light, 11-22% darker).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Light {
    pub direction: DVec3,
    pub camera_relative: bool,
    /// Linear RGB radiance scale of the light.
    pub color: [f64; 3],
    /// Constant ambient term (linear RGB), added before AO/IBL exist.
    pub ambient: [f64; 3],
}

impl Default for Light {
    fn default() -> Self {
        Light {
            direction: DVec3::new(-0.4, 0.6, 0.7).normalize(),
            camera_relative: true,
            color: [0.5, 0.5, 0.5],
            ambient: [0.8, 0.8, 0.9],
        }
    }
}

impl Light {
    /// The unit direction towards the light in world space, for a camera with frame (forward, right, up).
    pub fn world_direction(&self, forward: DVec3, right: DVec3, up: DVec3) -> DVec3 {
        let d = if self.camera_relative {
            self.direction.x * right + self.direction.y * up - self.direction.z * forward
        } else {
            self.direction
        };
        d.normalize_or(DVec3::Z)
    }
}

/// Surface material: linear albedo, and a Blinn-Phong specular lobe.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Material {
    pub albedo: [f64; 3],
    pub specular: f64,
    pub shininess: f64,
}

impl Default for Material {
    fn default() -> Self {
        Material { albedo: [0.85, 0.78, 0.68], specular: 0.25, shininess: 40.0 }
    }
}

/// Arbitrary output variables (DESIGN.md "AOVs"). Every non-colour AOV is 0 where a pixel has no hit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Aov {
    /// Final colour, 8-bit sRGB PNG.
    #[default]
    Color,
    /// Distance from the eye to the hit along the ray (world units).
    Depth,
    /// N = -grad f / |grad f| at the hit (points out of the object), not flipped towards the viewer.
    Normal,
    /// 1 where the ray hits the isosurface, else 0.
    Hit,
    /// A in [0, 1] (0 = fully open), the ambient occlusion of DESIGN.md.
    Occlusion,
    /// The bent normal: normalized mean of the unoccluded AO directions (N where none is).
    BentNormal,
    /// E(p) of DESIGN.md ("IBL") for albedo 1, before exposure: float RGB, what the IBL method estimates.
    Ibl,
}

impl Aov {
    pub const ALL: [Aov; 7] =
        [Aov::Color, Aov::Depth, Aov::Normal, Aov::Hit, Aov::Occlusion, Aov::BentNormal, Aov::Ibl];

    /// The AOV's name on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            Aov::Color => "color",
            Aov::Depth => "depth",
            Aov::Normal => "normal",
            Aov::Hit => "hit",
            Aov::Occlusion => "occlusion",
            Aov::BentNormal => "bent-normal",
            Aov::Ibl => "ibl",
        }
    }

    /// Number of float channels in the AOV's PFM (colour is written as PNG instead).
    pub fn channels(self) -> usize {
        match self {
            Aov::Color | Aov::Normal | Aov::BentNormal | Aov::Ibl => 3,
            Aov::Depth | Aov::Hit | Aov::Occlusion => 1,
        }
    }
}

/// The most AO rays per pixel per frame anything accepts (the CLI, a config, a frame state from the
/// network): more belongs in progressive accumulation, and a kernel must stay short.
pub const MAX_AO_SAMPLES: u32 = 1024;
/// The range of march steps, in voxels, accepted from outside.
pub const MIN_STEP_VOXELS: f64 = 0.05;
pub const MAX_STEP_VOXELS: f64 = 2.0;

/// DESIGN.md "AO": the AO rays start at `p + eps * Ng`, eps = 0.01 of the smallest spacing.
pub const AO_EPS_VOXELS: f64 = 0.01;

/// How ambient occlusion is computed (DESIGN.md "AO").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum AoMethod {
    /// Ours: cosine-weighted directions about N (as it is, not turned to the viewer) from a 2D
    /// low-discrepancy set ([`AoSequence`]) decorrelated per pixel and frame, concentric disk
    /// mapping, origin on the surface (`eps` = 0.01 voxel along the geometric normal Ng), occluded
    /// as soon as the ray reaches f >= iso within R (world units): every cell the ray crosses is
    /// tested exactly (`exact`, the default), or the ray marches with at most half a voxel per
    /// step.
    #[default]
    Ours,
    /// The 2008 RTPara shader, ported faithfully as the baseline (not our method).
    Seed,
}

impl AoMethod {
    /// Every AO method.
    pub const ALL: [AoMethod; 2] = [AoMethod::Ours, AoMethod::Seed];

    /// The variant's code: on the wire (`wire.rs`), in the kernels' parameters and in the WGSL's
    /// constants, one number everywhere (append only: a code never changes meaning).
    pub const fn code(self) -> u8 {
        match self {
            AoMethod::Ours => 0,
            AoMethod::Seed => 1,
        }
    }
}

/// The 2D point set the AO directions of ours come from (DESIGN.md "AO"; the formulas are in
/// `isowall_render::sampling`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum AoSequence {
    /// The R2 sequence with a per-pixel, per-frame Cranley-Patterson shift.
    R2,
    /// Sobol (first two dimensions) with hash-based Owen scrambling and index shuffling, seeded
    /// per pixel and frame: the lower error at every sample count measured (docs/accuracy).
    #[default]
    Sobol,
}

impl AoSequence {
    /// Every sequence.
    pub const ALL: [AoSequence; 2] = [AoSequence::R2, AoSequence::Sobol];

    /// The variant's code: on the wire (`wire.rs`), in the kernels' parameters and in the WGSL's
    /// constants, one number everywhere (append only: a code never changes meaning).
    pub const fn code(self) -> u8 {
        match self {
            AoSequence::R2 => 0,
            AoSequence::Sobol => 1,
        }
    }

    /// The name on the command line and in configs.
    pub fn name(self) -> &'static str {
        match self {
            AoSequence::R2 => "r2",
            AoSequence::Sobol => "sobol",
        }
    }
}

/// The AO radius R: world units, or unbounded (to the box).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AoRadius {
    /// 8 voxels of the largest spacing.
    Default,
    World(f64),
    Unbounded,
}

/// How the ambient term is lit (DESIGN.md "IBL").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum IblMethod {
    /// A constant ambient light (the light's `ambient`) times 1 - A.
    #[default]
    None,
    /// The 2008 method: the raw environment at the bent normal (as if the surface were a mirror),
    /// times 1 - A.
    Seed,
    /// The environment's diffuse irradiance (9 SH coefficients) at the bent normal, times 1 - A.
    Bent,
    /// Every escaping AO ray looks up L_env in its own direction: unbiased, no extra tracing.
    Rays,
}

impl IblMethod {
    /// Every IBL method.
    pub const ALL: [IblMethod; 4] = [IblMethod::None, IblMethod::Seed, IblMethod::Bent, IblMethod::Rays];

    /// The variant's code: on the wire (`wire.rs`), in the kernels' parameters and in the WGSL's
    /// constants, one number everywhere (append only: a code never changes meaning).
    pub const fn code(self) -> u8 {
        match self {
            IblMethod::None => 0,
            IblMethod::Seed => 1,
            IblMethod::Bent => 2,
            IblMethod::Rays => 3,
        }
    }

    /// The method's name, as the config and the command line spell it.
    pub fn name(self) -> &'static str {
        match self {
            IblMethod::None => "none",
            IblMethod::Seed => "seed",
            IblMethod::Bent => "bent",
            IblMethod::Rays => "rays",
        }
    }
}

/// Ambient occlusion and image-based lighting parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AoSettings {
    /// AO rays per pixel per frame; 0 turns AO off (A = 0, bent normal = N).
    pub samples: u32,
    pub radius: AoRadius,
    pub method: AoMethod,
    pub ibl: IblMethod,
    /// Ours: test every cell an AO ray crosses exactly (the cubic of the trilinear field along the
    /// ray, as the reference does), so no sheet is too thin; `false` marches with `step_voxels`
    /// instead (a variant for the speed/accuracy chart).
    pub exact: bool,
    /// March step of AO rays (ours, when not `exact`) in voxels of the smallest spacing.
    pub step_voxels: f64,
    /// The AO rays' origin `eps` off the surface along the geometric normal Ng, in voxels of the
    /// smallest spacing (DESIGN.md "AO": 0.01, [`AO_EPS_VOXELS`]).
    pub offset_voxels: f64,
    /// The 2D set of ours' directions.
    pub sequence: AoSequence,
    /// Frame index: with the pixel, it seeds the per-pixel shift of the sample pattern.
    pub frame: u32,
    /// A user seed mixed into every pixel's hash (`--seed`).
    pub seed: u32,
}

impl Default for AoSettings {
    fn default() -> Self {
        AoSettings {
            samples: 0,
            radius: AoRadius::Default,
            method: AoMethod::Ours,
            ibl: IblMethod::None,
            exact: true,
            step_voxels: 0.5,
            offset_voxels: AO_EPS_VOXELS,
            sequence: AoSequence::default(),
            frame: 0,
            seed: 0,
        }
    }
}

impl AoSettings {
    /// R in world units for a volume of the given spacing and box: `None` when unbounded.
    pub fn radius_world(&self, spacing: DVec3) -> Option<f64> {
        match self.radius {
            AoRadius::Default => Some(8.0 * spacing.max_element()),
            AoRadius::World(r) => Some(r),
            AoRadius::Unbounded => None,
        }
    }
}

/// Everything but the camera that decides a frame's pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderSettings {
    /// The iso value, in the data's own units (Hounsfield for CT).
    pub iso: f64,
    /// Primary-ray march step in voxels of the smallest spacing (the GPU's; the reference is exact).
    pub step_voxels: f64,
    /// Skip blocks whose min/max excludes the iso value (primary rays).
    pub empty_space_skipping: bool,
    pub shading: Shading,
    pub light: Light,
    pub material: Material,
    /// Exposure multiplier applied to linear colour before the sRGB transfer.
    pub exposure: f64,
    /// Linear RGB of pixels without a hit, in the colour image.
    pub background: [f64; 3],
    pub ao: AoSettings,
    /// The spatial filter of the occlusion and IBL terms (not part of the running sums: turning it
    /// on or off keeps the accumulation).
    pub denoise: Denoise,
}

impl RenderSettings {
    /// Whether the IBL method looks up an environment (every method but `none`).
    pub fn ibl_needs_environment(&self) -> bool {
        self.ao.ibl != IblMethod::None
    }

    pub fn new(iso: f64) -> Self {
        RenderSettings {
            iso,
            step_voxels: 0.5,
            empty_space_skipping: true,
            shading: Shading::default(),
            light: Light::default(),
            material: Material::default(),
            exposure: DEFAULT_EXPOSURE,
            background: [0.02, 0.025, 0.035],
            ao: AoSettings::default(),
            denoise: Denoise::Off,
        }
    }
}

/// The sRGB transfer function (IEC 61966-2-1) of a linear value, clamped to [0, 1].
pub fn linear_to_srgb(x: f64) -> f64 {
    let x = if x.is_finite() { x.clamp(0.0, 1.0) } else { 0.0 };
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

/// 8-bit sRGB of a linear value: the transfer function, rounded to the nearest code.
pub fn srgb8(x: f64) -> u8 {
    (linear_to_srgb(x) * 255.0 + 0.5).floor() as u8
}

/// Direct light at a surface point, linear RGB, for unit `n` (facing the viewer), unit `l` towards
/// the light and unit `v` towards the viewer: albedo * (ambient + light * N.L) + specular (Blinn-Phong).
/// The one formula both renderers follow (the WGSL twin is `shade` in shaders/shading.wgsl).
pub fn shade(settings: &RenderSettings, n: DVec3, l: DVec3, v: DVec3) -> [f64; 3] {
    let m = &settings.material;
    let lt = &settings.light;
    let ndl = n.dot(l).max(0.0);
    let spec = match settings.shading {
        Shading::Lambert => 0.0,
        Shading::BlinnPhong => {
            let h = (l + v).normalize_or(n);
            if ndl > 0.0 {
                m.specular * n.dot(h).max(0.0).powf(m.shininess)
            } else {
                0.0
            }
        }
    };
    std::array::from_fn(|c| m.albedo[c] * (lt.ambient[c] + lt.color[c] * ndl) + lt.color[c] * spec)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_transfer_endpoints_and_knee() {
        assert_eq!(linear_to_srgb(0.0), 0.0);
        assert!((linear_to_srgb(1.0) - 1.0).abs() < 1e-12);
        assert!((linear_to_srgb(0.5) - 0.735_356_983).abs() < 1e-6);
        assert_eq!(linear_to_srgb(f64::NAN), 0.0);
        assert_eq!(linear_to_srgb(7.0), linear_to_srgb(1.0));
        assert_eq!((srgb8(0.0), srgb8(1.0), srgb8(0.5), srgb8(f64::NAN)), (0, 255, 188, 0));
    }

    #[test]
    fn lambert_has_no_highlight_and_blinn_phong_does() {
        let mut s = RenderSettings::new(0.0);
        let n = DVec3::Z;
        s.shading = Shading::Lambert;
        let lam = shade(&s, n, n, n);
        s.shading = Shading::BlinnPhong;
        let bp = shade(&s, n, n, n);
        for c in 0..3 {
            assert!((lam[c] - s.material.albedo[c] * (s.light.ambient[c] + s.light.color[c])).abs() < 1e-12);
            assert!((bp[c] - lam[c] - s.light.color[c] * s.material.specular).abs() < 1e-12);
        }
        // Light from behind: ambient only.
        let back = shade(&s, n, -n, n);
        assert!((back[0] - s.material.albedo[0] * s.light.ambient[0]).abs() < 1e-12);
    }

    #[test]
    fn camera_relative_light_follows_the_camera() {
        let l = Light { direction: DVec3::new(0.0, 0.0, 1.0), ..Light::default() };
        let (f, r, u) = (DVec3::Y, DVec3::X, DVec3::Z);
        assert!((l.world_direction(f, r, u) - (-DVec3::Y)).length() < 1e-12);
    }
}
