//! Parts of a volume without the whole (object space, DESIGN.md "Distribution"): a node of an
//! object-space wall holds only its brick and halo. Two passes over a source, neither keeping the
//! whole volume:
//!
//! - [`VolumeStream::block_minmax`]: the per-block min/max of the whole volume (the occupancy grid
//!   the brick split balances on), read z-slice by z-slice: resident is one slice of voxels plus
//!   the block grid. It also checks the whole file (size, NaN/Inf) as a full read would.
//! - [`VolumeStream::read_region`]: the samples of a [`VoxelRange`] only.
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
    kind: Kind,
    progress: Option<ProgressFn>,
}

impl VolumeSource {
    /// Opens the source for partial reads: reads a file's header only (MetaImage, NIfTI and
    /// mirrored NRRD are read whole here; see the module's notes).
    pub fn stream(&self, raw: Option<&RawSpec>) -> Result<VolumeStream, VolumeError> {
        match self {
            VolumeSource::Procedural { kind, size } => {
                let dims = kind.dims(*size);
                let info = VolumeInfo {
                    name: format!("procedural:{}:{}", kind.name(), dims[0]),
                    dims,
                    spacing: DVec3::ONE,
                    origin: DVec3::ZERO,
                };
                Ok(VolumeStream { info, kind: Kind::Procedural(*kind, *size), progress: None })
            }
            VolumeSource::DicomSeries { path, series } => {
                Ok(VolumeStream::dicom(crate::io::dicom::Series::open(path, Some(series))?, path))
            }
            VolumeSource::Steps(_) => Err(time_series_refused(self)),
            VolumeSource::File(path) if crate::io::time_steps(path)? > 1 => Err(time_series_refused(self)),
            VolumeSource::File(path) if crate::io::dicom::is_dicom(path) => {
                Ok(VolumeStream::dicom(crate::io::dicom::Series::open(path, None)?, path))
            }
            VolumeSource::File(path) => match crate::io::plan(path, raw)? {
                Some((plan, spacing, origin)) => {
                    let info = VolumeInfo {
                        name: path.display().to_string(),
                        dims: plan.layout.dims,
                        spacing,
                        origin,
                    };
                    Ok(VolumeStream { info, kind: Kind::File(plan), progress: None })
                }
                None => {
                    let v = crate::io::load(path, raw)?;
                    let info = VolumeInfo {
                        name: v.name.clone(),
                        dims: v.dims(),
                        spacing: v.spacing(),
                        origin: v.origin(),
                    };
                    Ok(VolumeStream { info, kind: Kind::Whole(Box::new(v)), progress: None })
                }
            },
        }
    }
}

/// Object space reads one volume: time-varying sources are refused.
fn time_series_refused(source: &VolumeSource) -> VolumeError {
    VolumeError::Source(format!(
        "{source}: a time-varying volume cannot be split into bricks (object space); render it on a \
         screen-space wall or choose one step"
    ))
}

impl VolumeStream {
    fn dicom(series: crate::io::dicom::Series, path: &std::path::Path) -> VolumeStream {
        let info = VolumeInfo {
            name: path.display().to_string(),
            dims: series.dims,
            spacing: series.spacing,
            origin: series.origin,
        };
        VolumeStream { info, kind: Kind::Dicom(Box::new(series)), progress: None }
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
        assert!(block >= 1);
        let dims = self.info.dims;
        let cells = dims.map(|n| n.max(2) - 1);
        let counts = cells.map(|c| c.div_ceil(block));
        let mut minmax = vec![[f32::INFINITY, f32::NEG_INFINITY]; counts.iter().product()];
        // The blocks whose closed sample range on an axis holds sample s (two at a shared face).
        let blocks_of = |s: usize, a: usize| -> [Option<usize>; 2] {
            let b = (s / block).min(counts[a] - 1);
            let prev = (s.is_multiple_of(block) && s > 0).then(|| s / block - 1);
            [Some(b), prev.filter(|&p| p != b)]
        };
        let [nx, ny, _] = dims;
        let mut bad: Option<(usize, [usize; 3])> = None;
        self.for_each_slice(Pass::Scan, &VoxelRange::whole(dims), &mut |k, slice| {
            // Min/max of this slice per (bx, by) block column, shared edges in both.
            let mut col = vec![[f32::INFINITY, f32::NEG_INFINITY]; counts[0] * counts[1]];
            for j in 0..ny {
                let bys = blocks_of(j, 1);
                for i in 0..nx {
                    let x = slice[i + nx * j];
                    if !x.is_finite() {
                        let e = bad.get_or_insert((0, [i, j, k]));
                        e.0 += 1;
                        continue;
                    }
                    for by in bys.into_iter().flatten() {
                        for bx in blocks_of(i, 0).into_iter().flatten() {
                            let m = &mut col[bx + counts[0] * by];
                            m[0] = m[0].min(x);
                            m[1] = m[1].max(x);
                        }
                    }
                }
            }
            for bz in blocks_of(k, 2).into_iter().flatten() {
                let layer = &mut minmax[counts[0] * counts[1] * bz..counts[0] * counts[1] * (bz + 1)];
                for (m, c) in layer.iter_mut().zip(&col) {
                    m[0] = m[0].min(c[0]);
                    m[1] = m[1].max(c[1]);
                }
            }
        })?;
        if let Some((count, [i, j, k])) = bad {
            return Err(VolumeError::NonFinite { path: PathBuf::from(&self.info.name), count, i, j, k });
        }
        Ok(BlockMinMax { block, counts, minmax })
    }

    /// The samples of `range`, read without the rest (see the module's notes).
    pub fn read_region(&self, range: &VoxelRange) -> Result<Volume, VolumeError> {
        if !range.fits(self.info.dims) {
            return Err(VolumeError::Invalid(format!(
                "{}: region {range:?} does not fit dims {:?}",
                self.info.name, self.info.dims
            )));
        }
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
                let origin = self.info.origin
                    + self.info.spacing
                        * DVec3::new(range.lo[0] as f64, range.lo[1] as f64, range.lo[2] as f64);
                Volume::new(self.info.name.clone(), range.dims(), self.info.spacing, origin, data)
            }
        }
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
}
