//! Camera bookmarks: named cameras kept in a TOML file beside the wall config
//! (`CONFIG.bookmarks.toml`, e.g. `wall.toml` -> `wall.bookmarks.toml`), listed, saved, recalled
//! and deleted through the console. Names are 1 to [`MAX_NAME_CHARS`] characters of letters,
//! digits, space, `-`, `_` and `.`; at most [`MAX_BOOKMARKS`] are kept; the file is written whole
//! to a temporary file beside it and renamed over it (a crash leaves the old file or the new one).
//! A malformed file is reported with its FILE:LINE and is not fatal: the console runs on, lists
//! none, and refuses to write over it until it is mended.
//!
//! ```toml
//! [[bookmark]]
//! name = "front"
//! eye = [60.0, -70.0, 45.0]
//! target = [23.5, 23.5, 23.5]
//! up = [0.0, 0.0, 1.0]
//! fov_y = 40.0
//! ```

use serde::{Deserialize, Serialize};
use std::io::Read;
use std::path::{Path, PathBuf};

/// The most bookmarks a file may hold.
pub const MAX_BOOKMARKS: usize = 64;
/// The longest name, in characters.
pub const MAX_NAME_CHARS: usize = 40;
/// The largest bookmarks file read (64 bookmarks take a few kB).
pub const MAX_FILE_BYTES: u64 = 256 * 1024;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bookmark {
    pub name: String,
    pub eye: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub fov_y: f64,
}

#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    #[serde(default)]
    bookmark: Vec<Bookmark>,
}

#[derive(Debug, thiserror::Error)]
pub enum BookmarkError {
    #[error("{path}: {message}")]
    Malformed { path: String, message: String },
    #[error("{0}")]
    Name(String),
    #[error("no bookmark named `{0}`")]
    Unknown(String),
    #[error("{MAX_BOOKMARKS} bookmarks are kept at most: delete one first")]
    Full,
    #[error("cannot write {path}: {error}")]
    Write { path: String, error: std::io::Error },
}

/// The bookmarks file of the wall config at `config`.
pub fn path_for(config: &Path) -> PathBuf {
    let stem = config.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "wall".into());
    config.with_file_name(format!("{stem}.bookmarks.toml"))
}

/// Checks a bookmark's name.
pub fn check_name(name: &str) -> Result<(), BookmarkError> {
    let n = name.chars().count();
    if n == 0 || n > MAX_NAME_CHARS {
        return Err(BookmarkError::Name(format!(
            "a bookmark name is 1 to {MAX_NAME_CHARS} characters, not {n}"
        )));
    }
    if let Some(c) = name.chars().find(|c| !(c.is_ascii_alphanumeric() || " -_.".contains(*c))) {
        return Err(BookmarkError::Name(format!(
            "a bookmark name holds letters, digits, space, `-`, `_` and `.` only, not {c:?}"
        )));
    }
    if name.trim() != name {
        return Err(BookmarkError::Name("a bookmark name neither starts nor ends with a space".into()));
    }
    Ok(())
}

/// The 1-based line of byte offset `at` in `text`.
fn line_of(text: &str, at: usize) -> usize {
    text.as_bytes()[..at.min(text.len())].iter().filter(|b| **b == b'\n').count() + 1
}

