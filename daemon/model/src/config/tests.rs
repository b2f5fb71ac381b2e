use super::*;

const GOOD: &str = r#"[wall]
name = "test"

[volume]
source = "procedural:sphere"

[[tiles]]
name = "a"
x = 0
y = 0
width = 100
height = 80
bezel = [0, 10, 0, 0]

[[tiles]]
name = "b"
x = 110
y = 0
width = 100
height = 80

[[nodes]]
name = "n0"
address = "127.0.0.1:7401"
tiles = ["a"]

[[nodes]]
name = "n1"
address = "127.0.0.1:7402"
tiles = ["b"]
"#;

fn examples_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../wall-configs")
}

fn example(name: &str) -> WallConfig {
    let path = examples_dir().join(name);
    WallConfig::load(&path).unwrap_or_else(|e| panic!("{e}"))
}

fn problems(text: &str) -> Vec<Problem> {
    match WallConfig::parse(text, Path::new("wall.toml")) {
        Ok(_) => panic!("expected problems in:\n{text}"),
        Err(e) => {
            assert_eq!(e.path, Path::new("wall.toml"));
            e.problems
        }
    }
}

/// Asserts that `text` has a problem on `line` whose message contains `needle`, and returns
/// all its problems.
#[track_caller]
fn expect(text: &str, line: Option<usize>, needle: &str) -> Vec<Problem> {
    let ps = problems(text);
    assert!(
        ps.iter().any(|p| p.line == line && p.message.contains(needle)),
        "no problem at line {line:?} containing {needle:?}; got:\n{ps:#?}"
    );
    ps
}

/// GOOD with the first `from` replaced by `to` (which must be present).
fn with(from: &str, to: &str) -> String {
    assert!(GOOD.contains(from), "{from:?} not in GOOD");
    GOOD.replacen(from, to, 1)
}

#[test]
fn balance_is_off_by_default_and_only_for_screen_space() {
    let plain = WallConfig::parse(GOOD, Path::new("w.toml")).unwrap();
    assert!(!plain.wall.balance);
    let on =
        WallConfig::parse(&with("name = \"test\"", "name = \"test\"\nbalance = true"), Path::new("w.toml"))
            .unwrap();
    assert!(on.wall.balance);
    let object = with("name = \"test\"", "name = \"test\"\nmode = \"object\"\nbalance = true");
    expect(&object, Some(4), "object space splits the volume instead");
    expect(&with("name = \"test\"", "name = \"test\"\nbalance = \"yes\""), Some(3), "invalid type");
}

#[test]
fn object_mode_parses_and_refuses_an_unbounded_radius_or_the_seed_method() {
    let c = WallConfig::parse(
        &with("name = \"test\"", "name = \"test\"\nmode = \"object\""),
        Path::new("w.toml"),
    )
    .unwrap();
    assert_eq!(c.wall.mode, WallMode::Object);
    assert!(c.wall.compress);
    let plain = WallConfig::parse(GOOD, Path::new("w.toml")).unwrap();
    assert_eq!(plain.wall.mode, WallMode::Screen);
    let obj = "name = \"test\"\nmode = \"object\"\ncompress = false";
    let unbounded = format!("{}\n[render]\nao_radius = \"unbounded\"\n", with("name = \"test\"", obj));
    expect(&unbounded, Some(35), "object space needs a bounded AO radius");
    let seed = format!("{}\n[render]\nao_method = \"seed\"\n", with("name = \"test\"", obj));
    expect(&seed, Some(35), "cannot use the `seed` AO method");
    // "on" is accepted: the filter runs on the composited tile (its guard band travels too).
    let filtered = format!("{}\n[render]\nao_samples = 4\ndenoise = \"on\"\n", with("name = \"test\"", obj));
    let c = WallConfig::parse(&filtered, Path::new("w.toml")).unwrap();
    assert_eq!(c.render_settings(1.0).denoise, Denoise::On);
    assert!(c.filters_composited());
    // Still "on" without AO samples is refused, as in screen space.
    let nothing = format!("{}\n[render]\nao_samples = 0\ndenoise = \"on\"\n", with("name = \"test\"", obj));
    expect(&nothing, Some(36), "it needs `ao_samples` > 0");
    let governed =
        format!("{}\n[render]\nao_samples = 4\ntarget_frame_ms = 50\n", with("name = \"test\"", obj));
    let c = WallConfig::parse(&governed, Path::new("w.toml")).unwrap();
    assert_eq!(c.render.denoise, DenoiseSetting::Auto);
    assert_eq!(c.render_settings(1.0).denoise, Denoise::Off, "auto stays off in object space");
    assert!(!c.filters_composited());
    // A screen-space wall filters its tiles itself, never a composite.
    let screen = format!("[render]\nao_samples = 4\ndenoise = \"on\"\n\n{GOOD}");
    let c = WallConfig::parse(&screen, Path::new("w.toml")).unwrap();
    assert_eq!(c.render_settings(1.0).denoise, Denoise::On);
    assert!(!c.filters_composited());
    expect(&with("name = \"test\"", "name = \"test\"\nmode = \"sideways\""), Some(3), "sideways");
}

#[test]
fn the_base_config_is_valid() {
    let c = WallConfig::parse(GOOD, Path::new("/walls/test.toml")).unwrap();
    assert_eq!(c.wall.name, "test");
    assert_eq!(c.wall.deadline_ms, DEFAULT_DEADLINE_MS);
    assert_eq!(c.wall.message_limit_bytes, 64 << 20);
    assert_eq!(c.camera, CameraConfig::default());
    assert_eq!(c.render, RenderConfig::default());
    assert_eq!(c.certificates.dir, "keys");
    assert_eq!(c.wall_size(), (210, 80));
    assert_eq!(c.tile("b").unwrap().x, 110);
    assert_eq!(c.node("n1").unwrap().tiles, ["b"]);
    assert_eq!(c.node_of_tile("a").unwrap().name, "n0");
    assert_eq!(c.tiles_of("n0")[0].name, "a");
    assert!(c.tile("z").is_none() && c.node("z").is_none());
    assert_eq!(c.path, Path::new("/walls/test.toml"));
}

#[test]
fn every_example_config_is_valid() {
    let mut n = 0;
    for entry in std::fs::read_dir(examples_dir()).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let c = WallConfig::load(&path).unwrap_or_else(|e| panic!("{e}"));
            assert!(!c.tiles.is_empty() && !c.nodes.is_empty(), "{}", path.display());
            assert_eq!(c.certificates.dir, "keys", "{}", path.display());
            // The derives agree with the checked parser.
            let text = std::fs::read_to_string(&path).unwrap();
            let plain: WallConfig = toml::from_str(&text).unwrap();
            assert_eq!(WallConfig { path: path.clone(), ..plain }, c);
            n += 1;
        }
    }
    assert!(n >= 4, "only {n} example configs");
}

