//! Parts of a volume without the whole (object space, DESIGN.md "Distribution"): a node of an
//! object-space wall holds only its brick and halo. Two passes over a source, neither keeping the
//! whole volume:
//!
//! - [`VolumeStream::block_minmax`]: the per-block min/max of the whole volume (the occupancy grid
//!   the brick split balances on), read z-slice by z-slice: resident is one slice of voxels plus
//!   the block grid. It also checks the whole file (size, NaN/Inf) as a full read would.
//! - [`VolumeStream::read_region`]: the samples of a [`VoxelRange`] only.
//!
//! Time-varying volumes ([`VolumeSource::stream_step`]): each step is opened alone (a glob's
//! file; a 4-D NRRD's own slices of the file; a 4-D NIfTI's step read alone, whole), and
//! [`VolumeSource::read_step_region`] gives a step's region and the step's whole block grid in one
//! pass over the step ([`VolumeStream::read_region_and_blocks`]): every node marches the whole box
//! with the step's own empty-space skipping, so each node reads every step whole (a slice at a
//! time) and keeps its region.
//!
//! How each source is read:
//! - raw files and NRRD with `encoding: raw`: by seeking; a region reads, per z-slice of the range,
//!   the rows of its y-range (whole rows: the x-range is cropped in memory, one slice at a time);
//! - NRRD with `encoding: gzip`: by streaming: the stream is decompressed from its start and
//!   everything outside the region is decoded and dropped, a slice at a time (compressed streams
//!   cannot seek), so a region costs the decompression of the file up to the region's last slice;
//! - procedural volumes: only the region's samples are generated;
//! - DICOM series: only the slices (files) of the region's z-range are decoded, each whole
//!   (compressed slices cannot be decoded in part) and cropped in memory;
//! - MetaImage, NIfTI and NRRD whose `space directions` mirror an axis: the whole volume is read
//!   once and cropped (it is resident while that happens, then dropped): a documented limit.
//!
//! Every region is a [`Volume`] whose origin is the world position of the range's first sample.
//!
//! Both passes report their progress, z-slice by z-slice, to an observer set with
//! [`VolumeStream::on_progress`] (the daemon draws it as a bar, a systemd status and log lines).

use crate::io::{FilePlan, RawSpec};
use crate::{BlockMinMax, Volume, VolumeError, VolumeSource, VoxelRange};
use glam::DVec3;
use std::path::PathBuf;

/// What a volume is, without its voxels.
#[derive(Clone, Debug, PartialEq)]
pub struct VolumeInfo {
    pub name: String,
    pub dims: [usize; 3],
    pub spacing: DVec3,
    pub origin: DVec3,
}

impl VolumeInfo {
    pub fn box_min(&self) -> DVec3 {
        self.origin
    }
    pub fn box_max(&self) -> DVec3 {
        self.origin
            + self.spacing
                * DVec3::new((self.dims[0] - 1) as f64, (self.dims[1] - 1) as f64, (self.dims[2] - 1) as f64)
    }
}

enum Kind {
    File(FilePlan),
    Procedural(crate::procedural::Procedural, Option<usize>),
    /// A DICOM series: one file per z-slice.
    Dicom(Box<crate::io::dicom::Series>),
    /// Read whole, then cropped (formats without partial reads).
    Whole(Box<Volume>),
}

/// Which pass of a [`VolumeStream`] a progress report is about.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pass {
    /// [`VolumeStream::block_minmax`]: the whole volume, for the occupancy grid.
    Scan,
    /// [`VolumeStream::read_region`]: the samples of one region.
    Read,
}

impl Pass {
    pub fn name(self) -> &'static str {
        match self {
            Pass::Scan => "scanning",
            Pass::Read => "reading",
        }
    }
}

/// Progress of a pass: `done` of `total` z-slices.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Progress {
    pub pass: Pass,
    pub done: usize,
    pub total: usize,
}

/// The observer of [`VolumeStream::on_progress`].
pub type ProgressFn = Box<dyn Fn(Progress) + Send + Sync>;

/// A volume source opened for partial reads.
pub struct VolumeStream {
    info: VolumeInfo,
    /// The patient orientation the source gives, if any.
    orientation: Option<crate::Orientation>,
    kind: Kind,
    progress: Option<ProgressFn>,
}

