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
//!
//! The budget counts what the steps really hold: [`Resident::resident_bytes`] is a step's
//! allocation (capacity, not length, and its bookkeeping), a step of a 4-D file holds a buffer of
//! its own voxels only (never the whole file's), and the steps kept ahead are as many as fit at
//! the largest step seen so far (the steps of a glob may differ in size). While a step loads, the
//! ones kept stay resident: the peak is the budget plus one step. A 4-D file's steps are read
//! from one stream kept open ([`crate::io`]'s `StepFile`): a pass over the steps in order
//! inflates a compressed file once, not once per step.

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

/// What a loaded step holds in memory, in bytes (the cache's budget counts it): its allocations
/// as made (capacity, not length).
pub trait Resident {
    fn resident_bytes(&self) -> usize;
}

impl Resident for Volume {
    /// The voxel buffer as allocated, the name and the struct.
    fn resident_bytes(&self) -> usize {
        Volume::resident_bytes(self) + self.name.capacity() + std::mem::size_of::<Volume>()
    }
}

/// Reads step `k` of a [`StepCache`] (on the cache's loader thread).
pub type StepLoader<T> = Box<dyn FnMut(usize) -> Result<T, VolumeError> + Send>;

struct State<T> {
    current: usize,
    loaded: BTreeMap<usize, Arc<T>>,
    failed: BTreeMap<usize, String>,
    /// Bytes of the largest step loaded so far, with its place in the cache.
    step_bytes: Option<usize>,
    /// The most steps resident at once (for tests and reports).
    peak_resident: usize,
    /// Bytes the loaded steps hold now, and the most they held at once.
    resident_bytes: usize,
    peak_resident_bytes: usize,
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
            resident_bytes: 0,
            peak_resident_bytes: 0,
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
        // A 4-D file: its steps from one stream kept open (see the module's notes).
        let mut file = match &source {
            VolumeSource::File(path) => crate::io::step_file(path, &limit)?.filter(|f| f.steps > 1),
            _ => None,
        };
        let load = move |k| match &mut file {
            Some(file) => file.read(k),
            None => source.load_step_within(raw.as_ref(), k, &limit),
        };
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

