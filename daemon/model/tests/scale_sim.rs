//! The wall at scale (`isowall_model::sim`): the LAN model drives the real machines as the model
//! says it does, a lost packet is paid for as the protocol pays for it, a 256-node wall runs to
//! the end deterministically, and the object-space machines send what the footprints say.

use std::time::Duration;

use isowall_model::codec;
use isowall_model::messages::Message;
use isowall_model::sim::radix::{factors, message_bytes};
use isowall_model::sim::screen::percentiles;
use isowall_model::sim::{
    run_object, run_radix, run_screen, LanModel, ObjectSpec, ObjectWall, PixelCost, Scene, ScreenSpec,
};
use isowall_model::swap_timing::MarginSetting;
use isowall_model::wire::FrameState;
use isowall_model::{Camera, RenderSettings};

fn quiet() -> LanModel {
    LanModel { jitter: Duration::ZERO, loss: 0.0, ..LanModel::ten_gbe() }
}

fn quiet_spec(nodes: usize, lan: LanModel) -> ScreenSpec {
    ScreenSpec {
        lan,
        render_jitter: Duration::ZERO,
        clock_spread: Duration::ZERO,
        frames: 20,
        ..ScreenSpec::new(nodes, 1)
    }
}

/// The framed bytes of a message as the simulation sends it.
fn framed(msg: &Message) -> usize {
    codec::frame(msg).unwrap().len()
}

fn frame_state_bytes() -> usize {
    let camera = Camera::framing(glam::DVec3::ZERO, glam::DVec3::ONE, 1920, 1080);
    framed(&Message::FrameState(FrameState::new(1, &camera, &RenderSettings::new(0.5), 1)))
}

#[test]
fn the_barrier_is_the_broadcast_the_render_and_the_round_trip() {
    // The controller's NIC sends the N frame states one after the other; the last node renders
    // and its Ready comes back: N link times of a FrameState, the render, a Ready's link time
    // and the latency each way.
    let n = 4;
    let ready = framed(&Message::Ready { frame_id: 10, render_us: 10_000 });
    for latency_us in [50u64, 550, 1050] {
        let lan = LanModel { latency: Duration::from_micros(latency_us), ..quiet() };
        let spec = quiet_spec(n, lan);
        let r = run_screen(&spec);
        assert!(r.errors.is_empty(), "{:?}", r.errors);
        assert_eq!(r.frames.len(), 20);
        let want = lan.link_time(frame_state_bytes()) * n as u32
            + spec.render
            + lan.link_time(ready)
            + 2 * lan.latency;
        let barriers: Vec<Duration> = r.frames.iter().map(|f| f.barrier).collect();
        let (median, _, _) = percentiles(&barriers);
        // Ready is 10 bytes shorter or longer with the frame id's size: within a nanosecond.
        assert!(
            median.abs_diff(want) <= Duration::from_micros(1),
            "latency {latency_us} us: {median:?}, model {want:?}"
        );
        assert!(r.frames.iter().all(|f| f.ready == n && f.stragglers == 0));
    }
}

#[test]
fn the_swap_skew_is_the_controllers_broadcast_of_swaps() {
    // No jitter, equal links: the Swaps leave the controller's NIC a link time apart, and the
    // nodes show them on arrival: the true skew is (N - 1) link times of a Swap.
    for n in [4usize, 64] {
        let lan = quiet();
        let r = run_screen(&quiet_spec(n, lan));
        assert!(r.errors.is_empty(), "{:?}", r.errors);
        let want =
            lan.link_time(framed(&Message::Swap { frame_id: 10, present_at_us: None })) * (n as u32 - 1);
        for f in &r.frames {
            let t = f.true_skew.expect("every node showed it");
            assert!(
                t.abs_diff(want) <= Duration::from_micros(1),
                "{n} nodes, frame {}: {t:?} vs {want:?}",
                f.frame_id
            );
            assert!(f.swap_skew.is_some(), "the controller measured frame {}", f.frame_id);
        }
    }
}

