//! `isowalld render` as a user runs it: a real process, real files.

use isowall_e2e::{bin, gpu_ok, run_in, shared_dir};
use isowall_render::output::read_pfm;
use std::path::Path;
use std::process::Command;

#[test]
fn no_arguments_render_the_engine_to_isowall_png() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_in(dir.path(), "isowalld", &[]);
    if !gpu_ok("isowalld (no arguments)", &out) {
        return;
    }
    let img = image::open(dir.path().join("isowall.png")).expect("isowall.png written").to_rgb8();
    assert_eq!(img.dimensions(), (800, 600));
    // The engine covers a good part of the frame, lit: many pixels well above the dark background.
    let lit = img.pixels().filter(|p| p.0.iter().map(|&c| c as u32).sum::<u32>() > 200).count();
    let frac = lit as f64 / (800.0 * 600.0);
    assert!(frac > 0.15 && frac < 0.9, "lit fraction {frac}");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("procedural:engine:256") && stdout.contains("fetches/pixel"), "{stdout}");
}

#[test]
fn logs_to_a_redirected_stderr_carry_no_colour_codes() {
    let dir = tempfile::tempdir().unwrap();
    // The log lines come before the GPU opens: they are there with or without an adapter.
    let out = Command::new(bin("isowalld"))
        .current_dir(dir.path())
        .args(["render", "--volume", "procedural:sphere:16", "--size", "16x16"])
        .env("RUST_LOG", "info")
        .env_remove("NO_COLOR")
        .output()
        .expect("isowalld starts");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("INFO") && err.contains("loading volume"), "no log lines to check:\n{err}");
    assert!(!err.contains("\x1b["), "ANSI codes in a redirected stderr:\n{err:?}");
}

#[test]
fn an_iso_outside_the_datas_range_is_refused_before_rendering() {
    let dir = tempfile::tempdir().unwrap();
    // procedural:sphere:16's values run from about -7.7 to 4.4.
    let mut cases = vec![
        ("procedural:sphere:16".to_string(), "100", "every ray would miss"),
        ("procedural:sphere:16".to_string(), "-50", "a solid box"),
    ];
    if let Some(shared) = shared_dir() {
        let mri = shared.join("data/mri-brainsmall.nrrd");
        cases.push((mri.to_str().unwrap().to_string(), "-50", "a solid box"));
    }
    for (volume, iso, consequence) in &cases {
        let out = run_in(
            dir.path(),
            "isowalld",
            &["render", "--volume", volume, "--iso", iso, "--size", "16x16", "--out", "x.png"],
        );
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "--iso {iso} on {volume} was accepted:\n{err}");
        let named = format!("--iso {iso} is outside the volume's value range [");
        assert!(err.contains(&named) && err.contains(consequence), "{volume}: missing `{named}`:\n{err}");
        assert!(err.contains(volume.as_str()), "the volume is not named:\n{err}");
        assert!(!dir.path().join("x.png").exists(), "an image was written for --iso {iso}");
    }
}

#[test]
fn a_picture_where_no_pixel_hits_the_surface_says_so() {
    let dir = tempfile::tempdir().unwrap();
    // The sphere far behind the camera, and a sphere smaller than a pixel: written, with a word.
    for (case, args) in [
        ("out of view", ["--eye", "0,1000,0", "--target", "0,2000,0", "--size", "8x8"]),
        ("far away", ["--eye", "0,0,1e5", "--target", "8,8,8", "--size", "4x4"]),
    ] {
        let mut all = vec!["render", "--volume", "procedural:sphere:16", "--iso", "0", "--out", "x.png"];
        all.extend(args);
        let out = run_in(dir.path(), "isowalld", &all);
        let err = String::from_utf8_lossy(&out.stderr);
        if !gpu_ok("isowalld render", &out) {
            return;
        }
        assert!(out.status.success(), "{case}: {err}");
        assert!(err.contains("no pixel of the") && err.contains("thinner than a pixel"), "{case}: {err}");
    }
    // A picture that hits it says nothing of the kind.
    let out = run_in(
        dir.path(),
        "isowalld",
        &["render", "--volume", "procedural:sphere:16", "--iso", "0", "--size", "8x8"],
    );
    assert!(!String::from_utf8_lossy(&out.stderr).contains("no pixel of the"));
}

