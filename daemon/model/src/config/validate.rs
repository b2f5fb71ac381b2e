//! The rules a config must keep, table by table, each problem placed at its field.

use super::address::{parse_address, same_place_keys, AddressHost};
use super::diagnostics::*;
use super::*;
use std::collections::{HashMap, HashSet};

pub(crate) fn validate_wall(doc: &mut Doc<'_>, w: &WallSection) {
    let at = |f| [Seg::K("wall"), Seg::K(f)];
    if w.name.trim().is_empty() {
        doc.at(&at("name"), "wall: `name` is empty");
    }
    if !(1..=MAX_DEADLINE_MS).contains(&w.deadline_ms) {
        doc.at(
            &at("deadline_ms"),
            format!(
                "wall: `deadline_ms` {} is outside 1..={MAX_DEADLINE_MS} (a frame deadline of at most 10 minutes)",
                w.deadline_ms
            ),
        );
    }
    if !(MIN_MESSAGE_LIMIT_BYTES..=MAX_MESSAGE_LIMIT_BYTES).contains(&w.message_limit_bytes) {
        doc.at(
            &at("message_limit_bytes"),
            format!(
                "wall: `message_limit_bytes` {} is outside {MIN_MESSAGE_LIMIT_BYTES}..={MAX_MESSAGE_LIMIT_BYTES} \
                 (no decoder accepts a message over 1 GiB)",
                w.message_limit_bytes
            ),
        );
    }
    if let Err(e) = w.swap_margin() {
        doc.at(&at("swap_margin_ms"), format!("wall: `swap_margin_ms`: {e}"));
    }
    if let Err(e) = w.frame_rate() {
        doc.at(&at("frame_rate"), format!("wall: `frame_rate`: {e}"));
    }
    if w.present_priority > MAX_PRESENT_PRIORITY {
        doc.at(
            &at("present_priority"),
            format!(
                "wall: `present_priority` {} is outside 0..={MAX_PRESENT_PRIORITY} (0: normal scheduling; 1..=99: SCHED_FIFO)",
                w.present_priority
            ),
        );
    }
    if w.balance && w.mode == WallMode::Object {
        doc.at(
            &at("balance"),
            "wall: `balance` shares screen space's tiles between nodes; object space splits the volume \
             instead (set `mode = \"screen\"` or leave `balance` out)",
        );
    }
}

/// A node's snapshot (one message with all its tiles) must fit the wall's message limit.
pub(crate) fn validate_snapshot_size(
    doc: &mut Doc<'_>,
    w: &WallSection,
    tiles: &Parsed<TileConfig>,
    nodes: &Parsed<NodeConfig>,
) {
    if !(MIN_MESSAGE_LIMIT_BYTES..=MAX_MESSAGE_LIMIT_BYTES).contains(&w.message_limit_bytes) {
        return; // reported on its own
    }
    let by_name: HashMap<&str, &TileConfig> = tiles.items.iter().map(|(_, t)| (t.name.as_str(), t)).collect();
    for (i, n) in &nodes.items {
        let own: Vec<&TileConfig> =
            n.tiles.iter().filter_map(|name| by_name.get(name.as_str()).copied()).collect();
        let need = crate::messages::TileImage::snapshot_len_bound(
            own.iter().map(|t| (t.name.as_str(), t.width, t.height)),
        );
        if need > w.message_limit_bytes {
            let names: Vec<&str> = own.iter().map(|t| t.name.as_str()).collect();
            let message = format!(
                "wall: `message_limit_bytes` {} is too small for the snapshot of node '{}' (tiles {}: up to \
                 {need} bytes in one message); raise it to at least {need}",
                w.message_limit_bytes,
                n.name,
                names.join(", ")
            );
            let given = doc
                .value("wall")
                .and_then(|v| v.get_ref().as_table())
                .is_some_and(|t| t.iter().any(|(k, _)| k.get_ref() == "message_limit_bytes"));
            if given {
                doc.at(&[Seg::K("wall"), Seg::K("message_limit_bytes")], message);
            } else {
                doc.at(&[Seg::K("nodes"), Seg::I(*i), Seg::K("tiles")], message);
            }
        }
    }
}

