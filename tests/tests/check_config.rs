//! `isowall check-config` and `isowalld check-config` as a user runs them: a broken wall config
//! exits 1 naming FILE:LINE:COL for every problem; the example configs exit 0 with a summary.

use isowall_e2e::{free_udp_ports, repo_root, run_in, set_object_mode, shared_dir, wall_config_2x1};
use isowall_test_support::{lying_hdr, lying_png};

const BROKEN: &str = r#"[wall]
name = "broken"
colour = "red"

[volume]
source = "procedural:engine"

[[tiles]]
name = "t00"
x = 0
y = 0
width = 160
height = 120

[[tiles]]
name = "t00"
x = 400
y = 0
width = 160
height = 120

[[tiles]]
name = "t02"
x = 100
y = 60
width = 160
height = 120

[[nodes]]
name = "node0"
address = "127.0.0.1:7401"
tiles = ["t00", "t02"]
"#;

#[test]
fn a_broken_config_names_every_problem_with_its_position() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("broken.toml"), BROKEN).unwrap();
    for bin in ["isowall", "isowalld"] {
        let out = run_in(dir.path(), bin, &["check-config", "broken.toml"]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{bin}: {err}");
        for want in [
            "broken.toml:3:1: unknown field `colour`",
            "broken.toml:16:8: duplicate tile name 't00' (first at line 9)",
            "broken.toml:22:1: tile 't02' overlaps tile 't00'",
        ] {
            assert!(err.contains(want), "{bin}: stderr lacks {want:?}:\n{err}");
        }
        let positioned = err.lines().filter(|l| l.starts_with("broken.toml:")).count();
        assert_eq!(positioned, 3, "{bin}: one line per problem:\n{err}");
        assert!(out.stdout.is_empty(), "{bin}: nothing on stdout");
    }
}

#[test]
fn a_syntax_error_and_a_missing_file_exit_1() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("syntax.toml"), "[wall]\nname = \"x\nx = 1\n").unwrap();
    for bin in ["isowall", "isowalld"] {
        let out = run_in(dir.path(), bin, &["check-config", "syntax.toml"]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{bin}: {err}");
        assert!(err.lines().any(|l| l.starts_with("syntax.toml:2:")), "{bin}: {err}");
        let out = run_in(dir.path(), bin, &["check-config", "missing.toml"]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{bin}: {err}");
        assert!(err.contains("missing.toml: cannot read the wall config"), "{bin}: {err}");
    }
}

#[test]
fn every_example_config_checks_out_with_a_summary() {
    let dir = tempfile::tempdir().unwrap();
    let examples = repo_root().join("wall-configs");
    let mut n = 0;
    for entry in std::fs::read_dir(&examples).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "toml") {
            continue;
        }
        let name = path.file_stem().unwrap().to_string_lossy().into_owned();
        // sva-4 and the bench walls render the shared CT, which a node must hold.
        let on_shared_data = std::fs::read_to_string(&path).unwrap().contains("/shared/data/");
        if on_shared_data && shared_dir().is_none() {
            continue;
        }
        for bin in ["isowall", "isowalld"] {
            let out = run_in(dir.path(), bin, &["check-config", path.to_str().unwrap()]);
            let stdout = String::from_utf8_lossy(&out.stdout);
            assert!(out.status.success(), "{bin} {name}: {}", String::from_utf8_lossy(&out.stderr));
            assert!(stdout.contains(&format!("wall '{name}': ")), "{bin} {name}: {stdout}");
            assert!(stdout.contains(" px, ") && stdout.contains("tiles on"), "{bin} {name}: {stdout}");
        }
        n += 1;
    }
    assert!(n >= 4);
    let out =
        run_in(dir.path(), "isowall", &["check-config", examples.join("local-2x2.toml").to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("wall 'local-2x2': 328x248 px, 4 tiles on 4 nodes"), "{stdout}");
    assert!(stdout.contains("node3 (127.0.0.1:7404): t11 160x120+168+128"), "{stdout}");
}

