//! Hostile files and configs against the real binaries: volume bombs (gzip NRRD, NIfTI and
//! MetaImage claiming 1024^3 voxels from about 1 MB), a FIFO or a device as a volume's data, a
//! detached header pointing at /etc/passwd or above its folder, `keygen` over an existing CA,
//! names keygen could not write, key files open to others, certificates that end soon or have
//! ended, and configs that cannot work.
//!
//! Memory is bounded twice: the child's address space is capped (`ulimit -v`), so a reader that
//! allocated gigabytes fails the test instead of passing it, and its peak resident set (VmHWM of
//! /proc/PID/status, sampled while it runs) is reported and checked. Every child is killed after
//! a timeout, so a reader that blocks fails rather than hangs the suite.

use isowall_e2e::{bin, in_ci, run_in};
use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// What a bounded child did.
struct Bounded {
    /// `None`: killed at the timeout.
    code: Option<i32>,
    stderr: String,
    /// The largest VmHWM seen, KiB.
    peak_kib: u64,
    elapsed: Duration,
}

/// Runs binary `name` with `args` in `dir`, its address space capped at `cap_mib` MiB (0: no
/// cap), killed after `timeout`.
fn run_bounded(dir: &Path, name: &str, args: &[&str], cap_mib: u64, timeout: Duration) -> Bounded {
    let err_path = dir.join(format!("{name}-{}.stderr", std::process::id()));
    let err = std::fs::File::create(&err_path).unwrap();
    let cap = if cap_mib == 0 { "unlimited".to_string() } else { (cap_mib * 1024).to_string() };
    // The binaries are built on first use: that is not the command's time.
    let exe = bin(name);
    let start = Instant::now();
    let mut child = Command::new("sh")
        .args(["-c", "ulimit -v \"$1\" && shift && exec \"$@\"", "sh", &cap])
        .arg(exe)
        .args(args)
        .current_dir(dir)
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(err)
        .spawn()
        .unwrap();
    let status_path = format!("/proc/{}/status", child.id());
    let mut peak_kib = 0;
    let code = loop {
        if let Ok(s) = std::fs::read_to_string(&status_path) {
            if let Some(kib) = s
                .lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<u64>().ok())
            {
                peak_kib = peak_kib.max(kib);
            }
        }
        if let Some(status) = child.try_wait().unwrap() {
            break status.code();
        }
        if start.elapsed() > timeout {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(2));
    };
    let elapsed = start.elapsed();
    let stderr = std::fs::read_to_string(&err_path).unwrap_or_default();
    Bounded { code, stderr, peak_kib, elapsed }
}

