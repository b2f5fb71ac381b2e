//! The pinhole camera of DESIGN.md ("Camera"), exactly:
//!
//! pixel (px, py) of a W x H image, py = 0 the top row, ray through the pixel centre
//! `d = normalize(f + sx*r + sy*u)` with `sx = ((px+0.5)/W*2-1) * tan(fov_y/2) * W/H`,
//! `sy = (1-(py+0.5)/H*2) * tan(fov_y/2)`, `f = normalize(target - eye)`, `r = normalize(f x up)`,
//! `u = r x f`.
//!
//! A [`View`] is that camera over a full image of `full` pixels, of which a [`Rect`] is rendered. A
//! wall tile is such a rectangle of the one wall image (an off-axis sub-frustum), so the assembled
//! wall is exactly one big image.

use glam::DVec3;
use isowall_volume::{Orientation, PatientDir};
use serde::{Deserialize, Serialize};

/// The least eye distance a framing gives a box: relative to the box's size, so that a volume of
/// 1e-9 world units a voxel frames as one of 1 does (an absolute floor put its camera so far off
/// that it covered a pixel or two).
pub(crate) fn framing_floor(box_min: DVec3, box_max: DVec3) -> f64 {
    1e-6 * (box_max - box_min).length().max(f64::MIN_POSITIVE)
}

/// Whether a camera vector `field` is within +-[`MAX_CAMERA_COORD`] (one rule for the CLI, the
/// config and the console, which all check through [`Camera::validate`] or this).
pub fn check_range(field: &'static str, v: DVec3) -> Result<(), CameraError> {
    if v.abs().max_element() > MAX_CAMERA_COORD {
        return Err(CameraError::OutOfRange { field, value: v.to_array() });
    }
    Ok(())
}

/// A pinhole camera: eye, target, up and the *vertical* field of view in degrees.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub eye: DVec3,
    pub target: DVec3,
    pub up: DVec3,
    pub fov_y_deg: f64,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("camera eye and target coincide ({0:?})")]
    EyeIsTarget(DVec3),
    #[error("camera up {up:?} is parallel to the view direction {forward:?}")]
    UpParallel { up: DVec3, forward: DVec3 },
    #[error("vertical field of view {0} degrees is outside (0, 180)")]
    BadFov(f64),
    #[error("{0} is not finite")]
    NotFinite(&'static str),
    #[error(
        "{field} {value:?} has a coordinate beyond +-{MAX_CAMERA_COORD:e}: the GPU computes in f32, whose step \
         there is a world unit, so nothing would render"
    )]
    OutOfRange { field: &'static str, value: [f64; 3] },
}

/// The largest magnitude of a camera coordinate (eye, target, up) that renders: the GPU computes
/// rays in f32, whose spacing at 1e7 is one world unit (at 1e39 a coordinate is infinite in f32).
pub const MAX_CAMERA_COORD: f64 = 1e7;

/// The orthonormal frame of a camera: forward, right, up (DESIGN.md's f, r, u).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Basis {
    pub forward: DVec3,
    pub right: DVec3,
    pub up: DVec3,
    /// tan(fov_y / 2)
    pub tan_half_fov: f64,
}

impl Camera {
    /// The camera turned by `degrees` about the world up axis (+z) through its target: the eye and
    /// the up vector turn, the target stays (an orbit's step; + is counter-clockwise from above).
    pub fn yawed(&self, degrees: f64) -> Camera {
        let rot = glam::DQuat::from_rotation_z(degrees.to_radians());
        Camera { eye: self.target + rot * (self.eye - self.target), up: rot * self.up, ..*self }
    }

    /// Checks that the camera defines a frame that renders: finite, within +-[`MAX_CAMERA_COORD`],
    /// eye != target, up not parallel, 0 < fov < 180.
    pub fn validate(&self) -> Result<(), CameraError> {
        for (name, v) in [("eye", self.eye), ("target", self.target), ("up", self.up)] {
            if !v.is_finite() {
                return Err(CameraError::NotFinite(name));
            }
            check_range(name, v)?;
        }
        if !(self.fov_y_deg > 0.0 && self.fov_y_deg < 180.0) {
            return Err(CameraError::BadFov(self.fov_y_deg));
        }
        let d = self.target - self.eye;
        if d.length() <= 1e-12 * (1.0 + self.eye.length()) {
            return Err(CameraError::EyeIsTarget(self.eye));
        }
        let f = d.normalize();
        if f.cross(self.up).length() <= 1e-9 * self.up.length().max(1e-300) {
            return Err(CameraError::UpParallel { up: self.up, forward: f });
        }
        Ok(())
    }

