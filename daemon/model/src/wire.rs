//! Wire types: what a frame's state looks like on the network, kept apart from the model types
//! ([`Camera`], [`RenderSettings`]) so that either can change without silently changing the other.
//!
//! Conversions are explicit: model -> wire is `From` (it cannot fail), wire -> model is `TryFrom`
//! and validates everything a peer could get wrong (finite numbers, a camera that defines a frame,
//! positive steps, enum codes in range), returning a [`WireError`] that names the field.
//!
//! Enums travel as `u8` codes: each enum's `code()` in `render_state.rs` (append only; the kernels'
//! parameters and the WGSL use the same numbers). The AO radius kind is the wire's own: 0 default
//! (8 voxels), 1 world (`radius`), 2 unbounded.

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, CameraError};
use crate::render_state::{
    AoMethod, AoRadius, AoSequence, AoSettings, Denoise, IblMethod, Light, Material, RenderSettings, Shading,
};

/// A camera on the wire: [`Camera`] with plain arrays.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct WireCamera {
    pub eye: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub fov_y_deg: f64,
}

/// [`Light`] on the wire.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct WireLight {
    pub direction: [f64; 3],
    pub camera_relative: bool,
    pub color: [f64; 3],
    pub ambient: [f64; 3],
}

/// [`Material`] on the wire.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct WireMaterial {
    pub albedo: [f64; 3],
    pub specular: f64,
    pub shininess: f64,
}

/// [`AoSettings`] on the wire; the enums as codes (see the module docs).
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct WireAo {
    pub samples: u32,
    /// 0 default, 1 world (`radius` world units), 2 unbounded.
    pub radius_kind: u8,
    /// World units when `radius_kind` is 1; 0 otherwise.
    pub radius: f64,
    /// [`AoMethod::code`].
    pub method: u8,
    /// [`IblMethod::code`].
    pub ibl: u8,
    pub exact: bool,
    pub step_voxels: f64,
    pub offset_voxels: f64,
    /// [`AoSequence::code`].
    pub sequence: u8,
    pub frame: u32,
    pub seed: u32,
}

/// [`RenderSettings`] on the wire.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct WireSettings {
    pub iso: f64,
    pub step_voxels: f64,
    pub empty_space_skipping: bool,
    /// [`Shading::code`].
    pub shading: u8,
    pub light: WireLight,
    pub material: WireMaterial,
    pub exposure: f64,
    pub background: [f64; 3],
    pub ao: WireAo,
    /// [`Denoise::code`].
    pub denoise: u8,
}

/// How a frame's image relates to the frame before it on the same node: the one rule of when a
/// node keeps accumulating, carries its history into a moved camera, or starts over.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Continuity {
    /// The same image ([`FrameState::same_image`]): keep accumulating.
    Same,
    /// Only the view moved (the camera, and with it a light that follows the camera, or the
    /// light's direction): what a surface point receives is unchanged, so its history may be
    /// carried over (reprojection).
    ViewMoved,
    /// Anything else (iso, AO, light colour, environment, volume, time step, scale), or no frame
    /// before: start over.
    Changed,
}

/// What the controller broadcasts each frame.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct FrameState {
    pub frame_id: u64,
    pub camera: WireCamera,
    pub settings: WireSettings,
    /// The internal resolution divisor chosen by the controller's governor (1 = full resolution,
    /// 1 ..= [`MAX_SCALE`](crate::governor::MAX_SCALE); `lowres.rs`): the same for every node.
    /// (Protocol 3: this u32 was `quality`, unused, in protocol 2.)
    pub scale: u32,
    /// The time step of a time-varying volume every node renders in this frame (0 for a volume
    /// without time steps; a node takes it modulo its volume's step count). Protocol 5.
    pub time_step: u32,
}

impl FrameState {
    /// The frame state of a model frame, at time step 0.
    pub fn new(frame_id: u64, camera: &Camera, settings: &RenderSettings, scale: u32) -> Self {
        FrameState { frame_id, camera: camera.into(), settings: settings.into(), scale, time_step: 0 }
    }

    /// The same frame state at time step `time_step`.
    pub fn at_time_step(self, time_step: u32) -> Self {
        FrameState { time_step, ..self }
    }

