//! OME-Zarr (NGFF 0.4 on Zarr v2, NGFF 0.5 on Zarr v3, sharded or not) multiscale images,
//! read through `zarrs` and `ome_zarr_metadata`.
//!
//! A store is a folder (`*.ome.zarr`, or any folder with `zarr.json` or `.zattrs`) whose root
//! group holds `multiscales`; Isowall reads its first image. Its axes are up to five, in NGFF's
//! order: an optional `t` (time steps, [`OmeZarr::steps`]), an optional `c` of size 1, and three
//! space axes `z`, `y`, `x` (x fastest, as Isowall's volumes are). Each level's `scale` and
//! `translation` (then the image's own) place its samples in world space: voxel `(i, j, k)` of a
//! level sits at `translation + (i, j, k) * scale` on `x, y, z`.
//!
//! Until the brick cache streams levels on demand, a volume is read whole at one level: the finest
//! that fits the [`VolumeLimit`] ([`OmeZarr::finest_within`]); a coarser one is said in the log.
//!
//! What a hostile store can do is bounded ([`super::zarr_codecs`]): no metadata document over
//! [`MAX_METADATA_BYTES`], no chunk read larger than its shape allows, no chunk decoded past its
//! shape's bytes, no level read whole over [`MAX_VOXELS`]; errors name the store, the array and the chunk.
//!
//! Isowall's own keys live under `isowall` in the root group's attributes (ignored by other
//! readers): the patient axes of the grid (`patient_axes_lps`, three LPS unit vectors of +x, +y,
//! +z), which NGFF has no field for, and the per-brick min/max arrays [`super::ome_zarr_write`]
//! writes.

use super::zarr_codecs::{register_bounded_codecs, BoundedStore};
use super::{format_err, VolumeLimit, MAX_VOXELS};
use crate::brick_cache::{BrickKey, BrickLayout, BrickSource, DEFAULT_BRICK_CELLS};
use crate::orientation::{PatientAxes, PatientFrame};
use crate::{Volume, VolumeError};
use glam::DVec3;
use ome_zarr_metadata::AnyOmeFields;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::{Array, ArraySubset};
use zarrs::filesystem::FilesystemStore;
use zarrs::plugin::ExtensionName;

/// The largest metadata document (`zarr.json`, `.zarray`, `.zattrs`, `.zgroup`) read.
pub const MAX_METADATA_BYTES: u64 = 16 << 20;

/// The most samples a level of a store may have (2^50): a store's level 0 may be far larger
/// than what is read whole ([`MAX_VOXELS`]); only a level within that and the limit is read.
pub const MAX_LEVEL_VOXELS: u64 = 1 << 50;

/// The most samples one chunk (or shard) may hold: 2^27 (512 MiB of `float32`). A chunk is
/// decoded whole, so its shape, not the array's, sets what one read allocates.
pub const MAX_CHUNK_ELEMENTS: u64 = 1 << 27;

/// The key of Isowall's own attributes in the root group.
pub const ISOWALL_KEY: &str = "isowall";
/// The most bytes of one level's per-brick min/max read: two `f32` a brick, so 32M bricks, a level
/// of 2^43 samples (32 TB as `float32`) in bricks of 64^3.
pub const MAX_MINMAX_BYTES: u64 = 256 << 20;

type Store = BoundedStore<FilesystemStore>;

/// One level of the pyramid.
#[derive(Clone, Debug, PartialEq)]
pub struct Level {
    /// The array's path in the store (`0`, `1`, ... as Isowall writes them).
    pub path: String,
    /// Samples on x, y, z.
    pub dims: [usize; 3],
    pub spacing: DVec3,
    /// World position of sample (0, 0, 0).
    pub origin: DVec3,
    /// The chunk (or shard) shape on x, y, z.
    pub chunk: [usize; 3],
    /// The Zarr data type (`uint8`, `int16`, `float32`, ...).
    pub data_type: String,
}

impl Level {
    pub fn voxels(&self) -> u64 {
        self.dims.iter().map(|&n| n as u64).product()
    }
}

/// An opened OME-Zarr store: its levels, finest first.
pub struct OmeZarr {
    path: PathBuf,
    store: Arc<Store>,
    levels: Vec<Level>,
    /// The `t` axis' length (1 without one).
    steps: usize,
    /// Whether the arrays have a leading `t` and/or `c` axis (of the array's dimensions, how many
    /// come before z, y, x).
    leading: usize,
    has_t: bool,
    patient_axes: Option<PatientAxes>,
}

