//! The wall at scale on a virtual clock: a deterministic discrete-event LAN model ([`lan`]) driving
//! the real sans-IO machines of this crate, no sockets and no clocks.
//!
//! - [`screen`]: the controller's [`crate::FrameController`] and N [`crate::NodeMachine`]s, every
//!   message through the codec: barrier time and swap skew as the node count grows.
//! - [`object`]: N [`crate::object_machine::ObjectMachine`]s compositing a wall of 1080p tiles by
//!   direct send: bytes per node and compositing time per frame.
//! - [`balance`]: load-balanced screen space: the model's [`crate::balance::Balancer`] over a
//!   wall of 1080p tiles with a scan in the middle, against every node rendering its own tiles.
//! - [`radix`]: the sort-last schedules to compare with on the same network (radix-k, binary
//!   swap, direct-send as radix-k's one-round case), over the same brick footprints.
//!
//! `cargo run -p isowall-model --release --example wall_scale` prints the table and writes
//! docs/scale/; docs/scale.md reads it.

pub mod balance;
pub mod lan;
pub mod object;
pub mod radix;
pub mod screen;

pub use balance::{
    grid, measured_costs, run_balance, run_balance_on, BalanceFrame, BalanceSpec, FrameCosts, SimTile,
    Transfer,
};
pub use lan::{Events, Lan, LanCounts, LanModel, Rng, Scheduled};
pub use object::{run_object, ObjectReport, ObjectSpec, ObjectWall, PixelCost};
pub use radix::{run_radix, PixelBox, RadixReport, Scene};
pub use screen::{run_screen, ScreenReport, ScreenSpec};

use crate::{Camera, Rect, View};

/// Why a simulated wall cannot be built.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SimError {
    #[error("{nodes} nodes: a simulated wall is a square grid of tiles, one per node")]
    NotSquare { nodes: usize },
    #[error("tile divisor {divisor}: 1920 and 1080 must both divide by it")]
    Divisor { divisor: u32 },
    #[error("the simulated wall: {0}")]
    Config(String),
}

impl Scene {
    /// A wall's compositing at full resolution (`wall.divisor` must be 1 for 1080p pixels):
    /// node i's brick footprint and its tile.
    pub fn wall(wall: &ObjectWall) -> Scene {
        let (w, h) = wall.config.wall_size();
        let image = PixelBox { x0: 0, y0: 0, x1: i64::from(w), y1: i64::from(h) };
        let footprints =
            wall.footprints().into_iter().map(|f| f.map(PixelBox::of).unwrap_or_default()).collect();
        let tiles = wall
            .config
            .nodes
            .iter()
            .map(|n| PixelBox::of(wall.config.tile(&n.tiles[0]).expect("a tile").rect()))
            .collect();
        Scene { image, footprints, tiles }
    }

    /// One `width x height` image composited over `nodes` bricks of the 512^3 volume, framed as a
    /// wall camera frames it (the IceT setting: the image is not a wall).
    pub fn image(width: u32, height: u32, nodes: usize) -> Result<Scene, SimError> {
        let owned = object::brick_boxes(nodes)?;
        let hi = glam::DVec3::from_array(object::VOLUME_DIMS.map(|d| (d - 1) as f64));
        let camera = Camera::framing(glam::DVec3::ZERO, hi, width, height);
        let view = View { camera, full: (width, height), rect: Rect { x: 0, y: 0, width, height } };
        let footprints = owned
            .iter()
            .map(|&(lo, hi)| crate::bricks::covered_rect(&view, lo, hi).map(PixelBox::of).unwrap_or_default())
            .collect();
        let image = PixelBox { x0: 0, y0: 0, x1: i64::from(width), y1: i64::from(height) };
        Ok(Scene { image, footprints, tiles: Vec::new() })
    }
}
