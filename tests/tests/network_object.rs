//! A bad network in object space: a 4-node object-space
//! wall where every datagram, the controller's to each node and each node's pixels to each other
//! node, crosses a lossy UDP relay (loss 0, 1 and 5 percent each way, 2 ms ± 1 ms delay). Every frame
//! completes and the wall's image equals the one the same orbit gives without relays; the frame
//! time each loss rate costs is printed (run with `--nocapture`).
//!
//! The controller reaches the relays through a copy of the config with their addresses; each node
//! reaches each peer through a relay of its own for that peer (`isowalld run --peer-addr
//! NODE=HOST:PORT`), so there are 4 + 4 x 3 relays. One set of relayed daemons serves all loss
//! rates: the relays change their impairment between orbits while the connections stay up.

use isowall_e2e::orbit::{orbit, orbit_and_snapshot, OrbitRun};
use isowall_e2e::relay::{Impairment, Relay, RelayCounts};
use isowall_e2e::{
    free_udp_ports, run_in, set_object_mode, start_nodes, start_nodes_with, wall_config, Daemon,
};
use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

const NODES: usize = 4;
const FRAMES: u32 = 100;
/// Frames before the measured orbits: pipelines compiled, peer connections open.
const WARM_UP: u32 = 3;

fn assert_alive(daemons: &mut [Daemon]) {
    for (i, d) in daemons.iter_mut().enumerate() {
        assert!(d.child.try_wait().unwrap().is_none(), "node{i} exited:\n{}", d.log_text());
    }
}

fn total(relays: &[&Relay]) -> RelayCounts {
    relays.iter().fold(RelayCounts::default(), |t, r| {
        let c = r.counts();
        RelayCounts { forwarded: t.forwarded + c.forwarded, dropped: t.dropped + c.dropped }
    })
}

fn rgb(dir: &Path, png: &str) -> image::RgbImage {
    image::open(dir.join(png)).unwrap().to_rgb8()
}

#[test]
fn an_object_wall_with_lossy_relays_between_all_processes_completes_every_frame_with_the_same_image() {
    let dir = tempfile::tempdir().unwrap();
    let ports = free_udp_ports(NODES);
    let config = wall_config(dir.path(), "onet", &ports, 16, 12, 2, 10_000, "keys");
    set_object_mode(&config);
    assert!(run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()])
        .status
        .success());

    // Without relays: the image the wall must show after the orbit, and the clean frame time
    // (after a short warm-up orbit: pipelines, peer connections).
    let clean: OrbitRun = {
        let Some(mut daemons) = start_nodes(dir.path(), &config, NODES) else { return };
        orbit(dir.path(), &config, WARM_UP);
        let run = orbit_and_snapshot(dir.path(), &config, FRAMES, "direct.png", NODES);
        assert!(run.report.contains("object space"), "no object-space statistics:\n{}", run.report);
        assert_alive(&mut daemons);
        run
    };

    let target = |i: usize| -> SocketAddr { format!("127.0.0.1:{}", ports[i]).parse().unwrap() };
    let pass = Impairment { loss: 0.0, delay: Duration::ZERO, jitter: Duration::ZERO, seed: 0 };
    let controller: Vec<Relay> = (0..NODES).map(|i| Relay::start(target(i), pass).unwrap()).collect();
    // peers[a][b]: node a's way to node b.
    let peers: Vec<Vec<Option<Relay>>> = (0..NODES)
        .map(|a| (0..NODES).map(|b| (a != b).then(|| Relay::start(target(b), pass).unwrap())).collect())
        .collect();
    let peer_addr = |a: usize| -> Vec<String> {
        (0..NODES)
            .filter(|&b| b != a)
            .flat_map(|b| {
                ["--peer-addr".to_string(), format!("node{b}={}", peers[a][b].as_ref().unwrap().addr)]
            })
            .collect()
    };
    let Some(mut daemons) = start_nodes_with(dir.path(), &config, NODES, peer_addr, None) else { return };
    // The same wall with the controller's addresses at its relays.
    let mut text = std::fs::read_to_string(&config).unwrap();
    for (p, r) in ports.iter().zip(&controller) {
        text = text.replace(&format!("127.0.0.1:{p}\""), &format!("{}\"", r.addr));
    }
    let relayed = dir.path().join("onet-relayed.toml");
    std::fs::write(&relayed, text).unwrap();
    orbit(dir.path(), &relayed, WARM_UP);

    let controller_relays: Vec<&Relay> = controller.iter().collect();
    let peer_relays: Vec<&Relay> = peers.iter().flatten().flatten().collect();
    let mut rows = Vec::new();
    for (i, loss) in [0.0, 0.01, 0.05].into_iter().enumerate() {
        for (k, r) in controller_relays.iter().chain(&peer_relays).enumerate() {
            r.set_impairment(Impairment {
                loss,
                delay: Duration::from_millis(2),
                jitter: Duration::from_millis(1),
                seed: 1000 * (i as u64 + 1) + k as u64,
            });
        }
        let png = format!("loss{i}.png");
        let run = orbit_and_snapshot(dir.path(), &relayed, FRAMES, &png, NODES);
        let (c, p) = (total(&controller_relays), total(&peer_relays));
        // The pixels really cross the peer relays (and lose datagrams there), not a direct path.
        assert!(p.forwarded > 0, "no datagram crossed the relays between nodes at loss {loss}");
        if loss > 0.0 {
            assert!(c.dropped > 0 && p.dropped > 0, "the relays dropped nothing at loss {loss}: {c:?} {p:?}");
        }
        rows.push((loss, run, c, p, png));
    }
    assert_alive(&mut daemons);

    let reference = rgb(dir.path(), "direct.png");
    let colours: std::collections::HashSet<[u8; 3]> = reference.pixels().map(|p| p.0).collect();
    assert!(colours.len() > 10, "the direct snapshot is nearly blank ({} colours)", colours.len());
    eprintln!(
        "object space, {NODES} nodes, {FRAMES} frames, 2x2 wall of 16x12 tiles, torus 48^3, 4 AO samples; \
         relays 2 ms ± 1 ms each way on every path (controller-node and node-node)"
    );
    eprintln!("loss  fps    barrier p50  p99       controller fwd/dropped  nodes fwd/dropped  fps vs direct");
    eprintln!(
        "none  {:5.1}  {:7.2} ms  {:7.2} ms  (no relay)",
        clean.fps, clean.barrier_p50_ms, clean.barrier_p99_ms
    );
    for (loss, run, c, p, png) in &rows {
        eprintln!(
            "{:3.0}%  {:5.1}  {:7.2} ms  {:7.2} ms  {}/{}  {}/{}  {:.2}",
            loss * 100.0,
            run.fps,
            run.barrier_p50_ms,
            run.barrier_p99_ms,
            c.forwarded,
            c.dropped,
            p.forwarded,
            p.dropped,
            run.fps / clean.fps
        );
        let got = rgb(dir.path(), png);
        assert_eq!(got.dimensions(), reference.dimensions());
        let differ = got.pixels().zip(reference.pixels()).filter(|(a, b)| a != b).count();
        assert_eq!(
            differ, 0,
            "at loss {loss} the wall's image differs from the direct run in {differ} pixels"
        );
    }
}
