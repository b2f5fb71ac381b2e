//! The files of an environment (`[render] env`, `--env`): what names them ([`EnvSource`]), how
//! big their images may be ([`MAX_FACE`], [`MAX_ENVIRONMENT_TEXELS`]) and the checks made from
//! their headers before a pixel is decoded ([`EnvImage::open`], [`CubeFaces::open`]). One rule for
//! the node that loads an environment (`isowall_render::environment`, which decodes the images
//! these checks let through) and for `check-config` of both binaries, which reads the headers only
//! ([`EnvSource::check_headers`]). It lives here, beside the volume readers, because the controller
//! does not link the renderer.
//!
//! - an image's size is read from its own header (PNG or Radiance HDR) and refused when over the
//!   limit of its role ([`ImageRole`]) or empty; the decoder is then allowed to allocate only what
//!   that size needs;
//! - images are read from regular files only: a FIFO, a device or a socket is refused by its type
//!   and opened without blocking ([`crate::io::regular::open_regular`]);
//! - a cube map is a directory of six square faces of one size, `px nx py ny pz nz`, each `.png`
//!   or `.hdr` (not both); every face's header is checked before any face is decoded.

use crate::io::regular::{open_regular, RegularError};
use image::ImageDecoder;
use std::fmt;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// The most texels an environment holds: 8192 x 4096 (32 Mi texels, 512 MiB as the GPU's
/// `f32x4`). An equirectangular `.hdr` may have at most this many pixels; a cube face at most
/// [`MAX_FACE`] on a side, as its `4 F x 2 F` resampling must fit too.
pub const MAX_ENVIRONMENT_TEXELS: u64 = 1 << 25;

/// The largest cube face side: `4 F x 2 F` texels within [`MAX_ENVIRONMENT_TEXELS`].
pub const MAX_FACE: u32 = 2048;

/// The cube faces, in file-name order (the renderer numbers faces by this order).
pub const FACES: [&str; 6] = ["px", "nx", "py", "ny", "pz", "nz"];

/// Why an environment could not be made. Every variant names the file (or directory) and what is
/// wrong with it.
#[derive(Debug, thiserror::Error)]
pub enum EnvironmentError {
    #[error("{}: {error}", .path.display())]
    Io { path: PathBuf, error: std::io::Error },
    #[error("{}: it is {kind}, not a regular file: environment images are read from regular files only", .path.display())]
    NotRegular { path: PathBuf, kind: &'static str },
    #[error("{}: cannot decode image: {source}", .path.display())]
    Decode { path: PathBuf, source: image::ImageError },
    #[error("{}: {what}", .path.display())]
    TooLarge { path: PathBuf, what: String },
    #[error("{}: image is empty ({width}x{height})", .path.display())]
    Empty { path: PathBuf, width: u32, height: u32 },
    #[error("{}: not a directory (a cube map is a directory holding px nx py ny pz nz)", .path.display())]
    NotADirectory { path: PathBuf },
    #[error("{}: missing face {face} (.png or .hdr)", .dir.display())]
    MissingFace { dir: PathBuf, face: &'static str },
    #[error("{}: both {face}.png and {face}.hdr exist; keep only one", .dir.display())]
    AmbiguousFace { dir: PathBuf, face: &'static str },
    #[error("{}: face is {width}x{height}, but cube faces must be square", .path.display())]
    NotSquare { path: PathBuf, width: u32, height: u32 },
    #[error("{}: face is {size}x{size} but {other} is {other_size}x{other_size}", .path.display())]
    FaceSizeMismatch { path: PathBuf, size: u32, other: String, other_size: u32 },
    #[error("environment {name:?}: {width}x{height} needs {expected} texels, got {got}")]
    BadTexels { name: String, width: u32, height: u32, expected: usize, got: usize },
    #[error(
        "{value:?} is not an environment: give `sky` (the built-in procedural sky), a path to an \
         equirectangular Radiance .hdr file, or an existing directory holding six cube faces \
         px nx py ny pz nz (each .png or .hdr)"
    )]
    BadSource { value: String },
}

/// Where an environment comes from, as given on the command line or in a config.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum EnvSource {
    /// The built-in procedural sky.
    Sky,
    /// An equirectangular Radiance `.hdr` file.
    Hdr(PathBuf),
    /// A directory of six cube faces `px nx py ny pz nz` (`.png` or `.hdr`).
    CubeDir(PathBuf),
}

