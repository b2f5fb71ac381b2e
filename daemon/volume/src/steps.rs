//! Time steps kept ready ahead of playback: a [`StepCache`] loads the steps of a time-varying
//! [`VolumeSource`] on a thread of its own, the current one first and then the ones after it
//! (wrapping at the end), as many as fit in a memory budget (`cache_bytes`), and drops the steps
//! behind. Asking for a step never blocks: it is [`StepState::Ready`], [`StepState::Loading`]
//! (the caller reports it and renders what it has) or [`StepState::Failed`] with the reason;
//! [`StepCache::wait`] waits at most as long as it is told.
//!
//! What a step is comes from the loader function: [`StepCache::new`] loads whole volumes (screen
//! space), [`StepCache::with_loader`] anything that says its size ([`Resident`]): object space
//! loads each step's brick and halo ([`crate::region::StepRegion`]).

use crate::io::{RawSpec, VolumeLimit};
use crate::{Volume, VolumeError, VolumeSource};
use std::collections::BTreeMap;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Where a step stands.
#[derive(Debug)]
pub enum StepState<T = Volume> {
    Ready(Arc<T>),
    Loading,
    Failed(String),
}

impl<T> Clone for StepState<T> {
    fn clone(&self) -> Self {
        match self {
            StepState::Ready(v) => StepState::Ready(v.clone()),
            StepState::Loading => StepState::Loading,
            StepState::Failed(e) => StepState::Failed(e.clone()),
        }
    }
}

/// What a loaded step holds in memory, in bytes (the cache's budget counts it).
pub trait Resident {
    fn resident_bytes(&self) -> usize;
}

impl Resident for Volume {
    fn resident_bytes(&self) -> usize {
        Volume::resident_bytes(self)
    }
}

/// Reads step `k` of a [`StepCache`] (on the cache's loader thread).
pub type StepLoader<T> = Box<dyn FnMut(usize) -> Result<T, VolumeError> + Send>;

struct State<T> {
    current: usize,
    loaded: BTreeMap<usize, Arc<T>>,
    failed: BTreeMap<usize, String>,
    /// Bytes of one step, known once the first is loaded (steps are taken to be alike).
    step_bytes: Option<usize>,
    /// The most steps resident at once (for tests and reports).
    peak_resident: usize,
    loads: usize,
    stop: bool,
}

impl<T> Default for State<T> {
    fn default() -> Self {
        State {
            current: 0,
            loaded: BTreeMap::new(),
            failed: BTreeMap::new(),
            step_bytes: None,
            peak_resident: 0,
            loads: 0,
            stop: false,
        }
    }
}

struct Shared<T> {
    state: Mutex<State<T>>,
    changed: Condvar,
    steps: usize,
    cache_bytes: usize,
}

impl<T> Shared<T> {
    fn lock(&self) -> MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// How many steps from the current one on the budget holds (at least the current one).
    fn ahead(&self, s: &State<T>) -> usize {
        let per = s.step_bytes.unwrap_or(usize::MAX).max(1);
        (self.cache_bytes / per).clamp(1, self.steps)
    }

    /// Whether `step` is among those [`Shared::ahead`] keeps.
    fn is_ahead(&self, s: &State<T>, step: usize) -> bool {
        (step + self.steps - s.current) % self.steps < self.ahead(s)
    }
}

/// Steps of a source, prefetched within a memory budget (see the module's notes).
pub struct StepCache<T = Volume> {
    shared: Arc<Shared<T>>,
    worker: Option<std::thread::JoinHandle<()>>,
}

impl StepCache<Volume> {
    /// Counts the source's steps and starts loading step 0; every step is read within `limit`.
    pub fn new(
        source: VolumeSource,
        raw: Option<RawSpec>,
        cache_bytes: usize,
        limit: VolumeLimit,
    ) -> Result<StepCache<Volume>, VolumeError> {
        let steps = source.time_steps()?;
        let name = source.to_string();
        let load = move |k| source.load_step_within(raw.as_ref(), k, &limit);
        StepCache::with_loader(steps, cache_bytes, name, Box::new(load))
    }
}

