//! Environments for image-based lighting (DESIGN.md "IBL"), world up = +z. Every environment is
//! held as an equirectangular float RGB image: direction d maps to u = atan2(d.y, d.x) / (2 pi)
//! mod 1 (column 0 looks along +x, columns advance counter-clockwise seen from above),
//! v = acos(d.z) / pi (row 0 is the zenith).
//!
//! # Sources
//! [`EnvSource`] parses what a user types (`--env`): `sky` (the built-in procedural HDR sky,
//! [`Environment::sky`]), a path ending in `.hdr` (an equirectangular Radiance file,
//! [`Environment::load_hdr`]) or an existing directory of six cube faces
//! ([`Environment::load_cube_dir`]); [`Environment::from_source`] reads what it names. Everything
//! is converted to the one equirectangular layout below, so the renderers only ever do one kind
//! of lookup. `EnvSource`, the size limits ([`MAX_FACE`], [`MAX_ENVIRONMENT_TEXELS`]) and the
//! checks made from the image files' headers before anything is decoded live in
//! `isowall_volume::env_files`, the one rule `check-config` applies too.
//!
//! # Layout and lookup (the WGSL twin must do exactly this)
//! [`Environment::texels`] holds `width * height` linear-RGB radiances, row-major, rows from the
//! zenith (row 0) to the nadir (row `height - 1`), texel `(col, row)` at index `row * width + col`.
//! [`Environment::equirect_f32x4`] is the same array padded to `vec4<f32>` (w = 0) for a storage
//! buffer. Texel `(col, row)` is centred on `u = (col + 0.5) / W`, `v = (row + 0.5) / H`, i.e. on
//! the direction of azimuth `phi = 2 pi u` and polar angle `theta = pi v`
//! ([`Environment::uv_to_direction`]). [`Environment::lookup`] of a direction d is bilinear:
//!
//! ```text
//! (u, v) = direction_to_uv(d)            // u in [0, 1), v in [0, 1]
//! x = u * W - 0.5;   y = v * H - 0.5
//! x0 = floor(x);     y0 = floor(y)
//! fx = x - x0;       fy = y - y0         // weights, computed BEFORE wrapping / clamping
//! c0 = x0 mod W;     c1 = (x0 + 1) mod W // wrap in u (euclidean mod: -1 -> W - 1)
//! r0 = clamp(y0, 0, H - 1);  r1 = clamp(y0 + 1, 0, H - 1)   // clamp in v (edge rows repeat)
//! top = (1 - fx) * T[r0][c0] + fx * T[r0][c1]
//! bot = (1 - fx) * T[r1][c0] + fx * T[r1][c1]
//! L   = (1 - fy) * top + fy * bot
//! ```
//!
//! Near a pole (v < 0.5 / H or v > 1 - 0.5 / H) both rows clamp to the edge row, so the lookup
//! there only interpolates along that row. A zero or non-finite direction maps to (u, v) = (0, 0.5).
//!
//! # Cube maps
//! A cube directory holds six square faces of equal size, `px nx py ny pz nz`, each `.png` (8 or
//! 16 bit, sRGB-encoded, decoded to linear) or `.hdr` (linear). **The face names are world axes,
//! taken literally**: `px` is what you see looking along world +x, `pz` looking up (+z, the
//! zenith), `nz` looking down. Within a face, the image orientation is OpenGL's cube-map table
//! (major axis ma, then `s = (sc / |ma| + 1) / 2`, `t = (tc / |ma| + 1) / 2`, `t = 0` the top
//! row of the image, `s = 0` its left column):
//!
//! | face | major axis | sc  | tc  |
//! |------|------------|-----|-----|
//! | px   | +x         | -z  | -y  |
//! | nx   | -x         | +z  | -y  |
//! | py   | +y         | +x  | +z  |
//! | ny   | -y         | +x  | -z  |
//! | pz   | +z         | +x  | -y  |
//! | nz   | -z         | -x  | -y  |
//!
//! So this is OpenGL's table applied to Isowall's z-up world unchanged: it is *not* a y-up
//! skybox re-oriented to z-up. A skybox authored for a y-up viewer (OpenGL/Unity) therefore has
//! its sky in `py`; to use one, convert it first (the y-up direction (x, y, z) is the Isowall
//! direction (x, -z, y), so e.g. its `py` must become our `pz`, re-oriented by the table above).
//! The major axis is chosen with ties going to x, then y, then z. The faces are resampled into an
//! equirectangular image of `4 F x 2 F` texels (F = face size): each texel takes the bilinear
//! sample of its centre direction in the one face that direction hits (face pixel centres at
//! `(i + 0.5) / F`, clamped at the face's edges; no filtering across faces).
//!
//! # Diffuse irradiance
//! [`Environment::sh9`] projects the environment onto the 9 real spherical harmonics of bands
//! 0..2 ([`sh9_basis`]), each texel taken as constant over its patch of the sphere (its solid
//! angle is `(cos theta0 - cos theta1) * 2 pi / W`) and the basis integrated exactly over the
//! patch, accumulated in f64. [`Environment::irradiance`]
//! convolves them with the clamped cosine (Ramamoorthi & Hanrahan 2001: A0 = pi, A1 = 2 pi / 3,
//! A2 = pi / 4) and divides by pi, so it returns E(n) = (1/pi) * integral L(w) max(0, n.w) dw,
//! which equals L for a constant environment L (DESIGN.md's E without visibility).

