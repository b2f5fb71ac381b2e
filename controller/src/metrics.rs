//! The wall's metrics for a lab's Prometheus, in one place: each metric's name, help, type and
//! buckets, and the one way it is fed. [`Wall`](crate::wall::Wall) feeds them from the events its
//! report and the console's status are made of (a swap released: frames, barrier time, the nodes
//! that missed the deadline; a frame finished: its [`FrameStats`]; tile images; a node up or
//! down; the clocks' error bounds), so a counter and the report of the same run agree.
//!
//! Served in the Prometheus text format 0.0.4 at `/metrics` by the console (under its token,
//! origin and loopback rules) and by `isowall up --metrics ADDR` (loopback only). Counters only
//! count (`_total`; rates are the queries' job), durations are histograms in seconds (`_seconds`;
//! quantiles are the queries' job, `histogram_quantile`), gauges hold state (a node up, its
//! clock's error bound).
//!
//! Not here: cache hits and misses. The host cache of time steps (`isowall_volume::steps`) tells
//! the controller nothing of its hits; only a frame whose step was not loaded in time reaches it
//! (`StepLate`), counted as `isowall_node_step_late_total`.

use isowall_model::frame_controller::FrameStats;
use prometheus_client::encoding::prometheus_text;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::{Registry, Unit};
use std::net::SocketAddr;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

/// What `/metrics` answers with: the Prometheus text format, version 0.0.4.
pub const CONTENT_TYPE: &str = prometheus_text::CONTENT_TYPE;

/// A metric's labels: the node it is about (the config's name).
type Node = [(&'static str, String); 1];

fn node(name: &str) -> Node {
    [("node", name.to_string())]
}

/// Frame times (barrier, render, ready): 0.25 ms to 8.2 s, doubling; a wall's frames lie between
/// a fast GPU's tile and a deadline.
fn frame_time_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.000_25, 2.0, 16))
}

/// Swap skew: 10 us to 164 ms, doubling; a timed swap keeps it under a millisecond, a late one
/// is a frame.
fn skew_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.000_01, 2.0, 15))
}

/// Per node histograms, made by a named function (a family's constructor type).
type NodeHistograms = Family<Node, Histogram, fn() -> Histogram>;

/// The wall's metrics: what every front end's [`Wall`](crate::wall::Wall) counts and measures.
#[derive(Debug)]
pub struct WallMetrics {
    registry: Registry,
    nodes: Vec<String>,
    frames: Counter,
    barrier: Histogram,
    swap_skew: Histogram,
    /// Only where every node is on this machine (one clock): elsewhere there is no true skew.
    true_swap_skew: Option<Histogram>,
    late_swaps: Family<Node, Counter>,
    missed_deadlines: Family<Node, Counter>,
    downs: Family<Node, Counter>,
    sent_bytes: Family<Node, Counter>,
    image_bytes: Family<Node, Counter>,
    step_late: Family<Node, Counter>,
    render: NodeHistograms,
    ready: NodeHistograms,
    up: Family<Node, Gauge>,
    clock_error: Family<Node, Gauge<f64, AtomicU64>>,
}

