//! `[joystick]` of the wall config: how `isowall session` reads a gamepad (the controller maps
//! these names to gilrs's axes and buttons). Every field has a default, so the table is optional.
//!
//! ```toml
//! [joystick]
//! dead_zone = 0.15            # |value| below this counts as 0 (the rest is rescaled to 0..1)
//! orbit_x = "left-stick-x"    # turn about the world up axis
//! orbit_y = "left-stick-y"    # tilt up and down
//! zoom = "right-stick-y"      # towards / away from the target
//! orbit_degrees_per_second = 90.0
//! zoom_per_second = 1.0       # e-folds of the distance per second at full deflection
//! iso_up = "north"
//! iso_down = "west"
//! screenshot = "start"
//! ```

use serde::{Deserialize, Serialize};

/// A gamepad axis, by its position on a standard (Xbox/PlayStation-like) pad.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PadAxis {
    LeftStickX,
    LeftStickY,
    RightStickX,
    RightStickY,
    LeftZ,
    RightZ,
    DpadX,
    DpadY,
}

/// A gamepad button, by position (`south` is A on Xbox, cross on PlayStation).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PadButton {
    South,
    East,
    North,
    West,
    LeftTrigger,
    LeftTrigger2,
    RightTrigger,
    RightTrigger2,
    Select,
    Start,
    Mode,
    LeftThumb,
    RightThumb,
    DpadUp,
    DpadDown,
    DpadLeft,
    DpadRight,
}

/// `[joystick]`: the gamepad mapping of `isowall session`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct JoystickConfig {
    pub dead_zone: f64,
    pub orbit_x: PadAxis,
    pub orbit_y: PadAxis,
    pub zoom: PadAxis,
    pub orbit_degrees_per_second: f64,
    pub zoom_per_second: f64,
    pub iso_up: PadButton,
    pub iso_down: PadButton,
    pub screenshot: PadButton,
}

impl Default for JoystickConfig {
    fn default() -> Self {
        JoystickConfig {
            dead_zone: 0.15,
            orbit_x: PadAxis::LeftStickX,
            orbit_y: PadAxis::LeftStickY,
            zoom: PadAxis::RightStickY,
            orbit_degrees_per_second: 90.0,
            zoom_per_second: 1.0,
            iso_up: PadButton::North,
            iso_down: PadButton::West,
            screenshot: PadButton::Start,
        }
    }
}

impl JoystickConfig {
    /// Problems with the values, as (field, message).
    pub fn problems(&self) -> Vec<(&'static str, String)> {
        let mut p = Vec::new();
        if !(self.dead_zone.is_finite() && (0.0..1.0).contains(&self.dead_zone)) {
            p.push(("dead_zone", format!("joystick: `dead_zone` {} must be in [0, 1)", self.dead_zone)));
        }
        for (f, v) in [
            ("orbit_degrees_per_second", self.orbit_degrees_per_second),
            ("zoom_per_second", self.zoom_per_second),
        ] {
            if !(v.is_finite() && v > 0.0) {
                p.push((f, format!("joystick: `{f}` {v} must be > 0")));
            }
        }
        p
    }
}

#[cfg(test)]
mod tests {
    use crate::config::WallConfig;
    use std::path::Path;

    const BASE: &str = "[wall]\nname = \"w\"\n\n[volume]\nsource = \"procedural:torus\"\n\n\
                        [[tiles]]\nname = \"t\"\nx = 0\ny = 0\nwidth = 8\nheight = 8\n\n\
                        [[nodes]]\nname = \"n\"\naddress = \"127.0.0.1:7000\"\ntiles = [\"t\"]\n";

    #[test]
    fn the_joystick_table_is_optional_and_checked() {
        let c = WallConfig::parse(BASE, Path::new("w.toml")).unwrap();
        assert_eq!(c.joystick, super::JoystickConfig::default());
        let text = format!("{BASE}\n[joystick]\nzoom = \"left-z\"\nscreenshot = \"south\"\n");
        let c = WallConfig::parse(&text, Path::new("w.toml")).unwrap();
        assert_eq!(
            (c.joystick.zoom, c.joystick.screenshot),
            (super::PadAxis::LeftZ, super::PadButton::South)
        );
        // BASE is 17 lines, then a blank line, the table header (19) and its first key (20).
        let e = WallConfig::parse(
            &format!("{BASE}\n[joystick]\ndead_zone = 1.5\nturbo = true\nzoom = \"wheel\"\n"),
            Path::new("w.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("turbo") && e.contains("w.toml:"), "{e}");
        let e = WallConfig::parse(&format!("{BASE}\n[joystick]\ndead_zone = 1.5\n"), Path::new("w.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("w.toml:20:") && e.contains("`dead_zone` 1.5 must be in [0, 1)"), "{e}");
        let e = WallConfig::parse(&format!("{BASE}\n[joystick]\nzoom = \"wheel\"\n"), Path::new("w.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("w.toml:20:") && e.contains("wheel"), "{e}");
    }
}