    /// The camera frame. Call [`Camera::validate`] first; a degenerate camera gives NaNs here.
    pub fn basis(&self) -> Basis {
        let forward = (self.target - self.eye).normalize();
        let right = forward.cross(self.up).normalize();
        let up = right.cross(forward);
        Basis { forward, right, up, tan_half_fov: (self.fov_y_deg.to_radians() * 0.5).tan() }
    }

    /// A camera that frames an axis-aligned box: a three-quarter view from the front-right and
    /// above (world up is +z), at the distance where all eight corners fit a `width` x `height`
    /// image with a 5% margin.
    pub fn framing(box_min: DVec3, box_max: DVec3, width: u32, height: u32) -> Camera {
        let centre = 0.5 * (box_min + box_max);
        Camera::framing_towards(
            box_min,
            box_max,
            centre,
            THREE_QUARTER_SIDE.normalize(),
            DVec3::Z,
            DEFAULT_FOV_Y_DEG,
            width,
            height,
        )
    }

    /// The framing rule: a camera looking at `target` from the `side` direction (a unit world
    /// vector from the target towards the eye) with `up` and `fov_y_deg`, at the least distance
    /// where all eight corners of the box fit a `width` x `height` image with a 5% margin and the
    /// whole box (its bounding sphere, widened by the target's distance from its centre) stays in
    /// front of the eye. An `up` parallel to `side` or a bad field of view gives the camera at
    /// distance 1 (the caller's validation says what is wrong).
    #[allow(clippy::too_many_arguments)]
    pub fn framing_towards(
        box_min: DVec3,
        box_max: DVec3,
        target: DVec3,
        side: DVec3,
        up: DVec3,
        fov_y_deg: f64,
        width: u32,
        height: u32,
    ) -> Camera {
        let mut cam = Camera { eye: target + side, target, up, fov_y_deg };
        // The frame alone (at the origin: a far box's coordinates are the caller's to check).
        if (Camera { eye: side, target: DVec3::ZERO, up, fov_y_deg }).validate().is_err() {
            return cam;
        }
        let b = cam.basis();
        let tan_y = 0.95 * b.tan_half_fov;
        let tan_x = tan_y * width as f64 / height.max(1) as f64;
        // Corner c at lateral offsets (x, y) and depth z from the target fits when
        // |x| / (dist + z) <= tan_x and |y| / (dist + z) <= tan_y.
        let floor = framing_floor(box_min, box_max);
        let mut dist: f64 = floor;
        for corner in corners(box_min, box_max) {
            let c = corner - target;
            let z = c.dot(b.forward);
            dist = dist.max(c.dot(b.right).abs() / tan_x - z).max(c.dot(b.up).abs() / tan_y - z);
        }
        // Keep the eye outside the box's bounding sphere, so the whole box is in front of it.
        let centre = 0.5 * (box_min + box_max);
        let reach = 0.5 * (box_max - box_min).length() + (target - centre).length();
        dist = dist.max(1.01 * reach.max(floor));
        cam.eye = target - dist * b.forward;
        cam
    }

    /// The default camera for a scene: looking at the centre of `fit` (the box to frame: the
    /// object's at the current iso, [`isowall_volume::BlockMinMax::object_box`], or the volume's)
    /// from [`default_side`]'s direction, framed by [`Camera::framing_towards`].
    pub fn framing_view(
        fit: (DVec3, DVec3),
        view: Option<ViewPreset>,
        orientation: Option<Orientation>,
        width: u32,
        height: u32,
    ) -> Camera {
        let (side, up) = default_side(view, orientation);
        let centre = 0.5 * (fit.0 + fit.1);
        Camera::framing_towards(fit.0, fit.1, centre, side, up, DEFAULT_FOV_Y_DEG, width, height)
    }
}