impl WallMetrics {
    /// The metrics of a wall of `nodes`; `one_machine`: every node shares this machine's clock
    /// (`wall::one_machine`), so the true swap skew is measured too. Every node's series exist
    /// from the start (at 0, down), so a query sees a node that never came up.
    pub fn new(nodes: &[String], one_machine: bool) -> WallMetrics {
        let mut r = Registry::default();
        let frames = Counter::default();
        r.register("isowall_frames", "Swaps released since the controller started", frames.clone());
        let barrier = frame_time_histogram();
        r.register_with_unit(
            "isowall_barrier",
            "Time from a frame's state sent to its swap released (the swap barrier)",
            Unit::Seconds,
            barrier.clone(),
        );
        let swap_skew = skew_histogram();
        r.register_with_unit(
            "isowall_swap_skew",
            "Measured swap skew of a finished frame: the spread of the nodes' present moments, on the controller's clock through each node's measured offset",
            Unit::Seconds,
            swap_skew.clone(),
        );
        let true_swap_skew = one_machine.then(|| {
            let h = skew_histogram();
            r.register_with_unit(
                "isowall_swap_true_skew",
                "True swap skew of a finished frame: the spread of the nodes' own present times where every node runs on this machine's one clock",
                Unit::Seconds,
                h.clone(),
            );
            h
        });
        let late_swaps = Family::<Node, Counter>::default();
        r.register(
            "isowall_node_late_swaps",
            "Swaps that reached the node after their present time (it presented at once)",
            late_swaps.clone(),
        );
        let missed_deadlines = Family::<Node, Counter>::default();
        r.register(
            "isowall_node_missed_deadlines",
            "Swaps released without the node: it was connected but not ready by the deadline",
            missed_deadlines.clone(),
        );
        let downs = Family::<Node, Counter>::default();
        r.register(
            "isowall_node_downs",
            "Times the controller found the node down (connection lost, silent or refused)",
            downs.clone(),
        );
        let sent_bytes = Family::<Node, Counter>::default();
        r.register_with_unit(
            "isowall_node_sent",
            "Pixel bytes the node sent its peers (object space; a balanced wall's rectangles), as it reported per frame",
            Unit::Bytes,
            sent_bytes.clone(),
        );
        let image_bytes = Family::<Node, Counter>::default();
        r.register_with_unit(
            "isowall_node_image",
            "Bytes of tile images the node sent the controller (snapshots and thumbnails)",
            Unit::Bytes,
            image_bytes.clone(),
        );
        let step_late = Family::<Node, Counter>::default();
        r.register(
            "isowall_node_step_late",
            "Frames whose time step the node had not loaded when the frame came (it waited, bounded, or showed another step)",
            step_late.clone(),
        );
        let render = NodeHistograms::new_with_constructor(frame_time_histogram);
        r.register_with_unit(
            "isowall_node_render",
            "The render time the node reported for a frame",
            Unit::Seconds,
            render.clone(),
        );
        let ready = NodeHistograms::new_with_constructor(frame_time_histogram);
        r.register_with_unit(
            "isowall_node_ready",
            "Time from a frame's begin to the node's Ready (frames it was ready for before the release)",
            Unit::Seconds,
            ready.clone(),
        );
        let up = Family::<Node, Gauge>::default();
        r.register(
            "isowall_node_up",
            "1 while the controller holds the node's connection (it takes part in frames), 0 while it is down",
            up.clone(),
        );
        let clock_error = Family::<Node, Gauge<f64, AtomicU64>>::default();
        r.register_with_unit(
            "isowall_node_clock_error",
            "The error bound of the node's clock offset as of the last frame (absent before its first Pong)",
            Unit::Seconds,
            clock_error.clone(),
        );
        for n in nodes {
            let l = node(n);
            for family in [&late_swaps, &missed_deadlines, &downs, &sent_bytes, &image_bytes, &step_late] {
                let _ = family.get_or_create(&l);
            }
            up.get_or_create(&l).set(0);
        }
        WallMetrics {
            registry: r,
            nodes: nodes.to_vec(),
            frames,
            barrier,
            swap_skew,
            true_swap_skew,
            late_swaps,
            missed_deadlines,
            downs,
            sent_bytes,
            image_bytes,
            step_late,
            render,
            ready,
            up,
            clock_error,
        }
    }

    /// A swap released after `barrier`, without the `stragglers`.
    pub fn released(&self, barrier: Duration, stragglers: &[String]) {
        self.frames.inc();
        self.barrier.observe(barrier.as_secs_f64());
        for s in stragglers {
            self.missed_deadlines.get_or_create(&node(s)).inc();
        }
    }

