//! The wall config: one TOML file that describes a whole wall (its name and timing limits, the one
//! wall camera, the volume, the render defaults, the certificates, the screen tiles and the nodes
//! that drive them). Every table and field is checked (`deny_unknown_fields`), and every problem is
//! reported at once with its file, line and column.
//!
//! ```toml
//! [wall]
//! name = "local-2x2"
//! deadline_ms = 2000              # frame deadline of the swap barrier (default 2000, at most
//!                                 # 600000: ten minutes)
//! message_limit_bytes = 67108864  # the largest network message (default 64 MiB; 4 KiB to 1 GiB,
//!                                 # and room for each node's snapshot of its tiles)
//! swap_margin_ms = "auto"         # the timed swap: from a frame's release to the moment every
//!                                 # node presents it; "auto" (learned), milliseconds (at most
//!                                 # 1000), or "off" (each node presents when its Swap arrives)
//! frame_rate = "unpaced"          # or frames a second (e.g. 60, 30; at most 1000): frames
//!                                 # present on that grid of the controller's clock
//!
//! [camera]      # the one wall camera, over the whole wall image (DESIGN.md "Camera")
//! eye = [x, y, z]                 # optional: omitted -> a view that frames the volume's
//!                                 # surface at the iso (anterior for a scan with orientation)
//! view = "anterior"               # optional, not with eye: anterior | posterior | left | right |
//!                                 # superior | inferior (the patient's side; world axes as LPS
//!                                 # where the file has no orientation); sets the up direction
//! target = [x, y, z]              # optional: default the centre of what is framed
//! up = [0, 0, 1]                  # default +z (with a view or an oriented scan: the view's)
//! fov_y = 35.0                    # vertical, over the whole wall image, degrees (default 35)
//!
//! [volume]
//! source = "procedural:engine"    # PATH (relative to this file's folder; a DICOM folder or file)
//!                                 # or procedural:NAME[:N]
//! iso = 0.0                       # optional, data units
//! # raw files only: dims = [nx, ny, nz], type = "int16", spacing = [sx, sy, sz]
//! # DICOM only: series = "UID"    # the SeriesInstanceUID, where the folder holds several
//! max_bytes = 2147483648          # optional: the most the voxels may take as float32 on a node
//!                                 # (default 2 GiB; also at most the GPU's largest binding)
//! cache_bytes = 1073741824        # optional, time steps (`source = "steps/step_*.nrrd"` or a 4-D
//!                                 # file): what a node keeps loaded ahead of the step it shows
//!                                 # (default 1 GiB; 0: only the step it shows)
//! gpu_budget_mb = 256             # optional: read the volume through a brick cache of this
//!                                 # many MiB on each node's GPU, refined where its tiles look,
//!                                 # instead of loading it whole (screen space, balanced or not)
//! host_budget_mb = 512            # optional, with gpu_budget_mb: decoded bricks kept in memory
//!                                 # (default twice gpu_budget_mb)
//! upload_mb_per_frame = 16.0      # optional, with gpu_budget_mb: the most uploaded to the pool
//!                                 # in a frame (default gpu_budget_mb / 16)
//!
//! [render]      # render-state defaults, all optional
//! shading = "blinn-phong"         # lambert | blinn-phong
//! ao_samples = 16
//! ao_radius = 8.0                 # world units or "unbounded"; omitted: 8 voxels
//! ao_method = "ours"              # ours | seed
//! ao_sequence = "sobol"           # sobol | r2: the 2D set of ours' directions
//! ibl = "bent"                    # none | seed | bent | rays
//! env = "sky"                     # sky | FILE.hdr | DIR (relative to this file's folder)
//! exposure = 0.6                  # default 0.6
//! denoise = "auto"                # off | on | auto: the spatial filter of occlusion and IBL;
//!                                 # auto (the default): on where target_frame_ms is set and
//!                                 # ao_samples > 0, so that a governed wall's moving frames (at
//!                                 # few samples) are filtered; in object space only "on"
//!                                 # filters (the composited tile: its pixels travel as AOVs)
//! target_frame_ms = 100.0         # quality governor: AO samples chosen per frame for this
//!                                 # frame time while the camera moves (omitted: off)
//!
//! [certificates]
//! dir = "keys"                    # relative to this file (default "keys")
//!
//! [[tiles]]
//! name = "t00"
//! x = 0                           # top-left visible pixel in whole-wall pixels
//! y = 0
//! width = 320
//! height = 240
//! bezel = [0, 8, 0, 8]            # left, right, top, bottom hidden pixels (default 0)
//!
//! [[nodes]]
//! name = "node0"
//! address = "127.0.0.1:7401"      # host:port (QUIC over UDP)
//! tiles = ["t00"]
//! ```
//!
//! A tile is a rectangle of the one wall image: its bezels are hidden pixels of that image, so a
//! straight line stays straight across a mullion (DESIGN.md "Camera"). The model reads no files:
//! [`WallConfig::parse`] takes the text; [`WallConfig::load`] is a thin helper that only reads it.