#[test]
fn a_lost_packet_is_sent_again_and_its_frame_released_at_the_deadline() {
    // One packet in 200 lost: a lost message waits for the probe timeout (26 ms), and the
    // connection's later messages behind it (one stream, in order). A frame whose FrameState or
    // Ready comes past the 20 ms deadline is released then without that node, and the wall goes
    // on; one whose messages are only delayed is released late; the others as soon as all are
    // ready (11 ms and a little: the broadcast and the round trip).
    let lan = LanModel { loss: 5e-3, ..quiet() };
    let spec = ScreenSpec { deadline: Duration::from_millis(20), frames: 200, ..quiet_spec(16, lan) };
    let r = run_screen(&spec);
    assert!(r.errors.is_empty(), "loss is no protocol error: {:?}", r.errors);
    assert_eq!(r.frames.len(), 200, "every frame is released");
    assert!(r.lan.retransmitted > 0 && r.lan.tail_losses > 0, "{:?}", r.lan);
    let clean = Duration::from_millis(11) + Duration::from_micros(200);
    let (mut at_deadline, mut late) = (0u64, 0u64);
    for f in &r.frames {
        if f.stragglers > 0 {
            assert_eq!(f.barrier, spec.deadline, "frame {}", f.frame_id);
            assert_eq!(f.ready + f.stragglers, 16);
            at_deadline += 1;
        } else {
            assert!(f.barrier < spec.deadline, "frame {}: {:?}", f.frame_id, f.barrier);
            late += u64::from(f.barrier > clean);
        }
    }
    assert!(at_deadline > 0, "no frame lost a message in {:?}", r.lan);
    // A lost message holds up at most the frames begun within its probe timeout: two.
    assert!(
        at_deadline + late <= 2 * r.lan.retransmitted,
        "{at_deadline} at the deadline, {late} late, {:?}",
        r.lan
    );
    eprintln!("{at_deadline} frames released at the deadline, {late} late, of 200; {:?}", r.lan);
}

#[test]
fn a_256_node_wall_runs_to_the_end_and_a_seed_decides_everything() {
    let spec = ScreenSpec { frames: 12, ..ScreenSpec::new(256, 7) };
    let a = run_screen(&spec);
    assert!(a.errors.is_empty(), "{:?}", a.errors);
    assert_eq!(a.frames.len(), 12);
    assert!(a.frames.iter().all(|f| f.ready + f.stragglers == 256));
    assert!(a.frames.iter().all(|f| f.swap_skew.is_some() && f.true_skew.is_some()));
    let b = run_screen(&spec);
    assert_eq!(a, b, "the same seed, the same run");
    let c = run_screen(&ScreenSpec { seed: 8, ..spec });
    let barriers =
        |r: &isowall_model::sim::ScreenReport| r.frames.iter().map(|f| f.barrier).collect::<Vec<_>>();
    assert_ne!(barriers(&a), barriers(&c), "another seed, other jitter");
}

#[test]
fn the_machines_send_what_the_footprints_say_and_wait_for_the_links() {
    // 16 ObjectMachines on 240x135 tiles, sized for 1080p, against the schedule's geometry of the
    // same bricks at 1080p: the same bytes per node (within the covered rectangles' rounding, a
    // pixel at the small tiles' scale), and the compositing time of the busiest receiver no
    // shorter than its link carrying what it receives.
    let n = 16;
    let lan = LanModel::ten_gbe();
    let r = run_object(&ObjectSpec { frames: 2, ..ObjectSpec::new(n, 8, 3) }).unwrap();
    assert!(r.errors.is_empty(), "{:?}", r.errors);
    assert_eq!(r.frames.len(), 2);
    let scene = Scene::wall(&ObjectWall::new(n, 1).unwrap());
    let ds = run_radix(&scene, &[n], lan, PixelCost::memory_bound(), 3);
    for frame in &r.frames {
        let (mut sim_total, mut geo_total) = (0u64, 0u64);
        for (i, (s, g)) in frame.iter().zip(&ds.nodes).enumerate() {
            assert_eq!(s.missing, 0, "node{i}");
            assert_eq!(s.sent_messages, n as u64 - 1, "node{i}: one message per peer");
            let (a, b) = (s.sent_bytes as f64, g.sent_bytes as f64);
            assert!((a - b).abs() <= 0.06 * b.max(1e6), "node{i}: machines {a} bytes, footprints {b}");
            sim_total += s.sent_bytes;
            geo_total += g.sent_bytes;
            let link = lan.link_time(s.received_bytes as usize);
            assert!(s.composite >= link, "node{i}: composited in {:?}, its link needs {link:?}", s.composite);
        }
        let ratio = sim_total as f64 / geo_total as f64;
        assert!((0.97..1.05).contains(&ratio), "total bytes: machines / footprints = {ratio}");
    }
    // The footprint geometry at 1080p, against a message's own bytes.
    let sent: u64 = ds.nodes.iter().map(|x| x.sent_bytes).sum();
    let received: u64 = ds.nodes.iter().map(|x| x.received_bytes).sum();
    assert_eq!(sent, received);
    assert!(sent >= message_bytes(0) * (n * (n - 1)) as u64);
}