    /// A frame finished (presented everywhere, or its present deadline passed).
    pub fn finished(&self, stats: &FrameStats) {
        if let Some(s) = stats.swap_skew {
            self.swap_skew.observe(s.as_secs_f64());
        }
        if let (Some(h), Some(s)) = (&self.true_swap_skew, stats.node_clock_skew) {
            h.observe(s.as_secs_f64());
        }
        for n in &stats.per_node {
            let l = node(&n.node);
            if n.late_swap {
                self.late_swaps.get_or_create(&l).inc();
            }
            if let Some(b) = n.bytes_sent {
                self.sent_bytes.get_or_create(&l).inc_by(b);
            }
            if n.step_late.is_some() {
                self.step_late.get_or_create(&l).inc();
            }
            if let Some(t) = n.render {
                self.render.get_or_create(&l).observe(t.as_secs_f64());
            }
            if let Some(t) = n.ready_after {
                self.ready.get_or_create(&l).observe(t.as_secs_f64());
            }
        }
    }

    /// `bytes` of tile images from `node` (a snapshot's or a thumbnail's).
    pub fn tile_images(&self, node_name: &str, bytes: u64) {
        self.image_bytes.get_or_create(&node(node_name)).inc_by(bytes);
    }

    /// The controller found `node` down.
    pub fn node_down(&self, node_name: &str) {
        self.downs.get_or_create(&node(node_name)).inc();
        self.set_up(node_name, false);
    }

    /// Whether the controller holds `node`'s connection.
    pub fn set_up(&self, node_name: &str, up: bool) {
        self.up.get_or_create(&node(node_name)).set(i64::from(up));
    }

    /// `node`'s clock error bound, seconds (`None`: not measured yet; its series is absent).
    pub fn set_clock_error(&self, node_name: &str, seconds: Option<f64>) {
        let l = node(node_name);
        match seconds {
            Some(s) => {
                self.clock_error.get_or_create(&l).set(s);
            }
            None => {
                self.clock_error.remove(&l);
            }
        }
    }

    /// The wall is closed: no node is up, no clock is measured.
    pub fn closed(&self) {
        for n in &self.nodes {
            self.set_up(n, false);
        }
        self.clock_error.clear();
    }

    /// The text `/metrics` answers: these metrics, then the console's where it serves them.
    pub fn text(&self, console: Option<&ConsoleMetrics>) -> String {
        let mut out = String::new();
        // Writing to a String does not fail.
        let _ = prometheus_text::encode(&mut out, &self.registry);
        if let Some(c) = console {
            let _ = prometheus_text::encode(&mut out, &c.registry);
        }
        out
    }
}

/// The console's own metrics: the bytes it served (its status's `console.served_bytes`).
#[derive(Debug)]
pub struct ConsoleMetrics {
    registry: Registry,
}

impl ConsoleMetrics {
    pub fn new(served_bytes: &Counter) -> ConsoleMetrics {
        let mut registry = Registry::default();
        registry.register_with_unit(
            "isowall_console_served",
            "Bytes the console sent to pages and scripts (response bodies and WebSocket messages)",
            Unit::Bytes,
            served_bytes.clone(),
        );
        ConsoleMetrics { registry }
    }
}

/// `isowall up --metrics ADDR`: a loopback address (there is no token to guard another).
pub fn loopback_addr(s: &str) -> Result<SocketAddr, String> {
    let addr: SocketAddr =
        s.trim().parse().map_err(|_| format!("'{s}' is not an address:port (e.g. 127.0.0.1:9184)"))?;
    if !addr.ip().is_loopback() {
        return Err(format!(
            "{addr} is not a loopback address: `isowall up` serves its metrics on loopback only \
             (for a Prometheus on another machine, scrape `isowall console --token T`)"
        ));
    }
    Ok(addr)
}

#[cfg(test)]
mod tests {
    use super::*;
    use isowall_model::frame_controller::NodeFrameStats;

    fn node_stats(name: &str, render_ms: u64, late: bool, bytes: Option<u64>) -> NodeFrameStats {
        NodeFrameStats {
            node: name.to_string(),
            render: Some(Duration::from_millis(render_ms)),
            ready_after: Some(Duration::from_millis(render_ms + 1)),
            presented_at: None,
            presented_node_time_us: None,
            present_at_us: None,
            late_swap: late,
            went_down: false,
            bytes_sent: bytes,
            composite: None,
            resident_bytes: None,
            merge: None,
            step_late: None,
            surface: None,
        }
    }