pub(crate) fn validate_camera(doc: &mut Doc<'_>, c: &CameraConfig) {
    let at = |f| [Seg::K("camera"), Seg::K(f)];
    let mut finite = true;
    for (name, v) in [("eye", c.eye), ("target", c.target), ("up", Some(c.up))] {
        if let Some(v) = v {
            if !v.iter().all(|x| x.is_finite()) {
                doc.at(&at(name), format!("camera: `{name}` {v:?} is not finite"));
                finite = false;
            } else if let Err(e) = crate::camera::check_range(name, DVec3::from_array(v)) {
                doc.at(&at(name), format!("camera: {e}"));
                finite = false;
            }
        }
    }
    if c.view.is_some() && c.eye.is_some() {
        doc.at(&at("view"), "camera: `view` and `eye` both place the eye: give one");
    }
    if c.view.is_some() && c.up != CameraConfig::default().up {
        doc.at(
            &at("up"),
            "camera: `view` sets the up direction (superior, or anterior from above and below): drop `up`",
        );
    }
    if finite && DVec3::from_array(c.up).length() == 0.0 {
        doc.at(&at("up"), "camera: `up` is the zero vector");
        finite = false;
    }
    if !(c.fov_y > 0.0 && c.fov_y < 180.0) {
        doc.at(&at("fov_y"), format!("camera: `fov_y` {} is outside (0, 180) degrees", c.fov_y));
    }
    if let (true, Some(eye), Some(target)) = (finite, c.eye, c.target) {
        let cam = Camera {
            eye: DVec3::from_array(eye),
            target: DVec3::from_array(target),
            up: DVec3::from_array(c.up),
            fov_y_deg: DEFAULT_FOV_Y_DEG,
        };
        match cam.validate() {
            Err(crate::camera::CameraError::EyeIsTarget(_)) => {
                doc.at(&at("eye"), "camera: `eye` and `target` coincide")
            }
            Err(crate::camera::CameraError::UpParallel { .. }) => {
                doc.at(&at("up"), "camera: `up` is parallel to the view direction (target - eye)")
            }
            _ => {}
        }
    }
}

pub(crate) fn validate_volume(doc: &mut Doc<'_>, v: &VolumeConfig) {
    let at = |f| [Seg::K("volume"), Seg::K(f)];
    let procedural = v.source.strip_prefix("procedural:");
    if v.source.trim().is_empty() {
        doc.at(&at("source"), "volume: `source` is empty");
    }
    if let Some(rest) = procedural {
        let (name, size) = match rest.split_once(':') {
            Some((n, s)) => (n, Some(s)),
            None => (rest, None),
        };
        if let Err(e) = name.parse::<Procedural>() {
            doc.at(&at("source"), format!("volume: {e}"));
        }
        if let Some(s) = size {
            match s.parse::<usize>() {
                Ok(n) if isowall_volume::procedural::SIZES.contains(&n) => {}
                Ok(n) => {
                    let sizes = isowall_volume::procedural::SIZES;
                    doc.at(&at("source"), format!("volume: procedural size {n} is outside {sizes:?}"))
                }
                Err(_) => {
                    doc.at(&at("source"), format!("volume: procedural size '{s}' is not a whole number"))
                }
            }
        }
        for (field, given) in
            [("dims", v.dims.is_some()), ("type", v.voxel_type.is_some()), ("spacing", v.spacing.is_some())]
        {
            if given {
                doc.at(
                    &at(field),
                    format!("volume: `{field}` is for raw files only, not a procedural volume"),
                );
            }
        }
        if v.series.is_some() {
            doc.at(&at("series"), "volume: `series` is for DICOM folders only, not a procedural volume");
        }
    } else if v.dims.is_some() != v.voxel_type.is_some() || (v.spacing.is_some() && v.dims.is_none()) {
        let field = if v.dims.is_some() {
            "dims"
        } else if v.voxel_type.is_some() {
            "type"
        } else {
            "spacing"
        };
        doc.at(&at(field), "volume: a raw volume needs both `dims` and `type` (and optionally `spacing`)");
    }
    if let Some(iso) = v.iso {
        if !iso.is_finite() {
            doc.at(&at("iso"), format!("volume: `iso` {iso} is not a finite number"));
        }
    }
    if let Some(d) = v.dims {
        if d.contains(&0) {
            doc.at(&at("dims"), format!("volume: `dims` {d:?} has a zero dimension"));
        }
    }
    if let Some(t) = &v.voxel_type {
        if let Err(e) = t.parse::<VoxelType>() {
            doc.at(&at("type"), format!("volume: {e}"));
        }
    }
    if let Some(s) = v.spacing {
        if !s.iter().all(|x| x.is_finite() && *x > 0.0) {
            doc.at(&at("spacing"), format!("volume: `spacing` {s:?} must be finite and > 0"));
        }
    }
    if let Some(b) = v.cache_bytes {
        if b > MAX_CACHE_BYTES {
            doc.at(
                &at("cache_bytes"),
                format!("volume: `cache_bytes` {b} is over the limit of {MAX_CACHE_BYTES} (1 TiB)"),
            );
        }
        if v.source.starts_with("procedural:") {
            doc.at(&at("cache_bytes"), "volume: `cache_bytes` is for time steps, not a procedural volume");
        }
    }
    match v.gpu_budget_mb {
        Some(gpu) => {
            if let Err(e) = BrickBudgets::from_mb(gpu, v.host_budget_mb, v.upload_mb_per_frame) {
                doc.at(&at(e.field), format!("volume: `{}` {}", e.field, e.problem));
            }
        }
        None => {
            for (field, given) in [
                ("host_budget_mb", v.host_budget_mb.is_some()),
                ("upload_mb_per_frame", v.upload_mb_per_frame.is_some()),
            ] {
                if given {
                    doc.at(
                        &at(field),
                        format!("volume: `{field}` is the brick cache's: it needs `gpu_budget_mb`"),
                    );
                }
            }
        }
    }
    if let Some(b) = v.max_bytes {
        if !(4..=MAX_VOLUME_BYTES).contains(&b) {
            doc.at(
                &at("max_bytes"),
                format!("volume: `max_bytes` {b} is outside 4..={MAX_VOLUME_BYTES} (one voxel to 2^30 voxels as float32)"),
            );
        }
    }
}