impl VolumeSource {
    /// Opens the source (its first time step) for partial reads: [`VolumeSource::stream_step`]
    /// of step 0.
    pub fn stream(&self, raw: Option<&RawSpec>) -> Result<VolumeStream, VolumeError> {
        self.stream_step(raw, 0)
    }

    /// Opens time step `step` for partial reads: reads a file's header only (MetaImage, NIfTI and
    /// mirrored NRRD are read whole here; see the module's notes). A glob's step is its file
    /// `step`; a 4-D NRRD's step is read from its own slices of the file (a raw one by seeking);
    /// a 4-D NIfTI's step is read whole, alone (as [`VolumeSource::load_step`] does).
    pub fn stream_step(&self, raw: Option<&RawSpec>, step: usize) -> Result<VolumeStream, VolumeError> {
        let stream = self.open_step(raw, step)?;
        let i = &stream.info;
        crate::check_geometry(&i.name, i.dims, i.spacing, i.origin)?;
        Ok(stream)
    }

    /// [`VolumeSource::stream_step`] before its geometry is checked.
    fn open_step(&self, raw: Option<&RawSpec>, step: usize) -> Result<VolumeStream, VolumeError> {
        match self {
            VolumeSource::Procedural { kind, size } => {
                self.only_step_0(step)?;
                let dims = kind.dims(*size);
                let info = VolumeInfo {
                    name: format!("procedural:{}:{}", kind.name(), dims[0]),
                    dims,
                    spacing: DVec3::ONE,
                    origin: DVec3::ZERO,
                };
                Ok(VolumeStream {
                    info,
                    orientation: None,
                    kind: Kind::Procedural(*kind, *size),
                    progress: None,
                })
            }
            VolumeSource::DicomSeries { path, series } => {
                self.only_step_0(step)?;
                Ok(VolumeStream::dicom(crate::io::dicom::Series::open(path, Some(series))?, path))
            }
            VolumeSource::Steps(_) => VolumeSource::File(self.step_file(step)?).open_step(raw, 0),
            VolumeSource::File(path) if crate::io::dicom::is_dicom(path) => {
                self.only_step_0(step)?;
                Ok(VolumeStream::dicom(crate::io::dicom::Series::open(path, None)?, path))
            }
            VolumeSource::File(path) => {
                let steps = crate::io::time_steps(path)?;
                if step >= steps {
                    return Err(crate::io::format_err(
                        path,
                        format!("has no time step {step}: it holds {steps} (0 to {})", steps - 1),
                    ));
                }
                match crate::io::plan(path, raw)? {
                    Some((plan, spacing, origin)) => {
                        let plan = plan.time_step(step, steps);
                        let info = VolumeInfo {
                            name: path.display().to_string(),
                            dims: plan.layout.dims,
                            spacing,
                            origin,
                        };
                        let orientation = crate::io::plan_orientation(path)?;
                        Ok(VolumeStream { info, orientation, kind: Kind::File(plan), progress: None })
                    }
                    None => {
                        let v = crate::io::load_step(path, raw, step)?;
                        let info = VolumeInfo {
                            name: v.name.clone(),
                            dims: v.dims(),
                            spacing: v.spacing(),
                            origin: v.origin(),
                        };
                        let orientation = v.orientation();
                        Ok(VolumeStream { info, orientation, kind: Kind::Whole(Box::new(v)), progress: None })
                    }
                }
            }
        }
    }

    /// Object space, a time-varying source: step `step`'s samples of `range` and its whole block
    /// grid (blocks of `block` cells), in one pass over the step
    /// ([`VolumeStream::read_region_and_blocks`]). The step must have the grid of `first` (the
    /// step the bricks were split on), or it is refused with both.
    pub fn read_step_region(
        &self,
        raw: Option<&RawSpec>,
        step: usize,
        range: &VoxelRange,
        block: usize,
        first: &VolumeInfo,
    ) -> Result<StepRegion, VolumeError> {
        let stream = self.stream_step(raw, step)?;
        let info = stream.info();
        if info.dims != first.dims || info.spacing != first.spacing || info.origin != first.origin {
            return Err(VolumeError::Source(format!(
                "{self}: time step {step} ({}) has dims {:?}, spacing {:?}, origin {:?}, but the first \
                 step has {:?}, {:?}, {:?}: object space splits every step as the first",
                info.name, info.dims, info.spacing, info.origin, first.dims, first.spacing, first.origin
            )));
        }
        let (region, blocks) = stream.read_region_and_blocks(range, block)?;
        Ok(StepRegion { step, region, blocks })
    }
}

