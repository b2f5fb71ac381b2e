//! `isowalld bench frame` as a user runs it: a real process measuring a small tile's frame by the
//! node's own path and by the earlier one, its counts (allocations, bytes read back and uploaded)
//! being exact whatever the machine; then `--baseline` against its own `--save`.

use isowall_e2e::{gpu_ok, run_in};

const HEADER: &str = "scene,size,samples,path,variant,ms_per_frame,cpu_ms,gpu_ms_isosurface,gpu_ms_ao,gpu_ms_compose,gpu_ms_frame,allocations,bytes_read_back,bytes_uploaded";

#[test]
fn frame_bench_counts_what_a_frame_moves_on_every_path_and_compares_with_a_baseline() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("frame.csv");
    let (w, h) = (64.0, 48.0);
    let args = [
        "bench",
        "frame",
        "--scenes",
        "procedural:sphere-over-plane:16",
        "--size",
        "64x48",
        "--samples",
        "4",
        "--repeats",
        "2",
        "--paths",
        "screen,object,moving",
        "--variants",
        "default,before",
    ];
    let mut first = args.to_vec();
    first.extend(["--save", csv.to_str().unwrap()]);
    let out = run_in(dir.path(), "isowalld", &first);
    if !gpu_ok("isowalld bench frame", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let timestamps = stdout.contains("from timestamp queries");
    let saved = std::fs::read_to_string(&csv).expect("--save wrote the CSV");
    let mut lines = saved.lines().filter(|l| !l.starts_with('#'));
    assert_eq!(lines.next(), Some(HEADER), "{saved}");
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let row = |path: &str, variant: &str| -> Vec<f64> {
        let r = rows
            .iter()
            .find(|r| r[3] == path && r[4] == variant)
            .unwrap_or_else(|| panic!("no {path}/{variant} row:\n{saved}"));
        r[5..].iter().map(|v| v.parse::<f64>().unwrap_or(f64::NAN)).collect()
    };
    // Columns from ms_per_frame on: 0 ms, 1 cpu, 2 iso, 3 ao, 4 compose, 5 frame, 6 alloc, 7 read, 8 up.
    let (screen, object, moving) =
        (row("screen", "default"), row("object", "default"), row("moving", "default"));
    for (name, r) in [("screen", &screen), ("object", &object), ("moving", &moving)] {
        assert_eq!(r[6], 0.0, "{name}: the tile's resources are made once, no allocation per frame");
        assert!(r[8] < 1024.0, "{name}: only the frame's parameters are uploaded ({} bytes)", r[8]);
        assert!(r[0] > 0.0, "{name}: a frame takes time");
    }
    // Screen space reads back only the frame's counters (and timestamps); object space also the
    // share, 4 bytes of colour and 4 of depth per pixel.
    assert!(screen[7] > 0.0 && screen[7] < 256.0, "{saved}");
    assert_eq!(moving[7], screen[7], "{saved}");
    assert_eq!(object[7] - screen[7], 8.0 * w * h, "{saved}");
    // The snapshot reads the tile's image once: 4 bytes a pixel.
    assert_eq!(row("snapshot", "default")[7], 4.0 * w * h, "{saved}");
    // The earlier path: every shading AOV read back (64 bytes a pixel, through `render`, beside the
    // frame's counters and timestamps) and its buffers made every frame.
    for path in ["screen", "object", "moving"] {
        let b = row(path, "before");
        assert!(b[7] >= 64.0 * w * h && b[7] < 64.0 * w * h + 256.0, "{path}/before:\n{saved}");
        assert!(b[6] >= 10.0, "{path}/before: its buffers made every frame:\n{saved}");
    }
    // Steady accumulating frames do not run the isosurface kernel; moving ones do.
    if timestamps {
        assert!(screen[2].is_nan(), "{saved}");
        assert!(moving[2] >= 0.0, "{saved}");
    }

    let mut second = args.to_vec();
    second.extend(["--baseline", csv.to_str().unwrap()]);
    let out = run_in(dir.path(), "isowalld", &second);
    assert!(gpu_ok("isowalld bench frame --baseline", &out));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let ratios: Vec<&str> = stdout
        .lines()
        .skip_while(|l| !l.starts_with("scene,size,samples,path,variant,baseline_variant"))
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .collect();
    assert_eq!(ratios.len(), rows.len(), "a ratio line per row:\n{stdout}");
    // The counts are exact, so against itself each count's ratio is 1.
    let moving_ratio = ratios.iter().find(|l| l.contains(",moving,default,default,")).expect(&stdout);
    assert!(moving_ratio.ends_with(",1.000,1.000,1.000"), "{moving_ratio}");
}
