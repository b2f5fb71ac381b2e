//! `isowall bench CONFIG --table`: the report's table. Rows: AO samples (32/64/128/256);
//! columns: 1..N nodes (N = the wall's node count); each cell the frames per second of a fixed
//! orbit of the whole wall image (`--size`, default small enough for lavapipe) split into one
//! vertical strip per node, with the slowest node's median render time beside it and RTPara's
//! 2008 figure for the same cell where one is published (../shared/DESIGN.md: the 'engine'
//! volume, 1-4 nodes, 32-256 samples; every other cell "—"). Each column starts its own local
//! daemons (loopback nodes only) with a derived config: the same nodes, names, certificates,
//! volume and render settings, the strips as tiles. The render mode is a parameter of every
//! cell: in object space every node holds one brick and the strips are composited by depth. A
//! column that fails (a node that does not start, say) prints "n/a" with the reason; the others go on.

use crate::drive::{load, orbit_camera, runtime, scene};
use crate::local::{is_loopback, LocalDaemons};
use crate::report::quantile;
use crate::wall::{FrameRequest, Wall};
use anyhow::{bail, Context, Result};
use clap::Args;
use isowall_model::cli_args;
use isowall_model::config::{TileConfig, WallConfig, WallMode};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: Option<BenchCommand>,
    /// The wall config (TOML); its nodes must be on loopback (each column starts local daemons)
    #[arg(required = true)]
    pub config: Option<PathBuf>,
    /// Print the report's table (AO samples x nodes, fps and render time, 2008 beside ours)
    #[arg(long)]
    pub table: bool,
    /// Timed frames of the orbit per cell (after one untimed warm-up frame)
    #[arg(long, value_parser = cli_args::bench_frames_u64, default_value_t = 3)]
    pub frames: u64,
    /// The whole wall image, WIDTHxHEIGHT, split into one strip per node
    #[arg(long, default_value = "96x64", value_parser = cli_args::size)]
    pub size: (u32, u32),
    /// The rows: AO samples per pixel per frame
    #[arg(long, value_parser = cli_args::ao_samples, value_delimiter = ',', default_value = "32,64,128,256")]
    pub samples: Vec<u32>,
    /// The columns: node counts (default 1..N)
    #[arg(long, value_delimiter = ',')]
    pub nodes: Vec<usize>,
    /// Render modes: screen (sort-first), object (sort-last)
    #[arg(long, value_delimiter = ',', default_value = "screen,object", value_parser = ["screen", "object"])]
    pub modes: Vec<String>,
    /// Orbit step per frame, degrees
    #[arg(long, value_parser = cli_args::degrees, default_value_t = 4.0)]
    pub degrees_per_frame: f64,
    /// How long to wait for each column's nodes, seconds
    #[arg(long, value_parser = cli_args::start_timeout, default_value_t = 120)]
    pub start_timeout: u64,
    /// Measure the swap instead: the config's nodes started here (as `up` does) orbit --frames
    /// frames untimed (each node presents when its Swap arrives), then timed (`swap_margin_ms =
    /// "auto"`), then timed and paced at --paced-fps; each run's fps, swap skew (measured, and
    /// true where every node is on this machine), late swaps, margin and frame-interval jitter
    #[arg(long, conflicts_with = "table")]
    pub swap: bool,
    /// With --swap: the frame rate of the paced run
    #[arg(long, default_value_t = 30.0, value_parser = crate::drive::parse_fps)]
    pub paced_fps: f64,
}

#[derive(clap::Subcommand)]
pub enum BenchCommand {
    /// Load balancing: the config's nodes started here (as `up` does; nodes of other machines on
    /// free loopback ports) orbit unbalanced (every
    /// node renders its own tiles), then the same orbit balanced (`[wall] balance`, on for the
    /// run whatever the config says); per run and node its work (the costs its rectangles
    /// reported: fetches and pixels) and bytes sent per frame, the fps, and a last line
    /// `balance: slowest/mean X unbalanced, Y balanced` (the slowest node's work over the mean,
    /// averaged over each orbit's frames from the third on)
    Balance(BalanceArgs),
}