/// Object space, a time-varying source read step after step ([`VolumeSource::step_regions`]):
/// each step's region and block grid, as [`VolumeSource::read_step_region`] gives them, but a
/// 4-D NRRD's or NIfTI's steps come from one stream kept open (the crate's `StepFile`), so a
/// pass over the steps in order inflates a compressed file once, not once per step.
pub struct StepRegions {
    source: VolumeSource,
    raw: Option<RawSpec>,
    range: VoxelRange,
    block: usize,
    first: VolumeInfo,
    file: Option<crate::io::StepFile>,
}

impl VolumeSource {
    /// The reader of `range` and the block grid (blocks of `block` cells) of every step, each
    /// step's grid checked against `first` ([`StepRegions::read`]).
    pub fn step_regions(
        &self,
        raw: Option<&RawSpec>,
        range: VoxelRange,
        block: usize,
        first: VolumeInfo,
    ) -> Result<StepRegions, VolumeError> {
        let file = match self {
            // The brick's limit was checked when the bricks were split; mirrored files are
            // read a step at a time through `read_step_region`.
            VolumeSource::File(path) => {
                let none = crate::io::VolumeLimit::new(u64::MAX, "none for a brick's steps");
                crate::io::step_file(path, &none)?.filter(|f| f.steps > 1 && f.mirror.is_none())
            }
            _ => None,
        };
        Ok(StepRegions { source: self.clone(), raw: raw.cloned(), range, block, first, file })
    }
}

impl StepRegions {
    /// Step `step`'s region and whole block grid, in one pass over the step (one z-slice
    /// resident at a time besides the region).
    pub fn read(&mut self, step: usize) -> Result<StepRegion, VolumeError> {
        let Some(file) = self.file.as_mut() else {
            let (range, block) = (&self.range, self.block);
            return self.source.read_step_region(self.raw.as_ref(), step, range, block, &self.first);
        };
        let (dims, spacing, origin) = file.step_grid();
        let first = &self.first;
        if dims != first.dims || spacing != first.spacing || origin != first.origin {
            return Err(VolumeError::Source(format!(
                "{}: time step {step} has dims {dims:?}, spacing {spacing:?}, origin {origin:?}, but the first \
                 step has {:?}, {:?}, {:?}: object space splits every step as the first",
                self.source, first.dims, first.spacing, first.origin
            )));
        }
        let range = &self.range;
        if !range.fits(dims) {
            return Err(VolumeError::Invalid(format!(
                "{}: region {range:?} does not fit dims {dims:?}",
                first.name
            )));
        }
        let mut acc = BlockScan::new(dims, self.block);
        let nx = dims[0];
        let mut data = Vec::with_capacity(range.count());
        file.read_slices(step, &mut |k, slice| {
            acc.add_slice(k, slice);
            keep_region(range, nx, k, slice, &mut data);
        })?;
        let blocks = acc.finish(&first.name)?;
        let at = first.origin
            + first.spacing * DVec3::new(range.lo[0] as f64, range.lo[1] as f64, range.lo[2] as f64);
        let region = Volume::new(first.name.clone(), range.dims(), first.spacing, at, data)?;
        Ok(StepRegion { step, region, blocks })
    }

    /// How many times a compressed 4-D file's stream was opened (inflated from its start).
    pub fn inflations(&self) -> usize {
        self.file.as_ref().map_or(0, |f| f.inflations)
    }
}

/// Object space, a time-varying volume: one step's brick and halo, and the step's block grid
/// over the whole volume (empty-space skipping marches the whole box, so each node needs every
/// block's min/max of the step to march as the single render does).
#[derive(Debug)]
pub struct StepRegion {
    pub step: usize,
    pub region: Volume,
    pub blocks: BlockMinMax,
}

impl crate::steps::Resident for StepRegion {
    fn resident_bytes(&self) -> usize {
        self.region.resident_bytes()
            + self.region.name.capacity()
            + self.blocks.minmax.capacity() * std::mem::size_of::<[f32; 2]>()
            + std::mem::size_of::<StepRegion>()
    }
}

impl VolumeStream {
    fn dicom(series: crate::io::dicom::Series, path: &std::path::Path) -> VolumeStream {
        let info = VolumeInfo {
            name: path.display().to_string(),
            dims: series.dims,
            spacing: series.spacing,
            origin: series.origin,
        };
        let orientation = series.orientation;
        VolumeStream { info, orientation, kind: Kind::Dicom(Box::new(series)), progress: None }
    }