/// What a named view frames, kept by a session that offers the views: the box to frame (the
/// object's at the iso, or the volume's), the volume's patient orientation and the image size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewFraming {
    pub fit: (DVec3, DVec3),
    pub orientation: Option<Orientation>,
    pub size: (u32, u32),
}

impl ViewFraming {
    /// The camera of `view` with `fov_y_deg`, looking at the centre of the box and framing it
    /// ([`Camera::framing_towards`]).
    pub fn camera(&self, view: ViewPreset, fov_y_deg: f64) -> Camera {
        let (side, up) = view.directions(self.orientation);
        let (lo, hi) = self.fit;
        Camera::framing_towards(lo, hi, 0.5 * (lo + hi), side, up, fov_y_deg, self.size.0, self.size.1)
    }
}

/// The vertical field of view of a framing, degrees.
pub const DEFAULT_FOV_Y_DEG: f64 = 35.0;

/// The three-quarter view's side (not normalised): front-right and above, with world up +z.
const THREE_QUARTER_SIDE: DVec3 = DVec3::new(0.9, -1.5, 0.8);

/// Where a default camera looks from (`side`, a unit vector from the target towards the eye)
/// and its `up`: the named `view` where one is given; else, for a volume with a patient
/// orientation, [`ViewPreset::Anterior`] (the face, superior up); else the three-quarter view
/// from the front-right and above (world up +z), Isowall's default before orientations.
pub fn default_side(view: Option<ViewPreset>, orientation: Option<Orientation>) -> (DVec3, DVec3) {
    match (view, orientation) {
        (Some(v), o) => v.directions(o),
        (None, Some(o)) => ViewPreset::Anterior.directions(Some(o)),
        (None, None) => (THREE_QUARTER_SIDE.normalize(), DVec3::Z),
    }
}

/// A view of the volume from one side of the patient: the one list of view names, for the
/// command line, the config, the controller's keys and the console.
///
/// `anterior`: the eye in front of the face looking posterior, superior up; `posterior` from
/// behind, superior up; `left` / `right` from the patient's left / right side, superior up;
/// `superior` from above, anterior up; `inferior` from below, anterior up. Where the volume has
/// no orientation, the names mean the world axes read as LPS ([`Orientation::ASSUMED`], DICOM's
/// patient frame with world up +z): anterior looks from -y, posterior from +y, left from +x,
/// right from -x, superior from +z, inferior from -z.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ViewPreset {
    Anterior,
    Posterior,
    Left,
    Right,
    Superior,
    Inferior,
}

impl ViewPreset {
    pub const ALL: [ViewPreset; 6] = [
        ViewPreset::Anterior,
        ViewPreset::Posterior,
        ViewPreset::Left,
        ViewPreset::Right,
        ViewPreset::Superior,
        ViewPreset::Inferior,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ViewPreset::Anterior => "anterior",
            ViewPreset::Posterior => "posterior",
            ViewPreset::Left => "left",
            ViewPreset::Right => "right",
            ViewPreset::Superior => "superior",
            ViewPreset::Inferior => "inferior",
        }
    }

    /// Every name, `|`-separated, for messages and help.
    pub fn names() -> String {
        ViewPreset::ALL.map(ViewPreset::name).join("|")
    }

    /// The patient side the eye is on and the patient direction that is up on the screen.
    pub fn patient_side_and_up(self) -> (PatientDir, PatientDir) {
        use PatientDir::*;
        match self {
            ViewPreset::Anterior => (Anterior, Superior),
            ViewPreset::Posterior => (Posterior, Superior),
            ViewPreset::Left => (Left, Superior),
            ViewPreset::Right => (Right, Superior),
            ViewPreset::Superior => (Superior, Anterior),
            ViewPreset::Inferior => (Inferior, Anterior),
        }
    }

    /// The world directions of [`ViewPreset::patient_side_and_up`] for a volume of `orientation`
    /// ([`Orientation::ASSUMED`] where it has none): (side, a unit vector from the target
    /// towards the eye; up).
    pub fn directions(self, orientation: Option<Orientation>) -> (DVec3, DVec3) {
        let o = orientation.unwrap_or(Orientation::ASSUMED);
        let (side, up) = self.patient_side_and_up();
        (o.world_dir(side), o.world_dir(up))
    }
}