/// Whether `path` is a Zarr store: a folder holding `zarr.json` (v3) or `.zattrs`/`.zgroup`
/// (v2), or named `*.zarr`.
pub fn is_zarr(path: &Path) -> bool {
    let name = path.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    path.is_dir()
        && (name.ends_with(".zarr")
            || ["zarr.json", ".zattrs", ".zgroup"].iter().any(|f| path.join(f).is_file()))
}

fn err(path: &Path, what: impl Into<String>) -> VolumeError {
    format_err(path, what)
}

fn store(path: &Path, max_read: u64) -> Result<Arc<Store>, VolumeError> {
    let fs = FilesystemStore::new(path).map_err(|e| err(path, format!("not a readable Zarr store: {e}")))?;
    Ok(Arc::new(BoundedStore::new(fs, max_read)))
}

/// A coordinate transform list (`coordinateTransformations`, JSON) as (scale, translation) on the
/// axes, in the list's order. Read from the JSON as `f64`: the metadata crate keeps `f32`, which
/// would move a sample 100 mm from the origin by up to 4 µm.
fn transforms(
    path: &Path,
    what: &str,
    list: Option<&serde_json::Value>,
    ndim: usize,
) -> Result<(Vec<f64>, Vec<f64>), VolumeError> {
    let mut scale = vec![1.0; ndim];
    let mut translation = vec![0.0; ndim];
    let numbers = |t: &serde_json::Value, key: &str| -> Option<Vec<f64>> {
        let a = t.get(key)?.as_array()?;
        let v: Option<Vec<f64>> = a.iter().map(serde_json::Value::as_f64).collect();
        v.filter(|v| v.len() == ndim)
    };
    for t in list.and_then(serde_json::Value::as_array).map(Vec::as_slice).unwrap_or(&[]) {
        let kind = t.get("type").and_then(serde_json::Value::as_str).unwrap_or("");
        match (kind, numbers(t, kind)) {
            ("identity", _) => {}
            ("scale", Some(s)) => {
                for a in 0..ndim {
                    scale[a] *= s[a];
                    translation[a] *= s[a];
                }
            }
            ("translation", Some(s)) => {
                for a in 0..ndim {
                    translation[a] += s[a];
                }
            }
            _ => {
                return Err(err(
                    path,
                    format!("{what}: coordinate transform {t} is not a scale or translation of {ndim} numbers (a path to binary data is not read)"),
                ))
            }
        }
    }
    Ok((scale, translation))
}

