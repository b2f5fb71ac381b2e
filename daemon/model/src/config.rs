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
//!
//! [camera]      # the one wall camera, over the whole wall image (DESIGN.md "Camera")
//! eye = [x, y, z]                 # optional: omitted -> a view that frames the volume
//! target = [x, y, z]              # optional: default the volume's centre
//! up = [0, 0, 1]                  # default +z
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
//!
//! [render]      # render-state defaults, all optional
//! shading = "blinn-phong"         # lambert | blinn-phong
//! ao_samples = 16
//! ao_radius = 8.0                 # world units or "unbounded"; omitted: 8 voxels
//! ao_method = "ours"              # ours | seed
//! ao_sequence = "sobol"           # sobol | r2: the 2D set of ours' directions
//! ibl = "bent"                    # none | seed | bent | rays
//! env = "sky"                     # sky | FILE.hdr | DIR (relative to this file's folder)
//! exposure = 0.6                  # default 0.6 with an IBL method, else 1
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
//! A tile is a window of the one wall image: its bezels are hidden pixels of that image, so a
//! straight line stays straight across a mullion (DESIGN.md "Camera"). The model reads no files:
//! [`WallConfig::parse`] takes the text; [`WallConfig::load`] is a thin helper that only reads it.

use crate::camera::{Camera, View, Window};
use crate::names::name_problem;
use crate::render_state::{AoMethod, AoRadius, AoSequence, IblMethod, RenderSettings, Shading};
use glam::DVec3;
use isowall_volume::io::{RawSpec, VoxelType};
use isowall_volume::procedural::Procedural;
use isowall_volume::source::SERIES_SELECTOR;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};
use toml::de::{DeTable, DeValue, ValueDeserializer};
use toml::Spanned;

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
/// Largest extent of the whole wall image along either axis, in pixels.
pub const MAX_WALL_EXTENT: u64 = 1 << 20;
/// Default vertical field of view of the wall camera, degrees (that of [`Camera::framing`]).
pub const DEFAULT_FOV_Y_DEG: f64 = 35.0;
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
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
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
    /// `None`: the volume's centre.
    pub target: Option<[f64; 3]>,
    pub up: [f64; 3],
    /// Vertical field of view over the whole wall image, degrees.
    pub fov_y: f64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig { eye: None, target: None, up: [0.0, 0.0, 1.0], fov_y: DEFAULT_FOV_Y_DEG }
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
    /// `None`: 0.6 with an IBL method, else 1 (as `isowalld render`).
    pub exposure: Option<f64>,
    /// The quality governor's target frame time (ms); `None`: off (`ao_samples` every frame).
    pub target_frame_ms: Option<f64>,
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

/// `[[tiles]]`: one screen, a window of the wall image.
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
    /// The tile's visible pixels as a window of the wall image.
    pub fn window(&self) -> Window {
        Window { x: self.x, y: self.y, width: self.width, height: self.height }
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
}

/// One problem in a config file, at a line and column (1-based) where one is known.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Problem {
    pub line: Option<usize>,
    pub column: Option<usize>,
    pub message: String,
}

/// Everything wrong with a config file. `Display` prints one problem per line,
/// `FILE:LINE:COL: message` (or `FILE: message` where there is no position).
#[derive(Debug)]
pub struct ConfigErrors {
    pub path: PathBuf,
    pub problems: Vec<Problem>,
}

impl ConfigErrors {
    /// A single problem without a position (e.g. the file cannot be read).
    pub fn single(path: &Path, message: impl Into<String>) -> ConfigErrors {
        ConfigErrors {
            path: path.to_path_buf(),
            problems: vec![Problem { line: None, column: None, message: message.into() }],
        }
    }
}

impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, p) in self.problems.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            match (p.line, p.column) {
                (Some(l), Some(c)) => write!(f, "{}:{l}:{c}: {}", self.path.display(), p.message)?,
                (Some(l), None) => write!(f, "{}:{l}: {}", self.path.display(), p.message)?,
                _ => write!(f, "{}: {}", self.path.display(), p.message)?,
            }
        }
        Ok(())
    }
}

impl std::error::Error for ConfigErrors {}

/// The 1-based line and column (in characters) of a byte offset of `text`.
pub fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let mut offset = offset.min(text.len());
    while !text.is_char_boundary(offset) {
        offset -= 1;
    }
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    (line, text[line_start..offset].chars().count() + 1)
}

/// One step of a path into the TOML document: a key or an array index.
#[derive(Clone, Copy, Debug)]
enum Seg<'s> {
    K(&'s str),
    I(usize),
}

/// The parsed document with its spans, to place problems found after parsing.
struct Doc<'a> {
    text: &'a str,
    root: Spanned<DeTable<'a>>,
    problems: Vec<(Option<Range<usize>>, String)>,
}

impl<'a> Doc<'a> {
    /// The span of the value at `path`, or of the nearest enclosing value that exists (a table's
    /// span is its header).
    fn span(&self, path: &[Seg]) -> Option<Range<usize>> {
        let mut best = None;
        let mut table: Option<&DeTable> = Some(self.root.get_ref());
        let mut value: Option<&Spanned<DeValue>> = None;
        for seg in path {
            let next = match (seg, table, value) {
                (Seg::K(k), Some(t), _) => t.iter().find(|(key, _)| key.get_ref() == k).map(|(_, v)| v),
                (Seg::I(i), _, Some(v)) => v.get_ref().as_array().and_then(|a| a.get(*i)),
                _ => None,
            };
            let Some(next) = next else { break };
            best = Some(next.span());
            value = Some(next);
            table = next.get_ref().as_table();
        }
        best
    }

    fn at(&mut self, path: &[Seg], message: impl Into<String>) {
        let span = self.span(path);
        self.problems.push((span, message.into()));
    }

    fn at_span(&mut self, span: Option<Range<usize>>, message: impl Into<String>) {
        self.problems.push((span, message.into()));
    }

    /// A problem with something the file lacks: at `path` where it is there but empty (`nodes =
    /// []`), else at the file's last line, where it would go.
    fn at_missing(&mut self, path: &[Seg], message: impl Into<String>) {
        let end = self.text.trim_end().len();
        let line_start = self.text[..end].rfind('\n').map_or(0, |i| i + 1);
        let span = self.span(path).unwrap_or(line_start..line_start);
        self.problems.push((Some(span), message.into()));
    }

    /// The line of the value at `path`, for messages that refer to another place.
    fn line_of(&self, path: &[Seg]) -> Option<usize> {
        self.span(path).map(|s| line_column(self.text, s.start).0)
    }

    fn value(&self, key: &str) -> Option<&Spanned<DeValue<'a>>> {
        self.root.get_ref().iter().find(|(k, _)| k.get_ref() == key).map(|(_, v)| v)
    }

    /// Deserializes one value, recording its error (if any) with its position.
    fn de<T: for<'de> Deserialize<'de>>(&mut self, value: &Spanned<DeValue<'a>>) -> Option<T> {
        match T::deserialize(ValueDeserializer::from(value.clone())) {
            Ok(t) => Some(t),
            Err(e) => {
                let span = e.span().or_else(|| Some(value.span()));
                self.at_span(span, e.message().to_string());
                None
            }
        }
    }

    fn into_errors(self, path: &Path) -> ConfigErrors {
        let text = self.text;
        let mut problems: Vec<Problem> = self
            .problems
            .into_iter()
            .map(|(span, message)| {
                let pos = span.map(|s| line_column(text, s.start));
                Problem { line: pos.map(|p| p.0), column: pos.map(|p| p.1), message }
            })
            .collect();
        // In file order, problems without a position last (a stable sort keeps equal positions
        // in the order found).
        problems.sort_by_key(|p| (p.line.is_none(), p.line, p.column));
        ConfigErrors { path: path.to_path_buf(), problems }
    }
}

