//! Files read whole or streamed only where they are regular files: a FIFO, a device (`/dev/zero`),
//! a socket or a directory is refused by its type before it is opened, the file is opened without
//! blocking (a FIFO swapped in meanwhile cannot hold the reader) and checked again, and a file
//! read whole is read up to a limit, so a config path can neither hang a reader nor fill its
//! memory.

use std::fs::File;
use std::io::{self, Read};
use std::path::Path;

/// What a file that is not regular is, for the error ("a FIFO (named pipe)", "a device", ...).
pub fn kind_of(t: std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_dir() {
        "a directory"
    } else if t.is_char_device() || t.is_block_device() {
        "a device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a regular file"
    }
}

/// Why a file was not read.
#[derive(Debug, thiserror::Error)]
pub enum RegularError {
    #[error("it is {0}, not a regular file")]
    NotRegular(&'static str),
    #[error("it is a symbolic link, which is not followed here")]
    Link,
    #[error("it is {size} bytes or more, over the limit of {limit}")]
    TooLarge { size: u64, limit: u64 },
    #[error(transparent)]
    Io(#[from] io::Error),
}

/// Opens `path` if it is a regular file ([`RegularError::NotRegular`] says what it is instead).
/// Returns the file and its length.
pub fn open_regular(path: &Path) -> Result<(File, u64), RegularError> {
    use std::os::unix::fs::OpenOptionsExt;
    let kind = std::fs::metadata(path)?.file_type();
    if !kind.is_file() {
        return Err(RegularError::NotRegular(kind_of(kind)));
    }
    let file = std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NONBLOCK).open(path)?;
    let meta = file.metadata()?;
    if !meta.file_type().is_file() {
        return Err(RegularError::NotRegular(kind_of(meta.file_type())));
    }
    Ok((file, meta.len()))
}

/// Opens `path` if it is a regular file and not a symbolic link: for files a server reads on a
/// client's behalf from a folder of its own (the console's logs and bookmarks), which a link must
/// not lead out of. The link is refused by its type before opening and by `O_NOFOLLOW` while
/// opening (a link swapped in meanwhile fails the open). Returns the file and its length.
pub fn open_regular_no_link(path: &Path) -> Result<(File, u64), RegularError> {
    use std::os::unix::fs::OpenOptionsExt;
    let kind = std::fs::symlink_metadata(path)?.file_type();
    if kind.is_symlink() {
        return Err(RegularError::Link);
    }
    if !kind.is_file() {
        return Err(RegularError::NotRegular(kind_of(kind)));
    }
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOFOLLOW)
        .open(path)
        .map_err(|e| if e.raw_os_error() == Some(libc::ELOOP) { RegularError::Link } else { e.into() })?;
    let meta = file.metadata()?;
    if !meta.file_type().is_file() {
        return Err(RegularError::NotRegular(kind_of(meta.file_type())));
    }
    Ok((file, meta.len()))
}

/// Reads the regular file `path` whole as UTF-8 text, refusing one over `limit` bytes (by its
/// length, and by what it gives: a file that grows while read stops at the limit).
pub fn read_regular_text(path: &Path, limit: u64) -> Result<String, RegularError> {
    let (file, len) = open_regular(path)?;
    if len > limit {
        return Err(RegularError::TooLarge { size: len, limit });
    }
    let mut text = String::new();
    file.take(limit + 1).read_to_string(&mut text)?;
    if text.len() as u64 > limit {
        return Err(RegularError::TooLarge { size: text.len() as u64, limit });
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_regular_files_of_bounded_size_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let ok = dir.path().join("ok.toml");
        std::fs::write(&ok, "a = 1\n").unwrap();
        assert_eq!(read_regular_text(&ok, 6).unwrap(), "a = 1\n");
        let e = read_regular_text(&ok, 5).unwrap_err();
        assert!(e.to_string().contains("over the limit of 5"), "{e}");
        // A device that never ends and a FIFO nobody writes: refused at once, never read.
        let e = read_regular_text(Path::new("/dev/zero"), 1 << 20).unwrap_err();
        assert!(e.to_string().contains("a device, not a regular file"), "{e}");
        let fifo = dir.path().join("fifo");
        crate::io::testutil::mkfifo(&fifo);
        let e = read_regular_text(&fifo, 1 << 20).unwrap_err();
        assert!(e.to_string().contains("a FIFO (named pipe), not a regular file"), "{e}");
        let e = read_regular_text(dir.path(), 1 << 20).unwrap_err();
        assert!(e.to_string().contains("a directory"), "{e}");
    }

    #[test]
    fn a_link_is_not_followed_where_links_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let ok = dir.path().join("ok.log");
        std::fs::write(&ok, "a\n").unwrap();
        assert_eq!(open_regular_no_link(&ok).unwrap().1, 2);
        let link = dir.path().join("link.log");
        std::os::unix::fs::symlink(&ok, &link).unwrap();
        let e = open_regular_no_link(&link).unwrap_err();
        assert!(matches!(e, RegularError::Link), "{e}");
        assert!(open_regular(&link).is_ok(), "elsewhere a link is followed");
        let fifo = dir.path().join("fifo");
        crate::io::testutil::mkfifo(&fifo);
        let e = open_regular_no_link(&fifo).unwrap_err();
        assert!(e.to_string().contains("a FIFO (named pipe), not a regular file"), "{e}");
    }
}