impl OmeZarr {
    /// Opens a store's metadata (and no voxel).
    pub fn open(path: &Path) -> Result<OmeZarr, VolumeError> {
        register_bounded_codecs();
        if !path.is_dir() {
            return Err(err(path, "an OME-Zarr store is a folder"));
        }
        let meta = store(path, MAX_METADATA_BYTES)?;
        let group = zarrs::group::Group::open(meta.clone(), "/")
            .map_err(|e| err(path, format!("the root group does not open: {e}")))?;
        let attrs = serde_json::Value::Object(group.attributes().clone());
        let fields: AnyOmeFields = serde_json::from_value(attrs.clone()).map_err(|e| {
            err(path, format!("the root group's attributes are not OME-Zarr 0.4 or 0.5 metadata: {e}"))
        })?;
        let image = match fields {
            AnyOmeFields::V0_4(a) => a.multiscales.and_then(|m| m.into_iter().next()).map(Into::into),
            AnyOmeFields::V0_5(a) => a.multiscales.and_then(|m| m.into_iter().next()),
        };
        let image: ome_zarr_metadata::v0_5::MultiscaleImage =
            image.ok_or_else(|| err(path, "the root group has no `multiscales` image"))?;
        let names: Vec<String> = image.axes.iter().map(|a| a.name.to_ascii_lowercase()).collect();
        let ndim = names.len();
        let space_at =
            ndim.checked_sub(3).filter(|_| names[ndim - 3..] == ["z", "y", "x"]).ok_or_else(|| {
                err(path, format!("axes {names:?}: Isowall reads images whose last three axes are z, y, x"))
            })?;
        let leading = &names[..space_at];
        if !leading.iter().all(|n| n == "t" || n == "c") || leading.iter().filter(|n| *n == "t").count() > 1 {
            return Err(err(
                path,
                format!("axes {names:?}: only a `t` and a `c` axis may come before z, y, x"),
            ));
        }
        let has_t = leading.first().is_some_and(|n| n == "t");
        // The image's JSON, for its numbers as f64: `ome.multiscales[0]` (0.5) or `multiscales[0]` (0.4).
        let image_json = attrs.get("ome").unwrap_or(&attrs).get("multiscales").and_then(|m| m.get(0));
        let json_of = |key: &str| image_json.and_then(|i| i.get(key));
        let (image_scale, image_translation) =
            transforms(path, "the image", json_of("coordinateTransformations"), ndim)?;
        if image.datasets.is_empty() {
            return Err(err(path, "the image lists no datasets (levels)"));
        }
        let mut levels = Vec::with_capacity(image.datasets.len());
        let mut steps = 1;
        let mut max_chunk_bytes = 0u64;
        for (index, d) in image.datasets.iter().enumerate() {
            let what = format!("level `{}`", d.path);
            // A level lives inside the store: a path of names, never `..`, `.` or absolute.
            if d.path.is_empty()
                || d.path.starts_with('/')
                || d.path.split('/').any(|c| c.is_empty() || c == "." || c == "..")
            {
                return Err(err(
                    path,
                    format!("{what}: a dataset's path must name a folder inside the store"),
                ));
            }
            let array = Array::open(meta.clone(), &format!("/{}", d.path))
                .map_err(|e| err(path, format!("array `{}` does not open: {e}", d.path)))?;
            let shape = array.shape().to_vec();
            if shape.len() != ndim {
                return Err(err(
                    path,
                    format!("array `{}` has {} dimensions, the axes say {ndim}", d.path, shape.len()),
                ));
            }
            for (a, n) in leading.iter().enumerate() {
                if n == "c" && shape[a] != 1 {
                    return Err(err(
                        path,
                        format!(
                        "array `{}`: {} channels; Isowall renders one scalar (write one channel per store)",
                        d.path, shape[a]
                    ),
                    ));
                }
            }
            if has_t {
                steps = usize::try_from(shape[0]).unwrap_or(usize::MAX);
            }
            let dims = [shape[ndim - 1], shape[ndim - 2], shape[ndim - 3]];
            let voxels = dims.iter().try_fold(1u64, |a, &n| a.checked_mul(n)).unwrap_or(u64::MAX);
            if dims.contains(&0) || voxels > MAX_LEVEL_VOXELS {
                return Err(err(
                    path,
                    format!(
                        "array `{}`: {}x{}x{} samples, outside 1..={MAX_LEVEL_VOXELS} voxels",
                        d.path, dims[0], dims[1], dims[2]
                    ),
                ));
            }
            let data_type = array.data_type().name_v3().map(|n| n.to_string()).unwrap_or_default();
            let size = array.data_type().fixed_size().ok_or_else(|| {
                err(path, format!("array `{}`: data type {} has no fixed size", d.path, array.data_type()))
            })?;
            let chunk = array
                .chunk_shape(&vec![0; ndim])
                .map_err(|e| err(path, format!("array `{}`: no regular chunk grid: {e}", d.path)))?;
            let chunk_elems =
                chunk.iter().map(|n| n.get()).try_fold(1u64, |a, n| a.checked_mul(n)).unwrap_or(u64::MAX);
            if chunk_elems > MAX_CHUNK_ELEMENTS {
                return Err(err(path, format!(
                    "array `{}`: a chunk of {chunk_elems} samples is over the {MAX_CHUNK_ELEMENTS} Isowall decodes at once",
                    d.path
                )));
            }
            max_chunk_bytes = max_chunk_bytes.max(chunk_elems.saturating_mul(size as u64));
            let chunk = [chunk[ndim - 1].get(), chunk[ndim - 2].get(), chunk[ndim - 3].get()];
            let list = json_of("datasets")
                .and_then(|ds| ds.get(index))
                .and_then(|d| d.get("coordinateTransformations"));
            let (s, t) = transforms(path, &what, list, ndim)?;
            let at = |a: usize| (s[a] * image_scale[a], t[a] * image_scale[a] + image_translation[a]);
            let (sx, tx) = at(ndim - 1);
            let (sy, ty) = at(ndim - 2);
            let (sz, tz) = at(ndim - 3);
            let spacing = DVec3::new(sx, sy, sz);
            let origin = DVec3::new(tx, ty, tz);
            if !(spacing.is_finite() && spacing.min_element() > 0.0 && origin.is_finite()) {
                return Err(err(
                    path,
                    format!("{what}: scale {spacing:?} must be finite and positive, translation finite"),
                ));
            }
            let dims = dims.map(|n| n as usize);
            crate::check_geometry(&format!("{} {what}", path.display()), dims, spacing, origin)?;
            levels.push(Level {
                path: d.path.clone(),
                dims,
                spacing,
                origin,
                chunk: chunk.map(|n| usize::try_from(n).unwrap_or(usize::MAX)),
                data_type,
            });
        }
        // The largest read a chunk may need: its decoded bytes, with room for a compressor that
        // expands incompressible data (deflate and zstd add well under 1%) and a shard's index.
        let max_read = max_chunk_bytes.saturating_add(max_chunk_bytes / 64).saturating_add(1 << 20);
        let patient_axes = attrs
            .get(ISOWALL_KEY)
            .and_then(|i| i.get("patient_axes_lps"))
            .map(|v| {
                let cols: Option<Vec<DVec3>> = v.as_array().filter(|a| a.len() == 3).map(|a| {
                    a.iter()
                        .filter_map(|c| {
                            let c = c.as_array()?;
                            if c.len() == 3 {
                                Some(DVec3::new(c[0].as_f64()?, c[1].as_f64()?, c[2].as_f64()?))
                            } else {
                                None
                            }
                        })
                        .collect()
                });
                cols.filter(|c| c.len() == 3)
                    .and_then(|c| PatientAxes::new([c[0], c[1], c[2]], PatientFrame::Lps))
                    .ok_or_else(|| {
                        err(
                            path,
                            format!(
                                "`{ISOWALL_KEY}.patient_axes_lps` is not three orthogonal 3-vectors: {v}"
                            ),
                        )
                    })
            })
            .transpose()?;
        Ok(OmeZarr {
            path: path.to_path_buf(),
            store: store(path, max_read)?,
            levels,
            steps,
            leading: space_at,
            has_t,
            patient_axes,
        })
    }

