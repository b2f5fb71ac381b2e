//! The fuzz targets' code on stable, in the normal suite: every file of the committed corpus
//! (`tests/fuzz/corpus/<target>/`) goes through the very harness the cargo-fuzz targets run (`tests/fuzz/harness.rs`, shared by `#[path]`),
//! then a seeded mini-fuzzer mutates the valid examples a few thousand times per target. No input
//! may panic (a panic is caught and reported with the input); errors must be typed and say
//! something; the harness checks its invariants (bounded buffering, round trips, sane volumes).
//!
//! The corpus is made by this file's generator, deterministically:
//! `cargo test -p isowall-e2e --test fuzz_corpus -- --ignored write_corpus` rewrites the
//! `valid-*`, `bad-*` and `mut-*` files (inputs libFuzzer adds under other names stay).
//! `valid-*` inputs must be accepted and `bad-*` refused.

#[path = "../fuzz/harness.rs"]
mod harness;

use harness::Outcome;
use isowall_model::camera::Camera;
use isowall_model::codec;
use isowall_model::messages::{Message, NodeInfo, Role, TileImage, PROTOCOL_VERSION};
use isowall_model::render_state::RenderSettings;
use isowall_model::wire::FrameState;
use std::io::Write;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const TARGETS: [&str; 3] = ["decode_message", "parse_config", "read_volume"];

fn corpus_dir(target: &str) -> PathBuf {
    isowall_e2e::repo_root().join("tests/fuzz/corpus").join(target)
}

/// Runs `target`'s harness on `data`; `Err(panic message)` if it panicked.
fn run(target: &str, scratch: &Path, data: &[u8]) -> Result<Outcome, String> {
    catch_unwind(AssertUnwindSafe(|| match target {
        "decode_message" => harness::decode_message(data),
        "parse_config" => harness::parse_config(data),
        "read_volume" => harness::read_volume(scratch, data),
        _ => unreachable!("unknown target {target}"),
    }))
    .map_err(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "a panic without a message".into())
    })
}

// ---------------------------------------------------------------------------------------------
// The replay.

#[test]
fn every_committed_corpus_input_runs_without_a_panic() {
    let scratch = tempfile::tempdir().unwrap();
    let mut total_bytes = 0u64;
    let mut failures = Vec::new();
    for target in TARGETS {
        let dir = corpus_dir(target);
        let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        assert!(files.len() >= 20, "{target}: only {} corpus files in {}", files.len(), dir.display());
        let (mut ok, mut err) = (0, 0);
        for f in &files {
            let data = std::fs::read(f).unwrap();
            total_bytes += data.len() as u64;
            let name = f.file_name().unwrap().to_string_lossy().into_owned();
            match run(target, scratch.path(), &data) {
                Err(panic) => failures.push(format!("{target}/{name}: PANIC {panic}")),
                Ok(Ok(summary)) => {
                    ok += 1;
                    if name.starts_with("bad-") {
                        failures.push(format!("{target}/{name}: accepted ({summary}), must be refused"));
                    }
                }
                Ok(Err(e)) => {
                    err += 1;
                    if name.starts_with("valid-") {
                        failures.push(format!("{target}/{name}: refused, must be accepted: {e}"));
                    }
                    if name.starts_with("bad-") {
                        eprintln!("{target}/{name}: {}", e.lines().next().unwrap_or(""));
                    }
                }
            }
        }
        eprintln!("{target}: {} inputs replayed, {ok} accepted, {err} refused", files.len());
        assert!(ok > 0 && err > 0, "{target}: the corpus must hold accepted and refused inputs");
    }
    assert!(
        failures.is_empty(),
        "{} corpus input(s) failed (regenerate with `-- --ignored write_corpus` if the formats changed \
         on purpose):\n{}",
        failures.len(),
        failures.join("\n")
    );
    assert!(total_bytes < 1 << 20, "the corpus is {total_bytes} bytes; keep it under 1 MiB");
}

