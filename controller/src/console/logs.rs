//! A node's recent log lines for the console: the tail of the log file of a daemon the console
//! started (`logs/NODE.log`), read within a byte bound from the end (never the whole file), each
//! line cut to [`MAX_LINE_CHARS`] characters, control characters escaped (`printable`). Remote
//! nodes' logs stay on their machines (`journalctl -u isowalld`); the console shows what it hears
//! from them over the wall's connection (their state, reason, version and GPU) and says so.

use isowall_model::messages::printable;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

/// The most lines a request may ask for, and the default.
pub const MAX_LINES: usize = 200;
pub const DEFAULT_LINES: usize = 50;
/// The most bytes read from the end of a log.
pub const MAX_TAIL_BYTES: u64 = 64 * 1024;

/// The last `n` lines (at most [`MAX_LINES`]) of the file at `path`, from at most the last
/// [`MAX_TAIL_BYTES`] bytes; a first partial line of that window is dropped. Only a regular file
/// is read, never through a symbolic link (a link in `logs/` must not show a file outside it).
pub fn tail(path: &Path, n: usize) -> std::io::Result<Vec<String>> {
    use isowall_volume::io::regular::{open_regular_no_link, RegularError};
    let (mut f, len) = open_regular_no_link(path).map_err(|e| match e {
        RegularError::Io(e) => e,
        other => std::io::Error::new(std::io::ErrorKind::InvalidInput, other.to_string()),
    })?;
    let start = len.saturating_sub(MAX_TAIL_BYTES);
    f.seek(SeekFrom::Start(start))?;
    let mut bytes = Vec::with_capacity((len - start) as usize);
    f.take(MAX_TAIL_BYTES).read_to_end(&mut bytes)?;
    let text = String::from_utf8_lossy(&bytes);
    let mut lines: Vec<&str> = text.lines().collect();
    if start > 0 && !lines.is_empty() {
        lines.remove(0);
    }
    let n = n.min(MAX_LINES);
    Ok(lines[lines.len().saturating_sub(n)..].iter().map(|l| printable(strip_ansi(l).as_str())).collect())
}

/// `line` without the terminal colour codes (`ESC [ ... m`) tracing writes.
fn strip_ansi(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' && chars.peek() == Some(&'[') {
            chars.next();
            for d in chars.by_ref() {
                if d.is_ascii_alphabetic() {
                    break;
                }
            }
            continue;
        }
        out.push(c);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use isowall_model::messages::PRINTABLE_CHARS as MAX_LINE_CHARS;
    use std::io::Write;

    #[test]
    fn the_tail_is_bounded_in_lines_bytes_and_characters() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("node0.log");
        let mut f = std::fs::File::create(&path).unwrap();
        for i in 0..10_000 {
            writeln!(f, "line {i}").unwrap();
        }
        writeln!(f, "\u{1b}[32m INFO\u{1b}[0m {}<script>\u{7}", "x".repeat(1000)).unwrap();
        drop(f);
        let lines = tail(&path, 3).unwrap();
        assert_eq!(&lines[..2], ["line 9998", "line 9999"]);
        assert!(lines[2].starts_with(" INFO xxx"), "{}", lines[2]);
        assert!(lines[2].ends_with("..."), "cut to {MAX_LINE_CHARS} characters");
        assert_eq!(lines[2].chars().count(), MAX_LINE_CHARS + 3);
        assert_eq!(tail(&path, 10_000).unwrap().len(), MAX_LINES);
        // Most of a big file is never read: the window is the last 64 KiB, whole lines only.
        let mut f = std::fs::OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(&vec![b'y'; 200 * 1024]).unwrap();
        writeln!(f, "\nlast <script>alert(1)</script>\u{7}").unwrap();
        drop(f);
        assert_eq!(tail(&path, 2).unwrap(), vec!["last <script>alert(1)</script>\\u{7}".to_string()]);
        assert!(tail(&dir.path().join("none.log"), 5).is_err());
        // A link out of the folder is not followed, a FIFO not waited on.
        let outside = tempfile::tempdir().unwrap();
        std::fs::write(outside.path().join("secret"), "secret\n").unwrap();
        std::os::unix::fs::symlink(outside.path().join("secret"), dir.path().join("node1.log")).unwrap();
        let e = tail(&dir.path().join("node1.log"), 5).unwrap_err();
        assert!(e.to_string().contains("symbolic link"), "{e}");
        let fifo = dir.path().join("node2.log");
        assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        let e = tail(&fifo, 5).unwrap_err();
        assert!(e.to_string().contains("FIFO"), "{e}");
    }
}
