//! Scripted camera paths for `isowall demo`: keyframes in TOML (time, eye, target, up, fov, iso,
//! AO samples), checked field by field with every problem as FILE:LINE:COL, and their smooth
//! interpolation. Pure: no sockets, no clocks (the demo's frame clock passes the time in).
//!
//! ```toml
//! [[key]]
//! time = 0.0              # seconds from the start of the path, strictly increasing
//! eye = [600, -300, 250]  # world units
//! target = [127.5, 127.5, 58.5]
//! up = [0, 0, 1]          # optional, default +z
//! fov = 35.0              # optional, vertical degrees; default the wall's [camera] fov_y
//! iso = 0.5               # optional, data units; default the wall's iso
//! ao_samples = 16         # optional; default the wall's [render] ao_samples
//! step = 0                # optional, time-varying volumes: the time step; default 0
//! ```
//!
//! Between keys, eye, target and up follow a Catmull-Rom spline (a cubic Hermite whose tangent
//! at a key is the chord of its neighbours over their time span, so it passes through every key
//! with a continuous velocity, also for unevenly spaced keys); up is renormalised. A path whose
//! last key repeats its first (a closed loop) takes its end tangents across the seam, so a
//! looping demo turns smoothly there too. The field of view and the iso value are linear (no
//! overshoot); the AO sample count is stepwise: that of the last key at or before the time. The
//! time step is linear and rounded down (keys `step = 0` at 0 s and `step = 15` at 15 s play a
//! step a second; a node wraps a step past the volume's last).

use glam::DVec3;
use isowall_model::config::line_column;
use isowall_model::Camera;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// A camera path that does not load: FILE:LINE:COL and what is wrong.
#[derive(Debug, thiserror::Error)]
#[error("{}:{line}:{column}: {message}", path.display())]
pub struct PathError {
    pub path: PathBuf,
    pub line: usize,
    pub column: usize,
    pub message: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PathFile {
    key: Vec<toml::Spanned<KeyFile>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyFile {
    time: f64,
    eye: [f64; 3],
    target: [f64; 3],
    up: Option<[f64; 3]>,
    fov: Option<f64>,
    iso: Option<f64>,
    ao_samples: Option<u32>,
    step: Option<u32>,
}

/// What a key leaves out is taken from the wall.
#[derive(Debug, Clone, Copy)]
pub struct Defaults {
    pub fov_y_deg: f64,
    pub iso: f64,
    pub ao_samples: u32,
}

/// One keyframe, every field resolved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Key {
    pub time: f64,
    pub eye: DVec3,
    pub target: DVec3,
    pub up: DVec3,
    pub fov_y_deg: f64,
    pub iso: f64,
    pub ao_samples: u32,
    pub step: u32,
}

impl Key {
    pub fn camera(&self) -> Camera {
        Camera { eye: self.eye, target: self.target, up: self.up, fov_y_deg: self.fov_y_deg }
    }
}

/// A checked camera path: at least two keys, times strictly increasing from 0.
#[derive(Debug, Clone)]
pub struct CameraPath {
    pub keys: Vec<Key>,
    /// The last key repeats the first (camera, iso, samples): a loop closes smoothly.
    pub closed: bool,
    /// Each key's line in the file (for the warnings of [`CameraPath::misfits`]).
    pub lines: Vec<usize>,
}

impl CameraPath {
    /// Reads and checks a path file.
    pub fn load(path: &Path, defaults: Defaults, max_ao_samples: u32) -> Result<CameraPath, PathError> {
        let limit = isowall_model::config::MAX_CONFIG_BYTES;
        let text = isowall_volume::io::regular::read_regular_text(path, limit).map_err(|e| PathError {
            path: path.to_path_buf(),
            line: 1,
            column: 1,
            message: format!("cannot read the camera path: {e}"),
        })?;
        CameraPath::parse(&text, path, defaults, max_ao_samples)
    }