#[derive(Args)]
pub struct BalanceArgs {
    /// The wall config (TOML); every node runs on this machine
    pub config: PathBuf,
    /// Frames of each orbit
    #[arg(long, value_parser = cli_args::bench_frames_u64, default_value_t = 30)]
    pub frames: u64,
    /// Orbit step per frame, degrees
    #[arg(long, value_parser = cli_args::degrees, default_value_t = 1.0)]
    pub degrees_per_frame: f64,
    /// How long to wait for the nodes, seconds
    #[arg(long, value_parser = cli_args::start_timeout, default_value_t = 120)]
    pub start_timeout: u64,
    /// The internal resolution divisor of every frame (1: full resolution; up to 4): a wall of
    /// large tiles measured on a slow machine
    #[arg(long, default_value_t = 1, value_parser = cli_args::scale)]
    pub scale: u32,
    /// AO samples per pixel per frame (default: the config's)
    #[arg(long, value_parser = cli_args::ao_samples)]
    pub samples: Option<u32>,
    /// The wall's deadline for the run, ms (default: the config's; a slow machine wants more)
    #[arg(long, value_parser = cli_args::deadline_ms)]
    pub deadline_ms: Option<u64>,
}

/// Frames of each orbit left out of the averages: the first (the split starts from the nodes'
/// own tiles and learns from what it reports) and the one after.
const BALANCE_SETTLE_FRAMES: usize = 2;

/// `bench balance`: one wall, the same orbit unbalanced then balanced.
fn bench_balance(a: &BalanceArgs) -> Result<()> {
    if a.frames as usize <= BALANCE_SETTLE_FRAMES {
        bail!("--frames must be more than {BALANCE_SETTLE_FRAMES} (the first frames of each orbit are left out)");
    }
    let base_config = load(&a.config)?;
    if base_config.wall.mode == WallMode::Object {
        bail!(
            "{}: an object-space wall splits the volume, not the tiles: `bench balance` is for screen space",
            base_config.path.display()
        );
    }
    // The config as it is, balanced, its paths made absolute: the nodes read this copy.
    let mut c = base_config.clone();
    c.wall.balance = true;
    c.volume.source = base_config.volume_source();
    c.render.env = base_config.env_source();
    c.certificates.dir = std::path::absolute(base_config.cert_dir())?.to_string_lossy().into_owned();
    if let Some(ms) = a.deadline_ms {
        c.wall.deadline_ms = ms;
    }
    // A wall of other machines (e.g. sva-4) is measured here: its nodes on free loopback ports.
    for n in c.nodes.iter_mut().filter(|n| !is_loopback(&n.address)) {
        let port = std::net::UdpSocket::bind("127.0.0.1:0")
            .and_then(|s| s.local_addr())
            .context("cannot find a free loopback port")?
            .port();
        println!("isowall bench balance: node {} ({}) runs here on 127.0.0.1:{port}", n.name, n.address);
        n.address = format!("127.0.0.1:{port}");
    }
    let dir = tempfile_dir()?;
    let file = dir.join(format!("{}.balanced.toml", c.wall.name));
    std::fs::write(&file, toml::to_string(&c)?)
        .with_context(|| format!("cannot write {}", file.display()))?;
    let config = load(&file)?;
    let (base, mut settings) = scene(&config)?;
    if let Some(k) = a.samples {
        if k > isowall_model::render_state::MAX_AO_SAMPLES {
            bail!("--samples {k} is over the limit of {}", isowall_model::render_state::MAX_AO_SAMPLES);
        }
        settings.ao.samples = k;
    }
    let daemons = LocalDaemons::start(&config, &dir.join("logs"), "offscreen", false)?;
    println!(
        "isowall bench balance: wall '{}' ({} nodes, {} tiles), {} frames of an orbit ({} degrees/frame) per run \
         at 1/{} scale, {} AO samples, deadline {} ms, offscreen; work = the costs a node's rectangles reported \
         (fetches + {} per pixel)",
        config.wall.name,
        config.nodes.len(),
        config.tiles.len(),
        a.frames,
        a.degrees_per_frame,
        a.scale,
        settings.ao.samples,
        config.wall.deadline_ms,
        isowall_model::balance::node::PIXEL_FETCHES
    );
    let rt = runtime()?;
    let ratios = rt.block_on(async {
        let mut wall =
            Wall::connect(config, Duration::from_secs(a.start_timeout), Duration::from_secs(a.start_timeout))
                .await?;
        let mut ratios = Vec::new();
        for (name, on) in [("unbalanced", false), ("balanced", true)] {
            wall.set_balance(on);
            let first = wall.last_frame_id() + 1;
            let changes_before = wall.split().map_or(0, |s| s.2);
            wall.sync_clocks(3).await;
            let start = Instant::now();
            for k in 0..a.frames {
                let camera = orbit_camera(&base, k, a.degrees_per_frame);
                wall.frame(&FrameRequest { scale: a.scale, ..FrameRequest::new(camera, settings) }).await?;
            }
            let elapsed = start.elapsed();
            wall.settle().await;
            let ids = first + BALANCE_SETTLE_FRAMES as u64..=wall.last_frame_id();
            let fps = a.frames as f64 / elapsed.as_secs_f64().max(1e-9);
            let changes = wall.split().map_or(0, |s| s.2) - changes_before;
            ratios.push(print_balance_run(&wall, name, ids, fps, (changes, a.frames)));
        }
        wall.close("the bench is done").await;
        Ok::<Vec<f64>, anyhow::Error>(ratios)
    });
    drop(daemons);
    let ratios = ratios?;
    println!("balance: slowest/mean {:.3} unbalanced, {:.3} balanced", ratios[0], ratios[1]);
    Ok(())
}