#[test]
fn an_output_file_of_an_unsupported_format_is_refused_before_rendering() {
    let dir = tempfile::tempdir().unwrap();
    for (aov, out, wanted) in
        [("color", "x.jpg", ".png (PNG), not `.jpg`"), ("depth", "d.png", ".pfm (PFM), not `.png`")]
    {
        let out_path = dir.path().join(out);
        let o = run_in(
            dir.path(),
            "isowalld",
            &["render", "--volume", "procedural:sphere:16", "--size", "16x16", "--aov", aov, "--out", out],
        );
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "--out {out} accepted:\n{err}");
        assert!(err.contains(&format!("--out: {out}: the {aov} AOV is written as {wanted}")), "{err}");
        assert!(err.contains("supported: .png (color), .pfm (depth, normal"), "{err}");
        assert!(!err.contains("loading volume"), "refused only after loading the volume:\n{err}");
        assert!(!out_path.exists(), "{out} was left behind");
    }
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "files were left behind");
}

#[test]
fn a_multi_frame_render_shows_its_progress_on_a_redirected_stderr() {
    let dir = tempfile::tempdir().unwrap();
    for renderer in ["gpu", "reference"] {
        let out = run_in(
            dir.path(),
            "isowalld",
            &[
                "render",
                "--renderer",
                renderer,
                "--volume",
                "procedural:sphere:16",
                "--size",
                "16x16",
                "--ao-samples",
                "1",
                "--frames",
                "8",
            ],
        );
        if !gpu_ok(&format!("isowalld render --frames 8 --renderer {renderer}"), &out) {
            return;
        }
        let err = String::from_utf8_lossy(&out.stderr);
        let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("isowalld render: frame ")).collect();
        let frames: Vec<&str> =
            lines.iter().map(|l| l.split_whitespace().nth(3).unwrap_or_default()).collect();
        assert_eq!(frames, ["2", "4", "6", "8"], "{renderer}: a line at every quarter:\n{err}");
        assert!(lines[3].starts_with("isowalld render: frame 8 of 8 (100%), "), "{renderer}:\n{err}");
        assert!(
            !err.contains('\r') && !err.contains("\x1b["),
            "{renderer}: a terminal's bar in a pipe:\n{err:?}"
        );
    }
}

#[test]
fn render_help_names_every_contract_flag() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_in(dir.path(), "isowalld", &["render", "--help"]);
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for flag in [
        "--volume",
        "--iso",
        "--size",
        "--eye",
        "--view",
        "--target",
        "--up",
        "--fov-y",
        "--shading",
        "--aov",
        "--out",
        "--renderer",
        "--dims",
        "--type",
        "--spacing",
        "--ao-samples",
        "--ao-radius",
        "--ao-method",
        "--ibl",
        "--env",
        "--frames",
        "--seed",
        "--exposure",
    ] {
        assert!(help.contains(flag), "render --help lacks {flag}");
    }
}