impl FromStr for EnvSource {
    type Err = EnvironmentError;

    /// `sky` (any case) is the built-in sky (write `./sky` for a directory of that name); an
    /// existing directory is a cube map; a path ending in `.hdr` (any case) is an equirectangular
    /// HDR file (whether it exists is checked when it is read); anything else is an error
    /// explaining these three forms.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let path = Path::new(s);
        if s.eq_ignore_ascii_case("sky") {
            Ok(EnvSource::Sky)
        } else if !s.is_empty() && path.is_dir() {
            Ok(EnvSource::CubeDir(path.to_owned()))
        } else if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("hdr")) {
            Ok(EnvSource::Hdr(path.to_owned()))
        } else {
            Err(EnvironmentError::BadSource { value: s.to_owned() })
        }
    }
}

impl fmt::Display for EnvSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            EnvSource::Sky => f.write_str("sky"),
            EnvSource::Hdr(p) | EnvSource::CubeDir(p) => write!(f, "{}", p.display()),
        }
    }
}

impl EnvSource {
    /// What loading this environment would refuse from its files' headers, decoding nothing: a
    /// `.hdr` opened and sized ([`EnvImage::open`]), a cube map's six faces found, opened and
    /// sized ([`CubeFaces::open`]). The sky has no files.
    pub fn check_headers(&self) -> Result<(), EnvironmentError> {
        match self {
            EnvSource::Sky => Ok(()),
            EnvSource::Hdr(path) => {
                EnvImage::open(path, image::ImageFormat::Hdr, ImageRole::Equirect).map(drop)
            }
            EnvSource::CubeDir(dir) => CubeFaces::open(dir).map(drop),
        }
    }
}

/// What an image may be: a cube face (at most [`MAX_FACE`] on a side) or an equirectangular
/// image (at most [`MAX_ENVIRONMENT_TEXELS`] pixels).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageRole {
    Face,
    Equirect,
}

impl ImageRole {
    /// Why an image of `w`x`h` (as its `format` header says) is refused, if it is.
    pub fn refuse(self, format: &str, w: u32, h: u32) -> Option<String> {
        match self {
            ImageRole::Face if w > MAX_FACE || h > MAX_FACE => Some(format!(
                "the {format} header says {w}x{h}, over the largest cube face of {MAX_FACE}x{MAX_FACE} (the faces \
                 are resampled to 4 F x 2 F texels, at most {MAX_ENVIRONMENT_TEXELS}): refused before decoding"
            )),
            ImageRole::Equirect if u64::from(w) * u64::from(h) > MAX_ENVIRONMENT_TEXELS => Some(format!(
                "the {format} header says {w}x{h} ({} pixels), over the limit of {MAX_ENVIRONMENT_TEXELS} pixels \
                 (8192x4096) for an environment: refused before decoding",
                u64::from(w) * u64::from(h)
            )),
            _ => None,
        }
    }

    /// The most bytes a decoder may allocate for an image this role allows: its pixels at 16
    /// bytes each (RGBA of 32-bit floats, the widest any decoder here produces).
    pub fn max_alloc(self) -> u64 {
        let pixels = match self {
            ImageRole::Face => u64::from(MAX_FACE) * u64::from(MAX_FACE),
            ImageRole::Equirect => MAX_ENVIRONMENT_TEXELS,
        };
        pixels * 16
    }
}

/// An environment image whose header has been read and its size allowed, not yet decoded.
pub struct EnvImage {
    path: PathBuf,
    format: image::ImageFormat,
    width: u32,
    height: u32,
    decoder: Box<dyn ImageDecoder>,
}

impl fmt::Debug for EnvImage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("EnvImage")
            .field("path", &self.path)
            .field("format", &self.format)
            .field("width", &self.width)
            .field("height", &self.height)
            .finish_non_exhaustive()
    }
}