fn gzip_member(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// About 1 MB of gzip (members one after another: one stream to a reader) that inflates to
/// `prefix` and then 1 GiB of zeros.
fn gzip_bomb(prefix: &[u8]) -> Vec<u8> {
    static ZEROS: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    let zeros = ZEROS.get_or_init(|| gzip_member(&vec![0u8; 64 << 20]));
    let mut out = gzip_member(prefix);
    for _ in 0..16 {
        out.extend_from_slice(zeros);
    }
    out
}

/// A NIfTI-1 header (little endian, `n+1`) for 1024^3 uint8 voxels at byte 352.
fn nifti_header_1024() -> Vec<u8> {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    for (i, d) in [3i16, 1024, 1024, 1024, 1, 1, 1, 1].iter().enumerate() {
        h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
    }
    h[70..72].copy_from_slice(&2i16.to_le_bytes()); // uint8
    h[72..74].copy_from_slice(&8i16.to_le_bytes());
    for a in 0..4 {
        h[76 + 4 * a..80 + 4 * a].copy_from_slice(&1.0f32.to_le_bytes());
    }
    h[108..112].copy_from_slice(&352.0f32.to_le_bytes());
    h[344..348].copy_from_slice(b"n+1\0");
    h
}

/// Resident memory a refused bomb may cost a process, MiB (a reader that inflated it would need
/// over 1 GiB for the bytes and 4 GiB for the voxels).
const PEAK_MIB: u64 = 200;
/// The address space a process refusing a bomb gets (`isowalld render --renderer reference`
/// needs no GPU and well under this).
const CAP_MIB: u64 = 1024;

#[test]
fn volume_bombs_claiming_1024_cubed_are_refused_at_once_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let nrrd = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 1024 1024 1024\nencoding: gzip\n\n";
    let mha = "ObjectType = Image\nNDims = 3\nDimSize = 1024 1024 1024\nElementType = MET_UCHAR\n\
               CompressedData = True\nElementDataFile = LOCAL\n";
    let files: [(&str, Vec<u8>); 3] = [
        ("bomb.nrrd", [nrrd.as_bytes(), &gzip_bomb(&[])].concat()),
        ("bomb.nii.gz", gzip_bomb(&nifti_header_1024())),
        ("bomb.mha", [mha.as_bytes(), &gzip_bomb(&[])].concat()),
    ];
    for (name, bytes) in &files {
        assert!(bytes.len() < 2 << 20, "{name} is {} bytes", bytes.len());
        std::fs::write(d.join(name), bytes).unwrap();
        let args = ["render", "--renderer", "reference", "--size", "8x8", "--volume", name, "--out", "x.png"];
        let r = run_bounded(d, "isowalld", &args, CAP_MIB, Duration::from_secs(60));
        eprintln!(
            "{name} ({} bytes): exit {:?} after {:.2} s, peak resident {} KiB: {}",
            bytes.len(),
            r.code,
            r.elapsed.as_secs_f64(),
            r.peak_kib,
            r.stderr.trim()
        );
        assert_eq!(r.code, Some(1), "{name}: {}", r.stderr);
        assert!(r.stderr.contains(name), "{name}: the error does not name the file: {}", r.stderr);
        assert!(
            r.stderr.contains("1024x1024x1024 uint8 is 4294967296 bytes as float32, over the limit"),
            "{name}: {}",
            r.stderr
        );
        assert!(r.peak_kib < PEAK_MIB * 1024, "{name}: peak resident {} KiB", r.peak_kib);
    }
    // A raw volume claiming the same on the command line.
    std::fs::write(d.join("small.raw"), [0u8; 64]).unwrap();
    let args = [
        "render",
        "--renderer",
        "reference",
        "--volume",
        "small.raw",
        "--dims",
        "1024,1024,1024",
        "--type",
        "uint8",
    ];
    let r = run_bounded(d, "isowalld", &args, CAP_MIB, Duration::from_secs(60));
    assert_eq!(r.code, Some(1), "{}", r.stderr);
    assert!(r.stderr.contains("small.raw") && r.stderr.contains("over the limit"), "{}", r.stderr);
    // A tighter limit of one's own is named.
    std::fs::write(
        d.join("tiny.nrrd"),
        [nrrd.replace("1024 1024 1024", "64 64 64").as_bytes(), &gzip_member(&[0; 1 << 18])].concat(),
    )
    .unwrap();
    let args =
        ["render", "--renderer", "reference", "--volume", "tiny.nrrd", "--max-volume-bytes", "1000000"];
    let r = run_bounded(d, "isowalld", &args, CAP_MIB, Duration::from_secs(60));
    assert_eq!(r.code, Some(1), "{}", r.stderr);
    assert!(r.stderr.contains("over the limit of 1000000 bytes (--max-volume-bytes)"), "{}", r.stderr);
}

#[test]
fn a_wall_node_refuses_a_bomb_before_reading_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let nrrd = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 1024 1024 1024\nencoding: gzip\n\n";
    std::fs::write(d.join("bomb.nrrd"), [nrrd.as_bytes(), &gzip_bomb(&[])].concat()).unwrap();
    let port = isowall_e2e::free_udp_ports(1)[0];
    let config = format!(
        "[wall]\nname = \"bomb\"\n[volume]\nsource = \"bomb.nrrd\"\n\
         [[tiles]]\nname = \"t\"\nx = 0\ny = 0\nwidth = 16\nheight = 12\n\
         [[nodes]]\nname = \"node0\"\naddress = \"127.0.0.1:{port}\"\ntiles = [\"t\"]\n"
    );
    std::fs::write(d.join("wall.toml"), config).unwrap();
    assert!(run_in(d, "isowall", &["keygen", "--config", "wall.toml"]).status.success());
    // The controller reads the volume for its box: refused the same way.
    let r =
        run_bounded(d, "isowall", &["orbit", "wall.toml", "--frames", "1"], CAP_MIB, Duration::from_secs(60));
    eprintln!("isowall orbit: exit {:?}, peak {} KiB: {}", r.code, r.peak_kib, r.stderr.trim());
    assert_eq!(r.code, Some(1), "{}", r.stderr);
    assert!(r.stderr.contains("bomb.nrrd") && r.stderr.contains("over the limit"), "{}", r.stderr);
    assert!(r.peak_kib < PEAK_MIB * 1024, "controller peak resident {} KiB", r.peak_kib);
    // The node asks its GPU for the largest binding (no address-space cap: drivers map much).
    let r = run_bounded(
        d,
        "isowalld",
        &["run", "--config", "wall.toml", "--node", "node0", "--display", "offscreen"],
        0,
        Duration::from_secs(120),
    );
    eprintln!("isowalld run: exit {:?}, peak {} KiB: {}", r.code, r.peak_kib, r.stderr.trim());
    if r.stderr.contains("no Vulkan adapter") && !in_ci() {
        eprintln!("skipping the node's part: no Vulkan adapter");
        return;
    }
    assert_eq!(r.code, Some(1), "{}", r.stderr);
    assert!(r.stderr.contains("bomb.nrrd") && r.stderr.contains("over the limit"), "{}", r.stderr);
    assert!(r.peak_kib < 400 * 1024, "node peak resident {} KiB", r.peak_kib);
}