/// The bookmarks in `path` (none where the file does not exist); a file that is too large, not
/// TOML, not bookmarks, or holds a bad name, a non-finite number or too many, is an error naming
/// FILE:LINE.
pub fn load(path: &Path) -> Result<Vec<Bookmark>, BookmarkError> {
    let shown = path.display().to_string();
    let malformed = |line: Option<usize>, message: String| BookmarkError::Malformed {
        path: match line {
            Some(l) => format!("{shown}:{l}"),
            None => shown.clone(),
        },
        message,
    };
    // A regular file only, never through a link: a FIFO would hold the request, a link would
    // read a file outside the config's folder.
    use isowall_volume::io::regular::{open_regular_no_link, RegularError};
    let f = match open_regular_no_link(path) {
        Ok((f, _)) => f,
        Err(RegularError::Io(e)) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(malformed(None, e.to_string())),
    };
    let mut bytes = Vec::new();
    f.take(MAX_FILE_BYTES + 1).read_to_end(&mut bytes).map_err(|e| malformed(None, e.to_string()))?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(malformed(None, format!("larger than {MAX_FILE_BYTES} bytes")));
    }
    let text = String::from_utf8(bytes).map_err(|e| malformed(None, format!("not UTF-8: {e}")))?;
    let file: File = toml::from_str(&text).map_err(|e| {
        let line = e.span().map(|s| line_of(&text, s.start));
        malformed(line, e.message().to_string())
    })?;
    if file.bookmark.len() > MAX_BOOKMARKS {
        return Err(malformed(None, format!("{} bookmarks, more than {MAX_BOOKMARKS}", file.bookmark.len())));
    }
    for (i, b) in file.bookmark.iter().enumerate() {
        // The line of its name, to point at it.
        let at = text.match_indices("name").map(|(p, _)| p).nth(i);
        let line = at.map(|p| line_of(&text, p));
        check_name(&b.name).map_err(|e| malformed(line, e.to_string()))?;
        let numbers = b.eye.iter().chain(&b.target).chain(&b.up).chain(std::iter::once(&b.fov_y));
        if numbers.clone().any(|x| !x.is_finite()) {
            return Err(malformed(line, format!("bookmark `{}` holds a number that is not finite", b.name)));
        }
        if file.bookmark[..i].iter().any(|o| o.name == b.name) {
            return Err(malformed(line, format!("bookmark `{}` twice", b.name)));
        }
    }
    Ok(file.bookmark)
}

/// Writes `bookmarks` to `path` atomically: a temporary file beside it, synced, renamed over it.
pub fn store(path: &Path, bookmarks: &[Bookmark]) -> Result<(), BookmarkError> {
    let err = |error| BookmarkError::Write { path: path.display().to_string(), error };
    let file = File { bookmark: bookmarks.to_vec() };
    let text = toml::to_string_pretty(&file)
        .map_err(|e| err(std::io::Error::new(std::io::ErrorKind::InvalidData, e.to_string())))?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    let write = || -> std::io::Result<()> {
        use std::io::Write;
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(b"# Camera bookmarks of the isowall console (saved and deleted from its page).\n")?;
        f.write_all(text.as_bytes())?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    };
    write().map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        err(e)
    })
}

/// `bookmark` saved into `path`'s bookmarks (replacing one of the same name).
pub fn save(path: &Path, bookmark: Bookmark) -> Result<Vec<Bookmark>, BookmarkError> {
    check_name(&bookmark.name)?;
    let mut all = load(path)?;
    match all.iter().position(|b| b.name == bookmark.name) {
        Some(i) => all[i] = bookmark,
        None if all.len() >= MAX_BOOKMARKS => return Err(BookmarkError::Full),
        None => all.push(bookmark),
    }
    store(path, &all)?;
    Ok(all)
}

