//! Time-varying volumes on a wall: a 2x2 wall of local nodes plays a glob of time steps, a demo
//! path's `step` track advancing one step a frame; every recorded frame equals the single render
//! of its step (`isowalld render --step N`), so every node rendered the frame's own step, and the
//! frames of different steps differ. In screen space each node renders the whole step; in object
//! space each node renders its brick and halo of the step and the tiles are composited by depth.

use isowall_e2e::{
    compare_tiles, free_udp_ports, gpu_ok, in_bezel_2x2, render_whole, run_in, set_ball_steps_source,
    set_object_mode, wall_config, write_ball_steps,
};

const STEPS: usize = 4;

#[test]
fn a_2x2_wall_renders_every_frames_time_step_on_every_node() {
    play_steps_on_a_2x2_wall(false);
}

#[test]
fn a_2x2_object_space_wall_renders_every_frames_time_step_from_every_nodes_brick() {
    play_steps_on_a_2x2_wall(true);
}

fn play_steps_on_a_2x2_wall(object: bool) {
    let dir = tempfile::tempdir().unwrap();
    write_ball_steps(dir.path(), STEPS);
    let (w, h, bezel) = (40u32, 30u32, 3u32);
    let config = wall_config(dir.path(), "steps", &free_udp_ports(4), w, h, bezel, 60_000, "keys");
    set_ball_steps_source(&config);
    if object {
        set_object_mode(&config);
    }
    // The wall camera all along; one step a second at 1 fps: frame k shows step k.
    let key = "eye = [60, -70, 45]\ntarget = [23.5, 23.5, 23.5]";
    let last = STEPS - 1;
    std::fs::write(
        dir.path().join("path.toml"),
        format!("[[key]]\ntime = 0\n{key}\nstep = 0\n\n[[key]]\ntime = {last}\n{key}\nstep = {last}\n"),
    )
    .unwrap();
    let cfg = config.to_str().unwrap();
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", cfg]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let out = run_in(
        dir.path(),
        "isowall",
        &["demo", cfg, "--path", "path.toml", "--local", "--fps", "1", "--record", "rec"],
    );
    if !gpu_ok("isowall demo", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains(&format!("wrote {STEPS} frames")),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("time steps: 3 step changes"), "{stdout}");
    if object {
        // Each node composited from its brick, read per step (at 24^3 the halo reaches most of
        // the volume: resident bytes are checked by object_space.rs on a larger one).
        assert!(stdout.contains("object space"), "no object-space statistics:\n{stdout}");
        for i in 0..4 {
            let log =
                std::fs::read_to_string(dir.path().join(format!("logs/node{i}.log"))).unwrap_or_default();
            assert!(log.contains("time-varying volume: bricks per step"), "node{i}:\n{log}");
            assert!(
                stdout.contains(&format!("node{i}: sent")),
                "no object-space line for node{i}:\n{stdout}"
            );
        }
    }
    let (fw, fh) = (2 * w + 2 * bezel, 2 * h + 2 * bezel);
    let mut frames = Vec::new();
    for k in 0..STEPS {
        let single = format!("single-{k}.png");
        let step = k.to_string();
        let out = render_whole(
            dir.path(),
            "steps/step_*.nrrd",
            (fw, fh),
            4,
            &["--step", &step, "--iso", "0.5", "--out", &single],
        );
        assert!(gpu_ok("isowalld render", &out), "{}", String::from_utf8_lossy(&out.stderr));
        let wall = image::open(dir.path().join(format!("rec/frame-{k:06}.png"))).unwrap().to_rgb8();
        let whole = image::open(dir.path().join(&single)).unwrap().to_rgb8();
        assert_eq!(wall.dimensions(), (fw, fh));
        let d = compare_tiles(&wall, &whole, |x, y| in_bezel_2x2(x, y, w, h, bezel));
        assert_eq!(d.compared, 4 * (w * h) as u64);
        assert!(d.lit > 200, "step {k}: the ball is hardly in view ({} lit pixels)", d.lit);
        eprintln!(
            "step {k}: wall frame vs single render: max difference {} levels, mean {:.4}",
            d.max_diff, d.mean
        );
        assert!(d.max_diff <= 1 && d.mean < 0.01, "step {k}: {d:?}");
        frames.push(whole);
    }
    // The steps are different images: a node showing another step would be seen.
    for i in 0..STEPS {
        for j in i + 1..STEPS {
            let differing = frames[i].pixels().zip(frames[j].pixels()).filter(|(p, q)| p != q).count();
            assert!(differing > 100, "steps {i} and {j} differ in only {differing} pixels");
        }
    }
}
