//! What a node renders of a frame, decided here and carried out by the daemon's render thread:
//! the views (each with the tile it belongs to), the settings, the internal scale, how the frame
//! follows the one before, and whether its pixels are read back to travel to other nodes.
//!
//! The two spaces decide differently:
//! - screen space ([`RenderPlan::screen`]): each of the node's tiles' view of the wall camera, at
//!   the frame's scale; the frame stays on the GPU.
//! - object space ([`crate::object_machine::ObjectMachine::plan`]): the node's bricks over the
//!   rectangles they cover, always at scale 1 (the tiles are composited by full-resolution depth),
//!   with the settings bounded by the halo, the pixels read back in the wall's form.
//!
//! The daemon's [`crate::node_machine::NodeMachine`] says when to render (`NodeOutput::Render`);
//! the node's space turns that into a plan.

use crate::composite::PixelForm;
use crate::config::WallConfig;
use crate::wire::{Continuity, FrameSpec};
use crate::{Denoise, RenderSettings, View};

/// A frame to render (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct RenderPlan {
    pub frame_id: u64,
    /// Each view and the tile it belongs to.
    pub views: Vec<(String, View)>,
    /// object space: the brick each view renders, by index; empty: the one volume.
    pub bricks: Vec<usize>,
    pub settings: RenderSettings,
    /// The internal resolution divisor (1 ..= [`crate::governor::MAX_SCALE`]).
    pub scale: u32,
    /// Frames with the same image so far (`NodeOutput::Render`'s count).
    pub accumulate_frame: u32,
    /// How the frame follows the one started before it.
    pub continuity: Continuity,
    /// The frame's time step.
    pub time_step: u32,
    /// Read each view's pixels back in this form (they travel to the tile's owner); `None`: the
    /// frame stays on the GPU.
    pub share: Option<PixelForm>,
}

impl RenderPlan {
    /// Screen space: `tiles` (the node's, by name; a name the config lacks is left out) seen by
    /// the frame's camera, at the frame's scale and settings.
    pub fn screen(
        config: &WallConfig,
        tiles: &[String],
        spec: &FrameSpec,
        accumulate_frame: u32,
        continuity: Continuity,
    ) -> RenderPlan {
        let views =
            tiles.iter().filter_map(|t| config.tile_view(spec.camera, t).map(|v| (t.clone(), v))).collect();
        RenderPlan::of_views(spec, views, accumulate_frame, continuity, None)
    }

    /// The frame `spec` over `views` of the wall's own pixels (no bricks), at the frame's scale
    /// and settings, read back in `share`'s form where given: screen space's plan, and a balanced
    /// wall's (`crate::balance::node`), whose views are rows of tiles.
    pub fn of_views(
        spec: &FrameSpec,
        views: Vec<(String, View)>,
        accumulate_frame: u32,
        continuity: Continuity,
        share: Option<PixelForm>,
    ) -> RenderPlan {
        RenderPlan {
            frame_id: spec.frame_id,
            views,
            bricks: Vec::new(),
            settings: spec.settings,
            scale: spec.scale,
            accumulate_frame,
            continuity,
            time_step: spec.time_step,
            share,
        }
    }

    /// Whether the views are the wall's own pixels (screen space), not bricks' views that become
    /// a tile's only once composited (object space).
    pub fn views_are_tiles(&self) -> bool {
        self.bricks.is_empty()
    }

    /// The settings each view renders with: the AO sample pattern advanced by the frames of the
    /// same image so far (progressive AO averages decorrelated frames in), and the filter only
    /// where the views are tiles (object space filters the composited canvas at the tile's owner,
    /// by the frame's own settings).
    pub fn view_settings(&self) -> RenderSettings {
        let mut s = self.settings;
        s.ao.frame = s.ao.frame.wrapping_add(self.accumulate_frame);
        if !self.views_are_tiles() {
            s.denoise = Denoise::Off;
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Camera;
    use glam::DVec3;
    use std::path::Path;

    const WALL: &str = r#"
[wall]
name = "w"
[camera]
eye = [0, -10, 0]
target = [0, 0, 0]
up = [0, 0, 1]
[volume]
source = "procedural:engine"
[[tiles]]
name = "a"
x = 0
y = 0
width = 64
height = 48
[[tiles]]
name = "b"
x = 64
y = 0
width = 64
height = 48
[[nodes]]
name = "n0"
address = "127.0.0.1:7000"
tiles = ["a", "b"]
"#;

    #[test]
    fn screen_space_renders_each_own_tile_at_the_frames_scale_and_shares_nothing() {
        let config = WallConfig::parse(WALL, Path::new("w.toml")).unwrap();
        let camera =
            Camera { eye: DVec3::new(0.0, -10.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 40.0 };
        let spec =
            FrameSpec { frame_id: 7, camera, settings: RenderSettings::new(0.5), scale: 2, time_step: 3 };
        let tiles = vec!["b".to_string(), "gone".to_string()];
        let plan = RenderPlan::screen(&config, &tiles, &spec, 4, Continuity::Same);
        assert_eq!(plan.views.len(), 1, "a tile the config lacks is left out");
        assert_eq!(plan.views[0].0, "b");
        assert_eq!(plan.views[0].1, config.tile_view(camera, "b").unwrap());
        assert_eq!(plan.views[0].1.rect.x, 64);
        assert_eq!((plan.frame_id, plan.scale, plan.time_step, plan.accumulate_frame), (7, 2, 3, 4));
        assert_eq!(plan.continuity, Continuity::Same);
        assert_eq!((plan.share, plan.bricks.is_empty()), (None, true));
        assert_eq!(plan.settings, spec.settings);
    }

    #[test]
    fn views_render_with_the_pattern_of_their_frame_and_only_tiles_are_filtered() {
        let config = WallConfig::parse(WALL, Path::new("w.toml")).unwrap();
        let camera =
            Camera { eye: DVec3::new(0.0, -10.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 40.0 };
        let mut settings = RenderSettings::new(0.5);
        settings.ao.frame = u32::MAX - 1;
        settings.denoise = Denoise::On;
        let spec = FrameSpec { frame_id: 1, camera, settings, scale: 1, time_step: 0 };
        let mut plan = RenderPlan::screen(&config, &["a".to_string()], &spec, 3, Continuity::Same);
        let v = plan.view_settings();
        assert_eq!((v.ao.frame, v.denoise), (1, Denoise::On), "advanced by 3, wrapping; a tile is filtered");
        assert_eq!(plan.settings.ao.frame, u32::MAX - 1, "the frame's own settings stay as sent");
        plan.bricks = vec![0];
        assert!(!plan.views_are_tiles());
        assert_eq!(plan.view_settings().denoise, Denoise::Off, "a brick's view is filtered once composited");
    }
}
