//! `isowalld info VOLUME`: what a volume is and which iso values show its surfaces, before a
//! render or a wall config: its format, grid, patient orientation, value range, percentiles, a
//! histogram, and suggested iso values with how each was found (Otsu's thresholds of the
//! histogram, `isowall_volume::value_stats`). The volume is read whole, within the same limit as
//! `render` (`--max-volume-bytes`); an OME-Zarr store only by its metadata, its per-brick min/max
//! and its coarsest level (a store may be larger than memory).

use crate::args;
use anyhow::{Context, Result};
use clap::Args;
use isowall_volume::brick_cache::BrickSource;
use isowall_volume::io::ome_zarr::{is_zarr, OmeZarr};
use isowall_volume::value_stats::ValueStats;
use isowall_volume::{PatientDir, VolumeSource};

#[derive(Args, Debug)]
pub struct InfoArgs {
    /// The volume: a file (.nrrd .nhdr .mhd .mha .nii .nii.gz, a DICOM folder or one file of the
    /// series, an OME-Zarr store, or raw with --dims/--type/--spacing) or procedural:NAME[:N]
    #[arg(value_name = "VOLUME")]
    pub volume: String,
    #[command(flatten)]
    pub input: args::VolumeInputArgs,
    /// Bars of the histogram
    #[arg(long, value_name = "N", default_value_t = 16, value_parser = clap::value_parser!(u16).range(1..=256))]
    pub bars: u16,
}

impl InfoArgs {}

fn direction_name(d: PatientDir) -> &'static str {
    match d {
        PatientDir::Left => "left",
        PatientDir::Right => "right",
        PatientDir::Anterior => "anterior",
        PatientDir::Posterior => "posterior",
        PatientDir::Superior => "superior",
        PatientDir::Inferior => "inferior",
    }
}

pub fn run(a: &InfoArgs) -> Result<()> {
    let (source, _) = a.input.source(&a.volume)?;
    let store = match &source {
        VolumeSource::File(p) if is_zarr(p) => Some(OmeZarr::open(p)?),
        _ => None,
    };
    // A store: its coarsest level for the values, level 0 for the grid.
    let volume = match &store {
        Some(s) => {
            let coarsest = s.levels().len() - 1;
            let limit = a.input.limit();
            s.read_level(coarsest, a.input.step, &limit).with_context(|| format!("cannot read {source}"))?
        }
        None => a.input.read(&a.volume)?.1,
    };
    let (dims, s, o) = match &store {
        Some(st) => (st.levels()[0].dims, st.levels()[0].spacing, st.levels()[0].origin),
        None => (volume.dims(), volume.spacing(), volume.origin()),
    };
    let [nx, ny, nz] = dims;
    let format = match &source {
        VolumeSource::File(p) => isowall_volume::io::format_name(p),
        VolumeSource::DicomSeries { .. } => "DICOM",
        VolumeSource::Steps(_) => "time steps (a glob of files)",
        VolumeSource::Procedural { .. } => "procedural (built in)",
    };
    println!("volume: {source}");
    println!("format: {format}; voxels read as 32-bit float in the data's units");
    println!("dims: {nx} x {ny} x {nz} ({} voxels)", nx * ny * nz);
    println!("spacing: {} {} {} world units per voxel; origin {} {} {}", s.x, s.y, s.z, o.x, o.y, o.z);
    let top = isowall_volume::VolumeInfo { name: String::new(), dims, spacing: s, origin: o }.box_max();
    println!("box: {} {} {} .. {} {} {}", o.x, o.y, o.z, top.x, top.y, top.z);
    match volume.orientation() {
        Some(orient) => {
            let [x, y, z] = orient.axes().map(direction_name);
            println!(
                "orientation: {} (+x {x}, +y {y}, +z {z}): it opens on the face (anterior)",
                orient.code()
            );
        }
        None => println!("orientation: none in the file (views read the world axes as LPS)"),
    }
    if let Some(store) = store {
        let coarsest = &store.levels()[store.levels().len() - 1];
        println!(
            "levels ({} time steps; the values below are of the coarsest level, `{}`: a store is not read whole here):",
            store.steps(),
            coarsest.path
        );
        for (l, level) in store.levels().iter().enumerate() {
            let [x, y, z] = level.dims;
            let [cx, cy, cz] = level.chunk;
            println!(
                "  {l}: `{}` {x} x {y} x {z}, spacing {} {} {}, {} in chunks of {cx} x {cy} x {cz}",
                level.path, level.spacing.x, level.spacing.y, level.spacing.z, level.data_type
            );
        }
        let bricks = store.into_bricks(a.input.step)?;
        match bricks.value_range() {
            Some((lo, hi)) => println!("level 0's values: {lo} .. {hi} (from the store's per-brick min/max)"),
            None => {
                println!("level 0's values: unknown without reading it (the store has no per-brick min/max)")
            }
        }
    }
    let stats = ValueStats::of(volume.data()).context("the volume holds no values")?;
    println!("values: {} .. {}", stats.min, stats.max);
    let pct: Vec<String> = stats.percentiles.iter().map(|(p, v)| format!("{p}% {v}")).collect();
    println!("percentiles: {}", pct.join(", "));
    println!("histogram ({} bars, counts on a log scale):", a.bars);
    for line in stats.bars(usize::from(a.bars), 40) {
        println!("  {line}");
    }
    println!("suggested iso values (render with --iso V; a wall's [volume] iso):");
    if let Some(natural) = source.natural_iso() {
        println!("  {natural:<12} the procedural volume's own surface");
    }
    let (lo, hi) = stats.three_class;
    let round = |v: f64| format!("{:.4}", v).trim_end_matches('0').trim_end_matches('.').to_string();
    println!(
        "  {:<12} two-class threshold (Otsu's method on the histogram): between the background and the object (air and skin in a scan)",
        round(stats.two_class)
    );
    println!(
        "  {:<12} three-class thresholds (Otsu's method, two thresholds), the upper one: the densest class's surface (bone in a CT)",
        round(hi)
    );
    println!("  {:<12} three-class thresholds, the lower one", round(lo));
    Ok(())
}