pub(crate) fn validate_render(doc: &mut Doc<'_>, r: &RenderConfig) {
    for (field, message) in render_problems(r) {
        doc.at(&[Seg::K("render"), Seg::K(field)], message);
    }
}

/// The problems of a `[render]` table, each with the field it is about: the rules of the config
/// file, also applied to render settings changed while the wall runs (the operator console).
pub fn render_problems(r: &RenderConfig) -> Vec<(&'static str, String)> {
    let mut problems = Vec::new();
    if let AoRadius::World(radius) = r.ao_radius {
        if !(radius.is_finite() && radius > 0.0) {
            problems
                .push(("ao_radius", format!("render: `ao_radius` {radius} must be > 0 (or \"unbounded\")")));
        }
    }
    if r.ao_samples > crate::render_state::MAX_AO_SAMPLES {
        problems.push((
            "ao_samples",
            format!(
                "render: `ao_samples` {} is more than {} per frame (accumulate frames instead)",
                r.ao_samples,
                crate::render_state::MAX_AO_SAMPLES
            ),
        ));
    }
    if let Some(x) = r.exposure {
        if !(x.is_finite() && x >= 0.0) {
            problems.push(("exposure", format!("render: `exposure` {x} must be a finite number >= 0")));
        }
    }
    if let Some(t) = r.target_frame_ms {
        if let Err(e) = crate::governor::Governor::new(t, 1, 1, 1) {
            problems.push(("target_frame_ms", format!("render: `target_frame_ms`: {e}")));
        }
    }
    if r.env.trim().is_empty() {
        problems.push(("env", "render: `env` is empty (sky, FILE.hdr or DIR)".to_string()));
    }
    if r.denoise == DenoiseSetting::On && r.ao_samples == 0 {
        problems.push((
            "denoise",
            "render: `denoise` \"on\" filters the occlusion estimate: it needs `ao_samples` > 0".to_string(),
        ));
    }
    problems
}