fn doc_value<'a>(doc: &Doc<'a>, key: &str) -> Option<Spanned<DeValue<'a>>> {
    doc.value(key).cloned()
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
        // object space: the halo bounds the AO reach.
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
        if let Some(c) = &certificates {
            if c.dir.trim().is_empty() {
                doc.at(&[Seg::K("certificates"), Seg::K("dir")], "certificates: `dir` is empty");
            }
        }
        validate_tiles(&mut doc, &tiles);
        validate_nodes(&mut doc, &nodes, &tiles);
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

    /// Reads the file and parses it ([`WallConfig::parse`]); a read error is a problem too.
    pub fn load(path: &Path) -> Result<WallConfig, ConfigErrors> {
        let text = std::fs::read_to_string(path)
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

    /// What a tile shows: the wall camera over the whole wall image, the tile's pixels as the window.
    pub fn tile_view(&self, camera: Camera, tile: &str) -> Option<View> {
        let t = self.tile(tile)?;
        Some(View { camera, full: self.wall_size(), window: t.window() })
    }

    /// The configured wall camera with its defaults filled for a volume box: target the box
    /// centre, and without `eye` the view [`Camera::framing`] picks for the whole wall image
    /// (the same direction, at the distance where the box fits with the configured target, up and
    /// field of view).
    pub fn camera_for(&self, box_min: DVec3, box_max: DVec3) -> Camera {
        let c = &self.camera;
        let centre = 0.5 * (box_min + box_max);
        let target = c.target.map(DVec3::from_array).unwrap_or(centre);
        let up = DVec3::from_array(c.up);
        match c.eye {
            Some(eye) => Camera { eye: DVec3::from_array(eye), target, up, fov_y_deg: c.fov_y },
            None => {
                let (w, h) = self.wall_size();
                framing_with(box_min, box_max, target, up, c.fov_y, w.max(1), h.max(1))
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
        s.exposure = r.exposure.unwrap_or(if s.ibl_needs_environment() { 0.6 } else { 1.0 });
        s
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

/// [`Camera::framing`]'s view direction, generalised to a given target, up and field of view:
/// the distance where all eight corners fit a `width` x `height` image with a 5% margin, and the
/// whole box stays in front of the eye. With the box centre, +z and 35 degrees it is
/// `Camera::framing`.
fn framing_with(
    box_min: DVec3,
    box_max: DVec3,
    target: DVec3,
    up: DVec3,
    fov_y_deg: f64,
    width: u32,
    height: u32,
) -> Camera {
    let base = Camera::framing(box_min, box_max, width, height);
    let forward = (base.target - base.eye).normalize();
    let mut cam = Camera { eye: target - forward, target, up, fov_y_deg };
    if cam.validate().is_err() {
        // Up parallel to the framing direction, or a bad fov: give the camera as configured and
        // let the caller's validation say what is wrong.
        return cam;
    }
    let b = cam.basis();
    let tan_y = 0.95 * b.tan_half_fov;
    let tan_x = tan_y * width as f64 / height as f64;
    let mut dist: f64 = 1e-6;
    for i in 0..8 {
        let c = DVec3::new(
            if i & 1 == 0 { box_min.x } else { box_max.x },
            if i & 2 == 0 { box_min.y } else { box_max.y },
            if i & 4 == 0 { box_min.z } else { box_max.z },
        ) - target;
        let z = c.dot(b.forward);
        dist = dist.max(c.dot(b.right).abs() / tan_x - z).max(c.dot(b.up).abs() / tan_y - z);
    }
    let centre = 0.5 * (box_min + box_max);
    let reach = 0.5 * (box_max - box_min).length() + (target - centre).length();
    dist = dist.max(1.01 * reach.max(1e-6));
    cam.eye = target - dist * b.forward;
    cam
}

/// The items of `[[tiles]]` or `[[nodes]]` that parsed (with their index), and the names of those
/// that did not (so references to them are not reported twice).
struct Parsed<T> {
    items: Vec<(usize, T)>,
    failed_names: Vec<String>,
    any_failed: bool,
    present: bool,
}

fn doc_list<T: for<'de> Deserialize<'de>>(doc: &mut Doc<'_>, key: &str) -> Parsed<T> {
    let mut out = Parsed { items: Vec::new(), failed_names: Vec::new(), any_failed: false, present: false };
    let Some(value) = doc.value(key).cloned() else { return out };
    out.present = true;
    let Some(array) = value.get_ref().as_array() else {
        // Not an array: let serde say so.
        let _: Option<Vec<T>> = doc.de(&value);
        out.any_failed = true;
        return out;
    };
    for (i, item) in array.iter().enumerate() {
        match doc.de::<T>(item) {
            Some(t) => out.items.push((i, t)),
            None => {
                out.any_failed = true;
                if let Some(name) =
                    item.get_ref().as_table().and_then(|t| t.iter().find(|(k, _)| k.get_ref() == "name"))
                {
                    if let Some(s) = name.1.get_ref().as_str() {
                        out.failed_names.push(s.to_string());
                    }
                }
            }
        }
    }
    out
}

fn validate_wall(doc: &mut Doc<'_>, w: &WallSection) {
    let at = |f| [Seg::K("wall"), Seg::K(f)];
    if w.name.trim().is_empty() {
        doc.at(&at("name"), "wall: `name` is empty");
    }
    if !(1..=MAX_DEADLINE_MS).contains(&w.deadline_ms) {
        doc.at(
            &at("deadline_ms"),
            format!(
                "wall: `deadline_ms` {} is outside 1..={MAX_DEADLINE_MS} (a frame deadline of at most 10 minutes)",
                w.deadline_ms
            ),
        );
    }
    if !(MIN_MESSAGE_LIMIT_BYTES..=MAX_MESSAGE_LIMIT_BYTES).contains(&w.message_limit_bytes) {
        doc.at(
            &at("message_limit_bytes"),
            format!(
                "wall: `message_limit_bytes` {} is outside {MIN_MESSAGE_LIMIT_BYTES}..={MAX_MESSAGE_LIMIT_BYTES} \
                 (no decoder accepts a message over 1 GiB)",
                w.message_limit_bytes
            ),
        );
    }
}

/// A node's snapshot (one message with all its tiles) must fit the wall's message limit.
fn validate_snapshot_size(
    doc: &mut Doc<'_>,
    w: &WallSection,
    tiles: &Parsed<TileConfig>,
    nodes: &Parsed<NodeConfig>,
) {
    if !(MIN_MESSAGE_LIMIT_BYTES..=MAX_MESSAGE_LIMIT_BYTES).contains(&w.message_limit_bytes) {
        return; // reported on its own
    }
    for (i, n) in &nodes.items {
        let own: Vec<&TileConfig> = n
            .tiles
            .iter()
            .filter_map(|name| tiles.items.iter().map(|(_, t)| t).find(|t| t.name == *name))
            .collect();
        let need = crate::messages::TileImage::snapshot_len_bound(
            own.iter().map(|t| (t.name.as_str(), t.width, t.height)),
        );
        if need > w.message_limit_bytes {
            let names: Vec<&str> = own.iter().map(|t| t.name.as_str()).collect();
            let message = format!(
                "wall: `message_limit_bytes` {} is too small for the snapshot of node '{}' (tiles {}: up to \
                 {need} bytes in one message); raise it to at least {need}",
                w.message_limit_bytes,
                n.name,
                names.join(", ")
            );
            let given = doc
                .value("wall")
                .and_then(|v| v.get_ref().as_table())
                .is_some_and(|t| t.iter().any(|(k, _)| k.get_ref() == "message_limit_bytes"));
            if given {
                doc.at(&[Seg::K("wall"), Seg::K("message_limit_bytes")], message);
            } else {
                doc.at(&[Seg::K("nodes"), Seg::I(*i), Seg::K("tiles")], message);
            }
        }
    }
}

fn validate_camera(doc: &mut Doc<'_>, c: &CameraConfig) {
    let at = |f| [Seg::K("camera"), Seg::K(f)];
    let mut finite = true;
    for (name, v) in [("eye", c.eye), ("target", c.target), ("up", Some(c.up))] {
        if let Some(v) = v {
            if !v.iter().all(|x| x.is_finite()) {
                doc.at(&at(name), format!("camera: `{name}` {v:?} is not finite"));
                finite = false;
            }
        }
    }
    if finite && DVec3::from_array(c.up).length() == 0.0 {
        doc.at(&at("up"), "camera: `up` is the zero vector");
        finite = false;
    }
    if !(c.fov_y > 0.0 && c.fov_y < 180.0) {
        doc.at(&at("fov_y"), format!("camera: `fov_y` {} is outside (0, 180) degrees", c.fov_y));
    }
    if let (true, Some(eye), Some(target)) = (finite, c.eye, c.target) {
        let cam = Camera {
            eye: DVec3::from_array(eye),
            target: DVec3::from_array(target),
            up: DVec3::from_array(c.up),
            fov_y_deg: DEFAULT_FOV_Y_DEG,
        };
        match cam.validate() {
            Err(crate::camera::CameraError::EyeIsTarget(_)) => {
                doc.at(&at("eye"), "camera: `eye` and `target` coincide")
            }
            Err(crate::camera::CameraError::UpParallel { .. }) => {
                doc.at(&at("up"), "camera: `up` is parallel to the view direction (target - eye)")
            }
            _ => {}
        }
    }
}

fn validate_volume(doc: &mut Doc<'_>, v: &VolumeConfig) {
    let at = |f| [Seg::K("volume"), Seg::K(f)];
    let procedural = v.source.strip_prefix("procedural:");
    if v.source.trim().is_empty() {
        doc.at(&at("source"), "volume: `source` is empty");
    }
    if let Some(rest) = procedural {
        let (name, size) = match rest.split_once(':') {
            Some((n, s)) => (n, Some(s)),
            None => (rest, None),
        };
        if let Err(e) = name.parse::<Procedural>() {
            doc.at(&at("source"), format!("volume: {e}"));
        }
        if let Some(s) = size {
            match s.parse::<usize>() {
                Ok(n) if (2..=1024).contains(&n) => {}
                Ok(n) => doc.at(&at("source"), format!("volume: procedural size {n} is outside 2..=1024")),
                Err(_) => {
                    doc.at(&at("source"), format!("volume: procedural size '{s}' is not a whole number"))
                }
            }
        }
        for (field, given) in
            [("dims", v.dims.is_some()), ("type", v.voxel_type.is_some()), ("spacing", v.spacing.is_some())]
        {
            if given {
                doc.at(
                    &at(field),
                    format!("volume: `{field}` is for raw files only, not a procedural volume"),
                );
            }
        }
        if v.series.is_some() {
            doc.at(&at("series"), "volume: `series` is for DICOM folders only, not a procedural volume");
        }
    } else if v.dims.is_some() != v.voxel_type.is_some() || (v.spacing.is_some() && v.dims.is_none()) {
        let field = if v.dims.is_some() {
            "dims"
        } else if v.voxel_type.is_some() {
            "type"
        } else {
            "spacing"
        };
        doc.at(&at(field), "volume: a raw volume needs both `dims` and `type` (and optionally `spacing`)");
    }
    if let Some(iso) = v.iso {
        if !iso.is_finite() {
            doc.at(&at("iso"), format!("volume: `iso` {iso} is not a finite number"));
        }
    }
    if let Some(d) = v.dims {
        if d.contains(&0) {
            doc.at(&at("dims"), format!("volume: `dims` {d:?} has a zero dimension"));
        }
    }
    if let Some(t) = &v.voxel_type {
        if let Err(e) = t.parse::<VoxelType>() {
            doc.at(&at("type"), format!("volume: {e}"));
        }
    }
    if let Some(s) = v.spacing {
        if !s.iter().all(|x| x.is_finite() && *x > 0.0) {
            doc.at(&at("spacing"), format!("volume: `spacing` {s:?} must be finite and > 0"));
        }
    }
    if let Some(b) = v.cache_bytes {
        if b > MAX_CACHE_BYTES {
            doc.at(
                &at("cache_bytes"),
                format!("volume: `cache_bytes` {b} is over the limit of {MAX_CACHE_BYTES} (1 TiB)"),
            );
        }
        if v.source.starts_with("procedural:") {
            doc.at(&at("cache_bytes"), "volume: `cache_bytes` is for time steps, not a procedural volume");
        }
    }
    if let Some(b) = v.max_bytes {
        if !(4..=MAX_VOLUME_BYTES).contains(&b) {
            doc.at(
                &at("max_bytes"),
                format!("volume: `max_bytes` {b} is outside 4..={MAX_VOLUME_BYTES} (one voxel to 2^30 voxels as float32)"),
            );
        }
    }
}

fn validate_render(doc: &mut Doc<'_>, r: &RenderConfig) {
    for (field, message) in render_problems(r) {
        doc.at(&[Seg::K("render"), Seg::K(field)], message);
    }
}

/// The problems of a `[render]` table, each with the field it is about: the rules of the config
/// file, also applied to render settings changed while the wall runs (the operator console).
pub fn render_problems(r: &RenderConfig) -> Vec<(&'static str, String)> {
    let mut problems = Vec::new();
    if let AoRadius::World(radius) = r.ao_radius {
        if !(radius.is_finite() && radius > 0.0) {
            problems
                .push(("ao_radius", format!("render: `ao_radius` {radius} must be > 0 (or \"unbounded\")")));
        }
    }
    if r.ao_samples > crate::render_state::MAX_AO_SAMPLES {
        problems.push((
            "ao_samples",
            format!(
                "render: `ao_samples` {} is more than {} per frame (accumulate frames instead)",
                r.ao_samples,
                crate::render_state::MAX_AO_SAMPLES
            ),
        ));
    }
    if let Some(x) = r.exposure {
        if !(x.is_finite() && x >= 0.0) {
            problems.push(("exposure", format!("render: `exposure` {x} must be a finite number >= 0")));
        }
    }
    if let Some(t) = r.target_frame_ms {
        if let Err(e) = crate::governor::Governor::new(t, 1, 1, 1) {
            problems.push(("target_frame_ms", format!("render: `target_frame_ms`: {e}")));
        }
    }
    if r.env.trim().is_empty() {
        problems.push(("env", "render: `env` is empty (sky, FILE.hdr or DIR)".to_string()));
    }
    problems
}

fn validate_tiles(doc: &mut Doc<'_>, tiles: &Parsed<TileConfig>) {
    if !tiles.present || (tiles.items.is_empty() && !tiles.any_failed) {
        doc.at_missing(&[Seg::K("tiles")], "no tiles: a wall needs at least one [[tiles]] table");
        return;
    }
    let at = |i: usize, f: &'static str| [Seg::K("tiles"), Seg::I(i), Seg::K(f)];
    for (i, t) in &tiles.items {
        let i = *i;
        if let Some(p) = name_problem(&t.name) {
            doc.at(&at(i, "name"), format!("tile name {p}"));
        }
        for (field, v) in [("width", t.width), ("height", t.height)] {
            if !(1..=MAX_TILE_SIZE).contains(&v) {
                doc.at(
                    &at(i, field),
                    format!("tile '{}': `{field}` {v} is outside 1..={MAX_TILE_SIZE}", t.name),
                );
            }
        }
        if t.bezel.iter().any(|&b| b > MAX_TILE_SIZE) {
            doc.at(
                &at(i, "bezel"),
                format!("tile '{}': `bezel` {:?} has a width over {MAX_TILE_SIZE}", t.name, t.bezel),
            );
        }
        if t.bezel[0] > t.x {
            doc.at(
                &at(i, "bezel"),
                format!(
                    "tile '{}': its left bezel ({} px) reaches past the wall's left edge (x = {})",
                    t.name, t.bezel[0], t.x
                ),
            );
        }
        if t.bezel[2] > t.y {
            doc.at(
                &at(i, "bezel"),
                format!(
                    "tile '{}': its top bezel ({} px) reaches past the wall's top edge (y = {})",
                    t.name, t.bezel[2], t.y
                ),
            );
        }
        let (_, x1, _, y1) = t.outer();
        if x1 as u64 > MAX_WALL_EXTENT || y1 as u64 > MAX_WALL_EXTENT {
            doc.at(
                &at(i, "x"),
                format!(
                    "tile '{}': reaches pixel ({x1}, {y1}), beyond the largest wall image ({MAX_WALL_EXTENT} px a side)",
                    t.name
                ),
            );
        }
    }
    // Unique names.
    for (a, (i, t)) in tiles.items.iter().enumerate() {
        if let Some((j, _)) = tiles.items[..a].iter().find(|(_, u)| u.name == t.name) {
            let first =
                doc.line_of(&at(*j, "name")).map(|l| format!(" (first at line {l})")).unwrap_or_default();
            doc.at(&at(*i, "name"), format!("duplicate tile name '{}'{first}", t.name));
        }
    }
    // No overlaps, bezels included.
    for (a, (i, t)) in tiles.items.iter().enumerate() {
        let (ax0, ax1, ay0, ay1) = t.outer();
        for (j, u) in &tiles.items[..a] {
            let (bx0, bx1, by0, by1) = u.outer();
            if ax0 < bx1 && bx0 < ax1 && ay0 < by1 && by0 < ay1 {
                let other = doc
                    .line_of(&[Seg::K("tiles"), Seg::I(*j)])
                    .map(|l| format!(" (line {l})"))
                    .unwrap_or_default();
                doc.at(
                    &[Seg::K("tiles"), Seg::I(*i)],
                    format!(
                        "tile '{}' overlaps tile '{}'{other}, bezels included: x {ax0}..{ax1}, y {ay0}..{ay1} \
                         against x {bx0}..{bx1}, y {by0}..{by1}",
                        t.name, u.name
                    ),
                );
            }
        }
    }
}

/// Checks `host:port` (or `[v6]:port`): a valid port (1..=65535) and a plausible host name or IP
/// literal. Names are not resolved.
pub fn check_address(address: &str) -> Result<(), String> {
    parse_address(address).map(|_| ())
}

/// Where a node address leads, as far as the text says (the model does no I/O, so names other
/// than `localhost` are not resolved): an IP address (an IPv4-mapped IPv6 address as the IPv4
/// one), the loopback name (`localhost` and `*.localhost`, RFC 6761: 127.0.0.1 and ::1), or a
/// host name without regard to case or a final dot; and the port.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum AddressHost {
    Ip(std::net::IpAddr),
    Localhost,
    Name(String),
}

/// A node address, parsed: [`AddressHost`] and port.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NodeAddress {
    pub host: AddressHost,
    pub port: u16,
}

impl NodeAddress {
    /// Whether two addresses lead to the same socket: the same port, and the same IP address,
    /// the same name, or `localhost` and 127.0.0.1 or ::1.
    pub fn same_place(&self, other: &NodeAddress) -> bool {
        let loopback = |ip: &std::net::IpAddr| match ip {
            std::net::IpAddr::V4(v4) => *v4 == std::net::Ipv4Addr::LOCALHOST,
            std::net::IpAddr::V6(v6) => *v6 == std::net::Ipv6Addr::LOCALHOST,
        };
        self.port == other.port
            && match (&self.host, &other.host) {
                (AddressHost::Localhost, AddressHost::Ip(ip))
                | (AddressHost::Ip(ip), AddressHost::Localhost) => loopback(ip),
                (a, b) => a == b,
            }
    }
}

/// Parses `host:port` (or `[v6]:port`), as [`check_address`] checks it.
pub fn parse_address(address: &str) -> Result<NodeAddress, String> {
    use std::net::IpAddr;
    let ip_host = |ip: IpAddr| -> Result<AddressHost, String> {
        let ip = match ip {
            IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(IpAddr::V6(v6), IpAddr::V4),
            v4 => v4,
        };
        if ip.is_unspecified() {
            return Err(format!(
                "'{address}': {ip} is the unspecified address, which no controller or peer can reach: \
                 give the node's own address"
            ));
        }
        Ok(AddressHost::Ip(ip))
    };
    if let Some(rest) = address.strip_prefix('[') {
        let Some((host, port)) = rest.split_once("]:") else {
            return Err(format!("'{address}' is not [IPv6]:port"));
        };
        let ip =
            host.parse::<std::net::Ipv6Addr>().map_err(|_| format!("'{host}' is not an IPv6 address"))?;
        return Ok(NodeAddress { host: ip_host(IpAddr::V6(ip))?, port: parse_port(address, port)? });
    }
    let Some((host, port)) = address.rsplit_once(':') else {
        return Err(format!("'{address}' is not host:port (the port is missing)"));
    };
    if host.is_empty() {
        return Err(format!("'{address}' has no host"));
    }
    if host.contains(':') {
        return Err(format!("'{address}': write an IPv6 address in brackets, [addr]:port"));
    }
    let port = parse_port(address, port)?;
    if let Ok(ip) = host.parse::<std::net::Ipv4Addr>() {
        return Ok(NodeAddress { host: ip_host(IpAddr::V4(ip))?, port });
    }
    let label_ok = |l: &str| {
        !l.is_empty()
            && l.len() <= 63
            && l.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
            && !l.starts_with('-')
            && !l.ends_with('-')
    };
    let name = host.strip_suffix('.').unwrap_or(host).to_ascii_lowercase();
    if host.len() > 253 || !name.split('.').all(label_ok) {
        return Err(format!("'{host}' is not a valid host name or IP address"));
    }
    let host = if name == "localhost" || name.ends_with(".localhost") {
        AddressHost::Localhost
    } else {
        AddressHost::Name(name)
    };
    Ok(NodeAddress { host, port })
}

fn parse_port(address: &str, port: &str) -> Result<u16, String> {
    match port.parse::<u16>() {
        Ok(p) if p > 0 => Ok(p),
        _ => Err(format!("'{address}': port '{port}' is not in 1..=65535")),
    }
}

/// Whether two node addresses lead to the same socket ([`NodeAddress::same_place`]); an address
/// that does not parse is reported on its own.
fn same_address(a: &str, b: &str) -> bool {
    match (parse_address(a), parse_address(b)) {
        (Ok(a), Ok(b)) => a.same_place(&b),
        _ => false,
    }
}

fn validate_nodes(doc: &mut Doc<'_>, nodes: &Parsed<NodeConfig>, tiles: &Parsed<TileConfig>) {
    if !nodes.present || (nodes.items.is_empty() && !nodes.any_failed) {
        doc.at_missing(&[Seg::K("nodes")], "no nodes: a wall needs at least one [[nodes]] table");
        return;
    }
    let at = |i: usize, f: &'static str| [Seg::K("nodes"), Seg::I(i), Seg::K(f)];
    for (i, n) in &nodes.items {
        let i = *i;
        if let Some(p) = name_problem(&n.name) {
            doc.at(&at(i, "name"), format!("node name {p}"));
        } else if RESERVED_NODE_NAMES.iter().any(|r| r.eq_ignore_ascii_case(&n.name)) {
            doc.at(
                &at(i, "name"),
                format!("node name '{}' is reserved (its certificate files would clash)", n.name),
            );
        }
        if let Err(e) = check_address(&n.address) {
            doc.at(&at(i, "address"), format!("node '{}': address {e}", n.name));
        }
    }
    for (a, (i, n)) in nodes.items.iter().enumerate() {
        // TLS compares names without regard to case: `NODE0` beside `node0` could pose as it.
        if let Some((j, m)) = nodes.items[..a].iter().find(|(_, m)| m.name.eq_ignore_ascii_case(&n.name)) {
            let first =
                doc.line_of(&at(*j, "name")).map(|l| format!(" (first at line {l})")).unwrap_or_default();
            let same = if m.name == n.name {
                String::new()
            } else {
                format!(" (the same as '{}' without regard to case)", m.name)
            };
            doc.at(&at(*i, "name"), format!("duplicate node name '{}'{same}{first}", n.name));
        }
        if let Some((j, m)) = nodes.items[..a].iter().find(|(_, m)| same_address(&m.address, &n.address)) {
            let first = doc.line_of(&at(*j, "address")).map(|l| format!(" (line {l})")).unwrap_or_default();
            let message = if m.address == n.address {
                format!("node '{}' has the same address {} as node '{}'{first}", n.name, n.address, m.name)
            } else {
                format!(
                    "node '{}' at {} has the same address as node '{}' at {}{first} (localhost is 127.0.0.1 \
                     and ::1; names are compared without regard to case)",
                    n.name, n.address, m.name, m.address
                )
            };
            doc.at(&at(*i, "address"), message);
        }
    }
    // Tile references: every listed tile exists; every tile is driven by exactly one node.
    let known = |name: &str| {
        tiles.items.iter().any(|(_, t)| t.name == name) || tiles.failed_names.iter().any(|t| t == name)
    };
    let mut driver: Vec<(String, String, usize)> = Vec::new(); // (tile, node, line)
    for (i, n) in &nodes.items {
        for (k, tile) in n.tiles.iter().enumerate() {
            let path = [Seg::K("nodes"), Seg::I(*i), Seg::K("tiles"), Seg::I(k)];
            if n.tiles[..k].contains(tile) {
                doc.at(&path, format!("node '{}' lists tile '{tile}' twice", n.name));
                continue;
            }
            if !known(tile) {
                let names: Vec<&str> = tiles.items.iter().map(|(_, t)| t.name.as_str()).collect();
                doc.at(
                    &path,
                    format!("node '{}': no tile named '{tile}' (tiles: {})", n.name, names.join(", ")),
                );
                continue;
            }
            if let Some((_, other, line)) = driver.iter().find(|(t, _, _)| t == tile) {
                doc.at(
                    &path,
                    format!(
                        "tile '{tile}' is driven by two nodes: '{}' and '{other}' (line {line}); a tile has one node",
                        n.name
                    ),
                );
                continue;
            }
            let line = doc.line_of(&path).unwrap_or(0);
            driver.push((tile.clone(), n.name.clone(), line));
        }
    }
    if !nodes.any_failed {
        for (i, t) in &tiles.items {
            if !driver.iter().any(|(name, _, _)| *name == t.name) {
                doc.at(
                    &[Seg::K("tiles"), Seg::I(*i), Seg::K("name")],
                    format!("tile '{}' is driven by no node (list it in one node's `tiles`)", t.name),
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"[wall]
name = "test"

[volume]
source = "procedural:sphere"

[[tiles]]
name = "a"
x = 0
y = 0
width = 100
height = 80
bezel = [0, 10, 0, 0]

[[tiles]]
name = "b"
x = 110
y = 0
width = 100
height = 80

[[nodes]]
name = "n0"
address = "127.0.0.1:7401"
tiles = ["a"]

[[nodes]]
name = "n1"
address = "127.0.0.1:7402"
tiles = ["b"]
"#;

    fn examples_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../wall-configs")
    }

    fn example(name: &str) -> WallConfig {
        let path = examples_dir().join(name);
        WallConfig::load(&path).unwrap_or_else(|e| panic!("{e}"))
    }

    fn problems(text: &str) -> Vec<Problem> {
        match WallConfig::parse(text, Path::new("wall.toml")) {
            Ok(_) => panic!("expected problems in:\n{text}"),
            Err(e) => {
                assert_eq!(e.path, Path::new("wall.toml"));
                e.problems
            }
        }
    }

    /// Asserts that `text` has a problem on `line` whose message contains `needle`, and returns
    /// all its problems.
    #[track_caller]
    fn expect(text: &str, line: Option<usize>, needle: &str) -> Vec<Problem> {
        let ps = problems(text);
        assert!(
            ps.iter().any(|p| p.line == line && p.message.contains(needle)),
            "no problem at line {line:?} containing {needle:?}; got:\n{ps:#?}"
        );
        ps
    }

    /// GOOD with the first `from` replaced by `to` (which must be present).
    fn with(from: &str, to: &str) -> String {
        assert!(GOOD.contains(from), "{from:?} not in GOOD");
        GOOD.replacen(from, to, 1)
    }

    #[test]
    fn object_mode_parses_and_refuses_an_unbounded_radius_or_the_seed_method() {
        let c = WallConfig::parse(
            &with("name = \"test\"", "name = \"test\"\nmode = \"object\""),
            Path::new("w.toml"),
        )
        .unwrap();
        assert_eq!(c.wall.mode, WallMode::Object);
        assert!(c.wall.compress);
        let plain = WallConfig::parse(GOOD, Path::new("w.toml")).unwrap();
        assert_eq!(plain.wall.mode, WallMode::Screen);
        let obj = "name = \"test\"\nmode = \"object\"\ncompress = false";
        let unbounded = format!("{}\n[render]\nao_radius = \"unbounded\"\n", with("name = \"test\"", obj));
        expect(&unbounded, Some(35), "object space needs a bounded AO radius");
        let seed = format!("{}\n[render]\nao_method = \"seed\"\n", with("name = \"test\"", obj));
        expect(&seed, Some(35), "cannot use the `seed` AO method");
        expect(&with("name = \"test\"", "name = \"test\"\nmode = \"sideways\""), Some(3), "sideways");
    }

    #[test]
    fn the_base_config_is_valid() {
        let c = WallConfig::parse(GOOD, Path::new("/walls/test.toml")).unwrap();
        assert_eq!(c.wall.name, "test");
        assert_eq!(c.wall.deadline_ms, DEFAULT_DEADLINE_MS);
        assert_eq!(c.wall.message_limit_bytes, 64 << 20);
        assert_eq!(c.camera, CameraConfig::default());
        assert_eq!(c.render, RenderConfig::default());
        assert_eq!(c.certificates.dir, "keys");
        assert_eq!(c.wall_size(), (210, 80));
        assert_eq!(c.tile("b").unwrap().x, 110);
        assert_eq!(c.node("n1").unwrap().tiles, ["b"]);
        assert_eq!(c.node_of_tile("a").unwrap().name, "n0");
        assert_eq!(c.tiles_of("n0")[0].name, "a");
        assert!(c.tile("z").is_none() && c.node("z").is_none());
        assert_eq!(c.path, Path::new("/walls/test.toml"));
    }

    #[test]
    fn every_example_config_is_valid() {
        let mut n = 0;
        for entry in std::fs::read_dir(examples_dir()).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                let c = WallConfig::load(&path).unwrap_or_else(|e| panic!("{e}"));
                assert!(!c.tiles.is_empty() && !c.nodes.is_empty(), "{}", path.display());
                assert_eq!(c.certificates.dir, "keys", "{}", path.display());
                // The derives agree with the checked parser.
                let text = std::fs::read_to_string(&path).unwrap();
                let plain: WallConfig = toml::from_str(&text).unwrap();
                assert_eq!(WallConfig { path: path.clone(), ..plain }, c);
                n += 1;
            }
        }
        assert!(n >= 4, "only {n} example configs");
    }

    #[test]
    fn examples_say_what_the_brief_says() {
        let one = example("local-1x1.toml");
        assert_eq!((one.nodes.len(), one.wall_size()), (1, (320, 240)));
        let two = example("local-2x2.toml");
        assert_eq!(two.nodes.len(), 4);
        for (i, n) in two.nodes.iter().enumerate() {
            assert_eq!(n.address, format!("127.0.0.1:{}", 7401 + i));
        }
        assert_eq!(two.volume_source(), "procedural:engine");
        let s = two.render_settings(0.5);
        assert_eq!((s.ao.samples, s.ao.ibl, s.exposure, s.iso), (8, IblMethod::Bent, 0.6, 0.5));
        assert_eq!(two.env_source(), "sky");
        let three = example("local-3x1.toml");
        assert_eq!(three.tiles.len(), 3);
        let widths: std::collections::BTreeSet<u32> = three.tiles.iter().map(|t| t.width).collect();
        assert_eq!(widths.len(), 3, "the 3x1 wall is irregular");
        assert_eq!(three.render_settings(0.0).ao.radius, AoRadius::Unbounded);
        let sva = example("sva-4.toml");
        assert_eq!(sva.wall_size(), (3900, 2460));
        assert!(sva.nodes.iter().all(|n| n.address.ends_with(".cluster:7400")));
        assert!(sva.volume_source().ends_with("wall-configs/../../shared/data/ct-cranium.nrrd"));
        assert_eq!(sva.volume.iso, Some(300.0));
        assert_eq!(sva.render_settings(300.0).ao.radius, AoRadius::World(12.0));
    }

    #[test]
    fn the_2x2_windows_and_bezels_tile_the_wall_image_exactly() {
        let c = example("local-2x2.toml");
        let (w, h) = c.wall_size();
        assert_eq!((w, h), (328, 248));
        let mut cover = vec![0u8; (w * h) as usize];
        let mut visible = 0;
        let camera =
            Camera { eye: DVec3::new(0.0, -10.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 35.0 };
        for t in &c.tiles {
            let view = c.tile_view(camera, &t.name).unwrap();
            assert_eq!(view.full, (w, h));
            assert_eq!(view.window, t.window());
            visible += view.pixel_count();
            let (x0, x1, y0, y1) = t.outer();
            for y in y0..y1 {
                for x in x0..x1 {
                    cover[(y * w as i64 + x) as usize] += 1;
                }
            }
        }
        assert!(cover.iter().all(|&n| n == 1), "tiles with their bezels cover every wall pixel once");
        assert_eq!(visible, 4 * 160 * 120);
        assert_eq!(w * h - visible as u32, 8 * 248 + 8 * 320, "the hidden pixels are the two mullions");
        let windows: Vec<(u32, u32)> = c.tiles.iter().map(|t| (t.x, t.y)).collect();
        assert_eq!(windows, [(0, 0), (168, 0), (0, 128), (168, 128)]);
        assert!(c.tile_view(camera, "nope").is_none());
    }

    #[test]
    fn a_straight_line_stays_straight_across_a_bezel() {
        let c = example("local-2x2.toml");
        let camera = c.camera_for(DVec3::ZERO, DVec3::new(255.0, 255.0, 117.0));
        camera.validate().unwrap();
        let b = camera.basis();
        let (w, h) = c.wall_size();
        let whole = View::whole(camera, w, h);
        // Every tile pixel's ray is the whole wall image's ray through the same wall pixel.
        for t in &c.tiles {
            let v = c.tile_view(camera, &t.name).unwrap();
            for (x, y) in [(0, 0), (t.width - 1, 0), (0, t.height - 1), (t.width - 1, t.height - 1), (37, 51)]
            {
                assert_eq!(v.ray_dir(&b, x, y), whole.ray_dir_full(&b, t.x + x, t.y + y));
            }
        }
        // Across the vertical mullion, on row 60: the last pixel of t00 and the first of t10 are
        // 1 + 8 pixels apart on the image plane, exactly as far as 9 pixel steps inside a tile.
        let (t00, t10) = (c.tile_view(camera, "t00").unwrap(), c.tile_view(camera, "t10").unwrap());
        let plane_x = |d: DVec3| d.dot(b.right) / d.dot(b.forward);
        let across = plane_x(t10.ray_dir(&b, 0, 60)) - plane_x(t00.ray_dir(&b, 159, 60));
        let inside = plane_x(t00.ray_dir(&b, 9, 60)) - plane_x(t00.ray_dir(&b, 0, 60));
        assert!((across - inside).abs() < 1e-12, "{across} vs {inside}");
        // A slanted line of the wall image through t01 and t10, across both mullions: the wall
        // pixels (20 + 14k, 200 - 9k) seen by their tiles lie on one line of the image plane.
        let plane = |d: DVec3| (plane_x(d), d.dot(b.up) / d.dot(b.forward));
        let (t01, t10) = (c.tile_view(camera, "t01").unwrap(), t10);
        let points = [
            plane(t01.ray_dir(&b, 20, 200 - 128)), // k = 0: wall (20, 200)
            plane(t01.ray_dir(&b, 90, 155 - 128)), // k = 5: wall (90, 155)
            plane(t10.ray_dir(&b, 230 - 168, 65)), // k = 15: wall (230, 65)
            plane(t10.ray_dir(&b, 300 - 168, 20)), // k = 20: wall (300, 20)
        ];
        let (p, q) = (points[0], points[3]);
        for r in &points[1..3] {
            let cross = (q.0 - p.0) * (r.1 - p.1) - (q.1 - p.1) * (r.0 - p.0);
            assert!(cross.abs() < 1e-12, "{r:?} is off the line: {cross}");
        }
    }

    // ---- Validation: every rule with a failing example, its message and its line. ----

    #[test]
    fn syntax_errors_have_their_line_and_column() {
        let ps = expect(&with("x = 0\n", "x = = 0\n"), Some(9), "");
        assert_eq!(ps.len(), 1, "one problem per line: {ps:#?}");
        assert!(ps[0].column.is_some());
        // A duplicate key is a TOML error too.
        expect(&with("y = 0\n", "y = 0\ny = 1\n"), Some(11), "duplicate key");
    }

    #[test]
    fn unknown_keys_are_refused_where_they_are() {
        let ps = expect(
            &with("name = \"test\"\n", "name = \"test\"\ndeadline = 5\n"),
            Some(3),
            "unknown field `deadline`",
        );
        assert_eq!(ps[0].column, Some(1));
        expect(&format!("{GOOD}\n[extra]\nfoo = 1\n"), Some(32), "unknown field `extra`");
        expect(
            &with("height = 80\nbezel", "height = 80\nhieght = 3\nbezel"),
            Some(13),
            "unknown field `hieght`",
        );
        expect(&format!("[render]\nao_sample = 8\n\n{GOOD}"), Some(2), "unknown field `ao_sample`");
        expect(&format!("[camera]\nfov = 8\n\n{GOOD}"), Some(2), "unknown field `fov`");
        expect(&format!("[certificates]\npath = \"k\"\n\n{GOOD}"), Some(2), "unknown field `path`");
        expect(
            &with("source = \"procedural:sphere\"\n", "source = \"procedural:sphere\"\nisovalue = 1\n"),
            Some(6),
            "unknown field `isovalue`",
        );
        expect(&with("tiles = [\"a\"]\n", "tiles = [\"a\"]\ncolor = 1\n"), Some(26), "unknown field `color`");
    }

    #[test]
    fn missing_and_mistyped_fields_are_named() {
        // The tile lacks a width: reported at its [[tiles]] header, and the node that lists it is
        // not reported again.
        let ps = expect(
            &with("x = 110\ny = 0\nwidth = 100\n", "x = 110\ny = 0\n"),
            Some(15),
            "missing field `width`",
        );
        assert_eq!(ps.len(), 1, "{ps:#?}");
        expect(&with("width = 100", "width = \"100\""), Some(11), "invalid type");
        expect(&with("x = 0", "x = -1"), Some(9), "invalid value: integer `-1`");
        expect(&with("[wall]\nname = \"test\"\n", "[wall]\n"), Some(1), "missing field `name`");
        expect(&with("source = \"procedural:sphere\"\n", "iso = 1\n"), Some(4), "missing field `source`");
        expect(
            &format!("tiles = 3\n{}", &GOOD[GOOD.find("[wall]").unwrap()..].replace("[[tiles]]", "[[t]]")),
            Some(1),
            "invalid type",
        );
    }

    #[test]
    fn missing_sections_tiles_and_nodes_are_placed_at_the_end_or_where_empty() {
        let last_line = |t: &str| Some(t.trim_end().lines().count());
        let no_wall = &GOOD[GOOD.find("[volume]").unwrap()..];
        expect(no_wall, last_line(no_wall), "missing table [wall]");
        let no_volume = GOOD.replace("[volume]\nsource = \"procedural:sphere\"\n", "");
        expect(&no_volume, last_line(&no_volume), "missing table [volume]");
        let bare = "[wall]\nname = \"x\"\n[volume]\nsource = \"procedural:sphere\"\n\n";
        expect(bare, Some(4), "no tiles");
        let ps = expect(bare, Some(4), "no nodes");
        assert_eq!(ps.len(), 2);
        // Printed with the file and the line, like every other problem.
        let e = WallConfig::parse(bare, Path::new("w.toml")).unwrap_err().to_string();
        assert!(e.contains("w.toml:4:1: no nodes"), "{e}");
        // `nodes = []` is where it is.
        let empty = format!("nodes = []\n{bare}");
        expect(&empty, Some(1), "no nodes");
    }

    #[test]
    fn tile_names_are_unique() {
        let ps = expect(
            &with("name = \"b\"", "name = \"a\""),
            Some(16),
            "duplicate tile name 'a' (first at line 8)",
        );
        // The node that listed 'b' now names a tile that does not exist.
        assert!(ps.iter().any(|p| p.line == Some(30) && p.message.contains("no tile named 'b'")), "{ps:#?}");
        expect(&with("name = \"a\"", "name = \"a b\""), Some(8), "tile name 'a b' may hold only");
        expect(&with("name = \"a\"", "name = \"\""), Some(8), "tile name is empty");
    }

    #[test]
    fn node_names_are_unique_valid_and_not_reserved() {
        expect(
            &with("name = \"n1\"", "name = \"n0\""),
            Some(28),
            "duplicate node name 'n0' (first at line 23)",
        );
        expect(&with("name = \"n1\"", "name = \"controller\""), Some(28), "reserved");
        expect(&with("name = \"n1\"", "name = \"ca\""), Some(28), "reserved");
        // Without regard to case: TLS name matching ignores it.
        expect(&with("name = \"n1\"", "name = \"Controller\""), Some(28), "reserved");
        expect(&with("name = \"n1\"", "name = \"CA\""), Some(28), "reserved");
        expect(
            &with("name = \"n1\"", "name = \"N0\""),
            Some(28),
            "duplicate node name 'N0' (the same as 'n0' without regard to case) (first at line 23)",
        );
        expect(&with("name = \"n1\"", "name = \"../n1\""), Some(28), "may hold only");
    }

    #[test]
    fn every_node_tile_exists_and_every_tile_has_exactly_one_node() {
        let ps = expect(
            &with("tiles = [\"b\"]", "tiles = [\"c\"]"),
            Some(30),
            "node 'n1': no tile named 'c' (tiles: a, b)",
        );
        assert!(
            ps.iter().any(|p| p.line == Some(16) && p.message.contains("tile 'b' is driven by no node")),
            "{ps:#?}"
        );
        let ps = expect(
            &with("tiles = [\"b\"]", "tiles = [\"a\", \"b\"]"),
            Some(30),
            "tile 'a' is driven by two nodes: 'n1' and 'n0' (line 25)",
        );
        assert_eq!(ps[0].column, Some(10), "at the list element");
        expect(
            &with("tiles = [\"a\"]", "tiles = [\"a\", \"a\"]"),
            Some(25),
            "node 'n0' lists tile 'a' twice",
        );
        expect(&with("tiles = [\"a\"]", "tiles = []"), Some(8), "tile 'a' is driven by no node");
    }

    #[test]
    fn tiles_do_not_overlap_bezels_included() {
        // Visible pixels apart, but b starts inside a's right bezel.
        let ps = expect(
            &with("x = 110", "x = 105"),
            Some(15),
            "tile 'b' overlaps tile 'a' (line 7), bezels included",
        );
        assert!(ps[0].message.contains("x 0..110"), "{}", ps[0].message);
        expect(&with("x = 110", "x = 50"), Some(15), "overlaps");
        // Touching is fine.
        WallConfig::parse(&with("bezel = [0, 10, 0, 0]", "bezel = [0, 0, 0, 0]"), Path::new("w.toml"))
            .unwrap();
    }

    #[test]
    fn tile_sizes_and_bezels_are_bounded() {
        expect(&with("width = 100", "width = 0"), Some(11), "tile 'a': `width` 0 is outside 1..=16384");
        expect(
            &with("height = 80", "height = 16385"),
            Some(12),
            "tile 'a': `height` 16385 is outside 1..=16384",
        );
        expect(
            &with("bezel = [0, 10, 0, 0]", "bezel = [3, 10, 0, 0]"),
            Some(13),
            "left bezel (3 px) reaches past",
        );
        expect(
            &with("bezel = [0, 10, 0, 0]", "bezel = [0, 10, 2, 0]"),
            Some(13),
            "top bezel (2 px) reaches past",
        );
        expect(
            &with("bezel = [0, 10, 0, 0]", "bezel = [0, 99999, 0, 0]"),
            Some(13),
            "has a width over 16384",
        );
        expect(&with("x = 110", "x = 2000000"), Some(17), "beyond the largest wall image");
        expect(&with("bezel = [0, 10, 0, 0]", "bezel = [0, 10, 0]"), Some(13), "invalid length 3");
    }

    #[test]
    fn addresses_are_host_and_port() {
        for good in ["127.0.0.1:7401", "sva-node1.cluster:7400", "localhost:1", "[::1]:7400", "node_2:65535"]
        {
            assert_eq!(check_address(good), Ok(()), "{good}");
        }
        for (bad, why) in [
            ("127.0.0.1", "port is missing"),
            ("127.0.0.1:0", "not in 1..=65535"),
            ("127.0.0.1:70000", "not in 1..=65535"),
            ("host:http", "not in 1..=65535"),
            (":7400", "no host"),
            ("bad host:7400", "not a valid host name"),
            ("-x.org:7400", "not a valid host name"),
            ("a..b:7400", "not a valid host name"),
            ("::1:7400", "in brackets"),
            ("[::g]:7400", "not an IPv6 address"),
            ("[::1]7400", "not [IPv6]:port"),
        ] {
            let e = check_address(bad).unwrap_err();
            assert!(e.contains(why), "{bad}: {e}");
        }
        let ps = expect(
            &with("127.0.0.1:7401", "127.0.0.1"),
            Some(24),
            "node 'n0': address '127.0.0.1' is not host:port",
        );
        assert_eq!(ps[0].column, Some(11), "at the value");
        expect(
            &with("127.0.0.1:7402", "127.0.0.1:7401"),
            Some(29),
            "node 'n1' has the same address 127.0.0.1:7401 as node 'n0' (line 24)",
        );
        // The same socket written another way.
        for (a, b) in [
            ("127.0.0.1:7401", "localhost:7401"),
            ("[::1]:7401", "LocalHost.:7401"),
            ("127.0.0.1:7401", "[::ffff:127.0.0.1]:7401"),
            ("Node-A.cluster:7401", "node-a.cluster.:7401"),
            ("localhost:7401", "wall.localhost:7401"),
        ] {
            let text = with("127.0.0.1:7401", a).replacen("127.0.0.1:7402", b, 1);
            expect(
                &text,
                Some(29),
                &format!("node 'n1' at {b} has the same address as node 'n0' at {a} (line 24)"),
            );
        }
        // Different sockets.
        for (a, b) in
            [("localhost:7401", "127.0.0.2:7401"), ("localhost:7401", "localhost:7402"), ("a:1", "b:1")]
        {
            let text = with("127.0.0.1:7401", a).replacen("127.0.0.1:7402", b, 1);
            assert!(WallConfig::parse(&text, Path::new("w.toml")).is_ok(), "{a} {b}");
        }
        for bad in ["0.0.0.0:7401", "[::]:7401"] {
            let e = check_address(bad).unwrap_err();
            assert!(e.contains("unspecified address"), "{bad}: {e}");
        }
    }

    #[test]
    fn wall_limits_are_checked() {
        let w = |extra: &str| with("name = \"test\"\n", &format!("name = \"test\"\n{extra}\n"));
        expect(&w("deadline_ms = 0"), Some(3), "wall: `deadline_ms` 0 is outside 1..=600000");
        expect(
            &w("deadline_ms = 18446744073709551615"),
            Some(3),
            "`deadline_ms` 18446744073709551615 is outside",
        );
        assert!(WallConfig::parse(&w("deadline_ms = 600000"), Path::new("w.toml")).is_ok());
        expect(&w("message_limit_bytes = 10"), Some(3), "`message_limit_bytes` 10 is outside");
        // Over what the decoder accepts.
        let over = format!("message_limit_bytes = {}", crate::codec::MAX_FRAME_LEN + 1);
        expect(&w(&over), Some(3), "no decoder accepts a message over 1 GiB");
        let max = format!("message_limit_bytes = {}", crate::codec::MAX_FRAME_LEN);
        assert!(WallConfig::parse(&w(&max), Path::new("w.toml")).is_ok());
        expect(&with("name = \"test\"", "name = \" \""), Some(2), "wall: `name` is empty");
    }

    #[test]
    fn the_message_limit_holds_every_nodes_snapshot() {
        let w = |extra: &str| with("name = \"test\"\n", &format!("name = \"test\"\n{extra}\n"));
        // Tiles of 100x80: 24,000 bytes of pixels each.
        let ps =
            expect(&w("message_limit_bytes = 20000"), Some(3), "too small for the snapshot of node 'n0'");
        assert!(ps.iter().any(|p| p.message.contains("node 'n1' (tiles b")), "{ps:#?}");
        let need = crate::messages::TileImage::snapshot_len_bound([("a", 100, 80)]);
        assert!(ps[0].message.contains(&format!("raise it to at least {need}")), "{ps:#?}");
        assert!(WallConfig::parse(&w(&format!("message_limit_bytes = {need}")), Path::new("w.toml")).is_ok());
        // Without the field, the default holds them; a tile too large for it is placed at its node.
        let big = with("width = 100\nheight = 80\n\n[[nodes]]", "width = 16384\nheight = 16384\n\n[[nodes]]");
        let ps = expect(
            &big,
            Some(30),
            "`message_limit_bytes` 67108864 is too small for the snapshot of node 'n1'",
        );
        assert_eq!(ps.len(), 1, "{ps:#?}");
    }

    #[test]
    fn the_camera_is_checked() {
        let cam = |body: &str| format!("[camera]\n{body}\n\n{GOOD}");
        expect(&cam("fov_y = 0"), Some(2), "camera: `fov_y` 0 is outside (0, 180) degrees");
        expect(&cam("fov_y = 180.0"), Some(2), "outside (0, 180)");
        expect(&cam("fov_y = nan"), Some(2), "outside (0, 180)");
        expect(&cam("eye = [1, 2, 3]\ntarget = [1, 2, 3]"), Some(2), "camera: `eye` and `target` coincide");
        // `up` is not given: the problem is placed at the [camera] table.
        expect(
            &cam("eye = [0, 0, 10]\ntarget = [0, 0, 0]"),
            Some(1),
            "`up` is parallel to the view direction",
        );
        expect(&cam("up = [0, 0, 0]"), Some(2), "camera: `up` is the zero vector");
        expect(&cam("eye = [inf, 0, 0]"), Some(2), "camera: `eye` [inf, 0.0, 0.0] is not finite");
        expect(&cam("eye = [1, 2]"), Some(2), "invalid length 2");
    }

    #[test]
    fn the_volume_is_checked() {
        let vol = |body: &str| with("source = \"procedural:sphere\"\n", &format!("{body}\n"));
        expect(
            &vol("source = \"procedural:sphere\"\niso = nan"),
            Some(6),
            "volume: `iso` NaN is not a finite number",
        );
        expect(
            &vol("source = \"procedural:teapot\""),
            Some(5),
            "unknown procedural volume 'teapot' (one of: sphere,",
        );
        expect(&vol("source = \"procedural:sphere:1\""), Some(5), "procedural size 1 is outside 2..=1024");
        expect(
            &vol("source = \"procedural:sphere:x\""),
            Some(5),
            "procedural size 'x' is not a whole number",
        );
        expect(&vol("source = \"\""), Some(5), "volume: `source` is empty");
        expect(
            &vol("source = \"procedural:sphere\"\ndims = [2, 2, 2]"),
            Some(6),
            "`dims` is for raw files only",
        );
        expect(&vol("source = \"head.raw\"\ndims = [2, 2, 2]"), Some(6), "needs both `dims` and `type`");
        expect(&vol("source = \"head.raw\"\ntype = \"int16\""), Some(6), "needs both `dims` and `type`");
        expect(
            &vol("source = \"head.raw\"\ndims = [2, 2, 2]\ntype = \"int12\""),
            Some(7),
            "unknown voxel type 'int12'",
        );
        expect(
            &vol("source = \"head.raw\"\ndims = [0, 2, 2]\ntype = \"int16\""),
            Some(6),
            "has a zero dimension",
        );
        expect(
            &vol("source = \"head.raw\"\ndims = [2, 2, 2]\ntype = \"u8\"\nspacing = [1, 0, 1]"),
            Some(8),
            "must be finite and > 0",
        );
        let raw = vol(
            "source = \"head.raw\"\ndims = [2, 2, 2]\ntype = \"int16\"\nspacing = [1, 1, 2.5]\niso = 300",
        );
        let c = WallConfig::parse(&raw, Path::new("/w/wall.toml")).unwrap();
        assert_eq!((c.volume.dims, c.volume.voxel_type.as_deref()), (Some([2, 2, 2]), Some("int16")));
        assert_eq!(c.volume_source(), "/w/head.raw");
        assert_eq!(c.cache_bytes(), DEFAULT_CACHE_BYTES);
        expect(
            &vol("source = \"steps/step_*.nrrd\"\ncache_bytes = 1099511627777"),
            Some(6),
            "volume: `cache_bytes` 1099511627777 is over the limit of 1099511627776 (1 TiB)",
        );
        expect(
            &vol("source = \"steps/step_*.nrrd\"\ncache_bytes = -1"),
            Some(6),
            "invalid value: integer `-1`",
        );
        expect(
            &vol("source = \"procedural:sphere\"\ncache_bytes = 1000"),
            Some(6),
            "`cache_bytes` is for time steps, not a procedural volume",
        );
        let steps = WallConfig::parse(
            &vol("source = \"steps/step_*.nrrd\"\ncache_bytes = 0"),
            Path::new("/w/wall.toml"),
        )
        .unwrap();
        assert_eq!((steps.cache_bytes(), steps.volume_source().as_str()), (0, "/w/steps/step_*.nrrd"));
    }

    #[test]
    fn render_values_are_checked() {
        let render = |body: &str| format!("[render]\n{body}\n\n{GOOD}");
        expect(&render("ao_radius = 0"), Some(2), "render: `ao_radius` 0 must be > 0 (or \"unbounded\")");
        expect(&render("ao_radius = -2.5"), Some(2), "must be > 0");
        expect(
            &render("ao_radius = \"huge\""),
            Some(2),
            "a radius in world units (a number > 0) or \"unbounded\"",
        );
        expect(&render("exposure = -1"), Some(2), "render: `exposure` -1 must be a finite number >= 0");
        expect(&render("ao_samples = 5000"), Some(2), "render: `ao_samples` 5000 is more than 1024");
        expect(&render("target_frame_ms = 0"), Some(2), "render: `target_frame_ms`: target frame time 0 ms");
        expect(&render("target_frame_ms = -3.5"), Some(2), "target frame time -3.5 ms");
        let c = WallConfig::parse(&render("target_frame_ms = 50"), Path::new("w.toml")).unwrap();
        assert_eq!(c.render.target_frame_ms, Some(50.0));
        expect(&render("shading = \"phong\""), Some(2), "unknown variant `phong`");
        expect(&render("ibl = \"sh\""), Some(2), "unknown variant `sh`");
        expect(&render("ao_method = \"theirs\""), Some(2), "unknown variant `theirs`");
        expect(&render("ao_samples = -1"), Some(2), "invalid value");
        expect(&render("env = \"\""), Some(2), "render: `env` is empty");
        expect(&format!("[certificates]\ndir = \"\"\n\n{GOOD}"), Some(2), "certificates: `dir` is empty");
        let c = WallConfig::parse(&render("ao_radius = \"unbounded\"\nexposure = 0"), Path::new("w.toml"))
            .unwrap();
        assert_eq!((c.render.ao_radius, c.render.exposure), (AoRadius::Unbounded, Some(0.0)));
        let c = WallConfig::parse(&render("ao_radius = 3"), Path::new("w.toml")).unwrap();
        assert_eq!(c.render.ao_radius, AoRadius::World(3.0));
    }

    #[test]
    fn every_problem_is_collected_in_file_order_and_printed_with_its_position() {
        let text = format!("[camera]\nfov_y = 200\n\n{GOOD}")
            .replace("name = \"test\"\n", "name = \"test\"\ncolour = 1\n")
            .replace("x = 110", "x = 50")
            .replace("127.0.0.1:7402", "127.0.0.1:99999");
        let e = WallConfig::parse(&text, Path::new("walls/bad.toml")).unwrap_err();
        let lines: Vec<usize> = e.problems.iter().map(|p| p.line.unwrap()).collect();
        assert_eq!(lines, [2, 6, 19, 33], "{e}");
        let shown = e.to_string();
        let shown: Vec<&str> = shown.lines().collect();
        assert_eq!(shown.len(), 4);
        assert_eq!(shown[0], "walls/bad.toml:2:9: camera: `fov_y` 200 is outside (0, 180) degrees");
        assert!(shown[1].starts_with("walls/bad.toml:6:1: unknown field `colour`"), "{}", shown[1]);
        assert!(shown[2].starts_with("walls/bad.toml:19:1: tile 'b' overlaps tile 'a'"), "{}", shown[2]);
        assert!(shown[3].starts_with("walls/bad.toml:33:11: node 'n1': address"), "{}", shown[3]);
        // What the file lacks: at its last line.
        let e = WallConfig::parse(
            "[wall]\nname = \"x\"\n[volume]\nsource = \"procedural:sphere\"\n",
            Path::new("w.toml"),
        )
        .unwrap_err();
        assert_eq!(e.to_string(), "w.toml:4:1: no tiles: a wall needs at least one [[tiles]] table\nw.toml:4:1: no nodes: a wall needs at least one [[nodes]] table");
        let e = WallConfig::load(Path::new("/nonexistent/wall.toml")).unwrap_err();
        assert!(e.to_string().starts_with("/nonexistent/wall.toml: cannot read the wall config:"), "{e}");
    }

    #[test]
    fn line_and_column_count_characters() {
        let text = "a\nbé = 1\n";
        assert_eq!(line_column(text, 0), (1, 1));
        assert_eq!(line_column(text, 2), (2, 1));
        assert_eq!(line_column(text, 5), (2, 3), "after b and é (2 bytes)");
        assert_eq!(line_column(text, 999), (3, 1));
        // Line 2 is `name = "tést" = 1`: the stray `=` is character 15 (byte 16).
        let e =
            WallConfig::parse(&with("name = \"test\"", "name = \"tést\" = 1"), Path::new("w")).unwrap_err();
        assert_eq!((e.problems[0].line, e.problems[0].column), (Some(2), Some(15)), "{e}");
    }

    // ---- The model API. ----

    #[test]
    fn the_default_camera_frames_the_volume_over_the_whole_wall() {
        let c = example("local-2x2.toml");
        let (lo, hi) = (DVec3::ZERO, DVec3::new(255.0, 255.0, 117.0));
        let cam = c.camera_for(lo, hi);
        let framing = Camera::framing(lo, hi, 328, 248);
        assert!((cam.eye - framing.eye).length() < 1e-9 * framing.eye.length(), "{cam:?} vs {framing:?}");
        assert_eq!((cam.target, cam.up, cam.fov_y_deg), (framing.target, framing.up, framing.fov_y_deg));
        // Another fov, target and up: still every corner in view over the wall image.
        let mut c3 = example("local-3x1.toml");
        c3.camera.target = Some([100.0, 120.0, 50.0]);
        c3.camera.up = [0.0, 0.2, 1.0];
        let cam = c3.camera_for(lo, hi);
        cam.validate().unwrap();
        assert_eq!((cam.fov_y_deg, cam.target), (30.0, DVec3::new(100.0, 120.0, 50.0)));
        let (w, h) = c3.wall_size();
        let b = cam.basis();
        let tan_x = b.tan_half_fov * w as f64 / h as f64;
        for i in 0..8 {
            let corner = DVec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            );
            let v = corner - cam.eye;
            let z = v.dot(b.forward);
            assert!(z > 0.0 && v.dot(b.right).abs() / z <= tan_x && v.dot(b.up).abs() / z <= b.tan_half_fov);
        }
        // An explicit eye is kept; the target defaults to the box centre.
        let mut c4 = c.clone();
        c4.camera.eye = Some([1.0, -500.0, 2.0]);
        let cam = c4.camera_for(lo, hi);
        assert_eq!((cam.eye, cam.target), (DVec3::new(1.0, -500.0, 2.0), 0.5 * hi));
        let sva = example("sva-4.toml");
        let cam = sva.camera_for(lo, hi);
        assert_eq!(
            (cam.eye, cam.target, cam.fov_y_deg),
            (DVec3::new(122.0, -420.0, 190.0), DVec3::new(122.0, 122.0, 80.0), 32.0)
        );
    }

    #[test]
    fn render_settings_take_the_render_defaults() {
        let c = WallConfig::parse(GOOD, Path::new("w.toml")).unwrap();
        assert_eq!(c.render_settings(2.0), RenderSettings::new(2.0));
        let text = format!("[render]\nshading = \"lambert\"\nao_samples = 16\nao_radius = 4\nao_method = \"seed\"\nao_sequence = \"r2\"\nibl = \"rays\"\nexposure = 0.8\n\n{GOOD}");
        let s = WallConfig::parse(&text, Path::new("w.toml")).unwrap().render_settings(1.0);
        assert_eq!((s.shading, s.ao.samples, s.ao.radius), (Shading::Lambert, 16, AoRadius::World(4.0)));
        assert_eq!(s.ao.sequence, AoSequence::R2);
        assert_eq!((s.ao.method, s.ao.ibl, s.exposure), (AoMethod::Seed, IblMethod::Rays, 0.8));
    }

    #[test]
    fn paths_are_relative_to_the_config_file() {
        let text =
            format!("[certificates]\ndir = \"secrets/wall\"\n[render]\nenv = \"envs/studio.hdr\"\n\n{GOOD}");
        let c = WallConfig::parse(&text, Path::new("/etc/isowall/wall.toml")).unwrap();
        assert_eq!(c.cert_dir(), Path::new("/etc/isowall/secrets/wall"));
        assert_eq!(c.resolve("/abs/x"), Path::new("/abs/x"));
        assert_eq!(c.resolve("a/b"), Path::new("/etc/isowall/a/b"));
        assert_eq!(c.volume_source(), "procedural:sphere");
        assert_eq!(c.env_source(), "/etc/isowall/envs/studio.hdr");
        let c = WallConfig::parse(GOOD, Path::new("wall.toml")).unwrap();
        assert_eq!(c.cert_dir(), Path::new("keys"));
        assert_eq!(c.env_source(), "sky");
    }

    #[test]
    fn the_summary_names_the_wall_and_every_node() {
        let s = example("local-2x2.toml").summary();
        assert!(s.starts_with("wall 'local-2x2': 328x248 px, 4 tiles on 4 nodes"), "{s}");
        assert!(s.contains("node3 (127.0.0.1:7404): t11 160x120+168+128"), "{s}");
    }
}