/// Prints one run of `bench balance`: per node its work and bytes sent per frame over the frames
/// `ids`, the split's rows moved, the fps, how many of the run's `frames` changed the split.
/// Returns the slowest node's work over the mean,
/// averaged over those frames.
fn print_balance_run(
    wall: &Wall,
    name: &str,
    ids: std::ops::RangeInclusive<u64>,
    fps: f64,
    (changes, frames): (u64, u64),
) -> f64 {
    let mut per_node: std::collections::BTreeMap<&str, (Vec<u64>, Vec<u64>)> =
        wall.config.nodes.iter().map(|n| (n.name.as_str(), (Vec::new(), Vec::new()))).collect();
    let mut ratios = Vec::new();
    for id in ids.clone() {
        let Some(work) = wall.work(id) else { continue };
        let n = per_node.len().max(1) as f64;
        let mean = per_node.keys().map(|k| work.get(*k).copied().unwrap_or(0) as f64).sum::<f64>() / n;
        let max = per_node.keys().map(|k| work.get(*k).copied().unwrap_or(0)).max().unwrap_or(0) as f64;
        if mean > 0.0 {
            ratios.push(max / mean);
        }
        for (node, (w, _)) in per_node.iter_mut() {
            w.push(work.get(*node).copied().unwrap_or(0));
        }
    }
    for f in wall.finished.iter().filter(|f| ids.contains(&f.frame_id)) {
        for s in &f.per_node {
            if let (Some(b), Some(e)) = (s.bytes_sent, per_node.get_mut(s.node.as_str())) {
                e.1.push(b);
            }
        }
    }
    let ratio = ratios.iter().sum::<f64>() / ratios.len().max(1) as f64;
    let moved = wall.split().map_or(0, |(_, rows, _)| rows);
    let (misses, held) = wall.held_out().unwrap_or_default();
    println!(
        "\n== {name}: {fps:.2} fps; slowest/mean work {ratio:.3} (mean of {} frames); rows rendered away from their tile's node in the last split: {moved}; the split changed {changes} times in the run's {frames} frames; nodes held out of the split since the wall came up: {misses} times{}",
        ratios.len(),
        if held.is_empty() { String::new() } else { format!(" ({} now)", held.join(", ")) },
    );
    let median = |mut v: Vec<u64>| {
        v.sort_unstable();
        v.get(v.len().saturating_sub(1) / 2).copied().unwrap_or(0)
    };
    for (node, (work, bytes)) in per_node {
        println!(
            "  {node}: work p50 {:.2} M per frame; sent p50 {} B per frame",
            median(work) as f64 / 1e6,
            median(bytes)
        );
    }
    ratio
}

