//! Load-balanced screen space at scale (`sim::balance`): on walls of 4 to 64 nodes of 1080p
//! tiles with a scan in the middle, orbiting, the model's split keeps the slowest node within
//! 15% of the mean and the frame within 15% of the ideal (all work over the nodes plus the
//! split's transfer), from frame 8 on (the first frames learn the costs).

use isowall_model::balance::STILL_SETTLE_FRAMES;
use isowall_model::sim::{run_balance, BalanceFrame, BalanceSpec};

fn mean(frames: &[BalanceFrame], f: impl Fn(&BalanceFrame) -> f64) -> f64 {
    frames.iter().map(f).sum::<f64>() / frames.len() as f64
}

#[test]
fn the_split_balances_walls_of_4_to_64_nodes_within_15_percent_while_orbiting() {
    for (cols, rows) in [(2, 2), (4, 2), (6, 4), (8, 8)] {
        let frames = run_balance(&BalanceSpec::new(cols, rows));
        let settled = &frames[8..];
        let unbalanced = mean(settled, |f| f.unbalanced);
        let balanced = mean(settled, |f| f.balanced);
        let over_ideal = mean(settled, |f| f.balanced_ms / f.ideal_ms);
        let speedup = mean(settled, |f| f.unbalanced_ms / f.balanced_ms);
        println!(
            "{cols}x{rows}: slowest/mean {unbalanced:.3} unbalanced, {balanced:.3} balanced; \
             frame / ideal {over_ideal:.3}; {speedup:.2}x faster; {:.0} kpixels moved a frame",
            mean(settled, |f| f.moved_pixels as f64) / 1e3
        );
        assert!(balanced <= 1.15, "{cols}x{rows}: balanced slowest/mean {balanced}");
        assert!(over_ideal <= 1.15, "{cols}x{rows}: frame over ideal {over_ideal}");
        if cols * rows > 4 {
            assert!(
                unbalanced > 1.3,
                "{cols}x{rows}: the scan in the middle should unbalance it ({unbalanced})"
            );
        }
    }
}

/// A still view learns its costs for a few frames, then keeps its split: its rectangles keep
/// their renderers (and the pixels' running sums).
#[test]
fn a_still_wall_keeps_its_split() {
    let mut spec = BalanceSpec::new(4, 2);
    spec.degrees = 0.0;
    let frames = run_balance(&spec);
    let settled = STILL_SETTLE_FRAMES as usize + 1;
    let moved: Vec<u64> = frames[settled..].iter().map(|f| f.moved_pixels).collect();
    assert!(moved.windows(2).all(|w| w[0] == w[1]), "{moved:?}");
    let balanced: Vec<String> =
        frames.iter().map(|f| format!("{:.3}/{:.3}", f.balanced, f.balanced_ms / f.ideal_ms)).collect();
    assert!(mean(&frames[8..], |f| f.balanced) <= 1.15, "{balanced:?}");
}

/// The same over costs measured by rendering every band of the walls people have
/// (`isowalld bench imbalance --scale 8 --frames 30 --degrees 1 --still 2 --bands 32`, on lavapipe:
/// tests/data/imbalance-bands-*.csv): sva-4, a 4x2 and a 6x4 wall of 1080p screens with the CT in
/// the middle, orbiting at 1 degree a frame; at 0.3 ns a fetch and 1 ns a pixel, 3-byte pixels
/// over 10 Gbit/s.
#[test]
fn the_split_balances_the_measured_walls_within_15_percent() {
    use isowall_model::sim::{measured_costs, run_balance_on, Transfer};
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    let transfer = Transfer { bytes_per_pixel: 3.0, bandwidth: 1.25e9, noise: 0.05, seed: 7 };
    for wall in ["sva-4", "bench-4x2-1080p", "bench-6x4-1080p"] {
        let path = dir.join(format!("imbalance-bands-{wall}.csv"));
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let (tiles, frames) = measured_costs(&text, 0.3, 1.0).unwrap();
        let orbit: Vec<_> =
            frames.into_iter().filter(|(l, _)| l.starts_with("orbit")).map(|(_, c)| c).collect();
        assert_eq!(orbit.len(), 30, "{wall}");
        let frames = run_balance_on(&tiles, &orbit, &transfer, false);
        let settled = &frames[8..];
        let unbalanced = mean(settled, |f| f.unbalanced);
        let balanced = mean(settled, |f| f.balanced);
        let over_ideal = mean(settled, |f| f.balanced_ms / f.ideal_ms);
        println!("{wall}: slowest/mean {unbalanced:.3} unbalanced, {balanced:.3} balanced; frame / ideal {over_ideal:.3}");
        assert!(unbalanced > 1.3, "{wall}: measured unbalanced {unbalanced}");
        assert!(balanced <= 1.15, "{wall}: balanced slowest/mean {balanced}");
        assert!(over_ideal <= 1.15, "{wall}: frame over ideal {over_ideal}");
    }
}
