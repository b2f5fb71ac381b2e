//! What the benchmarks share: medians, error statistics, the scene and sample lists of their flags,
//! their CSV files and the comparison with a baseline file. It imports nothing of its sibling
//! modules.

use anyhow::{bail, Context, Result};
use std::path::Path;

/// The variant that measures the renderer as it was before its performance work: in `bench suite`
/// the options [`isowall_render::gpu::PerfOptions::PLAIN`], in `bench frame` the path that read
/// every AOV back and composed on the CPU.
pub const PLAIN: &str = "plain";
/// [`PLAIN`]'s first name, still accepted (documented, and in saved baselines).
pub const PLAIN_ALIAS: &str = "before";

/// Whether `name` names the [`PLAIN`] variant.
pub fn is_plain(name: &str) -> bool {
    name == PLAIN || name == PLAIN_ALIAS
}

/// CPU milliseconds this process has used, user and system (`/proc/self/stat`; Linux's clock
/// ticks are 1/100 s to user space), or `None` where that file cannot be read. On a CPU driver
/// (lavapipe) the kernels run on this process's threads, so a frame's CPU time is its cost
/// whatever else the machine runs, where its wall time is not.
pub fn process_cpu_ms() -> Option<f64> {
    cpu_ms_of(&std::fs::read_to_string("/proc/self/stat").ok()?)
}

/// utime + stime of a `/proc/PID/stat` line, in ms. The command name (2nd field, in parentheses)
/// may hold spaces and parentheses, so the fields are counted from its last ')': state is the 3rd
/// field, utime the 14th and stime the 15th.
fn cpu_ms_of(stat: &str) -> Option<f64> {
    let rest = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| fields.get(i - 3)?.parse::<u64>().ok();
    Some((ticks(14)? + ticks(15)?) as f64 * 10.0)
}

/// Writes a bench's rows to `path`: its `comment` line, the `header` line, then one line a row
/// (what [`csv_records`] reads back).
pub fn save_csv(path: &Path, comment: &str, header: &str, rows: impl Iterator<Item = String>) -> Result<()> {
    let mut text = format!("{comment}\n{header}\n");
    for r in rows {
        text.push_str(&r);
        text.push('\n');
    }
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
    println!("# saved {}", path.display());
    Ok(())
}

/// Prints the heading of a comparison with the baseline file `path`: what the ratios mean, then
/// the `columns` line.
pub fn print_baseline_heading(path: &Path, columns: &str) {
    println!(
        "# against the baseline {} (ratios new / baseline; below 1 is faster, fewer, smaller)",
        path.display()
    );
    println!("{columns}");
}

/// The baseline row a row is held against: the one with the row's `key`, else the one with
/// `fallback` (the same measurement of a variant every baseline has, for a variant or path the
/// baseline's build did not have); `None` where neither is there.
pub fn baseline_row<'a, R, K: PartialEq>(
    baseline: &'a [R],
    key_of: impl Fn(&R) -> K,
    key: &K,
    fallback: &K,
) -> Option<&'a R> {
    baseline.iter().find(|b| key_of(b) == *key).or_else(|| baseline.iter().find(|b| key_of(b) == *fallback))
}

/// The records of a CSV file a bench wrote: its `header` line first (blank lines and `#` comments
/// anywhere are passed over), then `fields` comma-separated fields a line, each with its line
/// number (from 1); errors name the file and the line.
pub fn csv_records<'a>(
    text: &'a str,
    file: &str,
    header: &str,
    fields: usize,
) -> Result<Vec<(usize, Vec<&'a str>)>> {
    let mut records = Vec::new();
    let mut header_seen = false;
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if !header_seen {
            if line != header {
                bail!("{file}:{}: expected the header '{header}'", i + 1);
            }
            header_seen = true;
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != fields {
            bail!("{file}:{}: {} fields, expected {fields}", i + 1, f.len());
        }
        records.push((i + 1, f));
    }
    if !header_seen {
        bail!("{file}: no header line '{header}'");
    }
    Ok(records)
}

pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Splits `VOLUME[@ISO]`.
pub fn scene_spec(scene: &str) -> Result<(&str, Option<f64>)> {
    Ok(match scene.rsplit_once('@') {
        Some((s, i)) => {
            (s, Some(i.parse::<f64>().map_err(|_| anyhow::anyhow!("{scene}: iso '{i}' is not a number"))?))
        }
        None => (scene, None),
    })
}

/// The short name of a scene: the procedural volume's name, or the file's stem.
pub fn scene_key(spec: &str) -> String {
    if let Some(rest) = spec.strip_prefix("procedural:") {
        return rest.split(':').next().unwrap_or(rest).to_string();
    }
    let name = std::path::Path::new(spec).file_name().and_then(|n| n.to_str()).unwrap_or(spec);
    [".nii.gz", ".nrrd", ".nhdr", ".mhd", ".mha", ".nii", ".raw"]
        .iter()
        .find_map(|ext| name.strip_suffix(ext))
        .unwrap_or(name)
        .to_string()
}