/// The bookmark named `name` deleted from `path`.
pub fn delete(path: &Path, name: &str) -> Result<Vec<Bookmark>, BookmarkError> {
    check_name(name)?;
    let mut all = load(path)?;
    let before = all.len();
    all.retain(|b| b.name != name);
    if all.len() == before {
        return Err(BookmarkError::Unknown(name.to_string()));
    }
    store(path, &all)?;
    Ok(all)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mark(name: &str, x: f64) -> Bookmark {
        Bookmark { name: name.into(), eye: [x, 2.0, 3.0], target: [0.0; 3], up: [0.0, 0.0, 1.0], fov_y: 40.0 }
    }

    #[test]
    fn saved_recalled_replaced_deleted_through_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = path_for(&dir.path().join("wall.toml"));
        assert_eq!(path.file_name().unwrap(), "wall.bookmarks.toml");
        assert_eq!(load(&path).unwrap(), vec![], "no file: no bookmarks");
        save(&path, mark("front", 1.0)).unwrap();
        save(&path, mark("side view_2.b", 2.0)).unwrap();
        let all = save(&path, mark("front", 5.0)).unwrap();
        assert_eq!(all, vec![mark("front", 5.0), mark("side view_2.b", 2.0)]);
        assert_eq!(load(&path).unwrap(), all, "what was written reads back");
        let left: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into())
            .collect();
        assert_eq!(left, vec!["wall.bookmarks.toml".to_string()], "no temporary file left");
        assert_eq!(delete(&path, "front").unwrap(), vec![mark("side view_2.b", 2.0)]);
        assert!(matches!(delete(&path, "front"), Err(BookmarkError::Unknown(_))));
        for bad in ["", " x", "a/b", "<script>", &"n".repeat(MAX_NAME_CHARS + 1), "é"] {
            assert!(matches!(save(&path, mark(bad, 0.0)), Err(BookmarkError::Name(_))), "{bad:?}");
        }
        for i in 1..MAX_BOOKMARKS {
            save(&path, mark(&format!("b{i}"), 0.0)).unwrap();
        }
        assert!(matches!(save(&path, mark("one too many", 0.0)), Err(BookmarkError::Full)));
        assert_eq!(load(&path).unwrap().len(), MAX_BOOKMARKS);
    }

    #[test]
    fn a_malformed_file_is_named_at_its_line_and_not_overwritten() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.bookmarks.toml");
        let text = "[[bookmark]]\nname = \"a\"\neye = [1, 2, 3]\ntarget = [0, 0, 0]\nup = [0, 0, 1]\nfov_y = \"wide\"\n";
        std::fs::write(&path, text).unwrap();
        let e = load(&path).unwrap_err().to_string();
        assert!(e.starts_with(&format!("{}:6: ", path.display())), "{e}");
        let e = save(&path, mark("b", 0.0)).unwrap_err().to_string();
        assert!(e.contains(":6: "), "{e}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), text, "left as it was");
        let bad_name = "[[bookmark]]\nname = \"ok\"\neye = [1, 2, 3]\ntarget = [0, 0, 0]\nup = [0, 0, 1]\nfov_y = 40\n\n[[bookmark]]\nname = \"a<b\"\neye = [1, 2, 3]\ntarget = [0, 0, 0]\nup = [0, 0, 1]\nfov_y = 40\n";
        std::fs::write(&path, bad_name).unwrap();
        let e = load(&path).unwrap_err().to_string();
        assert!(e.contains(":9: ") && e.contains("letters, digits"), "{e}");
        std::fs::write(&path, vec![b'#'; MAX_FILE_BYTES as usize + 1]).unwrap();
        assert!(load(&path).unwrap_err().to_string().contains("larger than"));
    }

    #[test]
    fn a_fifo_or_a_link_is_refused_at_once_and_not_written_over() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.bookmarks.toml");
        // A FIFO nobody writes: a plain open would wait for a writer forever.
        assert!(std::process::Command::new("mkfifo").arg(&path).status().unwrap().success());
        let e = load(&path).unwrap_err().to_string();
        assert!(e.contains("a FIFO (named pipe), not a regular file"), "{e}");
        assert!(save(&path, mark("b", 0.0)).is_err(), "not replaced by a save");
        std::fs::remove_file(&path).unwrap();
        // A link to a file outside the folder.
        let outside = tempfile::tempdir().unwrap();
        let target = outside.path().join("other.toml");
        std::fs::write(&target, "[[bookmark]]\nname = \"x\"\n").unwrap();
        std::os::unix::fs::symlink(&target, &path).unwrap();
        let e = load(&path).unwrap_err().to_string();
        assert!(e.contains("symbolic link") && !e.contains("\"x\""), "{e}");
        assert!(save(&path, mark("b", 0.0)).is_err());
        assert!(std::fs::symlink_metadata(&path).unwrap().file_type().is_symlink(), "left as it was");
    }
}