use crate::camera::{Camera, Rect, View, ViewPreset};
use crate::names::name_problem;
use crate::render_state::{
    AoMethod, AoRadius, AoSequence, Denoise, IblMethod, RenderSettings, Shading, DEFAULT_EXPOSURE,
};
use glam::DVec3;
use isowall_volume::io::{RawSpec, VoxelType};
use isowall_volume::procedural::Procedural;
use isowall_volume::source::SERIES_SELECTOR;
use isowall_volume::Orientation;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};
use toml::de::{DeTable, DeValue, ValueDeserializer};
use toml::Spanned;

mod address;
mod budgets;
mod diagnostics;
#[cfg(test)]
mod tests;
mod validate;

pub use address::{check_address, parse_address, AddressHost, NodeAddress};
pub use budgets::{BrickBudgets, BudgetError, MAX_BUDGET_MB};
use diagnostics::{doc_list, doc_value, Doc, Seg};
pub use diagnostics::{line_column, ConfigErrors, Problem};
pub use validate::render_problems;
use validate::*;

/// Default frame deadline of the swap barrier, in milliseconds.
pub const DEFAULT_DEADLINE_MS: u64 = 2000;
/// Longest frame deadline (10 minutes): the controller waits up to two deadlines for a node.
pub const MAX_DEADLINE_MS: u64 = 600_000;
/// Default limit on the size of one network message (64 MiB).
pub const DEFAULT_MESSAGE_LIMIT_BYTES: u64 = 64 << 20;
/// Smallest accepted message limit: a frame state must fit.
pub const MIN_MESSAGE_LIMIT_BYTES: u64 = 4096;
/// Largest accepted message limit: what the decoder accepts at most ([`crate::codec::MAX_FRAME_LEN`],
/// 1 GiB).
pub const MAX_MESSAGE_LIMIT_BYTES: u64 = crate::codec::MAX_FRAME_LEN as u64;
/// Largest `[volume] max_bytes`: 2^30 voxels as float32 (the readers' own cap).
pub const MAX_VOLUME_BYTES: u64 = 4 << 30;
/// Default `[volume] cache_bytes`: 1 GiB of time steps loaded ahead.
pub const DEFAULT_CACHE_BYTES: u64 = 1 << 30;
/// Largest `[volume] cache_bytes`: 1 TiB.
pub const MAX_CACHE_BYTES: u64 = 1 << 40;
/// Largest tile width or height, and largest bezel, in pixels.
pub const MAX_TILE_SIZE: u32 = 16384;
/// The largest config file read (a wall of thousands of tiles is a few MiB).
pub const MAX_CONFIG_BYTES: u64 = 16 << 20;
/// Largest extent of the whole wall image along either axis, in pixels.
pub const MAX_WALL_EXTENT: u64 = 1 << 20;
/// A wall image (the box around every tile, bezels included) may be larger than this only where
/// its tiles and bezels cover at least 1 / [`MAX_WALL_SPARSENESS`] of it: snapshots and
/// thumbnails are of the whole image, so two small tiles a million pixels apart would make each
/// one terabytes.
pub const SPARSE_WALL_PIXELS: u64 = 1 << 24;
pub const MAX_WALL_SPARSENESS: u64 = 64;
/// The GPU bytes a node's tile takes per pixel, at most (a temporal, reprojected, denoised tile:
/// `TileTarget` in daemon/render/src/gpu/tile.rs): six AOV buffers (84, the sample positions'
/// 16 included), the reprojection's history (80), the filter's buffers (80), the depth buffer (4)
/// and three RGBA8 images (12), each a pixel of the work rectangle (the filter's guard band
/// beyond the tile not counted). The render crate's `gpu_tile.rs` counts them from the
/// renderer's allocations and holds this to them.
pub const GPU_BYTES_PER_TILE_PIXEL: u64 = 260;
/// The most GPU memory a node's tiles may take together ([`GPU_BYTES_PER_TILE_PIXEL`] times their
/// pixels): 8 GiB, about 33 million pixels (three 3840x2160 tiles, or fifteen 1920x1080).
pub const MAX_NODE_GPU_BYTES: u64 = 8 << 30;
/// Default vertical field of view of the wall camera, degrees (that of [`Camera::framing`]).
pub const DEFAULT_FOV_Y_DEG: f64 = crate::camera::DEFAULT_FOV_Y_DEG;
/// Names a node may not have: its certificate files would clash with the CA's and the controller's.
pub const RESERVED_NODE_NAMES: [&str; 2] = ["ca", "controller"];

/// A whole wall, as read from its config file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WallConfig {
    pub wall: WallSection,
    #[serde(default)]
    pub camera: CameraConfig,
    pub volume: VolumeConfig,
    #[serde(default)]
    pub render: RenderConfig,
    #[serde(default)]
    pub certificates: CertConfig,
    #[serde(default)]
    pub tiles: Vec<TileConfig>,
    #[serde(default)]
    pub nodes: Vec<NodeConfig>,
    /// `[joystick]`: the gamepad mapping of `isowall session` (optional).
    #[serde(default)]
    pub joystick: crate::joystick::JoystickConfig,
    /// The config file (relative paths in it are relative to its folder).
    #[serde(skip)]
    pub path: PathBuf,
}

