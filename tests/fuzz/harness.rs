//! What the fuzz targets run, shared (by `#[path]`) between the cargo-fuzz crate
//! (`tests/fuzz/fuzz_targets/*.rs`, libFuzzer on nightly) and the replay test of the normal suite
//! (`tests/tests/fuzz_corpus.rs`, stable), so both exercise exactly the same code.
//!
//! Each function takes arbitrary bytes, drives one parser, and checks what must hold whatever the
//! bytes: no panic, errors that say something, and a few invariants (bounded buffering, round
//! trips, sane results). A violated invariant panics, which is what a fuzzer reports. Each returns
//! a one-line [`Outcome`]: `Ok` with what was accepted, `Err` with the error's message.

#![allow(dead_code)]

use isowall_model::codec::{self, Decoder, HEADER_LEN};
use isowall_model::config::WallConfig;
use isowall_model::messages::{Message, Role};
use isowall_model::node_machine::{NodeMachine, NodeOutput};
use isowall_model::wire::{FrameSpec, FrameState};
use isowall_volume::VolumeError;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// What one input did: `Ok(summary)` when accepted, `Err(message)` when refused.
pub type Outcome = Result<String, String>;

/// The decoder's frame limit in the fuzz target: small, so that oversized frames are easy to hit.
pub const DECODE_LIMIT: usize = 4096;

/// `decode_message`: the first byte chooses how the rest is cut into `push`es (all at once, byte
/// by byte, 7 bytes, or 1..=64 bytes); the rest is a stream of frames for a [`Decoder`] with
/// [`DECODE_LIMIT`], and also one frame body for [`codec::decode`]. Decoded messages drive a
/// daemon's [`NodeMachine`] (any order of any messages is fine for it: it refuses, never panics).
pub fn decode_message(data: &[u8]) -> Outcome {
    let Some((&ctl, bytes)) = data.split_first() else {
        return Err("empty input".into());
    };
    let chunk = match ctl % 4 {
        0 => bytes.len().max(1),
        1 => 1,
        2 => 7,
        _ => 1 + (ctl as usize / 4) % 64,
    };

    // The whole input as one frame body.
    let single = match codec::decode(bytes) {
        Ok(msg) => {
            // What decodes encodes again, and that encoding is stable: decode(encode(m)) encodes
            // to the same bytes (m itself may differ from the input's bytes: NaN payloads).
            let once = codec::encode(&msg).expect("a decoded message encodes");
            let again = codec::decode(&once).expect("an encoded message decodes");
            assert_eq!(codec::encode(&again).expect("encodes"), once, "{} does not round-trip", msg.kind());
            if let Message::Snapshot { tiles } = &msg {
                for t in tiles {
                    let _ = t.validate();
                }
            }
            let _ = codec::check_hello(&msg, Role::Controller);
            let _ = codec::check_hello(&msg, Role::Daemon);
            Some(msg.kind())
        }
        Err(e) => {
            assert!(!e.to_string().is_empty());
            None
        }
    };

    // The input as a stream, cut as `ctl` says, and all at once: the same messages either way.
    let (cut, cut_err) = decode_stream(bytes, chunk);
    let (whole, whole_err) = decode_stream(bytes, bytes.len().max(1));
    assert_eq!(cut, whole, "messages depend on how the stream is cut");
    assert_eq!(cut_err.is_some(), whole_err.is_some(), "errors depend on how the stream is cut");

    // The daemon's frame machine on what arrived, as `isowalld run` would drive it.
    let mut machine = NodeMachine::new("node0", vec!["t00".into()]);
    let mut refused = None;
    let mut t = Duration::ZERO;
    for body in &cut {
        t += Duration::from_millis(1);
        let msg = codec::decode(body).expect("decoded before");
        match machine.handle(t, msg) {
            Ok(outputs) => drive(&mut machine, t, outputs),
            Err(e) => {
                let text = e.to_string();
                assert!(text.contains("protocol violation"), "{text}");
                refused = Some(text);
                break;
            }
        }
    }
    let summary = format!(
        "single frame: {}; stream: {} message(s), {}{}",
        single.unwrap_or("malformed"),
        cut.len(),
        cut_err.as_deref().unwrap_or("no error"),
        refused.map(|r| format!("; daemon: {r}")).unwrap_or_default()
    );
    match cut_err {
        Some(e) => Err(format!("{e} ({summary})")),
        None => Ok(summary),
    }
}

