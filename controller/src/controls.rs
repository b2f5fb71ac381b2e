//! The interactive session's logic, free of terminals and gamepads: which key does what, how a
//! gamepad axis moves the camera (dead zone, rates), and how each action changes the session's
//! camera and settings. `session.rs` is the thin glue that reads crossterm and gilrs.

use glam::{DQuat, DVec3};
use isowall_model::joystick::JoystickConfig;
use isowall_model::render_state::MAX_AO_SAMPLES;
use isowall_model::{Camera, Denoise, IblMethod, RenderSettings, ViewFraming, ViewPreset};

/// A key, as the session sees it (the glue converts terminal key events).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Key {
    Char(char),
    Left,
    Right,
    Up,
    Down,
    PageUp,
    PageDown,
    Esc,
    CtrlC,
}

/// What an operator can ask for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    /// Turn about the world up axis through the target (degrees, + = counter-clockwise from above).
    OrbitYaw(i8),
    /// Tilt the eye up (+) or down (-) about the target.
    OrbitPitch(i8),
    /// Move eye and target along the view's right (+x) and up (+y).
    Pan(i8, i8),
    /// Closer (+) or farther (-).
    Zoom(i8),
    Iso(i8),
    /// Double (+) or halve (-) the AO samples.
    AoSamples(i8),
    /// The next IBL method (none, seed, bent, rays).
    NextIbl,
    /// Turn the spatial filter of the occlusion and IBL terms on or off.
    ToggleDenoise,
    /// Time steps: play or pause.
    PlayPause,
    /// Time steps: one step on (+) or back (-).
    Step(i8),
    /// Time steps: double (+) or halve (-) the play rate.
    Rate(i8),
    /// Look from a side of the patient, framed ([`ViewPreset`]).
    View(ViewPreset),
    Screenshot,
    Quit,
}

/// The key help shown by `isowall session`.
pub const KEY_HELP: &str =
    "arrows/wasd orbit, ijkl pan, +/- zoom, ]/[ iso, >/< AO samples, b IBL, f denoise, space play/pause, n/N step, )/( rate, 1-6 view anterior/posterior/left/right/superior/inferior, p screenshot, q quit";

/// The view keys: `1` to `6` in the order of [`ViewPreset::ALL`].
fn view_key(c: char) -> Option<ViewPreset> {
    let i = c.to_digit(10)? as usize;
    (1..=ViewPreset::ALL.len()).contains(&i).then(|| ViewPreset::ALL[i - 1])
}

/// The action of a key, if any.
pub fn action_for_key(key: Key) -> Option<Action> {
    use Action::*;
    Some(match key {
        Key::Left | Key::Char('a') => OrbitYaw(-1),
        Key::Right | Key::Char('d') => OrbitYaw(1),
        Key::Up | Key::Char('w') => OrbitPitch(1),
        Key::Down | Key::Char('s') => OrbitPitch(-1),
        Key::Char('j') => Pan(-1, 0),
        Key::Char('l') => Pan(1, 0),
        Key::Char('i') => Pan(0, 1),
        Key::Char('k') => Pan(0, -1),
        Key::Char('+') | Key::Char('=') | Key::PageUp => Zoom(1),
        Key::Char('-') | Key::Char('_') | Key::PageDown => Zoom(-1),
        Key::Char(']') => Iso(1),
        Key::Char('[') => Iso(-1),
        Key::Char('>') | Key::Char('.') => AoSamples(1),
        Key::Char('<') | Key::Char(',') => AoSamples(-1),
        Key::Char('b') => NextIbl,
        Key::Char('f') => ToggleDenoise,
        Key::Char(' ') => PlayPause,
        Key::Char('n') => Step(1),
        Key::Char('N') => Step(-1),
        Key::Char(')') => Rate(1),
        Key::Char('(') => Rate(-1),
        Key::Char(c) if view_key(c).is_some() => View(view_key(c)?),
        Key::Char('p') => Screenshot,
        Key::Char('q') | Key::Esc | Key::CtrlC => Quit,
        _ => return None,
    })
}

/// Steps of one key press.
pub const ORBIT_STEP_DEG: f64 = 5.0;
pub const PAN_STEP: f64 = 0.05;
pub const ZOOM_STEP: f64 = 0.9;
/// The eye never comes closer to the up axis (through the target) than this, degrees.
const MIN_POLE_DEG: f64 = 2.0;