    /// The levels, finest (level 0) first.
    pub fn levels(&self) -> &[Level] {
        &self.levels
    }

    /// Time steps: the `t` axis' length, 1 without one.
    pub fn steps(&self) -> usize {
        self.steps
    }

    pub fn patient_axes(&self) -> Option<PatientAxes> {
        self.patient_axes
    }

    /// The finest level whose voxels fit `limit` (as `f32`), if any.
    pub fn finest_within(&self, limit: &VolumeLimit) -> Option<usize> {
        self.levels.iter().position(|l| l.voxels() <= MAX_VOXELS && limit.check(l.voxels(), "").is_ok())
    }

    /// Why no level is read within `limit` (where [`OmeZarr::finest_within`] finds none).
    pub fn none_within(&self, limit: &VolumeLimit) -> VolumeError {
        let l = &self.levels[self.levels.len() - 1];
        let what =
            format!("even its coarsest level `{}` ({}x{}x{})", l.path, l.dims[0], l.dims[1], l.dims[2]);
        let why = match limit.check(l.voxels(), &what) {
            Err(e) => e,
            Ok(()) => format!("{what} is over the {MAX_VOXELS} voxels read whole"),
        };
        err(&self.path, why)
    }

    /// Reads time step `step` of level `level` whole, within `limit`.
    pub fn read_level(&self, level: usize, step: usize, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
        let l = self.levels.get(level).ok_or_else(|| {
            err(&self.path, format!("level {level} does not exist (the store has {})", self.levels.len()))
        })?;
        if step >= self.steps {
            return Err(err(
                &self.path,
                format!("time step {step} does not exist (the store has {})", self.steps),
            ));
        }
        let what = format!("level `{}` ({}x{}x{})", l.path, l.dims[0], l.dims[1], l.dims[2]);
        if l.voxels() > MAX_VOXELS {
            return Err(err(&self.path, format!("{what} is over the {MAX_VOXELS} voxels read whole")));
        }
        limit.check(l.voxels(), &what).map_err(|e| err(&self.path, e))?;
        let data = self.read_region(level, step, [0; 3], l.dims)?;
        let name = format!("{}", self.path.display());
        let v = Volume::new(name, l.dims, l.spacing, l.origin, data)?;
        let orientation = self.patient_axes.and_then(|p| p.orientation());
        Ok(v.with_orientation(orientation).with_patient_axes(self.patient_axes))
    }

