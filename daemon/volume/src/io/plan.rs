//! The file plan of a partial read: where a file's voxels are (its layout, where they start,
//! how they are encoded) and the read of a region's slices from it, decoded in place.

use crate::{VolumeError, VoxelRange};
use std::io::{Seek, SeekFrom};
use std::path::PathBuf;

/// Where a file's voxels are, for reading parts of it (region reads, `crate::region`).
#[derive(Clone, Debug)]
pub(crate) struct FilePlan {
    /// The file the user named (messages, the volume's name).
    pub header: PathBuf,
    /// The file holding the voxels.
    pub data: PathBuf,
    pub layout: crate::io::Layout,
    /// Raw: the byte of the data file where voxel 0 starts (the size already checked).
    /// Compressed: where the compressed stream starts.
    pub start: u64,
    pub encoding: crate::io::Encoding,
    /// Compressed only: decoded bytes before voxel 0.
    pub decoded_skip: u64,
    /// More voxels follow the plan's in the data (the later time steps of a 4-D file), so a
    /// whole pass does not check that the stream ends with them.
    pub trailing: bool,
}

impl FilePlan {
    /// The plan of time step `step` of the `steps` a 4-D file stacks along z (the layout's z
    /// holds them all): its voxels alone, skipped to without reading the steps before them
    /// where the encoding allows (raw: by seeking; compressed: decoded and dropped).
    pub(crate) fn time_step(mut self, step: usize, steps: usize) -> FilePlan {
        if steps <= 1 {
            return self;
        }
        let [nx, ny, nzt] = self.layout.dims;
        let nz = nzt / steps;
        let skip = (nx * ny * nz * step) as u64 * self.layout.voxel.size() as u64;
        match self.encoding {
            crate::io::Encoding::Raw => self.start += skip,
            _ => self.decoded_skip += skip,
        }
        self.layout.dims[2] = nz;
        self.trailing = self.trailing || step + 1 < steps;
        self
    }

    fn files(&self) -> crate::io::Files<'_> {
        crate::io::Files { header: &self.header, data: &self.data }
    }

    pub(crate) fn for_each_slice(
        &self,
        nx: usize,
        ny: usize,
        range: &VoxelRange,
        rows: usize,
        f: &mut dyn FnMut(usize, &[f32]),
    ) -> Result<(), VolumeError> {
        use crate::io::Encoding;
        let files = self.files();
        let size = self.layout.voxel.size() as u64;
        let slice_bytes = (nx * ny) as u64 * size;
        let want_bytes = (nx * rows) as u64 * size;
        let mut bytes = vec![0u8; want_bytes as usize];
        let mut values: Vec<f32> = Vec::with_capacity(nx * rows);
        let (file, _) = crate::io::open(&self.data)?;
        let mut decode = |k: usize, bytes: &[u8], values: &mut Vec<f32>| {
            values.clear();
            crate::io::decode_into(bytes, self.layout.voxel, self.layout.big_endian, None, values);
            f(k, values);
        };
        match self.encoding {
            Encoding::Raw => {
                let mut file = file;
                for k in range.lo[2]..=range.hi[2] {
                    let at = self.start + k as u64 * slice_bytes + (range.lo[1] * nx) as u64 * size;
                    file.seek(SeekFrom::Start(at)).map_err(|e| files.io(e))?;
                    let n = crate::io::read_full(&mut file, &mut bytes).map_err(|e| files.io(e))?;
                    if n < bytes.len() {
                        return Err(files.format(format!(
                            "data is truncated: slice {k} ends after {n} of {} bytes",
                            bytes.len()
                        )));
                    }
                    decode(k, &bytes, &mut values);
                }
                Ok(())
            }
            enc => {
                let mut r = file;
                crate::io::skip_bytes(files, &mut r, Encoding::Raw, self.start)?;
                let mut dec = enc.decoder(r).map_err(|e| files.io(e))?;
                crate::io::skip_bytes(files, &mut *dec, enc, self.decoded_skip)?;
                let whole = range.lo[1] == 0 && rows == ny && range.hi[2] + 1 == self.layout.dims[2];
                // Decoded bytes before the region's first slice, and before/after its rows.
                crate::io::skip_bytes(files, &mut *dec, enc, range.lo[2] as u64 * slice_bytes)?;
                let before = (range.lo[1] * nx) as u64 * size;
                let after = slice_bytes - before - want_bytes;
                for k in range.lo[2]..=range.hi[2] {
                    crate::io::skip_bytes(files, &mut *dec, enc, before)?;
                    let n = crate::io::read_full(&mut *dec, &mut bytes).map_err(|e| files.io(e))?;
                    if n < bytes.len() {
                        return Err(
                            files.format(format!("data is truncated: the {enc:?} data ends in slice {k}"))
                        );
                    }
                    if k < range.hi[2] || whole {
                        crate::io::skip_bytes(files, &mut *dec, enc, after)?;
                    }
                    decode(k, &bytes, &mut values);
                }
                if whole && !self.trailing {
                    // A whole pass also checks that the stream ends where the voxels do.
                    let mut probe = [0u8; 1];
                    if crate::io::read_full(&mut *dec, &mut probe).map_err(|e| files.io(e))? > 0 {
                        return Err(files.format(format!(
                            "extra data: the {enc:?} data decompresses to more than the {} bytes {} needs",
                            self.layout.byte_len(),
                            self.layout.describe()
                        )));
                    }
                }
                Ok(())
            }
        }
    }
}