pub(crate) fn validate_tiles(doc: &mut Doc<'_>, tiles: &Parsed<TileConfig>) {
    if !tiles.present || (tiles.items.is_empty() && !tiles.any_failed) {
        doc.at_missing(&[Seg::K("tiles")], "no tiles: a wall needs at least one [[tiles]] table");
        return;
    }
    let at = |i: usize, f: &'static str| [Seg::K("tiles"), Seg::I(i), Seg::K(f)];
    for (i, t) in &tiles.items {
        let i = *i;
        if let Some(p) = name_problem(&t.name) {
            doc.at(&at(i, "name"), format!("tile name {p}"));
        }
        for (field, v) in [("width", t.width), ("height", t.height)] {
            if !(1..=MAX_TILE_SIZE).contains(&v) {
                doc.at(
                    &at(i, field),
                    format!("tile '{}': `{field}` {v} is outside 1..={MAX_TILE_SIZE}", t.name),
                );
            }
        }
        if t.bezel.iter().any(|&b| b > MAX_TILE_SIZE) {
            doc.at(
                &at(i, "bezel"),
                format!("tile '{}': `bezel` {:?} has a width over {MAX_TILE_SIZE}", t.name, t.bezel),
            );
        }
        if t.bezel[0] > t.x {
            doc.at(
                &at(i, "bezel"),
                format!(
                    "tile '{}': its left bezel ({} px) reaches past the wall's left edge (x = {})",
                    t.name, t.bezel[0], t.x
                ),
            );
        }
        if t.bezel[2] > t.y {
            doc.at(
                &at(i, "bezel"),
                format!(
                    "tile '{}': its top bezel ({} px) reaches past the wall's top edge (y = {})",
                    t.name, t.bezel[2], t.y
                ),
            );
        }
        let (_, x1, _, y1) = t.outer();
        if x1 as u64 > MAX_WALL_EXTENT || y1 as u64 > MAX_WALL_EXTENT {
            doc.at(
                &at(i, "x"),
                format!(
                    "tile '{}': reaches pixel ({x1}, {y1}), beyond the largest wall image ({MAX_WALL_EXTENT} px a side)",
                    t.name
                ),
            );
        }
    }
    // Unique names (the first of each name kept).
    let mut first: HashMap<&str, usize> = HashMap::new();
    for (i, t) in &tiles.items {
        if let Some(&j) = first.get(t.name.as_str()) {
            let first =
                doc.line_of(&at(j, "name")).map(|l| format!(" (first at line {l})")).unwrap_or_default();
            doc.at(&at(*i, "name"), format!("duplicate tile name '{}'{first}", t.name));
        } else {
            first.insert(&t.name, *i);
        }
    }
    // No overlaps, bezels included: a sweep along x (tiles in order of their left edge, each
    // against the earlier ones still open at it), so a wall of many tiles side by side costs
    // about n log n, not n^2. Each overlapping pair is reported at the later tile in the file.
    let mut order: Vec<usize> = (0..tiles.items.len()).collect();
    order.sort_by_key(|&a| tiles.items[a].1.outer().0);
    let mut open: Vec<usize> = Vec::new();
    let mut pairs: Vec<(usize, usize)> = Vec::new();
    for &a in &order {
        let (ax0, _, ay0, ay1) = tiles.items[a].1.outer();
        open.retain(|&b| tiles.items[b].1.outer().1 > ax0);
        for &b in &open {
            let (_, _, by0, by1) = tiles.items[b].1.outer();
            if ay0 < by1 && by0 < ay1 {
                pairs.push((a.max(b), a.min(b)));
            }
        }
        open.push(a);
    }
    pairs.sort_unstable();
    for (a, b) in pairs {
        let ((i, t), (j, u)) = (&tiles.items[a], &tiles.items[b]);
        let (ax0, ax1, ay0, ay1) = t.outer();
        let (bx0, bx1, by0, by1) = u.outer();
        let other =
            doc.line_of(&[Seg::K("tiles"), Seg::I(*j)]).map(|l| format!(" (line {l})")).unwrap_or_default();
        doc.at(
            &[Seg::K("tiles"), Seg::I(*i)],
            format!(
                "tile '{}' overlaps tile '{}'{other}, bezels included: x {ax0}..{ax1}, y {ay0}..{ay1} \
                 against x {bx0}..{bx1}, y {by0}..{by1}",
                t.name, u.name
            ),
        );
    }
}