/// What the examples are for: every `local-*` wall runs on one machine (each node on loopback, so
/// `isowall up` starts it), and the 3x1 wall is the irregular one (three tile widths).
#[test]
fn local_examples_run_on_loopback_and_the_3x1_wall_is_irregular() {
    let mut local = 0;
    for entry in std::fs::read_dir(examples_dir()).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if name.starts_with("local-") && name.ends_with(".toml") {
            let c = WallConfig::load(&path).unwrap_or_else(|e| panic!("{e}"));
            for n in &c.nodes {
                assert!(n.address.starts_with("127.0.0.1:"), "{name}: node '{}' at {}", n.name, n.address);
            }
            local += 1;
        }
    }
    assert!(local >= 3, "only {local} local examples");
    let three = example("local-3x1.toml");
    let widths: std::collections::BTreeSet<u32> = three.tiles.iter().map(|t| t.width).collect();
    assert_eq!((three.tiles.len(), widths.len()), (3, 3), "the 3x1 wall has three tile widths");
}

#[test]
fn the_2x2_rects_and_bezels_tile_the_wall_image_exactly() {
    let c = example("local-2x2.toml");
    let (w, h) = c.wall_size();
    assert_eq!((w, h), (328, 248));
    let mut cover = vec![0u8; (w * h) as usize];
    let mut visible = 0;
    let camera =
        Camera { eye: DVec3::new(0.0, -10.0, 0.0), target: DVec3::ZERO, up: DVec3::Z, fov_y_deg: 35.0 };
    for t in &c.tiles {
        let view = c.tile_view(camera, &t.name).unwrap();
        assert_eq!(view.full, (w, h));
        assert_eq!(view.rect, t.rect());
        visible += view.pixel_count();
        let (x0, x1, y0, y1) = t.outer();
        for y in y0..y1 {
            for x in x0..x1 {
                cover[(y * w as i64 + x) as usize] += 1;
            }
        }
    }
    assert!(cover.iter().all(|&n| n == 1), "tiles with their bezels cover every wall pixel once");
    assert_eq!(visible, 4 * 160 * 120);
    assert_eq!(w * h - visible as u32, 8 * 248 + 8 * 320, "the hidden pixels are the two mullions");
    let origins: Vec<(u32, u32)> = c.tiles.iter().map(|t| (t.x, t.y)).collect();
    assert_eq!(origins, [(0, 0), (168, 0), (0, 128), (168, 128)]);
    assert!(c.tile_view(camera, "nope").is_none());
}

#[test]
fn a_straight_line_stays_straight_across_a_bezel() {
    let c = example("local-2x2.toml");
    let camera = c.camera_for(DVec3::ZERO, DVec3::new(255.0, 255.0, 117.0));
    camera.validate().unwrap();
    let b = camera.basis();
    let (w, h) = c.wall_size();
    let whole = View::whole(camera, w, h);
    // Every tile pixel's ray is the whole wall image's ray through the same wall pixel.
    for t in &c.tiles {
        let v = c.tile_view(camera, &t.name).unwrap();
        for (x, y) in [(0, 0), (t.width - 1, 0), (0, t.height - 1), (t.width - 1, t.height - 1), (37, 51)] {
            assert_eq!(v.ray_dir(&b, x, y), whole.ray_dir_full(&b, t.x + x, t.y + y));
        }
    }
    // Across the vertical mullion, on row 60: the last pixel of t00 and the first of t10 are
    // 1 + 8 pixels apart on the image plane, exactly as far as 9 pixel steps inside a tile.
    let (t00, t10) = (c.tile_view(camera, "t00").unwrap(), c.tile_view(camera, "t10").unwrap());
    let plane_x = |d: DVec3| d.dot(b.right) / d.dot(b.forward);
    let across = plane_x(t10.ray_dir(&b, 0, 60)) - plane_x(t00.ray_dir(&b, 159, 60));
    let inside = plane_x(t00.ray_dir(&b, 9, 60)) - plane_x(t00.ray_dir(&b, 0, 60));
    assert!((across - inside).abs() < 1e-12, "{across} vs {inside}");
    // A slanted line of the wall image through t01 and t10, across both mullions: the wall
    // pixels (20 + 14k, 200 - 9k) seen by their tiles lie on one line of the image plane.
    let plane = |d: DVec3| (plane_x(d), d.dot(b.up) / d.dot(b.forward));
    let (t01, t10) = (c.tile_view(camera, "t01").unwrap(), t10);
    let points = [
        plane(t01.ray_dir(&b, 20, 200 - 128)), // k = 0: wall (20, 200)
        plane(t01.ray_dir(&b, 90, 155 - 128)), // k = 5: wall (90, 155)
        plane(t10.ray_dir(&b, 230 - 168, 65)), // k = 15: wall (230, 65)
        plane(t10.ray_dir(&b, 300 - 168, 20)), // k = 20: wall (300, 20)
    ];
    let (p, q) = (points[0], points[3]);
    for r in &points[1..3] {
        let cross = (q.0 - p.0) * (r.1 - p.1) - (q.1 - p.1) * (r.0 - p.0);
        assert!(cross.abs() < 1e-12, "{r:?} is off the line: {cross}");
    }
}

// ---- Validation: every rule with a failing example, its message and its line. ----

#[test]
fn syntax_errors_have_their_line_and_column() {
    let ps = expect(&with("x = 0\n", "x = = 0\n"), Some(9), "");
    assert_eq!(ps.len(), 1, "one problem per line: {ps:#?}");
    assert!(ps[0].column.is_some());
    // A duplicate key is a TOML error too.
    expect(&with("y = 0\n", "y = 0\ny = 1\n"), Some(11), "duplicate key");
}

#[test]
fn unknown_keys_are_refused_where_they_are() {
    let ps = expect(
        &with("name = \"test\"\n", "name = \"test\"\ndeadline = 5\n"),
        Some(3),
        "unknown field `deadline`",
    );
    assert_eq!(ps[0].column, Some(1));
    expect(&format!("{GOOD}\n[extra]\nfoo = 1\n"), Some(32), "unknown field `extra`");
    expect(&with("height = 80\nbezel", "height = 80\nhieght = 3\nbezel"), Some(13), "unknown field `hieght`");
    expect(&format!("[render]\nao_sample = 8\n\n{GOOD}"), Some(2), "unknown field `ao_sample`");
    expect(&format!("[camera]\nfov = 8\n\n{GOOD}"), Some(2), "unknown field `fov`");
    expect(&format!("[certificates]\npath = \"k\"\n\n{GOOD}"), Some(2), "unknown field `path`");
    expect(
        &with("source = \"procedural:sphere\"\n", "source = \"procedural:sphere\"\nisovalue = 1\n"),
        Some(6),
        "unknown field `isovalue`",
    );
    expect(&with("tiles = [\"a\"]\n", "tiles = [\"a\"]\ncolor = 1\n"), Some(26), "unknown field `color`");
}