/// `[wall]`: the wall's name and limits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WallSection {
    pub name: String,
    /// Frame deadline of the swap barrier, milliseconds.
    #[serde(default = "default_deadline_ms")]
    pub deadline_ms: u64,
    /// The largest network message accepted, bytes.
    #[serde(default = "default_message_limit_bytes")]
    pub message_limit_bytes: u64,
    // object space
    /// `screen` (each node renders its tiles; the default) or `object` (each node renders its
    /// brick of the volume, composited by depth: `bricks.rs`).
    #[serde(default)]
    pub mode: WallMode,
    /// Object space: compress the pixels nodes send each other (lz4); `false` sends them raw.
    #[serde(default = "default_compress")]
    pub compress: bool,
    /// The timed swap's margin from a frame's release to its present time: `"auto"` (learned,
    /// the default), milliseconds, or `"off"` (each node presents when its Swap arrives).
    #[serde(default)]
    pub swap_margin_ms: WordOrNumber,
    /// Frames a second the wall presents at, on a steady grid (e.g. 60 or 30), or `"unpaced"`
    /// (the default: each frame as soon as it is ready).
    #[serde(default)]
    pub frame_rate: Option<WordOrNumber>,
    /// Screen space: share the work of busy tiles with idle nodes (`crate::balance`): each
    /// frame the controller cuts the wall into work rectangles of equal expected cost, and a
    /// node sends the rectangles of other nodes' tiles it rendered to their owners. `false` (the
    /// default): every node renders its own tiles.
    #[serde(default)]
    pub balance: bool,
    /// The real-time priority (`SCHED_FIFO`, 1..=99) of each node's presenting thread, the one
    /// thread that waits for a swap's present time and presents; 0: normal scheduling. A node's
    /// `[[nodes]] present_priority` overrides it.
    #[serde(default = "default_present_priority")]
    pub present_priority: u8,
}

/// The presenting thread's real-time priority by default: modest (audio servers run at 70-90;
/// any real-time priority wakes before every normal thread).
pub const DEFAULT_PRESENT_PRIORITY: u8 = 10;
/// The highest `SCHED_FIFO` priority.
pub const MAX_PRESENT_PRIORITY: u8 = 99;

fn default_present_priority() -> u8 {
    DEFAULT_PRESENT_PRIORITY
}

/// A config value that is a word or a number (`swap_margin_ms = "auto"` or `= 1.5`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum WordOrNumber {
    Word(String),
    Number(f64),
}

impl Default for WordOrNumber {
    fn default() -> Self {
        WordOrNumber::Word("auto".into())
    }
}

/// The most frames a second `[wall] frame_rate` may ask for.
pub const MAX_FRAME_RATE: f64 = 1000.0;

impl WallSection {
    /// `swap_margin_ms` read (the config's validation reports a bad one).
    pub fn swap_margin(&self) -> Result<crate::swap_timing::MarginSetting, String> {
        match &self.swap_margin_ms {
            WordOrNumber::Word(w) => w.parse(),
            WordOrNumber::Number(ms) => crate::swap_timing::MarginSetting::from_ms(*ms),
        }
    }

    /// `frame_rate` read: `None` unpaced (the config's validation reports a bad one).
    pub fn frame_rate(&self) -> Result<Option<f64>, String> {
        match &self.frame_rate {
            None => Ok(None),
            Some(WordOrNumber::Word(w)) if w.trim().eq_ignore_ascii_case("unpaced") => Ok(None),
            Some(WordOrNumber::Word(w)) => {
                Err(format!("frame rate {w:?} is not a number of frames a second or `unpaced`"))
            }
            Some(WordOrNumber::Number(r)) if *r > 0.0 && *r <= MAX_FRAME_RATE => Ok(Some(*r)),
            Some(WordOrNumber::Number(r)) => {
                Err(format!("frame rate {r} is not in (0, {MAX_FRAME_RATE}] frames a second"))
            }
        }
    }

    /// The wall's swap timing, as the config says (defaults where it is silent or wrong: the
    /// config's validation has reported that).
    pub fn swap_timing(&self) -> crate::swap_timing::SwapTiming {
        crate::swap_timing::SwapTiming::new(
            self.swap_margin().unwrap_or_default(),
            self.frame_rate().unwrap_or_default(),
        )
    }
}

/// How a wall distributes its work (DESIGN.md "Distribution").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WallMode {
    /// Sort-first: each node renders the pixels of its tiles from the whole volume.
    #[default]
    Screen,
    /// Sort-last: each node renders its brick; tile owners keep the nearest hit per pixel.
    Object,
}

fn default_compress() -> bool {
    true
}

fn default_deadline_ms() -> u64 {
    DEFAULT_DEADLINE_MS
}

fn default_message_limit_bytes() -> u64 {
    DEFAULT_MESSAGE_LIMIT_BYTES
}