/// `--view NAME`: an unknown name is refused with the list of names before anything is loaded,
/// `--view` with `--eye` is refused, and `--view anterior` of the real CT renders the skull.
#[test]
fn a_view_name_is_checked_and_the_anterior_view_of_the_ct_renders() {
    let dir = tempfile::tempdir().unwrap();
    let out =
        run_in(dir.path(), "isowalld", &["render", "--volume", "procedural:sphere:16", "--view", "front"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("unknown view 'front': one of anterior|posterior|left|right|superior|inferior"),
        "{err}"
    );
    let args = ["render", "--volume", "procedural:sphere:16", "--view", "left", "--eye", "1,2,3"];
    let out = run_in(dir.path(), "isowalld", &args);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--view") && err.contains("--eye") && err.contains("cannot be used with"), "{err}");

    let Some(shared) = shared_dir() else { return };
    let ct = shared.join("data/ct-cranium.nrrd");
    let file = dir.path().join("anterior.pfm");
    let args = [
        "render",
        "--volume",
        ct.to_str().unwrap(),
        "--iso",
        "300",
        "--size",
        "64x64",
        "--view",
        "anterior",
        "--aov",
        "hit",
        "--out",
        file.to_str().unwrap(),
    ];
    let out = run_in(dir.path(), "isowalld", &args);
    if !gpu_ok("render --view anterior", &out) {
        return;
    }
    let hit = read_pfm(&file).unwrap();
    let hits = hit.data.iter().filter(|&&v| v == 1.0).count();
    assert_eq!((hit.width, hit.height), (64, 64));
    assert!(hits > 64 * 64 / 10, "the anterior view hits {hits} of 4096 pixels");
}

/// A scan with a patient orientation (NRRD `space: RAS`) opens anterior, superior up: the default
/// render is `--view anterior`'s, and not the posterior one (two balls of different sizes, so no
/// two sides look alike).
#[test]
fn an_oriented_scan_opens_from_the_anterior() {
    let dir = tempfile::tempdir().unwrap();
    let mut bytes = b"NRRD0004\ntype: float\ndimension: 3\nsizes: 20 20 20\nspace: RAS\n\
                      space directions: (1,0,0) (0,1,0) (0,0,1)\nendian: little\nencoding: raw\n\n"
        .to_vec();
    for k in 0..20 {
        for j in 0..20 {
            for i in 0..20 {
                let p = [i as f64, j as f64, k as f64];
                let d = |c: [f64; 3], r: f64| r - ((0..3).map(|a| (p[a] - c[a]).powi(2)).sum::<f64>()).sqrt();
                let v = d([6.0, 8.0, 9.0], 4.0).max(d([13.0, 11.0, 10.0], 2.5));
                bytes.extend((v as f32).to_le_bytes());
            }
        }
    }
    std::fs::write(dir.path().join("balls.nrrd"), bytes).unwrap();
    let hits = |name: &str, extra: &[&str]| {
        let mut args =
            vec!["render", "--volume", "balls.nrrd", "--iso", "0", "--size", "48x40", "--aov", "hit"];
        args.extend(["--out", name]);
        args.extend_from_slice(extra);
        let out = run_in(dir.path(), "isowalld", &args);
        gpu_ok(&format!("render {extra:?}"), &out).then(|| read_pfm(&dir.path().join(name)).unwrap().data)
    };
    let Some(default) = hits("default.pfm", &[]) else { return };
    let anterior = hits("anterior.pfm", &["--view", "anterior"]).unwrap();
    let posterior = hits("posterior.pfm", &["--view", "posterior"]).unwrap();
    assert!(default.iter().filter(|&&v| v == 1.0).count() > 100, "the balls are hardly in view");
    assert!(default == anterior, "the default view of an oriented scan is not the anterior one");
    assert!(default != posterior, "the anterior and posterior views look alike");
}

fn median(mut v: Vec<f64>) -> f64 {
    assert!(!v.is_empty());
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Renders one AOV of a scene with both renderers through the CLI and returns (gpu, reference).
fn both(
    dir: &Path,
    volume: &str,
    iso: &str,
    aov: &str,
) -> Option<(isowall_render::output::Pfm, isowall_render::output::Pfm)> {
    let mut res = Vec::new();
    for renderer in ["gpu", "reference"] {
        let file = dir.join(format!("{aov}-{renderer}.pfm"));
        let args = [
            "render",
            "--volume",
            volume,
            "--iso",
            iso,
            "--size",
            "96x96",
            "--aov",
            aov,
            "--renderer",
            renderer,
            "--out",
            file.to_str().unwrap(),
        ];
        let out = run_in(dir, "isowalld", &args);
        if !gpu_ok(&format!("render {volume} {aov} {renderer}"), &out) {
            return None;
        }
        res.push(read_pfm(&file).unwrap());
    }
    let r = res.pop().unwrap();
    Some((res.pop().unwrap(), r))
}

/// `--aov depth|normal|hit` of ct-cranium agree with the exact
/// reference renderer: hit masks except on silhouette pixels, median depth error under 0.05 voxel,
/// median normal error under 1 degree.
#[test]
fn ct_cranium_depth_normal_hit_agree_with_the_reference() {
    let Some(shared) = shared_dir() else { return };
    let ct = shared.join("data/ct-cranium.nrrd");
    let ct = ct.to_str().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let Some((gh, rh)) = both(dir.path(), ct, "300", "hit") else { return };
    let (w, h) = (rh.width as i64, rh.height as i64);
    let at = |x: i64, y: i64| rh.data[(y * w + x) as usize];
    let silhouette = |x: i64, y: i64| {
        (-1..=1).any(|dy| {
            (-1..=1).any(|dx| {
                let (nx, ny) = (x + dx, y + dy);
                nx >= 0 && ny >= 0 && nx < w && ny < h && at(nx, ny) != at(x, y)
            })
        })
    };
    let mut off_silhouette = 0;
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            assert!(gh.data[i] == 0.0 || gh.data[i] == 1.0, "hit AOV holds {}", gh.data[i]);
            if gh.data[i] != rh.data[i] && !silhouette(x, y) {
                off_silhouette += 1;
            }
        }
    }
    let hits = rh.data.iter().filter(|&&v| v == 1.0).count();
    assert!(hits > 1000, "only {hits} reference hits: the view misses the skull");
    assert_eq!(off_silhouette, 0, "hit masks differ off the silhouette");
    let both_hit: Vec<usize> =
        (0..rh.data.len()).filter(|&i| rh.data[i] == 1.0 && gh.data[i] == 1.0).collect();

    let (gd, rd) = both(dir.path(), ct, "300", "depth").unwrap();
    let voxel = 0.9570312;
    let depth_err =
        median(both_hit.iter().map(|&i| (gd.data[i] - rd.data[i]).abs() as f64 / voxel).collect());
    assert!(depth_err < 0.05, "median depth error {depth_err} voxel");
    // No hit, no depth.
    assert!((0..rh.data.len()).all(|i| gh.data[i] == 1.0 || gd.data[i] == 0.0));

    let (gn, rn) = both(dir.path(), ct, "300", "normal").unwrap();
    let angle = |i: usize| {
        let (a, b) = (&gn.data[3 * i..3 * i + 3], &rn.data[3 * i..3 * i + 3]);
        let dot: f64 = (0..3).map(|c| a[c] as f64 * b[c] as f64).sum();
        dot.clamp(-1.0, 1.0).acos().to_degrees()
    };
    let normal_err = median(both_hit.iter().map(|&i| angle(i)).collect());
    assert!(normal_err < 1.0, "median normal error {normal_err} degrees");
    eprintln!("ct-cranium 96x96: {hits} hits, median depth error {depth_err:.2e} voxel, median normal error {normal_err:.2e} deg");
}