#[test]
fn every_problem_of_a_table_is_reported_not_only_its_unknown_key() {
    let shown = |text: &str| match WallConfig::parse(text, Path::new("wall.toml")) {
        Ok(_) => panic!("expected problems in:\n{text}"),
        Err(e) => e.to_string(),
    };
    // An unknown key after a bad value, and before one.
    for render in ["ibl = \"bnet\"\nao_sample = 8\n", "ao_sample = 8\nibl = \"bnet\"\n"] {
        let e = shown(&format!("[render]\n{render}\n{GOOD}"));
        let (ibl, key) = if render.starts_with("ibl") { (2, 3) } else { (3, 2) };
        assert!(e.contains(&format!("wall.toml:{ibl}:7: unknown variant `bnet`")), "{e}");
        assert!(e.contains(&format!("wall.toml:{key}:1: unknown field `ao_sample`")), "{e}");
        assert_eq!(e.lines().count(), 2, "{e}");
    }
    // An unknown key beside a value the table's own rules refuse (checked once the table reads).
    let e = shown(&format!("[render]\nao_sample = 8\nao_samples = 5000\n\n{GOOD}"));
    assert!(e.contains("wall.toml:2:1: unknown field `ao_sample`"), "{e}");
    assert!(e.contains("wall.toml:3:14: render: `ao_samples` 5000 is more than"), "{e}");
    // A required key with a bad value beside an unknown key: both, and not `missing field` too.
    let e = shown(&with("width = 100", "width = \"100\"\nwidht = 3"));
    assert!(e.contains("wall.toml:11:9: invalid type"), "{e}");
    assert!(e.contains("wall.toml:12:1: unknown field `widht`"), "{e}");
    assert!(!e.contains("missing field"), "{e}");
}

#[test]
fn missing_and_mistyped_fields_are_named() {
    // The tile lacks a width: reported at its [[tiles]] header, and the node that lists it is
    // not reported again.
    let ps =
        expect(&with("x = 110\ny = 0\nwidth = 100\n", "x = 110\ny = 0\n"), Some(15), "missing field `width`");
    assert_eq!(ps.len(), 1, "{ps:#?}");
    expect(&with("width = 100", "width = \"100\""), Some(11), "invalid type");
    expect(&with("x = 0", "x = -1"), Some(9), "invalid value: integer `-1`");
    expect(&with("[wall]\nname = \"test\"\n", "[wall]\n"), Some(1), "missing field `name`");
    expect(&with("source = \"procedural:sphere\"\n", "iso = 1\n"), Some(4), "missing field `source`");
    expect(
        &format!("tiles = 3\n{}", &GOOD[GOOD.find("[wall]").unwrap()..].replace("[[tiles]]", "[[t]]")),
        Some(1),
        "invalid type",
    );
}

#[test]
fn missing_sections_tiles_and_nodes_are_placed_at_the_end_or_where_empty() {
    let last_line = |t: &str| Some(t.trim_end().lines().count());
    let no_wall = &GOOD[GOOD.find("[volume]").unwrap()..];
    expect(no_wall, last_line(no_wall), "missing table [wall]");
    let no_volume = GOOD.replace("[volume]\nsource = \"procedural:sphere\"\n", "");
    expect(&no_volume, last_line(&no_volume), "missing table [volume]");
    let bare = "[wall]\nname = \"x\"\n[volume]\nsource = \"procedural:sphere\"\n\n";
    expect(bare, Some(4), "no tiles");
    let ps = expect(bare, Some(4), "no nodes");
    assert_eq!(ps.len(), 2);
    // Printed with the file and the line, like every other problem.
    let e = WallConfig::parse(bare, Path::new("w.toml")).unwrap_err().to_string();
    assert!(e.contains("w.toml:4:1: no nodes"), "{e}");
    // `nodes = []` is where it is.
    let empty = format!("nodes = []\n{bare}");
    expect(&empty, Some(1), "no nodes");
}

#[test]
fn tile_names_are_unique() {
    let ps =
        expect(&with("name = \"b\"", "name = \"a\""), Some(16), "duplicate tile name 'a' (first at line 8)");
    // The node that listed 'b' now names a tile that does not exist.
    assert!(ps.iter().any(|p| p.line == Some(30) && p.message.contains("no tile named 'b'")), "{ps:#?}");
    expect(&with("name = \"a\"", "name = \"a b\""), Some(8), "tile name 'a b' may hold only");
    expect(&with("name = \"a\"", "name = \"\""), Some(8), "tile name is empty");
}

#[test]
fn node_names_are_unique_valid_and_not_reserved() {
    expect(&with("name = \"n1\"", "name = \"n0\""), Some(28), "duplicate node name 'n0' (first at line 23)");
    expect(&with("name = \"n1\"", "name = \"controller\""), Some(28), "reserved");
    expect(&with("name = \"n1\"", "name = \"ca\""), Some(28), "reserved");
    // Without regard to case: TLS name matching ignores it.
    expect(&with("name = \"n1\"", "name = \"Controller\""), Some(28), "reserved");
    expect(&with("name = \"n1\"", "name = \"CA\""), Some(28), "reserved");
    expect(
        &with("name = \"n1\"", "name = \"N0\""),
        Some(28),
        "duplicate node name 'N0' (the same as 'n0' without regard to case) (first at line 23)",
    );
    expect(&with("name = \"n1\"", "name = \"../n1\""), Some(28), "may hold only");
}

#[test]
fn every_node_tile_exists_and_every_tile_has_exactly_one_node() {
    let ps = expect(
        &with("tiles = [\"b\"]", "tiles = [\"c\"]"),
        Some(30),
        "node 'n1': no tile named 'c' (tiles: a, b)",
    );
    assert!(
        ps.iter().any(|p| p.line == Some(16) && p.message.contains("tile 'b' is driven by no node")),
        "{ps:#?}"
    );
    let ps = expect(
        &with("tiles = [\"b\"]", "tiles = [\"a\", \"b\"]"),
        Some(30),
        "tile 'a' is driven by two nodes: 'n1' and 'n0' (line 25)",
    );
    assert_eq!(ps[0].column, Some(10), "at the list element");
    expect(&with("tiles = [\"a\"]", "tiles = [\"a\", \"a\"]"), Some(25), "node 'n0' lists tile 'a' twice");
    expect(&with("tiles = [\"a\"]", "tiles = []"), Some(8), "tile 'a' is driven by no node");
}

