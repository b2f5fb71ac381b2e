//! The report's table: `isowall bench CONFIG --table` on a small
//! local 2-node wall measures every cell (fps and the slowest node's render time), a row per AO
//! sample count and a column per node count, prints "—" where RTPara published no figure (here:
//! not the engine volume), in screen and in object space, and lists per-node render times.

use isowall_e2e::{free_udp_ports, gpu_ok, run_in, wall_config_2x1};

#[test]
fn bench_table_measures_every_cell_and_cites_only_published_2008_figures() {
    let dir = tempfile::tempdir().unwrap();
    let config = wall_config_2x1(dir.path(), "bench", &free_udp_ports(2), 16, 8, 0, 0);
    let out = run_in(dir.path(), "isowall", &["keygen", "--config", config.to_str().unwrap()]);
    assert!(out.status.success(), "keygen: {}", String::from_utf8_lossy(&out.stderr));
    let out = run_in(
        dir.path(),
        "isowall",
        &[
            "bench",
            config.to_str().unwrap(),
            "--table",
            "--samples",
            "1,2",
            "--frames",
            "1",
            "--size",
            "24x8",
        ],
    );
    if !gpu_ok("isowall bench --table", &out) {
        return;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let rows: Vec<&str> = text.lines().filter(|l| l.starts_with("| ")).collect();
    // Two tables (screen, object), each a header and two rows.
    assert_eq!(rows.len(), 6, "{text}");
    assert_eq!(rows[0], "| AO samples | 1 node: ours | 2008 | 2 nodes: ours | 2008 |");
    assert_eq!(rows[3], rows[0], "the object-space table has the same columns:\n{text}");
    for (row, k) in rows[1..3].iter().chain(&rows[4..6]).zip(["1", "2", "1", "2"]) {
        let cells: Vec<&str> = row.trim_matches('|').split('|').map(str::trim).collect();
        assert_eq!(cells[0], k, "{row}");
        for ours in [cells[1], cells[3]] {
            let fps: f64 = ours.split_whitespace().next().unwrap().parse().unwrap_or(0.0);
            assert!(fps > 0.0 && ours.contains(" fps (render "), "not a measurement: {ours}");
        }
        assert_eq!((cells[2], cells[4]), ("—", "—"), "2008 figures are for the engine only: {row}");
    }
    assert!(text.contains("1 samples, 2 node(s): node0 ") && text.contains(", node1 "), "{text}");
}
