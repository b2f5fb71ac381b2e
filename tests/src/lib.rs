//! Helpers for the end-to-end tests in `tests/tests/`: they run the real `isowalld` and `isowall`
//! binaries as separate processes (and, with the wall, over the network on loopback).

pub mod fake_node;
pub mod orbit;
pub mod relay;
pub mod x11;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// Whether this is a CI run (`CI=true`), where nothing may be skipped.
pub fn in_ci() -> bool {
    std::env::var("CI").as_deref() == Ok("true")
}

/// `../shared` beside the checkout, with the real data and convention vectors. `None` (after a
/// message) where it is absent, e.g. on a user's machine; under CI it must be there.
pub fn shared_dir() -> Option<PathBuf> {
    let dir = repo_root().join("../shared");
    if dir.join("DESIGN.md").exists() {
        return Some(dir);
    }
    assert!(!in_ci(), "{} is missing under CI=true", dir.display());
    eprintln!("skipping: {} not found (it sits beside the checkout for developers and CI)", dir.display());
    None
}

/// Path of a workspace binary, built once per test process with the same profile as the tests.
pub fn bin(name: &str) -> PathBuf {
    static BUILT: OnceLock<()> = OnceLock::new();
    let target_dir = std::env::current_exe()
        .ok()
        .and_then(|p| p.parent()?.parent().map(Path::to_path_buf))
        .expect("test executable lives in target/<profile>/deps");
    BUILT.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut cmd = Command::new(cargo);
        cmd.current_dir(repo_root()).args(["build", "--quiet", "--bins", "-p", "isowalld", "-p", "isowall"]);
        // What `cargo test` sets for this package would reach build scripts' rerun-if-env-changed
        // checks (ring's reads CARGO_PKG_NAME) and rebuild them here and again at the next
        // `cargo test`.
        for (key, _) in std::env::vars_os().filter_map(|(k, v)| Some((k.into_string().ok()?, v))) {
            if key.starts_with("CARGO_PKG_")
                || [
                    "CARGO_MANIFEST_DIR",
                    "CARGO_MANIFEST_PATH",
                    "CARGO_CRATE_NAME",
                    "CARGO_PRIMARY_PACKAGE",
                    "OUT_DIR",
                ]
                .contains(&key.as_str())
            {
                cmd.env_remove(key);
            }
        }
        if target_dir.file_name().is_some_and(|n| n == "release") {
            cmd.arg("--release");
        }
        let status = cmd.status().expect("cannot run cargo to build the binaries");
        assert!(status.success(), "building the binaries failed");
    });
    let path = target_dir.join(name);
    assert!(path.exists(), "{} was not built", path.display());
    path
}

/// Runs a binary with arguments in `dir` and returns its output (never panics on a non-zero exit).
pub fn run_in(dir: &Path, name: &str, args: &[&str]) -> Output {
    Command::new(bin(name)).current_dir(dir).args(args).output().expect("cannot start the binary")
}

/// For commands that need the GPU: `true` if it succeeded; `false` (skip, after a message) where no
/// Vulkan adapter exists outside CI; panics with the command's stderr on any other failure.
pub fn gpu_ok(what: &str, out: &Output) -> bool {
    if out.status.success() {
        return true;
    }
    let err = String::from_utf8_lossy(&out.stderr);
    if err.contains("no Vulkan adapter") && !in_ci() {
        eprintln!("skipping {what}: no Vulkan adapter (install mesa-vulkan-drivers)");
        return false;
    }
    panic!("{what} failed ({}):\n{err}", out.status);
}

/// `n` distinct UDP ports free on loopback right now (bound, read, released).
pub fn free_udp_ports(n: usize) -> Vec<u16> {
    let sockets: Vec<std::net::UdpSocket> =
        (0..n).map(|_| std::net::UdpSocket::bind("127.0.0.1:0").expect("bind a loopback UDP port")).collect();
    sockets.iter().map(|s| s.local_addr().expect("local address").port()).collect()
}