impl std::fmt::Display for ViewPreset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A view name that is none of [`ViewPreset::names`].
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("unknown view '{0}': one of {names}", names = ViewPreset::names())]
pub struct UnknownView(pub String);

impl std::str::FromStr for ViewPreset {
    type Err = UnknownView;
    fn from_str(s: &str) -> Result<ViewPreset, UnknownView> {
        ViewPreset::ALL.into_iter().find(|v| v.name() == s).ok_or_else(|| UnknownView(s.to_string()))
    }
}

/// The eight corners of the axis-aligned box `[lo, hi]`.
pub fn corners(lo: DVec3, hi: DVec3) -> [DVec3; 8] {
    std::array::from_fn(|i| {
        DVec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        )
    })
}

/// A rectangle of pixels inside the full image: `x, y` its top-left pixel, `width x height` its size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl Rect {
    /// The rectangle grown by `by` pixels on every side, clipped to a full image of `full` =
    /// (W, H) pixels: the guard band a tile renders (and, in object space, composites) beyond its
    /// edges so that the edge-aware filter, whose reach is `by`, sees there what the whole image
    /// has. The one rule for it: screen space's tile work area and object space's tile canvas are
    /// both this.
    pub fn grown(&self, by: u32, full: (u32, u32)) -> Rect {
        let (x0, y0) = (self.x.saturating_sub(by), self.y.saturating_sub(by));
        let x1 = self.x.saturating_add(self.width).saturating_add(by).min(full.0);
        let y1 = self.y.saturating_add(self.height).saturating_add(by).min(full.1);
        Rect { x: x0, y: y0, width: x1.saturating_sub(x0), height: y1.saturating_sub(y0) }
    }
}

/// A camera looking at a full image of `full` = (W, H) pixels, of which `rect` is rendered.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct View {
    pub camera: Camera,
    pub full: (u32, u32),
    pub rect: Rect,
}

impl View {
    /// The whole image of `width` x `height` pixels.
    pub fn whole(camera: Camera, width: u32, height: u32) -> View {
        View { camera, full: (width, height), rect: Rect { x: 0, y: 0, width, height } }
    }

    /// Number of pixels rendered (the rectangle's).
    pub fn pixel_count(&self) -> usize {
        self.rect.width as usize * self.rect.height as usize
    }

    /// The unit ray direction through the centre of pixel (px, py) of the *full* image.
    pub fn ray_dir_full(&self, basis: &Basis, px: u32, py: u32) -> DVec3 {
        let (w, h) = (self.full.0 as f64, self.full.1 as f64);
        let sx = ((px as f64 + 0.5) / w * 2.0 - 1.0) * basis.tan_half_fov * w / h;
        let sy = (1.0 - (py as f64 + 0.5) / h * 2.0) * basis.tan_half_fov;
        (basis.forward + sx * basis.right + sy * basis.up).normalize()
    }

    /// The four planes through the eye that bound the rays of the rectangle's pixels (its edges
    /// in the full image), each as (n, d) with `n . p + d >= 0` on the rays' side: together the
    /// cone of what the rectangle can see (nothing behind the eye). Call [`Camera::validate`]
    /// first.
    pub fn side_planes(&self) -> [(DVec3, f64); 4] {
        let b = self.camera.basis();
        let (w, h) = (self.full.0 as f64, self.full.1 as f64);
        let at = |x: f64, y: f64| {
            let sx = (x / w * 2.0 - 1.0) * b.tan_half_fov * w / h;
            let sy = (1.0 - y / h * 2.0) * b.tan_half_fov;
            b.forward + sx * b.right + sy * b.up
        };
        let r = self.rect;
        let (x0, y0) = (f64::from(r.x), f64::from(r.y));
        let (x1, y1) = (x0 + f64::from(r.width), y0 + f64::from(r.height));
        let corners = [at(x0, y0), at(x1, y0), at(x1, y1), at(x0, y1)];
        let inside = corners.iter().copied().sum::<DVec3>();
        std::array::from_fn(|i| {
            let n = corners[i].cross(corners[(i + 1) % 4]).normalize();
            let n = if n.dot(inside) < 0.0 { -n } else { n };
            (n, -n.dot(self.camera.eye))
        })
    }