#[test]
fn an_object_space_node_holds_its_brick_to_the_volume_limit() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ports = isowall_e2e::free_udp_ports(2);
    // The 48^3 torus is 442,368 bytes as float32; each of two bricks with its halo is well over
    // the 100,000 bytes allowed.
    let mut config = "[wall]\nname = \"brick-limit\"\nmode = \"object\"\n\
                      [volume]\nsource = \"procedural:torus:48\"\nmax_bytes = 100000\n"
        .to_string();
    for (i, port) in ports.iter().enumerate() {
        config += &format!(
            "[[tiles]]\nname = \"t{i}\"\nx = {}\ny = 0\nwidth = 16\nheight = 12\n\
             [[nodes]]\nname = \"node{i}\"\naddress = \"127.0.0.1:{port}\"\ntiles = [\"t{i}\"]\n",
            i * 16
        );
    }
    std::fs::write(d.join("wall.toml"), config).unwrap();
    assert!(run_in(d, "isowall", &["keygen", "--config", "wall.toml"]).status.success());
    let r = run_bounded(
        d,
        "isowalld",
        &["run", "--config", "wall.toml", "--node", "node0", "--display", "offscreen"],
        0,
        Duration::from_secs(60),
    );
    eprintln!("isowalld run: exit {:?}: {}", r.code, r.stderr.trim());
    if r.stderr.contains("no Vulkan adapter") && !in_ci() {
        eprintln!("skipping: no Vulkan adapter");
        return;
    }
    assert_eq!(r.code, Some(1), "{}", r.stderr);
    assert!(
        r.stderr.contains("brick 0 and its halo") && r.stderr.contains("[volume] max_bytes"),
        "{}",
        r.stderr
    );
}

/// `mkfifo PATH`.
fn mkfifo(path: &Path) {
    assert!(Command::new("mkfifo").arg(path).status().unwrap().success(), "mkfifo {}", path.display());
}

#[test]
fn a_fifo_or_a_device_as_volume_data_is_refused_without_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    mkfifo(&d.join("pipe.raw"));
    mkfifo(&d.join("pipe.nrrd"));
    let nrrd = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n";
    std::fs::write(d.join("fifo.nhdr"), format!("{nrrd}data file: pipe.raw\n")).unwrap();
    std::fs::write(
        d.join("fifo.mhd"),
        "NDims = 3\nDimSize = 4 4 4\nElementType = MET_UCHAR\nElementDataFile = pipe.raw\n",
    )
    .unwrap();
    std::os::unix::fs::symlink("/dev/zero", d.join("zero.raw")).unwrap();
    std::fs::write(d.join("zero.nhdr"), format!("{nrrd}data file: zero.raw\n")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", d.join("zero.nrrd")).unwrap();
    // No one ever writes to the FIFOs: a reader that opened one to read would wait forever.
    for (volume, why) in [
        ("fifo.nhdr", "pipe.raw: is a FIFO (named pipe)"),
        ("fifo.mhd", "pipe.raw: is a FIFO (named pipe)"),
        ("pipe.nrrd", "pipe.nrrd: is a FIFO (named pipe)"),
        // A data file that is a link out of the header's folder is refused before its type is.
        ("zero.nhdr", "data file: 'zero.raw' is a link to /dev/zero, outside the header's folder"),
        ("zero.nrrd", "zero.nrrd: is a device"),
    ] {
        let args = ["render", "--renderer", "reference", "--size", "8x8", "--volume", volume];
        let r = run_bounded(d, "isowalld", &args, CAP_MIB, Duration::from_secs(20));
        eprintln!("{volume}: exit {:?} after {:.2} s: {}", r.code, r.elapsed.as_secs_f64(), r.stderr.trim());
        assert_eq!(
            r.code,
            Some(1),
            "{volume}: killed after {:?} or failed otherwise: {}",
            r.elapsed,
            r.stderr
        );
        assert!(r.stderr.contains(why), "{volume}: {}", r.stderr);
    }
}