use glam::DVec3;
use std::f64::consts::PI;
use std::fmt;
use std::path::Path;

use isowall_volume::env_files::{CubeFaces, EnvImage};
/// What names an environment, its errors, and the size limits and header checks of its image
/// files: one rule, shared with `check-config` (which reads the headers only).
pub use isowall_volume::env_files::{
    EnvSource, EnvironmentError, ImageRole, MAX_ENVIRONMENT_TEXELS, MAX_FACE,
};

/// An environment as an equirectangular linear-RGB radiance image (layout in the module doc).
/// Invariant: `width >= 1`, `height >= 1`, `texels.len() == width * height`.
#[derive(Clone, PartialEq)]
pub struct Environment {
    pub width: u32,
    pub height: u32,
    /// Linear RGB radiance, row-major, rows from the zenith (row 0) to the nadir.
    pub texels: Vec<[f32; 3]>,
    /// Where it came from, for logs and reports ("sky", a file or directory path).
    pub name: String,
}

impl fmt::Debug for Environment {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Environment")
            .field("name", &self.name)
            .field("width", &self.width)
            .field("height", &self.height)
            .finish_non_exhaustive()
    }
}

/// The built-in sky's sun: elevation and azimuth (counter-clockwise from +x) in degrees.
const SUN_ELEVATION_DEG: f64 = 35.0;
const SUN_AZIMUTH_DEG: f64 = 45.0;
/// Angular radius of the sun disc (degrees) and its radiance.
const SUN_RADIUS_DEG: f64 = 1.0;
const SUN_RADIANCE: [f64; 3] = [80.0, 76.0, 68.0];

impl Environment {
    /// An environment from raw texels (layout in the module doc), checking the size.
    pub fn new(
        name: impl Into<String>,
        width: u32,
        height: u32,
        texels: Vec<[f32; 3]>,
    ) -> Result<Environment, EnvironmentError> {
        let name = name.into();
        let expected = width as usize * height as usize;
        if width == 0 || height == 0 || texels.len() != expected {
            return Err(EnvironmentError::BadTexels { name, width, height, expected, got: texels.len() });
        }
        Ok(Environment { width, height, texels, name })
    }

    /// Builds or reads the environment `source` names.
    pub fn from_source(source: &EnvSource) -> Result<Environment, EnvironmentError> {
        match source {
            EnvSource::Sky => Ok(Environment::sky()),
            EnvSource::Hdr(p) => Environment::load_hdr(p),
            EnvSource::CubeDir(p) => Environment::load_cube_dir(p),
        }
    }