/// `[camera]`: the one wall camera over the whole wall image. Omitted fields are filled by
/// [`WallConfig::camera_for`] once the volume's box is known.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// `None`: a view that frames the volume (see [`WallConfig::camera_for`]).
    pub eye: Option<[f64; 3]>,
    /// A named view (not with `eye`): the side of the patient the camera looks from.
    pub view: Option<ViewPreset>,
    /// `None`: the volume's centre.
    pub target: Option<[f64; 3]>,
    pub up: [f64; 3],
    /// Vertical field of view over the whole wall image, degrees.
    pub fov_y: f64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig { eye: None, view: None, target: None, up: [0.0, 0.0, 1.0], fov_y: DEFAULT_FOV_Y_DEG }
    }
}

/// `[volume]`: what is rendered.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeConfig {
    /// `PATH` (relative to the config file's folder) or `procedural:NAME[:N]`.
    pub source: String,
    /// The iso value in data units; `None`: the procedural volume's own, or the data's mid-range.
    #[serde(default)]
    pub iso: Option<f64>,
    /// Raw files only: dimensions (nx, ny, nz).
    #[serde(default)]
    pub dims: Option<[usize; 3]>,
    /// Raw files only: the voxel type (`uint8`, `int16`, `float32`, ...).
    #[serde(default, rename = "type")]
    pub voxel_type: Option<String>,
    /// Raw files only: the spacing (world units per voxel; default 1).
    #[serde(default)]
    pub spacing: Option<[f64; 3]>,
    /// DICOM only: the SeriesInstanceUID to read where the folder holds several series.
    #[serde(default)]
    pub series: Option<String>,
    /// The most bytes the volume may take on a node as float32 (4 a voxel), checked from the
    /// file's header before it is read; `None`: 2 GiB. A node also holds it to its GPU's largest
    /// storage binding.
    #[serde(default)]
    pub max_bytes: Option<u64>,
    /// Time-varying volumes: the bytes of time steps a node keeps loaded from the one it shows
    /// on (prefetch); `None`: [`DEFAULT_CACHE_BYTES`].
    #[serde(default)]
    pub cache_bytes: Option<u64>,
    /// The brick cache (DESIGN.md "Large volumes"): where given, a node reads the volume through
    /// a GPU pool of bricks of this many MiB, refined where its tiles look, instead of loading it
    /// whole (`max_bytes` then bounds only what a source that cannot be read by bricks loads).
    #[serde(default)]
    pub gpu_budget_mb: Option<u64>,
    /// The decoded bricks a node holds in memory, MiB (default twice `gpu_budget_mb`).
    #[serde(default)]
    pub host_budget_mb: Option<u64>,
    /// The most a node uploads to its pool in one frame, MiB (default a sixteenth of
    /// `gpu_budget_mb`).
    #[serde(default)]
    pub upload_mb_per_frame: Option<f64>,
}

/// `[render]`: the defaults of the render state (the controller may change them per frame).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RenderConfig {
    pub shading: Shading,
    pub ao_samples: u32,
    /// World units or `"unbounded"`; omitted: [`AoRadius::Default`] (8 voxels).
    #[serde(with = "ao_radius_serde")]
    pub ao_radius: AoRadius,
    pub ao_method: AoMethod,
    pub ao_sequence: AoSequence,
    pub ibl: IblMethod,
    /// `sky`, an equirectangular `FILE.hdr` or a cube-map `DIR` (relative to the config's folder).
    pub env: String,
    /// `None`: [`DEFAULT_EXPOSURE`] (as `isowalld render`).
    pub exposure: Option<f64>,
    /// The quality governor's target frame time (ms); `None`: off (`ao_samples` every frame).
    pub target_frame_ms: Option<f64>,
    /// The spatial filter of the occlusion and IBL terms (`off` | `on` | `auto`).
    pub denoise: DenoiseSetting,
}

/// `[render] denoise`: the spatial filter of the occlusion and IBL terms, or `auto` (the default):
/// on where the quality governor sets the frame time (`target_frame_ms`) and there are AO samples
/// to filter. A governed wall renders its moving frames at few samples, the noisiest images it
/// shows; the filter's strength falls as still frames accumulate samples
/// (`isowall_render::denoise::strength`), so the still image converges to the unfiltered one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum DenoiseSetting {
    Off,
    On,
    #[default]
    Auto,
}

impl DenoiseSetting {
    /// The filter a wall with this setting renders with: `auto` is on with a governor's target
    /// and AO samples, off otherwise.
    pub fn resolve(self, target_frame_ms: Option<f64>, ao_samples: u32) -> Denoise {
        match self {
            DenoiseSetting::Off => Denoise::Off,
            DenoiseSetting::On => Denoise::On,
            DenoiseSetting::Auto if target_frame_ms.is_some() && ao_samples > 0 => Denoise::On,
            DenoiseSetting::Auto => Denoise::Off,
        }
    }
}

impl From<Denoise> for DenoiseSetting {
    fn from(d: Denoise) -> DenoiseSetting {
        match d {
            Denoise::Off => DenoiseSetting::Off,
            Denoise::On => DenoiseSetting::On,
        }
    }
}

