//! What a tile's frame does with the running sums it holds, decided before anything is recorded:
//! keep accumulating, carry them into a moved view (reprojection), or start over. The decision
//! follows the model's rule of how a frame relates to the one before it
//! ([`Continuity`](isowall_model::wire::Continuity), from `FrameState::continuity`), so the GPU
//! side never compares parameters a second time; the GPU code carries the plan out
//! (`gpu/tile.rs`).

pub use isowall_model::wire::Continuity;

/// The most frames a tile's running sums (and `render_accumulated`) hold before starting over.
pub const MAX_FRAMES: u32 = 4096;

/// What a tile's running sums hold before the frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Sums {
    /// Frames added since they were last cleared or carried over.
    pub frames: u32,
    /// They hold a reprojected history: each pixel's weight is its own count (the IBL sum's w).
    pub per_pixel: bool,
}

/// How the frame starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Start {
    /// Add this frame's samples onto the sums (the isosurface kernel's outputs are kept).
    Accumulate,
    /// Clear the sums and run the isosurface kernel.
    Restart,
    /// Run the isosurface kernel for the moved view and carry the sums over onto its hits.
    Reproject,
}

/// A frame's plan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FramePlan {
    pub start: Start,
    /// What the sums hold after the frame.
    pub sums: Sums,
}

impl FramePlan {
    /// The plan of a frame that relates to the tile's last one by `continuity` (`Changed` where
    /// the tile has no last frame or its volume or environment changed), onto `sums`. `temporal`:
    /// a moved view may carry the history over; `with_ao`: the frame adds AO or IBL samples
    /// (without them nothing accumulates).
    pub fn new(continuity: Continuity, sums: Sums, temporal: bool, with_ao: bool) -> FramePlan {
        let start = match continuity {
            Continuity::ViewMoved if temporal && with_ao && sums.frames > 0 => Start::Reproject,
            Continuity::Same if sums.frames < MAX_FRAMES => Start::Accumulate,
            _ => Start::Restart,
        };
        let per_pixel = match start {
            Start::Accumulate => sums.per_pixel,
            Start::Restart => false,
            Start::Reproject => true,
        };
        let before = if start == Start::Accumulate { sums.frames } else { 0 };
        FramePlan { start, sums: Sums { frames: if with_ao { before + 1 } else { 0 }, per_pixel } }
    }

    /// The index the frame's sample patterns are drawn with: the settings' own (`ao_frame`, which
    /// the node advances with each accumulated frame), or, once the sums hold a reprojected
    /// history, new samples every frame by the frame id (the same on every node).
    pub fn sample_index(&self, ao_frame: u32, frame_id: u64) -> u32 {
        if self.sums.per_pixel {
            ao_frame.wrapping_add(frame_id as u32)
        } else {
            ao_frame
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EMPTY: Sums = Sums { frames: 0, per_pixel: false };

    #[test]
    fn the_same_image_accumulates_until_the_cap_then_restarts() {
        let mut sums = EMPTY;
        let first = FramePlan::new(Continuity::Changed, sums, true, true);
        assert_eq!((first.start, first.sums), (Start::Restart, Sums { frames: 1, per_pixel: false }));
        sums = first.sums;
        for k in 2..=5 {
            let p = FramePlan::new(Continuity::Same, sums, true, true);
            assert_eq!((p.start, p.sums.frames), (Start::Accumulate, k));
            sums = p.sums;
        }
        let full = Sums { frames: MAX_FRAMES, per_pixel: false };
        assert_eq!(FramePlan::new(Continuity::Same, full, true, true).start, Start::Restart);
    }

    #[test]
    fn a_moved_view_reprojects_only_with_temporal_samples_and_a_history() {
        let held = Sums { frames: 4, per_pixel: false };
        let p = FramePlan::new(Continuity::ViewMoved, held, true, true);
        assert_eq!((p.start, p.sums), (Start::Reproject, Sums { frames: 1, per_pixel: true }));
        assert_eq!(
            FramePlan::new(Continuity::ViewMoved, held, false, true).start,
            Start::Restart,
            "temporal off"
        );
        assert_eq!(FramePlan::new(Continuity::ViewMoved, held, true, false).start, Start::Restart, "no AO");
        assert_eq!(
            FramePlan::new(Continuity::ViewMoved, EMPTY, true, true).start,
            Start::Restart,
            "no history"
        );
        assert_eq!(FramePlan::new(Continuity::Changed, held, true, true).start, Start::Restart);
    }

    #[test]
    fn a_reprojected_history_keeps_per_pixel_weights_and_fresh_samples_until_a_restart() {
        let moved = FramePlan::new(Continuity::ViewMoved, Sums { frames: 3, per_pixel: false }, true, true);
        assert_eq!(moved.sample_index(7, 100), 107, "new samples every frame, by the frame id");
        let still = FramePlan::new(Continuity::Same, moved.sums, true, true);
        assert_eq!((still.start, still.sums), (Start::Accumulate, Sums { frames: 2, per_pixel: true }));
        assert_eq!(still.sample_index(8, 101), 109);
        let changed = FramePlan::new(Continuity::Changed, still.sums, true, true);
        assert_eq!(changed.sums, Sums { frames: 1, per_pixel: false });
        assert_eq!(changed.sample_index(0, 102), 0, "a restarted tile draws by the settings' index");
    }

    #[test]
    fn without_ao_nothing_is_counted() {
        let p = FramePlan::new(Continuity::Same, EMPTY, true, false);
        assert_eq!((p.start, p.sums.frames), (Start::Accumulate, 0));
        assert_eq!(FramePlan::new(Continuity::Changed, EMPTY, true, false).sums.frames, 0);
    }
}