/// `bench --swap`: one wall, three runs of the same orbit: untimed, timed, timed and paced.
fn bench_swap(a: &BenchArgs, config: WallConfig) -> Result<()> {
    use crate::drive::{drive, OrbitOptions};
    use isowall_model::swap_timing::{MarginSetting, SwapTiming};
    if !(a.paced_fps > 0.0 && a.paced_fps <= isowall_model::config::MAX_FRAME_RATE) {
        bail!("--paced-fps {} is not in (0, {}]", a.paced_fps, isowall_model::config::MAX_FRAME_RATE);
    }
    let (base, settings) = scene(&config)?;
    let log_dir = config.resolve("logs");
    let mut daemons = crate::local::LocalDaemons::start(&config, &log_dir, "offscreen", false)?;
    daemons.wait_started(Duration::from_secs(a.start_timeout));
    println!(
        "isowall bench --swap: wall '{}' ({} nodes{}), {} frames of an orbit ({} degrees/frame) per run, offscreen",
        config.wall.name,
        config.nodes.len(),
        if crate::wall::one_machine(&config) { ", every one on this machine" } else { "" },
        a.frames,
        a.degrees_per_frame
    );
    let runs = [
        ("untimed", SwapTiming::new(MarginSetting::Off, None)),
        ("timed", SwapTiming::new(MarginSetting::Auto, None)),
        ("timed, paced", SwapTiming::new(MarginSetting::Auto, Some(a.paced_fps))),
    ];
    let rt = runtime()?;
    rt.block_on(async {
        let mut wall =
            Wall::connect(config, Duration::from_secs(a.start_timeout), Duration::from_secs(5)).await?;
        for (name, timing) in runs {
            wall.set_swap_timing(timing);
            let o = OrbitOptions {
                frames: a.frames,
                degrees_per_frame: a.degrees_per_frame,
                fps: 0.0,
                target_frame_ms: None,
                still_frames: 0,
                record_frames: None,
                step: 0,
                play: false,
            };
            let (elapsed, _, _) = drive(&mut wall, &base, &settings, &o, None, &mut |_, _| {}).await?;
            println!(
                "\n== {name}: {} frames in {:.2} s ({:.2} fps)",
                a.frames,
                elapsed.as_secs_f64(),
                a.frames as f64 / elapsed.as_secs_f64().max(1e-9)
            );
            print!("{}", crate::report::swap_report(&wall));
        }
        wall.close("the bench is done").await;
        Ok::<(), anyhow::Error>(())
    })
}

/// How the wall splits the work.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Screen,
    Object,
}

impl Mode {
    fn parse(s: &str) -> Mode {
        if s == "object" {
            Mode::Object
        } else {
            Mode::Screen
        }
    }
    fn name(self) -> &'static str {
        match self {
            Mode::Screen => "screen space (sort-first: one strip of the image per node)",
            Mode::Object => "object space (sort-last: one brick of the volume per node)",
        }
    }
}

/// One cell's measurement.
#[derive(Debug, Clone, PartialEq)]
pub enum Cell {
    Measured {
        fps: f64,
        slowest_render: Duration,
        per_node: Vec<(String, Duration)>,
    },
    /// Not measured, and why.
    NotAvailable(String),
}