impl Default for RenderConfig {
    fn default() -> Self {
        RenderConfig {
            shading: Shading::default(),
            ao_samples: 0,
            ao_radius: AoRadius::Default,
            ao_method: AoMethod::default(),
            ao_sequence: AoSequence::default(),
            ibl: IblMethod::default(),
            env: "sky".into(),
            exposure: None,
            target_frame_ms: None,
            denoise: DenoiseSetting::Auto,
        }
    }
}

/// `ao_radius`: a number (world units) or the string `"unbounded"`.
mod ao_radius_serde {
    use crate::render_state::AoRadius;
    use serde::de::{self, Visitor};
    use serde::{Deserializer, Serializer};
    use std::fmt;

    pub fn serialize<S: Serializer>(r: &AoRadius, s: S) -> Result<S::Ok, S::Error> {
        match r {
            AoRadius::Default => s.serialize_none(),
            AoRadius::World(r) => s.serialize_f64(*r),
            AoRadius::Unbounded => s.serialize_str("unbounded"),
        }
    }

    struct RadiusVisitor;

    impl Visitor<'_> for RadiusVisitor {
        type Value = AoRadius;
        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("a radius in world units (a number > 0) or \"unbounded\"")
        }
        fn visit_f64<E: de::Error>(self, v: f64) -> Result<AoRadius, E> {
            Ok(AoRadius::World(v))
        }
        fn visit_i64<E: de::Error>(self, v: i64) -> Result<AoRadius, E> {
            Ok(AoRadius::World(v as f64))
        }
        fn visit_u64<E: de::Error>(self, v: u64) -> Result<AoRadius, E> {
            Ok(AoRadius::World(v as f64))
        }
        fn visit_str<E: de::Error>(self, v: &str) -> Result<AoRadius, E> {
            if v == "unbounded" {
                Ok(AoRadius::Unbounded)
            } else {
                Err(E::invalid_value(de::Unexpected::Str(v), &self))
            }
        }
        fn visit_none<E: de::Error>(self) -> Result<AoRadius, E> {
            Ok(AoRadius::Default)
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<AoRadius, D::Error> {
        d.deserialize_any(RadiusVisitor)
    }
}

/// `[certificates]`: where the wall's own certificates are (made by `isowall keygen`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CertConfig {
    /// Relative to the config file's folder; holds `ca.pem`, `<node>.pem`/`.key` and
    /// `controller.pem`/`.key`.
    pub dir: String,
}

impl Default for CertConfig {
    fn default() -> Self {
        CertConfig { dir: "keys".into() }
    }
}

/// `[[tiles]]`: one screen, a rectangle of the wall image.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TileConfig {
    pub name: String,
    /// Top-left visible pixel, in whole-wall pixels.
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
    /// Hidden mullion pixels: left, right, top, bottom.
    #[serde(default)]
    pub bezel: [u32; 4],
}

impl TileConfig {
    /// The tile's visible pixels as a rectangle of the wall image.
    pub fn rect(&self) -> Rect {
        Rect { x: self.x, y: self.y, width: self.width, height: self.height }
    }

    /// The tile with its bezels, `[x0, x1) x [y0, y1)` in wall pixels (x0, y0 may be negative in
    /// an invalid config; validation refuses that).
    pub fn outer(&self) -> (i64, i64, i64, i64) {
        let [l, r, t, b] = self.bezel.map(i64::from);
        let (x, y, w, h) = (self.x as i64, self.y as i64, self.width as i64, self.height as i64);
        (x - l, x + w + r, y - t, y + h + b)
    }
}

/// `[[nodes]]`: one wall node (an `isowalld`) and the tiles it drives.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeConfig {
    pub name: String,
    /// `host:port` (QUIC over UDP); `[v6]:port` for IPv6 literals.
    pub address: String,
    #[serde(default)]
    pub tiles: Vec<String>,
    /// This node's presenting thread's real-time priority, over `[wall] present_priority`.
    #[serde(default)]
    pub present_priority: Option<u8>,
    /// A core of its own for the presenting thread (its number, from 0); the render threads are
    /// kept off it.
    #[serde(default)]
    pub present_cpu: Option<usize>,
}

/// The most cores a `present_cpu` may name.
pub const MAX_PRESENT_CPU: usize = 4095;

impl NodeConfig {
    /// Its presenting thread's priority: its own, else the wall's (0: normal scheduling).
    pub fn present_priority(&self, wall: &WallSection) -> u8 {
        self.present_priority.unwrap_or(wall.present_priority)
    }
}

const SECTIONS: [&str; 8] =
    ["wall", "camera", "volume", "render", "certificates", "tiles", "nodes", "joystick"];