    /// The built-in procedural HDR sky, 256x128, deterministic. Above the horizon a blue gradient
    /// from the zenith (0.25, 0.45, 0.90) to a brighter horizon (0.80, 0.90, 1.05); a sun disc of
    /// 1 degree angular radius and radiance ~80 at elevation 35 degrees, azimuth 45 degrees (the
    /// direction (cos 35 cos 45, cos 35 sin 45, sin 35)), with a warm glow around it; below the
    /// horizon a warm-grey ground (0.22, 0.20, 0.17) that fades into the horizon haze over the
    /// first few degrees. Each texel is the solid-angle-weighted mean of 4x4 sub-samples, so the
    /// sun's energy is kept although the disc is only about two texels wide. Irradiance
    /// ([`Environment::irradiance`]) is about 1 looking up, 0.2 looking down.
    pub fn sky() -> Environment {
        const W: u32 = 256;
        const H: u32 = 128;
        const SS: u32 = 4;
        let mut texels = Vec::with_capacity((W * H) as usize);
        for row in 0..H {
            for col in 0..W {
                let mut sum = DVec3::ZERO;
                let mut wsum = 0.0;
                for j in 0..SS {
                    for i in 0..SS {
                        let u = (col as f64 + (i as f64 + 0.5) / SS as f64) / W as f64;
                        let v = (row as f64 + (j as f64 + 0.5) / SS as f64) / H as f64;
                        let w = (PI * v).sin();
                        sum += w * sky_radiance(Environment::uv_to_direction(u, v));
                        wsum += w;
                    }
                }
                let c = sum / wsum;
                texels.push([c.x as f32, c.y as f32, c.z as f32]);
            }
        }
        Environment { width: W, height: H, texels, name: "sky".to_owned() }
    }