#[test]
fn radix_k_takes_log_k_rounds_and_every_byte_sent_arrives() {
    let scene = Scene::wall(&ObjectWall::new(64, 1).unwrap());
    let lan = LanModel::ten_gbe();
    for (k, rounds) in [(2usize, 6usize), (8, 2), (64, 1)] {
        let f = factors(64, k);
        assert_eq!(f.len(), rounds, "k = {k}: {f:?}");
        let r = run_radix(&scene, &f, lan, PixelCost::memory_bound(), 1);
        let per_round: usize = f.iter().map(|k| k - 1).sum();
        for (i, x) in r.nodes.iter().enumerate() {
            // Its rounds' messages, and in a wall with more than one round maybe its part to the
            // node that shows it.
            let extra = x.sent_messages - per_round as u64;
            assert!(extra <= u64::from(rounds > 1), "k = {k}, node {i}: {} messages", x.sent_messages);
            assert!(x.done > Duration::ZERO, "k = {k}, node {i} never finished");
        }
        let sent: u64 = r.nodes.iter().map(|x| x.sent_bytes).sum();
        let received: u64 = r.nodes.iter().map(|x| x.received_bytes).sum();
        assert_eq!(sent, received, "k = {k}");
        assert_eq!(r.lan.messages, r.nodes.iter().map(|x| x.sent_messages).sum::<u64>());
    }
}

#[test]
fn object_space_at_64_nodes_composites_every_tile_and_a_seed_decides_everything() {
    let spec = ObjectSpec { frames: 1, ..ObjectSpec::new(64, 24, 11) };
    let a = run_object(&spec).unwrap();
    assert!(a.errors.is_empty(), "{:?}", &a.errors[..a.errors.len().min(3)]);
    assert_eq!(a.frames.len(), 1);
    assert!(a.frames[0].iter().all(|s| s.missing == 0 && s.composite > Duration::ZERO));
    assert_eq!(a.lan.messages, 64 + 64 * 63, "the frame states and one message per peer");
    let b = run_object(&spec).unwrap();
    assert_eq!(a, b, "the same seed, the same run");
}

