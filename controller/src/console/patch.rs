//! The changes `POST /api/render`, `POST /api/camera` and `POST /api/time` ask for, and how they
//! apply to the console's [`Controls`]: validated first (the render settings by the config's own rules,
//! [`isowall_model::config::render_problems`]), applied only when all of it is valid, so a refused
//! request changes nothing.

use crate::controls::{SessionState, MAX_RATE, MIN_RATE};
use isowall_model::config::{render_problems, RenderConfig};
use isowall_model::{AoMethod, Camera, Denoise, IblMethod, RenderSettings, Shading, ViewPreset};
use serde::{Deserialize, Deserializer};

/// A refused change: the field it is about and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Refusal {
    pub field: &'static str,
    pub message: String,
}

impl Refusal {
    fn new(field: &'static str, message: impl Into<String>) -> Refusal {
        Refusal { field, message: message.into() }
    }
}

/// `POST /api/render`: any subset of the render settings, with the config's names and units.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderPatch {
    /// Data units, within the volume's value range.
    pub iso: Option<f64>,
    pub ao_samples: Option<u32>,
    pub ao_method: Option<AoMethod>,
    pub ibl: Option<IblMethod>,
    pub exposure: Option<f64>,
    pub shading: Option<Shading>,
    /// `"off"` | `"on"`: the spatial filter of the occlusion and IBL terms.
    pub denoise: Option<Denoise>,
    /// A number turns the quality governor on for that frame time; `null` turns it off.
    #[serde(default, deserialize_with = "present")]
    pub target_frame_ms: Option<Option<f64>>,
}