    /// Whether `other` asks for the same image (everything but the frame id is equal): a daemon
    /// keeps accumulating progressive AO while this holds.
    pub fn same_image(&self, other: &FrameState) -> bool {
        self.camera == other.camera
            && self.settings == other.settings
            && self.scale == other.scale
            && self.time_step == other.time_step
    }

    /// How this frame relates to `previous` (the frame rendered before it; `None`: none).
    pub fn continuity(&self, previous: Option<&FrameState>) -> Continuity {
        let Some(p) = previous else { return Continuity::Changed };
        if self.same_image(p) {
            return Continuity::Same;
        }
        let unlit =
            |s: &WireSettings| WireSettings { light: WireLight { direction: [0.0; 3], ..s.light }, ..*s };
        if unlit(&self.settings) == unlit(&p.settings)
            && self.scale == p.scale
            && self.time_step == p.time_step
        {
            Continuity::ViewMoved
        } else {
            Continuity::Changed
        }
    }
}

/// Frames as a node starts them, one after another: how each follows the one before
/// ([`FrameState::continuity`]) and how many frames of the same image came before it (0 after any
/// change), the index progressive AO decorrelates its samples by.
#[derive(Debug, Clone, Default)]
pub struct FrameSequence {
    last: Option<FrameState>,
    same: u32,
}

impl FrameSequence {
    /// `state` starts: its continuity and its count of earlier frames of the same image.
    pub fn start(&mut self, state: FrameState) -> (Continuity, u32) {
        let continuity = state.continuity(self.last.as_ref());
        self.same = match continuity {
            Continuity::Same => self.same.saturating_add(1),
            Continuity::ViewMoved | Continuity::Changed => 0,
        };
        self.last = Some(state);
        (continuity, self.same)
    }
}

/// A frame's state in model types: what [`FrameState`] validates into.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameSpec {
    pub frame_id: u64,
    pub camera: Camera,
    pub settings: RenderSettings,
    /// The internal resolution divisor, 1 ..= [`MAX_SCALE`](crate::governor::MAX_SCALE).
    pub scale: u32,
    /// The time step ([`FrameState::time_step`]).
    pub time_step: u32,
}

impl From<&FrameSpec> for FrameState {
    fn from(f: &FrameSpec) -> Self {
        FrameState::new(f.frame_id, &f.camera, &f.settings, f.scale).at_time_step(f.time_step)
    }
}

impl TryFrom<&FrameState> for FrameSpec {
    type Error = WireError;
    fn try_from(s: &FrameState) -> Result<Self, WireError> {
        Ok(FrameSpec {
            frame_id: s.frame_id,
            camera: Camera::try_from(s.camera)?,
            settings: RenderSettings::try_from(s.settings)?,
            scale: if (1..=crate::governor::MAX_SCALE).contains(&s.scale) {
                s.scale
            } else {
                return Err(WireError::OutOfRange {
                    field: "scale",
                    value: s.scale as f64,
                    expected: "an internal resolution divisor in 1..=4",
                });
            },
            time_step: s.time_step,
        })
    }
}

impl TryFrom<FrameState> for FrameSpec {
    type Error = WireError;
    fn try_from(s: FrameState) -> Result<Self, WireError> {
        FrameSpec::try_from(&s)
    }
}

/// A wire value that does not make a valid model value; `field` is its path, e.g.
/// `settings.ao.step_voxels`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WireError {
    #[error("`{field}` is not finite ({value})")]
    NotFinite { field: &'static str, value: f64 },
    #[error("`{field}` = {value} is out of range: {expected}")]
    OutOfRange { field: &'static str, value: f64, expected: &'static str },
    #[error("`{field}` = {value} is not a known code (0..={max})")]
    UnknownCode { field: &'static str, value: u8, max: u8 },
    /// The camera does not define a frame ([`CameraError`], as text).
    #[error("`{field}`: {reason}")]
    Camera { field: &'static str, reason: String },
}

impl WireError {
    /// The path of the offending field.
    pub fn field(&self) -> &'static str {
        match self {
            WireError::NotFinite { field, .. }
            | WireError::OutOfRange { field, .. }
            | WireError::UnknownCode { field, .. }
            | WireError::Camera { field, .. } => field,
        }
    }
}

fn finite(field: &'static str, value: f64) -> Result<f64, WireError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(WireError::NotFinite { field, value })
    }
}