// ---------------------------------------------------------------------------------------------
// The mini-fuzzer: seeded mutations of the valid examples.

/// xorshift64*: deterministic, no dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
    fn bytes(&mut self, n: usize) -> Vec<u8> {
        (0..n).map(|_| self.next() as u8).collect()
    }
}

const INTERESTING_U32: [u32; 10] = [0, 1, 3, 4, 127, 4095, 4096, 4097, 0x7fff_ffff, u32::MAX];
const INTERESTING_TOKENS: [&str; 14] = [
    "0",
    "-1",
    "1",
    "4294967295",
    "4294967296",
    "18446744073709551616",
    "1e309",
    "nan",
    "inf",
    "-0.0",
    "\"\"",
    "[]",
    "{}",
    "3.5",
];

/// One to four byte-level mutations (and, for text, token and line mutations) of `input`;
/// `other` is another seed to splice from.
fn mutate(rng: &mut Rng, input: &[u8], other: &[u8], text: bool) -> Vec<u8> {
    let mut v = input.to_vec();
    for _ in 0..1 + rng.below(4) {
        let len = v.len();
        match rng.below(if text { 11 } else { 8 }) {
            0 if len > 0 => {
                let i = rng.below(len);
                v[i] ^= 1 << rng.below(8);
            }
            1 if len > 0 => {
                let i = rng.below(len);
                v[i] = [0, 1, 0x7f, 0x80, 0xff, b'\n', b'"', b'='][rng.below(8)];
            }
            2 => {
                let i = rng.below(len + 1);
                let n = 1 + rng.below(8);
                let b = rng.bytes(n);
                v.splice(i..i, b);
            }
            3 if len > 0 => {
                let i = rng.below(len);
                let n = 1 + rng.below((len - i).min(32));
                v.drain(i..i + n);
            }
            4 if len > 0 => {
                let i = rng.below(len);
                let n = 1 + rng.below((len - i).min(64));
                let piece = v[i..i + n].to_vec();
                let at = rng.below(len + 1);
                v.splice(at..at, piece);
            }
            5 if len > 0 => v.truncate(rng.below(len)),
            6 if len >= 4 => {
                let i = rng.below(len - 3);
                let x = INTERESTING_U32[rng.below(INTERESTING_U32.len())];
                v[i..i + 4].copy_from_slice(&x.to_le_bytes());
            }
            7 if !other.is_empty() => {
                let i = rng.below(len + 1);
                let j = rng.below(other.len());
                v.truncate(i);
                v.extend_from_slice(&other[j..]);
            }
            8 => {
                // A number (or a whole value) replaced by an extreme token.
                let s = String::from_utf8_lossy(&v).into_owned();
                let starts: Vec<usize> = s
                    .char_indices()
                    .filter(|&(i, c)| {
                        c.is_ascii_digit() && (i == 0 || !s.as_bytes()[i - 1].is_ascii_alphanumeric())
                    })
                    .map(|(i, _)| i)
                    .collect();
                if let Some(&i) = starts.get(rng.below(starts.len())) {
                    let end = s[i..]
                        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '.'))
                        .map_or(s.len(), |e| i + e);
                    let tok = INTERESTING_TOKENS[rng.below(INTERESTING_TOKENS.len())];
                    v = format!("{}{tok}{}", &s[..i], &s[end..]).into_bytes();
                }
            }
            9 | 10 => {
                // A line deleted, duplicated or moved.
                let s = String::from_utf8_lossy(&v).into_owned();
                let mut lines: Vec<&str> = s.split('\n').collect();
                let n = lines.len();
                let (i, j) = (rng.below(n), rng.below(n));
                match rng.below(3) {
                    0 if n > 1 => {
                        lines.remove(i);
                    }
                    1 => {
                        let l = lines[i];
                        lines.insert(j, l);
                    }
                    _ => lines.swap(i, j),
                }
                v = lines.join("\n").into_bytes();
            }
            _ => {}
        }
    }
    v
}

