//! `isowalld bench stream` as a user runs it, on a small store `convert` wrote: the first
//! picture, refinement, an orbit and the stop within a pool smaller than the view's bricks, the
//! closing line other tools read, and a budget too small for the coarsest level refused.

use isowall_e2e::{gpu_ok, run_in};

#[test]
fn bench_stream_converges_within_its_budgets_and_ends_with_its_line() {
    let dir = tempfile::tempdir().unwrap();
    let o =
        run_in(dir.path(), "isowalld", &["convert", "procedural:torus:64", "t.ome.zarr", "--chunk", "16"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let args = ["bench", "stream", "--volume", "t.ome.zarr", "--iso", "0", "--size", "48x36"];
    let extra = ["--gpu-budget-mb", "1", "--host-budget-mb", "1", "--frames", "3", "--degrees", "20"];
    let out = run_in(dir.path(), "isowalld", &[&args[..], &extra].concat());
    if !gpu_ok("isowalld bench stream", &out) {
        return;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    // The pool of 1 MiB holds fewer bricks of 17^3 than the torus's 64 at level 0: the still
    // views are finished by ray-guided rounds in passes.
    for line in stdout.lines().filter(|l| l.contains("level 0 everywhere the rays read")) {
        let passes: usize = line
            .split(" pass(es)")
            .next()
            .and_then(|l| l.rsplit(' ').next()?.parse().ok())
            .unwrap_or_else(|| panic!("no passes in {line}"));
        assert!(passes > 1 && line.contains("ray-guided rounds in"), "{line}");
    }
    assert_eq!(stdout.matches("level 0 everywhere the rays read").count(), 2, "{stdout}");
    let last = stdout.lines().last().unwrap_or_default();
    let numbers: Vec<f64> =
        last.split(|c: char| !(c.is_ascii_digit() || c == '.')).filter_map(|t| t.parse().ok()).collect();
    assert!(last.starts_with("stream: first ") && last.contains(" s after stop, peak gpu "), "{last}");
    let [first, converged, gpu, host] = numbers[..] else { panic!("four numbers in {last}") };
    assert!(first > 0.0 && converged >= 0.0 && host > 0.0, "{last}");
    assert!(gpu <= 1.048576 + 1e-6, "the pool stays within its 1 MiB: {last}");
    // The host cache stays within its budget.
    let cache = stdout.lines().find(|l| l.contains("host cache peak")).unwrap_or_default();
    let peak: f64 =
        cache.split("host cache peak ").nth(1).and_then(|r| r.split(' ').next()?.parse().ok()).unwrap();
    assert!(peak <= 1.0, "{cache}");

    let out = run_in(dir.path(), "isowalld", &[&args[..], &["--gpu-budget-mb", "0"]].concat());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--gpu-budget-mb 0 is outside 1..=1048576 (MiB)"), "{err}");
}