/// The wall image is bounded by its tiles: past [`SPARSE_WALL_PIXELS`], its tiles and bezels must
/// cover at least 1 / [`MAX_WALL_SPARSENESS`] of it (reported at the tile that reaches farthest).
pub(crate) fn validate_wall_image(doc: &mut Doc<'_>, tiles: &Parsed<TileConfig>) {
    let outer: Vec<(usize, (i64, i64, i64, i64))> =
        tiles.items.iter().map(|(i, t)| (*i, t.outer())).collect();
    let (Some(w), Some(h)) = (outer.iter().map(|o| o.1 .1).max(), outer.iter().map(|o| o.1 .3).max()) else {
        return;
    };
    let image = w.max(0) as u64 * h.max(0) as u64;
    let covered: u64 = outer.iter().map(|(_, (x0, x1, y0, y1))| ((x1 - x0) * (y1 - y0)).max(0) as u64).sum();
    if image <= SPARSE_WALL_PIXELS || covered.saturating_mul(MAX_WALL_SPARSENESS) >= image {
        return;
    }
    let far = outer.iter().max_by_key(|(_, (_, x1, _, y1))| x1 * y1).map_or(0, |o| o.0);
    let name = &tiles.items.iter().find(|(i, _)| *i == far).expect("a tile").1.name;
    doc.at(
        &[Seg::K("tiles"), Seg::I(far), Seg::K("x")],
        format!(
            "the wall's image is {w}x{h} pixels (to tile '{name}'s far corner) but its tiles and bezels cover \
             {:.4}% of it, under 1/{MAX_WALL_SPARSENESS}: every snapshot and thumbnail is of the whole image \
             ({} bytes as RGB); place the tiles side by side (a gap between screens is a bezel)",
            100.0 * covered as f64 / image as f64,
            image.saturating_mul(3)
        ),
    );
}

/// What a node's GPU holds for its tiles ([`GPU_BYTES_PER_TILE_PIXEL`] a pixel) must fit
/// [`MAX_NODE_GPU_BYTES`]: a node given more fails at its first frame.
pub(crate) fn validate_node_resources(
    doc: &mut Doc<'_>,
    nodes: &Parsed<NodeConfig>,
    tiles: &Parsed<TileConfig>,
) {
    let by_name: HashMap<&str, &TileConfig> = tiles.items.iter().map(|(_, t)| (t.name.as_str(), t)).collect();
    for (i, n) in &nodes.items {
        let own: Vec<&TileConfig> = n.tiles.iter().filter_map(|t| by_name.get(t.as_str()).copied()).collect();
        let pixels: u64 = own.iter().map(|t| t.width as u64 * t.height as u64).sum();
        let bytes = pixels.saturating_mul(GPU_BYTES_PER_TILE_PIXEL);
        if bytes > MAX_NODE_GPU_BYTES {
            doc.at(
                &[Seg::K("nodes"), Seg::I(*i), Seg::K("tiles")],
                format!(
                    "node '{}': its {} tile(s) hold {pixels} pixels, about {bytes} bytes of GPU buffers \
                     ({GPU_BYTES_PER_TILE_PIXEL} a pixel), over the {MAX_NODE_GPU_BYTES} a node may take: give \
                     some of its tiles to another node",
                    n.name,
                    own.len()
                ),
            );
        }
    }
}