/// Mutates a `read_volume` input: mostly the main file (a header is text), sometimes the
/// companion file or the extension.
fn mutate_volume(rng: &mut Rng, input: &[u8], other: &[u8]) -> Vec<u8> {
    let (sel, rest) = input.split_first().unwrap();
    let n = u32::from_le_bytes(rest[..4].try_into().unwrap()) as usize;
    let (main, companion) = rest[4..].split_at(n.min(rest.len() - 4));
    let other_main = other.get(5..).unwrap_or(&[]);
    let (mut sel, mut main, mut companion) = (*sel, main.to_vec(), companion.to_vec());
    match rng.below(10) {
        0 => sel = rng.next() as u8,
        1 => companion = mutate(rng, &companion, other_main, false),
        2 => return mutate(rng, input, other, false),
        _ => main = mutate(rng, &main, other_main, true),
    }
    let ext = harness::VOLUME_EXTS[sel as usize % harness::VOLUME_EXTS.len()];
    harness::volume_input(ext, &main, &companion)
}

/// Runs `iterations` mutants of `seeds` (within `budget`), collecting panics; saves each
/// panicking input under the system's temp folder and fails naming it.
fn mini_fuzz(target: &str, seed: u64, iterations: usize, budget: Duration) {
    let seeds: Vec<Vec<u8>> =
        generate(target).into_iter().filter(|(n, _)| n.starts_with("valid-")).map(|(_, d)| d).collect();
    assert!(!seeds.is_empty());
    let scratch = tempfile::tempdir().unwrap();
    let mut rng = Rng(seed);
    let start = Instant::now();
    let (mut ran, mut accepted) = (0usize, 0usize);
    let mut failures = Vec::new();
    while ran < iterations && start.elapsed() < budget {
        let a = &seeds[rng.below(seeds.len())];
        let b = &seeds[rng.below(seeds.len())];
        let input = match target {
            "read_volume" => mutate_volume(&mut rng, a, b),
            "parse_config" => mutate(&mut rng, a, b, true),
            _ => {
                // Keep the chunking byte; mutate the stream.
                let mut v = vec![if rng.below(4) == 0 { rng.next() as u8 } else { a[0] }];
                v.extend(mutate(&mut rng, &a[1..], &b[1..], false));
                v
            }
        };
        ran += 1;
        match run(target, scratch.path(), &input) {
            Ok(Ok(_)) => accepted += 1,
            Ok(Err(_)) => {}
            Err(panic) => {
                let dir = std::env::temp_dir().join("isowall-fuzz-failures");
                std::fs::create_dir_all(&dir).unwrap();
                let file = dir.join(format!("{target}-{seed:x}-{ran}"));
                std::fs::write(&file, &input).unwrap();
                failures.push(format!("{}: {panic}", file.display()));
            }
        }
    }
    eprintln!(
        "{target}: {ran} mutants in {:.1} s, {accepted} accepted, {} refused, {} panics",
        start.elapsed().as_secs_f64(),
        ran - accepted - failures.len(),
        failures.len()
    );
    assert!(
        failures.is_empty(),
        "{target}: inputs that panic (add them to the corpus once fixed):\n{}",
        failures.join("\n")
    );
    assert!(ran >= iterations.min(500), "{target}: only {ran} mutants ran in {budget:?}");
    assert!(
        accepted > 0 && accepted < ran,
        "{target}: {accepted} of {ran} mutants accepted: the mutator misses"
    );
}

#[test]
fn mutants_of_valid_messages_never_panic_the_decoder() {
    mini_fuzz("decode_message", 0x1505_0001, 40_000, Duration::from_secs(5));
}

#[test]
fn mutants_of_valid_configs_never_panic_the_parser() {
    mini_fuzz("parse_config", 0x1505_0002, 20_000, Duration::from_secs(5));
}

#[test]
fn mutants_of_valid_volume_files_never_panic_the_readers() {
    mini_fuzz("read_volume", 0x1505_0003, 20_000, Duration::from_secs(5));
}