fn finite3(field: &'static str, v: [f64; 3]) -> Result<[f64; 3], WireError> {
    for x in v {
        finite(field, x)?;
    }
    Ok(v)
}

/// A march step in voxels: a step far below a voxel only costs time (a frame could run for hours
/// on a kernel without a watchdog), one above two voxels skips the surface.
fn step(field: &'static str, value: f64) -> Result<f64, WireError> {
    if value.is_finite()
        && (crate::render_state::MIN_STEP_VOXELS..=crate::render_state::MAX_STEP_VOXELS).contains(&value)
    {
        Ok(value)
    } else {
        Err(WireError::OutOfRange { field, value, expected: "in 0.05..=2 voxels" })
    }
}

fn positive(field: &'static str, value: f64) -> Result<f64, WireError> {
    finite(field, value)?;
    if value > 0.0 {
        Ok(value)
    } else {
        Err(WireError::OutOfRange { field, value, expected: "> 0" })
    }
}

fn non_negative(field: &'static str, value: f64) -> Result<f64, WireError> {
    finite(field, value)?;
    if value >= 0.0 {
        Ok(value)
    } else {
        Err(WireError::OutOfRange { field, value, expected: ">= 0" })
    }
}

fn v3(a: [f64; 3]) -> DVec3 {
    DVec3::from_array(a)
}

impl From<&Camera> for WireCamera {
    fn from(c: &Camera) -> Self {
        WireCamera {
            eye: c.eye.to_array(),
            target: c.target.to_array(),
            up: c.up.to_array(),
            fov_y_deg: c.fov_y_deg,
        }
    }
}

impl From<Camera> for WireCamera {
    fn from(c: Camera) -> Self {
        (&c).into()
    }
}

impl TryFrom<WireCamera> for Camera {
    type Error = WireError;
    fn try_from(w: WireCamera) -> Result<Self, WireError> {
        let cam = Camera {
            eye: v3(finite3("camera.eye", w.eye)?),
            target: v3(finite3("camera.target", w.target)?),
            up: v3(finite3("camera.up", w.up)?),
            fov_y_deg: finite("camera.fov_y_deg", w.fov_y_deg)?,
        };
        cam.validate().map_err(|error| {
            let field = match &error {
                CameraError::EyeIsTarget(_) => "camera.target",
                CameraError::UpParallel { .. } => "camera.up",
                CameraError::BadFov(_) => "camera.fov_y_deg",
                CameraError::NotFinite(_) => "camera",
                CameraError::OutOfRange { field: "eye", .. } => "camera.eye",
                CameraError::OutOfRange { field: "target", .. } => "camera.target",
                CameraError::OutOfRange { .. } => "camera.up",
            };
            WireError::Camera { field, reason: error.to_string() }
        })?;
        Ok(cam)
    }
}

// Each enum's code has one home, its `code` in `render_state.rs` (shared with the kernels' parameters
// and the WGSL); decoding searches the variants for the code.

/// The variant of `all` whose code is `value`, or the error naming `field`.
fn decode_code<T: Copy>(
    all: &[T],
    code: fn(T) -> u8,
    field: &'static str,
    value: u8,
) -> Result<T, WireError> {
    all.iter().copied().find(|&v| code(v) == value).ok_or(WireError::UnknownCode {
        field,
        value,
        max: all.iter().map(|&v| code(v)).max().unwrap_or(0),
    })
}

impl From<&AoSettings> for WireAo {
    fn from(a: &AoSettings) -> Self {
        let (radius_kind, radius) = match a.radius {
            AoRadius::Default => (0, 0.0),
            AoRadius::World(r) => (1, r),
            AoRadius::Unbounded => (2, 0.0),
        };
        WireAo {
            samples: a.samples,
            radius_kind,
            radius,
            method: a.method.code(),
            ibl: a.ibl.code(),
            exact: a.exact,
            step_voxels: a.step_voxels,
            offset_voxels: a.offset_voxels,
            sequence: a.sequence.code(),
            frame: a.frame,
            seed: a.seed,
        }
    }
}