pub(crate) fn validate_nodes(doc: &mut Doc<'_>, nodes: &Parsed<NodeConfig>, tiles: &Parsed<TileConfig>) {
    if !nodes.present || (nodes.items.is_empty() && !nodes.any_failed) {
        doc.at_missing(&[Seg::K("nodes")], "no nodes: a wall needs at least one [[nodes]] table");
        return;
    }
    let at = |i: usize, f: &'static str| [Seg::K("nodes"), Seg::I(i), Seg::K(f)];
    for (i, n) in &nodes.items {
        let i = *i;
        if let Some(p) = name_problem(&n.name) {
            doc.at(&at(i, "name"), format!("node name {p}"));
        } else if RESERVED_NODE_NAMES.iter().any(|r| r.eq_ignore_ascii_case(&n.name)) {
            doc.at(
                &at(i, "name"),
                format!("node name '{}' is reserved (its certificate files would clash)", n.name),
            );
        }
        if let Err(e) = check_address(&n.address) {
            doc.at(&at(i, "address"), format!("node '{}': address {e}", n.name));
        }
        if let Some(p) = n.present_priority.filter(|&p| p > MAX_PRESENT_PRIORITY) {
            doc.at(
                &at(i, "present_priority"),
                format!("node '{}': `present_priority` {p} is outside 0..={MAX_PRESENT_PRIORITY}", n.name),
            );
        }
        if let Some(c) = n.present_cpu.filter(|&c| c > MAX_PRESENT_CPU) {
            doc.at(
                &at(i, "present_cpu"),
                format!("node '{}': `present_cpu` {c} is outside 0..={MAX_PRESENT_CPU}", n.name),
            );
        }
    }
    // TLS compares names without regard to case: `NODE0` beside `node0` could pose as it. Names and
    // addresses are looked up in maps of the earlier nodes' (a wall of many nodes costs n, not n^2).
    let mut names: HashMap<String, usize> = HashMap::new();
    let mut places: HashMap<(AddressHost, u16), usize> = HashMap::new();
    for (a, (i, n)) in nodes.items.iter().enumerate() {
        if let Some(&b) = names.get(&n.name.to_ascii_lowercase()) {
            let (j, m) = &nodes.items[b];
            let first =
                doc.line_of(&at(*j, "name")).map(|l| format!(" (first at line {l})")).unwrap_or_default();
            let same = if m.name == n.name {
                String::new()
            } else {
                format!(" (the same as '{}' without regard to case)", m.name)
            };
            doc.at(&at(*i, "name"), format!("duplicate node name '{}'{same}{first}", n.name));
        } else {
            names.insert(n.name.to_ascii_lowercase(), a);
        }
        let Ok(place) = parse_address(&n.address) else { continue }; // reported above
        let earlier = same_place_keys(&place).into_iter().filter_map(|k| places.get(&k).copied()).min();
        if let Some(b) = earlier {
            let (j, m) = &nodes.items[b];
            let first = doc.line_of(&at(*j, "address")).map(|l| format!(" (line {l})")).unwrap_or_default();
            let message = if m.address == n.address {
                format!("node '{}' has the same address {} as node '{}'{first}", n.name, n.address, m.name)
            } else {
                format!(
                    "node '{}' at {} has the same address as node '{}' at {}{first} (localhost is 127.0.0.1 \
                     and ::1; names are compared without regard to case)",
                    n.name, n.address, m.name, m.address
                )
            };
            doc.at(&at(*i, "address"), message);
        }
        places.entry((place.host, place.port)).or_insert(a);
    }
    // Tile references: every listed tile exists; every tile is driven by exactly one node.
    let known: HashSet<&str> = tiles
        .items
        .iter()
        .map(|(_, t)| t.name.as_str())
        .chain(tiles.failed_names.iter().map(String::as_str))
        .collect();
    // Each tile's node: (node index in the file, the reference's index in its list).
    let mut driver: HashMap<&str, (usize, usize)> = HashMap::new();
    for (i, n) in &nodes.items {
        let mut listed: HashSet<&str> = HashSet::new();
        for (k, tile) in n.tiles.iter().enumerate() {
            let path = [Seg::K("nodes"), Seg::I(*i), Seg::K("tiles"), Seg::I(k)];
            if !listed.insert(tile.as_str()) {
                doc.at(&path, format!("node '{}' lists tile '{tile}' twice", n.name));
                continue;
            }
            if !known.contains(tile.as_str()) {
                let names: Vec<&str> = tiles.items.iter().map(|(_, t)| t.name.as_str()).collect();
                doc.at(
                    &path,
                    format!("node '{}': no tile named '{tile}' (tiles: {})", n.name, names.join(", ")),
                );
                continue;
            }
            if let Some(&(j, kj)) = driver.get(tile.as_str()) {
                let other = &nodes.items.iter().find(|(x, _)| *x == j).expect("a listed node").1.name;
                let line =
                    doc.line_of(&[Seg::K("nodes"), Seg::I(j), Seg::K("tiles"), Seg::I(kj)]).unwrap_or(0);
                doc.at(
                    &path,
                    format!(
                        "tile '{tile}' is driven by two nodes: '{}' and '{other}' (line {line}); a tile has one node",
                        n.name
                    ),
                );
                continue;
            }
            driver.insert(tile, (*i, k));
        }
    }
    if !nodes.any_failed {
        for (i, t) in &tiles.items {
            if !driver.contains_key(t.name.as_str()) {
                doc.at(
                    &[Seg::K("tiles"), Seg::I(*i), Seg::K("name")],
                    format!("tile '{}' is driven by no node (list it in one node's `tiles`)", t.name),
                );
            }
        }
    }
}