/// The checkout this binary was built from: the benchmarks' default scenes name the shared data
/// beside it (`../shared/data/...`), relative to it.
pub fn checkout_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap_or(Path::new("."))
}

/// Where a scene's volume is read from ([`scene_file_in`] from the working folder and
/// [`checkout_dir`]).
pub fn scene_file(spec: &str) -> std::result::Result<String, String> {
    let cwd = std::env::current_dir().unwrap_or_else(|_| ".".into());
    scene_file_in(spec, &cwd, checkout_dir())
}

/// Where the volume of scene `spec` is read from: a procedural volume or a path that exists as
/// given (relative to `cwd`) as it is; else a relative path that exists relative to `checkout`
/// (so the default scenes are found from any folder, not only the checkout's root); else why not,
/// naming the places looked in.
pub fn scene_file_in(spec: &str, cwd: &Path, checkout: &Path) -> std::result::Result<String, String> {
    let path = Path::new(spec);
    if spec.starts_with("procedural:") || cwd.join(path).exists() {
        return Ok(spec.to_string());
    }
    if path.is_relative() {
        let beside = checkout.join(path);
        if beside.exists() {
            return Ok(beside.to_string_lossy().into_owned());
        }
        return Err(format!(
            "{spec} is neither in {} nor in the checkout {} (the shared data sits beside the checkout)",
            cwd.display(),
            checkout.display()
        ));
    }
    Err(format!("{spec} does not exist"))
}

/// RMSE and 99th percentile of |a - b| over pixels where `hit` holds.
pub fn error_stats(a: &[f32], b: &[f32], hit: &[bool]) -> (f64, f64) {
    let mut d: Vec<f64> =
        (0..a.len()).filter(|&i| hit[i]).map(|i| (a[i] as f64 - b[i] as f64).abs()).collect();
    if d.is_empty() {
        return (0.0, 0.0);
    }
    let rmse = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
    d.sort_by(f64::total_cmp);
    (rmse, d[(d.len() - 1) * 99 / 100])
}

/// A `--samples` list: AO sample counts, comma-separated, each in `render --ao-samples`'s range.
pub fn sample_list(list: &str) -> Result<Vec<u32>> {
    isowall_model::cli_args::sample_list(list).map_err(|e| anyhow::anyhow!("--samples: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scene_file_is_found_from_the_working_folder_else_the_checkout() {
        let root = std::env::temp_dir().join(format!("isowall-scene-file-{}", std::process::id()));
        let (checkout, elsewhere) = (root.join("repo"), root.join("away/elsewhere"));
        std::fs::create_dir_all(root.join("shared/data")).unwrap();
        std::fs::create_dir_all(&checkout).unwrap();
        std::fs::create_dir_all(elsewhere.join("mine")).unwrap();
        std::fs::write(root.join("shared/data/ct.nrrd"), b"").unwrap();
        std::fs::write(elsewhere.join("mine/v.nrrd"), b"").unwrap();
        let spec = "../shared/data/ct.nrrd";
        // From the checkout's root, as given; from elsewhere, beside the checkout.
        assert_eq!(scene_file_in(spec, &checkout, &checkout).unwrap(), spec);
        assert_eq!(
            scene_file_in(spec, &elsewhere, &checkout).unwrap(),
            checkout.join(spec).to_string_lossy()
        );
        // The working folder's own file wins; procedural volumes are as they are.
        assert_eq!(scene_file_in("mine/v.nrrd", &elsewhere, &checkout).unwrap(), "mine/v.nrrd");
        assert_eq!(scene_file_in("procedural:engine", &elsewhere, &checkout).unwrap(), "procedural:engine");
        let e = scene_file_in("../shared/data/mri.nrrd", &elsewhere, &checkout).unwrap_err();
        assert!(
            e.starts_with("../shared/data/mri.nrrd is neither in ")
                && e.contains(&*checkout.to_string_lossy()),
            "{e}"
        );
        std::fs::remove_dir_all(&root).unwrap();
        // This build's checkout holds its own sources.
        assert!(checkout_dir().join("daemon/src/bench/stats.rs").is_file());
    }

    #[test]
    fn cpu_time_is_read_past_an_odd_command_name() {
        let line = "4242 (isowalld (bench) x) R 1 2 3 4 5 6 7 8 9 10 123 45 0 0 20 0 9 0 100 2000 30";
        assert_eq!(super::cpu_ms_of(line), Some(1680.0));
        assert_eq!(super::cpu_ms_of("4242 (short) R 1 2"), None);
        assert!(super::process_cpu_ms().is_some(), "/proc/self/stat");
    }
}