/// RTPara's published frames per second (../shared/DESIGN.md, the 'engine' volume 256x256x118,
/// HP SVA, one GeForce 8600GT per node), by AO samples and node count; `None` where unpublished.
pub fn rtpara_2008(samples: u32, nodes: usize) -> Option<f64> {
    let row: [f64; 4] = match samples {
        32 => [3.6, 6.8, 9.8, 12.9],
        64 => [1.9, 3.8, 5.4, 7.1],
        128 => [1.0, 2.0, 2.9, 4.0],
        256 => [0.5, 1.0, 1.5, 2.0],
        _ => return None,
    };
    nodes.checked_sub(1).and_then(|i| row.get(i).copied())
}

/// The table as Markdown: one row per sample count, one column per node count; a cell reads
/// `ours FPS fps (render MS ms) | 2008 FPS` with "—" where 2008 has no figure (or `engine` is
/// false: another volume than the 2008 one).
pub fn format_table(
    mode: Mode,
    samples: &[u32],
    nodes: &[usize],
    cells: &[Vec<Cell>],
    engine: bool,
) -> String {
    let mut s = format!("{}\n\n| AO samples |", mode.name());
    for n in nodes {
        s += &format!(" {n} node{}: ours | 2008 |", if *n == 1 { "" } else { "s" });
    }
    s += "\n|---|";
    s += &"---|---|".repeat(nodes.len());
    s += "\n";
    for (r, &k) in samples.iter().enumerate() {
        s += &format!("| {k} |");
        for (c, &n) in nodes.iter().enumerate() {
            let ours = match &cells[r][c] {
                Cell::Measured { fps, slowest_render, .. } => {
                    format!("{fps:.2} fps (render {:.0} ms)", slowest_render.as_secs_f64() * 1e3)
                }
                Cell::NotAvailable(why) => format!("n/a ({why})"),
            };
            let then = rtpara_2008(k, n).filter(|_| engine).map_or("—".to_string(), |f| format!("{f}"));
            s += &format!(" {ours} | {then} |");
        }
        s += "\n";
    }
    s
}

/// Vertical strips covering `width` x `height`, one per node, widths differing by at most one.
pub fn strips(width: u32, height: u32, n: usize) -> Vec<TileConfig> {
    let n = n as u32;
    (0..n)
        .map(|i| {
            let (x0, x1) = (i * width / n, (i + 1) * width / n);
            TileConfig { name: format!("strip{i}"), x: x0, y: 0, width: x1 - x0, height, bezel: [0; 4] }
        })
        .collect()
}

/// The wall config of one column: the first `n` nodes, each driving one strip; absolute paths
/// for the volume, environment and certificates (the file lives in a temporary folder).
fn column_config(base: &WallConfig, n: usize, (w, h): (u32, u32)) -> Result<WallConfig> {
    let mut c = base.clone();
    c.volume.source = base.volume_source();
    c.render.env = base.env_source();
    c.certificates.dir = std::path::absolute(base.cert_dir())?.to_string_lossy().into_owned();
    c.tiles = strips(w, h, n);
    c.nodes = base.nodes[..n].to_vec();
    for (node, tile) in c.nodes.iter_mut().zip(&c.tiles) {
        node.tiles = vec![tile.name.clone()];
    }
    c.wall.name = format!("{}-bench-{n}", base.wall.name);
    Ok(c)
}