impl WallConfig {
    /// Parses and validates a config, collecting every problem. `path` names the file in messages
    /// and anchors relative paths; nothing is read here.
    pub fn parse(text: &str, path: &Path) -> Result<WallConfig, ConfigErrors> {
        let (root, syntax) = DeTable::parse_recoverable(text);
        let mut doc = Doc { text, root, problems: Vec::new() };
        if !syntax.is_empty() {
            // A syntax error makes the parser resynchronise, often reporting knock-on errors on the
            // same line: one per line is what helps.
            let mut lines = std::collections::BTreeSet::new();
            for e in syntax {
                let line = e.span().map(|s| line_column(text, s.start).0);
                if lines.insert(line) {
                    doc.at_span(e.span(), e.message().to_string());
                }
            }
            return Err(doc.into_errors(path));
        }

        // Unknown top-level keys.
        let unknown: Vec<(Range<usize>, String)> = doc
            .root
            .get_ref()
            .iter()
            .filter(|(k, _)| !SECTIONS.contains(&k.get_ref().as_ref()))
            .map(|(k, _)| (k.span(), k.get_ref().to_string()))
            .collect();
        for (span, key) in unknown {
            let expected: Vec<String> = SECTIONS.iter().map(|s| format!("`{s}`")).collect();
            doc.at_span(
                Some(span),
                format!("unknown field `{key}`, expected one of {}", expected.join(", ")),
            );
        }

        let wall: Option<WallSection> = match doc_value(&doc, "wall") {
            Some(v) => doc.de(&v),
            None => {
                doc.at_missing(
                    &[Seg::K("wall")],
                    "missing table [wall] (with at least `name`) up to the end of the file",
                );
                None
            }
        };
        let camera: Option<CameraConfig> = match doc_value(&doc, "camera") {
            Some(v) => doc.de(&v),
            None => Some(CameraConfig::default()),
        };
        let volume: Option<VolumeConfig> = match doc_value(&doc, "volume") {
            Some(v) => doc.de(&v),
            None => {
                doc.at_missing(
                    &[Seg::K("volume")],
                    "missing table [volume] (with at least `source`) up to the end of the file",
                );
                None
            }
        };
        let render: Option<RenderConfig> = match doc_value(&doc, "render") {
            Some(v) => doc.de(&v),
            None => Some(RenderConfig::default()),
        };
        let certificates: Option<CertConfig> = match doc_value(&doc, "certificates") {
            Some(v) => doc.de(&v),
            None => Some(CertConfig::default()),
        };
        let tiles = doc_list::<TileConfig>(&mut doc, "tiles");
        let nodes = doc_list::<NodeConfig>(&mut doc, "nodes");
        let joystick: Option<crate::joystick::JoystickConfig> = match doc_value(&doc, "joystick") {
            Some(v) => doc.de(&v),
            None => Some(Default::default()),
        };
        for (field, message) in joystick.iter().flat_map(|j| j.problems()) {
            doc.at(&[Seg::K("joystick"), Seg::K(field)], message);
        }

        if let Some(w) = &wall {
            validate_wall(&mut doc, w);
        }
        if let Some(c) = &camera {
            validate_camera(&mut doc, c);
        }
        if let Some(v) = &volume {
            validate_volume(&mut doc, v);
        }
        if let Some(r) = &render {
            validate_render(&mut doc, r);
        }
        // object space: the halo bounds the AO reach. `denoise = "on"` is accepted there: the
        // filter runs on the composited tile, whose guard band travels too.
        if let (Some(w), Some(r)) = (&wall, &render) {
            if w.mode == WallMode::Object {
                let mut s = RenderSettings::new(0.0);
                s.ao.radius = r.ao_radius;
                s.ao.method = r.ao_method;
                if let Err(e) = crate::bricks::ao_reach(&s, DVec3::ONE) {
                    let key = if r.ao_method == AoMethod::Seed { "ao_method" } else { "ao_radius" };
                    doc.at(&[Seg::K("render"), Seg::K(key)], format!("render: {key}: {e}"));
                }
            }
        }
        // The brick cache serves screen space; object space reads each node's brick whole.
        if let (Some(w), Some(v)) = (&wall, &volume) {
            if w.mode == WallMode::Object && v.gpu_budget_mb.is_some() {
                doc.at(
                    &[Seg::K("volume"), Seg::K("gpu_budget_mb")],
                    "volume: `gpu_budget_mb` is for screen space (balanced or not): in object space each node reads its own brick whole, within `max_bytes`",
                );
            }
        }
        if let Some(c) = &certificates {
            if c.dir.trim().is_empty() {
                doc.at(&[Seg::K("certificates"), Seg::K("dir")], "certificates: `dir` is empty");
            }
        }
        validate_tiles(&mut doc, &tiles);
        validate_nodes(&mut doc, &nodes, &tiles);
        validate_wall_image(&mut doc, &tiles);
        validate_node_resources(&mut doc, &nodes, &tiles);
        if let Some(w) = &wall {
            validate_snapshot_size(&mut doc, w, &tiles, &nodes);
        }

        match (wall, camera, volume, render, certificates, joystick) {
            (Some(wall), Some(camera), Some(volume), Some(render), Some(certificates), Some(joystick))
                if doc.problems.is_empty() =>
            {
                Ok(WallConfig {
                    wall,
                    camera,
                    volume,
                    render,
                    certificates,
                    tiles: tiles.items.into_iter().map(|(_, t)| t).collect(),
                    nodes: nodes.items.into_iter().map(|(_, n)| n).collect(),
                    joystick,
                    path: path.to_path_buf(),
                })
            }
            _ => Err(doc.into_errors(path)),
        }
    }

