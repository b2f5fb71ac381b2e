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