impl TryFrom<WireAo> for AoSettings {
    type Error = WireError;
    fn try_from(w: WireAo) -> Result<Self, WireError> {
        let radius = match w.radius_kind {
            0 => AoRadius::Default,
            1 => AoRadius::World(positive("settings.ao.radius", w.radius)?),
            2 => AoRadius::Unbounded,
            value => return Err(WireError::UnknownCode { field: "settings.ao.radius_kind", value, max: 2 }),
        };
        let method = decode_code(&AoMethod::ALL, AoMethod::code, "settings.ao.method", w.method)?;
        let ibl = decode_code(&IblMethod::ALL, IblMethod::code, "settings.ao.ibl", w.ibl)?;
        Ok(AoSettings {
            samples: if w.samples <= crate::render_state::MAX_AO_SAMPLES {
                w.samples
            } else {
                return Err(WireError::OutOfRange {
                    field: "settings.ao.samples",
                    value: w.samples as f64,
                    expected: "<= 1024",
                });
            },
            radius,
            method,
            ibl,
            exact: w.exact,
            step_voxels: step("settings.ao.step_voxels", w.step_voxels)?,
            offset_voxels: non_negative("settings.ao.offset_voxels", w.offset_voxels)?,
            sequence: decode_code(&AoSequence::ALL, AoSequence::code, "settings.ao.sequence", w.sequence)?,
            frame: w.frame,
            seed: w.seed,
        })
    }
}

impl From<&RenderSettings> for WireSettings {
    fn from(s: &RenderSettings) -> Self {
        WireSettings {
            iso: s.iso,
            step_voxels: s.step_voxels,
            empty_space_skipping: s.empty_space_skipping,
            shading: s.shading.code(),
            light: WireLight {
                direction: s.light.direction.to_array(),
                camera_relative: s.light.camera_relative,
                color: s.light.color,
                ambient: s.light.ambient,
            },
            material: WireMaterial {
                albedo: s.material.albedo,
                specular: s.material.specular,
                shininess: s.material.shininess,
            },
            exposure: s.exposure,
            background: s.background,
            ao: (&s.ao).into(),
            denoise: s.denoise.code(),
        }
    }
}

impl From<RenderSettings> for WireSettings {
    fn from(s: RenderSettings) -> Self {
        (&s).into()
    }
}

impl TryFrom<WireSettings> for RenderSettings {
    type Error = WireError;
    fn try_from(w: WireSettings) -> Result<Self, WireError> {
        let shading = decode_code(&Shading::ALL, Shading::code, "settings.shading", w.shading)?;
        Ok(RenderSettings {
            iso: finite("settings.iso", w.iso)?,
            step_voxels: step("settings.step_voxels", w.step_voxels)?,
            empty_space_skipping: w.empty_space_skipping,
            shading,
            light: Light {
                direction: v3(finite3("settings.light.direction", w.light.direction)?),
                camera_relative: w.light.camera_relative,
                color: finite3("settings.light.color", w.light.color)?,
                ambient: finite3("settings.light.ambient", w.light.ambient)?,
            },
            material: Material {
                albedo: finite3("settings.material.albedo", w.material.albedo)?,
                specular: finite("settings.material.specular", w.material.specular)?,
                shininess: non_negative("settings.material.shininess", w.material.shininess)?,
            },
            exposure: non_negative("settings.exposure", w.exposure)?,
            background: finite3("settings.background", w.background)?,
            ao: AoSettings::try_from(w.ao)?,
            denoise: decode_code(&Denoise::ALL, Denoise::code, "settings.denoise", w.denoise)?,
        })
    }
}

/// A work rectangle of the load-balanced split on the wire ([`crate::balance::WorkRect`]): the
/// tile and its renderer by their index in the wall config's `tiles` and `nodes` (both ends read
/// the same config), rows `first_row .. first_row + rows` of the tile, its full width.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub struct WireWorkRect {
    pub tile: u32,
    pub first_row: u32,
    pub rows: u32,
    pub renderer: u32,
}

/// A frame's split on the wire ([`crate::balance::Split`]); checked whole by
/// [`crate::balance::share::split_from_wire`] before a node uses any of it.
#[derive(Serialize, Deserialize, Debug, Clone, Default, PartialEq, Eq)]
pub struct WireSplit {
    pub rects: Vec<WireWorkRect>,
}