/// `Some(value)` for a field that is present (also `null`), `None` for one left out.
fn present<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Option<f64>>, D::Error> {
    Option::<f64>::deserialize(d).map(Some)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Play {
    Play,
    Pause,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DemoCommand {
    Start,
    Stop,
}

/// `POST /api/camera`: a camera set outright (eye, target, up, fov_y), moved (yaw, pitch,
/// zoom, as the session's keys do), reset to the config's, and the orbit and demo path played.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraPatch {
    /// A named view of the volume, framed (after `reset`, before the other fields apply):
    /// anterior | posterior | left | right | superior | inferior.
    pub view: Option<ViewPreset>,
    pub eye: Option<[f64; 3]>,
    pub target: Option<[f64; 3]>,
    pub up: Option<[f64; 3]>,
    pub fov_y: Option<f64>,
    /// Degrees about the world up axis through the target (+: counter-clockwise from above).
    pub yaw_deg: Option<f64>,
    /// Degrees up (+) or down about the target, stopping short of the poles.
    pub pitch_deg: Option<f64>,
    /// Distance factor (< 1: closer).
    pub zoom: Option<f64>,
    /// Back to the config's camera (before the other fields apply).
    #[serde(default)]
    pub reset: bool,
    pub orbit: Option<Play>,
    pub orbit_degrees_per_second: Option<f64>,
    pub demo: Option<DemoCommand>,
}

/// `POST /api/time`: a time-varying volume's playback (the session's [`Playback`]): the step
/// shown, play or pause, and the rate.
///
/// [`Playback`]: crate::controls::Playback
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimePatch {
    /// The step to show, 0 ..< the volume's steps (playing goes on from there).
    pub step: Option<u32>,
    pub play: Option<Play>,
    /// Steps per second while playing, MIN_RATE..=MAX_RATE.
    pub rate: Option<f64>,
}

/// What the operator controls: the session's camera, settings and time step, the governor's
/// target, the orbit and the demo path.
#[derive(Clone, Debug)]
pub struct Controls {
    pub session: SessionState,
    pub home: Camera,
    pub range: (f64, f64),
    pub env: String,
    pub target_frame_ms: Option<f64>,
    pub orbit: bool,
    pub orbit_degrees_per_second: f64,
    /// Whether a demo path was given, and whether it plays.
    pub demo_available: bool,
    pub demo: bool,
}

/// The largest orbit rate and single turn accepted, degrees.
const MAX_DEGREES: f64 = 360.0;

impl Controls {
    /// Applies `p` if all of it is valid; on a refusal nothing changes.
    pub fn apply_render(&mut self, p: &RenderPatch) -> Result<(), Refusal> {
        let mut s: RenderSettings = self.session.settings;
        let mut target = self.target_frame_ms;
        if let Some(iso) = p.iso {
            isowall_volume::check_iso(iso, self.range)
                .map_err(|e| Refusal::new("iso", format!("render: `iso` {e}")))?;
            s.iso = iso;
        }
        if let Some(n) = p.ao_samples {
            s.ao.samples = n;
        }
        if let Some(m) = p.ao_method {
            s.ao.method = m;
        }
        if let Some(m) = p.ibl {
            s.ao.ibl = m;
        }
        if let Some(x) = p.exposure {
            s.exposure = x;
        }
        if let Some(x) = p.shading {
            s.shading = x;
        }
        if let Some(d) = p.denoise {
            s.denoise = d;
        }
        if let Some(t) = p.target_frame_ms {
            target = t;
        }
        // The config's own rules, on the table these settings would be written as.
        let table = RenderConfig {
            shading: s.shading,
            ao_samples: s.ao.samples,
            ao_radius: s.ao.radius,
            ao_method: s.ao.method,
            ao_sequence: s.ao.sequence,
            ibl: s.ao.ibl,
            env: self.env.clone(),
            exposure: Some(s.exposure),
            target_frame_ms: target,
            denoise: s.denoise.into(),
        };
        if let Some((field, message)) = render_problems(&table).into_iter().next() {
            return Err(Refusal { field, message });
        }
        self.session.settings = s;
        self.target_frame_ms = target;
        Ok(())
    }

    /// Applies `p` if all of it is valid; on a refusal nothing changes.
    pub fn apply_camera(&mut self, p: &CameraPatch) -> Result<(), Refusal> {
        let mut next = self.clone();
        let c = &mut next.session.camera;
        if p.reset {
            *c = self.home;
        }
        if let Some(v) = p.view {
            if !next.session.view(v) {
                return Err(Refusal::new("view", "camera: `view`: no framing is known for this wall"));
            }
        }
        let c = &mut next.session.camera;
        let vec = |field: &'static str, v: [f64; 3]| {
            if v.iter().all(|x| x.is_finite()) {
                Ok(glam::DVec3::from_array(v))
            } else {
                Err(Refusal::new(field, format!("camera: `{field}` {v:?} is not three finite numbers")))
            }
        };
        if let Some(v) = p.eye {
            c.eye = vec("eye", v)?;
        }
        if let Some(v) = p.target {
            c.target = vec("target", v)?;
        }
        if let Some(v) = p.up {
            c.up = vec("up", v)?;
        }
        if let Some(f) = p.fov_y {
            c.fov_y_deg = f;
        }
        let turn = |field: &'static str, x: f64| {
            if x.is_finite() && x.abs() <= MAX_DEGREES {
                Ok(x)
            } else {
                Err(Refusal::new(
                    field,
                    format!("camera: `{field}` {x} is not a number of degrees in [-360, 360]"),
                ))
            }
        };
        if let Some(x) = p.yaw_deg {
            next.session.orbit_yaw(turn("yaw_deg", x)?);
        }
        if let Some(x) = p.pitch_deg {
            next.session.orbit_pitch(turn("pitch_deg", x)?);
        }
        if let Some(z) = p.zoom {
            if !(z.is_finite() && z > 0.0 && z <= 100.0) {
                return Err(Refusal::new("zoom", format!("camera: `zoom` {z} is not a factor in (0, 100]")));
            }
            next.session.zoom(z);
        }
        next.session.camera.validate().map_err(|e| Refusal::new("camera", format!("camera: {e}")))?;
        if let Some(r) = p.orbit_degrees_per_second {
            next.orbit_degrees_per_second = turn("orbit_degrees_per_second", r)?;
        }
        if let Some(play) = p.orbit {
            next.orbit = play == Play::Play;
        }
        match p.demo {
            Some(DemoCommand::Start) if !self.demo_available => {
                return Err(Refusal::new(
                    "demo",
                    "no demo path: start the console with --demo-path FILE (keyframes in TOML)",
                ))
            }
            Some(d) => next.demo = d == DemoCommand::Start,
            None => {}
        }
        *self = next;
        Ok(())
    }
}