#[test]
fn a_raw_volume_renders_from_its_flags() {
    let dir = tempfile::tempdir().unwrap();
    // A 24^3 uint8 ball, written by hand.
    let n = 24usize;
    let mut data = vec![0u8; n * n * n];
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let d = ((i as f64 - 11.5).powi(2) + (j as f64 - 11.5).powi(2) + (k as f64 - 11.5).powi(2))
                    .sqrt();
                data[i + n * (j + n * k)] = if d < 8.0 { 200 } else { 10 };
            }
        }
    }
    std::fs::write(dir.path().join("ball.raw"), &data).unwrap();
    let out = run_in(
        dir.path(),
        "isowalld",
        &[
            "render",
            "--volume",
            "ball.raw",
            "--dims",
            "24,24,24",
            "--type",
            "uint8",
            "--spacing",
            "1,1,2",
            "--iso",
            "100",
            "--size",
            "64x64",
            "--aov",
            "hit",
            "--out",
            "hit.pfm",
        ],
    );
    if !gpu_ok("raw render", &out) {
        return;
    }
    let hit = read_pfm(&dir.path().join("hit.pfm")).unwrap();
    let n_hit = hit.data.iter().filter(|&&v| v == 1.0).count();
    assert!(n_hit > 200, "{n_hit} hits");
    // Without --type the raw file cannot be read, and the error says what is missing.
    let out = run_in(dir.path(), "isowalld", &["render", "--volume", "ball.raw", "--dims", "24,24,24"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--type"));
}

#[test]
fn bad_volume_files_fail_with_the_file_named() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_in(dir.path(), "isowalld", &["render", "--volume", "no-such-file.nrrd"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no-such-file.nrrd"), "{err}");
    assert!(!err.contains("panicked"), "{err}");

    std::fs::write(
        dir.path().join("short.nrrd"),
        b"NRRD0004\ntype: short\ndimension: 3\nsizes: 4 4 4\nencoding: raw\nendian: little\n\n\x01\x02\x03",
    )
    .unwrap();
    let out = run_in(dir.path(), "isowalld", &["render", "--volume", "short.nrrd", "--iso", "1"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("short.nrrd") && err.contains("truncated"), "{err}");
    assert!(!err.contains("panicked"), "{err}");

    let out = run_in(dir.path(), "isowalld", &["render", "--volume", "procedural:teapot"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("teapot"));
}