    /// The patient orientation the source gives (NRRD `space`, NIfTI qform/sform, DICOM
    /// ImageOrientationPatient), if any.
    pub fn orientation(&self) -> Option<crate::Orientation> {
        self.orientation
    }

    /// Reports every z-slice a pass has done to `f` (from the calling thread, in order; the last
    /// report of a pass has `done == total`).
    pub fn on_progress(mut self, f: impl Fn(Progress) + Send + Sync + 'static) -> VolumeStream {
        self.progress = Some(Box::new(f));
        self
    }

    fn report(&self, pass: Pass, done: usize, total: usize) {
        if let Some(f) = &self.progress {
            f(Progress { pass, done, total });
        }
    }

    pub fn info(&self) -> &VolumeInfo {
        &self.info
    }

    /// Whether regions are read without the whole volume being resident at any time.
    pub fn partial(&self) -> bool {
        !matches!(self.kind, Kind::Whole(_))
    }

    /// Per-block min/max of the whole volume (blocks of `block` cells, as [`BlockMinMax::new`]),
    /// reading one z-slice at a time. Refuses NaN/Inf voxels like a full read.
    pub fn block_minmax(&self, block: usize) -> Result<BlockMinMax, VolumeError> {
        let mut acc = BlockScan::new(self.info.dims, block);
        self.for_each_slice(Pass::Scan, &VoxelRange::whole(self.info.dims), &mut |k, slice| {
            acc.add_slice(k, slice)
        })?;
        acc.finish(&self.info.name)
    }

    /// The samples of `range` and the block min/max of the whole volume, in one pass over it
    /// (one z-slice resident at a time besides the region): what a time step of object space
    /// needs ([`VolumeSource::read_step_region`]). Reported as [`Pass::Scan`].
    pub fn read_region_and_blocks(
        &self,
        range: &VoxelRange,
        block: usize,
    ) -> Result<(Volume, BlockMinMax), VolumeError> {
        self.check_range(range)?;
        let mut acc = BlockScan::new(self.info.dims, block);
        let nx = self.info.dims[0];
        let mut data = Vec::with_capacity(range.count());
        self.for_each_slice(Pass::Scan, &VoxelRange::whole(self.info.dims), &mut |k, slice| {
            acc.add_slice(k, slice);
            keep_region(range, nx, k, slice, &mut data);
        })?;
        let blocks = acc.finish(&self.info.name)?;
        Ok((self.region_volume(range, data)?, blocks))
    }

    fn check_range(&self, range: &VoxelRange) -> Result<(), VolumeError> {
        if !range.fits(self.info.dims) {
            return Err(VolumeError::Invalid(format!(
                "{}: region {range:?} does not fit dims {:?}",
                self.info.name, self.info.dims
            )));
        }
        Ok(())
    }

    /// The region's samples as a volume at the world position of its first sample.
    fn region_volume(&self, range: &VoxelRange, data: Vec<f32>) -> Result<Volume, VolumeError> {
        let origin = self.info.origin
            + self.info.spacing * DVec3::new(range.lo[0] as f64, range.lo[1] as f64, range.lo[2] as f64);
        Volume::new(self.info.name.clone(), range.dims(), self.info.spacing, origin, data)
    }

    /// The samples of `range`, read without the rest (see the module's notes).
    pub fn read_region(&self, range: &VoxelRange) -> Result<Volume, VolumeError> {
        self.check_range(range)?;
        let slices = range.dims()[2];
        match &self.kind {
            Kind::Procedural(p, size) => {
                let v = p.generate_region(*size, range);
                self.report(Pass::Read, slices, slices);
                Ok(v)
            }
            Kind::Whole(v) => {
                let v = v.crop(range);
                self.report(Pass::Read, slices, slices);
                v
            }
            Kind::File(_) | Kind::Dicom(_) => {
                let [rx, ry, _] = range.dims();
                let mut data = Vec::with_capacity(range.count());
                let nx = self.info.dims[0];
                self.for_each_slice(Pass::Read, range, &mut |_, rows| {
                    for j in 0..ry {
                        let row = &rows[nx * j..nx * (j + 1)];
                        data.extend_from_slice(&row[range.lo[0]..range.lo[0] + rx]);
                    }
                })?;
                self.region_volume(range, data)
            }
        }
    }

