//! [`PerfOptions`]: how the kernels do their work, never what they compute. Every option leaves
//! the image unchanged (the skipping is conservative and the early exit exact); they exist so that
//! `isowalld bench suite` can measure them against each other in one run. The defaults are the
//! measured best on lavapipe (docs/bench/perf-lavapipe.md). The one exception is the voxel
//! `format`, which rounds the voxels (its error is measured by the same bench).

use isowall_volume::VoxelFormat;

/// Performance options of a [`GpuRenderer`](super::GpuRenderer).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PerfOptions {
    /// Cells per block edge of the primary rays' min/max level (empty-space skipping).
    pub block: u32,
    /// Cells per block edge of the AO rays' own level (0: they use the primary rays' level). A
    /// level of its own keeps the primary rays' march, and so their hits, exactly as before.
    pub ao_block: u32,
    /// Cells per block edge of the coarse level AO rays cross whole where its max < iso
    /// (hierarchical skipping; 0: none).
    pub coarse: u32,
    /// An AO ray entering a block whose min >= iso is occluded without loading a cell.
    pub block_min_exit: bool,
    /// Workgroup shape (x, y) of the compute kernels.
    pub workgroup: (u32, u32),
    /// How volumes uploaded afterwards store their voxels on the GPU (the kernels are compiled
    /// for it: `VOXEL_FORMAT` in shaders/volume.wgsl). Not exact like the others: the voxels are
    /// rounded, and the CPU twin is `Volume::stored_as`.
    pub format: VoxelFormat,
    /// The primary rays march on a copy of the volume in a `texture_3d`, sampled through the
    /// hardware's trilinear filter (one sample instead of 8 loads), and refine the bracketing step
    /// from the storage volume exactly (`TEXTURE_MARCH` in shaders/isosurface.wgsl). Not exact
    /// like the others either: the filter's weights (and, without `FLOAT32_FILTERABLE`, the
    /// texture's r16float texels) can move which step brackets a crossing.
    pub texture: bool,
}

impl Default for PerfOptions {
    fn default() -> Self {
        // Measured on lavapipe (docs/bench/perf-lavapipe.md): AO rays on their own level of 4
        // cells load 0.61-0.67x the cells of the primary rays' blocks of 8 at the same error, and
        // were as fast or faster (2 cells: fewer still, but 8x the memory of 4 for no measured
        // gain); the coarse level and the early exit cost nothing; no workgroup shape tried beat
        // 8x8 beyond the noise. Voxels stay f32: packed r16/r16f keep the error but were not
        // faster on lavapipe (engine 1.07-1.42x slower in three runs, CT within the noise), and
        // r8 raises the AO error 2.5-9x at 256 samples; a GPU is unmeasured.
        PerfOptions {
            block: 8,
            ao_block: 4,
            coarse: 32,
            block_min_exit: true,
            workgroup: (8, 8),
            format: VoxelFormat::R32F,
            texture: false,
        }
    }
}

impl PerfOptions {
    /// The plain kernels, no speed option on: blocks of 8 for every ray, no coarse level, no
    /// early exit, 8x8 workgroups (`bench suite --variants before` measures them).
    pub const PLAIN: PerfOptions = PerfOptions {
        block: 8,
        ao_block: 0,
        coarse: 0,
        block_min_exit: false,
        workgroup: (8, 8),
        format: VoxelFormat::R32F,
        texture: false,
    };

    /// Refuses shapes a device need not support (at most 256 invocations, 256 per axis).
    pub fn validate(&self) -> Result<(), String> {
        let (x, y) = self.workgroup;
        if x == 0 || y == 0 || x * y > 256 {
            return Err(format!("workgroup {x}x{y}: each side at least 1 and at most 256 invocations"));
        }
        if !(1..=256).contains(&self.block) {
            return Err(format!("block {}: 1 to 256 cells per edge", self.block));
        }
        for (name, v) in [("AO block", self.ao_block), ("coarse block", self.coarse)] {
            if v > 256 {
                return Err(format!("{name} {v}: at most 256 cells per edge (0: none)"));
            }
        }
        Ok(())
    }

    /// Whether every block level's cells per edge is a power of two (the kernels then find a
    /// cell's block by a shift, `POW2_LEVELS` in shaders/volume.wgsl; an integer division runs
    /// lane by lane on a SIMD CPU driver).
    pub fn pow2_levels(&self) -> bool {
        let pow2 = |cells: u32| cells == 0 || cells.is_power_of_two();
        self.block.is_power_of_two() && pow2(self.ao_block) && pow2(self.coarse)
    }

    /// The pipeline constants of the volume kernels (shaders/volume.wgsl): the voxel format,
    /// whether the block levels are powers of two, and whether the volume is bricked (read
    /// through the page table of a [`BrickPool`](super::brick_pool::BrickPool)).
    pub fn volume_constants(&self, bricked: bool) -> [(&'static str, f64); 3] {
        [
            ("VOXEL_FORMAT", self.format.code() as f64),
            ("POW2_LEVELS", f64::from(u8::from(self.pow2_levels()))),
            ("BRICKED", f64::from(u8::from(bricked))),
        ]
    }

    /// The `perf.x` flags of `FrameParams`.
    pub fn flags(&self) -> u32 {
        if self.block_min_exit {
            super::frame_params::PERF_BLOCK_MIN_EXIT
        } else {
            0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_shapes_are_refused() {
        assert!(PerfOptions::default().validate().is_ok());
        assert!(PerfOptions::PLAIN.validate().is_ok());
        for wg in [(0, 8), (32, 16), (8, 0)] {
            assert!(PerfOptions { workgroup: wg, ..Default::default() }.validate().is_err(), "{wg:?}");
        }
        assert!(PerfOptions { block: 0, ..Default::default() }.validate().is_err());
        assert!(PerfOptions { coarse: 257, ..Default::default() }.validate().is_err());
        assert!(PerfOptions { ao_block: 300, ..Default::default() }.validate().is_err());
    }

    #[test]
    fn power_of_two_levels_are_recognised() {
        assert!(PerfOptions::default().pow2_levels());
        assert!(PerfOptions::PLAIN.pow2_levels());
        assert!(!PerfOptions { ao_block: 3, ..Default::default() }.pow2_levels());
        assert!(!PerfOptions { block: 6, ..Default::default() }.pow2_levels());
        assert!(!PerfOptions { coarse: 24, ..Default::default() }.pow2_levels());
    }

    #[test]
    fn flags_follow_the_options() {
        assert_eq!(PerfOptions::PLAIN.flags(), 0);
        assert_eq!(
            PerfOptions { block_min_exit: true, ..PerfOptions::PLAIN }.flags(),
            super::super::frame_params::PERF_BLOCK_MIN_EXIT
        );
    }
}