/// The camera, settings and time step a session drives.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SessionState {
    pub camera: Camera,
    pub settings: RenderSettings,
    /// One iso step (a hundredth of the volume's value range).
    pub iso_step: f64,
    /// The volume's value range: the iso keys stop at its ends (past them nothing, or the whole
    /// box, would be the surface).
    pub iso_range: (f64, f64),
    pub playback: Playback,
    /// What the named views frame; `None`: they are not offered.
    pub framing: Option<ViewFraming>,
}

impl SessionState {
    pub fn new(camera: Camera, settings: RenderSettings, value_range: (f64, f64)) -> Self {
        let span = (value_range.1 - value_range.0).abs();
        SessionState {
            camera,
            settings,
            iso_step: if span > 0.0 { span / 100.0 } else { 1e-3 },
            iso_range: (value_range.0.min(value_range.1), value_range.0.max(value_range.1)),
            playback: Playback::new(1, DEFAULT_RATE),
            framing: None,
        }
    }

    /// The camera of `view` with the current field of view, framed; `false` (nothing changes)
    /// where the session has no framing.
    pub fn view(&mut self, view: ViewPreset) -> bool {
        match self.framing {
            Some(f) => {
                self.camera = f.camera(view, self.camera.fov_y_deg);
                true
            }
            None => false,
        }
    }

    /// Turns the eye about the world up (+z) through the target.
    pub fn orbit_yaw(&mut self, degrees: f64) {
        self.camera = self.camera.yawed(degrees);
    }

    /// Tilts the eye about the view's right axis, stopping short of the poles.
    pub fn orbit_pitch(&mut self, degrees: f64) {
        let c = &mut self.camera;
        let offset = c.eye - c.target;
        let r = offset.length();
        let elevation = (offset.z / r).clamp(-1.0, 1.0).asin().to_degrees();
        let limit = 90.0 - MIN_POLE_DEG;
        let new = (elevation + degrees).clamp(-limit, limit);
        let right = DVec3::Z.cross(offset).normalize_or(DVec3::X);
        let rot = DQuat::from_axis_angle(right, -(new - elevation).to_radians());
        c.eye = c.target + rot * offset;
        c.up = DVec3::Z;
    }

    /// Moves eye and target together, by fractions of the distance.
    pub fn pan(&mut self, right: f64, up: f64) {
        let c = &mut self.camera;
        let forward = c.target - c.eye;
        let d = forward.length();
        let r = forward.cross(c.up).normalize_or(DVec3::X);
        let u = r.cross(forward).normalize_or(DVec3::Z);
        let shift = (r * right + u * up) * d;
        c.eye += shift;
        c.target += shift;
    }

    /// Scales the eye's distance to the target by `factor` (< 1: closer).
    pub fn zoom(&mut self, factor: f64) {
        let c = &mut self.camera;
        let offset = (c.eye - c.target) * factor;
        if offset.length() > 1e-3 {
            c.eye = c.target + offset;
        }
    }

    /// Applies one action; `true` if the session should quit (screenshots are the glue's).
    pub fn apply(&mut self, action: Action) -> bool {
        match action {
            Action::OrbitYaw(s) => self.orbit_yaw(ORBIT_STEP_DEG * s as f64),
            Action::OrbitPitch(s) => self.orbit_pitch(ORBIT_STEP_DEG * s as f64),
            Action::Pan(x, y) => self.pan(PAN_STEP * x as f64, PAN_STEP * y as f64),
            Action::Zoom(s) => self.zoom(if s > 0 { ZOOM_STEP } else { 1.0 / ZOOM_STEP }),
            Action::Iso(s) => {
                let (lo, hi) = self.iso_range;
                self.settings.iso = (self.settings.iso + self.iso_step * s as f64).clamp(lo, hi);
            }
            Action::AoSamples(s) => {
                let n = self.settings.ao.samples;
                self.settings.ao.samples = if s > 0 { (n * 2).clamp(1, MAX_AO_SAMPLES) } else { n / 2 };
            }
            Action::NextIbl => {
                self.settings.ao.ibl = match self.settings.ao.ibl {
                    IblMethod::None => IblMethod::Seed,
                    IblMethod::Seed => IblMethod::Bent,
                    IblMethod::Bent => IblMethod::Rays,
                    IblMethod::Rays => IblMethod::None,
                }
            }
            Action::ToggleDenoise => {
                self.settings.denoise = match self.settings.denoise {
                    Denoise::Off => Denoise::On,
                    Denoise::On => Denoise::Off,
                }
            }
            Action::PlayPause => self.playback.playing = !self.playback.playing,
            Action::Step(s) => self.playback.step_by(s as i32),
            Action::Rate(s) => self.playback.change_rate(s),
            Action::View(v) => {
                self.view(v);
            }
            Action::Screenshot => {}
            Action::Quit => return true,
        }
        false
    }