#[test]
fn tiles_do_not_overlap_bezels_included() {
    // Visible pixels apart, but b starts inside a's right bezel.
    let ps =
        expect(&with("x = 110", "x = 105"), Some(15), "tile 'b' overlaps tile 'a' (line 7), bezels included");
    assert!(ps[0].message.contains("x 0..110"), "{}", ps[0].message);
    expect(&with("x = 110", "x = 50"), Some(15), "overlaps");
    // Touching is fine.
    WallConfig::parse(&with("bezel = [0, 10, 0, 0]", "bezel = [0, 0, 0, 0]"), Path::new("w.toml")).unwrap();
}

#[test]
fn tile_sizes_and_bezels_are_bounded() {
    expect(&with("width = 100", "width = 0"), Some(11), "tile 'a': `width` 0 is outside 1..=16384");
    expect(&with("height = 80", "height = 16385"), Some(12), "tile 'a': `height` 16385 is outside 1..=16384");
    expect(
        &with("bezel = [0, 10, 0, 0]", "bezel = [3, 10, 0, 0]"),
        Some(13),
        "left bezel (3 px) reaches past",
    );
    expect(
        &with("bezel = [0, 10, 0, 0]", "bezel = [0, 10, 2, 0]"),
        Some(13),
        "top bezel (2 px) reaches past",
    );
    expect(&with("bezel = [0, 10, 0, 0]", "bezel = [0, 99999, 0, 0]"), Some(13), "has a width over 16384");
    expect(&with("x = 110", "x = 2000000"), Some(17), "beyond the largest wall image");
    expect(&with("bezel = [0, 10, 0, 0]", "bezel = [0, 10, 0]"), Some(13), "invalid length 3");
}

#[test]
fn addresses_are_host_and_port() {
    for good in ["127.0.0.1:7401", "sva-node1.cluster:7400", "localhost:1", "[::1]:7400", "node_2:65535"] {
        assert_eq!(check_address(good), Ok(()), "{good}");
    }
    for (bad, why) in [
        ("127.0.0.1", "port is missing"),
        ("127.0.0.1:0", "not in 1..=65535"),
        ("127.0.0.1:70000", "not in 1..=65535"),
        ("host:http", "not in 1..=65535"),
        (":7400", "no host"),
        ("bad host:7400", "not a valid host name"),
        ("-x.org:7400", "not a valid host name"),
        ("a..b:7400", "not a valid host name"),
        ("::1:7400", "in brackets"),
        ("[::g]:7400", "not an IPv6 address"),
        ("[::1]7400", "not [IPv6]:port"),
    ] {
        let e = check_address(bad).unwrap_err();
        assert!(e.contains(why), "{bad}: {e}");
    }
    let ps = expect(
        &with("127.0.0.1:7401", "127.0.0.1"),
        Some(24),
        "node 'n0': address '127.0.0.1' is not host:port",
    );
    assert_eq!(ps[0].column, Some(11), "at the value");
    expect(
        &with("127.0.0.1:7402", "127.0.0.1:7401"),
        Some(29),
        "node 'n1' has the same address 127.0.0.1:7401 as node 'n0' (line 24)",
    );
    // The same socket written another way.
    for (a, b) in [
        ("127.0.0.1:7401", "localhost:7401"),
        ("[::1]:7401", "LocalHost.:7401"),
        ("127.0.0.1:7401", "[::ffff:127.0.0.1]:7401"),
        ("Node-A.cluster:7401", "node-a.cluster.:7401"),
        ("localhost:7401", "wall.localhost:7401"),
    ] {
        let text = with("127.0.0.1:7401", a).replacen("127.0.0.1:7402", b, 1);
        expect(
            &text,
            Some(29),
            &format!("node 'n1' at {b} has the same address as node 'n0' at {a} (line 24)"),
        );
    }
    // Different sockets.
    for (a, b) in [("localhost:7401", "127.0.0.2:7401"), ("localhost:7401", "localhost:7402"), ("a:1", "b:1")]
    {
        let text = with("127.0.0.1:7401", a).replacen("127.0.0.1:7402", b, 1);
        assert!(WallConfig::parse(&text, Path::new("w.toml")).is_ok(), "{a} {b}");
    }
    for bad in ["0.0.0.0:7401", "[::]:7401"] {
        let e = check_address(bad).unwrap_err();
        assert!(e.contains("unspecified address"), "{bad}: {e}");
    }
}

#[test]
fn wall_limits_are_checked() {
    let w = |extra: &str| with("name = \"test\"\n", &format!("name = \"test\"\n{extra}\n"));
    expect(&w("deadline_ms = 0"), Some(3), "wall: `deadline_ms` 0 is outside 1..=600000");
    expect(
        &w("deadline_ms = 18446744073709551615"),
        Some(3),
        "`deadline_ms` 18446744073709551615 is outside",
    );
    assert!(WallConfig::parse(&w("deadline_ms = 600000"), Path::new("w.toml")).is_ok());
    expect(&w("message_limit_bytes = 10"), Some(3), "`message_limit_bytes` 10 is outside");
    // Over what the decoder accepts.
    let over = format!("message_limit_bytes = {}", crate::codec::MAX_FRAME_LEN + 1);
    expect(&w(&over), Some(3), "no decoder accepts a message over 1 GiB");
    let max = format!("message_limit_bytes = {}", crate::codec::MAX_FRAME_LEN);
    assert!(WallConfig::parse(&w(&max), Path::new("w.toml")).is_ok());
    expect(&with("name = \"test\"", "name = \" \""), Some(2), "wall: `name` is empty");
}

