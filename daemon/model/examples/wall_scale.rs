//! The wall at scale (docs/scale.md): the model's machines on the simulated LAN at 4, 16, 64 and
//! 256 nodes, the compositing schedules beside direct-send, and load-balanced screen space on
//! walls of 4 to 64 nodes (docs/balance.md). Prints the tables and writes
//! `docs/scale/*.csv` and `docs/scale/*.svg` (or into the folder given as the first argument).
//!
//! `cargo run -p isowall-model --release --example wall_scale [OUT_DIR]`

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Duration;

use isowall_model::sim::radix::factors;
use isowall_model::sim::screen::percentiles;
use isowall_model::sim::{
    measured_costs, run_balance, run_balance_on, run_object, run_radix, run_screen, BalanceFrame,
    BalanceSpec, LanModel, ObjectSpec, ObjectWall, PixelCost, RadixReport, Scene, ScreenSpec, Transfer,
};

const NODES: [usize; 4] = [4, 16, 64, 256];
/// The machines' tile divisor per node count (1080p tiles / divisor; bytes sized for 1080p).
const DIVISOR: [u32; 4] = [2, 4, 8, 15];
const SEED: u64 = 2026;
/// The schedules' CSV columns.
const HEADER: &str =
    "nodes,schedule,rounds,messages_per_node,sent_mb_mean,sent_mb_max,received_mb_max,composite_max_ms\n";

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn mb(b: f64) -> f64 {
    b / 1e6
}

struct Series {
    name: String,
    points: Vec<(f64, f64)>,
}

/// A line chart, log2 x axis, linear or log10 y axis, written as text.
fn svg(title: &str, x_label: &str, y_label: &str, series: &[Series], log_y: bool) -> String {
    let (w, h, l, r, t, b) = (760.0, 440.0, 70.0, 220.0, 40.0, 60.0);
    let pts = series.iter().flat_map(|s| s.points.iter().copied());
    let fy = |y: f64| if log_y { y.max(1e-9).log10() } else { y };
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (x, y) in pts {
        x0 = x0.min(x.log2());
        x1 = x1.max(x.log2());
        y0 = y0.min(fy(y));
        y1 = y1.max(fy(y));
    }
    if !log_y {
        y0 = 0.0;
    } else {
        y0 = y0.floor();
        y1 = y1.ceil();
    }
    if y1 <= y0 {
        y1 = y0 + 1.0;
    }
    y1 += (y1 - y0) * 0.05 * f64::from(u8::from(!log_y));
    let px = |x: f64| l + (x.log2() - x0) / (x1 - x0).max(1e-9) * (w - l - r);
    let py = |y: f64| h - b - (fy(y) - y0) / (y1 - y0) * (h - t - b);
    let colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"];
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"12\">\n\
         <rect width=\"{w}\" height=\"{h}\" fill=\"white\"/>\n<text x=\"{}\" y=\"24\" text-anchor=\"middle\" font-size=\"15\">{title}</text>\n",
        (w - r + l) / 2.0
    );
    let _ =
        writeln!(s, "<line x1=\"{l}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"black\"/>", h - b, w - r, h - b);
    let _ = writeln!(s, "<line x1=\"{l}\" y1=\"{t}\" x2=\"{l}\" y2=\"{}\" stroke=\"black\"/>", h - b);
    let mut xe = x0.ceil() as i32;
    while f64::from(xe) <= x1 + 1e-9 {
        let x = 2f64.powi(xe);
        let _ = writeln!(
            s,
            "<line x1=\"{0}\" y1=\"{1}\" x2=\"{0}\" y2=\"{t}\" stroke=\"#ddd\"/><text x=\"{0}\" y=\"{2}\" text-anchor=\"middle\">{3}</text>",
            px(x),
            h - b,
            h - b + 16.0,
            x
        );
        xe += if x1 - x0 > 8.0 { 2 } else { 1 };
    }
    // Ticks: every power of ten (log), or a 1-2-5 step (linear).
    let ticks: Vec<(f64, String)> = if log_y {
        (y0 as i32..=y1 as i32).map(|e| (10f64.powi(e), format!("{}", 10f64.powi(e)))).collect()
    } else {
        let raw = (y1 - y0) / 5.0;
        let mag = 10f64.powf(raw.log10().floor());
        let step = [1.0, 2.0, 5.0, 10.0].into_iter().map(|m| m * mag).find(|s| *s >= raw).unwrap_or(raw);
        (0..)
            .map(|i| f64::from(i) * step)
            .take_while(|v| *v <= y1 + 1e-9)
            .map(|v| (v, format!("{}", (v * 1e6).round() / 1e6)))
            .collect()
    };
    for (y, label) in ticks {
        let _ = writeln!(
            s,
            "<line x1=\"{l}\" y1=\"{0}\" x2=\"{1}\" y2=\"{0}\" stroke=\"#ddd\"/><text x=\"{2}\" y=\"{3}\" text-anchor=\"end\">{label}</text>",
            py(y),
            w - r,
            l - 6.0,
            py(y) + 4.0
        );
    }
    let _ = writeln!(
        s,
        "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{x_label}</text>",
        (w - r + l) / 2.0,
        h - 16.0
    );
    let _ = writeln!(
        s,
        "<text x=\"14\" y=\"{0}\" text-anchor=\"middle\" transform=\"rotate(-90 14 {0})\">{y_label}</text>",
        (h - b + t) / 2.0
    );
    for (i, se) in series.iter().enumerate() {
        let c = colours[i % colours.len()];
        let path: Vec<String> =
            se.points.iter().map(|&(x, y)| format!("{:.1},{:.1}", px(x), py(y))).collect();
        let _ = writeln!(
            s,
            "<polyline fill=\"none\" stroke=\"{c}\" stroke-width=\"2\" points=\"{}\"/>",
            path.join(" ")
        );
        for &(x, y) in &se.points {
            let _ = writeln!(s, "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"{c}\"/>", px(x), py(y));
        }
        let ly = t + 10.0 + 20.0 * i as f64;
        let _ = writeln!(
            s,
            "<line x1=\"{0}\" y1=\"{ly}\" x2=\"{1}\" y2=\"{ly}\" stroke=\"{c}\" stroke-width=\"2\"/><text x=\"{2}\" y=\"{3}\">{4}</text>",
            w - r + 10.0,
            w - r + 30.0,
            w - r + 36.0,
            ly + 4.0,
            se.name
        );
    }
    s + "</svg>\n"
}