    /// The bytes the loaded steps hold now ([`Resident::resident_bytes`] with the cache's own
    /// bookkeeping), and the most they held at once.
    pub fn resident_bytes(&self) -> (usize, usize) {
        let s = self.shared.lock();
        (s.resident_bytes, s.peak_resident_bytes)
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
    // The current step and the steps ahead at the last sweep of the steps behind, and how many
    // steps from the current one on are known loaded or failed since: each load costs a look at
    // one more step, not at all of them (a file may hold tens of thousands of steps).
    let mut swept = None;
    let mut scanned = 0;
    loop {
        if s.stop {
            return;
        }
        let ahead = shared.ahead(&s);
        if swept != Some((s.current, ahead)) {
            // The steps kept are the ring [current, current + ahead): only the keys outside it
            // are looked at.
            let (lo, hi, n) = (s.current, s.current + ahead, shared.steps);
            let behind: Vec<usize> = if hi <= n {
                s.loaded.range(..lo).chain(s.loaded.range(hi..)).map(|(&k, _)| k).collect()
            } else {
                s.loaded.range(hi - n..lo).map(|(&k, _)| k).collect()
            };
            for k in behind {
                if let Some(v) = s.loaded.remove(&k) {
                    s.resident_bytes -= held(&*v);
                }
            }
            swept = Some((s.current, ahead));
            scanned = 0;
        }
        let mut next = None;
        while scanned < ahead {
            let k = (s.current + scanned) % shared.steps;
            if !s.loaded.contains_key(&k) && !s.failed.contains_key(&k) {
                next = Some(k);
                break;
            }
            scanned += 1;
        }
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
                let bytes = held(&v);
                s.step_bytes = Some(s.step_bytes.unwrap_or(0).max(bytes));
                if shared.is_ahead(&s, step) {
                    s.loaded.insert(step, Arc::new(v));
                    s.resident_bytes += bytes;
                    s.peak_resident = s.peak_resident.max(s.loaded.len());
                    s.peak_resident_bytes = s.peak_resident_bytes.max(s.resident_bytes);
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

/// What a loaded step costs the cache: its own bytes, its `Arc`'s counts and its map entry.
fn held<T: Resident>(v: &T) -> usize {
    v.resident_bytes() + 2 * std::mem::size_of::<usize>() + std::mem::size_of::<(usize, Arc<T>)>()
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
        // Each step is 64 f32 = 256 bytes and its bookkeeping: a budget of 3 steps.
        let source = steps(dir.path(), 6);
        let one = held(&source.load_step(None, 0).unwrap());
        assert!((256..1024).contains(&one), "{one}");
        let c = StepCache::new(source, None, 3 * one + 10, VolumeLimit::default()).unwrap();
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
        // A region is 3x4x2 f32 (96 bytes) plus the 2x2x2 block grid (64 bytes) and their
        // bookkeeping: 2 steps fit.
        let one = held(&source.read_step_region(None, 0, &range, 2, &first).unwrap());
        assert!((160..1024).contains(&one), "{one}");
        let c: StepCache<StepRegion> =
            StepCache::with_loader(5, 2 * one + 10, source.to_string(), Box::new(loader)).unwrap();
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

    /// A gzip NRRD of `steps` time steps of `n`^3 uchar voxels, step k all `k % 251`.
    fn gzip_4d_nrrd(dir: &std::path::Path, n: usize, steps: usize) -> std::path::PathBuf {
        let voxels: Vec<u8> =
            (0..steps).flat_map(|k| std::iter::repeat_n((k % 251) as u8, n * n * n)).collect();
        let head =
            format!("NRRD0004\ntype: uchar\ndimension: 4\nsizes: {n} {n} {n} {steps}\nencoding: gzip\n\n");
        let p = dir.join("four.nrrd");
        std::fs::write(&p, [head.into_bytes(), crate::io::testutil::gzip(&voxels)].concat()).unwrap();
        p
    }

    #[test]
    fn a_4d_files_steps_hold_their_own_voxels_and_the_budget_counts_them() {
        // The attack, scaled down: a gzip NRRD of 16^3 x 64 steps (a few KB on disk, 1 MiB of
        // voxels as float32) under a budget of 4 steps. Each cached step used to keep the whole
        // file's buffer (64 steps' voxels) while the budget counted one step's.
        let dir = tempfile::tempdir().unwrap();
        let (n, steps) = (16, 64);
        let step_bytes = n * n * n * 4;
        let budget = 4 * step_bytes + 4096;
        let path = gzip_4d_nrrd(dir.path(), n, steps);
        let c = StepCache::new(VolumeSource::File(path), None, budget, VolumeLimit::default()).unwrap();
        for k in [0, 1, 2, 3, 4, 40, 63, 0, 5] {
            let v = ready(&c, k);
            assert_eq!(v.dims(), [n, n, n]);
            assert!(v.data().iter().all(|&x| x == k as f32), "step {k}");
            assert_eq!(
                v.data.capacity(),
                n * n * n,
                "step {k} holds a buffer of {} voxels",
                v.data.capacity()
            );
            assert!(Resident::resident_bytes(&*v) < step_bytes + 1024, "{}", Resident::resident_bytes(&*v));
        }
        let (now, peak) = c.resident_bytes();
        assert!(peak <= budget, "the cache held {peak} bytes at once, over its budget of {budget}");
        assert!(now <= peak);
        let (peak_steps, _) = c.counts();
        assert!(peak_steps <= 4, "{peak_steps} steps were resident at once");
    }

    #[test]
    fn tiny_steps_of_a_gzip_nifti_cost_their_own_bytes_and_one_inflation_a_pass() {
        // The attack: a few hundred bytes of `.nii.gz` holding 32,767 one-voxel steps. Each step
        // used to inflate the whole file into a buffer of all 32,767 voxels and keep it (0.9 GB
        // and climbing); now a step holds one voxel and a pass inflates the file once.
        let dir = tempfile::tempdir().unwrap();
        let steps = 32767usize;
        let mut h = vec![0u8; 352];
        h[0..4].copy_from_slice(&348i32.to_le_bytes());
        for (i, d) in [4i16, 1, 1, 1, steps as i16, 1, 1, 1].iter().enumerate() {
            h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
        }
        h[70..72].copy_from_slice(&2i16.to_le_bytes()); // datatype: uint8
        h[72..74].copy_from_slice(&8i16.to_le_bytes()); // bitpix
        for i in 0..8 {
            h[76 + 4 * i..80 + 4 * i].copy_from_slice(&1f32.to_le_bytes()); // pixdim
        }
        h[108..112].copy_from_slice(&352f32.to_le_bytes()); // vox_offset
        h[344..348].copy_from_slice(b"n+1\0");
        h.extend(vec![7u8; steps]);
        let gz = crate::io::testutil::gzip(&h);
        let path = dir.path().join("tiny.nii.gz");
        std::fs::write(&path, &gz).unwrap();
        assert!(gz.len() < 1000, "{} bytes", gz.len());

        let budget = 16 << 20;
        let start = Instant::now();
        let c =
            StepCache::new(VolumeSource::File(path.clone()), None, budget, VolumeLimit::default()).unwrap();
        assert_eq!(c.steps(), steps);
        ready(&c, 0);
        // The whole pass: every step fits the budget, so every step is loaded.
        let deadline = Instant::now() + Duration::from_secs(60);
        while c.counts().1 < steps && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(5));
        }
        let elapsed = start.elapsed();
        assert_eq!(c.counts().1, steps, "loaded in {elapsed:?}");
        let last = ready(&c, steps - 1);
        assert_eq!(last.data(), [7.0]);
        assert_eq!(last.data.capacity(), 1);
        let (now, peak) = c.resident_bytes();
        let (_, loads) = c.counts();
        eprintln!("{loads} steps loaded in {elapsed:?}, {now} bytes resident (peak {peak})");
        assert!(peak <= budget, "the cache held {peak} bytes, over its budget of {budget}");
        // Every step is counted with its bookkeeping: a few hundred bytes, not 4.
        assert!(now >= loads * (4 + std::mem::size_of::<Volume>()), "{now} bytes for {loads} steps");
        drop(c);

        // One pass in order inflates the file once; going back opens it again.
        let mut file = crate::io::step_file(&path, &VolumeLimit::default()).unwrap().unwrap();
        for k in 0..steps {
            assert_eq!(file.read(k).unwrap().data(), [7.0]);
        }
        assert_eq!(file.inflations, 1);
        file.read(3).unwrap();
        file.read(4).unwrap();
        assert_eq!(file.inflations, 2);
        let e = file.read(steps).unwrap_err().to_string();
        assert!(e.contains("tiny.nii.gz") && e.contains("has no time step 32767"), "{e}");
    }

    #[test]
    fn a_bricks_steps_of_a_gzip_4d_file_inflate_it_once_a_pass() {
        use crate::region::StepRegion;
        use crate::VoxelRange;
        let dir = tempfile::tempdir().unwrap();
        let (n, steps) = (8, 40);
        let source = VolumeSource::File(gzip_4d_nrrd(dir.path(), n, steps));
        let first = source.stream(None).unwrap().info().clone();
        let range = VoxelRange { lo: [1, 2, 3], hi: [6, 5, 7] };
        let mut regions = source.step_regions(None, range, 4, first.clone()).unwrap();
        for k in 0..steps {
            let r = regions.read(k).unwrap();
            let want = source.read_step_region(None, k, &range, 4, &first).unwrap();
            assert_eq!(
                (r.step, r.region.dims(), r.region.origin()),
                (k, want.region.dims(), want.region.origin())
            );
            assert_eq!(r.region.data(), want.region.data(), "step {k}");
            assert_eq!(r.blocks.minmax, want.blocks.minmax, "step {k}");
        }
        assert_eq!(regions.inflations(), 1, "one pass in order");
        regions.read(0).unwrap();
        assert_eq!(regions.inflations(), 2, "back to step 0: opened again");
        // Through the cache, as an object-space node plays it.
        let c: StepCache<StepRegion> =
            StepCache::with_loader(steps, 1 << 20, source.to_string(), Box::new(move |k| regions.read(k)))
                .unwrap();
        assert_eq!(ready(&c, 39).step, 39);
    }
}