// ---------------------------------------------------------------------------------------------
// The corpus generator.

/// Writes the generated corpus (`valid-*`, `bad-*`, `mut-*`) into `tests/fuzz/corpus/`.
#[test]
#[ignore = "writes the committed corpus: run it on purpose"]
fn write_corpus() {
    for target in TARGETS {
        let dir = corpus_dir(target);
        std::fs::create_dir_all(&dir).unwrap();
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            if ["valid-", "bad-", "mut-"].iter().any(|pre| name.starts_with(pre)) {
                std::fs::remove_file(&p).unwrap();
            }
        }
        let files = generate(target);
        for (name, data) in &files {
            std::fs::write(dir.join(name), data).unwrap();
        }
        eprintln!("{target}: wrote {} files to {}", files.len(), dir.display());
    }
}

/// Every corpus file of `target`: the valid examples, hand-made bad ones and seeded mutants.
fn generate(target: &str) -> Vec<(String, Vec<u8>)> {
    let (mut files, text, ext_of): (Vec<(String, Vec<u8>)>, bool, &str) = match target {
        "decode_message" => (message_seeds(), false, "bin"),
        "parse_config" => (config_seeds(), true, "toml"),
        "read_volume" => (volume_seeds(), false, "bin"),
        _ => unreachable!(),
    };
    let valid: Vec<Vec<u8>> =
        files.iter().filter(|(n, _)| n.starts_with("valid-")).map(|(_, d)| d.clone()).collect();
    let mut rng = Rng(0xC0FF_EE00 ^ target.len() as u64);
    for i in 0..16 {
        let a = &valid[rng.below(valid.len())];
        let b = &valid[rng.below(valid.len())];
        let m = match target {
            "read_volume" => mutate_volume(&mut rng, a, b),
            _ if text => mutate(&mut rng, a, b, true),
            _ => {
                let mut v = vec![a[0]];
                v.extend(mutate(&mut rng, &a[1..], &b[1..], false));
                v
            }
        };
        files.push((format!("mut-{i:02}.{ext_of}"), m));
    }
    // Garbage: random bytes of a few lengths.
    for (i, n) in [0usize, 1, 5, 64, 700].into_iter().enumerate() {
        files.push((format!("mut-garbage-{i}.{ext_of}"), rng.bytes(n)));
    }
    files
}

fn camera() -> Camera {
    Camera {
        eye: glam::DVec3::new(60.0, -70.0, 45.0),
        target: glam::DVec3::splat(23.5),
        up: glam::DVec3::Z,
        fov_y_deg: 40.0,
    }
}

/// A `decode_message` input: the chunking byte, then the frames of `msgs`.
fn stream(ctl: u8, msgs: &[Message]) -> Vec<u8> {
    let mut v = vec![ctl];
    for m in msgs {
        v.extend(codec::frame(m).unwrap());
    }
    v
}