/// Feeds `bytes` to a decoder `chunk` bytes at a time; returns the bodies of the decoded messages
/// (encoded again, to compare without float equality) and the first error.
fn decode_stream(bytes: &[u8], chunk: usize) -> (Vec<Vec<u8>>, Option<String>) {
    let mut d = Decoder::new(DECODE_LIMIT);
    let mut out = Vec::new();
    for piece in bytes.chunks(chunk) {
        d.push(piece);
        loop {
            match d.next() {
                Ok(Some(m)) => out.push(codec::encode(&m).expect("a decoded message encodes")),
                Ok(None) => break,
                Err(e) => {
                    let text = e.to_string();
                    assert!(!text.is_empty());
                    assert!(d.is_broken(), "an error breaks the decoder");
                    assert_eq!(d.buffered(), 0, "a broken decoder keeps no bytes");
                    assert!(d.next().is_err(), "a broken decoder stays broken");
                    return (out, Some(text));
                }
            }
        }
        // What waits is less than one frame: its header is within the limit.
        assert!(d.buffered() < HEADER_LEN + DECODE_LIMIT, "{} bytes buffered", d.buffered());
    }
    match d.finish() {
        Ok(()) => (out, None),
        Err(e) => (out, Some(e.to_string())),
    }
}

/// Carries out a daemon machine's outputs as if rendering and presenting took no time.
fn drive(machine: &mut NodeMachine, t: Duration, outputs: Vec<NodeOutput>) {
    let mut queue: std::collections::VecDeque<NodeOutput> = outputs.into();
    while let Some(out) = queue.pop_front() {
        match out {
            NodeOutput::Render { state, .. } => {
                assert!(FrameSpec::try_from(&state).is_ok(), "the machine renders only valid frames");
                queue.extend(machine.render_done(t, state.frame_id, Duration::from_micros(10)));
            }
            NodeOutput::Present { frame_id, .. } => queue.extend(machine.presented(t, frame_id, t)),
            NodeOutput::Send(_)
            | NodeOutput::LateSwap { .. }
            | NodeOutput::SnapshotWanted
            | NodeOutput::ThumbnailWanted { .. }
            | NodeOutput::Closed { .. }
            | NodeOutput::Restart { .. }
            | NodeOutput::Identify { .. }
            | NodeOutput::Bricks { .. }
            | NodeOutput::LoadBrick { .. }
            | NodeOutput::Split { .. } => {}
        }
    }
}

/// The config's name in messages of `parse_config`.
pub const CONFIG_PATH: &str = "fuzz/wall.toml";

/// `parse_config`: the bytes as text (invalid UTF-8 replaced) through [`WallConfig::parse`]. A
/// refused config has problems, each with a message, at positions inside the text; an accepted
/// one gives every tile a view inside the wall image and frame states the daemon accepts.
pub fn parse_config(data: &[u8]) -> Outcome {
    let text = String::from_utf8_lossy(data);
    let lines = text.matches('\n').count() + 1;
    match WallConfig::parse(&text, Path::new(CONFIG_PATH)) {
        Err(e) => {
            assert!(!e.problems.is_empty(), "a refused config names a problem");
            for p in &e.problems {
                assert!(!p.message.trim().is_empty(), "an empty problem");
                if let Some(l) = p.line {
                    assert!(l >= 1 && l <= lines, "problem at line {l} of {lines}: {}", p.message);
                }
            }
            let shown = e.to_string();
            assert!(shown.lines().all(|l| l.starts_with(CONFIG_PATH)), "{shown}");
            Err(shown)
        }
        Ok(c) => {
            let (w, h) = c.wall_size();
            let _ = c.summary();
            let (box_min, box_max) = (glam::DVec3::ZERO, glam::DVec3::new(47.0, 47.0, 23.0));
            let camera = c.camera_for(box_min, box_max);
            let settings = c.render_settings(c.volume.iso.unwrap_or(0.5));
            let state = FrameState::new(1, &camera, &settings, 1);
            // A config whose camera is unusable still parses; the daemon refuses its frames.
            let frames_ok = FrameSpec::try_from(&state).is_ok();
            for t in &c.tiles {
                let v = c.tile_view(camera, &t.name).expect("a configured tile has a view");
                let win = v.rect;
                assert!(
                    win.x as u64 + win.width as u64 <= w as u64
                        && win.y as u64 + win.height as u64 <= h as u64,
                    "tile {} at {win:?} outside the {w}x{h} wall",
                    t.name
                );
            }
            for n in &c.nodes {
                let _ = c.tiles_of(&n.name);
                let _ = resolve_quietly(&n.address);
            }
            let _ = (c.cert_dir(), c.volume_source(), c.env_source());
            Ok(format!(
                "{w}x{h} wall, {} tiles, {} nodes, frames {}",
                c.tiles.len(),
                c.nodes.len(),
                if frames_ok { "valid" } else { "refused" }
            ))
        }
    }
}