/// A 4-D file's time steps, read one at a time into buffers of exactly one step's voxels.
///
/// Raw data is read by seeking to the step. A compressed stream cannot seek, so reading step k
/// alone would inflate everything before it: a player asking for every step in turn would
/// inflate the file once per step (a 466-byte `.nii.gz` of 32,767 one-voxel steps kept a core
/// busy for minutes). Instead the inflating stream is kept open between reads and moves forward
/// only: step k+1 after step k continues where k ended, and the stream is opened again only when
/// an earlier step is asked for (playback wrapping to step 0, a jump back). One pass over the
/// steps in order inflates the file once, whatever the number of steps; resident besides the
/// step is the inflater's state (tens of KiB) and the open file.
pub(crate) struct StepFile {
    /// The whole file: the layout's z holds every step.
    pub plan: FilePlan,
    pub steps: usize,
    pub spacing: glam::DVec3,
    pub origin: glam::DVec3,
    pub scale: Option<crate::io::Scale>,
    /// Axes a NRRD's `space directions` mirror (x or y only: z is refused for 4-D files).
    pub mirror: Option<crate::io::AxisSteps>,
    open: Option<OpenStream>,
    /// How many times the compressed stream was opened (inflated from its start).
    pub inflations: usize,
}

struct OpenStream {
    dec: Box<dyn std::io::Read + Send>,
    /// The step the stream is at.
    next: usize,
}

impl StepFile {
    pub(crate) fn new(
        plan: FilePlan,
        steps: usize,
        spacing: glam::DVec3,
        origin: glam::DVec3,
        scale: Option<crate::io::Scale>,
        mirror: Option<crate::io::AxisSteps>,
    ) -> StepFile {
        StepFile { plan, steps: steps.max(1), spacing, origin, scale, mirror, open: None, inflations: 0 }
    }

    fn step_layout(&self) -> crate::io::Layout {
        let mut layout = self.plan.layout;
        layout.dims[2] /= self.steps;
        layout
    }

    /// Reads time step `step`: its voxels alone, in a buffer of exactly their size.
    pub(crate) fn read(&mut self, step: usize) -> Result<crate::Volume, VolumeError> {
        let header = self.plan.header.clone();
        let layout = self.step_layout();
        let mut data =
            Vec::with_capacity(layout.voxel_count().map_err(|e| crate::io::format_err(&header, e))?);
        self.read_slices(step, &mut |_, slice| data.extend_from_slice(slice))?;
        data.shrink_to_fit();
        let origin = match &self.mirror {
            Some(m) => m.apply(self.origin, layout.dims, &mut data),
            None => self.origin,
        };
        crate::io::make_volume(&header, layout.dims, self.spacing, origin, data)
    }