#[test]
fn swap_margin_and_frame_rate_are_read_and_checked() {
    use crate::swap_timing::MarginSetting;
    use std::time::Duration;
    let w = |extra: &str| with("name = \"test\"\n", &format!("name = \"test\"\n{extra}\n"));
    let parse = |extra: &str| WallConfig::parse(&w(extra), Path::new("w.toml")).unwrap().wall;
    let d = parse("");
    assert_eq!((d.swap_margin(), d.frame_rate()), (Ok(MarginSetting::Auto), Ok(None)));
    assert_eq!(
        parse("swap_margin_ms = 1.5").swap_margin(),
        Ok(MarginSetting::Fixed(Duration::from_micros(1_500)))
    );
    assert_eq!(parse("swap_margin_ms = 2").swap_margin(), Ok(MarginSetting::Fixed(Duration::from_millis(2))));
    assert_eq!(parse("swap_margin_ms = \"off\"").swap_margin(), Ok(MarginSetting::Off));
    assert_eq!(parse("frame_rate = 30").frame_rate(), Ok(Some(30.0)));
    assert_eq!(parse("frame_rate = \"unpaced\"").frame_rate(), Ok(None));
    let t = parse("frame_rate = 60\nswap_margin_ms = 1").swap_timing();
    assert_eq!(t.period(), Some(Duration::from_secs_f64(1.0 / 60.0)));
    assert_eq!(t.margin(), Duration::from_millis(1));
    expect(
        &w("swap_margin_ms = 0"),
        Some(3),
        "wall: `swap_margin_ms`: swap margin 0 ms is not in (0, 1000] ms",
    );
    expect(&w("swap_margin_ms = \"soon\""), Some(3), "is not `auto`, `off` or a number of milliseconds");
    expect(&w("frame_rate = 0"), Some(3), "wall: `frame_rate`: frame rate 0 is not in (0, 1000]");
    expect(&w("frame_rate = \"fast\""), Some(3), "frame rate \"fast\" is not a number");
}

#[test]
fn the_message_limit_holds_every_nodes_snapshot() {
    let w = |extra: &str| with("name = \"test\"\n", &format!("name = \"test\"\n{extra}\n"));
    // Tiles of 100x80: 24,000 bytes of pixels each.
    let ps = expect(&w("message_limit_bytes = 20000"), Some(3), "too small for the snapshot of node 'n0'");
    assert!(ps.iter().any(|p| p.message.contains("node 'n1' (tiles b")), "{ps:#?}");
    let need = crate::messages::TileImage::snapshot_len_bound([("a", 100, 80)]);
    assert!(ps[0].message.contains(&format!("raise it to at least {need}")), "{ps:#?}");
    assert!(WallConfig::parse(&w(&format!("message_limit_bytes = {need}")), Path::new("w.toml")).is_ok());
    // Without the field, the default holds them; a tile too large for it is placed at its node.
    let big = with("width = 100\nheight = 80\n\n[[nodes]]", "width = 16384\nheight = 16384\n\n[[nodes]]");
    let ps =
        expect(&big, Some(30), "`message_limit_bytes` 67108864 is too small for the snapshot of node 'n1'");
    // And its GPU buffers (70 GB) are more than a node may take.
    assert_eq!(ps.len(), 2, "{ps:#?}");
    assert!(
        ps.iter().any(|p| p.message.contains("node 'n1': its 1 tile(s) hold 268435456 pixels")),
        "{ps:#?}"
    );
}

#[test]
fn the_camera_is_checked() {
    let cam = |body: &str| format!("[camera]\n{body}\n\n{GOOD}");
    expect(&cam("fov_y = 0"), Some(2), "camera: `fov_y` 0 is outside (0, 180) degrees");
    expect(&cam("fov_y = 180.0"), Some(2), "outside (0, 180)");
    expect(&cam("fov_y = nan"), Some(2), "outside (0, 180)");
    expect(&cam("eye = [1, 2, 3]\ntarget = [1, 2, 3]"), Some(2), "camera: `eye` and `target` coincide");
    // `up` is not given: the problem is placed at the [camera] table.
    expect(&cam("eye = [0, 0, 10]\ntarget = [0, 0, 0]"), Some(1), "`up` is parallel to the view direction");
    expect(&cam("up = [0, 0, 0]"), Some(2), "camera: `up` is the zero vector");
    expect(&cam("eye = [inf, 0, 0]"), Some(2), "camera: `eye` [inf, 0.0, 0.0] is not finite");
    expect(&cam("eye = [1, 2]"), Some(2), "invalid length 2");
    // Finite in f64 but infinite in the GPU's f32: refused, as the CLI and the console refuse it.
    expect(&cam("eye = [1e39, 0, 0]"), Some(2), "camera: eye [1e39, 0.0, 0.0] has a coordinate beyond +-1e7");
    expect(&cam("target = [0, 0, -2e7]"), Some(2), "camera: target");
}

/// Two small tiles a million pixels apart make a wall image of 10^12 pixels, 3 TB a snapshot:
/// refused at the far tile; a wide but full wall, and a small sparse one, pass.
#[test]
fn a_sparse_wall_image_is_refused() {
    let far = with("x = 110\ny = 0", "x = 1000000\ny = 1000000");
    let ps = expect(&far, Some(17), "the wall's image is 1000100x1000080 pixels (to tile 'b's far corner)");
    assert!(ps[0].message.contains("under 1/64"), "{}", ps[0].message);
    // Within the sparse limit's small images: a gap of 500 pixels is fine.
    WallConfig::parse(&with("x = 110", "x = 610"), Path::new("w.toml")).unwrap();
    // A wall of 16 x 8 full-HD tiles side by side is large and full.
    let mut wide = String::from("[wall]\nname = \"wide\"\n\n[volume]\nsource = \"procedural:sphere\"\n");
    for i in 0..128 {
        let (x, y) = (1920 * (i % 16), 1080 * (i / 16));
        wide += &format!("\n[[tiles]]\nname = \"t{i}\"\nx = {x}\ny = {y}\nwidth = 1920\nheight = 1080\n");
        wide += &format!(
            "\n[[nodes]]\nname = \"n{i}\"\naddress = \"10.0.0.{}:7400\"\ntiles = [\"t{i}\"]\n",
            i + 1
        );
    }
    WallConfig::parse(&wide, Path::new("w.toml")).unwrap();
}

/// A node whose tiles' GPU buffers exceed what a node may take is refused before its first frame.
#[test]
fn a_node_given_more_tiles_than_its_gpu_holds_is_refused() {
    let wall = |count: usize| {
        let mut text = String::from(
            "[wall]\nname = \"heavy\"\nmessage_limit_bytes = 1073741824\n\n[volume]\nsource = \"procedural:sphere\"\n",
        );
        for i in 0..count {
            let (x, y) = (2048 * (i % 8), 2048 * (i / 8));
            text += &format!("\n[[tiles]]\nname = \"t{i}\"\nx = {x}\ny = {y}\nwidth = 2048\nheight = 2048\n");
        }
        let names: Vec<String> = (0..count).map(|i| format!("\"t{i}\"")).collect();
        text + &format!(
            "\n[[nodes]]\nname = \"n0\"\naddress = \"127.0.0.1:7400\"\ntiles = [{}]\n",
            names.join(", ")
        )
    };
    let ps = problems(&wall(40));
    assert_eq!(ps.len(), 1, "{ps:#?}");
    assert!(ps[0].message.contains("node 'n0': its 40 tile(s) hold 167772160 pixels"), "{ps:#?}");
    // Eight of them (8.7 GB) do not fit either; seven (7.6 GB) do.
    assert!(problems(&wall(8)).iter().any(|p| p.message.contains("GPU buffers")));
    WallConfig::parse(&wall(7), Path::new("w.toml")).unwrap();
}