#[test]
fn the_timed_swap_shows_a_256_node_wall_at_one_moment_despite_drifting_clocks() {
    // 4 to 256 nodes whose clocks are up to 20 ms apart and run up to 50 ppm fast or slow, on the
    // jittery 10 GbE LAN, pinged every 500 ms each (spread over the interval, as the controller
    // does); frames after 3 s of pings, over 8 s. Untimed, the skew is the Swap broadcast; timed,
    // what the clock estimates leave.
    for nodes in [4usize, 16, 64, 256] {
        let spec = ScreenSpec {
            frames: 480,
            drift_ppm: 50.0,
            present_jitter: Duration::from_micros(2),
            warm_up: Duration::from_secs(3),
            ping_interval: Duration::from_millis(500),
            ..ScreenSpec::new(nodes, 11)
        };
        let untimed = run_screen(&spec);
        let timed = run_screen(&ScreenSpec { timing: MarginSetting::Auto, ..spec.clone() });
        for r in [&untimed, &timed] {
            assert!(r.errors.is_empty(), "{:?}", r.errors);
            assert_eq!(r.frames.len(), 480);
        }
        let skews = |r: &isowall_model::sim::ScreenReport| {
            let t: Vec<Duration> = r.frames.iter().filter_map(|f| f.true_skew).collect();
            let m: Vec<Duration> = r.frames.iter().filter_map(|f| f.swap_skew).collect();
            let err: Vec<Duration> =
                r.frames.iter().filter_map(|f| Some(f.swap_skew?.abs_diff(f.true_skew?))).collect();
            (percentiles(&t), percentiles(&m), percentiles(&err))
        };
        let ((u50, u99, _), (um50, _, _), _) = skews(&untimed);
        let ((t50, t99, tmax), (m50, m99, _), (_, e99, emax)) = skews(&timed);
        let late: usize = timed.frames.iter().map(|f| f.late_swaps).sum();
        let margin = timed.frames.last().and_then(|f| f.margin).unwrap();
        eprintln!(
            "{nodes} nodes: untimed true skew p50 {u50:?} p99 {u99:?} (measured p50 {um50:?}); timed true p50 \
             {t50:?} p99 {t99:?} max {tmax:?}, measured p50 {m50:?} p99 {m99:?}, |measured - true| p99 {e99:?} \
             max {emax:?}, {late} late swaps, margin {margin:?}"
        );
        if nodes == 256 {
            assert!(u99 > Duration::from_millis(1), "the broadcast spreads untimed swaps: {u99:?}");
        }
        assert!(t99 <= Duration::from_micros(50), "{nodes} nodes: timed true skew p99 {t99:?}");
        // The measure cannot see the clock estimates' own errors: a 10 GbE link's 20 us of
        // jitter leaves each offset a few microseconds off, and 256 of them spread about 20 us.
        assert!(e99 <= Duration::from_micros(25), "{nodes} nodes: measured near the truth: p99 {e99:?}");
        // A lost Swap (one packet in 100,000) is late by QUIC's probe timeout; nothing else is.
        assert!(late <= 8, "{nodes} nodes: late swaps: {late}");
    }
}

#[test]
fn a_paced_wall_presents_on_the_grid_and_an_unpaced_one_as_fast_as_before() {
    // 16 nodes rendering 10 ms (+ up to 1 ms), frames begun as soon as the controller allows.
    let spec = ScreenSpec {
        nodes: 16,
        frames: 120,
        frame_interval: Duration::ZERO,
        drift_ppm: 50.0,
        present_jitter: Duration::from_micros(2),
        warm_up: Duration::from_secs(2),
        ping_interval: Duration::from_millis(500),
        timing: MarginSetting::Auto,
        ..ScreenSpec::new(16, 5)
    };
    let fps = |r: &isowall_model::sim::ScreenReport| {
        let t: Vec<Duration> = r.frames.iter().filter_map(|f| f.shown_at).collect();
        (t.len() - 1) as f64 / (t[t.len() - 1] - t[0]).as_secs_f64()
    };
    let untimed = run_screen(&ScreenSpec { timing: MarginSetting::Off, ..spec.clone() });
    let timed = run_screen(&spec);
    let paced = run_screen(&ScreenSpec { frame_rate: Some(60.0), ..spec.clone() });
    for r in [&untimed, &timed, &paced] {
        assert!(r.errors.is_empty(), "{:?}", r.errors);
        assert_eq!(r.frames.len(), 120);
    }
    let (fu, ft, fp) = (fps(&untimed), fps(&timed), fps(&paced));
    // Unpaced, the timed swap costs no frame rate: the next frame renders while one waits.
    assert!((ft - fu).abs() / fu < 0.05, "untimed {fu:.1} fps, timed {ft:.1}");
    // Paced at 60 (renders take 11 ms at most): every frame on the next slot of the grid.
    let period = Duration::from_secs_f64(1.0 / 60.0);
    let shown: Vec<Duration> = paced.frames.iter().filter_map(|f| f.shown_at).collect();
    let jitter: Vec<Duration> = shown.windows(2).map(|w| (w[1] - w[0]).abs_diff(period)).collect();
    let (j50, j99, jmax) = percentiles(&jitter);
    let latency: Vec<Duration> = paced.frames.iter().filter_map(|f| f.margin).collect();
    let (l50, l99, _) = percentiles(&latency);
    eprintln!(
        "16 nodes: untimed {fu:.1} fps, timed {ft:.1} fps, paced {fp:.2} fps; interval jitter p50 {j50:?} p99 \
         {j99:?} max {jmax:?}; release -> present p50 {l50:?} p99 {l99:?}"
    );
    assert!((fp - 60.0).abs() < 0.1, "paced at {fp} fps");
    assert!(j99 <= Duration::from_micros(50), "interval jitter p99 {j99:?}");
}
