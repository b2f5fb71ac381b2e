//! Writes a volume as a DICOM series, one CT slice per file (16-bit stored values, RescaleIntercept
//! -1024, so whole Hounsfield values come back exactly), e.g. the shared CT:
//!
//! ```text
//! cargo run --release -p isowall-volume --example dicom_series -- ../shared/data/ct-cranium.nrrd /tmp/ct-dicom
//! ```
//!
//! Optional third argument: the SeriesInstanceUID (default 1.2.826.0.1.3680043.10.1).

use isowall_volume::io::dicom_write::SeriesWriter;
use isowall_volume::VolumeSource;
use std::path::Path;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [source, dir, rest @ ..] = args.as_slice() else {
        return Err("usage: dicom_series SOURCE OUT_DIR [SERIES_UID]".into());
    };
    let uid = rest.first().map(String::as_str).unwrap_or("1.2.826.0.1.3680043.10.1");
    let volume = source.parse::<VolumeSource>()?.load(None)?;
    let files = SeriesWriter::new(uid).write(&volume, Path::new(dir))?;
    println!("{}: {} slices of {:?}, series {uid}", dir, files.len(), volume.dims());
    Ok(())
}
