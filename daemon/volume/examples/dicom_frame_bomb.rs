//! Measures a DICOM slice whose JPEG frame header lies about its size: MR_small.dcm's header
//! (64x64) with an 8-bit JPEG baseline frame whose SOF says `SIZE`x`SIZE`, read through the
//! series reader; prints the error, the time taken and the process's peak resident memory.
//!
//! `cargo run -p isowall-volume --example dicom_frame_bomb -- 45000`

use dicom_core::value::{PixelFragmentSequence, Value};
use dicom_core::{DataElement, PrimitiveValue, VR};
use dicom_dictionary_std::tags;
use isowall_volume::io::{dicom, VolumeLimit};
use std::time::Instant;

fn vm_hwm_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kib: f64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0.0);
    kib / 1024.0
}

fn main() {
    let size: u16 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(45000);
    let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/dicom/MR_small.dcm");
    let mut obj = dicom_object::open_file(&src).unwrap();
    let (w, h) = (64u16, 64u16);
    let mut jpeg = Vec::new();
    jpeg_encoder::Encoder::new(&mut jpeg, 90)
        .encode(&vec![100u8; usize::from(w) * usize::from(h)], w, h, jpeg_encoder::ColorType::Luma)
        .unwrap();
    let sof = jpeg.windows(2).position(|m| m == [0xFF, 0xC0]).unwrap();
    jpeg[sof + 5..sof + 7].copy_from_slice(&size.to_be_bytes());
    jpeg[sof + 7..sof + 9].copy_from_slice(&size.to_be_bytes());
    if jpeg.len() % 2 == 1 {
        jpeg.push(0);
    }
    let us = |tag, v: u16| DataElement::new(tag, VR::US, PrimitiveValue::from(v));
    obj.put(us(tags::BITS_ALLOCATED, 8));
    obj.put(us(tags::BITS_STORED, 8));
    obj.put(us(tags::HIGH_BIT, 7));
    obj.put(us(tags::PIXEL_REPRESENTATION, 0));
    obj.remove_element(tags::SMALLEST_IMAGE_PIXEL_VALUE);
    obj.remove_element(tags::LARGEST_IMAGE_PIXEL_VALUE);
    let value = Value::PixelSequence(PixelFragmentSequence::new(Vec::<u32>::new(), vec![jpeg]));
    obj.put(DataElement::new(tags::PIXEL_DATA, VR::OB, value));
    obj.meta_mut().transfer_syntax = "1.2.840.10008.1.2.4.50".to_string();
    obj.meta_mut().update_information_group_length();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("liar.dcm");
    obj.write_to_file(&path).unwrap();
    let bytes = std::fs::metadata(&path).unwrap().len();
    let before = vm_hwm_mib();
    let start = Instant::now();
    let result = dicom::read(&path, None, &VolumeLimit::default());
    println!(
        "{bytes}-byte slice, Rows/Columns 64x64, SOF {size}x{size}: {} in {:.2?}, VmHWM {:.1} MiB (before the read {:.1} MiB)",
        match &result {
            Ok(v) => format!("read {:?}", v.dims()),
            Err(e) => format!("refused: {e}"),
        },
        start.elapsed(),
        vm_hwm_mib(),
        before
    );
}
