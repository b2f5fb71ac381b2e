//! The shared model of Isowall: everything the controller, the daemons and the renderers agree on.
//! It opens no sockets, uses no GPU and reads no clock (time is passed in). It reads files in two
//! places only: [`WallConfig::load`] (and [`WallConfig::check_report`], through it) reads the
//! config file it is given, and the `cli` feature's `check_config` (the `check-config` command)
//! also reads headers, never pixels or voxels, through `isowall-volume`: a volume file's and the
//! environment images'. Everything else takes its input as values.
//!
//! - [`camera`]: the pinhole camera of DESIGN.md and the pixel-centre ray convention, for a whole
//!   image or a rectangle of it (a tile is a rectangle of the wall image).
//! - [`config`]: the wall config (TOML): wall, camera, volume, render defaults, tiles and nodes,
//!   validated with every problem at its file, line and column.
//! - [`render_state`]: what a frame is rendered with: iso value, shading, light, material, AOV.
//! - The frame protocol, sans-IO (time is passed in as a `Duration` since any epoch):
//!   [`wire`] (frame state on the wire, converted to and from the model), [`messages`], [`codec`]
//!   (the one place bytes are made: bincode, length-prefixed frames, limits), [`clock`] (offsets
//!   from Ping/Pong), [`frame_controller`] (the controller's swap barrier) and [`node_machine`] (a
//!   daemon's side).
//! - object space: [`bricks`] (the split, halos, covered rectangles), [`composite`] (depth
//!   compositing of peers' pixels, its caps and deadline), [`adoption`] (which node renders each
//!   brick when nodes die), [`object_machine`] (a node's object space: views, brick maps,
//!   compositing and its messages).
//! - [`links`]: which connection of each node is its current one (a counter, never reused).
//! - [`names`]: the one rule for node and tile names (a node's name is its certificate's name).
//! - [`governor`]: the quality governor (frame times in, AO samples per frame out).
//! - [`handshake_limit`]: handshakes a daemon starts per source address (a token bucket).
//! - [`peer_log`]: the lines a peer may make the operator read (a few per peer per interval).
//! - [`seat`]: which controller drives a node (one at a time; a second is refused with why).
//! - [`sim`]: the wall at scale: a LAN model on a virtual clock driving the machines above.

pub mod adoption;
pub mod balance;
pub mod bricks;
pub mod camera;
#[cfg(feature = "cli")]
pub mod check_config;
#[cfg(feature = "cli")]
pub mod cli_args;
pub mod clock;
pub mod codec;
pub mod composite;
pub mod config;
pub mod frame_controller;
pub mod governor;
pub mod handshake_limit;
pub mod joystick;
pub mod links;
pub mod lowres;
pub mod messages;
pub mod names;
pub mod node_machine;
pub mod object_machine;
pub mod peer_log;
pub mod render_plan;
pub mod render_state;
pub mod seat;
pub mod sim;
pub mod swap_timing;
pub mod wire;

pub use camera::{Camera, CameraError, Rect, UnknownView, View, ViewFraming, ViewPreset};
pub use config::{
    CameraConfig, CertConfig, ConfigErrors, NodeConfig, Problem, RenderConfig, TileConfig, VolumeConfig,
    WallConfig, WallMode, WallSection,
};
pub use frame_controller::{ControllerOutput, FrameController, FrameStats, NodeFrameStats};
pub use governor::{Governor, GovernorError, Motion, MAX_SCALE};
pub use isowall_volume::{Orientation, PatientDir};
pub use messages::{Message, ProtocolError, Role, TileImage, PROTOCOL_VERSION};
pub use node_machine::{NodeMachine, NodeOutput};
pub use render_state::{
    AoMethod, AoRadius, AoSequence, AoSettings, Aov, Denoise, IblMethod, Light, Material, RenderSettings,
    Shading,
};
pub use wire::{FrameSpec, FrameState};