fn message_seeds() -> Vec<(String, Vec<u8>)> {
    let mut settings = RenderSettings::new(0.5);
    settings.ao.samples = 4;
    let state = |id: u64| Message::FrameState(FrameState::new(id, &camera(), &settings, 2));
    let all = vec![
        codec::hello("controller", Role::Controller),
        codec::hello("node0", Role::Daemon),
        state(1),
        Message::Ready { frame_id: 1, render_us: 16_667 },
        Message::Swap { frame_id: 1, present_at_us: None },
        Message::Presented { frame_id: 1, node_time_us: -42, waiting_from_us: -42 },
        Message::Ping { id: 7, t0_us: 123_456 },
        Message::Pong { id: 7, t0_us: 123_456, t1_us: 654_321, sent_us: 654_321, resident_bytes: 250 << 20 },
        Message::SnapshotRequest,
        Message::Snapshot {
            tiles: vec![TileImage {
                name: "t00".into(),
                width: 2,
                height: 2,
                frame_id: 1,
                rgb8: (0..12).collect(),
            }],
        },
        Message::Bye { reason: "done".into() },
        Message::NodeInfo(NodeInfo {
            version: "0.1.0".into(),
            adapter: "llvmpipe (LLVM 19.1.7, 256 bits)".into(),
            backend: "Vulkan".into(),
            driver: "llvmpipe".into(),
            driver_info: "Mesa 25.0.7".into(),
            present: "SCHED_FIFO 10".into(),
        }),
        Message::Restart { reason: "the operator's console asked".into() },
        Message::Identify { on: true },
    ];
    let mut out: Vec<(String, Vec<u8>)> = all
        .iter()
        .enumerate()
        .map(|(i, m)| {
            (format!("valid-{i:02}-{}.bin", m.kind().to_lowercase()), stream(0, std::slice::from_ref(m)))
        })
        .collect();
    let hello = codec::hello("controller", Role::Controller);
    let session = [
        hello.clone(),
        state(1),
        Message::Swap { frame_id: 1, present_at_us: None },
        Message::Ping { id: 1, t0_us: 10 },
        state(2),
        Message::Swap { frame_id: 2, present_at_us: None },
        Message::SnapshotRequest,
        Message::Restart { reason: "operator".into() },
        Message::Bye { reason: "done".into() },
    ];
    for ctl in [0u8, 1, 2, 3 + 4 * 12] {
        out.push((format!("valid-session-cut{}.bin", ctl % 4), stream(ctl, &session)));
    }
    // Well framed, refused by the daemon's machine (the outcome is still Ok: the stream is fine).
    let wrong_version =
        Message::Hello { version: PROTOCOL_VERSION + 98, name: "controller".into(), role: Role::Controller };
    out.push(("valid-wrong-version.bin".into(), stream(0, &[wrong_version])));
    out.push((
        "valid-swap-out-of-order.bin".into(),
        stream(0, &[hello.clone(), Message::Swap { frame_id: 5, present_at_us: None }]),
    ));
    out.push(("valid-frame-goes-back.bin".into(), stream(0, &[hello.clone(), state(3), state(2)])));
    out.push(("valid-second-hello.bin".into(), stream(0, &[hello.clone(), hello.clone()])));
    // Broken streams.
    let mut over = stream(0, std::slice::from_ref(&hello));
    over.extend(u32::MAX.to_le_bytes());
    out.push(("bad-length-past-limit.bin".into(), over));
    let mut just_over = vec![1u8];
    just_over.extend((harness::DECODE_LIMIT as u32 + 1).to_le_bytes());
    just_over.extend([0u8; 16]);
    out.push(("bad-length-limit-plus-one.bin".into(), just_over));
    let mut trunc = stream(0, &[hello.clone(), state(1)]);
    trunc.truncate(trunc.len() - 3);
    out.push(("bad-truncated-frame.bin".into(), trunc));
    out.push(("bad-truncated-length.bin".into(), vec![0, 9, 0]));
    let mut garbage = stream(0, std::slice::from_ref(&hello));
    garbage.extend([5, 0, 0, 0, 200, 1, 2, 3, 4]);
    out.push(("bad-undecodable-body.bin".into(), garbage));
    let mut trailing = vec![0u8];
    let mut body = codec::encode(&Message::Swap { frame_id: 1, present_at_us: None }).unwrap();
    body.extend([9, 9]);
    trailing.extend((body.len() as u32).to_le_bytes());
    trailing.extend(body);
    out.push(("bad-trailing-bytes.bin".into(), trailing));
    out.push(("bad-empty-frame.bin".into(), vec![0, 0, 0, 0, 0]));
    // A string that claims 2^40 bytes inside a small frame.
    let mut body = codec::encode(&Message::Bye { reason: String::new() }).unwrap();
    body.pop();
    body.push(253);
    body.extend((1u64 << 40).to_le_bytes());
    let mut claim = vec![0u8];
    claim.extend((body.len() as u32).to_le_bytes());
    claim.extend(body);
    out.push(("bad-string-claims-a-terabyte.bin".into(), claim));
    out
}