    /// The samples `origin .. origin + size` (x, y, z; inside the level) of time step `step` of
    /// level `level`, x fastest, as `f32`. Only the chunks the region touches are read.
    pub fn read_region(
        &self,
        level: usize,
        step: usize,
        origin: [usize; 3],
        size: [usize; 3],
    ) -> Result<Vec<f32>, VolumeError> {
        let l = &self.levels[level];
        if (0..3).any(|a| size[a] == 0 || origin[a] + size[a] > l.dims[a]) || step >= self.steps {
            return Err(err(
                &self.path,
                format!("array `{}`: region {origin:?} + {size:?} of step {step} lies outside it", l.path),
            ));
        }
        let array = Array::open(self.store.clone(), &format!("/{}", l.path))
            .map_err(|e| err(&self.path, format!("array `{}` does not open: {e}", l.path)))?;
        let mut ranges = Vec::with_capacity(self.leading + 3);
        for a in 0..self.leading {
            let at = if a == 0 && self.has_t { step as u64 } else { 0 };
            ranges.push(at..at + 1);
        }
        for a in [2, 1, 0] {
            ranges.push(origin[a] as u64..(origin[a] + size[a]) as u64);
        }
        let subset = ArraySubset::new_with_ranges(&ranges);
        let failed = |e: zarrs::array::ArrayError| {
            err(&self.path, format!("array `{}` ({}) at {origin:?}: {e}", l.path, l.data_type))
        };
        macro_rules! read_as {
            ($t:ty) => {
                array
                    .retrieve_array_subset::<Vec<$t>>(&subset)
                    .map_err(failed)?
                    .into_iter()
                    .map(|v| v as f32)
                    .collect()
            };
        }
        let data: Vec<f32> = match l.data_type.as_str() {
            "uint8" => read_as!(u8),
            "int8" => read_as!(i8),
            "uint16" => read_as!(u16),
            "int16" => read_as!(i16),
            "uint32" => read_as!(u32),
            "int32" => read_as!(i32),
            "float32" => read_as!(f32),
            "float64" => read_as!(f64),
            other => {
                return Err(err(
                    &self.path,
                    format!(
                    "array `{}`: data type {other} is not read (uint8/16/32, int8/16/32, float32, float64)",
                    l.path
                ),
                ))
            }
        };
        if let Some(i) = data.iter().position(|v| !v.is_finite()) {
            return Err(err(
                &self.path,
                format!("array `{}`: a non-finite sample in the region at {origin:?} (index {i})", l.path),
            ));
        }
        Ok(data)
    }

    /// The store as a source of cache bricks ([`crate::brick_cache`]) for time step `step`: bricks
    /// of the per-brick min/max `isowalld convert` wrote (its chunks), whose ranges it reads here
    /// (small: two numbers a brick); for another program's store, bricks of
    /// [`DEFAULT_BRICK_CELLS`] cells with ranges unknown until read.
    pub fn into_bricks(self, step: usize) -> Result<ZarrBricks, VolumeError> {
        if step >= self.steps {
            return Err(err(
                &self.path,
                format!("time step {step} does not exist (the store has {})", self.steps),
            ));
        }
        let geometry: Vec<_> = self.levels.iter().map(|l| (l.dims, l.spacing, l.origin)).collect();
        let written = self.minmax_brick().filter(|c| c.is_power_of_two() && (2..=256).contains(c));
        let cells = written.unwrap_or(DEFAULT_BRICK_CELLS);
        let layout = BrickLayout::new(cells, &geometry).map_err(|e| err(&self.path, e))?;
        let ranges = (0..layout.levels.len())
            .map(|l| match written {
                Some(_) => self.read_minmax(l, &layout),
                None => Ok(None),
            })
            .collect::<Result<Vec<_>, _>>()?;
        let name = self.path.display().to_string();
        Ok(ZarrBricks { store: self, step, layout, ranges, name })
    }

    /// The brick of the `isowall.minmax` arrays, where the store has them.
    fn minmax_brick(&self) -> Option<usize> {
        let meta = store(&self.path, MAX_METADATA_BYTES).ok()?;
        let group = zarrs::group::Group::open(meta, "/").ok()?;
        let c = group.attributes().get(ISOWALL_KEY)?.get("minmax")?.get("brick")?.as_u64()?;
        usize::try_from(c).ok()
    }

