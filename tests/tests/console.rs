//! The operator console (`isowall console`): its JSON API over real HTTP (token refusal,
//! read-only, 4xx on bad input with nothing changed), and its page in a real browser (Debian's
//! chromium driven through chromedriver with fantoccini): a local 2x2 wall comes up, the page shows
//! its thumbnail and four nodes up, the iso slider changes the picture and the status, a killed
//! node's card turns down and comes back up when the node is restarted. On a wall of time steps
//! (a glob of NRRD files), `POST /api/time` sets the step (the status and the next snapshot show
//! it), plays and pauses, and refuses an out-of-range step or rate naming the field; the page shows
//! its time controls there (hidden for one step) and its play button plays the wall. A page of
//! another site cannot load a snapshot as an `<img>` nor read the live status over a WebSocket;
//! the console's own page opened with `#token=T` reads both (the token in a header and a
//! WebSocket subprotocol, never in a URL).
//!
//! A second browser test drives what an operator does beside the picture: each node's card shows
//! its isowalld version, GPU adapter and driver (as the node told them) and its recent log lines
//! as text (a `<script>` line in the log stays text); camera bookmarks are saved, recalled and
//! deleted from the page (the file beside the config), a malformed file is named at its line;
//! the operator lock taken in the page refuses another client's change with 423 until released;
//! the identify button makes the screen show its node's and tile's name (its snapshot's corner)
//! and takes it away again; the restart button restarts a local node (a new process) and its
//! card comes back up.
//!
//! The browser test also prints what the page costs (run it with `--nocapture`): the thumbnail's
//! latency (swap released -> painted in the page), fps without and with the page open, and the
//! bytes per second the page costs the wall and the console. With `CI=true` a missing chromium
//! or chromedriver fails the test instead of skipping it.

use isowall_e2e::{
    bin, free_udp_ports, in_ci, run_in, set_ball_steps_source, wait_until, wall_config, write_ball_steps,
    Daemon,
};
use serde_json::Value;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A running `isowall console`, killed (with its local daemons) when dropped.
struct Console {
    child: Child,
    base: String,
    agent: ureq::Agent,
    token: Option<String>,
}

impl Drop for Console {
    fn drop(&mut self) {
        // SIGINT first: the console stops its local daemons on the way out.
        let _ = Command::new("kill").args(["-INT", &self.child.id().to_string()]).status();
        let give_up = Instant::now() + Duration::from_secs(10);
        while Instant::now() < give_up {
            if self.child.try_wait().ok().flatten().is_some() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

struct Reply {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Reply {
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&self.body)))
    }

    fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k.eq_ignore_ascii_case(name)).map(|(_, v)| v.as_str())
    }
}

impl Console {
    /// Starts `isowall console CONFIG --listen 127.0.0.1:0 EXTRA...` and waits until it serves
    /// and has rendered a frame with every node up. `None` (skip) where there is no Vulkan
    /// adapter outside CI.
    fn start(dir: &Path, config: &Path, extra: &[&str], token: Option<&str>) -> Option<Console> {
        let err = std::fs::File::create(dir.join("console.err")).unwrap();
        let mut child = Command::new(bin("isowall"))
            .arg("console")
            .arg(config)
            .args(["--listen", "127.0.0.1:0"])
            .args(extra)
            .env_remove("DISPLAY")
            .env_remove("WAYLAND_DISPLAY")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(err)
            .spawn()
            .expect("start isowall console");
        let stdout = child.stdout.take().unwrap();
        let rx = isowall_e2e::console_urls(stdout);
        let agent = ureq::Agent::new_with_config(
            ureq::config::Config::builder()
                .http_status_as_error(false)
                .timeout_global(Some(Duration::from_secs(60)))
                .build(),
        );
        let logs = || {
            let mut s = std::fs::read_to_string(dir.join("console.err")).unwrap_or_default();
            for e in std::fs::read_dir(dir.join("logs")).into_iter().flatten().flatten() {
                s += &format!(
                    "\n--- {}:\n{}",
                    e.path().display(),
                    std::fs::read_to_string(e.path()).unwrap_or_default()
                );
            }
            s
        };
        let base = match rx.recv_timeout(Duration::from_secs(180)) {
            Ok(b) => b,
            Err(_) => {
                let _ = child.kill();
                let _ = child.wait();
                let log = logs();
                if log.contains("no Vulkan adapter") && !in_ci() {
                    eprintln!("skipping: no Vulkan adapter");
                    return None;
                }
                panic!("the console did not start serving:\n{log}");
            }
        };
        let console = Console { child, base, agent, token: token.map(str::to_string) };
        // The first frame, every node up.
        let give_up = Instant::now() + Duration::from_secs(120);
        loop {
            let r = console.get("/api/status");
            if r.status == 200 && r.json()["nodes"].as_array().unwrap().iter().all(|n| n["state"] == "up") {
                break;
            }
            assert!(Instant::now() < give_up, "no frame with every node up:\n{}", logs());
            std::thread::sleep(Duration::from_millis(200));
        }
        Some(console)
    }

    fn reply(r: Result<ureq::http::Response<ureq::Body>, ureq::Error>) -> Reply {
        let mut r = r.expect("the console answers");
        let headers =
            r.headers().iter().map(|(k, v)| (k.to_string(), v.to_str().unwrap_or("").to_string())).collect();
        Reply { status: r.status().as_u16(), headers, body: r.body_mut().read_to_vec().expect("a body") }
    }

    fn get_with(&self, path: &str, token: Option<&str>) -> Reply {
        let mut req = self.agent.get(format!("{}{path}", self.base));
        if let Some(t) = token {
            req = req.header("Authorization", format!("Bearer {t}"));
        }
        Console::reply(req.call())
    }

    fn get(&self, path: &str) -> Reply {
        self.get_with(path, self.token.as_deref())
    }

    fn post_as(&self, path: &str, content_type: &str, body: &str) -> Reply {
        let mut req = self.agent.post(format!("{}{path}", self.base)).header("Content-Type", content_type);
        if let Some(t) = &self.token {
            req = req.header("Authorization", format!("Bearer {t}"));
        }
        Console::reply(req.send(body))
    }

    fn post(&self, path: &str, body: &str) -> Reply {
        self.post_as(path, "application/json", body)
    }

    fn status(&self) -> Value {
        let r = self.get("/api/status");
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        r.json()
    }
}