/// Asks `poll` every 100 ms until it answers `Ok`, and returns that answer: how a test waits for
/// what follows a moment after its cause (a log line, a status, a closed connection), however
/// loaded the machine. After `timeout` it panics saying that `what` did not happen, with the
/// last `Err` (what there was instead).
pub fn wait_until<T>(what: &str, timeout: Duration, mut poll: impl FnMut() -> Result<T, String>) -> T {
    let give_up = Instant::now() + timeout;
    loop {
        let last = match poll() {
            Ok(done) => return done,
            Err(last) => last,
        };
        assert!(Instant::now() < give_up, "not within {timeout:?}: {what}\n{last}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A child process killed when dropped (a daemon under test).
pub struct Daemon {
    pub child: std::process::Child,
    pub log: PathBuf,
}

impl Daemon {
    /// Starts `isowalld run --config CONFIG --node NODE EXTRA...`, logging to `dir/NODE.log`.
    /// Headless whatever the desktop: DISPLAY and WAYLAND_DISPLAY are not passed on.
    pub fn start(dir: &Path, config: &Path, node: &str, extra: &[&str]) -> Daemon {
        Daemon::start_on(dir, config, node, extra, None)
    }

    /// [`Daemon::start`] with DISPLAY set to `display` (e.g. `:99`, an Xvfb) where given.
    pub fn start_on(dir: &Path, config: &Path, node: &str, extra: &[&str], display: Option<&str>) -> Daemon {
        let log = dir.join(format!("{node}.log"));
        let file = std::fs::File::create(&log).expect("log file");
        let mut cmd = Command::new(bin("isowalld"));
        cmd.env_remove("DISPLAY").env_remove("WAYLAND_DISPLAY");
        if let Some(d) = display {
            cmd.env("DISPLAY", d);
        }
        let child = cmd
            .args(["run", "--config"])
            .arg(config)
            .args(["--node", node])
            .args(extra)
            .stdout(file.try_clone().expect("log file"))
            .stderr(file)
            .spawn()
            .expect("start isowalld");
        Daemon { child, log }
    }

    /// Waits until the daemon printed that it listens (or exited, or `timeout`); `false` on failure.
    pub fn wait_ready(&mut self, timeout: std::time::Duration) -> bool {
        let start = std::time::Instant::now();
        while start.elapsed() < timeout {
            if std::fs::read_to_string(&self.log).is_ok_and(|l| l.contains("ready on")) {
                return true;
            }
            if self.child.try_wait().ok().flatten().is_some() {
                return false;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
        false
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts `isowalld run` for the nodes `node0..count` of `config` and waits until each listens;
/// `None` (skip, after a message) where no Vulkan adapter exists outside CI; panics with the log of
/// a node that does not start.
pub fn start_nodes(dir: &Path, config: &Path, count: usize) -> Option<Vec<Daemon>> {
    start_nodes_with(dir, config, count, |_| Vec::new(), None)
}

/// [`start_nodes`] with extra `isowalld run` arguments for node `i` (e.g. `--peer-addr`, fault
/// injection, `--display window`) and DISPLAY set to `display` where given (the window tests' Xvfb).
pub fn start_nodes_with(
    dir: &Path,
    config: &Path,
    count: usize,
    extra: impl Fn(usize) -> Vec<String>,
    display: Option<&str>,
) -> Option<Vec<Daemon>> {
    let mut daemons: Vec<Daemon> = (0..count)
        .map(|i| {
            let args = extra(i);
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            Daemon::start_on(dir, config, &format!("node{i}"), &args, display)
        })
        .collect();
    for (i, d) in daemons.iter_mut().enumerate() {
        if !d.wait_ready(std::time::Duration::from_secs(120)) {
            let log = d.log_text();
            if log.contains("no Vulkan adapter") && !in_ci() {
                eprintln!("skipping: no Vulkan adapter");
                return None;
            }
            panic!(
                "node{i} did not start{}:\n{log}",
                display.map(|d| format!(" on {d}")).unwrap_or_default()
            );
        }
    }
    Some(daemons)
}

/// `isowalld render` (in `dir`) of the whole image of a [`wall_config`] wall: its fixed camera, sky
/// light and bent-normal IBL, `volume` at `width`x`height` with `ao_samples`, then `extra`
/// arguments (`--out`, `--aov`, `--ao-radius` ...). The single render the wall tests compare with.
pub fn render_whole(
    dir: &Path,
    volume: &str,
    (width, height): (u32, u32),
    ao_samples: u32,
    extra: &[&str],
) -> std::process::Output {
    let (size, ao) = (format!("{width}x{height}"), ao_samples.to_string());
    let mut args = vec!["render", "--volume", volume, "--size", &size];
    args.extend(["--eye", "60,-70,45", "--target", "23.5,23.5,23.5", "--up", "0,0,1", "--fov-y", "40"]);
    args.extend(["--ao-samples", &ao, "--ibl", "bent", "--env", "sky"]);
    args.extend_from_slice(extra);
    run_in(dir, "isowalld", &args)
}

/// How a whole-wall image compares with the single render of the whole wall camera, over the
/// tiles' pixels of a 2x2 wall of `w`x`h` tiles with `bezel`-pixel mullions ([`wall_config`]).
#[derive(Debug, Clone, Copy)]
pub struct TileDiff {
    pub compared: u64,
    /// The largest difference of a channel, in 8-bit levels.
    pub max_diff: u8,
    /// The mean difference per channel, in levels.
    pub mean: f64,
    /// Pixels of the single render brighter than a dim background (the object is in view).
    pub lit: u64,
}

/// Compares the tiles' pixels of `wall` with `whole` (see [`TileDiff`]); `is_bezel(x, y)` says
/// which pixels are mullions, left out of the comparison.
pub fn compare_tiles(
    wall: &image::RgbImage,
    whole: &image::RgbImage,
    is_bezel: impl Fn(u32, u32) -> bool,
) -> TileDiff {
    let (mut compared, mut max_diff, mut sum_diff, mut lit) = (0u64, 0u8, 0u64, 0u64);
    for (x, y, b) in whole.enumerate_pixels() {
        if is_bezel(x, y) {
            continue;
        }
        let a = wall.get_pixel(x, y).0;
        compared += 1;
        for (&p, &q) in a.iter().zip(&b.0) {
            let d = p.abs_diff(q);
            max_diff = max_diff.max(d);
            sum_diff += d as u64;
        }
        lit += u64::from(b.0.iter().map(|&v| v as u32).sum::<u32>() > 200);
    }
    TileDiff { compared, max_diff, mean: sum_diff as f64 / (3 * compared.max(1)) as f64, lit }
}

/// Whether pixel (x, y) of a 2x2 wall of `w`x`h` tiles lies in a mullion of `bezel` pixels.
pub fn in_bezel_2x2(x: u32, y: u32, w: u32, h: u32, bezel: u32) -> bool {
    let tx = x < w || x >= w + 2 * bezel;
    let ty = y < h || y >= h + 2 * bezel;
    !(tx && ty)
}

/// Writes `dir/NAME.toml`: a 2x2 wall of `w`x`h` tiles with `bezel`-pixel mullions, nodes
/// `node0..3` on the given loopback ports, the torus at 48^3 with 4 AO samples and sky light, a
/// fixed camera, and the certificates in `dir/CERTS`.
#[expect(clippy::too_many_arguments, reason = "each call names the wall it tests, field by field")]
pub fn wall_config(
    dir: &Path,
    name: &str,
    ports: &[u16],
    w: u32,
    h: u32,
    bezel: u32,
    deadline_ms: u64,
    certs: &str,
) -> PathBuf {
    let mut s = format!(
        "[wall]\nname = \"{name}\"\ndeadline_ms = {deadline_ms}\n\n\
         [camera]\neye = [60.0, -70.0, 45.0]\ntarget = [23.5, 23.5, 23.5]\nup = [0, 0, 1]\nfov_y = 40.0\n\n\
         [volume]\nsource = \"procedural:torus:48\"\n\n\
         [render]\nao_samples = 4\nibl = \"bent\"\nenv = \"sky\"\n\n\
         [certificates]\ndir = \"{certs}\"\n"
    );
    for (i, port) in ports.iter().enumerate() {
        let (cx, cy) = ((i % 2) as u32, (i / 2) as u32);
        let border = [
            if cx == 0 { 0 } else { bezel },
            if cx == 0 { bezel } else { 0 },
            if cy == 0 { 0 } else { bezel },
            if cy == 0 { bezel } else { 0 },
        ];
        s += &format!(
            "\n[[tiles]]\nname = \"t{cx}{cy}\"\nx = {}\ny = {}\nwidth = {w}\nheight = {h}\nbezel = [{}, {}, {}, {}]\n",
            cx * (w + 2 * bezel),
            cy * (h + 2 * bezel),
            border[0], border[1], border[2], border[3]
        );
        s += &format!(
            "\n[[nodes]]\nname = \"node{i}\"\naddress = \"127.0.0.1:{port}\"\ntiles = [\"t{cx}{cy}\"]\n"
        );
    }
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, s).unwrap();
    path
}

/// Writes `steps` time steps `dir/steps/step_KK.nrrd`: 24^3 float voxels with spacing 2 (the box
/// 0..46, in [`wall_config`]'s camera view), f = 1 - |p - c| / 30 (a ball of radius 15 at iso 0.5)
/// whose centre moves 5 world units along x each step.
pub fn write_ball_steps(dir: &Path, steps: usize) {
    std::fs::create_dir_all(dir.join("steps")).unwrap();
    for k in 0..steps {
        let c = [12.0 + 5.0 * k as f32, 23.0, 23.0];
        let mut bytes =
            b"NRRD0004\ntype: float\ndimension: 3\nsizes: 24 24 24\nspacings: 2 2 2\nendian: little\nencoding: raw\n\n"
                .to_vec();
        for z in 0..24 {
            for y in 0..24 {
                for x in 0..24 {
                    let p = [2.0 * x as f32, 2.0 * y as f32, 2.0 * z as f32];
                    let d = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt();
                    bytes.extend((1.0 - d / 30.0).to_le_bytes());
                }
            }
        }
        std::fs::write(dir.join(format!("steps/step_{k:02}.nrrd")), bytes).unwrap();
    }
}

/// Makes the wall config at `path` a time-varying wall: `source = "steps/step_*.nrrd"` (see
/// [`write_ball_steps`]) at iso 0.5, in place of [`wall_config`]'s torus.
pub fn set_ball_steps_source(path: &Path) {
    let text = std::fs::read_to_string(path).expect("the wall config");
    let old = "source = \"procedural:torus:48\"";
    assert!(text.contains(old), "{} has no torus source", path.display());
    std::fs::write(path, text.replace(old, "source = \"steps/step_*.nrrd\"\niso = 0.5"))
        .expect("write the config");
}

/// Makes the wall config at `path` an object-space wall (`[wall] mode = "object"`).
pub fn set_object_mode(path: &Path) {
    let text = std::fs::read_to_string(path).expect("the wall config");
    assert!(!text.contains("mode = "), "{} already sets a mode", path.display());
    std::fs::write(path, text.replacen("[wall]\n", "[wall]\nmode = \"object\"\n", 1))
        .expect("write the config");
}

/// Writes `dir/NAME.toml`: a 2x1 wall of two `w`x`h` tiles side by side (a `bezel`-pixel mullion
/// on each side of the seam), nodes `node0`, `node1` on the given loopback ports, the torus at
/// 32^3 with `ao_samples` AO samples and sky light, a fixed camera, certificates in `dir/keys`.
pub fn wall_config_2x1(
    dir: &Path,
    name: &str,
    ports: &[u16],
    w: u32,
    h: u32,
    bezel: u32,
    ao_samples: u32,
) -> PathBuf {
    let mut s = format!(
        "[wall]\nname = \"{name}\"\ndeadline_ms = 60000\n\n\
         [camera]\neye = [45.0, -55.0, 35.0]\ntarget = [15.5, 15.5, 15.5]\nup = [0, 0, 1]\nfov_y = 40.0\n\n\
         [volume]\nsource = \"procedural:torus:32\"\n\n\
         [render]\nao_samples = {ao_samples}\nibl = \"bent\"\nenv = \"sky\"\n\n\
         [certificates]\ndir = \"keys\"\n"
    );
    for (i, port) in ports.iter().take(2).enumerate() {
        let bz = if i == 0 { format!("[0, {bezel}, 0, 0]") } else { format!("[{bezel}, 0, 0, 0]") };
        s += &format!(
            "\n[[tiles]]\nname = \"t{i}\"\nx = {}\ny = 0\nwidth = {w}\nheight = {h}\nbezel = {bz}\n\n\
             [[nodes]]\nname = \"node{i}\"\naddress = \"127.0.0.1:{port}\"\ntiles = [\"t{i}\"]\n",
            i as u32 * (w + 2 * bezel)
        );
    }
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, s).unwrap();
    path
}

/// The addresses a console prints on `stdout` (`isowall console: serving URL/`, without the
/// final slash), read on a thread of its own so the console never blocks on a full pipe.
pub fn console_urls(stdout: std::process::ChildStdout) -> std::sync::mpsc::Receiver<String> {
    use std::io::{BufRead, BufReader};
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(rest) = line.strip_prefix("isowall console: serving ") {
                let _ = tx.send(rest.trim_end_matches('/').to_string());
            }
        }
    });
    rx
}