#[test]
fn a_detached_header_cannot_read_or_size_other_files() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir(d.join("vol")).unwrap();
    std::fs::write(d.join("secret.raw"), vec![7u8; 12345]).unwrap();
    let passwd_len = std::fs::metadata("/etc/passwd").map(|m| m.len()).ok();
    let nrrd = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n";
    let mha = "NDims = 3\nDimSize = 4 4 4\nElementType = MET_UCHAR\n";
    for (name, text) in [
        ("passwd.nhdr", format!("{nrrd}data file: /etc/passwd\n")),
        ("up.nhdr", format!("{nrrd}data file: ../secret.raw\n")),
        ("deep.nhdr", format!("{nrrd}data file: ./x/../../secret.raw\n")),
        ("passwd.mhd", format!("{mha}ElementDataFile = /etc/passwd\n")),
        ("up.mhd", format!("{mha}ElementDataFile = ../secret.raw\n")),
    ] {
        std::fs::write(d.join("vol").join(name), text).unwrap();
        let volume = format!("vol/{name}");
        let args = ["render", "--renderer", "reference", "--size", "8x8", "--volume", &volume];
        let r = run_bounded(d, "isowalld", &args, CAP_MIB, Duration::from_secs(20));
        eprintln!("{name}: {}", r.stderr.trim());
        assert_eq!(r.code, Some(1), "{name}: {}", r.stderr);
        assert!(r.stderr.contains("is not a file in the header's folder"), "{name}: {}", r.stderr);
        assert!(!r.stderr.contains("12345"), "{name}: the other file's size is told: {}", r.stderr);
        if let Some(len) = passwd_len {
            assert!(!r.stderr.contains(&format!(" {len} bytes")), "{name}: /etc/passwd's size: {}", r.stderr);
        }
    }
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn mode(path: &Path) -> u32 {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

/// The notAfter of a PEM certificate, seconds since 1970.
fn not_after(path: &Path) -> i64 {
    use rustls::pki_types::pem::PemObject;
    let der = rustls::pki_types::CertificateDer::from_pem_slice(&read(path)).unwrap();
    x509_parser::parse_x509_certificate(&der).unwrap().1.validity().not_after.timestamp()
}

fn now_unix() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs() as i64
}

const WALL: &str = "[wall]\nname = \"k\"\n[volume]\nsource = \"procedural:sphere:16\"\n\
    [[tiles]]\nname = \"t\"\nx = 0\ny = 0\nwidth = 16\nheight = 12\n\
    [[nodes]]\nname = \"node0\"\naddress = \"127.0.0.1:7401\"\ntiles = [\"t\"]\n";