impl Controls {
    /// Applies `p` if all of it is valid; on a refusal nothing changes.
    pub fn apply_time(&mut self, p: &TimePatch) -> Result<(), Refusal> {
        let mut next = self.session.playback;
        let steps = next.steps;
        if let Some(step) = p.step {
            if step >= steps {
                return Err(Refusal::new(
                    "step",
                    format!(
                        "time: `step` {step} is out of range: the volume has {steps} time step{} (0..={})",
                        if steps == 1 { "" } else { "s" },
                        steps - 1
                    ),
                ));
            }
            next.show(step);
        }
        if let Some(rate) = p.rate {
            if !(rate.is_finite() && (MIN_RATE..=MAX_RATE).contains(&rate)) {
                return Err(Refusal::new(
                    "rate",
                    format!(
                        "time: `rate` {rate} is not a number of steps per second in [{MIN_RATE}, {MAX_RATE}]"
                    ),
                ));
            }
            next.rate = rate;
        }
        match p.play {
            Some(Play::Play) if steps < 2 => {
                return Err(Refusal::new(
                    "play",
                    "time: the volume has one time step, nothing to play (a glob of steps or a 4-D file has more)",
                ))
            }
            Some(play) => next.playing = play == Play::Play,
            None => {}
        }
        self.session.playback = next;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    fn controls() -> Controls {
        let cam =
            Camera { eye: DVec3::new(10.0, 0.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 35.0 };
        Controls {
            session: SessionState::new(cam, RenderSettings::new(0.5), (0.0, 2.0)),
            home: cam,
            range: (0.0, 2.0),
            env: "sky".into(),
            target_frame_ms: None,
            orbit: false,
            orbit_degrees_per_second: 20.0,
            demo_available: false,
            demo: false,
        }
    }

    fn render(json: &str) -> RenderPatch {
        serde_json::from_str(json).unwrap()
    }

    #[test]
    fn a_valid_render_patch_changes_only_what_it_names() {
        let mut c = controls();
        c.apply_render(&render(r#"{"iso": 1.25, "ao_samples": 32, "ibl": "rays", "ao_method": "seed"}"#))
            .unwrap();
        let s = c.session.settings;
        assert_eq!((s.iso, s.ao.samples, s.ao.ibl, s.ao.method), (1.25, 32, IblMethod::Rays, AoMethod::Seed));
        assert_eq!(s.exposure, RenderSettings::new(0.5).exposure);
        c.apply_render(&render(r#"{"target_frame_ms": 40}"#)).unwrap();
        assert_eq!(c.target_frame_ms, Some(40.0));
        c.apply_render(&render(r#"{"exposure": 0.8}"#)).unwrap();
        assert_eq!(c.target_frame_ms, Some(40.0), "left out: unchanged");
        c.apply_render(&render(r#"{"target_frame_ms": null}"#)).unwrap();
        assert_eq!(c.target_frame_ms, None);
        assert_eq!(c.session.settings.denoise, Denoise::Off);
        c.apply_render(&render(r#"{"denoise": "on"}"#)).unwrap();
        assert_eq!(c.session.settings.denoise, Denoise::On);
        assert_eq!(c.session.settings.exposure, 0.8, "left out: unchanged");
        let e = serde_json::from_str::<RenderPatch>(r#"{"denoise": "maybe"}"#).unwrap_err().to_string();
        assert!(e.contains("unknown variant `maybe`"), "{e}");
    }

    #[test]
    fn an_invalid_render_patch_names_its_field_and_changes_nothing() {
        let cases = [
            (r#"{"iso": 2.5, "ao_samples": 4}"#, "iso", "outside the volume's value range [0, 2]"),
            (r#"{"ao_samples": 5000, "iso": 1.0}"#, "ao_samples", "`ao_samples` 5000 is more than 1024"),
            (r#"{"exposure": -1}"#, "exposure", "`exposure` -1 must be a finite number >= 0"),
            (r#"{"target_frame_ms": 0}"#, "target_frame_ms", "`target_frame_ms`: target frame time 0 ms"),
        ];
        for (json, field, says) in cases {
            let mut c = controls();
            let before = c.session;
            let e = c.apply_render(&render(json)).unwrap_err();
            assert_eq!(e.field, field, "{json}: {e:?}");
            assert!(e.message.contains(says), "{json}: {}", e.message);
            assert_eq!(c.session, before, "{json} changed something");
        }
        let e = serde_json::from_str::<RenderPatch>(r#"{"isovalue": 1}"#).unwrap_err().to_string();
        assert!(e.contains("unknown field `isovalue`"), "{e}");
        let e = serde_json::from_str::<RenderPatch>(r#"{"ibl": "mirror"}"#).unwrap_err().to_string();
        assert!(e.contains("unknown variant `mirror`"), "{e}");
    }

    #[test]
    fn camera_patches_move_set_and_refuse() {
        let mut c = controls();
        let p: CameraPatch = serde_json::from_str(r#"{"yaw_deg": 90, "orbit": "play"}"#).unwrap();
        c.apply_camera(&p).unwrap();
        assert!(
            (c.session.camera.eye - DVec3::new(0.0, 10.0, 0.0)).length() < 1e-9,
            "{}",
            c.session.camera.eye
        );
        assert!(c.orbit);
        let p: CameraPatch =
            serde_json::from_str(r#"{"reset": true, "zoom": 0.5, "orbit": "pause"}"#).unwrap();
        c.apply_camera(&p).unwrap();
        assert!((c.session.camera.eye - DVec3::new(5.0, 0.0, 0.0)).length() < 1e-9);
        assert!(!c.orbit);
        let before = c.session;
        for (json, field) in [
            (r#"{"eye": [0, 0, 0], "yaw_deg": 10}"#, "camera"),
            (r#"{"fov_y": 200}"#, "camera"),
            (r#"{"zoom": -1}"#, "zoom"),
            (r#"{"yaw_deg": 1e9}"#, "yaw_deg"),
            (r#"{"demo": "start"}"#, "demo"),
        ] {
            let p: CameraPatch = serde_json::from_str(json).unwrap();
            let e = c.apply_camera(&p).unwrap_err();
            assert_eq!(e.field, field, "{json}: {e:?}");
            assert_eq!(c.session, before, "{json} changed something");
        }
        c.demo_available = true;
        c.apply_camera(&serde_json::from_str(r#"{"demo": "start"}"#).unwrap()).unwrap();
        assert!(c.demo);
    }

    #[test]
    fn a_view_patch_frames_the_box_then_the_other_fields_apply() {
        let mut c = controls();
        let p: CameraPatch = serde_json::from_str(r#"{"view": "left"}"#).unwrap();
        let before = c.session;
        assert_eq!(c.apply_camera(&p).unwrap_err().field, "view", "no framing known");
        assert_eq!(c.session, before);
        let fit = (DVec3::splat(-1.0), DVec3::splat(1.0));
        c.session.framing = Some(isowall_model::ViewFraming { fit, orientation: None, size: (64, 48) });
        c.apply_camera(&p).unwrap();
        let cam = c.session.camera;
        assert!((cam.eye - cam.target).normalize().x > 0.999, "left looks from +x: {cam:?}");
        let p: CameraPatch = serde_json::from_str(r#"{"view": "anterior", "fov_y": 20}"#).unwrap();
        c.apply_camera(&p).unwrap();
        let cam = c.session.camera;
        assert!((cam.eye - cam.target).normalize().y < -0.999 && cam.fov_y_deg == 20.0, "{cam:?}");
        let e = serde_json::from_str::<CameraPatch>(r#"{"view": "front"}"#).unwrap_err().to_string();
        assert!(e.contains("unknown variant `front`") && e.contains("`anterior`"), "{e}");
    }

    #[test]
    fn time_patches_show_play_and_refuse_naming_the_field() {
        let time = |json: &str| serde_json::from_str::<TimePatch>(json).unwrap();
        let mut c = controls();
        // One step: nothing to play, step 0 only.
        let e = c.apply_time(&time(r#"{"play": "play"}"#)).unwrap_err();
        assert_eq!(e.field, "play", "{e:?}");
        let e = c.apply_time(&time(r#"{"step": 1}"#)).unwrap_err();
        assert!(e.field == "step" && e.message.contains("has 1 time step (0..=0)"), "{e:?}");
        c.apply_time(&time(r#"{"step": 0, "play": "pause"}"#)).unwrap();
        c.session.playback.steps = 16;
        c.apply_time(&time(r#"{"step": 15, "play": "play", "rate": 8}"#)).unwrap();
        let p = c.session.playback;
        assert_eq!((p.step, p.playing, p.rate), (15, true, 8.0));
        let before = c.session;
        for (json, field, says) in [
            (
                r#"{"step": 16, "play": "pause"}"#,
                "step",
                "`step` 16 is out of range: the volume has 16 time steps (0..=15)",
            ),
            (
                r#"{"rate": 0, "step": 1}"#,
                "rate",
                "`rate` 0 is not a number of steps per second in [0.125, 240]",
            ),
            (r#"{"rate": -4}"#, "rate", "`rate` -4"),
            (r#"{"rate": 1e9, "play": "pause"}"#, "rate", "`rate` 1000000000"),
        ] {
            let e = c.apply_time(&time(json)).unwrap_err();
            assert_eq!(e.field, field, "{json}: {e:?}");
            assert!(e.message.contains(says), "{json}: {}", e.message);
            assert_eq!(c.session, before, "{json} changed something");
        }
        let e = serde_json::from_str::<TimePatch>(r#"{"steps": 3}"#).unwrap_err().to_string();
        assert!(e.contains("unknown field `steps`"), "{e}");
        c.apply_time(&time(r#"{"play": "pause", "step": 3}"#)).unwrap();
        assert_eq!((c.session.playback.step, c.session.playback.playing), (3, false));
    }
}