    /// Reads the file and parses it ([`WallConfig::parse`]); a read error is a problem too. Only
    /// a regular file of at most [`MAX_CONFIG_BYTES`] is read (a FIFO or `/dev/zero` is refused
    /// at once, never read).
    pub fn load(path: &Path) -> Result<WallConfig, ConfigErrors> {
        let text = isowall_volume::io::regular::read_regular_text(path, MAX_CONFIG_BYTES)
            .map_err(|e| ConfigErrors::single(path, format!("cannot read the wall config: {e}")))?;
        WallConfig::parse(&text, path)
    }

    /// The full wall image in pixels: the largest right and bottom edges of the tiles, bezels
    /// included.
    pub fn wall_size(&self) -> (u32, u32) {
        let w = self.tiles.iter().map(|t| t.outer().1).max().unwrap_or(0);
        let h = self.tiles.iter().map(|t| t.outer().3).max().unwrap_or(0);
        (w.clamp(0, u32::MAX as i64) as u32, h.clamp(0, u32::MAX as i64) as u32)
    }

    pub fn tile(&self, name: &str) -> Option<&TileConfig> {
        self.tiles.iter().find(|t| t.name == name)
    }

    pub fn node(&self, name: &str) -> Option<&NodeConfig> {
        self.nodes.iter().find(|n| n.name == name)
    }

    /// The node that drives a tile.
    pub fn node_of_tile(&self, tile: &str) -> Option<&NodeConfig> {
        self.nodes.iter().find(|n| n.tiles.iter().any(|t| t == tile))
    }

    /// The tiles a node drives, in its order.
    pub fn tiles_of(&self, node: &str) -> Vec<&TileConfig> {
        self.node(node).map(|n| n.tiles.iter().filter_map(|t| self.tile(t)).collect()).unwrap_or_default()
    }

    /// What a tile shows: the wall camera over the whole wall image, the tile's pixels as the
    /// rectangle.
    pub fn tile_view(&self, camera: Camera, tile: &str) -> Option<View> {
        let t = self.tile(tile)?;
        Some(View { camera, full: self.wall_size(), rect: t.rect() })
    }

    /// The configured wall camera with its defaults filled for a volume box: target the box
    /// centre, and without `eye` the view [`Camera::framing`] picks for the whole wall image
    /// (the same direction, at the distance where the box fits with the configured target, up and
    /// field of view).
    pub fn camera_for(&self, box_min: DVec3, box_max: DVec3) -> Camera {
        self.camera_framing((box_min, box_max), (box_min, box_max), None)
    }

    /// The configured wall camera with its defaults filled for a scene: `volume` the volume's
    /// box, `fit` the box to frame (the object's at the iso, or the volume's), `orientation` the
    /// volume's. Target: the configured one, else the centre of `fit`. Without `eye`: from the
    /// configured `view`'s side with its up, else (an oriented scan) from the anterior, else with
    /// the configured up from the three-quarter direction of [`Camera::framing`]
    /// ([`crate::camera::default_side`]), at the distance where `fit` fits the whole wall image.
    pub fn camera_framing(
        &self,
        volume: (DVec3, DVec3),
        fit: (DVec3, DVec3),
        orientation: Option<Orientation>,
    ) -> Camera {
        let c = &self.camera;
        let target = c.target.map(DVec3::from_array);
        let configured_up = DVec3::from_array(c.up);
        match c.eye {
            Some(eye) => Camera {
                eye: DVec3::from_array(eye),
                target: target.unwrap_or(0.5 * (volume.0 + volume.1)),
                up: configured_up,
                fov_y_deg: c.fov_y,
            },
            None => {
                let (w, h) = self.wall_size();
                let (side, view_up) = crate::camera::default_side(c.view, orientation);
                let up = if c.view.is_some() || orientation.is_some() { view_up } else { configured_up };
                let target = target.unwrap_or(0.5 * (fit.0 + fit.1));
                Camera::framing_towards(fit.0, fit.1, target, side, up, c.fov_y, w.max(1), h.max(1))
            }
        }
    }

    /// The render state for a frame at `iso`, with the `[render]` defaults.
    pub fn render_settings(&self, iso: f64) -> RenderSettings {
        let r = &self.render;
        let mut s = RenderSettings::new(iso);
        s.shading = r.shading;
        s.ao.samples = r.ao_samples;
        s.ao.radius = r.ao_radius;
        s.ao.method = r.ao_method;
        s.ao.sequence = r.ao_sequence;
        s.ao.ibl = r.ibl;
        s.exposure = r.exposure.unwrap_or(DEFAULT_EXPOSURE);
        s.denoise = self.denoise(r.target_frame_ms);
        s
    }

