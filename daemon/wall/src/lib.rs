//! The shared model of Isowall: everything the controller, the daemons and the renderers agree on,
//! with no I/O at all (no sockets, no GPU, no clocks, no files).
//!
//! - [`camera`]: the pinhole camera of DESIGN.md and the pixel-centre ray convention, for a whole
//!   image or a window of it (a tile is a window of the wall image).
//! - [`render_state`]: what a frame is rendered with: iso value, shading, light, material, AOV.

pub mod camera;
pub mod render_state;

pub use camera::{Camera, CameraError, View, Window};
pub use render_state::{
    AoMethod, AoRadius, AoSettings, Aov, IblMethod, Light, Material, RenderSettings, Shading,
};