    fn frame(id: u64, per_node: Vec<NodeFrameStats>, skew_us: u64) -> FrameStats {
        let late_swaps = per_node.iter().filter(|n| n.late_swap).count();
        FrameStats {
            frame_id: id,
            time_step: 0,
            per_node,
            swap_skew: Some(Duration::from_micros(skew_us)),
            node_clock_skew: Some(Duration::from_micros(skew_us / 2)),
            present_at: None,
            margin: None,
            late_swaps,
            barrier: Duration::from_millis(20),
            missing: Vec::new(),
        }
    }

    /// The value of the sample `name` (with its labels, exactly as written) in `text`.
    fn sample(text: &str, name: &str) -> Option<f64> {
        text.lines().find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
    }

    /// Each family's `# TYPE` line: (name, type).
    fn types(text: &str) -> Vec<(String, String)> {
        text.lines()
            .filter_map(|l| {
                let mut w = l.strip_prefix("# TYPE ")?.split(' ');
                Some((w.next()?.to_string(), w.next()?.to_string()))
            })
            .collect()
    }

    fn fed(one_machine: bool) -> String {
        let nodes = vec!["node0".to_string(), "node1".to_string()];
        let m = WallMetrics::new(&nodes, one_machine);
        m.set_up("node0", true);
        m.set_clock_error("node0", Some(0.000_250));
        for id in 1..=5u64 {
            let stragglers = if id == 3 { vec!["node1".to_string()] } else { Vec::new() };
            m.released(Duration::from_millis(10 * id), &stragglers);
            let per_node = vec![
                node_stats("node0", 4 * id, id == 2, Some(1000 * id)),
                node_stats("node1", 5 * id, id >= 4, None),
            ];
            m.finished(&frame(id, per_node, 100 * id));
        }
        m.tile_images("node1", 4096);
        m.node_down("node1");
        m.text(None)
    }

    #[test]
    fn counters_end_in_total_durations_in_seconds_and_histograms_have_buckets() {
        let text = fed(true);
        let types = types(&text);
        assert!(types.len() >= 14, "{text}");
        for (name, kind) in &types {
            assert!(name.starts_with("isowall_"), "{name}");
            match kind.as_str() {
                "counter" => assert!(name.ends_with("_total"), "{name} is a counter without _total"),
                "histogram" => {
                    assert!(name.ends_with("_seconds"), "{name}: a duration not in seconds");
                    assert!(text.contains(&format!("{name}_bucket{{")), "{name} has no buckets");
                    assert!(text.contains(&format!("{name}_sum")) && text.contains(&format!("{name}_count")));
                }
                "gauge" => assert!(!name.ends_with("_total"), "{name}: a gauge named as a counter"),
                other => panic!("{name}: type {other}"),
            }
            // Help for every family, no millisecond or other abbreviated unit in a name.
            assert!(text.contains(&format!("# HELP {name} ")), "{name} has no help");
            assert!(!name.contains("_ms") && !name.contains("_us"), "{name}");
        }
        let names: Vec<&str> = types.iter().map(|(n, _)| n.as_str()).collect();
        for want in [
            "isowall_frames_total",
            "isowall_node_late_swaps_total",
            "isowall_node_sent_bytes_total",
            "isowall_barrier_seconds",
            "isowall_node_render_seconds",
            "isowall_node_ready_seconds",
            "isowall_swap_skew_seconds",
            "isowall_swap_true_skew_seconds",
            "isowall_node_up",
            "isowall_node_clock_error_seconds",
        ] {
            assert!(names.contains(&want), "{want} missing from {names:?}");
        }
    }