/// Prints one schedule's row and adds it to `csv`: (max MB sent, max compositing ms).
fn radix_row(n: usize, name: &str, r: &RadixReport, csv: &mut String) -> (f64, f64) {
    let (sm, sx) = r.mean_max(|x| x.sent_bytes as f64);
    let (_, rx) = r.mean_max(|x| x.received_bytes as f64);
    let (msgs, _) = r.mean_max(|x| x.sent_messages as f64);
    let (_, tx) = r.mean_max(|x| x.done.as_secs_f64() * 1e3);
    let rounds = r.factors.len();
    println!(
        "| {n} | {name} | {rounds} | {msgs:.0} | {:.2} | {:.2} | {:.2} | {tx:.2} ms |",
        mb(sm),
        mb(sx),
        mb(rx)
    );
    let _ = writeln!(csv, "{n},{name},{rounds},{msgs:.1},{:.4},{:.4},{:.4},{tx:.4}", mb(sm), mb(sx), mb(rx));
    (mb(sx), tx)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../docs/scale"));
    std::fs::create_dir_all(&out)?;
    let lan = LanModel::ten_gbe();
    let cost = PixelCost::memory_bound();
    println!(
        "LAN: {:?} one way + up to {:?} jitter, {} Gbit/s per link, {:?} per message, {}+{} bytes per packet, loss {} per packet",
        lan.latency,
        lan.jitter,
        lan.bandwidth_bps / 1e9,
        lan.per_message,
        lan.packet_payload,
        lan.packet_overhead,
        lan.loss
    );

    // ---- screen space ----
    let mut csv = String::from("nodes,frames,barrier_median_ms,barrier_p99_ms,barrier_max_ms,skew_measured_median_ms,skew_measured_max_ms,skew_true_median_ms,skew_true_max_ms,stragglers,retransmitted\n");
    println!("\nscreen space: FrameController + N NodeMachines, 10 ms renders + [0, 1) ms, 60 frames");
    println!("| nodes | barrier median | p99 | max | swap skew measured median | max | true median | max | stragglers |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut barrier_series = (Vec::new(), Vec::new());
    let mut skew_series = (Vec::new(), Vec::new());
    for n in NODES {
        let r = run_screen(&ScreenSpec::new(n, SEED));
        if !r.errors.is_empty() {
            return Err(format!("{n} nodes: {:?}", r.errors).into());
        }
        let barriers: Vec<Duration> = r.frames.iter().map(|f| f.barrier).collect();
        let measured: Vec<Duration> = r.frames.iter().filter_map(|f| f.swap_skew).collect();
        let truth: Vec<Duration> = r.frames.iter().filter_map(|f| f.true_skew).collect();
        let (bm, b99, bmax) = percentiles(&barriers);
        let (sm, _, smax) = percentiles(&measured);
        let (tm, _, tmax) = percentiles(&truth);
        let stragglers: usize = r.frames.iter().map(|f| f.stragglers).sum();
        println!(
            "| {n} | {:.3} ms | {:.3} ms | {:.3} ms | {:.3} ms | {:.3} ms | {:.3} ms | {:.3} ms | {stragglers} |",
            ms(bm), ms(b99), ms(bmax), ms(sm), ms(smax), ms(tm), ms(tmax)
        );
        let _ = writeln!(
            csv,
            "{n},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{stragglers},{}",
            r.frames.len(),
            ms(bm),
            ms(b99),
            ms(bmax),
            ms(sm),
            ms(smax),
            ms(tm),
            ms(tmax),
            r.lan.retransmitted
        );
        barrier_series.0.push((n as f64, ms(bm)));
        barrier_series.1.push((n as f64, ms(b99)));
        skew_series.0.push((n as f64, ms(sm)));
        skew_series.1.push((n as f64, ms(tm)));
    }
    std::fs::write(out.join("screen.csv"), &csv)?;
    let charts = [
        (
            "screen_barrier.svg",
            "barrier time",
            [("barrier median", barrier_series.0), ("barrier p99", barrier_series.1)],
        ),
        (
            "screen_skew.svg",
            "swap skew",
            [("measured (median)", skew_series.0), ("true (median)", skew_series.1)],
        ),
    ];
    for (file, what, lines) in charts {
        let series: Vec<Series> =
            lines.into_iter().map(|(name, points)| Series { name: name.into(), points }).collect();
        let title = format!("Screen space: {what} per frame (10 GbE model)");
        std::fs::write(out.join(file), svg(&title, "nodes", "milliseconds", &series, false))?;
    }

    // ---- object space: the machines, direct send ----
    println!(
        "\nobject space: N ObjectMachines, direct-send of 1080p tiles (raw), 3 frames; per node per frame"
    );
    println!("| nodes | divisor | sent MB mean | max | received MB mean | max | messages sent | compositing mean | max |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut csv = String::from("nodes,divisor,sent_mb_mean,sent_mb_max,received_mb_mean,received_mb_max,messages_per_node,composite_mean_ms,composite_max_ms\n");
    let mut machine_rows = Vec::new();
    for (n, d) in NODES.into_iter().zip(DIVISOR) {
        let r = run_object(&ObjectSpec::new(n, d, SEED))?;
        if !r.errors.is_empty() {
            return Err(format!("{n} nodes: {:?}", &r.errors[..r.errors.len().min(3)]).into());
        }
        let (sm, sx) = r.mean_max(|s| s.sent_bytes as f64);
        let (rm, rx) = r.mean_max(|s| s.received_bytes as f64);
        let (msgs, _) = r.mean_max(|s| s.sent_messages as f64);
        let (cm, cx) = r.mean_max(|s| s.composite.as_secs_f64() * 1e3);
        println!(
            "| {n} | {d} | {:.2} | {:.2} | {:.2} | {:.2} | {msgs:.0} | {cm:.2} ms | {cx:.2} ms |",
            mb(sm),
            mb(sx),
            mb(rm),
            mb(rx)
        );
        let _ = writeln!(
            csv,
            "{n},{d},{:.4},{:.4},{:.4},{:.4},{msgs:.1},{cm:.4},{cx:.4}",
            mb(sm),
            mb(sx),
            mb(rm),
            mb(rx)
        );
        machine_rows.push((n, mb(sm), mb(sx), mb(rx), cx));
    }
    std::fs::write(out.join("object.csv"), &csv)?;

    // ---- the schedules over the same footprints, full resolution ----
    println!(
        "\ncompositing schedules on the same LAN, wall of N 1080p tiles (footprints at full resolution)"
    );
    println!("| nodes | schedule | rounds | messages per node | sent MB mean | max | received MB max | compositing max |");
    println!("|---|---|---|---|---|---|---|---|");
    let mut csv = String::from(HEADER);
    let mut bytes_series: Vec<Series> = ["direct-send", "binary swap", "radix-k (k=8)"]
        .iter()
        .map(|n| Series { name: format!("{n}: max sent"), points: Vec::new() })
        .collect();
    let mut time_series: Vec<Series> =
        ["direct-send", "binary swap", "radix-k (k=8)", "direct-send on 1 GbE"]
            .iter()
            .map(|n| Series { name: n.to_string(), points: Vec::new() })
            .collect();
    for n in [4usize, 16, 64, 256, 1024] {
        let scene = Scene::wall(&ObjectWall::new(n, 1)?);
        for (i, (name, f)) in
            [("direct-send", vec![n]), ("binary swap", factors(n, 2)), ("radix-k (k=8)", factors(n, 8))]
                .into_iter()
                .enumerate()
        {
            let r = run_radix(&scene, &f, lan, cost, SEED);
            let (bytes, t) = radix_row(n, name, &r, &mut csv);
            bytes_series[i].points.push((n as f64, bytes));
            time_series[i].points.push((n as f64, t));
        }
        let r = run_radix(&scene, &[n], LanModel::one_gbe(), cost, SEED);
        let (_, t) = radix_row(n, "direct-send on 1 GbE", &r, &mut csv);
        time_series[3].points.push((n as f64, t));
    }
    bytes_series.push(Series {
        name: "machines: max sent".into(),
        points: machine_rows.iter().map(|&(n, _, sx, _, _)| (n as f64, sx)).collect(),
    });
    time_series.push(Series {
        name: "machines (direct-send)".into(),
        points: machine_rows.iter().map(|&(n, _, _, _, cx)| (n as f64, cx)).collect(),
    });
    std::fs::write(out.join("schedules.csv"), &csv)?;
    std::fs::write(
        out.join("object_bytes.svg"),
        svg(
            "Object space: bytes sent per node per frame, 1080p tiles",
            "nodes",
            "MB (log scale)",
            &bytes_series,
            true,
        ),
    )?;
    std::fs::write(
        out.join("object_time.svg"),
        svg(
            "Object space: compositing time per frame (10 GbE unless named)",
            "nodes",
            "ms (log scale)",
            &time_series,
            true,
        ),
    )?;

    // ---- IceT's setting: one 64-megapixel image over many processes ----
    println!("\none 8192x8192 image (IceT's setting) over N bricks, same LAN and pixel costs");
    println!("| nodes | schedule | rounds | messages per node | sent MB mean | max | received MB max | compositing max |");
    println!("|---|---|---|---|---|---|---|---|");
    let mut csv = String::from(HEADER);
    let mut sweep: Vec<Series> = ["direct-send", "binary swap", "radix-k (k=8)", "radix-k (k=32)"]
        .iter()
        .map(|n| Series { name: n.to_string(), points: Vec::new() })
        .collect();
    for n in [64usize, 256, 1024, 2048, 32768] {
        let scene = Scene::image(8192, 8192, n)?;
        // Direct-send's N^2 messages only up to 2048 nodes (its floor at 32K is below).
        let direct = (n <= 2048).then(|| ("direct-send", vec![n]));
        let wide = (n >= 1024).then(|| ("radix-k (k=32)", factors(n, 32)));
        let schedules =
            [direct, Some(("binary swap", factors(n, 2))), Some(("radix-k (k=8)", factors(n, 8))), wide];
        for (name, f) in schedules.into_iter().flatten() {
            let r = run_radix(&scene, &f, lan, cost, SEED);
            let (_, t) = radix_row(n, name, &r, &mut csv);
            if let Some(s) = sweep.iter_mut().find(|s| s.name == name) {
                s.points.push((n as f64, t));
            }
        }
    }
    let n = 32768;
    let floor = ms(lan.per_message * (n as u32 - 1));
    println!("| {n} | direct-send | 1 | {} | - | - | - | >= {floor:.1} ms (its messages' per-message cost alone) |", n - 1);
    let _ = writeln!(csv, "{n},direct-send (per-message floor),1,{},,,,{floor:.4}", n - 1);
    sweep.push(Series { name: "direct-send floor".into(), points: vec![(n as f64, floor)] });
    std::fs::write(out.join("icet.csv"), &csv)?;
    std::fs::write(
        out.join("icet_time.svg"),
        svg(
            "One 64-megapixel image: compositing time (10 GbE model)",
            "processes",
            "ms (log scale)",
            &sweep,
            true,
        ),
    )?;
    println!("\nwrote {}", out.display());
    balance_table(&out)?;
    Ok(())
}

/// Load-balanced screen space (`sim::balance`): per wall and orbit speed, means from frame 8 on.
fn balance_table(out: &std::path::Path) -> Result<(), Box<dyn std::error::Error>> {
    let mean =
        |f: &[BalanceFrame], g: &dyn Fn(&BalanceFrame) -> f64| f.iter().map(g).sum::<f64>() / f.len() as f64;
    let mut csv = String::from(
        "cols,rows,degrees,unbalanced_slowest_over_mean,balanced_slowest_over_mean,unbalanced_ms,balanced_ms,ideal_ms,moved_mpixels\n",
    );
    println!("\nload-balanced screen space: 1080p tiles, one node each, a scan in the middle, 60 frames; means over frames 8-59");
    println!("| wall | degrees/frame | slowest/mean unbalanced | balanced | frame ms unbalanced | balanced | ideal | Mpixels moved |");
    println!("|---|---|---|---|---|---|---|---|");
    for (cols, rows) in [(2, 2), (4, 2), (6, 4), (8, 8)] {
        for degrees in [0.0, 1.0, 3.0] {
            let mut spec = BalanceSpec::new(cols, rows);
            spec.degrees = degrees;
            let frames = run_balance(&spec);
            let f = &frames[8..];
            let row = [
                mean(f, &|f| f.unbalanced),
                mean(f, &|f| f.balanced),
                mean(f, &|f| f.unbalanced_ms),
                mean(f, &|f| f.balanced_ms),
                mean(f, &|f| f.ideal_ms),
                mean(f, &|f| f.moved_pixels as f64 / 1e6),
            ];
            println!(
                "| {cols}x{rows} | {degrees} | {:.3} | {:.3} | {:.1} | {:.1} | {:.1} | {:.2} |",
                row[0], row[1], row[2], row[3], row[4], row[5]
            );
            let _ = writeln!(
                csv,
                "{cols},{rows},{degrees},{:.4},{:.4},{:.2},{:.2},{:.2},{:.3}",
                row[0], row[1], row[2], row[3], row[4], row[5]
            );
        }
    }
    std::fs::write(out.join("balance.csv"), csv)?;
    measured_balance_table()?;
    Ok(())
}

/// The same over the costs measured on lavapipe (`isowalld bench imbalance --bands 32`,
/// daemon/model/tests/data/imbalance-bands-*.csv), orbit frames only, at GPU-like rates (module
/// docs of docs/balance.md): 0.3 ns a fetch, 1 ns a pixel, 3-byte pixels over 10 Gbit/s.
fn measured_balance_table() -> Result<(), Box<dyn std::error::Error>> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    let transfer = Transfer { bytes_per_pixel: 3.0, bandwidth: 1.25e9, noise: 0.05, seed: SEED };
    println!("\nload-balanced screen space over measured costs (orbit frames, 1 degree each; means from the 8th on)");
    println!("| wall | nodes | slowest/mean unbalanced | balanced | frame ms unbalanced | balanced | ideal | balanced / ideal | Mpixels moved |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for wall in ["sva-4", "bench-4x2-1080p", "bench-6x4-1080p"] {
        let path = dir.join(format!("imbalance-bands-{wall}.csv"));
        let Ok(text) = std::fs::read_to_string(&path) else {
            println!("| {wall} | (no {}) |", path.display());
            continue;
        };
        let (tiles, frames) = measured_costs(&text, 0.3, 1.0)?;
        let orbit: Vec<_> =
            frames.into_iter().filter(|(l, _)| l.starts_with("orbit")).map(|(_, c)| c).collect();
        let f = run_balance_on(&tiles, &orbit, &transfer, false);
        let f = &f[8.min(f.len())..];
        let mean = |g: &dyn Fn(&BalanceFrame) -> f64| f.iter().map(g).sum::<f64>() / f.len().max(1) as f64;
        println!(
            "| {wall} | {} | {:.3} | {:.3} | {:.1} | {:.1} | {:.1} | {:.3} | {:.2} |",
            tiles.len(),
            mean(&|f| f.unbalanced),
            mean(&|f| f.balanced),
            mean(&|f| f.unbalanced_ms),
            mean(&|f| f.balanced_ms),
            mean(&|f| f.ideal_ms),
            mean(&|f| f.balanced_ms / f.ideal_ms),
            mean(&|f| f.moved_pixels as f64 / 1e6)
        );
    }
    Ok(())
}