    /// The direction of the built-in sky's sun (unit).
    pub fn sky_sun_direction() -> DVec3 {
        let (e, a) = (SUN_ELEVATION_DEG.to_radians(), SUN_AZIMUTH_DEG.to_radians());
        DVec3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin())
    }

    /// A uniform environment of radiance `rgb` (8x4 texels).
    pub fn constant(rgb: [f32; 3]) -> Environment {
        Environment {
            width: 8,
            height: 4,
            texels: vec![rgb; 32],
            name: format!("constant({}, {}, {})", rgb[0], rgb[1], rgb[2]),
        }
    }

    /// Reads an equirectangular Radiance `.hdr` file (any size; 2:1 is expected, and anything
    /// else is stretched to it with a warning). The file's first scanline is the zenith row.
    pub fn load_hdr(path: &Path) -> Result<Environment, EnvironmentError> {
        let image = EnvImage::open(path, image::ImageFormat::Hdr, ImageRole::Equirect)?;
        let (width, height) = image.dimensions();
        let texels = hdr_texels(image)?;
        if width != 2 * height {
            tracing::warn!(
                "{}: an equirectangular environment should be 2:1, this one is {width}x{height}",
                path.display()
            );
        }
        Ok(Environment { width, height, texels, name: path.display().to_string() })
    }

    /// Reads a cube map from a directory of six square faces of one size, `px nx py ny pz nz`,
    /// each `.png` (sRGB, decoded to linear) or `.hdr` (linear), and resamples it into an
    /// equirectangular image of `4 F x 2 F`. Orientation: see the module doc ("Cube maps").
    pub fn load_cube_dir(dir: &Path) -> Result<Environment, EnvironmentError> {
        // Every face is found, opened and sized from its header before any is decoded.
        let CubeFaces { faces, size: f } = CubeFaces::open(dir)?;
        let mut decoded: Vec<Vec<[f32; 3]>> = Vec::with_capacity(6);
        for face in faces {
            let texels = match face.format() {
                image::ImageFormat::Hdr => hdr_texels(face)?,
                _ => png_texels_linear(face)?,
            };
            decoded.push(texels);
        }
        let faces = decoded;
        let (width, height) = (4 * f, 2 * f);
        let mut texels = Vec::with_capacity(width as usize * height as usize);
        for row in 0..height {
            for col in 0..width {
                let d = Environment::uv_to_direction(
                    (col as f64 + 0.5) / width as f64,
                    (row as f64 + 0.5) / height as f64,
                );
                let (face, s, t) = cube_face_st(d);
                texels.push(sample_face(&faces[face], f, s, t));
            }
        }
        Ok(Environment { width, height, texels, name: dir.display().to_string() })
    }

    /// Equirectangular coordinates of a direction (need not be unit): u = atan2(d.y, d.x) / (2 pi)
    /// mod 1, in [0, 1); v = acos(d.z / |d|) / pi, in [0, 1]. A zero or non-finite d gives (0, 0.5).
    pub fn direction_to_uv(d: DVec3) -> (f64, f64) {
        let len = d.length();
        if !(len > 0.0 && len.is_finite()) {
            return (0.0, 0.5);
        }
        let mut u = (d.y.atan2(d.x) / (2.0 * PI)).rem_euclid(1.0);
        if u >= 1.0 {
            // rem_euclid of a tiny negative number rounds up to 1.0.
            u = 0.0;
        }
        let v = (d.z / len).clamp(-1.0, 1.0).acos() / PI;
        (u, v)
    }

    /// The unit direction at equirectangular coordinates (u, v): azimuth phi = 2 pi u from +x
    /// counter-clockwise seen from above, polar angle theta = pi v from +z. Inverse of
    /// [`Environment::direction_to_uv`].
    pub fn uv_to_direction(u: f64, v: f64) -> DVec3 {
        let (phi, theta) = (2.0 * PI * u, PI * v);
        DVec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos())
    }

    /// Radiance towards direction `d`: bilinear, wrapping in u, clamping in v (exact recipe in the
    /// module doc).
    pub fn lookup(&self, d: DVec3) -> [f32; 3] {
        let (u, v) = Environment::direction_to_uv(d);
        self.lookup_uv(u, v)
    }

    /// The bilinear lookup at (u, v) (see [`Environment::lookup`]).
    pub fn lookup_uv(&self, u: f64, v: f64) -> [f32; 3] {
        let (w, h) = (self.width as i64, self.height as i64);
        let x = u * w as f64 - 0.5;
        let y = v * h as f64 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let c0 = x0.rem_euclid(w) as usize;
        let c1 = (x0 + 1).rem_euclid(w) as usize;
        let r0 = y0.clamp(0, h - 1) as usize;
        let r1 = (y0 + 1).clamp(0, h - 1) as usize;
        let t = |r: usize, c: usize| self.texels[r * self.width as usize + c];
        let (a, b, c, d) = (t(r0, c0), t(r0, c1), t(r1, c0), t(r1, c1));
        std::array::from_fn(|k| {
            let top = (1.0 - fx) * a[k] as f64 + fx * b[k] as f64;
            let bot = (1.0 - fx) * c[k] as f64 + fx * d[k] as f64;
            ((1.0 - fy) * top + fy * bot) as f32
        })
    }

    /// Projection onto the 9 real spherical harmonics of bands 0..2, in the order of
    /// [`sh9_basis`]: `sh[i] = integral L(w) Y_i(w) dw`, with L taken as constant over each texel
    /// (texel (col, row) covers theta in [pi row / H, pi (row + 1) / H] and phi in
    /// [2 pi col / W, 2 pi (col + 1) / W]). Each texel's weight is the exact integral of Y_i over
    /// its patch, with dw = sin(theta) dtheta dphi, in closed form and f64; so the weights of
    /// Y00 are the texels' solid angles (summing to 4 pi), and a constant environment has exactly
    /// zero coefficients beyond band 0 at any resolution (a midpoint rule would not: with 4 rows
    /// its Y20 is off by ~ 10%).
    pub fn sh9(&self) -> [[f32; 3]; 9] {
        let (w, h) = (self.width as usize, self.height as usize);
        // Integrals over a texel of the monomials the basis is built from, split into a theta
        // factor (with the sin(theta) of dw) and a phi factor, one per basis function:
        // 1, y, z, x, xy, yz, z^2 (Y20 is built from z^2 and 1 below), xz, x^2 - y^2.
        let rows: Vec<[f64; 9]> = (0..h)
            .map(|r| {
                let (t0, t1) = (PI * r as f64 / h as f64, PI * (r + 1) as f64 / h as f64);
                let (c0, c1) = (t0.cos(), t1.cos());
                let (s0, s1) = (t0.sin(), t1.sin());
                let one = c0 - c1; // int sin
                let z = (c0 * c0 - c1 * c1) / 2.0; // int cos sin
                let zz = (c0.powi(3) - c1.powi(3)) / 3.0; // int cos^2 sin
                let s2 = (t1 - t0) / 2.0 - ((2.0 * t1).sin() - (2.0 * t0).sin()) / 4.0; // int sin^2
                let s2c = (s1.powi(3) - s0.powi(3)) / 3.0; // int sin^2 cos
                let s3 = (c0 - c1) - (c0.powi(3) - c1.powi(3)) / 3.0; // int sin^3
                [one, s2, z, s2, s3, s2c, zz, s2c, s3]
            })
            .collect();
        let cols: Vec<[f64; 9]> = (0..w)
            .map(|c| {
                let (p0, p1) = (2.0 * PI * c as f64 / w as f64, 2.0 * PI * (c + 1) as f64 / w as f64);
                let dp = p1 - p0;
                let cos = p1.sin() - p0.sin(); // int cos phi
                let sin = p0.cos() - p1.cos(); // int sin phi
                let cs = (p1.sin().powi(2) - p0.sin().powi(2)) / 2.0; // int cos sin
                let c2 = ((2.0 * p1).sin() - (2.0 * p0).sin()) / 2.0; // int cos 2 phi = x^2 - y^2
                [dp, sin, dp, cos, cs, sin, dp, cos, c2]
            })
            .collect();
        let c0 = (1.0 / (4.0 * PI)).sqrt();
        let c1 = (3.0 / (4.0 * PI)).sqrt();
        let c2 = (15.0 / (4.0 * PI)).sqrt();
        let c20 = (5.0 / (16.0 * PI)).sqrt();
        let c22 = (15.0 / (16.0 * PI)).sqrt();
        let k = [c0, c1, c1, c1, c2, c2, c20, c2, c22];
        let mut acc = [[0.0f64; 3]; 9];
        for (row, rw) in rows.iter().enumerate() {
            for (col, cw) in cols.iter().enumerate() {
                let l = self.texels[row * w + col];
                let mut y: [f64; 9] = std::array::from_fn(|i| k[i] * rw[i] * cw[i]);
                // Y20 = c20 (3 z^2 - 1): the z^2 integral times 3, minus the solid angle.
                y[6] = c20 * (3.0 * rw[6] * cw[6] - rw[0] * cw[0]);
                for (i, yi) in y.iter().enumerate() {
                    for c in 0..3 {
                        acc[i][c] += l[c] as f64 * yi;
                    }
                }
            }
        }
        acc.map(|c| c.map(|x| x as f32))
    }

    /// Diffuse irradiance over pi, E(n) = (1/pi) * integral L(w) max(0, n.w) dw, from the SH9
    /// coefficients of [`Environment::sh9`]: `sum_i A_l(i) / pi * sh[i] * Y_i(n)` with
    /// A0 / pi = 1, A1 / pi = 2/3, A2 / pi = 1/4; negative results are clamped to 0. A constant
    /// environment L gives L. `n` need not be unit (a zero n gives the mean radiance).
    pub fn irradiance(sh: &[[f32; 3]; 9], n: DVec3) -> [f32; 3] {
        const A: [f64; 9] = [1.0, 2.0 / 3.0, 2.0 / 3.0, 2.0 / 3.0, 0.25, 0.25, 0.25, 0.25, 0.25];
        let n = n.normalize_or_zero();
        let y = sh9_basis(n);
        // A zero n keeps band 0 only: the mean radiance.
        let bands = if n == DVec3::ZERO { 1 } else { 9 };
        std::array::from_fn(|c| {
            let e: f64 = (0..bands).map(|i| A[i] * sh[i][c] as f64 * y[i]).sum();
            e.max(0.0) as f32
        })
    }

    /// The texels padded to `vec4<f32>` (w = 0) for a GPU storage buffer, same order as
    /// [`Environment::texels`].
    pub fn equirect_f32x4(&self) -> Vec<[f32; 4]> {
        self.texels.iter().map(|&[r, g, b]| [r, g, b, 0.0]).collect()
    }
}