/// Runs one column: starts its daemons, measures every row, stops them.
fn measure_column(a: &BenchArgs, config: &WallConfig, dir: &Path) -> Result<Vec<Cell>> {
    let file = dir.join(format!("{}.toml", config.wall.name));
    std::fs::write(&file, toml::to_string(config)?)
        .with_context(|| format!("cannot write {}", file.display()))?;
    let config = load(&file)?;
    let (base, settings) = scene(&config)?;
    let daemons = LocalDaemons::start(&config, &dir.join("logs"), "offscreen", false)?;
    let rt = runtime()?;
    let cells = rt.block_on(async {
        let mut wall =
            Wall::connect(config, Duration::from_secs(a.start_timeout), Duration::from_secs(a.start_timeout))
                .await?;
        let mut cells = Vec::new();
        for &k in &a.samples {
            let mut s = settings;
            s.ao.samples = k;
            wall.frame(&FrameRequest::new(orbit_camera(&base, 0, a.degrees_per_frame), s)).await?;
            wall.settle().await;
            let first = wall.finished.len();
            let start = Instant::now();
            for f in 1..=a.frames {
                wall.frame(&FrameRequest::new(orbit_camera(&base, f, a.degrees_per_frame), s)).await?;
            }
            let elapsed = start.elapsed();
            wall.settle().await;
            let mut per_node: Vec<(String, Duration)> = wall
                .config
                .nodes
                .iter()
                .map(|n| {
                    let times: Vec<Duration> = wall.finished[first..]
                        .iter()
                        .flat_map(|f| f.per_node.iter().filter(|p| p.node == n.name).filter_map(|p| p.render))
                        .collect();
                    (n.name.clone(), quantile(times, 0.5).unwrap_or_default())
                })
                .collect();
            per_node.sort_by(|x, y| x.0.cmp(&y.0));
            let slowest = per_node.iter().map(|p| p.1).max().unwrap_or_default();
            let fps = a.frames as f64 / elapsed.as_secs_f64().max(1e-9);
            eprintln!(
                "isowall bench: {} node(s), {k} AO samples: {fps:.2} fps, slowest node render {:.0} ms",
                wall.config.nodes.len(),
                slowest.as_secs_f64() * 1e3
            );
            cells.push(Cell::Measured { fps, slowest_render: slowest, per_node });
        }
        wall.close("the bench is done").await;
        Ok::<_, anyhow::Error>(cells)
    });
    drop(daemons);
    cells
}