    /// The filter this wall renders with when its governor aims at `target_frame_ms` (`None`: no
    /// governor): `[render] denoise` resolved ([`DenoiseSetting::resolve`]). In object space only
    /// `"on"` filters ([`WallConfig::filters_composited`]): `auto` stays off there, since the
    /// filter runs on the composited tile and the pixels that travels in (the shading form, with
    /// the guard band) cost about ten times the bytes of the colour form.
    pub fn denoise(&self, target_frame_ms: Option<f64>) -> Denoise {
        match self.wall.mode {
            WallMode::Object if self.filters_composited() => Denoise::On,
            WallMode::Object => Denoise::Off,
            WallMode::Screen => self.render.denoise.resolve(target_frame_ms, self.render.ao_samples),
        }
    }

    /// Whether this wall filters its *composited* tiles: an object-space wall with `[render]
    /// denoise = "on"`. Its nodes send their pixels in the shading form and composite each tile
    /// over the tile grown by the filter's guard band (`crate::composite`,
    /// `crate::object_machine`); the whole wall decides it from this one config.
    pub fn filters_composited(&self) -> bool {
        self.wall.mode == WallMode::Object && self.render.denoise == DenoiseSetting::On
    }

    /// A path relative to the config file's folder (absolute paths are kept).
    pub fn resolve(&self, relative: &str) -> PathBuf {
        let p = Path::new(relative);
        if p.is_absolute() {
            return p.to_path_buf();
        }
        match self.path.parent() {
            Some(dir) => dir.join(p),
            None => p.to_path_buf(),
        }
    }

    /// The certificates folder.
    pub fn cert_dir(&self) -> PathBuf {
        self.resolve(&self.certificates.dir)
    }

    /// The volume source with a relative PATH resolved (`procedural:...` unchanged) and the
    /// DICOM `series` chosen (`PATH?series=UID`).
    pub fn volume_source(&self) -> String {
        let s = &self.volume.source;
        if s.starts_with("procedural:") {
            s.clone()
        } else {
            let path = self.resolve(s).to_string_lossy().into_owned();
            match &self.volume.series {
                Some(uid) => format!("{path}{SERIES_SELECTOR}{uid}"),
                None => path,
            }
        }
    }

    /// How to read a raw volume file, from `[volume] dims`, `type` and `spacing`; `None` when the
    /// file has a header of its own (no `dims` and `type`).
    pub fn raw_spec(&self) -> Result<Option<RawSpec>, String> {
        let v = &self.volume;
        match (v.dims, &v.voxel_type) {
            (Some(dims), Some(t)) => Ok(Some(RawSpec {
                dims,
                voxel: t.parse().map_err(|e: String| format!("[volume] type: {e}"))?,
                spacing: DVec3::from_array(v.spacing.unwrap_or([1.0; 3])),
                big_endian: false,
                header_bytes: 0,
            })),
            _ => Ok(None),
        }
    }

    /// The brick cache's budgets where `[volume] gpu_budget_mb` is given (validated at load).
    pub fn brick_budgets(&self) -> Option<BrickBudgets> {
        let v = &self.volume;
        let mb = v.gpu_budget_mb?;
        BrickBudgets::from_mb(mb, v.host_budget_mb, v.upload_mb_per_frame).ok()
    }

    /// `[volume] cache_bytes`, or its default.
    pub fn cache_bytes(&self) -> u64 {
        self.volume.cache_bytes.unwrap_or(DEFAULT_CACHE_BYTES)
    }

    /// The environment of `[render] env`: `sky` unchanged, a FILE.hdr or DIR resolved.
    pub fn env_source(&self) -> String {
        let e = &self.render.env;
        if e.eq_ignore_ascii_case("sky") {
            e.clone()
        } else {
            self.resolve(e).to_string_lossy().into_owned()
        }
    }

    /// What `check-config FILE` prints, for both binaries: `Ok(text)` for a valid config (the
    /// file and a summary), `Err((problems, last line))` with every problem as FILE:LINE:COL.
    pub fn check_report(path: &Path) -> Result<String, (String, String)> {
        match WallConfig::load(path) {
            Ok(config) => Ok(format!("{}: ok\n{}", path.display(), config.summary())),
            Err(errors) => {
                let n = errors.problems.len();
                Err((
                    errors.to_string(),
                    format!("{}: {n} problem{}", path.display(), if n == 1 { "" } else { "s" }),
                ))
            }
        }
    }

    /// A short human summary: the wall, its image size, and the tiles of every node.
    pub fn summary(&self) -> String {
        let (w, h) = self.wall_size();
        let mut s = format!(
            "wall '{}': {w}x{h} px, {} tiles on {} nodes, volume {}",
            self.wall.name,
            self.tiles.len(),
            self.nodes.len(),
            self.volume.source
        );
        for n in &self.nodes {
            let tiles: Vec<String> = self
                .tiles_of(&n.name)
                .iter()
                .map(|t| format!("{} {}x{}+{}+{}", t.name, t.width, t.height, t.x, t.y))
                .collect();
            let list = if tiles.is_empty() { "(no tiles)".to_string() } else { tiles.join(", ") };
            s.push_str(&format!("\n  {} ({}): {list}", n.name, n.address));
        }
        s
    }
}