    /// Moves the camera by the gamepad's (dead-zoned) axes held for `dt` seconds.
    pub fn apply_axes(&mut self, axes: Axes, dt: f64, j: &JoystickConfig) {
        let (x, y, z) = (
            dead_zone(axes.orbit_x, j.dead_zone),
            dead_zone(axes.orbit_y, j.dead_zone),
            dead_zone(axes.zoom, j.dead_zone),
        );
        if x != 0.0 {
            self.orbit_yaw(-x * j.orbit_degrees_per_second * dt);
        }
        if y != 0.0 {
            self.orbit_pitch(y * j.orbit_degrees_per_second * dt);
        }
        if z != 0.0 {
            self.zoom((-z * j.zoom_per_second * dt).exp());
        }
    }
}

/// Playing a time-varying volume: the step shown, whether it plays, and at how many steps a
/// second. Pure: the frame loop passes the time that went by.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Playback {
    /// The volume's time steps (1: nothing to play).
    pub steps: u32,
    pub step: u32,
    pub playing: bool,
    /// Steps per second while playing.
    pub rate: f64,
    /// The part of a step played since `step` was shown, in steps (0 ..< 1).
    phase: f64,
}

/// The play rate a session starts with, steps per second.
pub const DEFAULT_RATE: f64 = 4.0;
/// The fastest and slowest play rates, steps per second.
pub const MAX_RATE: f64 = 240.0;
pub const MIN_RATE: f64 = 0.125;

impl Playback {
    /// Paused at step 0, at `rate` steps a second (clamped to MIN_RATE..=MAX_RATE).
    pub fn new(steps: u32, rate: f64) -> Playback {
        let rate = if rate.is_finite() { rate.clamp(MIN_RATE, MAX_RATE) } else { 1.0 };
        Playback { steps: steps.max(1), step: 0, playing: false, rate, phase: 0.0 }
    }

    /// Moves on by `dt` seconds of play (nothing while paused), wrapping at the last step.
    pub fn advance(&mut self, dt: f64) {
        if !(self.playing && dt.is_finite() && dt > 0.0) {
            return;
        }
        let total = self.phase + dt * self.rate;
        let whole = total.floor();
        self.phase = total - whole;
        self.step = ((self.step as u64 + whole as u64) % self.steps as u64) as u32;
    }

    /// One step on (+) or back (-), wrapping; the phase starts again.
    pub fn step_by(&mut self, delta: i32) {
        let n = self.steps as i64;
        self.step = (self.step as i64 + delta as i64).rem_euclid(n) as u32;
        self.phase = 0.0;
    }

    /// Shows `step` (wrapped into the steps); the phase starts again.
    pub fn show(&mut self, step: u32) {
        self.step = step % self.steps.max(1);
        self.phase = 0.0;
    }

    /// Doubles (+) or halves (-) the rate, within MIN_RATE..=MAX_RATE.
    pub fn change_rate(&mut self, sign: i8) {
        let r = if sign > 0 { self.rate * 2.0 } else { self.rate / 2.0 };
        self.rate = r.clamp(MIN_RATE, MAX_RATE);
    }
}

/// The gamepad's mapped axes, each in [-1, 1] (stick up and right positive).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Axes {
    pub orbit_x: f64,
    pub orbit_y: f64,
    pub zoom: f64,
}

