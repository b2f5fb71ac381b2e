//! What a run of frames reports: the frame statistics' text (`up`, `orbit`, `demo`), the timed
//! swap's line, interval jitter and time steps, and the quantiles they share.

use crate::wall::{micros, one_machine, Wall};
use isowall_model::frame_controller::{FrameStats, SurfaceLevels};
use std::collections::BTreeMap;
use std::time::Duration;

/// The swap's lines of the report: the skew measured (and, on one machine, the true one), the
/// timed swap's margin and late swaps, the clocks' error bounds, and on a paced wall the
/// frame-interval jitter.
pub fn swap_report(wall: &Wall) -> String {
    let ms = |d: Option<Duration>| d.map_or("-".to_string(), |d| format!("{:.3} ms", d.as_secs_f64() * 1e3));
    let line = |what: &str, v: Vec<Duration>| {
        format!(
            "{what}: p50 {} p99 {} max {} over {} frames\n",
            ms(quantile(v.clone(), 0.5)),
            ms(quantile(v.clone(), 0.99)),
            ms(quantile(v.clone(), 1.0)),
            v.len()
        )
    };
    let mut s = line(
        "swap skew (measured, controller clock)",
        wall.finished.iter().filter_map(|f| f.swap_skew).collect(),
    );
    if one_machine(&wall.config) {
        s += &line(
            "swap skew (true: every node on this machine's one clock)",
            wall.finished.iter().filter_map(|f| f.node_clock_skew).collect(),
        );
    }
    let timing = wall.machine().swap_timing();
    let presents: usize = wall
        .finished
        .iter()
        .map(|f| f.per_node.iter().filter(|n| n.presented_node_time_us.is_some()).count())
        .sum();
    let late: usize = wall.finished.iter().map(|f| f.late_swaps).sum();
    let margins: Vec<Duration> = wall.finished.iter().filter_map(|f| f.margin).collect();
    if margins.is_empty() {
        s += &format!("timed swap: {} (each node presents when its Swap arrives)\n", timing.setting());
    } else {
        s += &format!(
            "timed swap: margin {} (release -> present: p50 {} p99 {}), late swaps {late} of {presents} presents\n",
            timing.setting(),
            ms(quantile(margins.clone(), 0.5)),
            ms(quantile(margins, 0.99)),
        );
    }
    let now = micros(wall.now());
    let offsets: Vec<(String, i64, i64)> = wall
        .machine()
        .nodes()
        .filter_map(|n| {
            let o = wall.machine().clock_offset(n)?;
            Some((n.to_string(), o.offset_at(now), o.error_at(now)))
        })
        .collect();
    if let Some((node, _, worst)) = offsets.iter().max_by_key(|b| b.2) {
        s += &format!(
            "clock offsets (node - controller, within the error bound): worst bound {worst} us ({node}); {}\n",
            offsets.iter().map(|(n, o, b)| format!("{n} {o:+} us within {b}")).collect::<Vec<_>>().join(", ")
        );
    }
    // How precisely each node presented at its present time, by its own clock.
    let mut waits: BTreeMap<&str, Vec<Duration>> = BTreeMap::new();
    for n in wall.finished.iter().flat_map(|f| &f.per_node).filter(|n| !n.late_swap) {
        if let (Some(at), Some(shown)) = (n.present_at_us, n.presented_node_time_us) {
            let after = u64::try_from(shown.saturating_sub(at)).unwrap_or(0);
            waits.entry(n.node.as_str()).or_default().push(Duration::from_micros(after));
        }
    }
    if !waits.is_empty() {
        s += &format!(
            "presented after the present time (on-time swaps, node clocks): {}\n",
            waits
                .into_iter()
                .map(|(n, v)| format!(
                    "{n} p50 {} p99 {}",
                    ms(quantile(v.clone(), 0.5)),
                    ms(quantile(v, 0.99))
                ))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    // Whether each node's presenting thread wakes ahead of the renders.
    let presenting: Vec<String> = wall
        .config
        .nodes
        .iter()
        .filter_map(|n| wall.node_info(&n.name).map(|i| format!("{} {}", n.name, i.present)))
        .collect();
    if !presenting.is_empty() {
        s += &format!("presenting threads: {}\n", presenting.join(", "));
    }
    if let Some((period, jitter)) = interval_jitter(wall) {
        s += &format!(
            "frame pacing: {:.2} fps; {}",
            1.0 / period.as_secs_f64(),
            line("interval jitter |interval - period|", jitter)
        );
    }
    s
}

/// On a paced wall, its period and each interval's |interval - period| between consecutive
/// finished frames' present moments (each the mean of its nodes', in controller time).
pub fn interval_jitter(wall: &Wall) -> Option<(Duration, Vec<Duration>)> {
    let period = wall.machine().swap_timing().period()?;
    let moments: Vec<f64> = wall
        .finished
        .iter()
        .filter_map(|f| {
            let t: Vec<f64> =
                f.per_node.iter().filter_map(|n| n.presented_at).map(|d| d.as_secs_f64()).collect();
            (!t.is_empty()).then(|| t.iter().sum::<f64>() / t.len() as f64)
        })
        .collect();
    let jitter = moments
        .windows(2)
        .map(|w| Duration::from_secs_f64(((w[1] - w[0]) - period.as_secs_f64()).abs()))
        .collect();
    Some((period, jitter))
}

/// p-quantile of durations (nearest rank).
pub fn quantile(mut v: Vec<Duration>, q: f64) -> Option<Duration> {
    if v.is_empty() {
        return None;
    }
    v.sort();
    Some(v[((v.len() - 1) as f64 * q).round() as usize])
}

/// Time-varying volumes: the steps the frames played and the frames whose step was not loaded
/// on some node when the frame came (it waited, bounded) or that showed another step. Empty
/// when every frame was at step 0.
pub fn time_step_report(finished: &[FrameStats]) -> String {
    if finished.iter().all(|f| f.time_step == 0) {
        return String::new();
    }
    let changes = finished.windows(2).filter(|w| w[0].time_step != w[1].time_step).count();
    let (mut waited, mut other) = (Vec::new(), Vec::new());
    for f in finished {
        for n in &f.per_node {
            if let Some(l) = n.step_late {
                waited.push(format!("{}@{}", n.node, f.frame_id));
                if l.shown_step != f.time_step {
                    other.push(format!(
                        "{}@{} (step {} for {})",
                        n.node, f.frame_id, l.shown_step, f.time_step
                    ));
                }
            }
        }
    }
    let frames_waited: std::collections::BTreeSet<u64> = finished
        .iter()
        .filter(|f| f.per_node.iter().any(|n| n.step_late.is_some()))
        .map(|f| f.frame_id)
        .collect();
    let mut s = format!(
        "time steps: {} step changes over {} frames; frames that waited for their step: {}; frames with another step shown: {}\n",
        changes,
        finished.len(),
        frames_waited.len(),
        other.len()
    );
    if !waited.is_empty() {
        s += &format!("  waited (node@frame): {}\n", waited.join(", "));
    }
    if !other.is_empty() {
        s += &format!("  another step shown: {}\n", other.join(", "));
    }
    s
}

/// A frame's surface pixels and those level 0 drew, over the nodes that read their volume through
/// a brick cache (their Surface claims); `None` where no node sent one.
pub fn frame_surface(f: &FrameStats) -> Option<SurfaceLevels> {
    f.per_node.iter().filter_map(|n| n.surface).reduce(|a, b| a + b)
}

/// Volumes read through the nodes' brick caches: the share of the surface pixels the frames drew
/// with level 0 (the rest from coarser levels, while the caches refine), from the nodes' Surface
/// claims. Empty when no node sent one.
pub fn surface_report(finished: &[FrameStats]) -> String {
    let frames: Vec<(u64, SurfaceLevels)> =
        finished.iter().filter_map(|f| frame_surface(f).map(|s| (f.frame_id, s))).collect();
    let Some(&(last_id, last)) = frames.last() else {
        return String::new();
    };
    let whole = frames.iter().filter(|(_, s)| s.level0 == s.hits).count();
    let first_whole = frames
        .iter()
        .find(|(_, s)| s.level0 == s.hits)
        .map_or("none".to_string(), |(id, _)| format!("frame {id}"));
    let (low_id, low) = frames.iter().min_by(|a, b| a.1.share().total_cmp(&b.1.share())).expect("one frame");
    format!(
        "level 0 (brick cache): frame {last_id} drew {:.1}% of its {} surface pixels with level 0; {whole} of {} frames at 100% (the first: {first_whole}); the lowest {:.1}% (frame {low_id})\n",
        100.0 * last.share(),
        last.hits,
        frames.len(),
        100.0 * low.share()
    )
}

/// Human statistics of a run.
pub fn report(wall: &Wall, elapsed: Duration) -> String {
    let frames = wall.released;
    let mut s = format!(
        "frames: {frames} in {:.2} s ({:.1} fps)\n",
        elapsed.as_secs_f64(),
        frames as f64 / elapsed.as_secs_f64().max(1e-9)
    );
    if frames > wall.releases.len() as u64 {
        s += &format!("(the statistics below are over the last {} frames)\n", wall.releases.len());
    }
    let ms = |d: Option<Duration>| d.map_or("-".to_string(), |d| format!("{:.2} ms", d.as_secs_f64() * 1e3));
    let barrier: Vec<Duration> = wall.releases.iter().map(|r| r.1).collect();
    s += &format!(
        "barrier (frame state sent -> swap released): p50 {} p99 {} max {}\n",
        ms(quantile(barrier.clone(), 0.5)),
        ms(quantile(barrier.clone(), 0.99)),
        ms(quantile(barrier, 1.0))
    );
    s += &swap_report(wall);
    let mut per_node: BTreeMap<&str, (Vec<Duration>, Vec<Duration>)> = BTreeMap::new();
    for f in &wall.finished {
        for n in &f.per_node {
            let e = per_node.entry(n.node.as_str()).or_default();
            e.0.extend(n.render);
            e.1.extend(n.ready_after);
        }
    }
    for (node, (render, ready)) in per_node {
        s += &format!(
            "  {node}: render p50 {} max {}; ready after p50 {} max {}\n",
            ms(quantile(render.clone(), 0.5)),
            ms(quantile(render, 1.0)),
            ms(quantile(ready.clone(), 0.5)),
            ms(quantile(ready, 1.0)),
        );
    }
    // What the nodes said that was not asked for, or could not be true: ignored, counted here.
    for node in wall.machine().nodes() {
        if let Some(c) = wall.machine().counters(node).filter(|c| c.ignored + c.refused_times > 0) {
            s += &format!(
                "  {node}: {} unsolicited messages ignored, {} impossible times refused (kept out of the skew)\n",
                c.ignored, c.refused_times
            );
        }
    }
    // object space: bytes each node sent its peers per frame, and its compositing time.
    // Per node: bytes sent, compositing times, resident bytes, compositing work.
    type ObjectStats = (Vec<u64>, Vec<Duration>, u64, Vec<Duration>);
    let mut object: BTreeMap<&str, ObjectStats> = BTreeMap::new();
    for f in &wall.finished {
        for n in &f.per_node {
            if let (Some(b), Some(c)) = (n.bytes_sent, n.composite) {
                let e = object.entry(n.node.as_str()).or_default();
                e.0.push(b);
                e.1.push(c);
                e.2 = n.resident_bytes.unwrap_or(0);
                e.3.extend(n.merge);
            }
        }
    }
    if !object.is_empty() && wall.config.wall.balance {
        s += "balance (bytes of rectangles sent to their tiles' owners per frame and in all; placing: own render \
              done -> tiles placed, of which work: encode, decode, place):\n";
    } else if !object.is_empty() {
        s += "object space (bytes sent to peers per frame and in all; compositing: own render done -> tiles \
              composited, of which work: encode, decode, merge):\n";
    }
    for (node, (mut bytes, composite, resident, merge)) in object {
        bytes.sort_unstable();
        let median = bytes[(bytes.len() - 1) / 2];
        let total: u64 = bytes.iter().sum();
        s += &format!(
            "  {node}: sent p50 {median} B ({:.2} MB) max {} B total {total} B; composite p50 {} max {}; work p50 {} max {}; resident volume {resident} B\n",
            median as f64 / 1e6,
            bytes.last().copied().unwrap_or(0),
            ms(quantile(composite.clone(), 0.5)),
            ms(quantile(composite, 1.0)),
            ms(quantile(merge.clone(), 0.5)),
            ms(quantile(merge, 1.0)),
        );
    }
    s += &time_step_report(&wall.finished);
    s += &surface_report(&wall.finished);
    let stragglers: Vec<String> =
        wall.releases.iter().flat_map(|r| r.2.iter().map(|n| format!("{n}@{}", r.0))).collect();
    if !stragglers.is_empty() {
        s += &format!("stragglers (node@frame): {}\n", stragglers.join(", "));
    }
    s
}