    /// Parses and checks the text of a path file (`path` names it in errors).
    pub fn parse(text: &str, path: &Path, d: Defaults, max_ao_samples: u32) -> Result<CameraPath, PathError> {
        let at = |offset: usize, message: String| {
            let (line, column) = line_column(text, offset);
            PathError { path: path.to_path_buf(), line, column, message }
        };
        let file: PathFile = toml::from_str(text).map_err(|e| {
            let offset = e.span().map_or(0, |s| s.start);
            at(offset, e.message().trim().to_string())
        })?;
        if file.key.len() < 2 {
            return Err(at(
                0,
                format!("a camera path needs at least 2 [[key]] tables, found {}", file.key.len()),
            ));
        }
        let mut keys: Vec<Key> = Vec::with_capacity(file.key.len());
        let mut lines = Vec::with_capacity(file.key.len());
        for (i, spanned) in file.key.iter().enumerate() {
            let offset = spanned.span().start;
            lines.push(line_column(text, offset).0);
            let k = spanned.get_ref();
            let err = |m: String| at(offset, format!("key {} (time {}): {m}", i + 1, k.time));
            let finite = |name: &str, v: &[f64]| {
                if v.iter().all(|x| x.is_finite()) {
                    Ok(())
                } else {
                    Err(err(format!("`{name}` has a value that is not a finite number: {v:?}")))
                }
            };
            finite("time", &[k.time])?;
            finite("eye", &k.eye)?;
            finite("target", &k.target)?;
            let up = k.up.unwrap_or([0.0, 0.0, 1.0]);
            finite("up", &up)?;
            let key = Key {
                time: k.time,
                eye: DVec3::from_array(k.eye),
                target: DVec3::from_array(k.target),
                up: DVec3::from_array(up),
                fov_y_deg: k.fov.unwrap_or(d.fov_y_deg),
                iso: k.iso.unwrap_or(d.iso),
                ao_samples: k.ao_samples.unwrap_or(d.ao_samples),
                step: k.step.unwrap_or(0),
            };
            finite("fov", &[key.fov_y_deg])?;
            finite("iso", &[key.iso])?;
            if i == 0 && key.time != 0.0 {
                return Err(err("the first key must be at time 0".into()));
            }
            if let Some(prev) = keys.last() {
                if key.time <= prev.time {
                    return Err(err(format!("`time` must increase: the previous key is at {}", prev.time)));
                }
            }
            if key.ao_samples > max_ao_samples {
                return Err(err(format!(
                    "`ao_samples` {} is over the limit of {max_ao_samples}",
                    key.ao_samples
                )));
            }
            key.camera().validate().map_err(|e| err(e.to_string()))?;
            keys.push(key);
        }
        let (first, last) = (keys[0], keys[keys.len() - 1]);
        let closed = first.eye == last.eye
            && first.target == last.target
            && first.up == last.up
            && first.fov_y_deg == last.fov_y_deg
            && first.iso == last.iso
            && first.ao_samples == last.ao_samples
            && first.step == last.step;
        Ok(CameraPath { keys, closed, lines })
    }

    /// The time of the last key (seconds).
    pub fn duration(&self) -> f64 {
        self.keys[self.keys.len() - 1].time
    }

    /// The Catmull-Rom tangent of `f` at key `i` (per second).
    fn tangent(&self, i: usize, f: impl Fn(&Key) -> DVec3) -> DVec3 {
        let k = &self.keys;
        let n = k.len() - 1;
        if self.closed && (i == 0 || i == n) && n >= 2 {
            let span = (k[1].time - k[0].time) + (k[n].time - k[n - 1].time);
            return (f(&k[1]) - f(&k[n - 1])) / span;
        }
        let (a, b) = (i.saturating_sub(1), (i + 1).min(n));
        (f(&k[b]) - f(&k[a])) / (k[b].time - k[a].time)
    }