    /// Calls `f(k, slice)` for every whole z-slice of the volume, in order, one resident at a
    /// time for the sources that read partially ([`VolumeStream::partial`]), reporting each as
    /// [`Pass::Read`].
    pub fn for_each_z_slice(&self, f: &mut dyn FnMut(usize, &[f32])) -> Result<(), VolumeError> {
        self.for_each_slice(Pass::Read, &VoxelRange::whole(self.info.dims), f)
    }

    /// A volume already in memory as a stream (read whole).
    pub fn of_volume(v: Volume) -> VolumeStream {
        let info =
            VolumeInfo { name: v.name.clone(), dims: v.dims(), spacing: v.spacing(), origin: v.origin() };
        VolumeStream { info, orientation: v.orientation(), kind: Kind::Whole(Box::new(v)), progress: None }
    }

    /// Calls `f(k, rows)` for every z-slice k of `range` in order, with the slice's rows of the
    /// y-range, whole along x (`nx * (hi.y - lo.y + 1)` values), reporting each as `pass`.
    fn for_each_slice(
        &self,
        pass: Pass,
        range: &VoxelRange,
        f: &mut dyn FnMut(usize, &[f32]),
    ) -> Result<(), VolumeError> {
        let total = range.dims()[2];
        let f = &mut |k: usize, rows: &[f32]| {
            f(k, rows);
            self.report(pass, k + 1 - range.lo[2], total);
        };
        let [nx, ny, _] = self.info.dims;
        let rows = range.hi[1] + 1 - range.lo[1];
        match &self.kind {
            Kind::Whole(v) => {
                let mut buf = Vec::with_capacity(nx * rows);
                for k in range.lo[2]..=range.hi[2] {
                    buf.clear();
                    let start = nx * (range.lo[1] + ny * k);
                    buf.extend_from_slice(&v.data()[start..start + nx * rows]);
                    f(k, &buf);
                }
                Ok(())
            }
            Kind::Procedural(p, size) => {
                for k in range.lo[2]..=range.hi[2] {
                    let r = VoxelRange { lo: [0, range.lo[1], k], hi: [nx - 1, range.hi[1], k] };
                    let v = p.generate_region(*size, &r);
                    f(k, v.data());
                }
                Ok(())
            }
            Kind::File(plan) => plan.for_each_slice(nx, ny, range, rows, f),
            Kind::Dicom(series) => {
                let mut slice = Vec::with_capacity(nx * ny);
                for k in range.lo[2]..=range.hi[2] {
                    slice.clear();
                    series.read_slice(k, &mut slice)?;
                    f(k, &slice[nx * range.lo[1]..nx * (range.lo[1] + rows)]);
                }
                Ok(())
            }
        }
    }
}

/// The block min/max of a volume accumulated z-slice by z-slice (whole slices, in order), and
/// its non-finite voxels (the first and the count).
pub(crate) struct BlockScan {
    dims: [usize; 3],
    block: usize,
    counts: [usize; 3],
    minmax: Vec<[f32; 2]>,
    bad: Option<(usize, [usize; 3])>,
}

impl BlockScan {
    pub(crate) fn new(dims: [usize; 3], block: usize) -> BlockScan {
        assert!(block >= 1);
        let cells = dims.map(|n| n.max(2) - 1);
        let counts = cells.map(|c| c.div_ceil(block));
        let minmax = vec![[f32::INFINITY, f32::NEG_INFINITY]; counts.iter().product()];
        BlockScan { dims, block, counts, minmax, bad: None }
    }

    /// The blocks whose closed sample range on axis `a` holds sample s (two at a shared face).
    fn blocks_of(&self, s: usize, a: usize) -> [Option<usize>; 2] {
        let (block, counts) = (self.block, self.counts);
        let b = (s / block).min(counts[a] - 1);
        let prev = (s.is_multiple_of(block) && s > 0).then(|| s / block - 1);
        [Some(b), prev.filter(|&p| p != b)]
    }