pub fn bench(a: &BenchArgs) -> Result<()> {
    if let Some(BenchCommand::Balance(b)) = &a.what {
        return bench_balance(b);
    }
    let Some(config_path) = &a.config else { bail!("say which wall config to measure") };
    if !a.table && !a.swap {
        bail!(
            "say what to measure: `isowall bench CONFIG --table` (the report's table) or `--swap` (the swap's \
             skew untimed, timed and paced)"
        );
    }
    if a.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let config = load(config_path)?;
    if a.swap {
        return bench_swap(a, config);
    }
    if let Some(n) = config.nodes.iter().find(|n| !is_loopback(&n.address)) {
        bail!(
            "{}: node {} at {} is not on loopback: `bench --table` starts its own local nodes for every column",
            config.path.display(),
            n.name,
            n.address
        );
    }
    let nodes: Vec<usize> =
        if a.nodes.is_empty() { (1..=config.nodes.len()).collect() } else { a.nodes.clone() };
    if let Some(&bad) = nodes.iter().find(|&&n| n == 0 || n > config.nodes.len()) {
        bail!("--nodes {bad}: the wall has {} node(s)", config.nodes.len());
    }
    if let Some(&bad) = a.samples.iter().find(|&&k| k > isowall_model::render_state::MAX_AO_SAMPLES) {
        bail!("--samples {bad} is over the limit of {}", isowall_model::render_state::MAX_AO_SAMPLES);
    }
    let engine = config.volume_source() == "procedural:engine";
    let dir = tempfile_dir()?;
    println!(
        "isowall bench --table: wall '{}', volume {}, image {}x{} split over 1..N nodes, {} timed frame(s) \
         of an orbit ({} degrees/frame) per cell after a warm-up frame; fps = frames / time to the last \
         swap; render = the slowest node's median render time",
        config.wall.name,
        config.volume_source(),
        a.size.0,
        a.size.1,
        a.frames,
        a.degrees_per_frame
    );
    let modes: Vec<Mode> = a.modes.iter().map(|m| Mode::parse(m)).collect();
    let mut details = String::new();
    for mode in modes {
        let mut columns: Vec<Vec<Cell>> = Vec::new();
        for &n in &nodes {
            let mut c = column_config(&config, n, a.size)?;
            c.wall.mode = match mode {
                Mode::Screen => WallMode::Screen,
                Mode::Object => WallMode::Object,
            };
            columns.push(measure_column(a, &c, &dir).unwrap_or_else(|e| {
                eprintln!("isowall bench: {} node(s), {}: {e:#}", n, mode.name());
                vec![
                    Cell::NotAvailable(format!("{e:#}").lines().next().unwrap_or("failed").to_string());
                    a.samples.len()
                ]
            }));
        }
        // Rows by sample count.
        let cells: Vec<Vec<Cell>> =
            (0..a.samples.len()).map(|r| columns.iter().map(|c| c[r].clone()).collect()).collect();
        println!("\n{}", format_table(mode, &a.samples, &nodes, &cells, engine));
        for (r, k) in a.samples.iter().enumerate() {
            for (c, n) in nodes.iter().enumerate() {
                if let Cell::Measured { per_node, .. } = &cells[r][c] {
                    let list: Vec<String> = per_node
                        .iter()
                        .map(|(name, t)| format!("{name} {:.0} ms", t.as_secs_f64() * 1e3))
                        .collect();
                    details += &format!("  {k} samples, {n} node(s): {}\n", list.join(", "));
                }
            }
        }
    }
    if !details.is_empty() {
        println!("per-node median render time:\n{details}");
    }
    if engine {
        println!(
            "2008: RTPara, HP Scalable Visualization Array, one GeForce 8600GT per node, the 'engine' \
             volume 256x256x118 (../shared/DESIGN.md; its image size is not stated); \"—\": no published figure."
        );
    } else {
        println!(
            "2008: \"—\" throughout: RTPara's figures are for the 'engine' volume (procedural:engine here)."
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// A fresh folder for the columns' configs and logs.
fn tempfile_dir() -> Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!("isowall-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    Ok(dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_2008_figures_are_the_published_ones_and_nothing_else() {
        assert_eq!(rtpara_2008(32, 1), Some(3.6));
        assert_eq!(rtpara_2008(256, 4), Some(2.0));
        assert_eq!(rtpara_2008(128, 3), Some(2.9));
        assert_eq!(rtpara_2008(32, 5), None);
        assert_eq!(rtpara_2008(16, 1), None);
        assert_eq!(rtpara_2008(64, 0), None);
    }

    #[test]
    fn the_table_puts_2008_beside_ours_and_dashes_where_unpublished() {
        let m =
            |fps: f64| Cell::Measured { fps, slowest_render: Duration::from_millis(250), per_node: vec![] };
        let cells =
            vec![vec![m(1.5), m(2.25)], vec![m(0.5), Cell::NotAvailable("object mode not built".into())]];
        let t = format_table(Mode::Screen, &[32, 512], &[1, 5], &cells, true);
        let rows: Vec<&str> = t.lines().filter(|l| l.starts_with("| ")).collect();
        assert_eq!(rows[0], "| AO samples | 1 node: ours | 2008 | 5 nodes: ours | 2008 |");
        assert_eq!(rows[1], "| 32 | 1.50 fps (render 250 ms) | 3.6 | 2.25 fps (render 250 ms) | — |");
        assert_eq!(rows[2], "| 512 | 0.50 fps (render 250 ms) | — | n/a (object mode not built) | — |");
        let other = format_table(Mode::Screen, &[32], &[1], &[vec![m(1.0)]], false);
        assert!(other.contains("| 32 | 1.00 fps (render 250 ms) | — |"), "{other}");
    }

    #[test]
    fn strips_cover_the_image_exactly() {
        let s = strips(100, 30, 3);
        assert_eq!(s.iter().map(|t| t.width).sum::<u32>(), 100);
        assert_eq!((s[0].x, s[1].x, s[2].x), (0, 33, 66));
        assert!(s.iter().all(|t| t.height == 30 && t.y == 0));
        for w in s.windows(2) {
            assert_eq!(w[0].x + w[0].width, w[1].x);
        }
    }
}