fn config_seeds() -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let examples = isowall_e2e::repo_root().join("wall-configs");
    let mut names: Vec<PathBuf> = std::fs::read_dir(&examples)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    names.sort();
    for p in names {
        let stem = p.file_stem().unwrap().to_string_lossy().into_owned();
        out.push((format!("valid-{stem}.toml"), std::fs::read(&p).unwrap()));
    }
    let base = "[wall]\nname = \"w\"\ndeadline_ms = 5000\nmessage_limit_bytes = 4096\n\n\
                [camera]\neye = [60.0, -70.0, 45.0]\ntarget = [23.5, 23.5, 23.5]\nup = [0, 0, 1]\nfov_y = 40.0\n\n\
                [volume]\nsource = \"ct.nrrd\"\niso = 300.0\n\n\
                [render]\nshading = \"lambert\"\nao_samples = 4\nao_radius = \"unbounded\"\nao_method = \"seed\"\nibl = \"rays\"\nenv = \"sky\"\nexposure = 0.8\n\n\
                [certificates]\ndir = \"keys\"\n\n\
                [[tiles]]\nname = \"a\"\nx = 0\ny = 0\nwidth = 16\nheight = 12\nbezel = [0, 2, 0, 0]\n\n\
                [[tiles]]\nname = \"b\"\nx = 20\ny = 0\nwidth = 16\nheight = 12\nbezel = [2, 0, 0, 0]\n\n\
                [[nodes]]\nname = \"node0\"\naddress = \"127.0.0.1:7401\"\ntiles = [\"a\"]\n\n\
                [[nodes]]\nname = \"node1\"\naddress = \"[::1]:7402\"\ntiles = [\"b\"]\n";
    out.push(("valid-two-nodes.toml".into(), base.into()));
    out.push((
        "valid-raw-volume.toml".into(),
        base.replace("iso = 300.0", "iso = 300.0\ndims = [4, 4, 4]\ntype = \"int16\"\nspacing = [1, 1, 2]")
            .into(),
    ));
    let bad = [
        ("syntax", "[wall\nname = 1\n".to_string()),
        ("empty", String::new()),
        ("unknown-key", base.replace("deadline_ms = 5000", "deadline_ms = 5000\ncolour = 3")),
        ("unknown-table", format!("{base}\n[extra]\nx = 1\n")),
        ("missing-wall", base.replace("[wall]\nname = \"w\"\n", "")),
        ("unknown-tile", base.replace("tiles = [\"b\"]", "tiles = [\"zz\"]")),
        ("tile-twice", base.replace("name = \"b\"", "name = \"a\"")),
        ("limit-too-small", base.replace("message_limit_bytes = 4096", "message_limit_bytes = 10")),
        ("width-not-a-number", base.replace("width = 16", "width = \"wide\"")),
        ("width-overflows", base.replace("width = 16", "width = 4294967296")),
        ("negative-position", base.replace("x = 20", "x = -20")),
        ("fov-nan", base.replace("fov_y = 40.0", "fov_y = nan")),
        ("bad-enum", base.replace("ibl = \"rays\"", "ibl = \"sideways\"")),
        ("invalid-utf8", format!("{base}\n# \u{fffd}\u{fffd}\n[wall]\n")),
    ];
    for (name, text) in bad {
        out.push((format!("bad-{name}.toml"), text.into_bytes()));
    }
    // Invalid UTF-8 bytes (the harness replaces them).
    let mut bytes = base.as_bytes().to_vec();
    bytes.splice(7..7, [0xff, 0xfe, 0xc3]);
    out.push(("bad-invalid-bytes.toml".into(), bytes));
    out
}

fn gzip(b: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(b).unwrap();
    e.finish().unwrap()
}

fn zlib(b: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(b).unwrap();
    e.finish().unwrap()
}