/// 0 inside the dead zone; outside it, rescaled so the response starts at 0 and reaches ±1.
pub fn dead_zone(v: f64, zone: f64) -> f64 {
    if !v.is_finite() {
        return 0.0;
    }
    let v = v.clamp(-1.0, 1.0);
    if v.abs() <= zone {
        0.0
    } else {
        v.signum() * (v.abs() - zone) / (1.0 - zone)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state() -> SessionState {
        let cam =
            Camera { eye: DVec3::new(10.0, 0.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 35.0 };
        SessionState::new(cam, RenderSettings::new(0.5), (0.0, 2.0))
    }

    #[test]
    fn keys_map_to_actions() {
        assert_eq!(action_for_key(Key::Left), Some(Action::OrbitYaw(-1)));
        assert_eq!(action_for_key(Key::Char('w')), Some(Action::OrbitPitch(1)));
        assert_eq!(action_for_key(Key::Char('+')), Some(Action::Zoom(1)));
        assert_eq!(action_for_key(Key::Char(']')), Some(Action::Iso(1)));
        assert_eq!(action_for_key(Key::Char('<')), Some(Action::AoSamples(-1)));
        assert_eq!(action_for_key(Key::Char('b')), Some(Action::NextIbl));
        assert_eq!(action_for_key(Key::Char('f')), Some(Action::ToggleDenoise));
        assert_eq!(action_for_key(Key::Char('p')), Some(Action::Screenshot));
        assert_eq!(action_for_key(Key::CtrlC), Some(Action::Quit));
        assert_eq!(action_for_key(Key::Char(' ')), Some(Action::PlayPause));
        assert_eq!(action_for_key(Key::Char('N')), Some(Action::Step(-1)));
        assert_eq!(action_for_key(Key::Char(')')), Some(Action::Rate(1)));
        assert_eq!(action_for_key(Key::Char('z')), None);
        assert_eq!(action_for_key(Key::Char('1')), Some(Action::View(ViewPreset::Anterior)));
        assert_eq!(action_for_key(Key::Char('5')), Some(Action::View(ViewPreset::Superior)));
        assert_eq!(action_for_key(Key::Char('6')), Some(Action::View(ViewPreset::Inferior)));
        assert_eq!(action_for_key(Key::Char('0')), None);
        assert_eq!(action_for_key(Key::Char('7')), None);
    }

    #[test]
    fn view_keys_frame_the_box_from_the_patient_side() {
        let mut s = state();
        let before = s.camera;
        assert!(!s.view(ViewPreset::Left), "no framing, no view");
        assert_eq!(s.camera, before);
        let fit = (DVec3::new(-1.0, -2.0, -3.0), DVec3::new(3.0, 2.0, 1.0));
        s.framing = Some(ViewFraming { fit, orientation: None, size: (64, 48) });
        assert!(!s.apply(Action::View(ViewPreset::Superior)));
        let c = s.camera;
        assert_eq!((c.target, c.up, c.fov_y_deg), (DVec3::new(1.0, 0.0, -1.0), -DVec3::Y, before.fov_y_deg));
        assert!((c.eye - c.target).normalize().z > 0.999, "superior looks from +z: {c:?}");
    }

    #[test]
    fn orbit_keeps_distance_and_target_and_stops_short_of_the_pole() {
        let mut s = state();
        s.apply(Action::OrbitYaw(1));
        assert!((s.camera.eye.length() - 10.0).abs() < 1e-9);
        assert!(s.camera.eye.y > 0.0, "counter-clockwise from above: {}", s.camera.eye);
        for _ in 0..100 {
            s.apply(Action::OrbitPitch(1));
        }
        let elevation = (s.camera.eye.z / s.camera.eye.length()).asin().to_degrees();
        assert!((elevation - 88.0).abs() < 1e-6, "{elevation}");
        assert!(s.camera.validate().is_ok());
        assert_eq!(s.camera.target, DVec3::ZERO);
    }

    #[test]
    fn pan_moves_eye_and_target_together_and_zoom_scales_the_distance() {
        let mut s = state();
        s.apply(Action::Pan(1, 0));
        assert!((s.camera.eye - s.camera.target - DVec3::new(10.0, 0.0, 0.0)).length() < 1e-9);
        assert!(s.camera.target.length() > 0.4 && s.camera.target.z.abs() < 1e-9, "{}", s.camera.target);
        let mut s = state();
        s.apply(Action::Zoom(1));
        assert!((s.camera.eye.length() - 9.0).abs() < 1e-9);
        s.apply(Action::Zoom(-1));
        assert!((s.camera.eye.length() - 10.0).abs() < 1e-9);
    }

    #[test]
    fn iso_keys_stop_at_the_ends_of_the_value_range() {
        let mut s = state();
        for _ in 0..200 {
            s.apply(Action::Iso(1));
        }
        assert_eq!(s.settings.iso, 2.0);
        for _ in 0..200 {
            s.apply(Action::Iso(-1));
        }
        assert_eq!(s.settings.iso, 0.0);
        assert!(isowall_volume::check_iso(s.settings.iso, s.iso_range).is_ok());
    }

    #[test]
    fn iso_ao_samples_and_ibl_step() {
        let mut s = state();
        s.apply(Action::Iso(1));
        assert!((s.settings.iso - 0.52).abs() < 1e-12);
        s.settings.ao.samples = 0;
        s.apply(Action::AoSamples(1));
        assert_eq!(s.settings.ao.samples, 1);
        s.apply(Action::AoSamples(1));
        assert_eq!(s.settings.ao.samples, 2);
        s.apply(Action::AoSamples(-1));
        s.apply(Action::AoSamples(-1));
        assert_eq!(s.settings.ao.samples, 0);
        s.settings.ao.samples = MAX_AO_SAMPLES;
        s.apply(Action::AoSamples(1));
        assert_eq!(s.settings.ao.samples, MAX_AO_SAMPLES);
        let seen: Vec<IblMethod> = (0..4)
            .map(|_| {
                s.apply(Action::NextIbl);
                s.settings.ao.ibl
            })
            .collect();
        assert_eq!(seen, [IblMethod::Seed, IblMethod::Bent, IblMethod::Rays, IblMethod::None]);
        assert_eq!(s.settings.denoise, Denoise::Off);
        s.apply(Action::ToggleDenoise);
        assert_eq!(s.settings.denoise, Denoise::On);
        s.apply(Action::ToggleDenoise);
        assert_eq!(s.settings.denoise, Denoise::Off);
        assert!(s.apply(Action::Quit));
    }

    #[test]
    fn dead_zone_is_zero_inside_and_continuous_outside() {
        assert_eq!(dead_zone(0.1, 0.15), 0.0);
        assert_eq!(dead_zone(-0.15, 0.15), 0.0);
        assert!(dead_zone(0.1500001, 0.15) < 1e-5);
        assert!((dead_zone(1.0, 0.15) - 1.0).abs() < 1e-12);
        assert!((dead_zone(-1.0, 0.15) + 1.0).abs() < 1e-12);
        assert!((dead_zone(0.575, 0.15) - 0.5).abs() < 1e-12);
        assert_eq!(dead_zone(3.0, 0.15), 1.0);
        assert_eq!(dead_zone(f64::NAN, 0.15), 0.0);
    }

    #[test]
    fn axes_move_at_the_configured_rates() {
        let j = JoystickConfig::default();
        let mut s = state();
        // Full right for a second: 90 degrees clockwise from above.
        s.apply_axes(Axes { orbit_x: 1.0, ..Default::default() }, 1.0, &j);
        assert!((s.camera.eye - DVec3::new(0.0, -10.0, 0.0)).length() < 1e-9, "{}", s.camera.eye);
        // A resting stick inside the dead zone moves nothing.
        let before = s;
        s.apply_axes(Axes { orbit_x: 0.1, orbit_y: -0.1, zoom: 0.12 }, 1.0, &j);
        assert_eq!(s, before);
        // Stick up for a second: one e-fold closer.
        s.apply_axes(Axes { zoom: 1.0, ..Default::default() }, 1.0, &j);
        assert!((s.camera.eye.length() - 10.0 * (-1.0f64).exp()).abs() < 1e-9);
    }

    #[test]
    fn playback_steps_at_its_rate_wraps_and_pauses() {
        let mut p = Playback::new(16, 4.0);
        p.advance(1.0);
        assert_eq!(p.step, 0, "paused at first");
        p.playing = true;
        // 4 steps a second: 0.3 s is one step and a fifth, the fifth kept.
        p.advance(0.3);
        assert_eq!(p.step, 1);
        p.advance(0.25);
        assert_eq!(p.step, 2);
        p.advance(3.5);
        assert_eq!(p.step, (2 + 14) % 16, "wraps at the last step");
        p.step_by(-2);
        assert_eq!(p.step, 14);
        p.step_by(1);
        assert_eq!(p.step, 15);
        p.show(3);
        assert_eq!(p.step, 3);
        p.show(17);
        assert_eq!(p.step, 1, "wraps");
        p.show(15);
        p.change_rate(1);
        assert_eq!(p.rate, 8.0);
        for _ in 0..20 {
            p.change_rate(1);
        }
        assert_eq!(p.rate, MAX_RATE);
        p.playing = false;
        p.advance(10.0);
        assert_eq!(p.step, 15, "paused");
        // A volume without time steps stays at 0.
        let mut one = Playback::new(1, 4.0);
        one.playing = true;
        one.advance(5.0);
        one.step_by(3);
        assert_eq!(one.step, 0);
        // Through the session's keys.
        let cam =
            Camera { eye: DVec3::new(0.0, -5.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 35.0 };
        let mut s = SessionState::new(cam, RenderSettings::new(0.5), (0.0, 1.0));
        s.playback = Playback::new(4, 1.0);
        s.apply(Action::PlayPause);
        assert!(s.playback.playing);
        s.apply(Action::Step(1));
        s.apply(Action::Rate(-1));
        assert_eq!((s.playback.step, s.playback.rate), (1, 0.5));
    }
}
