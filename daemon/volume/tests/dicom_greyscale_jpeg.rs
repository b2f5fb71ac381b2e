//! Greyscale JPEG slices through Isowall's own DICOM reader (`io::dicom::read`, as a series of
//! one slice), each against its uncompressed twin: `MR_small.dcm`'s 16-bit pixels as JPEG lossless
//! (process 14, selection value 1) read back exactly, and the same pixels at 8 bits as JPEG
//! baseline within the codec's loss. pydicom's wheel ships no greyscale JPEG lossless or 8-bit
//! baseline slice (its `JPEG-LL.dcm` and `JPGLosslessP14SV1_1s_1f_8b.dcm` are downloaded at run
//! time from pydicom-data), so the test encodes them: lossless with the small encoder below,
//! baseline with `jpeg-encoder` (the encoder dicom-rs itself uses).

use dicom_core::value::{PixelFragmentSequence, Value};
use dicom_core::{DataElement, PrimitiveValue, VR};
use dicom_dictionary_std::tags;
use isowall_volume::io::{dicom, VolumeLimit};
use isowall_volume::Volume;
use std::path::{Path, PathBuf};

const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
const JPEG_BASELINE: &str = "1.2.840.10008.1.2.4.50";
const JPEG_LOSSLESS_SV1: &str = "1.2.840.10008.1.2.4.70";

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/dicom").join(name)
}