    /// Level `l`'s per-brick min/max (`isowall_minmax/<l>`), checked against `layout`'s brick
    /// counts; `None` where the array is missing.
    fn read_minmax(&self, l: usize, layout: &BrickLayout) -> Result<Option<Vec<[f32; 2]>>, VolumeError> {
        let path = format!("isowall_minmax/{l}");
        let Ok(array) = Array::open(self.store.clone(), &format!("/{path}")) else {
            return Ok(None);
        };
        let c = layout.levels[l].counts;
        let bytes = c.iter().try_fold(8u64, |a, &n| a.checked_mul(n as u64)).unwrap_or(u64::MAX);
        if bytes > MAX_MINMAX_BYTES {
            return Err(err(
                &self.path,
                format!(
                    "array `{path}`: {bytes} bytes of per-brick min/max, over the {MAX_MINMAX_BYTES} read"
                ),
            ));
        }
        let want = vec![c[2] as u64, c[1] as u64, c[0] as u64, 2];
        if array.shape() != want.as_slice() {
            return Err(err(
                &self.path,
                format!("array `{path}`: shape {:?}, the level's bricks need {want:?}", array.shape()),
            ));
        }
        let subset = ArraySubset::new_with_shape(want);
        let flat = array
            .retrieve_array_subset::<Vec<f32>>(&subset)
            .map_err(|e| err(&self.path, format!("array `{path}`: {e}")))?;
        let pairs: Vec<[f32; 2]> = flat.chunks_exact(2).map(|p| [p[0], p[1]]).collect();
        if pairs.iter().any(|p| !(p[0].is_finite() && p[1].is_finite() && p[0] <= p[1])) {
            return Err(err(
                &self.path,
                format!("array `{path}`: a brick's min/max is not finite min <= max"),
            ));
        }
        Ok(Some(pairs))
    }
}

/// An OME-Zarr store's time step as a source of cache bricks ([`OmeZarr::into_bricks`]).
pub struct ZarrBricks {
    store: OmeZarr,
    step: usize,
    layout: BrickLayout,
    ranges: Vec<Option<Vec<[f32; 2]>>>,
    name: String,
}

impl ZarrBricks {
    pub fn store(&self) -> &OmeZarr {
        &self.store
    }
}

impl BrickSource for ZarrBricks {
    fn layout(&self) -> &BrickLayout {
        &self.layout
    }
    fn ranges(&self, l: usize) -> Option<&[[f32; 2]]> {
        self.ranges[l].as_deref()
    }
    fn read_brick(&self, key: BrickKey) -> Result<Vec<f32>, VolumeError> {
        let l = key.level as usize;
        let dims = self.layout.levels[l].dims;
        let origin = key.brick.map(|b| b as usize * self.layout.cells);
        let size: [usize; 3] = std::array::from_fn(|a| (self.layout.samples()).min(dims[a] - origin[a]));
        let region = self.store.read_region(l, self.step, origin, size)?;
        // The region as a level of its own, cut as a brick at its origin (the far edges repeated).
        let local = BrickLayout::new(self.layout.cells, &[(size, glam::DVec3::ONE, glam::DVec3::ZERO)])
            .map_err(|e| err(&self.store.path, e))?;
        Ok(local.cut(BrickKey { level: 0, brick: [0; 3] }, &region))
    }
    fn name(&self) -> &str {
        &self.name
    }
}

/// Reads step `step` of a store at the finest level within `limit` (a coarser one is logged).
pub fn read(path: &Path, step: usize, limit: &VolumeLimit) -> Result<Volume, VolumeError> {
    let store = OmeZarr::open(path)?;
    let Some(level) = store.finest_within(limit) else {
        return Err(store.none_within(limit));
    };
    if level > 0 {
        let (l, l0) = (&store.levels[level], &store.levels[0]);
        tracing::warn!(
            "{}: level 0 ({}x{}x{}) is over {} bytes ({}); reading level {level} ({}x{}x{}, spacing {:.4} {:.4} {:.4})",
            path.display(),
            l0.dims[0], l0.dims[1], l0.dims[2],
            limit.bytes,
            limit.source,
            l.dims[0], l.dims[1], l.dims[2],
            l.spacing.x, l.spacing.y, l.spacing.z
        );
    }
    store.read_level(level, step, limit)
}
