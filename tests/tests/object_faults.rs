//! A node killed in object space: its brick goes to a
//! survivor, which loads it, and the image is correct again; restarted, the node gets its brick
//! back and the whole wall is correct. A 2x2 wall of tiny tiles over the torus at 48^3, a fixed
//! camera and no AO (so every frame is the same image, and each recorded frame is compared with
//! one single render of the wall camera; tolerance as in `object_space.rs`).

use isowall_e2e::{
    bin, free_udp_ports, gpu_ok, render_whole, run_in, set_object_mode, start_nodes_with, wall_config, Daemon,
};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Fault injection on every node: an adopted brick waits this long before it is read, so that
/// frames run while it loads (they must complete without it, and differ from the single render).
const ADOPT_DELAY: &[&str] = &["--adopt-delay-ms", "1500"];

/// The controller, killed when dropped.
struct Controller(Child);

impl Drop for Controller {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn unix_ms() -> u128 {
    SystemTime::now().duration_since(UNIX_EPOCH).unwrap().as_millis()
}

/// Waits until `file` contains `needle`; returns the Unix time (ms) it was seen, or `None`.
fn wait_for(file: &Path, needle: &str, timeout: Duration) -> Option<u128> {
    let start = Instant::now();
    while start.elapsed() < timeout {
        if std::fs::read_to_string(file).is_ok_and(|t| t.contains(needle)) {
            return Some(unix_ms());
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    None
}

/// A recorded frame: its id, when it was recorded (Unix ms), each answering tile's frame id.
struct Recorded {
    id: u64,
    at: u128,
    tiles: BTreeMap<String, u64>,
}

fn recorded(dir: &Path) -> Vec<Recorded> {
    let text = std::fs::read_to_string(dir.join("frames.txt")).unwrap_or_default();
    text.lines()
        .filter_map(|l| {
            let mut w = l.split_whitespace();
            let id = w.next()?.parse().ok()?;
            let at = w.next()?.parse().ok()?;
            let tiles = w
                .filter_map(|t| t.split_once('='))
                .filter_map(|(n, f)| Some((n.to_string(), f.parse().ok()?)))
                .collect();
            Some(Recorded { id, at, tiles })
        })
        .collect()
}

/// Waits until a frame with id >= `id` is recorded.
fn wait_frame(dir: &Path, id: u64, timeout: Duration) -> bool {
    let start = Instant::now();
    while start.elapsed() < timeout {
        if recorded(dir).iter().any(|r| r.id >= id) {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    false
}

/// The controller's stderr and every daemon's log.
fn logs(err: &Path, daemons: &[Daemon]) -> String {
    let mut s = std::fs::read_to_string(err).unwrap_or_default();
    for d in daemons {
        s += &format!("\n---- {}\n{}", d.log.display(), d.log_text());
    }
    s
}

/// The number after `prefix` in the first line of `text` holding it.
fn number_after(text: &str, prefix: &str) -> Option<u64> {
    text.split(prefix).nth(1)?.split(|c: char| !c.is_ascii_digit()).next()?.parse().ok()
}

#[test]
fn object_space_a_killed_nodes_brick_is_adopted_and_given_back() {
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let (w, h, bezel, deadline_ms) = (40u32, 30u32, 2u32, 1000u64);
    let config = wall_config(dir.path(), "objkill", &free_udp_ports(4), w, h, bezel, deadline_ms, "keys");
    set_object_mode(&config);
    let text = std::fs::read_to_string(&config).unwrap();
    std::fs::write(&config, text.replace("ao_samples = 4", "ao_samples = 0")).unwrap();
    let cfg = config.to_str().unwrap();
    assert!(run_in(dir.path(), "isowall", &["keygen", "--config", cfg]).status.success());
    let wall_cfg = isowall_model::WallConfig::load(&config).unwrap();
    let (fw, fh) = wall_cfg.wall_size();

    // The single render of the wall camera.
    let whole = render_whole(dir.path(), "procedural:torus:48", (fw, fh), 0, &["--out", "whole.png"]);
    if !gpu_ok("isowalld render", &whole) {
        return;
    }
    eprintln!("keygen and the single render after {:.1} s", started.elapsed().as_secs_f64());
    let whole = image::open(dir.path().join("whole.png")).unwrap().to_rgb8();
    // Per tile of a recorded frame: (max difference in levels, mean difference) against it.
    let compare = |id: u64, tile: &str| -> (u8, f64) {
        let img = image::open(dir.path().join(format!("rec/frame-{id:06}.png"))).unwrap().to_rgb8();
        let t = wall_cfg.tile(tile).unwrap();
        let (mut max, mut sum) = (0u8, 0u64);
        for y in t.y..t.y + t.height {
            for x in t.x..t.x + t.width {
                let (a, b) = (img.get_pixel(x, y).0, whole.get_pixel(x, y).0);
                for c in 0..3 {
                    max = max.max(a[c].abs_diff(b[c]));
                    sum += a[c].abs_diff(b[c]) as u64;
                }
            }
        }
        (max, sum as f64 / (3 * t.width * t.height) as f64)
    };
    let correct = |id: u64, tile: &str| {
        let (max, mean) = compare(id, tile);
        max <= 1 && mean < 0.01
    };

    let t0 = Instant::now();
    let Some(mut daemons) = start_nodes_with(
        dir.path(),
        &config,
        4,
        |_| ADOPT_DELAY.iter().map(|a| a.to_string()).collect(),
        None,
    ) else {
        return;
    };
    eprintln!("4 nodes up after {:.1} s", t0.elapsed().as_secs_f64());
    let err = dir.path().join("orbit.err");
    let child = Command::new(bin("isowall"))
        .arg("orbit")
        .arg(&config)
        .args(["--frames", "100000", "--fps", "10", "--degrees-per-frame", "0", "--record-frames", "rec"])
        .current_dir(dir.path())
        .stdout(std::fs::File::create(dir.path().join("orbit.out")).unwrap())
        .stderr(std::fs::File::create(&err).unwrap())
        .stdin(Stdio::null())
        .spawn()
        .unwrap();
    let mut controller = Controller(child);
    let rec = dir.path().join("rec");
    assert!(
        wait_frame(&rec, 5, Duration::from_secs(60)),
        "the wall did not start:\n{}",
        logs(&err, &daemons)
    );

    eprintln!("5 frames after {:.1} s", t0.elapsed().as_secs_f64());
    // SIGKILL node1 (tile t10): the controller names it down, a survivor adopts brick 1.
    let killed_at = unix_ms();
    daemons[1].child.kill().unwrap();
    let down = wait_for(&err, "node node1 is down", Duration::from_secs(20))
        .unwrap_or_else(|| panic!("node1's death was not reported:\n{}", logs(&err, &daemons)));
    let adopted = wait_for(&err, "adopted brick 1", Duration::from_secs(30))
        .unwrap_or_else(|| panic!("brick 1 was not adopted:\n{}", logs(&err, &daemons)));
    let text = std::fs::read_to_string(&err).unwrap();
    let from =
        text.lines().find(|l| l.contains("adopted brick 1")).and_then(|l| number_after(l, "from frame "));
    let from = from.unwrap_or_else(|| panic!("no frame for the adoption:\n{text}"));
    let adopter = text
        .lines()
        .find(|l| l.contains("adopted brick 1"))
        .and_then(|l| l.split("node ").nth(1)?.split_whitespace().next().map(str::to_string));
    assert!(
        wait_frame(&rec, from + 3, Duration::from_secs(30)),
        "no frames after the adoption:\n{}",
        logs(&err, &daemons)
    );

    // Restart node1: it rejoins and gets its brick back.
    let restarted_at = unix_ms();
    daemons[1] = Daemon::start(dir.path(), &config, "node1", ADOPT_DELAY);
    assert!(
        daemons[1].wait_ready(Duration::from_secs(120)),
        "node1 did not restart:\n{}",
        logs(&err, &daemons)
    );
    let ready_at = unix_ms();
    let back = wait_for(&err, "brick 1 is back with node node1", Duration::from_secs(30))
        .unwrap_or_else(|| panic!("brick 1 did not go back to node1:\n{}", logs(&err, &daemons)));
    let text = std::fs::read_to_string(&err).unwrap();
    let line = text.lines().find(|l| l.contains("brick 1 is back with node node1")).unwrap();
    let home_from = number_after(line, "from frame ").unwrap();
    assert!(
        wait_frame(&rec, home_from + 3, Duration::from_secs(30)),
        "no frames after the rejoin:\n{}",
        logs(&err, &daemons)
    );
    drop(controller.0.kill());
    let _ = controller.0.wait();

    eprintln!("frames recorded after {:.1} s", started.elapsed().as_secs_f64());
    // The recorded frames, by phase. A tile is current when its image is of the frame itself.
    let frames = recorded(&rec);
    let tiles_of = |node: &str| wall_cfg.tiles_of(node).iter().map(|t| t.name.clone()).collect::<Vec<_>>();
    let dead_tile = tiles_of("node1");
    let survivors: Vec<String> = ["node0", "node2", "node3"].iter().flat_map(|n| tiles_of(n)).collect();
    let current = |r: &Recorded, t: &str| r.tiles.get(t) == Some(&r.id);
    // Before the kill: every tile correct.
    let before: Vec<&Recorded> = frames.iter().filter(|r| r.at < killed_at).collect();
    assert!(before.len() >= 3, "{} frames before the kill", before.len());
    for r in &before {
        for t in wall_cfg.tiles.iter().map(|t| &t.name) {
            assert!(
                current(r, t) && correct(r.id, t),
                "frame {} tile {t} before the kill: {:?}",
                r.id,
                compare(r.id, t)
            );
        }
    }
    // After the death is reported, before the adoption: frames complete (no straggling) but lack
    // brick 1, so some surviving tile differs (the comparison can fail).
    let orphan: Vec<&Recorded> = frames
        .iter()
        .filter(|r| r.at >= down && r.id < from && survivors.iter().all(|t| current(r, t)))
        .collect();
    assert!(
        orphan.len() >= 3,
        "fewer than 3 frames completed between the report and the adoption:\n{}",
        logs(&err, &daemons)
    );
    let wrong = orphan.iter().filter(|r| survivors.iter().any(|t| !correct(r.id, t))).count();
    assert!(
        wrong > 0,
        "frames without brick 1 equal the single render: the brick does not show on the survivors' tiles"
    );
    // From the adoption's frame to node1's return: the survivors' tiles are correct, node1's
    // tile is a placeholder (no image).
    let adopted_frames: Vec<&Recorded> =
        frames.iter().filter(|r| r.id >= from && r.at < restarted_at).collect();
    assert!(adopted_frames.len() >= 3, "{} frames with the adopted brick", adopted_frames.len());
    for r in &adopted_frames {
        assert!(
            dead_tile.iter().all(|t| !r.tiles.contains_key(t)),
            "frame {}: node1's tile has an image",
            r.id
        );
        for t in &survivors {
            assert!(current(r, t), "frame {}: tile {t} is not of this frame: {:?}", r.id, r.tiles);
            assert!(correct(r.id, t), "frame {} tile {t} after the adoption: {:?}", r.id, compare(r.id, t));
        }
    }
    // From node1's return on: every tile correct.
    let home: Vec<&Recorded> = frames.iter().filter(|r| r.id >= home_from).collect();
    assert!(home.len() >= 3);
    for r in &home {
        for t in wall_cfg.tiles.iter().map(|t| &t.name) {
            assert!(
                current(r, t) && correct(r.id, t),
                "frame {} tile {t} after the return: {:?} {:?}",
                r.id,
                r.tiles,
                compare(r.id, t)
            );
        }
    }
    // The adopter dropped its copy.
    let adopter = adopter.unwrap();
    let i: usize = adopter.trim_start_matches("node").parse().unwrap();
    assert!(
        daemons[i].log_text().contains("dropping adopted brick"),
        "{adopter} did not drop brick 1:\n{}",
        daemons[i].log_text()
    );

    let first_after_adoption = adopted_frames.first().unwrap();
    let first_home = home.first().unwrap();
    eprintln!(
        "object space, node1 killed: reported down {} ms after the kill; brick 1 adopted by {adopter} {} ms after the report \
         ({} ms after the kill); first correct frame ({}) {} ms after the kill; {} frames completed without brick 1 \
         meanwhile ({wrong} of them differing from the single render); restart: ready {} ms after the start, \
         brick 1 back {} ms after the start, first correct whole frame ({}) {} ms after the start ({} ms after ready)",
        down - killed_at,
        adopted - down,
        adopted - killed_at,
        first_after_adoption.id,
        first_after_adoption.at - killed_at,
        orphan.len(),
        ready_at - restarted_at,
        back - restarted_at,
        first_home.id,
        first_home.at - restarted_at,
        first_home.at - ready_at,
    );
    eprintln!("checked after {:.1} s", started.elapsed().as_secs_f64());
    let load_line = text.lines().find(|l| l.contains("adopted brick 1")).unwrap_or_default().to_string();
    eprintln!("{load_line}");
}