/// The 9 real spherical harmonics of bands 0..2 at unit direction d, indexed l (l + 1) + m:
/// Y00 = 0.282095; Y1-1 = 0.488603 y, Y10 = 0.488603 z, Y11 = 0.488603 x;
/// Y2-2 = 1.092548 xy, Y2-1 = 1.092548 yz, Y20 = 0.315392 (3 z^2 - 1), Y21 = 1.092548 xz,
/// Y22 = 0.546274 (x^2 - y^2) (exact constants: sqrt(1/(4 pi)), sqrt(3/(4 pi)), sqrt(15/(4 pi)),
/// sqrt(5/(16 pi)), sqrt(15/(16 pi))).
pub fn sh9_basis(d: DVec3) -> [f64; 9] {
    let c0 = (1.0 / (4.0 * PI)).sqrt();
    let c1 = (3.0 / (4.0 * PI)).sqrt();
    let c2 = (15.0 / (4.0 * PI)).sqrt();
    let c20 = (5.0 / (16.0 * PI)).sqrt();
    let c22 = (15.0 / (16.0 * PI)).sqrt();
    let DVec3 { x, y, z } = d;
    [
        c0,
        c1 * y,
        c1 * z,
        c1 * x,
        c2 * x * y,
        c2 * y * z,
        c20 * (3.0 * z * z - 1.0),
        c2 * x * z,
        c22 * (x * x - y * y),
    ]
}

