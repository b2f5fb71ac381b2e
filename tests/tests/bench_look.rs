//! `isowalld bench look` as a user runs it, at a small size: the default look darkens creases by
//! at least the goal against open surface at the same N.L, and the look before did not.

use isowall_e2e::{gpu_ok, run_in};

#[test]
fn the_default_look_darkens_occluded_surface_and_the_earlier_one_did_not() {
    let dir = tempfile::tempdir().unwrap();
    let pictures = dir.path().join("look");
    let out = run_in(
        dir.path(),
        "isowalld",
        &[
            "bench",
            "look",
            "--scenes",
            "procedural:engine:128,procedural:sphere:32",
            "--size",
            "128x128",
            "--samples",
            "16",
            "--frames",
            "4",
            "--before",
            "--out",
            pictures.to_str().unwrap(),
        ],
    );
    if !gpu_ok("isowalld bench look", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let rows: Vec<Vec<&str>> =
        stdout.lines().filter(|l| l.starts_with("engine,")).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 4, "none and bent, default and before:\n{stdout}");
    let darkness = |look: &str, ibl: &str| -> f64 {
        let r = rows.iter().find(|r| r[1] == look && r[2] == ibl).unwrap_or_else(|| panic!("{look} {ibl}"));
        r[7].parse().unwrap_or_else(|_| panic!("darkness of {r:?}"))
    };
    for ibl in ["none", "bent"] {
        assert!(darkness("default", ibl) >= 0.3, "{ibl}:\n{stdout}");
        assert!(darkness("before", ibl) < darkness("default", ibl), "{ibl}:\n{stdout}");
    }
    assert!(darkness("before", "none") < 0.3, "the earlier look is the one that failed:\n{stdout}");
    // A sphere has nothing occluded: said, and left out of the worst case.
    let last = stdout.lines().last().unwrap_or_default();
    assert!(last.starts_with("look: darkness ") && last.contains("meets the goal"), "{stdout}");
    assert!(last.contains("no pixels to compare in sphere (none), sphere (bent)"), "{stdout}");
    for name in ["look-engine-none.png", "look-engine-bent-before.png", "look-sphere-none.png"] {
        let bytes = std::fs::read(pictures.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(bytes.starts_with(b"\x89PNG"), "{name}");
    }
}