    /// Adds z-slice `k` (`nx * ny` samples).
    pub(crate) fn add_slice(&mut self, k: usize, slice: &[f32]) {
        let [nx, ny, _] = self.dims;
        let counts = self.counts;
        // Min/max of this slice per (bx, by) block column, shared edges in both.
        let mut col = vec![[f32::INFINITY, f32::NEG_INFINITY]; counts[0] * counts[1]];
        for j in 0..ny {
            let bys = self.blocks_of(j, 1);
            for i in 0..nx {
                let x = slice[i + nx * j];
                if !x.is_finite() {
                    let e = self.bad.get_or_insert((0, [i, j, k]));
                    e.0 += 1;
                    continue;
                }
                for by in bys.into_iter().flatten() {
                    for bx in self.blocks_of(i, 0).into_iter().flatten() {
                        let m = &mut col[bx + counts[0] * by];
                        m[0] = m[0].min(x);
                        m[1] = m[1].max(x);
                    }
                }
            }
        }
        for bz in self.blocks_of(k, 2).into_iter().flatten() {
            let layer = &mut self.minmax[counts[0] * counts[1] * bz..counts[0] * counts[1] * (bz + 1)];
            for (m, c) in layer.iter_mut().zip(&col) {
                m[0] = m[0].min(c[0]);
                m[1] = m[1].max(c[1]);
            }
        }
    }

    pub(crate) fn finish(self, name: &str) -> Result<BlockMinMax, VolumeError> {
        if let Some((count, [i, j, k])) = self.bad {
            return Err(VolumeError::NonFinite { path: PathBuf::from(name), count, i, j, k });
        }
        Ok(BlockMinMax { block: self.block, counts: self.counts, minmax: self.minmax })
    }
}

