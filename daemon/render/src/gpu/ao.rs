//! `Kernel::Ao` (shaders/ao.wgsl): ambient occlusion (ours, or the 2008 `seed` baseline), bent
//! normal and the IBL term of one frame at every hit, added into accumulators.

use super::frame_params::gpu_code;
use super::{
    buffer_entries, frame_entries, marks_entry, storage_entry, Aovs, FrameParams, GpuContext, GpuError,
    GpuVolume, PerfOptions,
};
use crate::shaders::Kernel;
use isowall_model::AoMethod;

/// The most dispatches one frame's AO samples are split over.
pub const MAX_AO_DISPATCHES: u32 = 256;

/// Loop iterations per sample besides the ray's own walk, counted generously: the sample loop's
/// own and slack (the sampling itself has no loop).
const SAMPLE_LOOP_EXTRA: u32 = 40;

/// Iterations an invocation may use before the budget's end, kept free (the set-up's loops).
const LOOP_BUDGET_RESERVE: u32 = 1024;

/// How a frame's AO samples are split over dispatches of the kernel. Mesa's lavapipe (llvmpipe)
/// ends every loop of an invocation once the invocation's loops together have iterated 65535
/// times (gallivm's `LP_MAX_TGSI_LOOP_ITERATIONS`, one counter shared by all loops of the
/// shader): past it, each loop runs its body once and leaves, silently. A pixel with many samples
/// of long rays (the CT at an unbounded radius: ~1024 samples of ~60 cells) reached it, its later
/// rays came back "open" and its occlusion low. Where the device has such a budget, each dispatch
/// takes only as many samples as the budget holds in the worst case (every ray at its iteration
/// cap); the dispatches add their share of the frame's estimate, so the sum is the frame's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AoDispatches {
    /// Samples per dispatch (the last may take fewer).
    pub samples: u32,
    /// Dispatches per frame.
    pub count: u32,
    /// The kernel's pipeline that runs them.
    pub path: AoPath,
}

/// Which of the kernel's two pipelines runs a frame (`AO_PATH` in shaders/ao.wgsl). A SIMD CPU
/// driver (lavapipe) runs every branch of a kernel for each group of pixels, masked, whether a lane
/// takes it or not, so the default's own pipeline holds none of the other paths' load sites
/// (docs/bench/kernel-time-lavapipe.md, "Fifth session").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AoPath {
    /// Every method and test, the frame's parameters choosing.
    Any,
    /// Only ours with the exact test and no environment rays (the defaults).
    Exact,
}

impl AoPath {
    /// The path a frame of `params` takes.
    pub fn of(params: &FrameParams) -> AoPath {
        let ours = params.ao_method == gpu_code(AoMethod::Ours.code());
        if ours && params.ao_exact == 1 && params.ibl != gpu_code(isowall_model::IblMethod::Rays.code()) {
            AoPath::Exact
        } else {
            AoPath::Any
        }
    }

    /// The kernel's code (shaders/ao.wgsl: `AO_PATH_*`).
    pub fn code(self) -> u32 {
        match self {
            AoPath::Any => 0,
            AoPath::Exact => 1,
        }
    }
}

impl AoDispatches {
    /// Splits `params`' samples (the most a pixel takes: `ao_samples`, or `ao_pass[2]` where it is
    /// larger) for a device whose invocations may iterate `budget` times in all (`None`: no
    /// limit, one dispatch), and writes the samples per dispatch into `params`.
    pub fn split(params: &mut FrameParams, budget: Option<u32>) -> AoDispatches {
        // The most samples a pixel takes: the frame's, or more where they are spent by history.
        let total = params.ao_samples.max(params.ao_pass[2]).max(1);
        let per_ray = if params.ao_method == gpu_code(AoMethod::Seed.code()) {
            SEED_STEPS
        } else if params.ao_exact == 1 {
            params.ao_pass[1]
        } else {
            params.max_steps
        };
        let samples = match budget {
            None => total,
            Some(b) => {
                let per_sample = per_ray.saturating_add(SAMPLE_LOOP_EXTRA).max(1);
                (b.saturating_sub(LOOP_BUDGET_RESERVE) / per_sample).max(1)
            }
        };
        // At most MAX_AO_DISPATCHES (past it the budget may run out on the worst rays).
        let samples = samples.max(total.div_ceil(MAX_AO_DISPATCHES)).min(total);
        params.ao_pass[0] = samples;
        AoDispatches { samples, count: total.div_ceil(samples), path: AoPath::of(params) }
    }
}

/// The seed's march length per ray (shaders/ao.wgsl `seed_occluded`), plus one.
const SEED_STEPS: u32 = 91;

