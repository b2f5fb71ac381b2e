//! Lower internal resolution while the camera moves (the governor's `scale`, 1 ..= 4).
//!
//! A tile rendered at scale `s` renders the view of a full image of `ceil(W / s) x ceil(H / s)`
//! pixels: the low-resolution pixel `(X, Y)` of the *whole* image covers the full-resolution pixels
//! `s*X .. s*X + s` (nearest-neighbour upsampling, each low pixel replicated into an `s x s`
//! block). A tile's low rectangle is the set of low pixels its full rectangle touches (its origin
//! rounded down, its end rounded up), and upsampling crops the blocks back to the full rectangle.
//! So every full-resolution pixel takes the colour of the same low pixel of the whole image
//! whichever tile it lies in: tiles meet exactly at their edges even when their origins and sizes
//! are not multiples of `s` (they then render the shared low pixels twice). The sample pattern
//! stays seeded by the low pixel's position in the whole low image and the frame index.
//!
//! Where `W` is not a multiple of `s`, the low image is a fraction of a pixel wider than `W / s`
//! and its rays are those of that slightly larger image (a stretch under one full pixel), which is
//! invisible while the camera moves; still frames are always at scale 1.

use crate::camera::{Rect, View};

/// The view a tile renders at internal resolution divisor `scale` (1: `view` itself).
pub fn scaled_view(view: &View, scale: u32) -> View {
    let s = scale.max(1);
    if s == 1 {
        return *view;
    }
    let w = view.rect;
    let (x0, y0) = (w.x / s, w.y / s);
    let (x1, y1) = ((w.x + w.width).div_ceil(s), (w.y + w.height).div_ceil(s));
    View {
        camera: view.camera,
        full: (view.full.0.div_ceil(s), view.full.1.div_ceil(s)),
        rect: Rect { x: x0, y: y0, width: x1 - x0, height: y1 - y0 },
    }
}

/// Nearest-neighbour upsampling of a tile's image rendered with `scaled_view(view, scale)`
/// (`low`, rows top to bottom) to `view`'s rectangle, cropped to it.
pub fn upsample_nearest<T: Copy>(low: &[T], view: &View, scale: u32) -> Vec<T> {
    let s = scale.max(1);
    let lv = scaled_view(view, s);
    debug_assert_eq!(low.len(), lv.pixel_count());
    let w = view.rect;
    let lw = lv.rect.width as usize;
    let mut out = Vec::with_capacity(view.pixel_count());
    for y in 0..w.height {
        let ly = ((w.y + y) / s - lv.rect.y) as usize;
        for x in 0..w.width {
            let lx = ((w.x + x) / s - lv.rect.x) as usize;
            out.push(low[ly * lw + lx]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use glam::DVec3;

    fn view(full: (u32, u32), rect: Rect) -> View {
        let camera =
            Camera { eye: DVec3::new(0.0, -5.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 30.0 };
        View { camera, full, rect }
    }

    /// A "render" of a low view: each pixel holds its position in the whole low image.
    fn render(v: &View) -> Vec<(u32, u32)> {
        let w = v.rect;
        (0..w.height).flat_map(|y| (0..w.width).map(move |x| (w.x + x, w.y + y))).collect()
    }

    #[test]
    fn tiles_upsample_to_the_whole_images_pixels() {
        for s in 1..=4 {
            let whole = view((100, 70), Rect { x: 0, y: 0, width: 100, height: 70 });
            let want = upsample_nearest(&render(&scaled_view(&whole, s)), &whole, s);
            // Tiles whose origins are and are not multiples of s.
            for (x, y, width, height) in [(0, 0, 50, 35), (50, 35, 50, 35), (33, 17, 41, 29), (99, 69, 1, 1)]
            {
                let t = view((100, 70), Rect { x, y, width, height });
                let got = upsample_nearest(&render(&scaled_view(&t, s)), &t, s);
                for ty in 0..height {
                    for tx in 0..width {
                        let g = got[(ty * width + tx) as usize];
                        let w = want[((y + ty) * 100 + x + tx) as usize];
                        assert_eq!(g, w, "scale {s}, tile at ({x},{y}), pixel ({tx},{ty})");
                        assert_eq!(g, ((x + tx) / s, (y + ty) / s));
                    }
                }
            }
        }
    }

    #[test]
    fn the_low_view_divides_the_full_image() {
        let v = view((1920, 1080), Rect { x: 960, y: 540, width: 960, height: 540 });
        let l = scaled_view(&v, 2);
        assert_eq!(l.full, (960, 540));
        assert_eq!(l.rect, Rect { x: 480, y: 270, width: 480, height: 270 });
        let l = scaled_view(&v, 4);
        assert_eq!(l.full, (480, 270));
        assert_eq!(l.rect, Rect { x: 240, y: 135, width: 240, height: 135 });
        // Not a multiple: rounded out.
        let v = view((101, 7), Rect { x: 3, y: 1, width: 5, height: 6 });
        let l = scaled_view(&v, 2);
        assert_eq!(l.full, (51, 4));
        assert_eq!(l.rect, Rect { x: 1, y: 0, width: 3, height: 4 });
        assert_eq!(scaled_view(&v, 1), v);
    }
}