/// A NIfTI-1 header of a 3x2x2 volume (`datatype`, `bitpix`), `vox_offset`, magic, byte order.
fn nifti_header(datatype: i16, bitpix: i16, vox_offset: f32, magic: &[u8; 4], big: bool) -> Vec<u8> {
    let mut h = vec![0u8; 348];
    let mut put = |o: usize, b: &[u8]| {
        let mut b = b.to_vec();
        if big {
            b.reverse();
        }
        h[o..o + b.len()].copy_from_slice(&b);
    };
    put(0, &348i32.to_le_bytes());
    for (i, d) in [3i16, 3, 2, 2, 1, 1, 1, 1].iter().enumerate() {
        put(40 + 2 * i, &d.to_le_bytes());
    }
    put(70, &datatype.to_le_bytes());
    put(72, &bitpix.to_le_bytes());
    for (i, p) in [1.0f32, 0.5, 2.0, -1.25, 1.0, 0.0, 0.0, 0.0].iter().enumerate() {
        put(76 + 4 * i, &p.to_le_bytes());
    }
    put(108, &vox_offset.to_le_bytes());
    put(112, &1.0f32.to_le_bytes());
    put(252, &1i16.to_le_bytes()); // qform_code
    for (i, q) in [-3.0f32, 4.5, 0.0].iter().enumerate() {
        put(268 + 4 * i, &q.to_le_bytes());
    }
    h[344..348].copy_from_slice(magic);
    h
}