/// The compiled kernel.
pub struct AoKernel {
    /// The pipelines of `AoPath::Any` and `AoPath::Exact`.
    any: wgpu::ComputePipeline,
    exact: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    workgroup: (u32, u32),
    /// The dispatch indices 0..MAX_AO_DISPATCHES, one per `dispatch_stride` bytes, bound at 9
    /// with a dynamic offset.
    dispatch_index: wgpu::Buffer,
    dispatch_stride: u32,
}

impl AoKernel {
    /// The bind group layout: the frame's inputs (0-2, 11), the primary hits, the accumulators and the
    /// pass's sample range (a test holds it to naga's reflection of the WGSL).
    pub(crate) fn entries() -> Vec<wgpu::BindGroupLayoutEntry> {
        let [e0, e1, e2, marks] = frame_entries();
        vec![
            e0,
            e1,
            e2,
            marks,
            storage_entry(3, true),
            storage_entry(4, true),
            storage_entry(5, true),
            storage_entry(6, false),
            storage_entry(7, false),
            storage_entry(8, false),
            storage_entry(10, false),
            wgpu::BindGroupLayoutEntry {
                binding: 9,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: true },
                    has_dynamic_offset: true,
                    min_binding_size: wgpu::BufferSize::new(16),
                },
                count: None,
            },
        ]
    }

    /// The kernel compiled for `perf`'s workgroup shape, voxel format and block levels, for
    /// volumes held whole or `bricked`.
    pub fn new(ctx: &GpuContext, perf: &PerfOptions, bricked: bool) -> Result<AoKernel, GpuError> {
        let entries = Self::entries();
        let workgroup = perf.workgroup;
        let with_path = |path: AoPath| {
            let mut constants = perf.volume_constants(bricked).to_vec();
            constants.push(("AO_PATH", f64::from(path.code())));
            constants
        };
        let (any, layout) = ctx.pipeline(Kernel::Ao, &entries, workgroup, &with_path(AoPath::Any))?;
        let exact = ctx.pipeline_for_layout(Kernel::Ao, &layout, workgroup, &with_path(AoPath::Exact))?;
        let dispatch_stride = ctx.device.limits().min_storage_buffer_offset_alignment.max(16);
        let mut indices = vec![0u8; (dispatch_stride * MAX_AO_DISPATCHES) as usize];
        for k in 0..MAX_AO_DISPATCHES {
            let at = (k * dispatch_stride) as usize;
            indices[at..at + 4].copy_from_slice(&k.to_le_bytes());
        }
        let dispatch_index = ctx.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("ao dispatch index"),
            contents: &indices,
            usage: wgpu::BufferUsages::STORAGE,
        });
        Ok(AoKernel { any, exact, layout, workgroup, dispatch_index, dispatch_stride })
    }

    /// The bind group of the kernel's inputs and `io` (as [`AoKernel::encode`] takes them), made
    /// once per tile, volume and environment ([`TileTarget`](super::tile::TileTarget)).
    pub(crate) fn bind(
        &self,
        ctx: &GpuContext,
        params: &wgpu::Buffer,
        volume: &GpuVolume,
        env: &wgpu::Buffer,
        aovs: &Aovs,
    ) -> wgpu::BindGroup {
        let a = aovs;
        let buffers = [
            params,
            &volume.voxels,
            &volume.block_minmax,
            &a.direct,
            &a.geometry,
            env,
            &a.ao_sum,
            &a.ibl_sum,
            &a.fetches,
        ];
        let mut entries = buffer_entries(&buffers);
        entries.push(wgpu::BindGroupEntry { binding: 10, resource: a.pos_sum.as_entire_binding() });
        entries.push(marks_entry(volume));
        entries.push(wgpu::BindGroupEntry {
            binding: 9,
            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer: &self.dispatch_index,
                offset: 0,
                size: wgpu::BufferSize::new(16),
            }),
        });
        ctx.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("ao"),
            layout: &self.layout,
            entries: &entries,
        })
    }

    /// Records one frame of the kernel over a `size` rectangle with a bind group from
    /// [`AoKernel::bind`]: `dispatches.count` dispatches, each adding its share of the samples.
    /// `timestamps` bracket them all (the first's beginning, the last's end).
    pub(crate) fn pass(
        &self,
        enc: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        size: (u32, u32),
        dispatches: AoDispatches,
        timestamps: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        let count = dispatches.count.clamp(1, MAX_AO_DISPATCHES);
        for k in 0..count {
            // A pass between the first and the last writes no timestamp: it has no writes at all
            // (wgpu refuses timestamp writes that name neither index).
            let timestamp_writes = timestamps
                .as_ref()
                .map(|t| wgpu::ComputePassTimestampWrites {
                    query_set: t.query_set,
                    beginning_of_pass_write_index: if k == 0 {
                        t.beginning_of_pass_write_index
                    } else {
                        None
                    },
                    end_of_pass_write_index: if k + 1 == count { t.end_of_pass_write_index } else { None },
                })
                .filter(|t| t.beginning_of_pass_write_index.is_some() || t.end_of_pass_write_index.is_some());
            let mut pass =
                enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("ao"), timestamp_writes });
            pass.set_pipeline(match dispatches.path {
                AoPath::Any => &self.any,
                AoPath::Exact => &self.exact,
            });
            pass.set_bind_group(0, bind_group, &[k * self.dispatch_stride]);
            pass.dispatch_workgroups(size.0.div_ceil(self.workgroup.0), size.1.div_ceil(self.workgroup.1), 1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(samples: u32, method: AoMethod, exact: bool, walk_cap: u32) -> FrameParams {
        let mut p: FrameParams = bytemuck::Zeroable::zeroed();
        p.ao_samples = samples;
        p.ao_method = gpu_code(method.code());
        p.ao_exact = u32::from(exact);
        p.ao_pass = [samples.max(1), walk_cap, 0, 0];
        p.max_steps = 900;
        p
    }

    #[test]
    fn the_wgsl_names_the_paths_by_their_codes() {
        let ao = crate::shaders::tests::wgsl_constants(Kernel::Ao);
        assert_eq!(ao.get("AO_PATH_ANY"), Some(&AoPath::Any.code()));
        assert_eq!(ao.get("AO_PATH_EXACT"), Some(&AoPath::Exact.code()));
    }

    #[test]
    fn only_ours_exact_without_environment_rays_takes_the_exact_pipeline() {
        use isowall_model::IblMethod;
        for ibl in IblMethod::ALL {
            for (method, exact) in [(AoMethod::Ours, true), (AoMethod::Ours, false), (AoMethod::Seed, true)] {
                let mut p = params(32, method, exact, 172);
                p.ibl = gpu_code(ibl.code());
                let want = if method == AoMethod::Ours && exact && ibl != IblMethod::Rays {
                    AoPath::Exact
                } else {
                    AoPath::Any
                };
                assert_eq!(AoPath::of(&p), want, "{method:?} exact {exact} {ibl:?}");
                assert_eq!(AoDispatches::split(&mut p, Some(65535)).path, want);
            }
        }
    }

    #[test]
    fn dispatches_fit_the_loop_budget_and_cover_every_sample() {
        // No budget: one dispatch of every sample, whatever the walk.
        let mut p = params(1024, AoMethod::Ours, true, 2496);
        let exact = AoPath::Exact;
        assert_eq!(AoDispatches::split(&mut p, None), AoDispatches { samples: 1024, count: 1, path: exact });
        assert_eq!(p.ao_pass[0], 1024);
        // lavapipe's budget, the CT's whole-box cap: (65535 - 1024) / (2496 + 40) = 25 per dispatch.
        let d = AoDispatches::split(&mut p, Some(65535));
        assert_eq!(d, AoDispatches { samples: 25, count: 41, path: exact });
        assert_eq!(p.ao_pass[0], 25);
        for (samples, method, exact, cap) in [
            (32, AoMethod::Ours, true, 172),
            (256, AoMethod::Ours, true, 172),
            (4096, AoMethod::Ours, true, 2496),
            (1000, AoMethod::Ours, false, 0),
            (1024, AoMethod::Seed, true, 0),
            (0, AoMethod::Ours, true, 172),
        ] {
            let mut p = params(samples, method, exact, cap);
            let d = AoDispatches::split(&mut p, Some(65535));
            // Every sample is in exactly one dispatch, none empty, within the cap on dispatches.
            assert!(d.count >= 1 && d.count <= MAX_AO_DISPATCHES, "{samples} {method:?}: {d:?}");
            assert!(d.samples * d.count >= samples.max(1) && d.samples * (d.count - 1) < samples.max(1));
            let per_ray = match (method, exact) {
                (AoMethod::Seed, _) => SEED_STEPS,
                (_, true) => cap,
                (_, false) => 900,
            };
            // The worst case fits the budget unless the dispatch cap forced more per dispatch.
            if d.count < MAX_AO_DISPATCHES {
                assert!(d.samples * (per_ray + SAMPLE_LOOP_EXTRA) + LOOP_BUDGET_RESERVE <= 65535, "{d:?}");
            }
        }
        // The default radius on a unit-spacing volume fits 256 samples in one dispatch.
        let mut p = params(256, AoMethod::Ours, true, 172);
        assert_eq!(AoDispatches::split(&mut p, Some(65535)).count, 1);
        // Samples spent by history: the dispatches cover the most a pixel takes.
        let mut p = params(4, AoMethod::Ours, true, 2496);
        p.ao_pass[2] = 64;
        let d = AoDispatches::split(&mut p, Some(65535));
        assert_eq!(d, AoDispatches { samples: 25, count: 3, path: exact });
    }
}
