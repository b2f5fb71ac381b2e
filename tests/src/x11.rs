//! An X server for the window tests (`present.rs`, `present_wall.rs`): Xvfb on a display number
//! it picks itself, and a parser for the X window dumps `xwd` writes.

use crate::in_ci;
use std::io::BufRead;
use std::process::{Child, ChildStdout, Command, Stdio};

/// A virtual X server on a display number it picked itself; killed when dropped.
pub struct Xvfb {
    child: Child,
    pub display: String,
    /// Kept open: Xvfb reported its display number on it.
    _stdout: std::io::BufReader<ChildStdout>,
}

impl Xvfb {
    /// Starts Xvfb with one `width`x`height` 24-bit screen; `None` (after a message) where there
    /// is no Xvfb outside CI.
    pub fn start(width: u32, height: u32) -> Option<Xvfb> {
        let spawned = Command::new("Xvfb")
            // -displayfd: take the first free display number and write it on fd 1 once ready.
            .args(["-displayfd", "1", "-screen", "0", &format!("{width}x{height}x24"), "-nolisten", "tcp"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn();
        let mut child = match spawned {
            Ok(c) => c,
            Err(e) => {
                assert!(!in_ci(), "cannot run Xvfb under CI=true ({e}): scripts/setup.sh installs xvfb");
                eprintln!("skipping: cannot run Xvfb ({e}); install it: apt-get install xvfb x11-apps");
                return None;
            }
        };
        let mut stdout = std::io::BufReader::new(child.stdout.take().expect("piped"));
        let mut line = String::new();
        let _ = stdout.read_line(&mut line);
        let number = line.trim();
        if number.is_empty() || !number.bytes().all(|b| b.is_ascii_digit()) {
            let _ = child.kill();
            let _ = child.wait();
            assert!(!in_ci(), "Xvfb did not start under CI=true (it reported {line:?})");
            eprintln!("skipping: Xvfb did not start (it reported {line:?})");
            return None;
        }
        Some(Xvfb { display: format!(":{number}"), child, _stdout: stdout })
    }

    /// [`Xvfb::start`] where `xwd` (the screenshots) runs too; `None` (after a message) where
    /// either is missing outside CI.
    pub fn start_with_xwd(width: u32, height: u32) -> Option<Xvfb> {
        let xvfb = Xvfb::start(width, height)?;
        if let Err(e) = Command::new("xwd").arg("-help").output() {
            assert!(!in_ci(), "cannot run xwd under CI=true ({e}): scripts/setup.sh installs x11-apps");
            eprintln!("skipping: cannot run xwd ({e}); install it: apt-get install x11-apps");
            return None;
        }
        Some(xvfb)
    }

    /// A screenshot with `xwd ARGS` (`-root`: the whole screen; `-name TITLE`: one window).
    pub fn xwd(&self, args: &[&str]) -> Result<Rgb, String> {
        let out = Command::new("xwd")
            .args(["-display", &self.display, "-silent"])
            .args(args)
            .output()
            .map_err(|e| format!("cannot run xwd: {e}"))?;
        if !out.status.success() {
            return Err(format!("xwd {}: {}", args.join(" "), String::from_utf8_lossy(&out.stderr)));
        }
        parse_xwd(&out.stdout)
    }
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An image as 8-bit RGB, rows top to bottom.
pub struct Rgb {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[u8; 3]>,
}

/// Parses an X window dump (XWD version 7, as `xwd` writes it) of a TrueColor visual with 32 bits
/// per pixel (Xvfb's 24-bit depth): a big-endian header of 25 32-bit fields, the window name, the
/// colormap (12 bytes per entry), then the pixels, `bytes_per_line` per row.
pub fn parse_xwd(bytes: &[u8]) -> Result<Rgb, String> {
    let field = |i: usize| -> Result<u32, String> {
        let b = bytes.get(4 * i..4 * i + 4).ok_or("XWD header truncated")?;
        Ok(u32::from_be_bytes(b.try_into().expect("4 bytes")))
    };
    let (header_size, version, width, height) = (field(0)?, field(1)?, field(4)?, field(5)?);
    let (byte_order, bits_per_pixel, bytes_per_line, visual_class) =
        (field(7)?, field(11)?, field(12)?, field(13)?);
    let masks = [field(14)?, field(15)?, field(16)?];
    let ncolors = field(19)?;
    if version != 7 || bits_per_pixel != 32 || visual_class != 4 {
        return Err(format!(
            "unsupported XWD: version {version}, {bits_per_pixel} bits per pixel, visual class {visual_class} \
             (want 7, 32, TrueColor 4)"
        ));
    }
    let start = header_size as usize + 12 * ncolors as usize;
    let need = start + bytes_per_line as usize * height as usize;
    if bytes.len() < need || (bytes_per_line as usize) < 4 * width as usize {
        return Err(format!("XWD truncated: {} bytes, {need} needed", bytes.len()));
    }
    let mut pixels = Vec::with_capacity(width as usize * height as usize);
    for y in 0..height as usize {
        for x in 0..width as usize {
            let at = start + y * bytes_per_line as usize + 4 * x;
            let b: [u8; 4] = bytes[at..at + 4].try_into().expect("4 bytes");
            let v = if byte_order == 0 { u32::from_le_bytes(b) } else { u32::from_be_bytes(b) };
            pixels.push(masks.map(|m| ((v & m) >> m.trailing_zeros()) as u8));
        }
    }
    Ok(Rgb { width, height, pixels })
}