/// Walls of many tiles and nodes are checked in about n log n: 4,000 tiles in a row and 4,000
/// nodes take well under a second where pair-by-pair checks with line lookups took tens of
/// seconds; overlaps and shared addresses among them are still found.
#[test]
fn a_wall_of_many_tiles_is_checked_quickly_and_fully() {
    let n = 4000;
    let mut text = String::from("[wall]\nname = \"big\"\n\n[volume]\nsource = \"procedural:sphere\"\n");
    for i in 0..n {
        // Tile 3999 overlaps tile 3998; node 3999 shares node 0's address (as localhost).
        let x = if i == n - 1 { 64 * (i - 1) + 10 } else { 64 * i };
        text += &format!("\n[[tiles]]\nname = \"t{i}\"\nx = {x}\ny = 0\nwidth = 64\nheight = 48\n");
    }
    for i in 0..n {
        let address =
            if i == n - 1 { "localhost:7000".to_string() } else { format!("127.0.0.1:{}", 7000 + i) };
        text += &format!("\n[[nodes]]\nname = \"n{i}\"\naddress = \"{address}\"\ntiles = [\"t{i}\"]\n");
    }
    let start = std::time::Instant::now();
    let ps = problems(&text);
    let took = start.elapsed();
    assert_eq!(ps.len(), 2, "{ps:#?}");
    assert!(ps[0].message.contains("tile 't3999' overlaps tile 't3998'"), "{ps:#?}");
    assert!(
        ps[1].message.contains("node 'n3999' at localhost:7000 has the same address as node 'n0'"),
        "{ps:#?}"
    );
    assert!(took < std::time::Duration::from_secs(5), "{took:?} for {n} tiles and nodes");
}

#[test]
fn the_volume_is_checked() {
    let vol = |body: &str| with("source = \"procedural:sphere\"\n", &format!("{body}\n"));
    expect(
        &vol("source = \"procedural:sphere\"\niso = nan"),
        Some(6),
        "volume: `iso` NaN is not a finite number",
    );
    expect(
        &vol("source = \"procedural:teapot\""),
        Some(5),
        "unknown procedural volume 'teapot' (one of: sphere,",
    );
    expect(&vol("source = \"procedural:sphere:1\""), Some(5), "procedural size 1 is outside 2..=1024");
    expect(&vol("source = \"procedural:sphere:x\""), Some(5), "procedural size 'x' is not a whole number");
    expect(&vol("source = \"\""), Some(5), "volume: `source` is empty");
    expect(&vol("source = \"procedural:sphere\"\ndims = [2, 2, 2]"), Some(6), "`dims` is for raw files only");
    expect(&vol("source = \"head.raw\"\ndims = [2, 2, 2]"), Some(6), "needs both `dims` and `type`");
    expect(&vol("source = \"head.raw\"\ntype = \"int16\""), Some(6), "needs both `dims` and `type`");
    expect(
        &vol("source = \"head.raw\"\ndims = [2, 2, 2]\ntype = \"int12\""),
        Some(7),
        "unknown voxel type 'int12'",
    );
    expect(
        &vol("source = \"head.raw\"\ndims = [0, 2, 2]\ntype = \"int16\""),
        Some(6),
        "has a zero dimension",
    );
    expect(
        &vol("source = \"head.raw\"\ndims = [2, 2, 2]\ntype = \"u8\"\nspacing = [1, 0, 1]"),
        Some(8),
        "must be finite and > 0",
    );
    let raw =
        vol("source = \"head.raw\"\ndims = [2, 2, 2]\ntype = \"int16\"\nspacing = [1, 1, 2.5]\niso = 300");
    let c = WallConfig::parse(&raw, Path::new("/w/wall.toml")).unwrap();
    assert_eq!((c.volume.dims, c.volume.voxel_type.as_deref()), (Some([2, 2, 2]), Some("int16")));
    assert_eq!(c.volume_source(), "/w/head.raw");
    assert_eq!(c.cache_bytes(), DEFAULT_CACHE_BYTES);
    expect(
        &vol("source = \"steps/step_*.nrrd\"\ncache_bytes = 1099511627777"),
        Some(6),
        "volume: `cache_bytes` 1099511627777 is over the limit of 1099511627776 (1 TiB)",
    );
    expect(&vol("source = \"steps/step_*.nrrd\"\ncache_bytes = -1"), Some(6), "invalid value: integer `-1`");
    expect(
        &vol("source = \"procedural:sphere\"\ncache_bytes = 1000"),
        Some(6),
        "`cache_bytes` is for time steps, not a procedural volume",
    );
    let steps =
        WallConfig::parse(&vol("source = \"steps/step_*.nrrd\"\ncache_bytes = 0"), Path::new("/w/wall.toml"))
            .unwrap();
    assert_eq!((steps.cache_bytes(), steps.volume_source().as_str()), (0, "/w/steps/step_*.nrrd"));
}

#[test]
fn the_brick_cache_budgets_are_checked_and_only_for_screen_space() {
    let vol =
        |body: &str| with("source = \"procedural:sphere\"\n", &format!("source = \"ct.ome.zarr\"\n{body}\n"));
    let c =
        WallConfig::parse(&vol("gpu_budget_mb = 64\nupload_mb_per_frame = 2.5"), Path::new("/w/wall.toml"))
            .unwrap();
    let b = c.brick_budgets().unwrap();
    assert_eq!((b.gpu, b.host, b.upload_per_frame), (64 << 20, 128 << 20, 5 << 19));
    assert!(WallConfig::parse(GOOD, Path::new("w.toml")).unwrap().brick_budgets().is_none());
    expect(&vol("gpu_budget_mb = 0"), Some(6), "volume: `gpu_budget_mb` 0 is outside 1..=1048576 (MiB)");
    expect(&vol("gpu_budget_mb = 8\nhost_budget_mb = 0"), Some(7), "volume: `host_budget_mb` 0 is outside");
    expect(
        &vol("gpu_budget_mb = 8\nupload_mb_per_frame = -1.0"),
        Some(7),
        "volume: `upload_mb_per_frame` -1 is",
    );
    expect(
        &vol("host_budget_mb = 8"),
        Some(6),
        "volume: `host_budget_mb` is the brick cache's: it needs `gpu_budget_mb`",
    );
    let object = with("name = \"test\"", "name = \"test\"\nmode = \"object\"");
    let object = object.replacen(
        "source = \"procedural:sphere\"\n",
        "source = \"procedural:sphere\"\ngpu_budget_mb = 8\n",
        1,
    );
    expect(&object, Some(7), "`gpu_budget_mb` is for screen space (balanced or not)");
}