/// Reads `path` through the series reader, alone in a folder of its own.
fn read_alone(path: &Path) -> Volume {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join(path.file_name().unwrap());
    std::fs::copy(path, &p).unwrap();
    dicom::read(&p, None, &VolumeLimit::default()).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Bits written most significant first, with JPEG's byte stuffing (0x00 after 0xFF) and the
/// last byte padded with ones.
#[derive(Default)]
struct Bits {
    out: Vec<u8>,
    acc: u32,
    n: u32,
}

impl Bits {
    fn put(&mut self, value: u32, bits: u32) {
        for i in (0..bits).rev() {
            self.acc = (self.acc << 1) | ((value >> i) & 1);
            self.n += 1;
            if self.n == 8 {
                self.byte();
            }
        }
    }

    fn byte(&mut self) {
        let b = self.acc as u8;
        self.out.push(b);
        if b == 0xFF {
            self.out.push(0x00);
        }
        self.acc = 0;
        self.n = 0;
    }

    fn finish(mut self) -> Vec<u8> {
        if self.n > 0 {
            let pad = 8 - self.n;
            self.put((1 << pad) - 1, pad);
        }
        self.out
    }
}

/// A greyscale JPEG lossless image (SOF3, predictor 1: the sample on the left; the first row
/// predicted from the left, the first column from above, the first sample from 2^(P-1)), one
/// Huffman table giving each difference category 0..=16 a 5-bit code.
fn jpeg_lossless(samples: &[u16], width: usize, height: usize, precision: u8) -> Vec<u8> {
    assert_eq!(samples.len(), width * height);
    let mut out = vec![0xFF, 0xD8];
    out.extend([0xFF, 0xC3, 0, 11, precision]);
    out.extend((height as u16).to_be_bytes());
    out.extend((width as u16).to_be_bytes());
    out.extend([1, 1, 0x11, 0]);
    let mut counts = [0u8; 16];
    counts[4] = 17;
    out.extend([0xFF, 0xC4, 0, 2 + 1 + 16 + 17, 0x00]);
    out.extend(counts);
    out.extend(0u8..=16);
    out.extend([0xFF, 0xDA, 0, 8, 1, 1, 0x00, 1, 0, 0]);
    let mut bits = Bits::default();
    for y in 0..height {
        for x in 0..width {
            let s = i32::from(samples[y * width + x]);
            let predicted = match (x, y) {
                (0, 0) => 1 << (precision - 1),
                (0, _) => i32::from(samples[(y - 1) * width]),
                _ => i32::from(samples[y * width + x - 1]),
            };
            // Differences are modulo 2^16: -32767 ..= 32768.
            let d = (s - predicted).rem_euclid(65536);
            let d = if d > 32768 { d - 65536 } else { d };
            let category = 32 - d.unsigned_abs().leading_zeros();
            bits.put(category, 5);
            if (1..16).contains(&category) {
                let v = (if d < 0 { d - 1 } else { d }) as u32;
                bits.put(v & ((1 << category) - 1), category);
            }
        }
    }
    out.extend(bits.finish());
    out.extend([0xFF, 0xD9]);
    out
}

/// `MR_small.dcm` with its pixel data replaced: `stored` (8 or 16 bits) as `pixels`, encapsulated
/// in one fragment under `ts` or native under explicit VR little endian.
fn rewrite(out: &Path, ts: &str, stored: u16, pixels: Vec<u8>) {
    let mut obj = dicom_object::open_file(data("MR_small.dcm")).unwrap();
    let us = |tag, v: u16| DataElement::new(tag, VR::US, PrimitiveValue::from(v));
    obj.put(us(tags::BITS_ALLOCATED, stored));
    obj.put(us(tags::BITS_STORED, stored));
    obj.put(us(tags::HIGH_BIT, stored - 1));
    obj.put(us(tags::PIXEL_REPRESENTATION, 0));
    obj.remove_element(tags::SMALLEST_IMAGE_PIXEL_VALUE);
    obj.remove_element(tags::LARGEST_IMAGE_PIXEL_VALUE);
    let value = if ts == EXPLICIT_LE {
        Value::Primitive(PrimitiveValue::from(pixels))
    } else {
        let mut fragment = pixels;
        if fragment.len() % 2 == 1 {
            fragment.push(0);
        }
        Value::PixelSequence(PixelFragmentSequence::new(Vec::<u32>::new(), vec![fragment]))
    };
    obj.put(DataElement::new(tags::PIXEL_DATA, VR::OB, value));
    obj.meta_mut().transfer_syntax = ts.to_string();
    obj.meta_mut().update_information_group_length();
    obj.write_to_file(out).unwrap();
}

/// MR_small's stored values and its size.
fn mr_small() -> (Vec<u16>, usize, usize) {
    let obj = dicom_object::open_file(data("MR_small.dcm")).unwrap();
    let rows = obj.element(tags::ROWS).unwrap().to_int::<usize>().unwrap();
    let cols = obj.element(tags::COLUMNS).unwrap().to_int::<usize>().unwrap();
    let bytes = obj.element(tags::PIXEL_DATA).unwrap().to_bytes().unwrap();
    let values: Vec<u16> = bytes.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect();
    assert_eq!(values.len(), rows * cols);
    (values, cols, rows)
}

#[test]
fn a_greyscale_jpeg_lossless_slice_reads_exactly_as_its_uncompressed_twin() {
    let (values, w, h) = mr_small();
    let dir = tempfile::tempdir().unwrap();
    let twin = dir.path().join("twin.dcm");
    let lossless = dir.path().join("lossless.dcm");
    let le: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    rewrite(&twin, EXPLICIT_LE, 16, le);
    rewrite(&lossless, JPEG_LOSSLESS_SV1, 16, jpeg_lossless(&values, w, h, 16));
    let (a, b) = (read_alone(&twin), read_alone(&lossless));
    assert_eq!(a.dims(), [w, h, 1]);
    assert_eq!(b.dims(), a.dims());
    assert_eq!(&a.data()[..4], &[905.0, 1019.0, 1227.0, 1259.0], "MR_small's first row");
    assert_eq!(b.data(), a.data(), "lossless: exactly the stored values");
    assert_eq!(b.value_range(), a.value_range());
    // The same through the uncompressed original (signed, 16 bits): the twin is its copy.
    assert_eq!(read_alone(&data("MR_small.dcm")).data(), a.data());
}

#[test]
fn an_8_bit_greyscale_jpeg_baseline_slice_reads_within_its_loss() {
    let (values, w, h) = mr_small();
    let max = u32::from(*values.iter().max().unwrap()).max(1);
    let bytes: Vec<u8> = values.iter().map(|&v| (u32::from(v) * 255 / max) as u8).collect();
    let mut jpeg = Vec::new();
    jpeg_encoder::Encoder::new(&mut jpeg, 90)
        .encode(&bytes, w as u16, h as u16, jpeg_encoder::ColorType::Luma)
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let twin = dir.path().join("twin8.dcm");
    let baseline = dir.path().join("baseline.dcm");
    rewrite(&twin, EXPLICIT_LE, 8, bytes.clone());
    rewrite(&baseline, JPEG_BASELINE, 8, jpeg);
    let (a, b) = (read_alone(&twin), read_alone(&baseline));
    assert_eq!(b.dims(), [w, h, 1]);
    let expected: Vec<f32> = bytes.iter().map(|&v| f32::from(v)).collect();
    assert_eq!(a.data(), &expected[..], "the 8-bit twin reads its bytes");
    let diffs: Vec<f32> = a.data().iter().zip(b.data()).map(|(x, y)| (x - y).abs()).collect();
    let worst = diffs.iter().copied().fold(0.0f32, f32::max);
    let mean = diffs.iter().sum::<f32>() / diffs.len() as f32;
    eprintln!("JPEG baseline (quality 90) against its 8-bit twin: max {worst} levels, mean {mean:.3}");
    assert!(a.data() != b.data(), "baseline is lossy: identical pixels mean it was not decoded as JPEG");
    assert!(worst <= 24.0 && mean < 3.0, "baseline differs by up to {worst} levels (mean {mean})");
}

#[test]
fn a_jpeg_frame_larger_than_the_dicom_header_says_is_refused_before_decoding() {
    // The attack: Rows/Columns say MR_small's 64x64, the JPEG frame header (SOF0) says 4096x4096
    // (45000x45000 took a node to 2.86 GB and 21 s before the size check after decoding).
    let (values, w, h) = mr_small();
    let bytes: Vec<u8> = values.iter().map(|&v| (v >> 4) as u8).collect();
    let mut jpeg = Vec::new();
    jpeg_encoder::Encoder::new(&mut jpeg, 90)
        .encode(&bytes, w as u16, h as u16, jpeg_encoder::ColorType::Luma)
        .unwrap();
    let sof = jpeg.windows(2).position(|m| m == [0xFF, 0xC0]).expect("a baseline frame header");
    // FF C0, length (2), precision (1), then height and width (2 each, big-endian).
    jpeg[sof + 5..sof + 7].copy_from_slice(&4096u16.to_be_bytes());
    jpeg[sof + 7..sof + 9].copy_from_slice(&4096u16.to_be_bytes());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("liar.dcm");
    rewrite(&path, JPEG_BASELINE, 8, jpeg);
    let start = std::time::Instant::now();
    let e = dicom::read(&path, None, &VolumeLimit::default()).unwrap_err().to_string();
    let took = start.elapsed();
    eprintln!("refused in {took:?}: {e}");
    assert!(
        e.contains("liar.dcm")
            && e.contains("(7FE0,0010)")
            && e.contains("the JPEG frame header says 4096x4096 (columns x rows) where Rows/Columns")
            && e.contains(&format!("say {w}x{h}: refused before decoding")),
        "{e}"
    );
    // The same refusal from the headers alone, as check-config reads them.
    let series = dicom::Series::open(&path, None).unwrap();
    let e = series.check_frames().unwrap_err().to_string();
    assert!(e.contains("liar.dcm") && e.contains("says 4096x4096"), "{e}");
    // An honest frame passes the same check.
    let honest = dir.path().join("honest");
    std::fs::create_dir(&honest).unwrap();
    let mut jpeg = Vec::new();
    jpeg_encoder::Encoder::new(&mut jpeg, 90)
        .encode(&bytes, w as u16, h as u16, jpeg_encoder::ColorType::Luma)
        .unwrap();
    rewrite(&honest.join("ok.dcm"), JPEG_BASELINE, 8, jpeg);
    dicom::Series::open(&honest, None).unwrap().check_frames().unwrap();
}