impl EnvImage {
    /// Opens the regular file `path` as an image of `format` and reads its header only. A size
    /// over what `role` allows ([`ImageRole::refuse`]) or an empty image is refused; the decoder
    /// kept for [`EnvImage::decode`] may allocate no more than `role` allows.
    pub fn open(
        path: &Path,
        format: image::ImageFormat,
        role: ImageRole,
    ) -> Result<EnvImage, EnvironmentError> {
        let file = open_regular(path).map(|(file, _)| file).map_err(|e| match e {
            RegularError::NotRegular(kind) => EnvironmentError::NotRegular { path: path.to_owned(), kind },
            RegularError::Io(error) => EnvironmentError::Io { path: path.to_owned(), error },
            other => EnvironmentError::Io { path: path.to_owned(), error: std::io::Error::other(other) },
        })?;
        let mut reader = image::ImageReader::with_format(BufReader::new(file), format);
        let mut limits = image::Limits::default();
        limits.max_alloc = Some(role.max_alloc());
        reader.limits(limits);
        // The decoder reads the header only; the pixels are decoded by `decode`.
        let decoder = reader
            .into_decoder()
            .map_err(|source| EnvironmentError::Decode { path: path.to_owned(), source })?;
        let (width, height) = decoder.dimensions();
        let name = format.extensions_str().first().copied().unwrap_or("image").to_uppercase();
        if let Some(what) = role.refuse(&name, width, height) {
            return Err(EnvironmentError::TooLarge { path: path.to_owned(), what });
        }
        if width == 0 || height == 0 {
            return Err(EnvironmentError::Empty { path: path.to_owned(), width, height });
        }
        Ok(EnvImage { path: path.to_owned(), format, width, height, decoder: Box::new(decoder) })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn format(&self) -> image::ImageFormat {
        self.format
    }

    /// Width and height, as the header says.
    pub fn dimensions(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Decodes the pixels (an image of [`EnvImage::dimensions`]), naming the file on error.
    pub fn decode(self) -> Result<image::DynamicImage, EnvironmentError> {
        let path = self.path;
        image::DynamicImage::from_decoder(self.decoder)
            .map_err(|source| EnvironmentError::Decode { path, source })
    }
}

/// The six faces of a cube-map directory, each opened and sized from its header.
#[derive(Debug)]
pub struct CubeFaces {
    /// The faces in [`FACES`] order.
    pub faces: [EnvImage; 6],
    /// Their side F (every face is F x F).
    pub size: u32,
}

impl CubeFaces {
    /// Finds the six faces of `dir` (`NAME.png` or `NAME.hdr`, not both), opens each with its
    /// header read ([`EnvImage::open`], role [`ImageRole::Face`]) and checks that it is square
    /// and of the same size as the faces before it. Nothing is decoded.
    pub fn open(dir: &Path) -> Result<CubeFaces, EnvironmentError> {
        if !dir.is_dir() {
            return Err(EnvironmentError::NotADirectory { path: dir.to_owned() });
        }
        let mut faces = Vec::with_capacity(6);
        let mut first: Option<(u32, String)> = None;
        for face in FACES {
            let png = dir.join(format!("{face}.png"));
            let hdr = dir.join(format!("{face}.hdr"));
            let (path, format) = match (png.is_file(), hdr.is_file()) {
                (true, true) => return Err(EnvironmentError::AmbiguousFace { dir: dir.to_owned(), face }),
                (true, false) => (png, image::ImageFormat::Png),
                (false, true) => (hdr, image::ImageFormat::Hdr),
                (false, false) => return Err(EnvironmentError::MissingFace { dir: dir.to_owned(), face }),
            };
            let image = EnvImage::open(&path, format, ImageRole::Face)?;
            let (w, h) = image.dimensions();
            if w != h {
                return Err(EnvironmentError::NotSquare { path, width: w, height: h });
            }
            match &first {
                None => {
                    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                    first = Some((w, name));
                }
                Some((s, other)) if *s != w => {
                    return Err(EnvironmentError::FaceSizeMismatch {
                        path,
                        size: w,
                        other: other.clone(),
                        other_size: *s,
                    })
                }
                Some(_) => {}
            }
            faces.push(image);
        }
        let faces: [EnvImage; 6] = faces.try_into().expect("six faces");
        let size = faces[0].width;
        Ok(CubeFaces { faces, size })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use isowall_test_support::{lying_hdr, lying_png};

    fn faces(dir: &Path, size: impl Fn(&str) -> (u32, u32)) {
        for face in FACES {
            let (w, h) = size(face);
            lying_png(&dir.join(format!("{face}.png")), w, h);
        }
    }

    fn check(source: &EnvSource) -> String {
        source.check_headers().unwrap_err().to_string()
    }

    #[test]
    fn headers_over_the_limits_are_refused_naming_file_and_size() {
        let dir = tempfile::tempdir().unwrap();
        let cube = EnvSource::CubeDir(dir.path().to_owned());
        faces(dir.path(), |_| (8192, 8192));
        let e = check(&cube);
        assert!(
            e.contains("px.png: the PNG header says 8192x8192, over the largest cube face of 2048x2048")
                && e.contains("refused before decoding"),
            "{e}"
        );
        // One face over the limit, the others small: that face is named.
        faces(dir.path(), |f| if f == "pz" { (2049, 2049) } else { (4, 4) });
        assert!(check(&cube).contains("pz.png: the PNG header says 2049x2049"), "{}", check(&cube));
        // At the limit the headers pass (their data is not read).
        faces(dir.path(), |_| (MAX_FACE, MAX_FACE));
        let cube_faces = CubeFaces::open(dir.path()).unwrap();
        assert_eq!(cube_faces.size, MAX_FACE);
        // The pixels behind such a header are a decode error.
        let [px, ..] = cube_faces.faces;
        assert!(matches!(px.decode(), Err(EnvironmentError::Decode { .. })));

        let hdr = dir.path().join("big.hdr");
        lying_hdr(&hdr, 16384, 8192);
        let e = check(&EnvSource::Hdr(hdr.clone()));
        assert!(
            e.contains(
                "big.hdr: the HDR header says 16384x8192 (134217728 pixels), over the limit of 33554432"
            ) && e.contains("refused before decoding"),
            "{e}"
        );
        lying_hdr(&hdr, 8192, 4096);
        EnvSource::Hdr(hdr).check_headers().unwrap();
    }

    #[test]
    fn a_cube_map_the_loader_would_refuse_is_refused_from_its_headers() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let cube = EnvSource::CubeDir(d.to_owned());
        faces(d, |_| (8, 8));
        cube.check_headers().unwrap();

        faces(d, |f| if f == "ny" { (8, 4) } else { (8, 8) });
        assert!(
            check(&cube).contains("ny.png: face is 8x4, but cube faces must be square"),
            "{}",
            check(&cube)
        );
        faces(d, |f| if f == "nx" { (4, 4) } else { (8, 8) });
        assert!(check(&cube).contains("nx.png: face is 4x4 but px.png is 8x8"), "{}", check(&cube));
        faces(d, |f| if f == "py" { (0, 0) } else { (8, 8) });
        assert!(check(&cube).contains("py.png: "), "{}", check(&cube));

        faces(d, |_| (8, 8));
        std::fs::write(d.join("pz.hdr"), b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 8 +X 8\n").unwrap();
        assert!(check(&cube).contains("both pz.png and pz.hdr exist"), "{}", check(&cube));
        std::fs::remove_file(d.join("pz.png")).unwrap();
        cube.check_headers().unwrap();
        std::fs::remove_file(d.join("nz.png")).unwrap();
        let e = check(&cube);
        assert!(e.contains(&d.display().to_string()) && e.contains("missing face nz (.png or .hdr)"), "{e}");
        std::fs::write(d.join("nz.png"), b"not a png at all").unwrap();
        assert!(check(&cube).contains("nz.png: cannot decode image"), "{}", check(&cube));

        let file = d.join("px.png");
        let e = CubeFaces::open(&file).unwrap_err().to_string();
        assert!(e.contains("px.png: not a directory"), "{e}");
    }

    #[test]
    fn an_hdr_that_is_missing_or_not_a_regular_file_is_refused_without_blocking() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing.hdr");
        let e = check(&EnvSource::Hdr(missing));
        assert!(e.contains("missing.hdr: No such file"), "{e}");
        let fifo = dir.path().join("fifo.hdr");
        crate::io::testutil::mkfifo(&fifo);
        let e = check(&EnvSource::Hdr(fifo));
        assert!(e.contains("fifo.hdr: it is a FIFO (named pipe), not a regular file"), "{e}");
        let e = check(&EnvSource::Hdr("/dev/zero".into()));
        assert!(e.contains("/dev/zero: it is a device, not a regular file"), "{e}");
        EnvSource::Sky.check_headers().unwrap();
    }
}
