//! A bad network: the controller drives a 2x2 wall
//! through lossy UDP relays (loss 0, 1 and 5 percent each way, 2 ms ± 1 ms delay), every frame
//! completes, and the image on the wall is the same as after the same orbit driven without the
//! relays. The frame time each loss rate costs is printed (run with `--nocapture`).
//!
//! In screen space the only traffic is controller <-> daemons; daemons do not talk to each other
//! (object space, where they do, is `network_object.rs`).

use isowall_e2e::orbit::orbit_and_snapshot;
use isowall_e2e::relay::{Impairment, Relay};
use isowall_e2e::{free_udp_ports, run_in, start_nodes, wall_config};
use std::time::Duration;

#[test]
fn a_wall_behind_lossy_relays_completes_every_frame_with_the_same_image() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(4);
    let direct = wall_config(dir.path(), "net", &ports, 16, 12, 2, 10_000, "keys");
    assert!(run_in(dir.path(), "isowall", &["keygen", "--config", direct.to_str().unwrap()])
        .status
        .success());
    let Some(mut daemons) = start_nodes(dir.path(), &direct, 4) else { return };
    let frames = 100;
    // First without relays: warms the daemons up (pipelines, connections) and gives the image the
    // wall must show after this orbit; it runs again at the end for the frame-time comparison.
    orbit_and_snapshot(dir.path(), &direct, frames, "direct.png", 4);
    let text = std::fs::read_to_string(&direct).unwrap();
    let mut rows = Vec::new();
    for (i, loss) in [0.0, 0.01, 0.05].into_iter().enumerate() {
        let imp = Impairment {
            loss,
            delay: Duration::from_millis(2),
            jitter: Duration::from_millis(1),
            seed: 1000 + i as u64,
        };
        let relays: Vec<Relay> = ports
            .iter()
            .map(|p| Relay::start(format!("127.0.0.1:{p}").parse().unwrap(), imp).unwrap())
            .collect();
        // The same wall (name, certificates, nodes) with the controller's addresses at the relays.
        let mut relayed = text.clone();
        for (p, r) in ports.iter().zip(&relays) {
            relayed = relayed.replace(&format!("127.0.0.1:{p}\""), &format!("{}\"", r.addr));
        }
        let config = dir.path().join(format!("net-loss{i}.toml"));
        std::fs::write(&config, relayed).unwrap();
        let png = format!("loss{i}.png");
        let run = orbit_and_snapshot(dir.path(), &config, frames, &png, 4);
        let (fwd, dropped) = relays.iter().fold((0, 0), |(f, d), r| {
            let c = r.counts();
            (f + c.forwarded, d + c.dropped)
        });
        if loss > 0.0 {
            assert!(dropped > 0, "the relays dropped nothing at loss {loss}");
        }
        rows.push((loss, run, fwd, dropped, png));
    }
    // The same orbit without relays: the wall must show the same image after each run.
    let clean = orbit_and_snapshot(dir.path(), &direct, frames, "direct-again.png", 4);
    let reference = image::open(dir.path().join("direct.png")).unwrap().to_rgb8();
    let colours: std::collections::HashSet<[u8; 3]> = reference.pixels().map(|p| p.0).collect();
    assert!(colours.len() > 10, "the direct snapshot is nearly blank ({} colours)", colours.len());
    eprintln!(
        "frames {frames}, 2x2 wall of 16x12 tiles, torus 48^3, 4 AO samples; relay 2 ms ± 1 ms each way"
    );
    eprintln!("loss  fps    barrier p50  p99       datagrams forwarded/dropped  fps vs direct");
    eprintln!(
        "none  {:5.1}  {:7.2} ms  {:7.2} ms  (no relay)",
        clean.fps, clean.barrier_p50_ms, clean.barrier_p99_ms
    );
    for (loss, run, fwd, dropped, png) in &rows {
        eprintln!(
            "{:3.0}%  {:5.1}  {:7.2} ms  {:7.2} ms  {fwd}/{dropped}  {:.2}",
            loss * 100.0,
            run.fps,
            run.barrier_p50_ms,
            run.barrier_p99_ms,
            run.fps / clean.fps
        );
        let got = image::open(dir.path().join(png)).unwrap().to_rgb8();
        assert_eq!(got.dimensions(), reference.dimensions());
        let differ = got.pixels().zip(reference.pixels()).filter(|(a, b)| a != b).count();
        assert_eq!(
            differ, 0,
            "at loss {loss} the wall's image differs from the direct run in {differ} pixels"
        );
    }
    // A snapshot by a controller that has begun no frame has none to wait for: it answers well
    // within the wall's deadline (10 s), where it used to wait two deadlines for a frame.
    let started = std::time::Instant::now();
    let out = run_in(dir.path(), "isowall", &["snapshot", direct.to_str().unwrap(), "--out", "last.png"]);
    let waited = started.elapsed();
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && said.contains("4 of 4 tiles"),
        "{said}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("a snapshot on its own: {:.2} s", waited.as_secs_f64());
    assert!(waited < Duration::from_secs(10), "a snapshot on its own took {waited:?}");
    for (i, d) in daemons.iter_mut().enumerate() {
        assert!(d.child.try_wait().unwrap().is_none(), "node{i} exited:\n{}", d.log_text());
    }
}