/// Radiance of the built-in sky towards unit direction d.
fn sky_radiance(d: DVec3) -> DVec3 {
    let zenith = DVec3::new(0.25, 0.45, 0.90);
    let horizon = DVec3::new(0.80, 0.90, 1.05);
    let ground = DVec3::new(0.22, 0.20, 0.17);
    let z = d.z.clamp(-1.0, 1.0);
    let base = if z >= 0.0 {
        let t = (1.0 - z) * (1.0 - z);
        zenith.lerp(horizon, t)
    } else {
        // The ground fades in from the horizon haze over the first ~5 degrees below the horizon.
        let s = (-z / 0.087).min(1.0);
        let s = s * s * (3.0 - 2.0 * s);
        horizon.lerp(ground, s)
    };
    // Sun: only above the horizon (its glow is cut there too, softly).
    let above = (z / 0.02).clamp(0.0, 1.0);
    let sun = Environment::sky_sun_direction();
    let angle = d.dot(sun).clamp(-1.0, 1.0).acos();
    let r = SUN_RADIUS_DEG.to_radians();
    let disc = if angle <= r { DVec3::from_array(SUN_RADIANCE) } else { DVec3::ZERO };
    let sigma = 5f64.to_radians();
    let glow = DVec3::new(1.0, 0.85, 0.6) * (8.0 * (-0.5 * (angle / sigma).powi(2)).exp())
        + DVec3::new(1.0, 0.9, 0.75) * (0.4 * (-angle / 0.35).exp());
    base + above * (disc + glow)
}

/// Face number (index into [`FACES`](isowall_volume::env_files::FACES)) and (s, t) in [0, 1]^2 of direction d, by OpenGL's
/// major-axis table with the face names as world axes (module doc). Ties go to x, then y.
fn cube_face_st(d: DVec3) -> (usize, f64, f64) {
    let a = d.abs();
    let (face, sc, tc, ma) = if a.x >= a.y && a.x >= a.z {
        if d.x >= 0.0 {
            (0, -d.z, -d.y, a.x)
        } else {
            (1, d.z, -d.y, a.x)
        }
    } else if a.y >= a.z {
        if d.y >= 0.0 {
            (2, d.x, d.z, a.y)
        } else {
            (3, d.x, -d.z, a.y)
        }
    } else if d.z >= 0.0 {
        (4, d.x, -d.y, a.z)
    } else {
        (5, -d.x, -d.y, a.z)
    };
    (face, (sc / ma + 1.0) / 2.0, (tc / ma + 1.0) / 2.0)
}