    /// The camera and settings at `t` seconds (clamped to the path).
    pub fn at(&self, t: f64) -> Key {
        let k = &self.keys;
        let t = t.clamp(0.0, self.duration());
        // The segment [i, i+1] holding t (the last for t = duration).
        let i = k.partition_point(|key| key.time <= t).saturating_sub(1).min(k.len() - 2);
        let (k0, k1) = (&k[i], &k[i + 1]);
        let dt = k1.time - k0.time;
        let s = ((t - k0.time) / dt).clamp(0.0, 1.0);
        let (s2, s3) = (s * s, s * s * s);
        let (h00, h10, h01, h11) =
            (2.0 * s3 - 3.0 * s2 + 1.0, s3 - 2.0 * s2 + s, -2.0 * s3 + 3.0 * s2, s3 - s2);
        let hermite = |f: &dyn Fn(&Key) -> DVec3| {
            h00 * f(k0) + h10 * dt * self.tangent(i, f) + h01 * f(k1) + h11 * dt * self.tangent(i + 1, f)
        };
        let eye = hermite(&|k: &Key| k.eye);
        let target = hermite(&|k: &Key| k.target);
        let up = hermite(&|k: &Key| k.up).normalize_or(k0.up.normalize_or(DVec3::Z));
        let lerp = |a: f64, b: f64| a + (b - a) * s;
        // Stepwise: the samples of the last key at or before t.
        let ao_samples = if s >= 1.0 { k1.ao_samples } else { k0.ao_samples };
        Key {
            time: t,
            eye,
            target,
            up,
            fov_y_deg: lerp(k0.fov_y_deg, k1.fov_y_deg),
            iso: lerp(k0.iso, k1.iso),
            ao_samples,
            step: lerp(k0.step as f64, k1.step as f64).floor().max(0.0) as u32,
        }
    }
}

/// Keys whose target lies further outside the volume's box than this fraction of its diagonal.
const TARGET_SLACK: f64 = 0.05;
/// The object's centre this far from the view's centre (a fraction of the half height) sits off
/// to a side or a corner.
const OFF_CENTRE: f64 = 0.5;
/// An object whose bounding sphere spans less than this fraction of the view's height is lost in it.
const SMALL: f64 = 0.15;
/// Problems named per kind at most (the count says the rest).
const NAMED: usize = 4;

impl CameraPath {
    /// Where the path looks away from the volume it plays on: keys whose target lies outside the
    /// volume's box (`volume`, world units), and keys whose view has the object (`object`: the
    /// box of what reaches the iso value, as the wall's default camera frames it) off its centre
    /// or small in it. A path written for another volume (the engine's, played on an MRI) shows
    /// the surface in a corner or not at all; `isowall demo` says so at start, with each key's
    /// FILE:LINE, and plays it anyway. Empty when the path fits.
    pub fn misfits(&self, file: &Path, volume: (DVec3, DVec3), object: (DVec3, DVec3)) -> Vec<String> {
        let slack = (volume.1 - volume.0).length() * TARGET_SLACK;
        let (centre, radius) = ((object.0 + object.1) * 0.5, (object.1 - object.0).length() * 0.5);
        let name = |i: usize| {
            format!("{}:{}: key {} (time {} s)", file.display(), self.lines[i], i + 1, self.keys[i].time)
        };
        let mut outside = Vec::new();
        let mut off = Vec::new();
        let mut small = Vec::new();
        // The last key of a closed path repeats the first.
        let keys = if self.closed { self.keys.len() - 1 } else { self.keys.len() };
        for (i, k) in self.keys.iter().enumerate().take(keys) {
            let beyond = (volume.0 - k.target).max(k.target - volume.1).max(DVec3::ZERO);
            if beyond.length() > slack {
                outside.push(format!("{}: target {:?}", name(i), k.target.to_array()));
            }
            let axis = (k.target - k.eye).normalize_or_zero();
            let to_centre = centre - k.eye;
            let along = to_centre.dot(axis);
            let half = (k.fov_y_deg.to_radians() * 0.5).tan();
            if along <= radius.max(f64::EPSILON) {
                off.push(format!("{}: the object is beside or behind the eye", name(i)));
                continue;
            }
            let offset = (to_centre - axis * along).length() / along / half;
            let size = radius / along / half;
            if offset > OFF_CENTRE {
                off.push(format!(
                    "{}: {:.0}% of the half height off the view's centre",
                    name(i),
                    offset * 100.0
                ));
            } else if size < SMALL {
                small.push(format!("{}: {:.0}% of the view's height", name(i), size * 100.0));
            }
        }
        let mut said = Vec::new();
        let mut say = |list: Vec<String>, what: String| {
            if list.is_empty() {
                return;
            }
            let more = list.len().saturating_sub(NAMED);
            let mut text = format!("{what}: {}", list.into_iter().take(NAMED).collect::<Vec<_>>().join("; "));
            if more > 0 {
                text.push_str(&format!("; and {more} more"));
            }
            said.push(text);
        };
        let [a, b] = [volume.0.to_array(), volume.1.to_array()];
        say(outside, format!("camera targets outside the volume's box {a:?}..{b:?}"));
        let c = centre.to_array();
        say(off, format!("views with the object (centre {c:?}) far off their centre"));
        say(small, format!("views the object (radius {radius:.1}) fills little of"));
        said
    }
}

/// The fixed frame clock: frame `i` shows the path at `i / fps` seconds (wrapped with `looping`),
/// never the wall clock, so a recorded run is the same every time. `None` once a path that does
/// not loop is over.
pub fn frame_time(i: u64, fps: f64, duration: f64, looping: bool) -> Option<f64> {
    let t = i as f64 / fps;
    if looping {
        Some(t.rem_euclid(duration))
    } else if t <= duration + 1e-9 {
        Some(t.min(duration))
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const D: Defaults = Defaults { fov_y_deg: 35.0, iso: 0.5, ao_samples: 8 };

    fn parse(text: &str) -> Result<CameraPath, PathError> {
        CameraPath::parse(text, Path::new("p.toml"), D, 1024)
    }

    const SQUARE: &str = "\
[[key]]\ntime = 0\neye = [10, 0, 0]\ntarget = [0, 0, 0]\nao_samples = 4\n\n\
[[key]]\ntime = 1\neye = [0, 10, 0]\ntarget = [0, 0, 0]\niso = 1.5\nfov = 45\nao_samples = 16\n\n\
[[key]]\ntime = 3\neye = [-10, 0, 2]\ntarget = [0, 0, 1]\nao_samples = 32\n\n\
[[key]]\ntime = 4\neye = [0, -10, 0]\ntarget = [0, 0, 0]\n";

    #[test]
    fn the_path_passes_through_every_key() {
        let p = parse(SQUARE).unwrap();
        assert!(!p.closed);
        for k in &p.keys {
            let a = p.at(k.time);
            assert!((a.eye - k.eye).length() < 1e-12, "{a:?} vs {k:?}");
            assert!((a.target - k.target).length() < 1e-12);
            assert!((a.up - k.up.normalize()).length() < 1e-12);
            assert_eq!(a.fov_y_deg, k.fov_y_deg);
            assert_eq!(a.iso, k.iso);
            assert_eq!(a.ao_samples, k.ao_samples);
        }
        // Defaults filled in where a key leaves fields out.
        assert_eq!(p.keys[0].fov_y_deg, 35.0);
        assert_eq!(p.keys[0].iso, 0.5);
        assert_eq!(p.keys[3].ao_samples, 8);
    }

    #[test]
    fn the_path_is_continuous_with_a_continuous_velocity_across_keys() {
        let p = parse(SQUARE).unwrap();
        let h = 1e-6;
        for k in &p.keys[1..p.keys.len() - 1] {
            let (before, after) = (p.at(k.time - h), p.at(k.time + h));
            assert!((before.eye - after.eye).length() < 1e-4, "jump at {}", k.time);
            let v_in = (p.at(k.time).eye - p.at(k.time - 1e-4).eye) / 1e-4;
            let v_out = (p.at(k.time + 1e-4).eye - p.at(k.time).eye) / 1e-4;
            assert!(
                (v_in - v_out).length() < 1e-2 * v_in.length().max(1.0),
                "kink at {}: {v_in} {v_out}",
                k.time
            );
        }
        // Small steps in time make small steps in space everywhere (no jumps inside segments).
        let mut prev = p.at(0.0).eye;
        for i in 1..=4000 {
            let e = p.at(i as f64 * 1e-3).eye;
            assert!((e - prev).length() < 0.05, "jump near t = {}", i as f64 * 1e-3);
            prev = e;
        }
    }

    #[test]
    fn iso_is_linear_and_ao_samples_stepwise() {
        let p = parse(SQUARE).unwrap();
        assert!((p.at(0.25).iso - 0.75).abs() < 1e-12);
        assert!((p.at(0.5).fov_y_deg - 40.0).abs() < 1e-12);
        assert_eq!(p.at(0.999).ao_samples, 4);
        assert_eq!(p.at(1.0).ao_samples, 16);
        assert_eq!(p.at(2.9).ao_samples, 16);
        assert_eq!(p.at(3.5).ao_samples, 32);
        // Past the ends: clamped.
        assert_eq!(p.at(-1.0).eye, p.keys[0].eye);
        assert_eq!(p.at(9.0).eye, p.keys[3].eye);
    }

    #[test]
    fn the_time_step_is_linear_rounded_down() {
        let text = "[[key]]\ntime = 0\neye = [5, 0, 0]\ntarget = [0, 0, 0]\n\n\
                    [[key]]\ntime = 15\neye = [5, 0, 0]\ntarget = [0, 0, 0]\nstep = 15\n";
        let p = parse(text).unwrap();
        let steps: Vec<u32> =
            [0.0, 0.99, 1.0, 7.5, 14.99, 15.0, 20.0].iter().map(|&t| p.at(t).step).collect();
        assert_eq!(steps, [0, 0, 1, 7, 14, 15, 15]);
        assert!(!p.closed, "a path back at its first camera on another step is not a loop");
        assert!(parse(&text.replace("step = 15", "step = -1")).is_err());
    }

    #[test]
    fn a_closed_path_turns_smoothly_at_its_seam() {
        let text = "[[key]]\ntime = 0\neye = [10, 0, 0]\ntarget = [0, 0, 0]\n\
                    [[key]]\ntime = 1\neye = [0, 10, 0]\ntarget = [0, 0, 0]\n\
                    [[key]]\ntime = 2\neye = [-10, 0, 0]\ntarget = [0, 0, 0]\n\
                    [[key]]\ntime = 3\neye = [0, -10, 0]\ntarget = [0, 0, 0]\n\
                    [[key]]\ntime = 4\neye = [10, 0, 0]\ntarget = [0, 0, 0]\n";
        let p = parse(text).unwrap();
        assert!(p.closed);
        let v_end = (p.at(4.0).eye - p.at(4.0 - 1e-4).eye) / 1e-4;
        let v_start = (p.at(1e-4).eye - p.at(0.0).eye) / 1e-4;
        assert!((v_end - v_start).length() < 1e-2 * v_start.length(), "{v_end} vs {v_start}");
        // By symmetry the tangent at the seam points along +y.
        assert!(v_start.x.abs() < 1e-2 && v_start.y > 1.0, "{v_start}");
    }

    #[test]
    fn the_frame_clock_is_frame_index_over_fps() {
        assert_eq!(frame_time(0, 30.0, 4.0, false), Some(0.0));
        assert_eq!(frame_time(45, 30.0, 4.0, false), Some(1.5));
        assert_eq!(frame_time(120, 30.0, 4.0, false), Some(4.0));
        assert_eq!(frame_time(121, 30.0, 4.0, false), None);
        assert_eq!(frame_time(150, 30.0, 4.0, true), Some(1.0));
    }

    #[test]
    fn errors_name_the_file_line_and_what_is_wrong() {
        let e = parse("[[key]]\ntime = 0\neye = [1, 0, 0]\ntarget = [0, 0, 0]\nzoom = 2\n").unwrap_err();
        assert_eq!((e.line, e.column), (5, 1), "{e}");
        assert!(e.to_string().starts_with("p.toml:5:1: ") && e.to_string().contains("zoom"), "{e}");
        let two = "[[key]]\ntime = 0\neye = [1, 0, 0]\ntarget = [0, 0, 0]\n\n[[key]]\ntime = 0\neye = [2, 0, 0]\ntarget = [0, 0, 0]\n";
        let e = parse(two).unwrap_err();
        assert_eq!(e.line, 6, "{e}");
        assert!(e.to_string().contains("`time` must increase"), "{e}");
        let e = parse(&two.replace("time = 0\neye = [2", "time = 1\neye = [0")).unwrap_err();
        assert!(e.to_string().contains("coincide"), "{e}");
        let e =
            parse(&two.replace("time = 0\neye = [2", "time = 1\nao_samples = 5000\neye = [2")).unwrap_err();
        assert!(e.to_string().contains("over the limit of 1024"), "{e}");
        let e = parse("[[key]]\ntime = 0\neye = [1, 0, 0]\ntarget = [0, 0, 0]\n").unwrap_err();
        assert!(e.to_string().contains("at least 2"), "{e}");
        let e = parse("[[key]]\ntime = 0\neye = [1, 0]\ntarget = [0, 0, 0]\n").unwrap_err();
        assert_eq!(e.line, 3, "{e}");
    }

    #[test]
    fn the_shipped_engine_demo_loads() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../wall-configs/demos/engine.toml");
        let p = CameraPath::load(&path, D, 1024).unwrap();
        assert!(p.keys.len() >= 4 && p.duration() > 5.0);
    }

    #[test]
    fn a_path_is_checked_against_the_volume_it_plays_on() {
        let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("../wall-configs/demos/engine.toml");
        let p = CameraPath::load(&file, D, 1024).unwrap();
        // The engine (256x256x118 voxels, unit spacing): the path was written for it.
        let engine = (DVec3::ZERO, DVec3::new(255.0, 255.0, 117.0));
        assert_eq!(p.misfits(&file, engine, engine), Vec::<String>::new());
        // The MRI (128x128x84): the targets lie on its box's edge, the head off the views' centres.
        let mri = (DVec3::ZERO, DVec3::new(127.0, 127.0, 83.0));
        let said = p.misfits(&file, mri, mri);
        assert_eq!(said.len(), 1, "{said:#?}");
        assert!(
            said[0].starts_with("views with the object (centre [63.5, 63.5, 41.5]) far off"),
            "{said:#?}"
        );
        // A small head at the origin (what the engine's path shows of an MRI): its targets lie
        // outside, the head sits off the views' centres; each key named with its line.
        let head = (DVec3::ZERO, DVec3::new(47.0, 47.0, 29.0));
        let said = p.misfits(&file, head, head);
        assert_eq!(said.len(), 2, "{said:#?}");
        assert!(said[0].starts_with("camera targets outside the volume's box"), "{said:#?}");
        assert!(said[0].contains(&format!("engine.toml:{}: key 1 (time 0 s)", p.lines[0])), "{said:#?}");
        assert!(said[0].ends_with("; and 4 more"), "{said:#?}");
        assert!(said[1].starts_with("views with the object"), "{said:#?}");
        // Far away and narrow is small, not off-centre.
        let far = parse(
            "[[key]]\ntime = 0\neye = [0, -2000, 0]\ntarget = [0, 0, 0]\n\n\
             [[key]]\ntime = 1\neye = [2000, 0, 0]\ntarget = [0, 0, 0]\n",
        )
        .unwrap();
        let cube = (DVec3::splat(-20.0), DVec3::splat(20.0));
        let said = far.misfits(Path::new("p.toml"), cube, cube);
        assert_eq!(said.len(), 1, "{said:#?}");
        assert!(
            said[0].starts_with("views the object (radius 34.6) fills little of: p.toml:1: key 1"),
            "{said:#?}"
        );
        // The object behind the eye.
        let behind = parse(
            "[[key]]\ntime = 0\neye = [0, -100, 0]\ntarget = [0, -200, 0]\n\n\
             [[key]]\ntime = 1\neye = [0, -100, 0]\ntarget = [0, -200, 1]\n",
        )
        .unwrap();
        let big = (DVec3::splat(-300.0), DVec3::splat(300.0));
        let said = behind.misfits(Path::new("p.toml"), big, cube);
        assert_eq!(said.len(), 1, "{said:#?}");
        assert!(said[0].contains("beside or behind the eye"), "{said:#?}");
    }
}