#[test]
fn keygen_keeps_a_working_ca_renews_from_it_and_writes_private_keys() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("wall.toml"), WALL).unwrap();
    let keys = d.join("keys");
    let out = run_in(d, "isowall", &["keygen", "--config", "wall.toml"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for name in ["ca", "node0", "controller"] {
        assert_eq!(mode(&keys.join(format!("{name}.key"))), 0o600, "{name}.key");
    }
    // Two years, not 1975 to 4096.
    let two_years = now_unix() + 730 * 86_400;
    assert!((not_after(&keys.join("node0.pem")) - two_years).abs() < 600);
    let before: Vec<Vec<u8>> =
        ["ca.pem", "ca.key", "node0.pem", "node0.key"].iter().map(|f| read(&keys.join(f))).collect();

    // Again: refused, nothing replaced.
    let out = run_in(d, "isowall", &["keygen", "--config", "wall.toml"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("ca.pem: a wall CA is already here") && err.contains("--renew"), "{err}");
    let after: Vec<Vec<u8>> =
        ["ca.pem", "ca.key", "node0.pem", "node0.key"].iter().map(|f| read(&keys.join(f))).collect();
    assert_eq!(before, after, "a refused keygen changed files");

    // Renewal keeps the CA, issues node0 again for 30 days.
    let out = run_in(d, "isowall", &["keygen", "--config", "wall.toml", "--renew", "--days", "30"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(
        (read(&keys.join("ca.pem")), read(&keys.join("ca.key"))),
        (before[0].clone(), before[1].clone())
    );
    assert_ne!(read(&keys.join("node0.pem")), before[2]);
    assert!((not_after(&keys.join("node0.pem")) - (now_unix() + 30 * 86_400)).abs() < 600);
    assert_eq!(mode(&keys.join("node0.key")), 0o600);
    let stray: Vec<String> = std::fs::read_dir(&keys)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(stray.is_empty(), "temporary files left: {stray:?}");

    // --force replaces it.
    let out = run_in(d, "isowall", &["keygen", "--config", "wall.toml", "--force"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_ne!(read(&keys.join("ca.pem")), before[0]);
}

#[test]
fn a_certificate_near_its_end_is_warned_about_and_an_expired_one_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("wall.toml"), WALL).unwrap();
    // `keygen --days 1`: check-config passes with a warning for each certificate, naming it.
    let out = run_in(d, "isowall", &["keygen", "--config", "wall.toml", "--days", "1"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = run_in(d, "isowall", &["check-config", "wall.toml"]);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    eprintln!("check-config, certificates of 1 day:\n{err}");
    assert!(out.status.success(), "{err}");
    for name in ["node0", "controller"] {
        let line = format!("warning: keys/{name}.pem: the certificate expires on");
        assert!(err.contains(&line) && err.contains("in 1 day:"), "no warning for {name}:\n{err}");
    }
    assert!(!err.contains("ca.pem"), "the CA (10 years) was warned about:\n{err}");
    // node0's certificate, signed by the wall's CA, ended yesterday: check-config fails and the
    // daemon refuses to start, each naming the file and the date.
    use rcgen::{CertificateParams, DnType, Issuer, KeyPair};
    let keys = d.join("keys");
    let ca_key = KeyPair::from_pem(&std::fs::read_to_string(keys.join("ca.key")).unwrap()).unwrap();
    let issuer =
        Issuer::from_ca_cert_pem(&std::fs::read_to_string(keys.join("ca.pem")).unwrap(), ca_key).unwrap();
    let key = KeyPair::generate().unwrap();
    let mut params = CertificateParams::new(vec!["node0".to_string()]).unwrap();
    params.distinguished_name.push(DnType::CommonName, "node0");
    let day = |days: i64| {
        rcgen::date_time_ymd(1970, 1, 1) + Duration::from_secs((now_unix() + days * 86_400) as u64)
    };
    params.not_before = day(-10);
    params.not_after = day(-1);
    let cert = params.signed_by(&key, &issuer).unwrap();
    std::fs::write(keys.join("node0.pem"), cert.pem()).unwrap();
    std::fs::write(keys.join("node0.key"), key.serialize_pem()).unwrap();
    let out = run_in(d, "isowall", &["check-config", "wall.toml"]);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    eprintln!("check-config, node0's certificate expired:\n{err}");
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("keys/node0.pem: the certificate expired on") && err.contains("--renew"), "{err}");
    let args = ["run", "--config", "wall.toml", "--node", "node0", "--display", "offscreen"];
    let r = run_bounded(d, "isowalld", &args, 0, Duration::from_secs(60));
    assert_eq!(r.code, Some(1), "{}", r.stderr);
    assert!(r.stderr.contains("node0.pem: the certificate expired on"), "{}", r.stderr);
}

#[test]
fn a_key_open_to_others_is_refused_naming_the_file() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("wall.toml"), WALL).unwrap();
    assert!(run_in(d, "isowall", &["keygen", "--config", "wall.toml"]).status.success());
    let key = d.join("keys/node0.key");
    for open in [0o644, 0o640, 0o604] {
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(open)).unwrap();
        let args = ["run", "--config", "wall.toml", "--node", "node0", "--display", "offscreen"];
        let r = run_bounded(d, "isowalld", &args, 0, Duration::from_secs(60));
        assert_eq!(r.code, Some(1), "{open:o}: {}", r.stderr);
        assert!(
            r.stderr.contains("node0.key: the private key is open to its group or to others"),
            "{}",
            r.stderr
        );
        assert!(
            r.stderr.contains(&format!("(mode {open:04o})")) && r.stderr.contains("chmod 600"),
            "{}",
            r.stderr
        );
        // The fix is chmod, not keygen (which on a deployed wall would replace its CA).
        assert!(!r.stderr.contains("keygen"), "{}", r.stderr);
    }
    // A node missing its certificate: copy the files keygen made; the OS's reason said once.
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
    std::fs::rename(d.join("keys/node0.pem"), d.join("node0.pem.away")).unwrap();
    let args = ["run", "--config", "wall.toml", "--node", "node0", "--display", "offscreen"];
    let r = run_bounded(d, "isowalld", &args, 0, Duration::from_secs(60));
    assert_eq!(r.code, Some(1), "{}", r.stderr);
    assert!(r.stderr.contains("node0.pem: No such file or directory"), "{}", r.stderr);
    assert!(r.stderr.contains("copy ca.pem, node0.pem and node0.key"), "{}", r.stderr);
    assert_eq!(r.stderr.matches("No such file or directory").count(), 1, "said twice: {}", r.stderr);
    std::fs::rename(d.join("node0.pem.away"), d.join("keys/node0.pem")).unwrap();
    // The controller's own key, the same.
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
    let ckey = d.join("keys/controller.key");
    std::fs::set_permissions(&ckey, std::fs::Permissions::from_mode(0o644)).unwrap();
    let r = run_bounded(d, "isowall", &["orbit", "wall.toml", "--frames", "1"], 0, Duration::from_secs(60));
    assert_eq!(r.code, Some(1), "{}", r.stderr);
    assert!(r.stderr.contains("controller.key: the private key is open"), "{}", r.stderr);
}

#[test]
fn names_keygen_cannot_write_are_refused_by_the_config_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let long = "n".repeat(100);
    for (bad, why) in [
        ("node_1", "may hold only"),
        (long.as_str(), "100 characters, more than 63"),
        ("10.0.0.1", "digits only"),
    ] {
        std::fs::write(d.join("wall.toml"), WALL.replace("\"node0\"", &format!("\"{bad}\""))).unwrap();
        let out = run_in(d, "isowall", &["check-config", "wall.toml"]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{bad}: {err}");
        assert!(err.contains("wall.toml:12:8: node name") && err.contains(why), "{bad}: {err}");
        let out = run_in(d, "isowall", &["keygen", "--config", "wall.toml"]);
        assert_eq!(out.status.code(), Some(1), "{bad}");
        assert!(!d.join("keys").exists(), "{bad}: keygen wrote files");
    }
}

#[test]
fn configs_that_cannot_work_are_refused_with_file_line_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let two = "[wall]\nname = \"w\"\n[volume]\nsource = \"procedural:sphere:16\"\n\
        [[tiles]]\nname = \"a\"\nx = 0\ny = 0\nwidth = 160\nheight = 120\n\
        [[tiles]]\nname = \"b\"\nx = 160\ny = 0\nwidth = 160\nheight = 120\n\
        [[nodes]]\nname = \"n0\"\naddress = \"127.0.0.1:7401\"\ntiles = [\"a\"]\n\
        [[nodes]]\nname = \"n1\"\naddress = \"127.0.0.1:7402\"\ntiles = [\"b\"]\n";
    let wall = |extra: &str| two.replacen("name = \"w\"\n", &format!("name = \"w\"\n{extra}\n"), 1);
    for (text, want) in [
        (
            two.replace("127.0.0.1:7402", "localhost:7401"),
            "w.toml:23:11: node 'n1' at localhost:7401 has the same address as node 'n0' at 127.0.0.1:7401 (line 19)",
        ),
        (two.replace("127.0.0.1:7402", "[::ffff:127.0.0.1]:7401"), "w.toml:23:11: node 'n1' at [::ffff:127.0.0.1]:7401"),
        (wall("message_limit_bytes = 2147483648"), "w.toml:3:23: wall: `message_limit_bytes` 2147483648 is outside"),
        (wall("message_limit_bytes = 4096"), "w.toml:3:23: wall: `message_limit_bytes` 4096 is too small for the snapshot of node 'n0'"),
        (wall("deadline_ms = 18446744073709551615"), "w.toml:3:15: wall: `deadline_ms` 18446744073709551615 is outside 1..=600000"),
        (two[..two.find("[[nodes]]").unwrap()].to_string(), "w.toml:16:1: no nodes"),
        (format!("nodes = []\n{}", &two[..two.find("[[nodes]]").unwrap()]), "w.toml:1:9: no nodes"),
    ] {
        std::fs::write(d.join("w.toml"), &text).unwrap();
        for b in ["isowall", "isowalld"] {
            let out = run_in(d, b, &["check-config", "w.toml"]);
            let err = String::from_utf8_lossy(&out.stderr);
            assert_eq!(out.status.code(), Some(1), "{b} accepted:\n{text}\n{err}");
            assert!(err.contains(want), "{b}: wanted {want:?}:\n{err}");
        }
    }
}