/// Bilinear sample of a square face of `f x f` texels (rows top to bottom) at (s, t), pixel
/// centres at (i + 0.5) / f, clamped at the edges.
fn sample_face(face: &[[f32; 3]], f: u32, s: f64, t: f64) -> [f32; 3] {
    let n = f as i64;
    let x = s * f as f64 - 0.5;
    let y = t * f as f64 - 0.5;
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (x0, y0) = (x0 as i64, y0 as i64);
    let cl = |i: i64| i.clamp(0, n - 1) as usize;
    let (c0, c1, r0, r1) = (cl(x0), cl(x0 + 1), cl(y0), cl(y0 + 1));
    let p = |r: usize, c: usize| face[r * f as usize + c];
    let (a, b, c, d) = (p(r0, c0), p(r0, c1), p(r1, c0), p(r1, c1));
    std::array::from_fn(|k| {
        let top = (1.0 - fx) * a[k] as f64 + fx * b[k] as f64;
        let bot = (1.0 - fx) * c[k] as f64 + fx * d[k] as f64;
        ((1.0 - fy) * top + fy * bot) as f32
    })
}

/// A Radiance .hdr image as linear RGB, rows top to bottom (non-finite and negative values 0).
fn hdr_texels(image: EnvImage) -> Result<Vec<[f32; 3]>, EnvironmentError> {
    let img = image.decode()?.into_rgb32f();
    Ok(img.pixels().map(|p| p.0.map(|x| if x.is_finite() { x.max(0.0) } else { 0.0 })).collect())
}

/// A PNG (8 or 16 bit, any colour type; alpha ignored) decoded from sRGB to linear RGB.
fn png_texels_linear(image: EnvImage) -> Result<Vec<[f32; 3]>, EnvironmentError> {
    let img = image.decode()?.into_rgb32f();
    Ok(img.pixels().map(|p| p.0.map(|x| srgb_to_linear(x as f64) as f32)).collect())
}

/// The sRGB decoding function (IEC 61966-2-1) of an encoded value in [0, 1].
fn srgb_to_linear(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    if x <= 0.040_45 {
        x / 12.92
    } else {
        ((x + 0.055) / 1.055).powf(2.4)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use isowall_test_support::{lying_hdr, lying_png};
    use isowall_volume::env_files::FACES;

    #[test]
    fn environment_images_whose_header_says_a_huge_size_are_refused_before_decoding() {
        // The attack: six small PNG faces whose headers say 8192x8192 (each 192 MiB as RGB8, under
        // the image crate's default allocation limit; as float texels and resampled, gigabytes).
        let dir = tempfile::tempdir().unwrap();
        for face in FACES {
            lying_png(&dir.path().join(format!("{face}.png")), 8192, 8192);
        }
        let start = std::time::Instant::now();
        let e = Environment::load_cube_dir(dir.path()).unwrap_err();
        let took = start.elapsed();
        let msg = e.to_string();
        eprintln!("refused in {took:?}: {msg}");
        assert!(matches!(e, EnvironmentError::TooLarge { .. }), "{msg}");
        assert!(
            msg.contains("px.png: the PNG header says 8192x8192, over the largest cube face of 2048x2048")
                && msg.contains("refused before decoding"),
            "{msg}"
        );
        // At the limit a face passes the size check: its data, too short, is a decode error.
        for face in FACES {
            lying_png(&dir.path().join(format!("{face}.png")), MAX_FACE, MAX_FACE);
        }
        let e = Environment::load_cube_dir(dir.path()).unwrap_err();
        assert!(matches!(e, EnvironmentError::Decode { .. }), "{e}");
        // An equirectangular .hdr whose header says 16384x8192 (2^27 pixels).
        let hdr = dir.path().join("big.hdr");
        lying_hdr(&hdr, 16384, 8192);
        let e = Environment::load_hdr(&hdr).unwrap_err().to_string();
        assert!(
            e.contains(
                "big.hdr: the HDR header says 16384x8192 (134217728 pixels), over the limit of 33554432"
            ) && e.contains("refused before decoding"),
            "{e}"
        );
    }
}
