//! The operator's identify label (`Message::Identify`): a tile's node and tile name drawn white on
//! black in its top-left corner, with the charts' embedded font (`bench/chart.rs`). Drawn on the
//! CPU once per tile and size, then written over the tile's rendered image on the GPU
//! (`GpuRenderer::stamp`), so the screen and a snapshot show it alike.

use plotters::prelude::*;

/// The label's height in pixels at most (a smaller tile gets a smaller label).
pub const LABEL_HEIGHT: u32 = 24;

/// The label `text` as 8-bit RGBA rows, at most `max` (width, height) pixels: its size and bytes.
pub fn label(text: &str, max: (u32, u32)) -> (u32, u32, Vec<u8>) {
    crate::bench::chart::register_font();
    let h = LABEL_HEIGHT.min(max.1).max(1);
    let font_px = f64::from(h) * 0.75;
    // DejaVu Sans's mean advance is about 0.6 em; a margin of a quarter of the height each side.
    let w = ((text.chars().count() as f64 * font_px * 0.62) as u32 + h / 2).clamp(1, max.0.max(1));
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    {
        let area = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        let style = (crate::bench::chart::FAMILY, font_px).into_font().color(&WHITE);
        if area.draw_text(text, &style, ((h / 4) as i32, (h / 8) as i32)).is_err() {
            tracing::debug!("identify label: the text did not draw");
        }
        let _ = area.present();
    }
    let rgba = rgb.chunks_exact(3).flat_map(|p| [p[0], p[1], p[2], 255]).collect();
    (w, h, rgba)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_label_is_white_text_on_black_within_its_bounds() {
        let (w, h, rgba) = label("node0 t00", (200, 100));
        assert_eq!(h, LABEL_HEIGHT);
        assert!(w > 40 && w <= 200, "{w}");
        assert_eq!(rgba.len() as u32, w * h * 4);
        let white = rgba.chunks_exact(4).filter(|p| p[0] > 200).count();
        let black = rgba.chunks_exact(4).filter(|p| p[0] == 0).count();
        assert!(white > 20 && black > white, "{white} white, {black} black of {}", w * h);
        let (w, h, _) = label("node0 t00", (16, 12));
        assert_eq!((w, h), (16, 12), "cut to a small tile");
    }
}
