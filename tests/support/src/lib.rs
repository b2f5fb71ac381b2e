//! What the tests of more than one crate need: environment images whose headers claim a size
//! their data does not have (the render crate's, the volume crate's and the end-to-end tests
//! of refusing them before decoding). Used only as a dev-dependency.

use std::path::Path;

/// A valid 4x4 PNG whose header is rewritten to say `width`x`height` (its CRC fixed): a few
/// dozen bytes of data behind a header that may claim megapixels.
pub fn lying_png_bytes(width: u32, height: u32) -> Vec<u8> {
    let mut bytes = Vec::new();
    image::RgbImage::from_pixel(4, 4, image::Rgb([200, 100, 50]))
        .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .expect("encode a 4x4 PNG");
    // The signature (8), the IHDR chunk's length (4) and type (4), then width and height.
    assert_eq!(&bytes[12..16], b"IHDR");
    bytes[16..20].copy_from_slice(&width.to_be_bytes());
    bytes[20..24].copy_from_slice(&height.to_be_bytes());
    // The chunk's CRC covers its type and its 13 bytes of data.
    let crc = crc32fast::hash(&bytes[12..29]);
    bytes[29..33].copy_from_slice(&crc.to_be_bytes());
    bytes
}

/// Writes [`lying_png_bytes`] to `path`.
pub fn lying_png(path: &Path, width: u32, height: u32) {
    std::fs::write(path, lying_png_bytes(width, height))
        .unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
}

/// Writes to `path` a Radiance `.hdr` whose header says `width`x`height` followed by four bytes
/// of pixel data: what a reader that trusts the header would allocate for, with nothing behind it.
pub fn lying_hdr(path: &Path, width: u32, height: u32) {
    let mut bytes = format!("#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {height} +X {width}\n").into_bytes();
    bytes.extend_from_slice(b"\x02\x02\x40\x00");
    std::fs::write(path, bytes).unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lying_png_says_the_size_it_is_given_and_is_otherwise_valid() {
        let bytes = lying_png_bytes(8192, 300);
        let (w, h) = image::ImageReader::with_format(std::io::Cursor::new(&bytes), image::ImageFormat::Png)
            .into_dimensions()
            .unwrap();
        assert_eq!((w, h), (8192, 300));
        // The real size: the data is 4x4, so the claimed image cannot be decoded.
        assert!(image::load_from_memory(&bytes).is_err());
        assert!(image::load_from_memory(&lying_png_bytes(4, 4)).is_ok());
    }

    #[test]
    fn a_lying_hdr_says_the_size_it_is_given() {
        let dir = std::env::temp_dir().join(format!("isowall-test-support-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("big.hdr");
        lying_hdr(&path, 16384, 8192);
        let (w, h) = image::ImageReader::open(&path).unwrap().into_dimensions().unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!((w, h), (16384, 8192));
    }
}