/// Appends the part of z-slice `k` (rows of `nx` values) that lies in `range` to `data`.
fn keep_region(range: &VoxelRange, nx: usize, k: usize, slice: &[f32], data: &mut Vec<f32>) {
    if (range.lo[2]..=range.hi[2]).contains(&k) {
        let [rx, ry, _] = range.dims();
        for j in range.lo[1]..range.lo[1] + ry {
            let row = &slice[nx * j..nx * (j + 1)];
            data.extend_from_slice(&row[range.lo[0]..range.lo[0] + rx]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::testutil::{encode, gzip};
    use crate::io::VoxelType;
    use crate::procedural::Procedural;

    fn check_same(region: &Volume, whole: &Volume, r: &VoxelRange) {
        let c = whole.crop(r).unwrap();
        assert_eq!(region.dims(), r.dims());
        assert_eq!(region.data(), c.data());
        assert!((region.origin() - c.origin()).length() < 1e-12, "{:?} {:?}", region.origin(), c.origin());
        assert_eq!(region.resident_bytes(), r.count() * 4);
    }

    fn blocks_equal(a: &BlockMinMax, b: &BlockMinMax) {
        assert_eq!(a.counts, b.counts);
        assert_eq!(a.minmax, b.minmax);
    }

    #[test]
    fn procedural_regions_and_blocks_equal_the_whole() {
        let src: VolumeSource = "procedural:torus:21".parse().unwrap();
        let whole = Procedural::Torus.generate(Some(21));
        let s = src.stream(None).unwrap();
        assert!(s.partial());
        let r = VoxelRange { lo: [3, 0, 7], hi: [20, 9, 15] };
        check_same(&s.read_region(&r).unwrap(), &whole, &r);
        blocks_equal(&s.block_minmax(4).unwrap(), &BlockMinMax::new(&whole, 4));
        blocks_equal(&s.block_minmax(8).unwrap(), &BlockMinMax::new(&whole, 8));
    }

    #[test]
    fn passes_report_every_slice_in_order_and_end_at_the_total() {
        use std::sync::{Arc, Mutex};
        let seen = Arc::new(Mutex::new(Vec::new()));
        let log = seen.clone();
        let src: VolumeSource = "procedural:torus:21".parse().unwrap();
        let s = src.stream(None).unwrap().on_progress(move |p| log.lock().unwrap().push(p));
        let nz = s.info().dims[2];
        s.block_minmax(4).unwrap();
        let r = VoxelRange { lo: [0, 0, 5], hi: [20, 9, 11] };
        s.read_region(&r).unwrap();
        let seen = seen.lock().unwrap();
        let scan: Vec<usize> = seen.iter().filter(|p| p.pass == Pass::Scan).map(|p| p.done).collect();
        assert_eq!(scan, (1..=nz).collect::<Vec<_>>());
        assert!(seen.iter().filter(|p| p.pass == Pass::Scan).all(|p| p.total == nz));
        // A procedural region is generated at once: one report, done == total == its slices.
        let read: Vec<Progress> = seen.iter().copied().filter(|p| p.pass == Pass::Read).collect();
        assert_eq!(read, vec![Progress { pass: Pass::Read, done: 7, total: 7 }]);
    }

    #[test]
    fn raw_and_nrrd_raw_and_gzip_regions_equal_the_whole() {
        let dims = [13usize, 9, 11];
        let n: usize = dims.iter().product();
        let values: Vec<f64> = (0..n).map(|i| ((i * 7919) % 251) as f64 - 100.0).collect();
        let bytes = encode(&values, VoxelType::I16, false);
        let dir = tempfile::tempdir().unwrap();
        let raw_path = dir.path().join("v.raw");
        let mut with_header = vec![7u8; 5];
        with_header.extend_from_slice(&bytes);
        std::fs::write(&raw_path, &with_header).unwrap();
        let spec = RawSpec {
            dims,
            voxel: VoxelType::I16,
            spacing: DVec3::new(1.0, 2.0, 0.5),
            big_endian: false,
            header_bytes: 5,
        };
        let header = |enc: &str| {
            format!(
                "NRRD0004\ntype: short\ndimension: 3\nsizes: 13 9 11\nendian: little\nencoding: {enc}\n\
                 space origin: (1,2,3)\nspacings: 1 2 0.5\n\n"
            )
        };
        let nrrd_raw = dir.path().join("v.nrrd");
        let mut f = header("raw").into_bytes();
        f.extend_from_slice(&bytes);
        std::fs::write(&nrrd_raw, f).unwrap();
        let nrrd_gz = dir.path().join("g.nrrd");
        let mut f = header("gzip").into_bytes();
        f.extend_from_slice(&gzip(&bytes));
        std::fs::write(&nrrd_gz, f).unwrap();
        let ranges = [
            VoxelRange { lo: [0, 0, 0], hi: [12, 8, 10] },
            VoxelRange { lo: [2, 3, 4], hi: [7, 8, 6] },
            VoxelRange { lo: [5, 0, 0], hi: [12, 4, 2] },
            VoxelRange { lo: [0, 8, 10], hi: [0, 8, 10] },
        ];
        for (path, raw) in [(&raw_path, Some(&spec)), (&nrrd_raw, None), (&nrrd_gz, None)] {
            let whole = crate::io::load(path, raw).unwrap();
            let s = VolumeSource::File(path.clone()).stream(raw).unwrap();
            assert!(s.partial(), "{}", path.display());
            assert_eq!(s.info().dims, dims);
            for r in &ranges {
                check_same(&s.read_region(r).unwrap(), &whole, r);
            }
            blocks_equal(&s.block_minmax(4).unwrap(), &BlockMinMax::new(&whole, 4));
            // A file region reports each of its slices as it is read.
            let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
            let log = seen.clone();
            let s = s.on_progress(move |p| log.lock().unwrap().push((p.pass, p.done, p.total)));
            s.read_region(&ranges[1]).unwrap();
            let want: Vec<_> = (1..=3).map(|d| (Pass::Read, d, 3)).collect();
            assert_eq!(*seen.lock().unwrap(), want, "{}", path.display());
        }
        // A truncated gzip stream is an error naming the file, not a panic.
        let mut f = header("gzip").into_bytes();
        let gz = gzip(&bytes);
        f.extend_from_slice(&gz[..gz.len() / 2]);
        std::fs::write(&nrrd_gz, f).unwrap();
        let s = VolumeSource::File(nrrd_gz.clone()).stream(None).unwrap();
        let e = s.block_minmax(4).unwrap_err().to_string();
        assert!(e.contains("g.nrrd"), "{e}");
    }

    #[test]
    fn nan_voxels_are_refused_by_the_streaming_pass() {
        let dims = [4usize, 4, 4];
        let mut values = vec![1.0f64; 64];
        values[4 + 16 * 2 + 3] = f64::NAN;
        let bytes = encode(&values, VoxelType::F32, false);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("n.raw");
        std::fs::write(&p, &bytes).unwrap();
        let spec =
            RawSpec { dims, voxel: VoxelType::F32, spacing: DVec3::ONE, big_endian: false, header_bytes: 0 };
        let s = VolumeSource::File(p).stream(Some(&spec)).unwrap();
        let e = s.block_minmax(2).unwrap_err();
        assert!(matches!(e, VolumeError::NonFinite { count: 1, i: 3, j: 1, k: 2, .. }), "{e}");
    }

    /// `n` steps of 9x7x6 short voxels, step k's voxel i = (i * 31 + 7 * k) % 97 - 40: as a glob
    /// of raw-encoded NRRD files, and as 4-D NRRD files (raw and gzip).
    fn step_sources(dir: &std::path::Path, n: usize) -> (Vec<VolumeSource>, Vec<Vec<f64>>) {
        let dims = [9usize, 7, 6];
        let count: usize = dims.iter().product();
        let steps: Vec<Vec<f64>> =
            (0..n).map(|k| (0..count).map(|i| ((i * 31 + 7 * k) % 97) as f64 - 40.0).collect()).collect();
        let header = |dimension: usize, enc: &str| {
            let sizes = if dimension == 3 { "9 7 6".to_string() } else { format!("9 7 6 {n}") };
            let spacings = if dimension == 3 { "1 2 0.5" } else { "1 2 0.5 nan" };
            format!(
                "NRRD0004\ntype: short\ndimension: {dimension}\nsizes: {sizes}\nendian: little\n\
                 encoding: {enc}\nspacings: {spacings}\n\n"
            )
        };
        std::fs::create_dir_all(dir.join("steps")).unwrap();
        let mut all = Vec::new();
        for (k, values) in steps.iter().enumerate() {
            let bytes = encode(values, VoxelType::I16, false);
            all.extend_from_slice(&bytes);
            let mut f = header(3, "raw").into_bytes();
            f.extend_from_slice(&bytes);
            std::fs::write(dir.join(format!("steps/step_{k:02}.nrrd")), f).unwrap();
        }
        let mut sources = vec![format!("{}/steps/step_*.nrrd", dir.display()).parse().unwrap()];
        for (name, enc, data) in [("four.nrrd", "raw", all.clone()), ("four_gz.nrrd", "gzip", gzip(&all))] {
            let mut f = header(4, enc).into_bytes();
            f.extend_from_slice(&data);
            std::fs::write(dir.join(name), f).unwrap();
            sources.push(VolumeSource::File(dir.join(name)));
        }
        (sources, steps)
    }

    #[test]
    fn a_time_steps_region_and_block_grid_equal_the_whole_steps() {
        let dir = tempfile::tempdir().unwrap();
        let (sources, steps) = step_sources(dir.path(), 3);
        let r = VoxelRange { lo: [2, 1, 3], hi: [7, 6, 5] };
        for src in &sources {
            assert_eq!(src.time_steps().unwrap(), 3, "{src}");
            let first = src.stream(None).unwrap().info().clone();
            assert_eq!(first.dims, [9, 7, 6], "{src}");
            for (k, values) in steps.iter().enumerate() {
                let whole = src.load_step(None, k).unwrap();
                assert_eq!(whole.data()[5], values[5] as f32, "{src} step {k}");
                let s = src.stream_step(None, k).unwrap();
                assert!(s.partial(), "{src}");
                check_same(&s.read_region(&r).unwrap(), &whole, &r);
                blocks_equal(&s.block_minmax(4).unwrap(), &BlockMinMax::new(&whole, 4));
                // One pass: the region and the step's whole block grid.
                let got = src.read_step_region(None, k, &r, 4, &first).unwrap();
                assert_eq!(got.step, k);
                check_same(&got.region, &whole, &r);
                blocks_equal(&got.blocks, &BlockMinMax::new(&whole, 4));
                use crate::steps::Resident;
                let own = got.region.name.len() + std::mem::size_of::<StepRegion>();
                assert_eq!(got.resident_bytes(), r.count() * 4 + got.blocks.minmax.len() * 8 + own);
            }
            let e = src.stream_step(None, 3).err().unwrap().to_string();
            assert!(e.contains("has no time step 3"), "{src}: {e}");
        }
        // A step whose grid is not the first's is refused, naming both.
        let other = dir.path().join("steps/step_01.nrrd");
        let text = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 9 7 5\nencoding: raw\n\n";
        std::fs::write(&other, [text.as_bytes(), &[0u8; 9 * 7 * 5]].concat()).unwrap();
        let first = sources[0].stream(None).unwrap().info().clone();
        let e = sources[0].read_step_region(None, 1, &r, 4, &first).unwrap_err().to_string();
        assert!(e.contains("time step 1") && e.contains("[9, 7, 5]") && e.contains("[9, 7, 6]"), "{e}");
        // Sources of one step have step 0 only.
        let torus: VolumeSource = "procedural:torus:21".parse().unwrap();
        assert!(torus.stream_step(None, 1).err().unwrap().to_string().contains("has no time step 1"));
    }
}