/// A config path that is a FIFO nobody writes, or `/dev/zero`, is refused at once by both
/// binaries (before: a FIFO held `check-config` forever, `/dev/zero` was read until memory ran
/// out), naming what the path is.
#[test]
fn a_config_that_is_a_fifo_or_a_device_is_refused_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("wall.toml");
    assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    for (path, what) in [(fifo.to_str().unwrap(), "a FIFO (named pipe)"), ("/dev/zero", "a device")] {
        for bin in ["isowall", "isowalld"] {
            let mut child = std::process::Command::new(isowall_e2e::bin(bin))
                .args(["check-config", path])
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap();
            let start = std::time::Instant::now();
            while child.try_wait().unwrap().is_none() && start.elapsed() < std::time::Duration::from_secs(20)
            {
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
            if child.try_wait().unwrap().is_none() {
                child.kill().unwrap();
                panic!("{bin} check-config {path} still running after 20 s");
            }
            let out = child.wait_with_output().unwrap();
            let err = String::from_utf8_lossy(&out.stderr);
            assert_eq!(out.status.code(), Some(1), "{bin} {path}: {err}");
            assert!(
                err.contains(&format!(
                    "{path}: cannot read the wall config: it is {what}, not a regular file"
                )),
                "{bin}: {err}"
            );
        }
    }
}

/// `[render] env` images whose own headers say a size over the limits fail the check of both
/// binaries, naming the file and the size, as a node refuses them at start: six PNG faces of
/// 4x4 pixels whose headers say 8192x8192, and a 56-byte `.hdr` whose header says 16384x8192
/// (before: `ok`, exit 0, and every node refused to start). Faces of 8x8 pass, and an
/// environment that is not on this machine is left to the nodes.
#[test]
fn an_environment_whose_headers_say_a_size_over_the_limits_fails_the_check() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let wall = |env: &str| {
        format!(
            "[wall]\nname = \"w\"\n[volume]\nsource = \"procedural:sphere:16\"\n[render]\nenv = \"{env}\"\n\
             [[tiles]]\nname = \"t\"\nx = 0\ny = 0\nwidth = 160\nheight = 120\n\
             [[nodes]]\nname = \"n0\"\naddress = \"127.0.0.1:7401\"\ntiles = [\"t\"]\n"
        )
    };
    std::fs::create_dir(d.join("faces")).unwrap();
    for face in ["px", "nx", "py", "ny", "pz", "nz"] {
        lying_png(&d.join(format!("faces/{face}.png")), 8192, 8192);
    }
    lying_hdr(&d.join("big.hdr"), 16384, 8192);
    for (env, want) in [
        ("faces", "faces/px.png: the PNG header says 8192x8192, over the largest cube face of 2048x2048"),
        ("big.hdr", "big.hdr: the HDR header says 16384x8192 (134217728 pixels), over the limit of 33554432"),
    ] {
        std::fs::write(d.join("w.toml"), wall(env)).unwrap();
        for bin in ["isowall", "isowalld"] {
            let out = run_in(d, bin, &["check-config", "w.toml"]);
            let err = String::from_utf8_lossy(&out.stderr);
            eprintln!("{bin} check-config, env = {env:?}: {err}");
            assert_eq!(out.status.code(), Some(1), "{bin} {env}: {err}");
            assert!(
                err.contains("w.toml: [render] env: ")
                    && err.contains(want)
                    && err.contains("refused before decoding"),
                "{bin} {env}: wanted {want:?}:\n{err}"
            );
        }
    }
    let good = image::RgbImage::from_pixel(8, 8, image::Rgb([10, 20, 30]));
    for face in ["px", "nx", "py", "ny", "pz", "nz"] {
        good.save(d.join(format!("faces/{face}.png"))).unwrap();
    }
    // Good faces pass both; files not on this machine pass the controller (the nodes hold them)
    // and fail a node, which could not load them.
    for env in ["faces", "elsewhere.hdr", "elsewhere-faces"] {
        std::fs::write(d.join("w.toml"), wall(env)).unwrap();
        for bin in ["isowall", "isowalld"] {
            let out = run_in(d, bin, &["check-config", "w.toml"]);
            let err = String::from_utf8_lossy(&out.stderr);
            if env != "faces" && bin == "isowalld" {
                assert_eq!(out.status.code(), Some(1), "{bin} {env}: {err}");
                assert!(
                    err.contains(&format!("{env}: no such file or folder on this node")),
                    "{bin} {env}: {err}"
                );
                continue;
            }
            assert!(out.status.success(), "{bin} {env}: {err}");
            assert!(String::from_utf8_lossy(&out.stdout).contains("w.toml: ok"), "{bin} {env}");
        }
    }
}