impl<T: Resident + Send + Sync + 'static> StepCache<T> {
    /// `steps` steps (at least 1), each read by `load` on the cache's loader thread, step 0 first;
    /// `name` names the source in its warnings.
    pub fn with_loader(
        steps: usize,
        cache_bytes: usize,
        name: String,
        load: StepLoader<T>,
    ) -> Result<StepCache<T>, VolumeError> {
        if steps == 0 {
            return Err(VolumeError::Source(format!("{name}: no time steps")));
        }
        let shared =
            Arc::new(Shared { state: Mutex::default(), changed: Condvar::new(), steps, cache_bytes });
        let worker = {
            let shared = shared.clone();
            std::thread::Builder::new()
                .name("isowall-steps".into())
                .spawn(move || load_ahead(&shared, &name, load))
                .map_err(|e| VolumeError::Source(format!("cannot start the time-step loader: {e}")))?
        };
        Ok(StepCache { shared, worker: Some(worker) })
    }
}

impl<T> StepCache<T> {
    pub fn steps(&self) -> usize {
        self.shared.steps
    }

    /// Makes `step` (modulo the count) the current step, so it and the ones after it are loaded,
    /// and says where it stands now, without waiting.
    pub fn get(&self, step: usize) -> StepState<T> {
        let mut s = self.shared.lock();
        self.look(&mut s, step)
    }

    /// [`StepCache::get`], waiting at most `timeout` for the step to be loaded.
    pub fn wait(&self, step: usize, timeout: Duration) -> StepState<T> {
        let deadline = Instant::now() + timeout;
        let mut s = self.shared.lock();
        loop {
            match self.look(&mut s, step) {
                StepState::Loading => {}
                done => return done,
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return StepState::Loading;
            }
            s = self.shared.changed.wait_timeout(s, left).unwrap_or_else(|p| p.into_inner()).0;
        }
    }

    fn look(&self, s: &mut State<T>, step: usize) -> StepState<T> {
        let step = step % self.shared.steps;
        if s.current != step {
            s.current = step;
            self.shared.changed.notify_all();
        }
        if let Some(v) = s.loaded.get(&step) {
            StepState::Ready(v.clone())
        } else if let Some(e) = s.failed.get(&step) {
            StepState::Failed(e.clone())
        } else {
            StepState::Loading
        }
    }

    /// The most steps that were resident at once, and the loads done so far.
    pub fn counts(&self) -> (usize, usize) {
        let s = self.shared.lock();
        (s.peak_resident, s.loads)
    }
}