#[test]
fn render_values_are_checked() {
    let render = |body: &str| format!("[render]\n{body}\n\n{GOOD}");
    expect(&render("ao_radius = 0"), Some(2), "render: `ao_radius` 0 must be > 0 (or \"unbounded\")");
    expect(&render("ao_radius = -2.5"), Some(2), "must be > 0");
    expect(
        &render("ao_radius = \"huge\""),
        Some(2),
        "a radius in world units (a number > 0) or \"unbounded\"",
    );
    expect(&render("exposure = -1"), Some(2), "render: `exposure` -1 must be a finite number >= 0");
    expect(&render("ao_samples = 5000"), Some(2), "render: `ao_samples` 5000 is more than 1024");
    expect(&render("target_frame_ms = 0"), Some(2), "render: `target_frame_ms`: target frame time 0 ms");
    expect(&render("target_frame_ms = -3.5"), Some(2), "target frame time -3.5 ms");
    let c = WallConfig::parse(&render("target_frame_ms = 50"), Path::new("w.toml")).unwrap();
    assert_eq!(c.render.target_frame_ms, Some(50.0));
    expect(&render("shading = \"phong\""), Some(2), "unknown variant `phong`");
    expect(&render("ibl = \"sh\""), Some(2), "unknown variant `sh`");
    expect(&render("ao_method = \"theirs\""), Some(2), "unknown variant `theirs`");
    expect(&render("denoise = \"maybe\""), Some(2), "unknown variant `maybe`");
    expect(&render("denoise = \"on\""), Some(2), "`denoise` \"on\" filters the occlusion estimate");
    expect(&render("ao_samples = -1"), Some(2), "invalid value");
    expect(&render("env = \"\""), Some(2), "render: `env` is empty");
    expect(&format!("[certificates]\ndir = \"\"\n\n{GOOD}"), Some(2), "certificates: `dir` is empty");
    let c =
        WallConfig::parse(&render("ao_radius = \"unbounded\"\nexposure = 0"), Path::new("w.toml")).unwrap();
    assert_eq!((c.render.ao_radius, c.render.exposure), (AoRadius::Unbounded, Some(0.0)));
    let c = WallConfig::parse(&render("ao_radius = 3"), Path::new("w.toml")).unwrap();
    assert_eq!(c.render.ao_radius, AoRadius::World(3.0));
}

#[test]
fn every_problem_is_collected_in_file_order_and_printed_with_its_position() {
    let text = format!("[camera]\nfov_y = 200\n\n{GOOD}")
        .replace("name = \"test\"\n", "name = \"test\"\ncolour = 1\n")
        .replace("x = 110", "x = 50")
        .replace("127.0.0.1:7402", "127.0.0.1:99999");
    let e = WallConfig::parse(&text, Path::new("walls/bad.toml")).unwrap_err();
    let lines: Vec<usize> = e.problems.iter().map(|p| p.line.unwrap()).collect();
    assert_eq!(lines, [2, 6, 19, 33], "{e}");
    let shown = e.to_string();
    let shown: Vec<&str> = shown.lines().collect();
    assert_eq!(shown.len(), 4);
    assert_eq!(shown[0], "walls/bad.toml:2:9: camera: `fov_y` 200 is outside (0, 180) degrees");
    assert!(shown[1].starts_with("walls/bad.toml:6:1: unknown field `colour`"), "{}", shown[1]);
    assert!(shown[2].starts_with("walls/bad.toml:19:1: tile 'b' overlaps tile 'a'"), "{}", shown[2]);
    assert!(shown[3].starts_with("walls/bad.toml:33:11: node 'n1': address"), "{}", shown[3]);
    // What the file lacks: at its last line.
    let e = WallConfig::parse(
        "[wall]\nname = \"x\"\n[volume]\nsource = \"procedural:sphere\"\n",
        Path::new("w.toml"),
    )
    .unwrap_err();
    assert_eq!(e.to_string(), "w.toml:4:1: no tiles: a wall needs at least one [[tiles]] table\nw.toml:4:1: no nodes: a wall needs at least one [[nodes]] table");
    let e = WallConfig::load(Path::new("/nonexistent/wall.toml")).unwrap_err();
    assert!(e.to_string().starts_with("/nonexistent/wall.toml: cannot read the wall config:"), "{e}");
}

#[test]
fn line_and_column_count_characters() {
    let text = "a\nbé = 1\n";
    assert_eq!(line_column(text, 0), (1, 1));
    assert_eq!(line_column(text, 2), (2, 1));
    assert_eq!(line_column(text, 5), (2, 3), "after b and é (2 bytes)");
    assert_eq!(line_column(text, 999), (3, 1));
    // Line 2 is `name = "tést" = 1`: the stray `=` is character 15 (byte 16).
    let e = WallConfig::parse(&with("name = \"test\"", "name = \"tést\" = 1"), Path::new("w")).unwrap_err();
    assert_eq!((e.problems[0].line, e.problems[0].column), (Some(2), Some(15)), "{e}");
}

// ---- The model API. ----

#[test]
fn the_default_camera_frames_the_volume_over_the_whole_wall() {
    let c = example("local-2x2.toml");
    let (lo, hi) = (DVec3::ZERO, DVec3::new(255.0, 255.0, 117.0));
    let cam = c.camera_for(lo, hi);
    let framing = Camera::framing(lo, hi, 328, 248);
    assert!((cam.eye - framing.eye).length() < 1e-9 * framing.eye.length(), "{cam:?} vs {framing:?}");
    assert_eq!((cam.target, cam.up, cam.fov_y_deg), (framing.target, framing.up, framing.fov_y_deg));
    // Another fov, target and up: still every corner in view over the wall image.
    let mut c3 = example("local-3x1.toml");
    c3.camera.target = Some([100.0, 120.0, 50.0]);
    c3.camera.up = [0.0, 0.2, 1.0];
    let cam = c3.camera_for(lo, hi);
    cam.validate().unwrap();
    assert_eq!((cam.fov_y_deg, cam.target), (30.0, DVec3::new(100.0, 120.0, 50.0)));
    let (w, h) = c3.wall_size();
    let b = cam.basis();
    let tan_x = b.tan_half_fov * w as f64 / h as f64;
    for corner in crate::camera::corners(lo, hi) {
        let v = corner - cam.eye;
        let z = v.dot(b.forward);
        assert!(z > 0.0 && v.dot(b.right).abs() / z <= tan_x && v.dot(b.up).abs() / z <= b.tan_half_fov);
    }
    // An explicit eye is kept; the target defaults to the box centre.
    let mut c4 = c.clone();
    c4.camera.eye = Some([1.0, -500.0, 2.0]);
    let cam = c4.camera_for(lo, hi);
    assert_eq!((cam.eye, cam.target), (DVec3::new(1.0, -500.0, 2.0), 0.5 * hi));
    let sva = example("sva-4.toml");
    let cam = sva.camera_for(lo, hi);
    assert_eq!(
        (cam.eye, cam.target, cam.fov_y_deg),
        (DVec3::new(122.0, 664.0, 190.0), DVec3::new(122.0, 122.0, 80.0), 32.0)
    );
}