/// Parses a node address the way the daemon would, without a DNS look-up (only `IP:PORT`).
fn resolve_quietly(address: &str) -> Option<std::net::SocketAddr> {
    address.parse().ok()
}

/// The file extensions `read_volume` chooses from, by its first byte.
pub const VOLUME_EXTS: [&str; 7] = ["nrrd", "nhdr", "mha", "mhd", "nii", "nii.gz", "hdr"];
/// The companion file a detached header may name (`.nhdr`, `.mhd`); a `.hdr`'s is `vol.img`.
pub const DATA_FILE: &str = "data.raw";

/// Builds a `read_volume` input: the extension's index, then the main file's length (`u32`
/// little-endian), the main file, and the companion file.
pub fn volume_input(ext: &str, main: &[u8], companion: &[u8]) -> Vec<u8> {
    let sel = VOLUME_EXTS.iter().position(|e| *e == ext).expect("a known extension") as u8;
    let mut v = vec![sel];
    v.extend((main.len() as u32).to_le_bytes());
    v.extend(main);
    v.extend(companion);
    v
}

/// `read_volume`: the first byte chooses the extension of `dir/vol.EXT` ([`VOLUME_EXTS`]), the
/// next four the main file's length (the rest of the input when it claims more), and what
/// follows the main file is the companion file (`dir/data.raw`, or `dir/vol.img` for `.hdr`).
/// Both are written and the volume read with `isowall_volume::io::load`, as `isowalld` does
/// (the readers read files: there is no in-memory API). An accepted volume must be consistent;
/// an error must be typed and name the file.
///
/// Inputs that mention `/dev/`, `/proc/` or `/sys/` are skipped: a header may name any data file,
/// and a fuzzer must not read a device (a terminal or a pipe would block it).
pub fn read_volume(dir: &Path, data: &[u8]) -> Outcome {
    if [&b"/dev/"[..], b"/proc/", b"/sys/"].iter().any(|d| data.windows(d.len()).any(|w| w == *d)) {
        return Err("skipped: names a device or kernel file".into());
    }
    let Some((&sel, rest)) = data.split_first() else {
        return Err("empty input".into());
    };
    let ext = VOLUME_EXTS[sel as usize % VOLUME_EXTS.len()];
    let (main, companion) = if rest.len() >= 4 {
        let n = u32::from_le_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
        rest[4..].split_at(n.min(rest.len() - 4))
    } else {
        (rest, &[][..])
    };
    let path = dir.join(format!("vol.{ext}"));
    let companion_path = if ext == "hdr" { dir.join("vol.img") } else { dir.join(DATA_FILE) };
    for stale in ["vol.img", DATA_FILE] {
        let _ = std::fs::remove_file(dir.join(stale));
    }
    std::fs::write(&path, main).expect("write the volume file");
    std::fs::write(&companion_path, companion).expect("write the companion file");
    let result = isowall_volume::io::load(&path, None);
    let _ = std::fs::remove_file(&path);
    match result {
        Ok(v) => {
            let [nx, ny, nz] = v.dims();
            assert_eq!(v.data().len(), nx * ny * nz, "{ext}: data does not match the dims");
            assert!(v.data().iter().all(|x| x.is_finite()), "{ext}: a non-finite voxel was accepted");
            let s = v.spacing();
            assert!(s.is_finite() && s.min_element() > 0.0, "{ext}: spacing {s}");
            assert!(v.origin().is_finite(), "{ext}: origin {}", v.origin());
            Ok(format!("{ext}: {nx}x{ny}x{nz}"))
        }
        Err(e) => {
            let text = e.to_string();
            assert!(!text.trim().is_empty(), "{ext}: an empty error");
            match &e {
                VolumeError::Format { path: p, what } => {
                    assert_eq!(p, &path, "{ext}: a format error names another file: {text}");
                    assert!(!what.trim().is_empty(), "{ext}: {text}");
                }
                VolumeError::NonFinite { path: p, .. } => {
                    assert_eq!(p, &path, "{ext}: {text}")
                }
                VolumeError::Io { .. } | VolumeError::Invalid(_) | VolumeError::Source(_) => {}
            }
            Err(text)
        }
    }
}

/// A scratch folder for `read_volume`, one per process.
pub fn scratch_dir() -> PathBuf {
    static DIR: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("isowall-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&d).expect("create the scratch folder");
        d
    })
    .clone()
}
