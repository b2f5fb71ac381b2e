//! Metrics for Prometheus over real processes: `isowall up --metrics ADDR` on an object-space
//! wall of two nodes is scraped with a real HTTP client during its orbit and after it (the run's
//! final counts, held with `--metrics-hold`); every scrape passes Debian's `promtool check
//! metrics`, and the final counters agree with the run's own report (frames, late swaps, each
//! node's bytes sent to its peers, the histograms' counts). Its server refuses another Host and a
//! page of another site, and `--metrics` refuses an address off loopback before any node starts.
//! The console's `/metrics` is under the API's token and origin rules, passes promtool, and a real
//! `prometheus` started by the test scrapes it with the token and answers a query of its frames.
//! Every metric a scrape names is listed in docs/operating.md.
//!
//! With `CI=true` a missing `promtool` or `prometheus` (Debian's `prometheus` package) fails the
//! test; elsewhere it is skipped with a message.

use isowall_e2e::{bin, free_udp_ports, in_ci, repo_root, run_in, set_object_mode, wall_config};
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// A child process, stopped (SIGINT, then SIGKILL) when dropped.
struct Running(Child);

impl Drop for Running {
    fn drop(&mut self) {
        if self.0.try_wait().ok().flatten().is_some() {
            return;
        }
        let _ = Command::new("kill").args(["-INT", &self.0.id().to_string()]).status();
        let give_up = Instant::now() + Duration::from_secs(10);
        while Instant::now() < give_up {
            if self.0.try_wait().ok().flatten().is_some() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A tool of Debian's `prometheus` package: its path, or `None` (skip) outside CI.
fn tool(name: &str) -> Option<PathBuf> {
    let found = std::env::var_os("PATH")
        .into_iter()
        .flat_map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .map(|d| d.join(name))
        .find(|p| p.is_file());
    if found.is_none() {
        assert!(
            !in_ci(),
            "{name} is missing under CI=true (Debian's `prometheus` package; scripts/setup.sh)"
        );
        eprintln!("skipping: {name} not found (apt-get install prometheus)");
    }
    found
}

/// `promtool check metrics` on a scrape: it must pass, saying nothing.
fn promtool_check(promtool: &Path, text: &str, what: &str) {
    let mut child = Command::new(promtool)
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run promtool");
    child.stdin.take().unwrap().write_all(text.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(
        out.status.success() && said.trim().is_empty(),
        "promtool check metrics ({what}): {said}\n{text}"
    );
    eprintln!("promtool check metrics ({what}): passed, {} lines", text.lines().count());
}

/// A scrape's samples: `name{labels}` as written -> value.
fn samples(text: &str) -> BTreeMap<String, f64> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .filter_map(|l| {
            let (k, v) = l.rsplit_once(' ')?;
            Some((k.to_string(), v.parse().ok()?))
        })
        .collect()
}

/// The sum of every sample of family `name` (all its labels).
fn sum_of(s: &BTreeMap<String, f64>, name: &str) -> f64 {
    s.iter().filter(|(k, _)| *k == name || k.starts_with(&format!("{name}{{"))).map(|(_, v)| v).sum()
}

/// Every family a scrape declares (`# TYPE NAME KIND`).
fn families(text: &str) -> Vec<String> {
    text.lines().filter_map(|l| Some(l.strip_prefix("# TYPE ")?.split(' ').next()?.to_string())).collect()
}

/// Each family of `text` is listed in docs/operating.md's metrics section.
fn documented(text: &str) {
    let doc = std::fs::read_to_string(repo_root().join("docs/operating.md")).unwrap();
    let at = doc.find("## Metrics for Prometheus").expect("docs/operating.md has a metrics section");
    let section = &doc[at..];
    for f in families(text) {
        assert!(
            section.contains(&format!("`{f}`")),
            "{f} is not listed in docs/operating.md's metrics section"
        );
    }
}

fn agent() -> ureq::Agent {
    ureq::Agent::new_with_config(
        ureq::config::Config::builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(30)))
            .build(),
    )
}

/// GET `url` with `headers`: status, Content-Type, body.
fn get(agent: &ureq::Agent, url: &str, headers: &[(&str, &str)]) -> (u16, String, String) {
    let mut req = agent.get(url);
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    let mut r = req.call().expect("an answer");
    let kind = r.headers().get("content-type").and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
    (r.status().as_u16(), kind, r.body_mut().read_to_string().unwrap_or_default())
}

/// A scrape of `url` that must be a 200 in the Prometheus text format 0.0.4.
fn scrape(agent: &ureq::Agent, url: &str, headers: &[(&str, &str)]) -> String {
    let (status, kind, body) = get(agent, url, headers);
    assert_eq!(status, 200, "{url}: {body}");
    assert!(kind.starts_with("text/plain; version=0.0.4"), "{url}: Content-Type {kind}");
    body
}

/// Reads a child's pipe into `into`, line by line, on a thread of its own.
fn collect(pipe: impl std::io::Read + Send + 'static, into: Arc<Mutex<String>>) {
    std::thread::spawn(move || {
        for line in BufReader::new(pipe).lines().map_while(Result::ok) {
            let mut s = into.lock().unwrap();
            s.push_str(&line);
            s.push('\n');
        }
    });
}

/// The number after `key` in the first line of `text` that contains `key`.
fn number_after(text: &str, key: &str) -> Option<f64> {
    text.lines().find_map(|l| isowall_e2e::orbit::number_after(l, key))
}

fn keys(dir: &Path, config: &Path) {
    let out = run_in(dir, "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
}

/// How long `up` serves its final counts after the run: the test scrapes them at once.
const HOLD_S: u64 = 10;

#[test]
fn up_serves_metrics_during_its_orbit_that_agree_with_its_report() {
    let Some(promtool) = tool("promtool") else { return };
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config(dir.path(), "metrics", &free_udp_ports(2), 32, 24, 2, 60_000, "keys");
    // Object space: each node sends its peers pixels, counted in bytes.
    set_object_mode(&config);
    keys(dir.path(), &config);
    let c = config.to_str().unwrap();

    // Off loopback (no token here) and a hold without a server: refused before any node starts.
    let out = run_in(dir.path(), "isowall", &["up", c, "--metrics", "0.0.0.0:9184"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("not a loopback address"), "{err}");
    let out = run_in(dir.path(), "isowall", &["up", c, "--metrics-hold", "5"]);
    assert!(
        !out.status.success(),
        "--metrics-hold without --metrics: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!dir.path().join("logs").exists(), "a node was started for a refused run");

    let frames = 12u64;
    let mut child = Command::new(bin("isowall"))
        .current_dir(dir.path())
        .args(["up", c, "--frames", &frames.to_string(), "--fps", "4", "--start-timeout", "180"])
        .args(["--metrics", "127.0.0.1:0", "--metrics-hold", &HOLD_S.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start isowall up");
    let (stdout, stderr) = (Arc::new(Mutex::new(String::new())), Arc::new(Mutex::new(String::new())));
    collect(child.stdout.take().unwrap(), stdout.clone());
    collect(child.stderr.take().unwrap(), stderr.clone());
    let mut child = Running(child);
    let said = |s: &Arc<Mutex<String>>| s.lock().unwrap().clone();
    let logs = || {
        let mut s = format!("stdout:\n{}\nstderr:\n{}", said(&stdout), said(&stderr));
        for e in std::fs::read_dir(dir.path().join("logs")).into_iter().flatten().flatten() {
            s += &format!(
                "\n--- {}:\n{}",
                e.path().display(),
                std::fs::read_to_string(e.path()).unwrap_or_default()
            );
        }
        s
    };

    // Its address, printed once the wall is up.
    let give_up = Instant::now() + Duration::from_secs(240);
    let url = loop {
        if let Some(u) = said(&stderr).lines().find_map(|l| l.strip_prefix("isowall: metrics at ")) {
            break u.trim().to_string();
        }
        if child.0.try_wait().unwrap().is_some() || Instant::now() > give_up {
            let log = logs();
            if log.contains("no Vulkan adapter") && !in_ci() {
                eprintln!("skipping: no Vulkan adapter");
                return;
            }
            panic!("isowall up did not serve its metrics:\n{log}");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let agent = agent();

    // During the orbit: scraped until the run is done.
    let mut during: Option<String> = None;
    let give_up = Instant::now() + Duration::from_secs(300);
    while !said(&stderr).contains("its final metrics stay at") {
        assert!(child.0.try_wait().unwrap().is_none(), "isowall up ended before its hold:\n{}", logs());
        assert!(Instant::now() < give_up, "the run did not end:\n{}", logs());
        let text = scrape(&agent, &url, &[]);
        let n = samples(&text).get("isowall_frames_total").copied().unwrap_or(0.0);
        if n >= 1.0 && (n as u64) < frames && during.is_none() {
            during = Some(text);
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let during = during.unwrap_or_else(|| panic!("no scrape while the orbit ran:\n{}", logs()));
    promtool_check(&promtool, &during, "isowall up, during the orbit");
    let d = samples(&during);
    for n in ["node0", "node1"] {
        assert_eq!(d.get(&format!("isowall_node_up{{node=\"{n}\"}}")), Some(&1.0), "{n} up:\n{during}");
        let bound = d.get(&format!("isowall_node_clock_error_seconds{{node=\"{n}\"}}"));
        assert!(bound.is_some_and(|b| *b >= 0.0 && *b < 1.0), "{n}'s clock error bound: {bound:?}");
    }

    // After the run: the final counts, the nodes stopped.
    let last = scrape(&agent, &url, &[]);
    promtool_check(&promtool, &last, "isowall up, after the run");
    documented(&last);
    let m = samples(&last);
    let report = said(&stdout);
    eprintln!("the run's report:\n{report}");
    let reported_frames = number_after(&report, "frames:").expect("frames in the report");
    assert_eq!(reported_frames, frames as f64, "{report}");
    assert_eq!(m["isowall_frames_total"], reported_frames, "frames: metrics against the report");
    assert_eq!(m["isowall_barrier_seconds_count"], reported_frames);
    // The timed swap's line: late swaps L of P presents (an untimed swap has none: 0).
    let late = number_after(&report, "late swaps").unwrap_or(0.0);
    assert_eq!(sum_of(&m, "isowall_node_late_swaps_total"), late, "late swaps: metrics against the report");
    let skews = report
        .lines()
        .find(|l| l.starts_with("swap skew (measured"))
        .and_then(|l| isowall_e2e::orbit::number_before(l, " frames"))
        .expect("the measured skew's line");
    assert_eq!(m["isowall_swap_skew_seconds_count"], skews, "measured skews: metrics against the report");
    for n in ["node0", "node1"] {
        let line =
            report.lines().find(|l| l.starts_with(&format!("  {n}: sent p50"))).expect("its bytes' line");
        let total = isowall_e2e::orbit::number_after(line, "total").expect("its total bytes");
        assert!(total > 0.0, "{line}");
        assert_eq!(
            m[&format!("isowall_node_sent_bytes_total{{node=\"{n}\"}}")],
            total,
            "{n}'s bytes: {line}"
        );
        // Ready for every frame (a 60 s deadline): a render time for each.
        assert_eq!(m[&format!("isowall_node_render_seconds_count{{node=\"{n}\"}}")], reported_frames);
        assert_eq!(m[&format!("isowall_node_missed_deadlines_total{{node=\"{n}\"}}")], 0.0);
        // The wall is closed: no node up, no clock measured.
        assert_eq!(m[&format!("isowall_node_up{{node=\"{n}\"}}")], 0.0);
        assert!(!m.contains_key(&format!("isowall_node_clock_error_seconds{{node=\"{n}\"}}")));
    }
    eprintln!(
        "counters against the report: frames {} = {reported_frames}, late swaps {} = {late}, bytes node0 {} node1 {}",
        m["isowall_frames_total"],
        sum_of(&m, "isowall_node_late_swaps_total"),
        m["isowall_node_sent_bytes_total{node=\"node0\"}"],
        m["isowall_node_sent_bytes_total{node=\"node1\"}"]
    );

    // The console's rules for a server without a token: a loopback Host, no page of another site.
    // (The Host written by hand: an HTTP client sends the URL's.)
    let addr = url.trim_start_matches("http://").split('/').next().unwrap().to_string();
    let mut s = std::net::TcpStream::connect(&addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: evil.example\r\nConnection: close\r\n\r\n").unwrap();
    let mut answer = String::new();
    std::io::Read::read_to_string(&mut s, &mut answer).unwrap();
    assert!(answer.starts_with("HTTP/1.1 403") && answer.contains("not a loopback name"), "{answer}");
    let (status, _, body) = get(&agent, &url, &[("Origin", "http://evil.example")]);
    assert_eq!(status, 403, "{body}");
    assert_eq!(get(&agent, &url.replace("/metrics", "/api/status"), &[]).0, 404);

    // The hold ends, and the run with it: a clean exit, nothing served any more.
    let give_up = Instant::now() + Duration::from_secs(HOLD_S + 60);
    let status = loop {
        if let Some(s) = child.0.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < give_up, "isowall up did not end after its hold:\n{}", logs());
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(status.success(), "isowall up after its hold: {status}\n{}", logs());
    assert!(std::net::TcpStream::connect(&addr).is_err(), "{addr} still serves after the run");
}

#[test]
fn the_console_serves_metrics_under_its_token_and_origin_rules_to_a_real_prometheus() {
    let Some(promtool) = tool("promtool") else { return };
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config(dir.path(), "console-metrics", &free_udp_ports(1), 32, 24, 2, 20_000, "keys");
    keys(dir.path(), &config);
    let token = "metrics-0123456789abcdef";
    let mut child = Command::new(bin("isowall"))
        .current_dir(dir.path())
        .args(["console", config.to_str().unwrap(), "--listen", "127.0.0.1:0", "--local", "--token", token])
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(dir.path().join("console.err")).unwrap())
        .spawn()
        .expect("start isowall console");
    let urls = isowall_e2e::console_urls(child.stdout.take().unwrap());
    let _console = Running(child);
    let logs = || std::fs::read_to_string(dir.path().join("console.err")).unwrap_or_default();
    let Ok(base) = urls.recv_timeout(Duration::from_secs(180)) else {
        if logs().contains("no Vulkan adapter") && !in_ci() {
            eprintln!("skipping: no Vulkan adapter");
            return;
        }
        panic!("the console did not start:\n{}", logs());
    };
    let agent = agent();
    let bearer = format!("Bearer {token}");
    let auth = [("Authorization", bearer.as_str())];
    let give_up = Instant::now() + Duration::from_secs(120);
    let released = loop {
        let (status, _, body) = get(&agent, &format!("{base}/api/status"), &auth);
        if status == 200 {
            let s: serde_json::Value = serde_json::from_str(&body).unwrap();
            if s["frame"]["released"].as_u64().unwrap_or(0) > 0 {
                break s["frame"]["released"].as_u64().unwrap();
            }
        }
        assert!(Instant::now() < give_up, "no frame:\n{}", logs());
        std::thread::sleep(Duration::from_millis(200));
    };
    let url = format!("{base}/metrics");
    // The API's rules: the token, never in a URL, and no page of another site even with it.
    let (status, _, body) = get(&agent, &url, &[]);
    assert!(status == 401 && body.contains("needs a token"), "{status} {body}");
    assert_eq!(get(&agent, &url, &[("Authorization", "Bearer metrics-0123456789abcdeX")]).0, 401);
    assert_eq!(get(&agent, &format!("{url}?token={token}"), &[]).0, 400);
    let (status, _, body) = get(&agent, &url, &[auth[0], ("Origin", "http://evil.example")]);
    assert!(status == 403 && body.contains("evil.example"), "{status} {body}");
    let (status, _, _) = get(&agent, &url, &[auth[0], ("Sec-Fetch-Site", "cross-site")]);
    assert_eq!(status, 403);

    let text = scrape(&agent, &url, &auth);
    promtool_check(&promtool, &text, "isowall console");
    documented(&text);
    let m = samples(&text);
    // Made after the status above: at least its frames.
    assert!(m["isowall_frames_total"] >= released as f64, "{} < {released}", m["isowall_frames_total"]);
    assert_eq!(m["isowall_node_up{node=\"node0\"}"], 1.0);
    assert!(m["isowall_console_served_bytes_total"] > 0.0, "{text}");

    // A real Prometheus scrapes it with the token and answers a query of its frames.
    let Some(prometheus) = tool("prometheus") else { return };
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let target = base.trim_start_matches("http://");
    let yml = dir.path().join("prometheus.yml");
    std::fs::write(
        &yml,
        format!(
            "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\n\
             scrape_configs:\n  - job_name: isowall\n    authorization:\n      credentials: {token}\n    \
             static_configs:\n      - targets: ['{target}']\n"
        ),
    )
    .unwrap();
    let prom_log = dir.path().join("prometheus.log");
    let prom = Command::new(prometheus)
        .arg(format!("--config.file={}", yml.display()))
        .arg(format!("--storage.tsdb.path={}", dir.path().join("tsdb").display()))
        .arg(format!("--web.listen-address=127.0.0.1:{port}"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&prom_log).unwrap())
        .spawn()
        .expect("start prometheus");
    let _prom = Running(prom);
    let query = |q: &str| -> Option<f64> {
        let mut req = agent.get(format!("http://127.0.0.1:{port}/api/v1/query"));
        req = req.query("query", q);
        let mut r = req.call().ok()?;
        let v: serde_json::Value = serde_json::from_str(&r.body_mut().read_to_string().ok()?).ok()?;
        v["data"]["result"][0]["value"][1].as_str()?.parse().ok()
    };
    let started = Instant::now();
    let frames = loop {
        if let (Some(1.0), Some(f)) =
            (query("up{job=\"isowall\"}"), query("isowall_frames_total{job=\"isowall\"}"))
        {
            if f > 0.0 {
                break f;
            }
        }
        assert!(
            started.elapsed() < Duration::from_secs(90),
            "prometheus did not scrape the console:\n{}",
            std::fs::read_to_string(&prom_log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(250));
    };
    eprintln!(
        "prometheus scraped the console within {:.1} s of its start: isowall_frames_total {frames}",
        started.elapsed().as_secs_f64()
    );
}