#[test]
fn a_camera_view_is_one_of_the_names_and_not_with_eye_or_another_up() {
    let camera = |body: &str| format!("[camera]\n{body}\n\n{GOOD}");
    let c = WallConfig::parse(&camera("view = \"superior\""), Path::new("w.toml")).unwrap();
    assert_eq!(c.camera.view, Some(ViewPreset::Superior));
    let ps = expect(&camera("view = \"front\""), Some(2), "unknown variant `front`");
    assert!(ps[0].message.contains("`anterior`") && ps[0].message.contains("`inferior`"), "{ps:?}");
    expect(&camera("eye = [1, 2, 3]\nview = \"left\""), Some(3), "`view` and `eye` both place the eye");
    expect(&camera("view = \"left\"\nup = [0, 1, 0]"), Some(3), "`view` sets the up direction");
    // The default up written out is no conflict.
    WallConfig::parse(&camera("view = \"left\"\nup = [0, 0, 1]"), Path::new("w.toml")).unwrap();
}

#[test]
fn the_default_camera_frames_the_object_box_from_the_view_or_the_orientation() {
    use crate::PatientDir::*;
    let mut c = example("local-2x2.toml");
    let volume = (DVec3::ZERO, DVec3::new(255.0, 255.0, 117.0));
    let fit = (DVec3::new(100.0, 80.0, 20.0), DVec3::new(150.0, 200.0, 90.0));
    let (w, h) = c.wall_size();
    // No view, no orientation: the three-quarter framing of the object's box.
    let cam = c.camera_framing(volume, fit, None);
    assert_eq!(cam, Camera::framing_view(fit, None, None, w, h));
    // An oriented scan opens anterior, its superior up, whatever the configured up.
    let ras = Orientation::new([Right, Anterior, Superior]).unwrap();
    let cam = c.camera_framing(volume, fit, Some(ras));
    assert_eq!(cam, Camera::framing_view(fit, Some(ViewPreset::Anterior), Some(ras), w, h));
    assert!((cam.eye - cam.target).normalize().y > 0.999, "RAS anterior is +y: {cam:?}");
    // A configured view; an explicit target is kept.
    c.camera.view = Some(ViewPreset::Left);
    c.camera.target = Some([120.0, 130.0, 50.0]);
    let cam = c.camera_framing(volume, fit, None);
    assert_eq!((cam.target, cam.up), (DVec3::new(120.0, 130.0, 50.0), DVec3::Z));
    assert!((cam.eye - cam.target).normalize().x > 0.999, "left is +x without orientation: {cam:?}");
}

#[test]
fn render_settings_take_the_render_defaults() {
    let c = WallConfig::parse(GOOD, Path::new("w.toml")).unwrap();
    assert_eq!(c.render_settings(2.0), RenderSettings::new(2.0));
    let text = format!("[render]\nshading = \"lambert\"\nao_samples = 16\nao_radius = 4\nao_method = \"seed\"\nao_sequence = \"r2\"\nibl = \"rays\"\nexposure = 0.8\ndenoise = \"on\"\n\n{GOOD}");
    let s = WallConfig::parse(&text, Path::new("w.toml")).unwrap().render_settings(1.0);
    assert_eq!(s.denoise, Denoise::On);
    assert_eq!((s.shading, s.ao.samples, s.ao.radius), (Shading::Lambert, 16, AoRadius::World(4.0)));
    assert_eq!(s.ao.sequence, AoSequence::R2);
    assert_eq!((s.ao.method, s.ao.ibl, s.exposure), (AoMethod::Seed, IblMethod::Rays, 0.8));
}

#[test]
fn auto_denoise_filters_a_governed_wall_with_ao_samples() {
    let settings = |body: &str| {
        WallConfig::parse(&format!("[render]\n{body}\n\n{GOOD}"), Path::new("w.toml"))
            .unwrap()
            .render_settings(1.0)
            .denoise
    };
    assert_eq!(WallConfig::parse(GOOD, Path::new("w.toml")).unwrap().render.denoise, DenoiseSetting::Auto);
    assert_eq!(settings("ao_samples = 4\ntarget_frame_ms = 50"), Denoise::On);
    assert_eq!(settings("ao_samples = 4"), Denoise::Off, "no governor");
    assert_eq!(settings("target_frame_ms = 50"), Denoise::Off, "no AO samples");
    assert_eq!(settings("ao_samples = 4\ntarget_frame_ms = 50\ndenoise = \"off\""), Denoise::Off);
    assert_eq!(settings("ao_samples = 4\ndenoise = \"on\""), Denoise::On);
    // auto with no samples is not a contradiction (it resolves to off); on is.
    assert!(
        WallConfig::parse(&format!("[render]\ndenoise = \"auto\"\n\n{GOOD}"), Path::new("w.toml")).is_ok()
    );
}

#[test]
fn paths_are_relative_to_the_config_file() {
    let text =
        format!("[certificates]\ndir = \"secrets/wall\"\n[render]\nenv = \"envs/studio.hdr\"\n\n{GOOD}");
    let c = WallConfig::parse(&text, Path::new("/etc/isowall/wall.toml")).unwrap();
    assert_eq!(c.cert_dir(), Path::new("/etc/isowall/secrets/wall"));
    assert_eq!(c.resolve("/abs/x"), Path::new("/abs/x"));
    assert_eq!(c.resolve("a/b"), Path::new("/etc/isowall/a/b"));
    assert_eq!(c.volume_source(), "procedural:sphere");
    assert_eq!(c.env_source(), "/etc/isowall/envs/studio.hdr");
    let c = WallConfig::parse(GOOD, Path::new("wall.toml")).unwrap();
    assert_eq!(c.cert_dir(), Path::new("keys"));
    assert_eq!(c.env_source(), "sky");
}

#[test]
fn the_summary_names_the_wall_and_every_node() {
    let s = example("local-2x2.toml").summary();
    assert!(s.starts_with("wall 'local-2x2': 328x248 px, 4 tiles on 4 nodes"), "{s}");
    assert!(s.contains("node3 (127.0.0.1:7404): t11 160x120+168+128"), "{s}");
}