    /// The unit ray direction through the centre of pixel (x, y) of the *rectangle*.
    pub fn ray_dir(&self, basis: &Basis, x: u32, y: u32) -> DVec3 {
        self.ray_dir_full(basis, self.rect.x + x, self.rect.y + y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rectangles_side_planes_hold_its_pixels_rays_and_nothing_behind_the_eye() {
        let camera = Camera {
            eye: DVec3::new(3.0, -40.0, 7.0),
            target: DVec3::new(1.0, 2.0, 3.0),
            up: DVec3::Z,
            fov_y_deg: 35.0,
        };
        let full = View::whole(camera, 64, 48);
        let view = View { rect: Rect { x: 10, y: 20, width: 16, height: 8 }, ..full };
        let planes = view.side_planes();
        let b = camera.basis();
        let inside = |p: DVec3| planes.iter().all(|(n, d)| n.dot(p) + d >= -1e-9);
        for y in 0..48 {
            for x in 0..64 {
                let p = camera.eye + 10.0 * full.ray_dir_full(&b, x, y);
                let mine = (10..26).contains(&x) && (20..28).contains(&y);
                assert_eq!(inside(p), mine, "pixel ({x}, {y})");
            }
        }
        assert!(!inside(camera.eye - 10.0 * view.ray_dir(&b, 3, 3)), "behind the eye");
    }

    #[test]
    fn a_grown_rect_is_clipped_at_every_edge_of_the_image_and_the_same_at_zero() {
        let full = (100, 80);
        let r = |x, y, width, height| Rect { x, y, width, height };
        // Inside: grown on all four sides.
        assert_eq!(r(20, 30, 10, 5).grown(7, full), r(13, 23, 24, 19));
        // At the left and top edges: clipped at 0.
        assert_eq!(r(3, 2, 10, 5).grown(7, full), r(0, 0, 20, 14));
        // At the right and bottom edges: clipped at the image's size.
        assert_eq!(r(85, 70, 10, 5).grown(7, full), r(78, 63, 22, 17));
        // The whole image grows into nothing; a band wider than the image is the image.
        assert_eq!(r(0, 0, 100, 80).grown(62, full), r(0, 0, 100, 80));
        assert_eq!(r(40, 40, 1, 1).grown(u32::MAX, full), r(0, 0, 100, 80));
        for rect in [r(0, 0, 100, 80), r(3, 2, 10, 5), r(85, 70, 15, 10), r(99, 79, 1, 1)] {
            assert_eq!(rect.grown(0, full), rect, "the identity at 0");
        }
    }

    #[test]
    fn pixel_rays_match_the_convention_vectors() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared/conventions/camera-and-hits.json");
        let Ok(text) = std::fs::read_to_string(path) else {
            assert!(std::env::var("CI").as_deref() != Ok("true"), "{path} missing under CI=true");
            eprintln!("skipping: {path} not found (the shared/ folder is beside the checkout only in CI and for developers)");
            return;
        };
        let j: serde_json::Value = serde_json::from_str(&text).unwrap();
        let v3 = |v: &serde_json::Value| {
            DVec3::new(v[0].as_f64().unwrap(), v[1].as_f64().unwrap(), v[2].as_f64().unwrap())
        };
        let cam = &j["camera"];
        let camera = Camera {
            eye: v3(&cam["eye"]),
            target: v3(&cam["target"]),
            up: v3(&cam["up"]),
            fov_y_deg: cam["fov_y_deg"].as_f64().unwrap(),
        };
        camera.validate().unwrap();
        let (w, h) = (cam["width"].as_u64().unwrap() as u32, cam["height"].as_u64().unwrap() as u32);
        let view = View::whole(camera, w, h);
        let basis = camera.basis();
        let pixels = j["pixels"].as_array().unwrap();
        assert!(pixels.len() >= 5);
        for p in pixels {
            let (px, py) = (p["px"].as_u64().unwrap() as u32, p["py"].as_u64().unwrap() as u32);
            let want = v3(&p["dir"]);
            let got = view.ray_dir_full(&basis, px, py);
            assert!((got - want).length() < 1e-8, "pixel ({px},{py}): got {got:?}, want {want:?}");
        }
    }

    #[test]
    fn a_rect_sees_the_same_rays_as_the_whole_image() {
        let camera =
            Camera { eye: DVec3::new(3.0, -7.0, 2.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 40.0 };
        let whole = View::whole(camera, 64, 48);
        let tile = View { rect: Rect { x: 32, y: 24, width: 32, height: 24 }, ..whole };
        let b = camera.basis();
        assert_eq!(tile.ray_dir(&b, 3, 5), whole.ray_dir_full(&b, 35, 29));
        assert_ne!(tile.ray_dir(&b, 3, 5), whole.ray_dir_full(&b, 3, 5));
    }

    #[test]
    fn degenerate_cameras_are_rejected() {
        let ok =
            Camera { eye: DVec3::new(0.0, -5.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 30.0 };
        assert!(ok.validate().is_ok());
        assert!(matches!(Camera { target: ok.eye, ..ok }.validate(), Err(CameraError::EyeIsTarget(_))));
        assert!(matches!(Camera { up: DVec3::Y, ..ok }.validate(), Err(CameraError::UpParallel { .. })));
        assert!(matches!(Camera { fov_y_deg: 180.0, ..ok }.validate(), Err(CameraError::BadFov(_))));
        assert!(matches!(Camera { eye: DVec3::NAN, ..ok }.validate(), Err(CameraError::NotFinite("eye"))));
        // Finite in f64, infinite (1e39) or a world unit a step (past 1e7) in the GPU's f32.
        for far in [1e39, 2.0 * MAX_CAMERA_COORD] {
            let e = Camera { eye: DVec3::new(far, 0.0, 0.0), ..ok }.validate().unwrap_err();
            assert!(matches!(e, CameraError::OutOfRange { field: "eye", .. }), "{e}");
            assert!(e.to_string().contains("f32"), "{e}");
            let e = Camera { target: DVec3::new(0.0, 0.0, -far), ..ok }.validate().unwrap_err();
            assert!(matches!(e, CameraError::OutOfRange { field: "target", .. }), "{e}");
        }
        assert!(Camera { eye: DVec3::new(MAX_CAMERA_COORD, 0.0, 0.0), ..ok }.validate().is_ok());
    }

    /// A box of any scale is framed alike: the eye's distance scales with it (at 1e-9 world units
    /// a voxel an absolute floor of 1e-6 left the volume a pixel or two of the image).
    #[test]
    fn framing_scales_with_the_box() {
        let hi = DVec3::new(31.0, 31.0, 31.0);
        let unit = Camera::framing(DVec3::ZERO, hi, 64, 48);
        for k in [1e-12, 1e-9, 1e6] {
            let cam = Camera::framing(DVec3::ZERO, k * hi, 64, 48);
            let ratio = (cam.eye - cam.target).length() / ((unit.eye - unit.target).length() * k);
            assert!((ratio - 1.0).abs() < 1e-6, "scale {k}: distance ratio {ratio}");
        }
    }

    #[test]
    fn framing_keeps_the_box_in_view() {
        let (lo, hi) = (DVec3::ZERO, DVec3::new(255.0, 255.0, 117.0));
        for (w, h) in [(64, 64), (128, 32), (32, 128)] {
            let cam = Camera::framing(lo, hi, w, h);
            cam.validate().unwrap();
            let b = cam.basis();
            let tan_x = b.tan_half_fov * w as f64 / h as f64;
            for c in corners(lo, hi) {
                let v = c - cam.eye;
                let z = v.dot(b.forward);
                assert!(z > 0.0);
                assert!(v.dot(b.right).abs() / z <= tan_x, "corner {c:?} outside horizontally for {w}x{h}");
                assert!(
                    v.dot(b.up).abs() / z <= b.tan_half_fov,
                    "corner {c:?} outside vertically for {w}x{h}"
                );
            }
        }
    }

    /// Each view looks from its side of the patient with its up, in a volume's own orientation
    /// and, where it has none, in the world axes read as LPS.
    #[test]
    fn views_look_from_their_patient_side() {
        use PatientDir::*;
        let (lo, hi) = (DVec3::ZERO, DVec3::new(40.0, 30.0, 20.0));
        let centre = 0.5 * (lo + hi);
        // No orientation: LPS world axes.
        let lps = [
            (ViewPreset::Anterior, -DVec3::Y, DVec3::Z),
            (ViewPreset::Posterior, DVec3::Y, DVec3::Z),
            (ViewPreset::Left, DVec3::X, DVec3::Z),
            (ViewPreset::Right, -DVec3::X, DVec3::Z),
            (ViewPreset::Superior, DVec3::Z, -DVec3::Y),
            (ViewPreset::Inferior, -DVec3::Z, -DVec3::Y),
        ];
        // A RAS volume whose z runs inferior (a flipped NIfTI).
        let rai = Orientation::new([Right, Anterior, Inferior]).unwrap();
        let ras_flipped = [
            (ViewPreset::Anterior, DVec3::Y, -DVec3::Z),
            (ViewPreset::Left, -DVec3::X, -DVec3::Z),
            (ViewPreset::Superior, -DVec3::Z, DVec3::Y),
        ];
        for (orientation, cases) in [(None, &lps[..]), (Some(rai), &ras_flipped[..])] {
            for &(view, side, up) in cases {
                let cam = Camera::framing_view((lo, hi), Some(view), orientation, 64, 48);
                cam.validate().unwrap();
                assert_eq!(cam.target, centre);
                let to_eye = (cam.eye - cam.target).normalize();
                assert!((to_eye - side).length() < 1e-12, "{view} {orientation:?}: eye towards {to_eye}");
                assert_eq!(cam.up, up, "{view} {orientation:?}");
            }
        }
        // Looking at the face from the anterior, the patient's left is on the screen's right.
        let cam = Camera::framing_view((lo, hi), Some(ViewPreset::Anterior), None, 64, 48);
        assert!(cam.basis().right.dot(Orientation::ASSUMED.world_dir(Left)) > 0.99);
        // The default: an oriented scan opens anterior, superior up; one without keeps the
        // three-quarter view of `framing`.
        let oriented = Camera::framing_view((lo, hi), None, Some(rai), 64, 48);
        assert_eq!(oriented, Camera::framing_view((lo, hi), Some(ViewPreset::Anterior), Some(rai), 64, 48));
        let plain = Camera::framing_view((lo, hi), None, None, 64, 48);
        let old = Camera::framing(lo, hi, 64, 48);
        assert!((plain.eye - old.eye).length() < 1e-9 && plain.target == old.target && plain.up == old.up);
    }

    #[test]
    fn view_names_round_trip_and_unknown_names_list_them() {
        for v in ViewPreset::ALL {
            assert_eq!(v.name().parse::<ViewPreset>(), Ok(v));
        }
        let e = "front".parse::<ViewPreset>().unwrap_err().to_string();
        assert_eq!(e, "unknown view 'front': one of anterior|posterior|left|right|superior|inferior");
    }

    /// Framing a sub-box fills the image with it: the box's projected extent reaches the 5%
    /// margin on one side, where framing the whole volume leaves it small.
    #[test]
    fn framing_a_sub_box_fills_the_image_with_it() {
        let (vlo, vhi) = (DVec3::ZERO, DVec3::new(100.0, 100.0, 100.0));
        let (lo, hi) = (DVec3::new(40.0, 45.0, 30.0), DVec3::new(60.0, 55.0, 50.0));
        let extent = |cam: &Camera, w: u32, h: u32| {
            let b = cam.basis();
            let tan_x = b.tan_half_fov * w as f64 / h as f64;
            let mut m: f64 = 0.0;
            for c in corners(lo, hi) {
                let v = c - cam.eye;
                let z = v.dot(b.forward);
                m = m.max(v.dot(b.right).abs() / z / tan_x).max(v.dot(b.up).abs() / z / b.tan_half_fov);
            }
            m
        };
        for view in [None, Some(ViewPreset::Anterior), Some(ViewPreset::Superior)] {
            let sub = Camera::framing_view((lo, hi), view, None, 64, 48);
            let whole = Camera::framing_view((vlo, vhi), view, None, 64, 48);
            let (fs, fw) = (extent(&sub, 64, 48), extent(&whole, 64, 48));
            assert!((fs - 0.95).abs() < 1e-9, "{view:?}: the sub-box reaches {fs} of the half-image");
            assert!(fw < 0.5, "{view:?}: framed with the volume, the sub-box reaches only {fw}");
            assert_eq!(sub.target, 0.5 * (lo + hi));
        }
    }
}