/// A wall of `n` (1 or 4) tiny tiles with its keys, in `dir`.
fn wall(dir: &Path, n: usize, (w, h): (u32, u32), deadline_ms: u64) -> PathBuf {
    let config = wall_config(dir, "console", &free_udp_ports(n), w, h, 2, deadline_ms, "keys");
    let out = run_in(dir, "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    config
}

#[test]
fn a_console_off_loopback_needs_a_token() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall(dir.path(), 1, (16, 12), 5000);
    let c = config.to_str().unwrap();
    let out = run_in(dir.path(), "isowall", &["console", c, "--listen", "0.0.0.0:0", "--local"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("not a loopback address") && err.contains("--token"),
        "{err}"
    );
    let out = run_in(dir.path(), "isowall", &["console", c, "--listen", "0.0.0.0:0", "--token", "short"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("at least 16 characters"), "{err}");
    assert!(!dir.path().join("logs").exists(), "no node was started for a refused console");
}

#[test]
fn the_api_refuses_missing_tokens_and_bad_input_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall(dir.path(), 1, (32, 24), 20000);
    let token = "sesame-0123456789abcdef";
    let Some(con) = Console::start(dir.path(), &config, &["--local", "--token", token], Some(token)) else {
        return;
    };
    // No token, a wrong one: 401 and a reason; the right one: the status.
    let r = con.get_with("/api/status", None);
    assert_eq!(r.status, 401);
    assert!(r.json()["error"].as_str().unwrap().contains("needs a token"));
    assert_eq!(r.header("www-authenticate"), Some("Bearer"));
    assert_eq!(con.get_with("/api/status", Some("sesame-0123456789abcdeX")).status, 401);
    assert_eq!(con.get_with("/api/snapshot.png?width=8", Some("wrong")).status, 401);
    // Never in a URL (it would end up in logs): refused, even when right.
    let r = con.get_with(&format!("/api/status?token={token}"), None);
    assert_eq!(r.status, 400);
    assert!(r.json()["error"].as_str().unwrap().contains("token in the URL"), "{}", r.json());
    // The node tells its own resident memory with its Pongs (twice a second), local or not.
    let give_up = Instant::now() + Duration::from_secs(20);
    let rss_kib = loop {
        if let Some(kib) = con.status()["nodes"][0]["rss_kib"].as_u64() {
            break kib;
        }
        assert!(Instant::now() < give_up, "no resident memory from node0: {}", con.status());
        std::thread::sleep(Duration::from_millis(200));
    };
    // A daemon holding a wgpu device and a volume: more than 4 MiB, less than this machine.
    assert!(rss_kib > 4 << 10 && rss_kib < 24 << 20, "node0 resident {rss_kib} KiB");
    let before = con.status();
    let (lo, hi) = (before["volume"]["min"].as_f64().unwrap(), before["volume"]["max"].as_f64().unwrap());
    // Bad input: a 4xx with the reason, naming the field where there is one.
    let cases: [(&str, &str, &str, u16, &str); 11] = [
        ("/api/render", "application/json", "{\"iso\": ", 400, "EOF"),
        ("/api/render", "application/json", "{\"isovalue\": 1}", 422, "unknown field `isovalue`"),
        ("/api/render", "application/json", "{\"ibl\": \"mirror\"}", 422, "unknown variant `mirror`"),
        ("/api/render", "application/json", "{\"ao_samples\": \"many\"}", 422, "ao_samples"),
        ("/api/render", "text/plain", "{\"iso\": 0.1}", 415, "Content-Type"),
        ("/api/render", "application/json", "{\"ao_samples\": 100000}", 422, "is more than 1024"),
        ("/api/render", "application/json", "{\"exposure\": -2}", 422, "`exposure` -2 must be"),
        ("/api/camera", "application/json", "{\"zoom\": 0}", 422, "`zoom` 0 is not a factor"),
        (
            "/api/camera",
            "application/json",
            "{\"view\": \"front\"}",
            422,
            "unknown variant `front`, expected one of `anterior`",
        ),
        ("/api/time", "application/json", "{\"play\": \"play\"}", 422, "one time step, nothing to play"),
        ("/api/time", "application/json", "{\"step\": 1}", 422, "the volume has 1 time step (0..=0)"),
    ];
    for (path, kind, body, status, says) in cases {
        let r = con.post_as(path, kind, body);
        let text = String::from_utf8_lossy(&r.body).to_string();
        assert_eq!(r.status, status, "{path} {body}: {text}");
        assert!(text.contains(says), "{path} {body}: {text}");
    }
    // A refused key is named in `field`, as the docs promise.
    for (body, field) in [("{\"isovalue\": 1}", "isovalue"), ("{\"ao_samples\": \"many\"}", "ao_samples")] {
        let r = con.post("/api/render", body);
        assert_eq!((r.status, r.json()["field"].as_str()), (422, Some(field)), "{body}");
    }
    let r = con.post("/api/render", &format!("{{\"iso\": {}, \"ao_samples\": 2}}", hi + (hi - lo) + 1.0));
    assert_eq!(
        (r.status, r.json()["field"].as_str()),
        (422, Some("iso")),
        "{}",
        String::from_utf8_lossy(&r.body)
    );
    let r = con.get("/api/snapshot.png?width=0");
    assert_eq!((r.status, r.json()["field"].as_str()), (400, Some("width")));
    assert_eq!(con.get("/api/snapshot.png?size=3").status, 400);
    let r = con.get("/api/live?hz=1000");
    assert_eq!((r.status, r.json()["field"].as_str()), (400, Some("hz")));
    let r = con.get("/api/live");
    assert_eq!(r.status, 400);
    assert!(r.json()["error"].as_str().unwrap().contains("is a WebSocket"));
    // Nothing changed.
    let after = settled(&con);
    assert_eq!(after["render"], before["render"]);
    assert_eq!((after["time"]["steps"].as_u64(), after["time"]["playing"].as_bool()), (Some(1), Some(false)));
    // A valid change is applied, and the thumbnail is the wall's size over the divisor.
    assert_eq!(before["render"]["denoise"], "off");
    assert_eq!(
        con.post("/api/render", "{\"ao_samples\": 2, \"exposure\": 0.9, \"denoise\": \"on\"}").status,
        200
    );
    let give_up = Instant::now() + Duration::from_secs(30);
    loop {
        let r = &con.status()["render"];
        if r["ao_samples"] == 2 && r["denoise"] == "on" {
            break;
        }
        assert!(Instant::now() < give_up, "the change never showed in the status: {r}");
        std::thread::sleep(Duration::from_millis(100));
    }
    // The wall is its 32x24 tile and the tile's 2-pixel bezels on the right and at the bottom:
    // 34x26. A thumbnail is the wall over the smallest divisor whose width fits.
    for (width, size, why) in [(17, (17, 13), "34x26 over 2"), (16, (12, 9), "34 / 2 > 16: over 3")] {
        // The tile's own pixels, not the grey placeholder of a tile that did not fit. A node
        // that misses the thumbnail's give-up (2 s, on a loaded machine) gives a picture of
        // placeholders, which carries no frame; a tile that does not fit is one every time. So
        // the test waits, with a deadline, for a picture whose tile fitted and that names its
        // frame, asking again after the 250 ms a picture is served again.
        let give_up = Instant::now() + Duration::from_secs(20);
        let mut placeholders = Vec::new();
        let fitted = loop {
            let r = con.get(&format!("/api/snapshot.png?width={width}"));
            assert_eq!(r.status, 200);
            assert_eq!(r.header("content-type"), Some("image/png"));
            let img = image::load_from_memory(&r.body).unwrap();
            assert_eq!((img.width(), img.height()), size, "?width={width}: {why}");
            assert_eq!(r.header("x-isowall-size"), Some(format!("{}x{}", size.0, size.1).as_str()));
            let rgb = img.to_rgb8();
            let placeholder = rgb.pixels().filter(|p| p.0 == [96, 96, 96] || p.0 == [40, 40, 40]).count();
            placeholders.push(placeholder);
            if placeholder < rgb.pixels().len() / 4 {
                break r;
            }
            assert!(
                Instant::now() < give_up,
                "?width={width}: placeholder pixels in each of {} pictures in 20 s: {placeholders:?}",
                placeholders.len()
            );
            std::thread::sleep(Duration::from_millis(300));
        };
        assert!(
            fitted.header("x-isowall-frame").is_some() && fitted.header("x-isowall-frame-age-ms").is_some(),
            "?width={width}: a picture whose tile fitted names its frame"
        );
        if placeholders.len() > 1 {
            eprintln!("?width={width}: placeholder pixels {placeholders:?} (asked again)");
        }
    }
    let full = con.get("/api/snapshot.png?download=1");
    let img = image::load_from_memory(&full.body).unwrap();
    assert_eq!((img.width(), img.height()), (34, 26), "the whole wall, bezels included");
    assert!(full.header("content-disposition").is_some_and(|d| d.contains("attachment")));
    // Every answer, the page's included: no type sniffing, the page's own script only, no framing.
    for r in [&full, &con.get("/")] {
        assert_eq!(r.header("x-content-type-options"), Some("nosniff"));
        let csp = r.header("content-security-policy").unwrap_or_default();
        assert!(csp.contains("script-src 'self'") && csp.contains("frame-ancestors 'none'"), "{csp}");
    }

    // The frame statistics the charts and cards show: rolling series, ordered quantiles, and the
    // node's own render and ready times (ready: the frame began -> its Ready arrived, so never less
    // than its render time).
    let s = con.status();
    // No brick cache on this wall: no share of surface pixels at level 0 to show.
    let frame = s["frame"].as_object().expect("frame");
    assert!(frame.get("level0_share").is_some_and(|v| v.is_null()), "{}", s["frame"]);
    let (frames, p50, p99) = (
        s["frame"]["frame_ms"].as_array().unwrap(),
        s["frame"]["frame_ms_p50"].as_f64().expect("frame_ms_p50"),
        s["frame"]["frame_ms_p99"].as_f64().expect("frame_ms_p99"),
    );
    assert!(
        !frames.is_empty() && 0.0 < p50 && p50 <= p99,
        "frame ms p50 {p50}, p99 {p99}, {} frames",
        frames.len()
    );
    let (lo, hi) =
        frames.iter().filter_map(Value::as_f64).fold((f64::MAX, 0.0_f64), |(l, h), x| (l.min(x), h.max(x)));
    assert!(lo <= p99 && p50 <= hi, "quantiles {p50}/{p99} outside the series' {lo}..{hi}");
    let (skew50, skew99) = (s["frame"]["skew_ms_p50"].as_f64(), s["frame"]["skew_ms_p99"].as_f64());
    assert!(
        skew50.zip(skew99).is_some_and(|(a, b)| 0.0 <= a && a <= b),
        "skew p50 {skew50:?}, p99 {skew99:?}"
    );
    // The timed swap (the config's default, `auto`): its margin, late swaps, the node's clock
    // error bound, and the true skew (its nodes are on this machine).
    let f = &s["frame"];
    assert_eq!(f["swap_margin"], "auto");
    let margin = f["swap_margin_ms"].as_f64();
    assert!(margin.is_some_and(|m| m > 0.0 && m <= 25.0), "margin {margin:?} ms");
    assert!(f["late_swaps"].as_u64().is_some() && f["frame_rate"].is_null());
    assert!(f["true_skew_ms_p50"].as_f64().is_some_and(|t| t >= 0.0), "{f}");
    let node = &s["nodes"][0];
    let clock = node["clock_error_us"].as_i64();
    assert!(clock.is_some_and(|e| e > 0 && e < 1_000_000), "clock error {clock:?} us");
    let (render, ready) = (node["render_ms"].as_f64(), node["ready_ms"].as_f64());
    assert!(
        render.zip(ready).is_some_and(|(r, q)| 0.0 < r && r <= q && q < 20_000.0),
        "node0 render {render:?} ms, ready {ready:?} ms"
    );

    // A camera change through the API: the status's camera moves and the next picture differs;
    // the orbit plays and pauses; reset brings back the config's camera.
    let eye0 = s["camera"]["eye"].clone();
    let picture0 = fresh_snapshot(&con);
    let r = con.post("/api/camera", "{\"yaw_deg\": 40, \"zoom\": 0.8}");
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let give_up = Instant::now() + Duration::from_secs(30);
    while con.status()["camera"]["eye"] == eye0 {
        assert!(Instant::now() < give_up, "the camera change never showed in the status");
        std::thread::sleep(Duration::from_millis(100));
    }
    let give_up = Instant::now() + Duration::from_secs(30);
    loop {
        let moved = changed_pixels(&picture0, &snapshot(&con));
        if moved > 26 * 34 / 20 {
            break;
        }
        assert!(Instant::now() < give_up, "only {moved} pixels changed after the camera moved");
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(con.post("/api/camera", "{\"orbit\": \"play\"}").status, 200);
    let give_up = Instant::now() + Duration::from_secs(30);
    while con.status()["orbit"]["playing"] != true {
        assert!(Instant::now() < give_up, "the orbit never played");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(con.post("/api/camera", "{\"orbit\": \"pause\", \"reset\": true}").status, 200);
    let give_up = Instant::now() + Duration::from_secs(30);
    loop {
        let s = con.status();
        if s["orbit"]["playing"] == false && s["camera"]["eye"] == eye0 {
            break;
        }
        assert!(Instant::now() < give_up, "reset kept eye {} (was {eye0})", s["camera"]["eye"]);
        std::thread::sleep(Duration::from_millis(100));
    }
    // A named view: from above (superior is +z for a volume without orientation).
    assert_eq!(con.post("/api/camera", "{\"view\": \"superior\"}").status, 200);
    let give_up = Instant::now() + Duration::from_secs(30);
    loop {
        let c = con.status()["camera"].clone();
        let (eye, target) = (&c["eye"], &c["target"]);
        let dz = eye[2].as_f64().unwrap() - target[2].as_f64().unwrap();
        let dxy = (eye[0].as_f64().unwrap() - target[0].as_f64().unwrap()).abs()
            + (eye[1].as_f64().unwrap() - target[1].as_f64().unwrap()).abs();
        if dz > 0.0 && dxy < 1e-6 * dz {
            break;
        }
        assert!(Instant::now() < give_up, "the superior view never showed: {c}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn a_read_only_console_shows_but_refuses_changes() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall(dir.path(), 1, (32, 24), 20000);
    let Some(con) = Console::start(dir.path(), &config, &["--local", "--read-only"], None) else { return };
    let before = con.status();
    assert_eq!(before["console"]["read_only"], true);
    for (path, body) in [
        ("/api/render", "{\"iso\": 0.0}"),
        ("/api/camera", "{\"orbit\": \"play\"}"),
        ("/api/time", "{\"step\": 0}"),
    ] {
        let r = con.post(path, body);
        assert_eq!(r.status, 403, "{path}");
        assert!(r.json()["error"].as_str().unwrap().contains("read-only"));
    }
    assert_eq!(con.get("/api/snapshot.png?width=8").status, 200);
    assert!(String::from_utf8_lossy(&con.get("/").body).contains("<title>Isowall console</title>"));
    // A request naming another host (DNS rebinding) is refused on a loopback console.
    // (Raw HTTP: a client library sets the Host from the address.)
    let addr = con.base.trim_start_matches("http://");
    let mut tcp = std::net::TcpStream::connect(addr).unwrap();
    tcp.write_all(b"GET /api/status HTTP/1.1\r\nHost: evil.example\r\nConnection: close\r\n\r\n").unwrap();
    let mut answer = String::new();
    tcp.read_to_string(&mut answer).unwrap();
    assert!(answer.starts_with("HTTP/1.1 403") && answer.contains("not a loopback name"), "{answer}");
    let after = con.status();
    assert_eq!(
        (after["render"].clone(), after["orbit"]["playing"].clone()),
        (before["render"].clone(), false.into())
    );
}

/// The whole wall's pixels, as `GET /api/snapshot.png` gives them.
fn snapshot(con: &Console) -> image::RgbImage {
    let r = con.get("/api/snapshot.png");
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    image::load_from_memory(&r.body).expect("a PNG").to_rgb8()
}

/// A picture of the wall drawn after every change asked before this call: the console has
/// carried the changes out (`settled`), and the picture's frame was begun after that.
fn fresh_snapshot(con: &Console) -> image::RgbImage {
    let released = settled(con)["frame"]["id"].as_u64().expect("the last released frame's id");
    wait_until("a picture of a frame begun after the changes", Duration::from_secs(30), || {
        let r = con.get("/api/snapshot.png");
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        match r.header("x-isowall-frame").and_then(|f| f.parse::<u64>().ok()) {
            // Frames already broadcast when the change was carried out may still be drawn
            // with the state before it: two frames of margin.
            Some(f) if f > released + 2 => Ok(image::load_from_memory(&r.body).expect("a PNG").to_rgb8()),
            f => Err(format!("the picture's frame is {f:?}, the change came at {released}")),
        }
    })
}

/// Pixels of two images of the same size whose channels differ by more than 32 levels.
fn changed_pixels(a: &image::RgbImage, b: &image::RgbImage) -> usize {
    assert_eq!(a.dimensions(), b.dimensions());
    a.pixels().zip(b.pixels()).filter(|(p, q)| p.0.iter().zip(q.0).any(|(x, y)| x.abs_diff(y) > 32)).count()
}

/// Polls the status until `done` holds of its `time` block (30 s at most).
fn wait_time(con: &Console, what: &str, done: impl Fn(&Value) -> bool) -> Value {
    wait_until(what, Duration::from_secs(30), || {
        let t = con.status()["time"].clone();
        if done(&t) {
            Ok(t)
        } else {
            Err(format!("the status says {t}"))
        }
    })
}

/// Asks for a change that moves nothing on the wall, the paused orbit's rate, and returns the
/// first status that shows it: the console carries out changes in order, so what any change
/// asked before it did shows there too.
fn settled(con: &Console) -> Value {
    let rate = con.status()["orbit"]["degrees_per_second"].as_f64().expect("the orbit's rate");
    let next = if rate < 180.0 { rate + 1.0 } else { rate - 1.0 };
    let r = con.post("/api/camera", &format!("{{\"orbit_degrees_per_second\": {next}}}"));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    wait_until("the orbit's new rate in the status", Duration::from_secs(30), || {
        let s = con.status();
        if s["orbit"]["degrees_per_second"] == next {
            Ok(s)
        } else {
            Err(s["orbit"].to_string())
        }
    })
}

#[test]
fn the_api_shows_and_sets_the_time_step_of_a_time_varying_volume() {
    let dir = tempfile::tempdir().unwrap();
    write_ball_steps(dir.path(), 4);
    let config = wall(dir.path(), 1, (48, 36), 20000);
    set_ball_steps_source(&config);
    let Some(con) = Console::start(dir.path(), &config, &["--local"], None) else { return };
    let t = con.status()["time"].clone();
    assert_eq!(
        (t["steps"].as_u64(), t["step"].as_u64(), t["playing"].as_bool(), t["rate"].as_f64()),
        (Some(4), Some(0), Some(false), Some(4.0)),
        "{t}"
    );
    // Two pictures of step 0: how much a still frame changes by itself (AO refining).
    let still_a = fresh_snapshot(&con);
    let still_b = fresh_snapshot(&con);
    let noise = changed_pixels(&still_a, &still_b);
    // Refusals name the field and change nothing.
    for (body, field, says) in [
        ("{\"step\": 4}", "step", "`step` 4 is out of range: the volume has 4 time steps (0..=3)"),
        ("{\"step\": 1, \"rate\": 0}", "rate", "`rate` 0 is not a number of steps per second"),
        ("{\"rate\": 1e6, \"play\": \"play\"}", "rate", "`rate` 1000000"),
    ] {
        let r = con.post("/api/time", body);
        let text = String::from_utf8_lossy(&r.body).to_string();
        assert_eq!((r.status, r.json()["field"].as_str()), (422, Some(field)), "{body}: {text}");
        assert!(text.contains(says), "{body}: {text}");
    }
    let r = con.post("/api/time", "{\"step\": -1}");
    assert_eq!(r.status, 422, "{}", String::from_utf8_lossy(&r.body));
    let t = settled(&con)["time"].clone();
    assert_eq!(
        (t["step"].as_u64(), t["playing"].as_bool(), t["rate"].as_f64()),
        (Some(0), Some(false), Some(4.0))
    );
    // Step 2: the status reports it and the wall shows it (the ball 10 units on).
    let r = con.post("/api/time", "{\"step\": 2}");
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    wait_time(&con, "step 2", |t| t["step"] == 2 && t["playing"] == false);
    let give_up = Instant::now() + Duration::from_secs(30);
    let moved = loop {
        let n = changed_pixels(&still_b, &snapshot(&con));
        if n > 3 * noise + 40 {
            break n;
        }
        assert!(Instant::now() < give_up, "step 2 looks like step 0: {n} pixels changed, {noise} by noise");
        std::thread::sleep(Duration::from_millis(100));
    };
    eprintln!("step 0 -> 2: {moved} pixels changed ({noise} between two stills of step 0)");
    // Play at 8 steps a second: the step moves on by itself; paused, it stays.
    assert_eq!(con.post("/api/time", "{\"play\": \"play\", \"rate\": 8}").status, 200);
    wait_time(&con, "playing from step 2", |t| t["playing"] == true && t["rate"] == 8.0 && t["step"] != 2);
    assert_eq!(con.post("/api/time", "{\"play\": \"pause\", \"step\": 1}").status, 200);
    let t = wait_time(&con, "paused at step 1", |t| t["playing"] == false && t["step"] == 1);
    // A fixed time: playing at 8 steps a second, the step would have moved in it.
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(con.status()["time"]["step"], t["step"], "paused, the step stays");
}

// ---- the browser ----

/// chromedriver on a free port, killed when dropped.
struct Driver {
    child: Child,
    url: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn found(cmd: &str) -> Option<PathBuf> {
    std::env::var_os("PATH")?.to_str()?.split(':').map(|d| Path::new(d).join(cmd)).find(|p| p.exists())
}

/// Starts chromedriver, or `None` (skip) where chromium or chromedriver is not installed outside
/// CI; under CI their absence fails.
fn driver() -> Option<(Driver, PathBuf)> {
    let (Some(chromium), Some(chromedriver)) = (found("chromium"), found("chromedriver")) else {
        assert!(
            !in_ci(),
            "chromium and chromedriver are needed under CI=true (apt-get install chromium chromium-driver)"
        );
        eprintln!(
            "skipping: chromium or chromedriver is not installed (apt-get install chromium chromium-driver)"
        );
        return None;
    };
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let child = Command::new(chromedriver)
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start chromedriver");
    let give_up = Instant::now() + Duration::from_secs(30);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < give_up, "chromedriver did not listen on {port}");
        std::thread::sleep(Duration::from_millis(100));
    }
    Some((Driver { child, url: format!("http://127.0.0.1:{port}") }, chromium))
}

async fn browser(driver: &Driver, chromium: &Path, profile: &Path) -> fantoccini::Client {
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        serde_json::json!({
            "binary": chromium,
            "args": [
                "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--window-size=1280,1200", format!("--user-data-dir={}", profile.display()),
            ],
        }),
    );
    fantoccini::ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(caps)
        .connect(&driver.url)
        .await
        .expect("a chromium session through chromedriver")
}

/// Evaluates `expr` in the page.
async fn js(page: &fantoccini::Client, expr: &str) -> Value {
    page.execute(&format!("return ({expr});"), vec![]).await.unwrap_or_else(|e| panic!("{expr}: {e}"))
}

/// Waits until `expr` is true in the page; returns how long it took.
async fn until(page: &fantoccini::Client, expr: &str, timeout: Duration) -> Duration {
    let start = Instant::now();
    loop {
        if js(page, expr).await == Value::Bool(true) {
            return start.elapsed();
        }
        assert!(start.elapsed() < timeout, "not within {timeout:?}: {expr}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The wall canvas's pixels (RGB of every other pixel of every other row).
async fn canvas(page: &fantoccini::Client) -> Vec<u8> {
    let v = js(
        page,
        "(() => { const c = document.getElementById('wall'); \
           const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; const out = []; \
           for (let y = 0; y < c.height; y += 2) for (let x = 0; x < c.width; x += 2) { \
             const i = (y * c.width + x) * 4; out.push(d[i], d[i + 1], d[i + 2]); } return out; })()",
    )
    .await;
    v.as_array().expect("pixels").iter().map(|x| x.as_u64().unwrap_or(0) as u8).collect()
}

/// Mean absolute difference of two images, per channel value.
fn difference(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len(), "the canvas changed size");
    let sum: u64 = a.iter().zip(b).map(|(x, y)| u64::from(x.abs_diff(*y))).sum();
    sum as f64 / a.len().max(1) as f64
}

/// Swaps per second over `span`, from the status's released counter.
fn fps_over(con: &Console, span: Duration) -> (f64, Value, Value) {
    let a = con.status();
    let t = Instant::now();
    std::thread::sleep(span);
    let b = con.status();
    let frames = b["frame"]["released"].as_u64().unwrap() - a["frame"]["released"].as_u64().unwrap();
    (frames as f64 / t.elapsed().as_secs_f64(), a, b)
}

fn delta(a: &Value, b: &Value, field: &str) -> u64 {
    b["console"][field].as_u64().unwrap() - a["console"][field].as_u64().unwrap()
}

fn card_state(node: &str, state: &str) -> String {
    format!("document.querySelector('.node-card[data-node=\"{node}\"]')?.dataset.state === '{state}'")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_shows_the_wall_its_nodes_and_drives_it_in_a_real_browser() {
    let Some((driver, chromium)) = driver() else { return };
    let dir = tempfile::tempdir().unwrap();
    let deadline_ms = 3000;
    let config = wall(dir.path(), 4, (96, 72), deadline_ms);
    let (d, c) = (dir.path().to_path_buf(), config.clone());
    let Some(con) =
        tokio::task::spawn_blocking(move || Console::start(&d, &c, &["--local"], None)).await.unwrap()
    else {
        return;
    };
    let con = std::sync::Arc::new(con);
    let measure = |secs: u64| {
        let con = con.clone();
        tokio::task::spawn_blocking(move || fps_over(&con, Duration::from_secs(secs)))
    };
    // The wall alone, no page open.
    let (fps_alone, a0, b0) = measure(10).await.unwrap();

    let page = browser(&driver, &chromium, &dir.path().join("chromium-profile")).await;
    page.goto(&format!("{}/", con.base)).await.unwrap();
    let first = until(&page, "window.isowall.thumbnails >= 1", Duration::from_secs(60)).await;
    until(
        &page,
        "document.querySelectorAll('.node-card[data-state=up]').length === 4",
        Duration::from_secs(30),
    )
    .await;
    let status = con.status();
    assert_eq!(status["nodes"].as_array().unwrap().len(), 4);
    // A volume without time steps: no time controls.
    assert_eq!(status["time"]["steps"], 1);
    assert_eq!(js(&page, "document.getElementById('time').hidden").await, Value::Bool(true));
    assert_eq!(js(&page, "document.getElementById('orbit').offsetParent !== null").await, Value::Bool(true));

    // With the page open (it polls the thumbnail and gets the live status).
    let (fps_page, a1, b1) = measure(10).await.unwrap();
    // Every card shows its node's resident memory (told by the node itself with its Pongs).
    let cards_with_memory =
        "[...document.querySelectorAll('.node-card')].filter(c => /\\d+ MiB/.test(c.textContent)).length";
    until(&page, &format!("{cards_with_memory} === 4"), Duration::from_secs(10)).await;
    // ... and its render and ready times, in ms, as /api/status has them.
    let cards_with_times = "[...document.querySelectorAll('.node-card')].filter(c => \
        /render\\s*\\d+\\.\\d ms/.test(c.textContent) && /ready\\s*\\d+\\.\\d ms/.test(c.textContent)).length";
    until(&page, &format!("{cards_with_times} === 4"), Duration::from_secs(10)).await;
    let frame = &con.status()["frame"];
    assert!(
        frame["frame_ms_p50"]
            .as_f64()
            .zip(frame["frame_ms_p99"].as_f64())
            .is_some_and(|(a, b)| 0.0 < a && a <= b),
        "frame quantiles: {frame}"
    );
    let latencies = js(&page, "window.isowall.latencies").await;
    let mut lat: Vec<f64> = latencies.as_array().unwrap().iter().filter_map(Value::as_f64).collect();
    lat.sort_by(f64::total_cmp);

    // The iso slider, moved with the keyboard like an operator would: the status reports the new
    // iso, and the next thumbnail differs from the last one by far more than two thumbnails of
    // the still camera do (the progressive AO refines between them).
    let iso0 = status["render"]["iso"].as_f64().unwrap();
    let still_a = canvas(&page).await;
    let seen = js(&page, "window.isowall.thumbnails").await.as_u64().unwrap();
    until(&page, &format!("window.isowall.thumbnails > {seen}"), Duration::from_secs(30)).await;
    let still_b = canvas(&page).await;
    let slider = page.find(fantoccini::Locator::Id("iso")).await.unwrap();
    slider.click().await.unwrap();
    // ArrowRight: 20 steps of 1/200 of the value range.
    let right: String = std::iter::repeat_n('\u{E014}', 20).collect();
    slider.send_keys(&right).await.unwrap();
    let wanted: f64 = js(&page, "Number(document.getElementById('iso').value)").await.as_f64().unwrap();
    assert!((wanted - iso0).abs() > 1e-9, "the slider did not move from {iso0}");
    let con2 = con.clone();
    let iso1 = tokio::task::spawn_blocking(move || {
        let give_up = Instant::now() + Duration::from_secs(30);
        loop {
            let iso = con2.status()["render"]["iso"].as_f64().unwrap();
            if (iso - wanted).abs() < 1e-9 {
                return iso;
            }
            assert!(Instant::now() < give_up, "the status kept iso {iso}, the slider says {wanted}");
            std::thread::sleep(Duration::from_millis(100));
        }
    })
    .await
    .unwrap();
    let changed_at = js(&page, "window.isowall.thumbnails").await.as_u64().unwrap();
    // A thumbnail asked for after the change (the one in flight may show the old iso).
    until(&page, &format!("window.isowall.thumbnails > {}", changed_at + 1), Duration::from_secs(30)).await;
    let after = canvas(&page).await;
    let (noise, change) = (difference(&still_a, &still_b), difference(&still_b, &after));
    assert!(
        change > 3.0 * noise + 0.5,
        "iso {iso0} -> {iso1}: the picture changed by {change:.2} (noise {noise:.2})"
    );

    // Kill node1: its card turns down within two deadlines (a straggler at the first, down at
    // the second); restarted, it is up again.
    let pid = status["nodes"][1]["pid"].as_u64().expect("the console started node1");
    assert_eq!(status["nodes"][1]["name"], "node1");
    assert!(Command::new("kill").args(["-KILL", &pid.to_string()]).status().unwrap().success());
    let killed = Instant::now();
    until(&page, &card_state("node1", "down"), Duration::from_millis(2 * deadline_ms + 3000)).await;
    let down_after = killed.elapsed();
    // Three still up.
    assert_eq!(js(&page, "document.querySelectorAll('.node-card[data-state=up]').length").await, 3);
    let shot_down = page.screenshot().await.unwrap();
    let mut restarted = Daemon::start(dir.path(), &config, "node1", &[]);
    assert!(restarted.wait_ready(Duration::from_secs(60)), "node1 restart:\n{}", restarted.log_text());
    let back = until(&page, &card_state("node1", "up"), Duration::from_secs(40)).await;
    until(
        &page,
        "document.querySelectorAll('.node-card[data-state=up]').length === 4",
        Duration::from_secs(10),
    )
    .await;
    // Let the charts and cards fill in, then the picture for the README.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let shot = page.screenshot().await.unwrap();
    let out = PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
    std::fs::write(out.join("console.png"), &shot).unwrap();
    std::fs::write(out.join("console-node-down.png"), &shot_down).unwrap();
    assert!(image::load_from_memory(&shot).is_ok_and(|i| i.width() > 0));
    page.close().await.unwrap();

    let secs = |a: &Value, b: &Value| {
        b["console"]["uptime_s"].as_f64().unwrap() - a["console"]["uptime_s"].as_f64().unwrap()
    };
    let (t0, t1) = (secs(&a0, &b0), secs(&a1, &b1));
    let median = lat.get(lat.len() / 2).copied().unwrap_or(f64::NAN);
    eprintln!("console measurements (2x2 wall of 96x72 tiles, torus 48^3, 4 AO samples, lavapipe):");
    eprintln!("  first thumbnail in the page {:.0} ms after it loaded", first.as_secs_f64() * 1e3);
    eprintln!(
        "  thumbnail latency (swap released -> painted in the page) over {} thumbnails: median {median:.0} ms, min {:.0} ms, max {:.0} ms",
        lat.len(),
        lat.first().copied().unwrap_or(f64::NAN),
        lat.last().copied().unwrap_or(f64::NAN)
    );
    eprintln!(
        "  fps without a page {fps_alone:.2}, with the page open {fps_page:.2}: ratio {:.3}",
        fps_page / fps_alone
    );
    eprintln!(
        "  nodes -> controller image bytes: {:.0} B/s without a page, {:.0} B/s with it; console -> page {:.0} B/s ({} thumbnails asked of the nodes in {t1:.1} s)",
        delta(&a0, &b0, "node_image_bytes") as f64 / t0,
        delta(&a1, &b1, "node_image_bytes") as f64 / t1,
        delta(&a1, &b1, "served_bytes") as f64 / t1,
        delta(&a1, &b1, "thumbnails"),
    );
    eprintln!(
        "  node1 killed -> card down after {:.0} ms (deadline {deadline_ms} ms); restarted -> up after {:.0} ms",
        down_after.as_secs_f64() * 1e3,
        back.as_secs_f64() * 1e3
    );
    eprintln!("  screenshot: {}", out.join("console.png").display());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_shows_time_controls_for_time_steps_and_plays_them() {
    let Some((driver, chromium)) = driver() else { return };
    let dir = tempfile::tempdir().unwrap();
    write_ball_steps(dir.path(), 4);
    let config = wall(dir.path(), 1, (48, 36), 20000);
    set_ball_steps_source(&config);
    let (d, c) = (dir.path().to_path_buf(), config.clone());
    let Some(con) =
        tokio::task::spawn_blocking(move || Console::start(&d, &c, &["--local"], None)).await.unwrap()
    else {
        return;
    };
    let con = std::sync::Arc::new(con);
    let page = browser(&driver, &chromium, &dir.path().join("chromium-profile")).await;
    page.goto(&format!("{}/", con.base)).await.unwrap();
    until(&page, "document.getElementById('time').hidden === false", Duration::from_secs(60)).await;
    assert_eq!(js(&page, "document.getElementById('step').max").await, "3");
    assert_eq!(js(&page, "document.getElementById('play').textContent").await, "play");
    // The play button: the wall plays (the status says so and the step moves), the button says pause.
    page.find(fantoccini::Locator::Id("play")).await.unwrap().click().await.unwrap();
    let con2 = con.clone();
    tokio::task::spawn_blocking(move || {
        wait_time(&con2, "playing after the page's play button", |t| t["playing"] == true && t["step"] != 0)
    })
    .await
    .unwrap();
    until(&page, "document.getElementById('play').textContent === 'pause'", Duration::from_secs(10)).await;
    page.find(fantoccini::Locator::Id("play")).await.unwrap().click().await.unwrap();
    let con2 = con.clone();
    tokio::task::spawn_blocking(move || wait_time(&con2, "paused by the page", |t| t["playing"] == false))
        .await
        .unwrap();
    page.close().await.unwrap();
}

/// Serves `html` to every request on a port of its own: a page of another site (another origin
/// on this machine, as a page a browser opened from anywhere would be).
fn foreign_site(html: String) -> String {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}/", listener.local_addr().unwrap());
    std::thread::spawn(move || {
        for mut s in listener.incoming().map_while(Result::ok) {
            let mut buf = [0u8; 4096];
            let _ = s.read(&mut buf);
            let head = format!(
                "HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                html.len()
            );
            let _ = s.write_all(head.as_bytes()).and_then(|()| s.write_all(html.as_bytes()));
        }
    });
    url
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_page_of_another_site_cannot_read_the_console_and_a_token_page_can() {
    let Some((driver, chromium)) = driver() else { return };
    let dir = tempfile::tempdir().unwrap();
    let config = wall(dir.path(), 1, (32, 24), 20000);
    let (d, c) = (dir.path().to_path_buf(), config.clone());
    let Some(con) =
        tokio::task::spawn_blocking(move || Console::start(&d, &c, &["--local"], None)).await.unwrap()
    else {
        return;
    };
    // Another site's page tries what any page could: an <img> of a snapshot (no token needed on
    // loopback), a no-cors fetch, and the live status over a WebSocket.
    let host = con.base.trim_start_matches("http://");
    let evil = foreign_site(format!(
        r#"<html><body><script>
window.result = {{ img: "pending", ws: "pending" }};
const i = new Image();
i.onload = () => (result.img = "loaded");
i.onerror = () => (result.img = "refused");
i.src = "http://{host}/api/snapshot.png?width=16";
const ws = new WebSocket("ws://{host}/api/live");
ws.onmessage = (e) => (result.ws = "read " + e.data.length + " bytes");
ws.onerror = () => {{ if (result.ws === "pending") result.ws = "refused"; }};
</script></body></html>"#
    ));
    let before = con.status()["console"]["thumbnails"].as_u64().unwrap();
    let page = browser(&driver, &chromium, &dir.path().join("chromium-profile")).await;
    page.goto(&evil).await.unwrap();
    until(
        &page,
        "window.result.img !== 'pending' && window.result.ws !== 'pending'",
        Duration::from_secs(30),
    )
    .await;
    let result = js(&page, "window.result").await;
    eprintln!("a page of another site: {result}");
    assert_eq!(result["img"], "refused", "{result}");
    assert_eq!(result["ws"], "refused", "{result}");
    assert_eq!(con.status()["console"]["thumbnails"].as_u64().unwrap(), before, "the nodes were asked");
    page.close().await.unwrap();
    drop(con);

    // With a token: the console's own page opened as #token=T reads the live status (its
    // WebSocket sends the token as a subprotocol) and shows thumbnails (the token in a header).
    let token = "sesame-0123456789abcdef";
    let (d, c) = (dir.path().to_path_buf(), config.clone());
    let Some(con) = tokio::task::spawn_blocking(move || {
        Console::start(&d, &c, &["--local", "--token", token], Some(token))
    })
    .await
    .unwrap() else {
        return;
    };
    let page = browser(&driver, &chromium, &dir.path().join("chromium-profile-2")).await;
    page.goto(&format!("{}/#token={token}", con.base)).await.unwrap();
    until(
        &page,
        "window.isowall.statusMessages > 0 && window.isowall.thumbnails > 0 && !location.href.includes('token')",
        Duration::from_secs(60),
    )
    .await;
    assert_eq!(js(&page, "document.getElementById('link').textContent").await, "live");
    page.close().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_shows_each_nodes_gpu_and_log_and_drives_bookmarks_the_lock_and_restarts() {
    let Some((driver, chromium)) = driver() else { return };
    let dir = tempfile::tempdir().unwrap();
    let config = wall(dir.path(), 1, (32, 24), 20000);
    let (d, c) = (dir.path().to_path_buf(), config.clone());
    let Some(con) =
        tokio::task::spawn_blocking(move || Console::start(&d, &c, &["--local"], None)).await.unwrap()
    else {
        return;
    };
    let con = std::sync::Arc::new(con);
    let status = |con: &std::sync::Arc<Console>| {
        let con = con.clone();
        async move { tokio::task::spawn_blocking(move || con.status()).await.unwrap() }
    };
    let page = browser(&driver, &chromium, &dir.path().join("chromium-profile")).await;
    page.goto(&format!("{}/", con.base)).await.unwrap();
    until(
        &page,
        "document.querySelectorAll('.node-card[data-state=up]').length === 1",
        Duration::from_secs(60),
    )
    .await;

    // Version, GPU and driver: what the node told, in the status and on its card (in a message
    // of its own, after its Hello: a node is up a moment before they are known).
    let con2 = con.clone();
    let s = tokio::task::spawn_blocking(move || {
        wait_until("node0's version in the status", Duration::from_secs(30), || {
            let s = con2.status();
            if s["nodes"][0]["version"].is_string() {
                Ok(s)
            } else {
                Err(s["nodes"][0].to_string())
            }
        })
    })
    .await
    .unwrap();
    let n = &s["nodes"][0];
    let (version, adapter, backend) =
        (n["version"].as_str().unwrap(), n["adapter"].as_str().unwrap(), n["backend"].as_str().unwrap());
    assert_eq!(version, env!("CARGO_PKG_VERSION"));
    assert!(!adapter.is_empty() && !backend.is_empty(), "{n}");
    let field = |f: &str| {
        format!(
            "document.querySelector('.node-card[data-node=\"node0\"] dd[data-field=\"{f}\"]').textContent"
        )
    };
    until(
        &page,
        &format!("{} === {}", field("version"), serde_json::json!(version)),
        Duration::from_secs(10),
    )
    .await;
    let gpu = js(&page, &field("gpu")).await;
    assert_eq!(gpu.as_str(), Some(format!("{adapter} ({backend})").as_str()));
    assert_eq!(n["local_log"], true);

    // The log: its last lines, as text; a line of markup stays text.
    let log = dir.path().join("logs/node0.log");
    let hostile = "<script>window.pwned = 1</script><b id=\"injected\">bold</b>";
    std::fs::OpenOptions::new()
        .append(true)
        .open(&log)
        .unwrap()
        .write_all(format!("{hostile}\n").as_bytes())
        .unwrap();
    page.find(fantoccini::Locator::Css(".node-card[data-node=\"node0\"] details.log summary"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let pre = "document.querySelector('.node-card[data-node=\"node0\"] pre.log')";
    until(
        &page,
        &format!("{pre}.textContent.includes({})", serde_json::json!(hostile)),
        Duration::from_secs(10),
    )
    .await;
    assert_eq!(js(&page, &format!("{pre}.textContent.includes('ready on')")).await, Value::Bool(true));
    assert_eq!(
        js(&page, "document.getElementById('injected') === null && window.pwned === undefined").await,
        Value::Bool(true)
    );
    assert_eq!(js(&page, &format!("{pre}.children.length")).await, 0, "the log became markup");

    // Bookmarks: save the camera under a name, move, recall, delete; the file beside the config.
    let file = dir.path().join("console.bookmarks.toml");
    let eye0 = s["camera"]["eye"].clone();
    let name_box = page.find(fantoccini::Locator::Id("bookmark-name")).await.unwrap();
    name_box.send_keys("front view").await.unwrap();
    page.find(fantoccini::Locator::Id("bookmark-save")).await.unwrap().click().await.unwrap();
    until(
        &page,
        "[...document.getElementById('bookmark-list').options].some(o => o.value === 'front view')",
        Duration::from_secs(10),
    )
    .await;
    assert!(std::fs::read_to_string(&file).unwrap().contains("name = \"front view\""));
    assert_eq!(con.post("/api/camera", "{\"yaw_deg\": 50}").status, 200);
    let (con2, saved) = (con.clone(), eye0.clone());
    let moved = tokio::task::spawn_blocking(move || {
        wait_until("the camera moved off the bookmark", Duration::from_secs(30), || {
            let eye = con2.status()["camera"]["eye"].clone();
            if eye != saved {
                Ok(eye)
            } else {
                Err(format!("the eye is still {eye}"))
            }
        })
    })
    .await
    .unwrap();
    assert_ne!(moved, eye0);
    page.find(fantoccini::Locator::Id("bookmark-recall")).await.unwrap().click().await.unwrap();
    let give_up = Instant::now() + Duration::from_secs(20);
    loop {
        let eye = status(&con).await["camera"]["eye"].clone();
        let near = eye
            .as_array()
            .unwrap()
            .iter()
            .zip(eye0.as_array().unwrap())
            .all(|(a, b)| (a.as_f64().unwrap() - b.as_f64().unwrap()).abs() < 1e-6);
        if near {
            break;
        }
        assert!(Instant::now() < give_up, "recall kept eye {eye}, the bookmark has {eye0}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    page.find(fantoccini::Locator::Id("bookmark-delete")).await.unwrap().click().await.unwrap();
    until(&page, "document.getElementById('bookmark-list').options.length === 0", Duration::from_secs(10))
        .await;
    assert!(!std::fs::read_to_string(&file).unwrap().contains("front view"));
    // A malformed file: the page names it at its line; the console goes on.
    std::fs::write(&file, "[[bookmark]]\nname = 7\n").unwrap();
    js(&page, "(loadBookmarks(), true)").await;
    until(
        &page,
        "document.getElementById('bookmark-note').textContent.includes('console.bookmarks.toml:2: ')",
        Duration::from_secs(10),
    )
    .await;

    // The lock: taken in the page; another client's change is refused with 423 naming the
    // holder, the page's own changes go ahead; released, the other client may change again.
    page.find(fantoccini::Locator::Id("lock-holder")).await.unwrap().send_keys("alice").await.unwrap();
    page.find(fantoccini::Locator::Id("lock-take")).await.unwrap().click().await.unwrap();
    until(
        &page,
        "document.getElementById('lock-note').textContent.startsWith('you hold the lock')",
        Duration::from_secs(10),
    )
    .await;
    // A status made before the take, arriving after its answer, leaves the tab's lock alone.
    let stale = "(() => { const s = JSON.parse(JSON.stringify(status)); s.console.lock = null; \
                 s.console.lock_changes = lockChanges - 1; show(s); return lockId !== null; })()";
    assert_eq!(js(&page, stale).await, Value::Bool(true), "a stale status dropped the tab's lock");
    let r = con.post("/api/render", "{\"exposure\": 0.5}");
    assert_eq!(
        (r.status, r.json()["holder"].as_str()),
        (423, Some("alice")),
        "{}",
        String::from_utf8_lossy(&r.body)
    );
    // The page writes the answer to its change there: nothing when it went ahead, the reason
    // when it was refused. Marked first, to tell the answer from what was there before.
    js(&page, "(document.getElementById('control-error').textContent = 'asking', true)").await;
    page.find(fantoccini::Locator::Id("home")).await.unwrap().click().await.unwrap();
    until(
        &page,
        "document.getElementById('control-error').textContent !== 'asking'",
        Duration::from_secs(20),
    )
    .await;
    assert_eq!(
        js(&page, "document.getElementById('control-error').textContent").await,
        "",
        "the holder's change was refused"
    );
    page.find(fantoccini::Locator::Id("lock-release")).await.unwrap().click().await.unwrap();
    until(
        &page,
        "document.getElementById('lock-note').textContent.startsWith('nobody holds')",
        Duration::from_secs(10),
    )
    .await;
    assert_eq!(con.post("/api/render", "{\"exposure\": 0.5}").status, 200);

    // Identify: the screen shows its node's and tile's name in its top-left corner (in the
    // snapshot, which is what the screen shows); off again, the corner is the picture's again.
    let corner = |img: &image::RgbImage| -> Vec<u8> {
        let (w, h) = (img.width().min(32), img.height().min(24));
        (0..h).flat_map(|y| (0..w).flat_map(move |x| img.get_pixel(x, y).0)).collect()
    };
    let mean_diff = |a: &[u8], b: &[u8]| {
        a.iter().zip(b).map(|(x, y)| f64::from(x.abs_diff(*y))).sum::<f64>() / a.len().max(1) as f64
    };
    let shot = |con: &std::sync::Arc<Console>| {
        let con = con.clone();
        async move { tokio::task::spawn_blocking(move || snapshot(&con)).await.unwrap() }
    };
    // The picture with the exposure just asked: one drawn after it, not the last one shown.
    let before = {
        let con = con.clone();
        tokio::task::spawn_blocking(move || fresh_snapshot(&con)).await.unwrap()
    };
    page.find(fantoccini::Locator::Id("identify")).await.unwrap().click().await.unwrap();
    until(
        &page,
        "document.getElementById('identify').textContent === 'stop identifying'",
        Duration::from_secs(10),
    )
    .await;
    // White text on black over the corner: far from the picture there before.
    let labelled = |c: &[u8]| {
        c.chunks(3).any(|p| p.iter().all(|v| *v > 200))
            && c.chunks(3).filter(|p| p.iter().all(|v| *v < 10)).count() > c.len() / 6
    };
    let give_up = Instant::now() + Duration::from_secs(20);
    loop {
        let c = corner(&shot(&con).await);
        if labelled(&c) && mean_diff(&c, &corner(&before)) > 20.0 {
            break;
        }
        assert!(
            Instant::now() < give_up,
            "the label never showed in the corner (difference {:.1} from before)",
            mean_diff(&c, &corner(&before))
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    page.find(fantoccini::Locator::Id("identify")).await.unwrap().click().await.unwrap();
    let give_up = Instant::now() + Duration::from_secs(20);
    loop {
        let c = corner(&shot(&con).await);
        let diff = mean_diff(&c, &corner(&before));
        if diff < 3.0 {
            break;
        }
        assert!(
            Instant::now() < give_up,
            "the label stayed after identify was turned off (difference {diff:.1} from before, \
             labelled: {})",
            labelled(&c)
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }

    // Restart from the page: a local node is killed and started again (a new process, its log
    // going on), and its card comes back up.
    let pid0 = status(&con).await["nodes"][0]["pid"].as_u64().expect("a local node's pid");
    js(&page, "(window.confirm = () => true, true)").await;
    page.find(fantoccini::Locator::Css(".node-card[data-node=\"node0\"] button.restart"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    until(
        &page,
        "document.querySelector('.node-card[data-node=\"node0\"] .restart-note').textContent.includes('killed and started again')",
        Duration::from_secs(20),
    )
    .await;
    let give_up = Instant::now() + Duration::from_secs(90);
    loop {
        let s = status(&con).await;
        let n = &s["nodes"][0];
        if n["pid"].as_u64().is_some_and(|p| p != pid0)
            && n["state"] == "up"
            && s["frame"]["released"].as_u64() > Some(0)
        {
            break;
        }
        assert!(Instant::now() < give_up, "node0 did not come back after its restart: {n}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert!(
        std::fs::read_to_string(&log).unwrap().contains(hostile),
        "the restarted node's log started over"
    );
    until(&page, &card_state("node0", "up"), Duration::from_secs(30)).await;
    page.close().await.unwrap();
}