#[test]
fn a_configs_iso_outside_the_datas_range_is_refused_by_the_node_and_the_controller() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config_2x1(dir.path(), "iso", &free_udp_ports(2), 16, 8, 0, 0);
    let text = std::fs::read_to_string(&config).unwrap();
    // procedural:torus:32's values lie well within [-100, 100].
    std::fs::write(
        &config,
        text.replace("source = \"procedural:torus:32\"\n", "source = \"procedural:torus:32\"\niso = 1000\n"),
    )
    .unwrap();
    let config = config.to_str().unwrap();
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", config]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let named = format!("{config}: [volume] iso 1000 is outside the volume's value range [");
    let started = std::time::Instant::now();
    let out = run_in(dir.path(), "isowall", &["orbit", config, "--frames", "1"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains(&named), "isowall orbit: missing `{named}`:\n{err}");
    assert!(!err.contains("cannot reach"), "refused only after trying the nodes:\n{err}");
    assert!(started.elapsed() < std::time::Duration::from_secs(5), "took {:?}", started.elapsed());
    let out = run_in(dir.path(), "isowalld", &["run", "--config", config, "--node", "node0"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains(&named), "isowalld run: missing `{named}`:\n{err}");
    // In object space a node reads only its brick: the range comes from the block grid.
    set_object_mode(std::path::Path::new(config));
    let out = run_in(dir.path(), "isowalld", &["run", "--config", config, "--node", "node1"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains(&named),
        "isowalld run (object): missing `{named}`:\n{err}"
    );
}

#[test]
fn a_volume_file_that_is_not_there_is_named_by_the_check() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config_2x1(dir.path(), "nofile", &free_udp_ports(2), 16, 8, 0, 0);
    let text = std::fs::read_to_string(&config).unwrap();
    let with_source = |source: &str| {
        std::fs::write(&config, text.replace("procedural:torus:32", source)).unwrap();
        let config = config.to_str().unwrap();
        let node = run_in(dir.path(), "isowalld", &["check-config", config]);
        let controller = run_in(dir.path(), "isowall", &["check-config", config]);
        (node, controller)
    };
    // Its folder is here (a misspelt name): both binaries fail naming the file.
    let (node, controller) = with_source("ct-cranum.nrrd");
    let file = dir.path().join("ct-cranum.nrrd").display().to_string();
    for (bin, out) in [("isowalld", &node), ("isowall", &controller)] {
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{bin} passed:\n{err}");
        assert!(err.contains(&format!("[volume] source: {file}: no such file")), "{bin}:\n{err}");
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(!stdout.contains(": ok"), "{bin} said ok and failed:\n{stdout}");
    }
    // Nor its folder: a node fails; a controller machine passes with a warning naming it.
    let (node, controller) = with_source("data/ct.nrrd");
    let file = dir.path().join("data/ct.nrrd").display().to_string();
    let err = String::from_utf8_lossy(&node.stderr);
    assert!(!node.status.success() && err.contains(&format!("{file}: no such file on this node")), "{err}");
    let err = String::from_utf8_lossy(&controller.stderr);
    assert!(controller.status.success(), "{err}");
    assert!(err.contains("warning: ") && err.contains(&format!("{file} is not on this machine")), "{err}");
}