    /// The step's grid: (dims, spacing, origin), its axes as stored (a mirrored axis not undone).
    pub(crate) fn step_grid(&self) -> ([usize; 3], glam::DVec3, glam::DVec3) {
        (self.step_layout().dims, self.spacing, self.origin)
    }

    /// Calls `f(k, slice)` for every z-slice of step `step` in order (`nx * ny` values, rescaled,
    /// as stored: a mirrored axis is not undone), one slice resident at a time.
    pub(crate) fn read_slices(
        &mut self,
        step: usize,
        f: &mut dyn FnMut(usize, &[f32]),
    ) -> Result<(), VolumeError> {
        let (steps, header) = (self.steps, self.plan.header.clone());
        if step >= steps {
            return Err(crate::io::format_err(
                &header,
                format!("has no time step {step}: it holds {steps} (0 to {})", steps - 1),
            ));
        }
        let result = self.read_step(step, f);
        if result.is_err() {
            self.open = None;
        }
        result
    }

    fn read_step(&mut self, step: usize, f: &mut dyn FnMut(usize, &[f32])) -> Result<(), VolumeError> {
        use crate::io::{skip_bytes, Encoding};
        use std::io::Read;
        let layout = self.step_layout();
        let step_bytes = layout.byte_len();
        let (data, header) = (self.plan.data.clone(), self.plan.header.clone());
        let files = crate::io::Files { header: &header, data: &data };
        match self.plan.encoding {
            Encoding::Raw => {
                // The file's size was checked against all the steps when the plan was made.
                let (mut file, _) = crate::io::open(&data)?;
                file.seek(SeekFrom::Start(self.plan.start + step as u64 * step_bytes))
                    .map_err(|e| files.io(e))?;
                step_slices(files, &mut file.take(step_bytes), Encoding::Raw, &layout, self.scale, f)
            }
            enc => {
                if self.open.as_ref().is_none_or(|o| o.next > step) {
                    self.open = None;
                    let (mut file, _) = crate::io::open(&data)?;
                    skip_bytes(files, &mut file, Encoding::Raw, self.plan.start)?;
                    let mut dec = enc.decoder(file).map_err(|e| files.io(e))?;
                    skip_bytes(files, &mut *dec, enc, self.plan.decoded_skip)?;
                    self.inflations += 1;
                    self.open = Some(OpenStream { dec, next: 0 });
                }
                let Some(open) = self.open.as_mut() else { unreachable!("opened above") };
                skip_bytes(files, &mut *open.dec, enc, (step - open.next) as u64 * step_bytes)?;
                step_slices(files, &mut (&mut *open.dec).take(step_bytes), enc, &layout, self.scale, f)?;
                open.next = step + 1;
                if open.next == self.steps {
                    // The last step: the stream must end with it.
                    let mut probe = [0u8; 1];
                    let more = crate::io::read_full(&mut *open.dec, &mut probe)
                        .map_err(|e| files.read_error(enc, e))?;
                    self.open = None;
                    if more > 0 {
                        return Err(files.format(format!(
                            "extra data: the {} data decompresses to more than the {} bytes {} needs",
                            enc.name(),
                            self.plan.layout.byte_len(),
                            self.plan.layout.describe()
                        )));
                    }
                }
                Ok(())
            }
        }
    }
}

/// Reads the z-slices of `layout` from `r` (decoded from `enc`), one at a time, each checked
/// whole (a short one is "truncated"), and calls `f(k, slice)` for each.
fn step_slices(
    files: crate::io::Files,
    r: &mut dyn std::io::Read,
    enc: crate::io::Encoding,
    layout: &crate::io::Layout,
    scale: Option<crate::io::Scale>,
    f: &mut dyn FnMut(usize, &[f32]),
) -> Result<(), VolumeError> {
    use std::io::Read;
    let [nx, ny, nz] = layout.dims;
    let slice = crate::io::Layout { dims: [nx, ny, 1], ..*layout };
    for k in 0..nz {
        let values = crate::io::read_voxels(files, &mut r.take(slice.byte_len()), enc, 0, &slice, scale)?;
        f(k, &values);
    }
    Ok(())
}
