//! `isowalld convert IN OUT.ome.zarr`: any volume Isowall reads, written as an OME-Zarr pyramid
//! (NGFF 0.5 on Zarr v3) that Isowall and other viewers (napari, neuroglancer, Fiji) open. The
//! levels, chunks, placement and Isowall's own keys are `isowall_volume::io::ome_zarr_write`'s.

use crate::args;
use anyhow::{Context, Result};
use clap::Args;
use isowall_volume::io::ome_zarr_write::{self, PyramidOptions};
use std::path::PathBuf;

#[derive(Args, Debug)]
#[command(after_help = "The input is read one z-slice at a time and written as it comes: level 0 \
is the volume, each next level the 2x2x2 mean of the one before, until a level fits one chunk. \
Memory holds a chunk's depth of slices of each level (about chunk x NX x NY x 4.6 bytes), so a \
volume larger than memory converts from raw files, NRRD (raw or gzip), DICOM series and \
procedural volumes; MetaImage, NIfTI, mirrored NRRD and OME-Zarr are read whole first (as \
float32, within 2 GiB), and --iso reads the input whole again (within --max-volume-bytes). The \
store keeps the input's patient orientation, and per-brick min/max of every level \
(isowall_minmax/<level>), which other readers ignore. Nothing is overwritten: OUT must not \
exist, or be an empty folder.")]
pub struct ConvertArgs {
    /// The volume: a file (.nrrd .nhdr .mhd .mha .nii .nii.gz, a DICOM folder or one file of the
    /// series, an OME-Zarr store, or raw with --dims/--type/--spacing) or procedural:NAME[:N]
    #[arg(value_name = "IN")]
    pub input: String,
    /// The store to write, a folder (e.g. ct.ome.zarr)
    #[arg(value_name = "OUT")]
    pub output: PathBuf,
    /// Samples per chunk side (a brick of the pyramid)
    #[arg(long, value_name = "N", default_value_t = 64, value_parser = clap::value_parser!(u16).range(8..=512))]
    pub chunk: u16,
    /// zstd's compression level (1 fast .. 19 small)
    #[arg(long, value_name = "L", default_value_t = 3, value_parser = clap::value_parser!(i32).range(1..=19))]
    pub zstd_level: i32,
    /// Also measure what the pyramid's first coarse level does to the surface at this iso value:
    /// the share of level 0's surface samples its field puts on the other side (and the same for
    /// a level of every other sample, the rule not used)
    #[arg(long, value_name = "V", allow_negative_numbers = true)]
    pub iso: Option<f32>,
    #[command(flatten)]
    pub source: args::VolumeInputArgs,
}

pub fn run(a: &ConvertArgs) -> Result<()> {
    let (source, raw) = a.source.source(&a.input)?;
    let stream =
        source.stream_step(raw.as_ref(), a.source.step).with_context(|| format!("cannot read {source}"))?;
    let orientation = stream.orientation();
    let opts = PyramidOptions { chunk: usize::from(a.chunk), zstd_level: a.zstd_level };
    let mut progress: Option<crate::progress::Counted> = None;
    let what = a.output.display().to_string();
    let summary = ome_zarr_write::write_stream(&stream, None, &a.output, &opts, &mut |done, total| {
        progress
            .get_or_insert_with(|| {
                crate::progress::Counted::of("isowalld convert", "chunk", total as u64, &what)
            })
            .done_of(done as u64);
    });
    drop(progress);
    let summary = summary.with_context(|| format!("cannot convert {source}"))?;
    let levels: Vec<String> = summary.levels.iter().map(|d| format!("{}x{}x{}", d[0], d[1], d[2])).collect();
    println!(
        "converted {source} to {}: {} level{} ({}), {} chunks of {}^3, orientation {}",
        a.output.display(),
        levels.len(),
        if levels.len() == 1 { "" } else { "s" },
        levels.join(", "),
        summary.chunks,
        a.chunk,
        orientation.map_or_else(|| "none given".to_string(), |o| o.code())
    );
    if let Some(iso) = a.iso {
        let (_, volume) = a.source.read(&a.input)?;
        let (lo, hi) = volume.value_range();
        isowall_volume::check_iso(f64::from(iso), (f64::from(lo), f64::from(hi))).context("--iso")?;
        let (mean, surface) =
            ome_zarr_write::surface_disagreement(&volume, &ome_zarr_write::mean_level(&volume), iso);
        let (every, _) =
            ome_zarr_write::surface_disagreement(&volume, &ome_zarr_write::subsampled_level(&volume), iso);
        println!(
            "iso {iso}: level 1 puts {:.2}% of level 0's {surface} surface samples on the other side (2x2x2 mean; \
             every other sample would put {:.2}%)",
            mean * 100.0,
            every * 100.0
        );
    }
    Ok(())
}