/// What rendering rows `first_row .. first_row + rows` of tile `tile` (its index in the wall
/// config) cost a node in one frame, in the unit of `crate::balance::node::rect_cost`.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub struct WireRectCost {
    pub tile: u32,
    pub first_row: u32,
    pub rows: u32,
    pub cost: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_variant_has_its_own_code_and_decodes_back() {
        fn check<T: Copy + PartialEq + std::fmt::Debug>(all: &[T], code: fn(T) -> u8) {
            for (i, &v) in all.iter().enumerate() {
                assert_eq!(decode_code(all, code, "f", code(v)).unwrap(), v);
                assert!(all[..i].iter().all(|&u| code(u) != code(v)), "{v:?} shares its code");
            }
            let max = all.iter().map(|&v| code(v)).max().unwrap();
            let e = decode_code(all, code, "f", max + 1).unwrap_err();
            assert!(matches!(e, WireError::UnknownCode { field: "f", max: m, .. } if m == max), "{e:?}");
        }
        check(&Shading::ALL, Shading::code);
        check(&AoMethod::ALL, AoMethod::code);
        check(&AoSequence::ALL, AoSequence::code);
        check(&IblMethod::ALL, IblMethod::code);
        check(&Denoise::ALL, Denoise::code);
    }

    fn camera() -> Camera {
        Camera {
            eye: DVec3::new(3.0, -7.0, 2.0),
            target: DVec3::new(0.5, 0.25, 0.0),
            up: DVec3::Z,
            fov_y_deg: 40.0,
        }
    }

    fn settings() -> RenderSettings {
        let mut s = RenderSettings::new(300.0);
        s.shading = Shading::Lambert;
        s.ao = AoSettings {
            samples: 32,
            radius: AoRadius::World(12.5),
            method: AoMethod::Seed,
            ibl: IblMethod::Rays,
            exact: false,
            step_voxels: 0.25,
            offset_voxels: 0.0,
            sequence: AoSequence::R2,
            frame: 9,
            seed: 77,
        };
        s
    }

    #[test]
    fn model_wire_model_round_trips() {
        let spec = FrameSpec { frame_id: 42, camera: camera(), settings: settings(), scale: 3, time_step: 7 };
        let wire = FrameState::from(&spec);
        assert_eq!(FrameSpec::try_from(&wire).unwrap(), spec);
        // Every enum value survives.
        for radius in [AoRadius::Default, AoRadius::World(1.0), AoRadius::Unbounded] {
            for method in [AoMethod::Ours, AoMethod::Seed] {
                for ibl in [IblMethod::None, IblMethod::Seed, IblMethod::Bent, IblMethod::Rays] {
                    for shading in [Shading::Lambert, Shading::BlinnPhong] {
                        let mut s = settings();
                        s.shading = shading;
                        s.ao.radius = radius;
                        s.ao.method = method;
                        s.ao.ibl = ibl;
                        assert_eq!(RenderSettings::try_from(WireSettings::from(&s)).unwrap(), s);
                    }
                }
            }
        }
    }

    #[test]
    fn invalid_wire_values_name_their_field() {
        let good = FrameState::new(1, &camera(), &settings(), 1);
        let check = |f: &dyn Fn(&mut FrameState), field: &str| {
            let mut s = good;
            f(&mut s);
            let err = FrameSpec::try_from(&s).unwrap_err();
            assert_eq!(err.field(), field, "{err}");
            assert!(err.to_string().contains(field), "{err}");
        };
        check(&|s| s.camera.eye[1] = f64::NAN, "camera.eye");
        check(&|s| s.camera.up = [0.0, 0.0, f64::INFINITY], "camera.up");
        check(&|s| s.camera.target = s.camera.eye, "camera.target");
        check(&|s| s.camera.up = [3.0 - 0.5, -7.0 - 0.25, 2.0], "camera.up");
        check(&|s| s.camera.fov_y_deg = 0.0, "camera.fov_y_deg");
        check(&|s| s.camera.fov_y_deg = f64::NAN, "camera.fov_y_deg");
        check(&|s| s.settings.iso = f64::NEG_INFINITY, "settings.iso");
        check(&|s| s.settings.step_voxels = 0.0, "settings.step_voxels");
        check(&|s| s.settings.step_voxels = 1e-9, "settings.step_voxels");
        check(&|s| s.settings.ao.step_voxels = 50.0, "settings.ao.step_voxels");
        check(&|s| s.settings.ao.samples = 5000, "settings.ao.samples");
        check(&|s| s.settings.shading = 2, "settings.shading");
        check(&|s| s.settings.light.direction[0] = f64::NAN, "settings.light.direction");
        check(&|s| s.settings.light.color[2] = f64::INFINITY, "settings.light.color");
        check(&|s| s.settings.material.shininess = -1.0, "settings.material.shininess");
        check(&|s| s.settings.exposure = -0.5, "settings.exposure");
        check(&|s| s.settings.background[0] = f64::NAN, "settings.background");
        check(&|s| s.settings.ao.radius_kind = 3, "settings.ao.radius_kind");
        check(&|s| s.settings.ao.radius = -2.0, "settings.ao.radius");
        check(&|s| s.settings.ao.method = 200, "settings.ao.method");
        check(&|s| s.settings.ao.ibl = 4, "settings.ao.ibl");
        check(&|s| s.settings.ao.step_voxels = f64::NAN, "settings.ao.step_voxels");
        check(&|s| s.settings.ao.offset_voxels = -0.1, "settings.ao.offset_voxels");
        check(&|s| s.settings.ao.sequence = 2, "settings.ao.sequence");
        check(&|s| s.scale = 0, "scale");
        check(&|s| s.scale = 5, "scale");
        for scale in 1..=4 {
            assert_eq!(FrameSpec::try_from(&FrameState { scale, ..good }).unwrap().scale, scale);
        }
    }

    #[test]
    fn same_image_ignores_only_the_frame_id() {
        let a = FrameState::new(1, &camera(), &settings(), 2);
        let mut b = a;
        b.frame_id = 2;
        assert!(a.same_image(&b));
        b.scale = 3;
        assert!(!a.same_image(&b));
        let mut c = a;
        c.settings.ao.frame += 1;
        assert!(!a.same_image(&c));
        assert!(!a.same_image(&a.at_time_step(1)), "another time step is another image");
        assert_eq!(a.at_time_step(5).time_step, 5);
    }

    #[test]
    fn continuity_is_same_for_the_same_image_view_moved_for_camera_or_light_direction_else_changed() {
        let a = FrameState::new(1, &camera(), &settings(), 2);
        assert_eq!(a.continuity(None), Continuity::Changed, "no frame before");
        let mut next = a;
        next.frame_id = 2;
        assert_eq!(next.continuity(Some(&a)), Continuity::Same);
        let mut moved = next;
        moved.camera.eye[0] += 1.0;
        assert_eq!(moved.continuity(Some(&a)), Continuity::ViewMoved);
        let mut turned = next;
        turned.settings.light.direction = [1.0, 0.0, 0.0];
        assert_eq!(turned.continuity(Some(&a)), Continuity::ViewMoved, "the light's direction only");
        type Change = (&'static str, fn(&mut FrameState));
        let changes: [Change; 6] = [
            ("iso", |f| f.settings.iso += 1.0),
            ("AO samples", |f| f.settings.ao.samples += 1),
            ("light colour", |f| f.settings.light.color[0] += 0.1),
            ("exposure", |f| f.settings.exposure += 0.1),
            ("scale", |f| f.scale += 1),
            ("time step", |f| f.time_step += 1),
        ];
        for (what, change) in changes {
            let mut c = moved;
            change(&mut c);
            assert_eq!(c.continuity(Some(&a)), Continuity::Changed, "{what} with the camera moved");
            let mut still = next;
            change(&mut still);
            assert_eq!(still.continuity(Some(&a)), Continuity::Changed, "{what}");
        }
    }

    #[test]
    fn a_sequence_counts_frames_of_the_same_image_and_starts_over_on_any_change() {
        let mut seq = FrameSequence::default();
        let a = FrameState::new(1, &camera(), &settings(), 1);
        let at = |id, mut f: FrameState| {
            f.frame_id = id;
            f
        };
        assert_eq!(seq.start(a), (Continuity::Changed, 0));
        assert_eq!(seq.start(at(2, a)), (Continuity::Same, 1));
        assert_eq!(seq.start(at(3, a)), (Continuity::Same, 2));
        let mut moved = at(4, a);
        moved.camera.eye[0] += 1.0;
        assert_eq!(seq.start(moved), (Continuity::ViewMoved, 0));
        assert_eq!(seq.start(at(5, moved)), (Continuity::Same, 1));
        let mut iso = at(6, moved);
        iso.settings.iso += 1.0;
        assert_eq!(seq.start(iso), (Continuity::Changed, 0));
    }
}