    #[test]
    fn the_counts_are_what_was_fed() {
        let text = fed(true);
        assert_eq!(sample(&text, "isowall_frames_total"), Some(5.0), "{text}");
        assert_eq!(sample(&text, "isowall_barrier_seconds_count"), Some(5.0));
        // 10 + 20 + 30 + 40 + 50 ms.
        let sum = sample(&text, "isowall_barrier_seconds_sum").unwrap();
        assert!((sum - 0.150).abs() < 1e-9, "{sum}");
        // 10 ms is over the 8 ms bucket, within the 16 ms one; 50 ms within 64 ms.
        assert_eq!(sample(&text, "isowall_barrier_seconds_bucket{le=\"0.008\"}"), Some(0.0), "{text}");
        assert_eq!(sample(&text, "isowall_barrier_seconds_bucket{le=\"0.016\"}"), Some(1.0));
        assert_eq!(sample(&text, "isowall_barrier_seconds_bucket{le=\"0.064\"}"), Some(5.0));
        assert_eq!(sample(&text, "isowall_barrier_seconds_bucket{le=\"+Inf\"}"), Some(5.0));
        assert_eq!(sample(&text, "isowall_node_late_swaps_total{node=\"node0\"}"), Some(1.0));
        assert_eq!(sample(&text, "isowall_node_late_swaps_total{node=\"node1\"}"), Some(2.0));
        assert_eq!(sample(&text, "isowall_node_missed_deadlines_total{node=\"node1\"}"), Some(1.0));
        assert_eq!(sample(&text, "isowall_node_missed_deadlines_total{node=\"node0\"}"), Some(0.0));
        // 1000 + ... + 5000 bytes from node0; node1 reported none (and is listed at 0).
        assert_eq!(sample(&text, "isowall_node_sent_bytes_total{node=\"node0\"}"), Some(15000.0));
        assert_eq!(sample(&text, "isowall_node_sent_bytes_total{node=\"node1\"}"), Some(0.0));
        assert_eq!(sample(&text, "isowall_node_image_bytes_total{node=\"node1\"}"), Some(4096.0));
        assert_eq!(sample(&text, "isowall_node_render_seconds_count{node=\"node1\"}"), Some(5.0));
        assert_eq!(sample(&text, "isowall_swap_skew_seconds_count"), Some(5.0));
        assert_eq!(sample(&text, "isowall_swap_true_skew_seconds_count"), Some(5.0));
        assert_eq!(sample(&text, "isowall_node_up{node=\"node0\"}"), Some(1.0));
        assert_eq!(sample(&text, "isowall_node_up{node=\"node1\"}"), Some(0.0));
        assert_eq!(sample(&text, "isowall_node_downs_total{node=\"node1\"}"), Some(1.0));
        assert_eq!(sample(&text, "isowall_node_clock_error_seconds{node=\"node0\"}"), Some(0.00025));
        assert_eq!(sample(&text, "isowall_node_clock_error_seconds{node=\"node1\"}"), None);
    }

    #[test]
    fn the_true_skew_exists_only_on_one_machine_and_a_closed_wall_has_no_node_up() {
        let text = fed(false);
        assert!(!text.contains("isowall_swap_true_skew"), "{text}");
        assert_eq!(sample(&text, "isowall_swap_skew_seconds_count"), Some(5.0));
        let m = WallMetrics::new(&["a".to_string()], false);
        m.set_up("a", true);
        m.set_clock_error("a", Some(0.001));
        m.closed();
        let text = m.text(None);
        assert_eq!(sample(&text, "isowall_node_up{node=\"a\"}"), Some(0.0));
        assert!(!text.contains("isowall_node_clock_error_seconds{"), "{text}");
        let served = Counter::default();
        served.inc_by(1234);
        let text = m.text(Some(&ConsoleMetrics::new(&served)));
        assert_eq!(sample(&text, "isowall_console_served_bytes_total"), Some(1234.0), "{text}");
    }

    #[test]
    fn up_serves_its_metrics_on_loopback_only() {
        assert_eq!(loopback_addr("127.0.0.1:9184").unwrap().port(), 9184);
        assert!(loopback_addr("[::1]:0").is_ok());
        let e = loopback_addr("0.0.0.0:9184").unwrap_err();
        assert!(e.contains("not a loopback address") && e.contains("--token"), "{e}");
        assert!(loopback_addr("localhost:9184").unwrap_err().contains("not an address:port"));
    }
}