fn volume_seeds() -> Vec<(String, Vec<u8>)> {
    use harness::volume_input as input;
    // 3x2x2 voxels of each type.
    let u8s: Vec<u8> = (0..12).map(|i| i * 20).collect();
    let i16le: Vec<u8> = (0..12i16).flat_map(|i| (i * 100 - 300).to_le_bytes()).collect();
    let f32le: Vec<u8> = (0..12).flat_map(|i| (i as f32 * 0.25).to_le_bytes()).collect();
    let f32be: Vec<u8> = (0..12).flat_map(|i| (i as f32 * 0.25).to_be_bytes()).collect();
    let nrrd = |extra: &str, ty: &str, enc: &str| {
        format!("NRRD0004\n# a comment\ntype: {ty}\ndimension: 3\nsizes: 3 2 2\n{extra}encoding: {enc}\n")
    };
    let mha = |extra: &str, ty: &str, data: &str| {
        format!(
            "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n{extra}\
             ElementSpacing = 0.5 1 2\nOffset = 1 2 3\nDimSize = 3 2 2\nElementType = {ty}\nElementDataFile = {data}\n"
        )
    };
    let cat = |a: String, b: &[u8]| [a.as_bytes(), b].concat();
    let mut out = vec![
        (
            "valid-raw-short.nrrd",
            input("nrrd", &cat(nrrd("endian: little\nspacings: 0.5 1 2\n", "short", "raw") + "\n", &i16le), &[]),
        ),
        (
            "valid-gzip-float.nrrd",
            input(
                "nrrd",
                &cat(
                    nrrd(
                        "endian: little\nspace: right-anterior-superior\nspace directions: (1,0,0) (0,-1,0) (0,0,2)\nspace origin: (1,2,3)\n",
                        "float",
                        "gzip",
                    ) + "\n",
                    &gzip(&f32le),
                ),
                &[],
            ),
        ),
        (
            "valid-detached.nhdr",
            input("nhdr", nrrd(&format!("data file: {}\n", harness::DATA_FILE), "uchar", "raw").as_bytes(), &u8s),
        ),
        ("valid-local-short.mha", input("mha", &cat(mha("", "MET_SHORT", "LOCAL"), &i16le), &[])),
        (
            "valid-zlib-float.mha",
            input("mha", &cat(mha("CompressedData = True\n", "MET_FLOAT", "LOCAL"), &zlib(&f32le)), &[]),
        ),
        ("valid-detached.mhd", input("mhd", mha("", "MET_UCHAR", harness::DATA_FILE).as_bytes(), &u8s)),
        ("valid-int16.nii", input("nii", &[nifti_header(4, 16, 352.0, b"n+1\0", false), vec![0; 4], i16le.clone()].concat(), &[])),
        ("valid-float-big-endian.nii", input("nii", &[nifti_header(16, 32, 352.0, b"n+1\0", true), vec![0; 4], f32be].concat(), &[])),
        (
            "valid-uint8.nii.gz",
            input("nii.gz", &gzip(&[nifti_header(2, 8, 352.0, b"n+1\0", false), vec![0; 4], u8s.clone()].concat()), &[]),
        ),
        ("valid-pair.hdr", input("hdr", &nifti_header(2, 8, 0.0, b"ni1\0", false), &u8s)),
    ];
    let mut nan = f32le.clone();
    nan[20..24].copy_from_slice(&f32::NAN.to_le_bytes());
    let short = &i16le[..i16le.len() - 1];
    out.extend([
        (
            "bad-truncated.nrrd",
            input("nrrd", &cat(nrrd("endian: little\n", "short", "raw") + "\n", short), &[]),
        ),
        (
            "bad-extra-data.nrrd",
            input(
                "nrrd",
                &cat(nrrd("endian: little\n", "short", "raw") + "\n", &[&i16le[..], &[1, 2]].concat()),
                &[],
            ),
        ),
        ("bad-nan.nrrd", input("nrrd", &cat(nrrd("endian: little\n", "float", "raw") + "\n", &nan), &[])),
        (
            "bad-claims-a-gigavoxel.nrrd",
            input(
                "nrrd",
                &cat(
                    nrrd("", "uchar", "gzip").replace("sizes: 3 2 2", "sizes: 1024 1024 1024") + "\n",
                    &gzip(&u8s),
                ),
                &[],
            ),
        ),
        (
            "bad-overflowing-sizes.nrrd",
            input(
                "nrrd",
                &cat(
                    nrrd("", "uchar", "raw").replace("sizes: 3 2 2", "sizes: 18446744073709551615 2 2")
                        + "\n",
                    &u8s,
                ),
                &[],
            ),
        ),
        (
            "bad-missing-data-file.nhdr",
            input("nhdr", nrrd("data file: missing.raw\n", "uchar", "raw").as_bytes(), &[]),
        ),
        ("bad-no-blank-line.nrrd", input("nrrd", nrrd("", "uchar", "raw").as_bytes(), &[])),
        (
            "bad-2d.mha",
            input("mha", &cat(mha("", "MET_UCHAR", "LOCAL").replace("NDims = 3", "NDims = 2"), &u8s), &[]),
        ),
        ("bad-list.mhd", input("mhd", mha("", "MET_UCHAR", "LIST").as_bytes(), &u8s)),
        (
            "bad-zlib-corrupt.mha",
            input(
                "mha",
                &cat(mha("CompressedData = True\n", "MET_UCHAR", "LOCAL"), &[0x78, 0x9c, 1, 2, 3, 4]),
                &[],
            ),
        ),
        (
            "bad-magic.nii",
            input(
                "nii",
                &[nifti_header(2, 8, 352.0, b"n+2\0", false), vec![0; 4], u8s.clone()].concat(),
                &[],
            ),
        ),
        (
            "bad-vox-offset.nii",
            input("nii", &[nifti_header(2, 8, 100.0, b"n+1\0", false), u8s.clone()].concat(), &[]),
        ),
        ("bad-truncated-header.nii", input("nii", &nifti_header(2, 8, 352.0, b"n+1\0", false)[..200], &[])),
        (
            "bad-bomb.nii.gz",
            input(
                "nii.gz",
                &gzip(&[nifti_header(2, 8, 352.0, b"n+1\0", false), vec![0; 200_000]].concat()),
                &[],
            ),
        ),
        ("bad-pair-without-image.hdr", input("hdr", &nifti_header(2, 8, 0.0, b"ni1\0", false), &[])),
    ]);
    out.into_iter().map(|(n, d)| (n.to_string(), d)).collect()
}
