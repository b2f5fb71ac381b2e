//! A wall's picture: every tile's image placed by the wall geometry into one image (snapshots and
//! the console's thumbnails), bounded in bytes.

use isowall_model::config::WallConfig;
use isowall_model::messages::TileImage;
use std::collections::{BTreeMap, HashMap};

/// Places every tile's image by the wall geometry into one RGB image; bezels and gaps dark, tiles
/// with no image (a node down) a grey placeholder.
pub fn compose(config: &WallConfig, tiles: &BTreeMap<String, Vec<TileImage>>) -> (u32, u32, Vec<u8>) {
    compose_scaled(config, tiles, 1)
}

/// The most bytes a composed wall image takes (RGB): a wall whose image at the asked scale is
/// larger is composed smaller (by a whole factor more), so no snapshot or thumbnail allocates more.
pub const MAX_WALL_IMAGE_BYTES: u64 = 512 << 20;

/// The divisor a wall image asked at `divisor` is composed at: the least multiple of it whose
/// image fits [`MAX_WALL_IMAGE_BYTES`].
pub fn bounded_divisor(config: &WallConfig, divisor: u32) -> u32 {
    let d = divisor.max(1);
    let (w, h) = config.wall_size();
    let bytes = |k: u32| 3 * w.div_ceil(d * k) as u64 * h.div_ceil(d * k) as u64;
    let k = (1..=u32::MAX / d).find(|&k| bytes(k) <= MAX_WALL_IMAGE_BYTES).unwrap_or(u32::MAX / d);
    d * k
}

/// [`compose`] of tiles downscaled by `divisor` (`TileImage::downscaled`): the wall image
/// `ceil(w / D)` x `ceil(h / D)`, tile (x, y) placed at (x / D, y / D), with D = `divisor`, or
/// the [`bounded_divisor`] where the image would be larger than [`MAX_WALL_IMAGE_BYTES`] (the
/// tiles are then downscaled further here).
pub fn compose_scaled(
    config: &WallConfig,
    tiles: &BTreeMap<String, Vec<TileImage>>,
    divisor: u32,
) -> (u32, u32, Vec<u8>) {
    let asked = divisor.max(1);
    let d = bounded_divisor(config, asked);
    let (w, h) = config.wall_size();
    let (w, h) = (w.div_ceil(d), h.div_ceil(d));
    let mut img = vec![12u8; w as usize * h as usize * 3];
    let smaller: Vec<TileImage> = if d == asked {
        Vec::new()
    } else {
        tiles.values().flatten().map(|t| t.downscaled(d / asked)).collect()
    };
    let by_name: HashMap<&str, &TileImage> = if d == asked {
        tiles.values().flatten().map(|t| (t.name.as_str(), t)).collect()
    } else {
        smaller.iter().map(|t| (t.name.as_str(), t)).collect()
    };
    for full in &config.tiles {
        let tile = isowall_model::config::TileConfig {
            x: full.x / d,
            y: full.y / d,
            width: full.width.div_ceil(d).min(w - full.x / d),
            height: full.height.div_ceil(d).min(h - full.y / d),
            ..full.clone()
        };
        let image = by_name
            .get(tile.name.as_str())
            .filter(|t| t.width == full.width.div_ceil(d) && t.height == full.height.div_ceil(d));
        for y in 0..tile.height {
            let row = (tile.y + y) as usize * w as usize;
            for x in 0..tile.width {
                let dst = (row + (tile.x + x) as usize) * 3;
                let px: [u8; 3] = match image {
                    Some(t) => {
                        let src = ((y * t.width + x) * 3) as usize;
                        [t.rgb8[src], t.rgb8[src + 1], t.rgb8[src + 2]]
                    }
                    // Placeholder: grey with a darker diagonal cross.
                    None if x * tile.height / tile.width.max(1) == y
                        || (tile.width - 1 - x) * tile.height / tile.width.max(1) == y =>
                    {
                        [40, 40, 40]
                    }
                    None => [96, 96, 96],
                };
                img[dst..dst + 3].copy_from_slice(&px);
            }
        }
    }
    (w, h, img)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A wall of 16 x 8 UHD tiles is 61440x17280 pixels, 3.2 GB as RGB: its snapshot is composed
    /// at 1/3 scale (1.06 GB at 1/2 would be over the bound), each tile placed where it belongs.
    #[test]
    fn a_wall_image_over_the_bound_is_composed_smaller() {
        let mut text = String::from("[wall]\nname = \"huge\"\nmessage_limit_bytes = 1073741824\n\n[volume]\nsource = \"procedural:sphere\"\n");
        for i in 0..128 {
            let (x, y) = (3840 * (i % 16), 2160 * (i / 16));
            text += &format!("\n[[tiles]]\nname = \"t{i}\"\nx = {x}\ny = {y}\nwidth = 3840\nheight = 2160\n");
            text += &format!(
                "\n[[nodes]]\nname = \"n{i}\"\naddress = \"10.0.0.{}:7400\"\ntiles = [\"t{i}\"]\n",
                i + 1
            );
        }
        let config = WallConfig::parse(&text, std::path::Path::new("huge.toml")).unwrap();
        assert_eq!(config.wall_size(), (61440, 17280));
        assert_eq!(bounded_divisor(&config, 1), 3);
        assert_eq!(bounded_divisor(&config, 4), 4, "a thumbnail's divisor already within the bound");
        // Tile t17 (second row, second column) all white; no other tile has an image.
        let white = TileImage {
            name: "t17".into(),
            width: 3840,
            height: 2160,
            frame_id: 1,
            rgb8: vec![255; 3840 * 2160 * 3],
        };
        let tiles = BTreeMap::from([("n17".to_string(), vec![white])]);
        let (w, h, rgb) = compose(&config, &tiles);
        assert_eq!((w, h), (20480, 5760));
        assert!(rgb.len() as u64 <= MAX_WALL_IMAGE_BYTES);
        let at = |x: u32, y: u32| rgb[(y as usize * w as usize + x as usize) * 3];
        assert_eq!(at(1280 + 640, 720 + 360), 255, "t17's centre");
        assert_eq!(at(100, 300), 96, "t0 has no image: the placeholder's grey");
    }
}