impl<T> Drop for StepCache<T> {
    fn drop(&mut self) {
        self.shared.lock().stop = true;
        self.shared.changed.notify_all();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

/// The loader thread: keeps the steps the budget holds from the current one loaded, drops the
/// others.
fn load_ahead<T: Resident>(shared: &Shared<T>, name: &str, mut load: StepLoader<T>) {
    let mut s = shared.lock();
    loop {
        if s.stop {
            return;
        }
        let keep: Vec<usize> = s.loaded.keys().copied().filter(|&k| shared.is_ahead(&s, k)).collect();
        s.loaded.retain(|k, _| keep.contains(k));
        let ahead = shared.ahead(&s);
        let next = (0..ahead)
            .map(|d| (s.current + d) % shared.steps)
            .find(|k| !s.loaded.contains_key(k) && !s.failed.contains_key(k));
        let Some(step) = next else {
            s = shared.changed.wait(s).unwrap_or_else(|p| p.into_inner());
            continue;
        };
        drop(s);
        let result = load(step);
        s = shared.lock();
        s.loads += 1;
        match result {
            Ok(v) => {
                s.step_bytes.get_or_insert(v.resident_bytes());
                if shared.is_ahead(&s, step) {
                    s.loaded.insert(step, Arc::new(v));
                    s.peak_resident = s.peak_resident.max(s.loaded.len());
                }
            }
            Err(e) => {
                tracing::warn!("time step {step} of {name}: {e}");
                s.failed.insert(step, e.to_string());
            }
        }
        shared.changed.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` one-voxel-per-step NRRD files `step_K.nrrd` of 4x4x4 uchar voxels, all `K`.
    fn steps(dir: &std::path::Path, n: usize) -> VolumeSource {
        for k in 0..n {
            let mut bytes = b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n\n".to_vec();
            bytes.extend([k as u8; 64]);
            std::fs::write(dir.join(format!("step_{k:02}.nrrd")), bytes).unwrap();
        }
        format!("{}/step_*.nrrd", dir.display()).parse().unwrap()
    }

    fn ready<T: std::fmt::Debug>(c: &StepCache<T>, step: usize) -> Arc<T> {
        match c.wait(step, Duration::from_secs(20)) {
            StepState::Ready(v) => v,
            other => panic!("step {step}: {other:?}"),
        }
    }

    #[test]
    fn steps_ahead_are_prefetched_within_the_budget() {
        let dir = tempfile::tempdir().unwrap();
        // Each step is 64 f32 = 256 bytes: a budget of 3 steps.
        let c = StepCache::new(steps(dir.path(), 6), None, 3 * 256 + 10, VolumeLimit::default()).unwrap();
        assert_eq!(c.steps(), 6);
        assert_eq!(ready(&c, 0).data()[0], 0.0);
        // Steps 1 and 2 arrive without being asked for beyond the current one.
        let deadline = Instant::now() + Duration::from_secs(20);
        while c.shared.lock().loaded.len() < 3 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(c.shared.lock().loaded.keys().copied().collect::<Vec<_>>(), [0, 1, 2]);
        // Playing on: step 4 drops 0..=3 behind it; the steps ahead wrap to 0.
        assert_eq!(ready(&c, 4).data()[0], 4.0);
        assert_eq!(ready(&c, 5).data()[0], 5.0);
        assert_eq!(ready(&c, 0).data()[0], 0.0);
        let (peak, loads) = c.counts();
        assert!(peak <= 3, "{peak} steps were resident at once");
        // 0, 1, 2, then 4 and 5 (0 stays among the steps ahead from 4 on).
        assert!(loads >= 5, "{loads}");
    }

    #[test]
    fn a_step_not_loaded_is_reported_and_a_broken_one_fails_with_its_file() {
        let dir = tempfile::tempdir().unwrap();
        let source = steps(dir.path(), 3);
        std::fs::write(dir.path().join("step_01.nrrd"), b"NRRD0004\ntype: uchar\n").unwrap();
        let c = StepCache::new(source, None, 1, VolumeLimit::default()).unwrap();
        // A zero wait never blocks: the step is loading (or, on a fast machine, ready).
        assert!(!matches!(c.wait(2, Duration::ZERO), StepState::Failed(_)));
        match c.wait(1, Duration::from_secs(20)) {
            StepState::Failed(e) => assert!(e.contains("step_01.nrrd"), "{e}"),
            other => panic!("{other:?}"),
        }
        assert_eq!(ready(&c, 2).data()[0], 2.0);
    }

    #[test]
    fn a_bricks_steps_are_region_reads_prefetched_within_the_budget() {
        use crate::region::StepRegion;
        use crate::VoxelRange;
        let dir = tempfile::tempdir().unwrap();
        let source = steps(dir.path(), 5);
        let first = source.stream(None).unwrap().info().clone();
        let range = VoxelRange { lo: [1, 0, 2], hi: [3, 3, 3] };
        let loader = {
            let (source, first) = (source.clone(), first.clone());
            move |k| source.read_step_region(None, k, &range, 2, &first)
        };
        // A region is 3x4x2 f32 (96 bytes) plus the 2x2x2 block grid (64 bytes): 2 steps fit.
        let c: StepCache<StepRegion> =
            StepCache::with_loader(5, 2 * 160 + 10, source.to_string(), Box::new(loader)).unwrap();
        assert_eq!(c.steps(), 5);
        for k in [0, 1, 2, 4, 0] {
            let r = ready(&c, k);
            assert_eq!(r.step, k);
            assert_eq!(r.region.dims(), [3, 4, 2]);
            assert!(r.region.data().iter().all(|&x| x == k as f32), "step {k}");
            assert_eq!(r.blocks.value_range(), (k as f32, k as f32));
            assert_eq!(r.blocks.counts, [2, 2, 2]);
        }
        let (peak, loads) = c.counts();
        assert!(peak <= 2, "{peak} steps were resident at once");
        assert!(loads >= 5, "{loads}");
        // A broken step fails with its file, the others still load.
        std::fs::write(dir.path().join("step_03.nrrd"), b"NRRD0004\ntype: uchar\n").unwrap();
        match c.wait(3, Duration::from_secs(20)) {
            StepState::Failed(e) => assert!(e.contains("step_03.nrrd"), "{e}"),
            other => panic!("{other:?}"),
        }
        assert_eq!(ready(&c, 4).step, 4);
    }
}
