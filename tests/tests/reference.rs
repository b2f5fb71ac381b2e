//! docs/reference.md cannot drift from the binaries: every command of `isowalld` and `isowall` has
//! its section, each section lists exactly the flags and arguments its `--help` shows, with the
//! default `--help` states; and the config's tables list exactly the keys the config's own types
//! accept (read from `isowall check-config`'s "expected one of" for an unknown key in each table).

use isowall_e2e::{repo_root, run_in};
use std::collections::{BTreeMap, BTreeSet};

/// A row of the reference: its first cell's name (`--flag`, `<ARG>` or a key) and second cell.
type Rows = BTreeMap<String, String>;

fn reference() -> String {
    let path = repo_root().join("docs/reference.md");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The reference's sections by heading text inside backticks (`### \`isowalld render\``).
fn sections(doc: &str) -> BTreeMap<String, Rows> {
    let mut out = BTreeMap::new();
    let mut current: Option<(String, Rows)> = None;
    for line in doc.lines() {
        if line.starts_with('#') {
            if let Some((h, rows)) = current.take() {
                out.insert(h, rows);
            }
            if let Some(h) = line.trim_start_matches('#').trim().strip_prefix('`') {
                if let Some(end) = h.find('`') {
                    current = Some((h[..end].to_string(), Rows::new()));
                }
            }
            continue;
        }
        let Some((_, rows)) = current.as_mut() else { continue };
        let Some(rest) = line.strip_prefix("| `") else { continue };
        let cells: Vec<&str> = split_cells(rest);
        let name = cells[0].trim_end_matches('`');
        let name = name.split([' ', '=']).next().unwrap_or(name).to_string();
        let default = cells.get(1).map(|c| c.trim().replace("\\|", "|")).unwrap_or_default();
        assert!(rows.insert(name.clone(), default).is_none(), "{name} listed twice: {line}");
    }
    if let Some((h, rows)) = current {
        out.insert(h, rows);
    }
    out
}

/// A table row's cells (after the leading `| `), `\|` kept inside a cell.
fn split_cells(row: &str) -> Vec<&str> {
    let mut cells = Vec::new();
    let (mut start, bytes) = (0, row.as_bytes());
    for i in 0..bytes.len() {
        if bytes[i] == b'|' && (i == 0 || bytes[i - 1] != b'\\') {
            cells.push(row[start..i].trim());
            start = i + 1;
        }
    }
    cells
}

fn help(args: &[&str]) -> String {
    let dir = tempfile::tempdir().unwrap();
    let mut with_help: Vec<&str> = args[1..].to_vec();
    with_help.push("--help");
    let out = run_in(dir.path(), args[0], &with_help);
    assert!(out.status.success(), "{args:?} --help: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The subcommands a `--help` lists (without `help`).
fn subcommands(help: &str) -> Vec<String> {
    let mut subs = Vec::new();
    let mut inside = false;
    for line in help.lines() {
        if line.starts_with("Commands:") {
            inside = true;
        } else if inside {
            match line.strip_prefix("  ").and_then(|l| l.split_whitespace().next()) {
                Some(name) if !line.starts_with("   ") && name != "help" => subs.push(name.to_string()),
                Some(_) if !line.starts_with("   ") => {}
                _ if line.trim().is_empty() => inside = false,
                _ => {}
            }
        }
    }
    subs
}

/// The flags and arguments of a `--help`, each with its `[default: X]` where it has one.
fn options(help: &str) -> Rows {
    let mut rows = Rows::new();
    let mut current: Option<String> = None;
    let mut listing = false;
    for line in help.lines() {
        if line.starts_with("Options:") || line.starts_with("Arguments:") {
            listing = true;
            continue;
        }
        if !listing {
            continue;
        }
        if !line.starts_with(' ') && !line.trim().is_empty() {
            listing = false;
            continue;
        }
        let t = line.trim_start();
        let indent = line.len() - t.len();
        let name = if indent <= 6 {
            let t = t.strip_prefix("-h, ").or_else(|| t.strip_prefix("-V, ")).unwrap_or(t);
            let t =
                if t.len() > 4 && t.as_bytes()[0] == b'-' && t.as_bytes()[2] == b',' { &t[4..] } else { t };
            if t.starts_with("--") || t.starts_with('<') || t.starts_with('[') {
                t.split([' ', '=']).next().map(|n| n.trim_matches(['[', ']']).to_string())
            } else {
                None
            }
        } else {
            None
        };
        if let Some(n) = name {
            let n = if n.starts_with('<') || n.starts_with("--") { n } else { format!("<{n}>") };
            rows.insert(n.clone(), String::new());
            current = Some(n);
        }
        if let (Some(c), Some(start)) = (&current, line.find("[default: ")) {
            let rest = &line[start + "[default: ".len()..];
            let end = rest.find(']').unwrap_or(rest.len());
            rows.insert(c.clone(), rest[..end].to_string());
        }
    }
    rows.remove("--help");
    rows.remove("--version");
    rows
}

#[test]
fn every_command_and_flag_is_in_the_reference_with_its_default() {
    let doc = sections(&reference());
    let mut commands = Vec::new();
    for bin in ["isowalld", "isowall"] {
        for sub in subcommands(&help(&[bin])) {
            let nested = subcommands(&help(&[bin, &sub]));
            // A command with subcommands may take arguments of its own too (`isowall bench`).
            if nested.is_empty() || !options(&help(&[bin, &sub])).is_empty() {
                commands.push(vec![bin.to_string(), sub.clone()]);
            }
            if !nested.is_empty() {
                commands.extend(nested.into_iter().map(|n| vec![bin.to_string(), sub.clone(), n]));
            }
        }
    }
    assert!(commands.len() >= 18, "{commands:?}");
    let mut problems = Vec::new();
    for cmd in &commands {
        let title = cmd.join(" ");
        let args: Vec<&str> = cmd.iter().map(String::as_str).collect();
        let shown = options(&help(&args));
        let Some(listed) = doc.get(&title) else {
            problems.push(format!("`{title}` has no section"));
            continue;
        };
        for (flag, default) in &shown {
            match listed.get(flag) {
                None => problems.push(format!("`{title}`: {flag} is not listed")),
                Some(d) if !default.is_empty() && d != default => problems
                    .push(format!("`{title}` {flag}: the reference says default '{d}', --help '{default}'")),
                Some(_) => {}
            }
        }
        for flag in listed.keys().filter(|f| !shown.contains_key(*f)) {
            problems.push(format!("`{title}`: {flag} is listed but --help has no such flag"));
        }
    }
    assert!(problems.is_empty(), "docs/reference.md has drifted:\n{}", problems.join("\n"));
}

#[test]
fn every_config_key_is_in_the_reference() {
    let doc = sections(&reference());
    let tables = ["wall", "camera", "volume", "render", "certificates", "joystick", "tiles", "nodes"];
    // An unknown key in every table: the config's types answer with the keys they accept.
    let mut text = String::from("zz_not_a_key = 1\n");
    let mut at_line = BTreeMap::new();
    for t in tables {
        let header = if t == "tiles" || t == "nodes" { format!("[[{t}]]") } else { format!("[{t}]") };
        text.push_str(&header);
        text.push('\n');
        at_line.insert(text.lines().count() + 1, t);
        text.push_str("zz_not_a_key = 1\n");
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("keys.toml");
    std::fs::write(&path, &text).unwrap();
    let out = run_in(dir.path(), "isowall", &["check-config", path.to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    let mut accepted: BTreeMap<&str, BTreeSet<String>> = BTreeMap::new();
    for line in stdout.lines().filter(|l| l.contains("unknown field `zz_not_a_key`")) {
        let line_no: usize = line.split(':').nth(1).and_then(|n| n.parse().ok()).unwrap_or(0);
        let table = if line_no == 1 { "" } else { at_line.get(&line_no).copied().unwrap_or("?") };
        let expected = line.split("expected").nth(1).unwrap_or_default();
        let keys = expected.split('`').skip(1).step_by(2).map(str::to_string).collect();
        accepted.insert(table, keys);
    }
    assert_eq!(accepted.len(), tables.len() + 1, "one unknown-key problem per table and the top:\n{stdout}");
    let mut problems = Vec::new();
    let documented_tables: BTreeSet<String> = doc
        .keys()
        .filter_map(|h| h.strip_prefix('[').map(|t| t.trim_matches(['[', ']']).to_string()))
        .collect();
    if accepted[""] != documented_tables {
        problems
            .push(format!("tables: the config has {:?}, the reference {documented_tables:?}", accepted[""]));
    }
    for t in tables {
        let heading = if t == "tiles" || t == "nodes" { format!("[[{t}]]") } else { format!("[{t}]") };
        let listed: BTreeSet<String> =
            doc.get(&heading).map(|r| r.keys().cloned().collect()).unwrap_or_default();
        if accepted[t] != listed {
            problems.push(format!(
                "{heading}: the config accepts {:?}, the reference lists {listed:?}",
                accepted[t]
            ));
        }
    }
    assert!(problems.is_empty(), "docs/reference.md has drifted:\n{}", problems.join("\n"));
}

#[test]
fn the_reference_parser_reads_rows_and_help_reads_defaults() {
    let doc = "### `x run`\n\n| flag | default | what |\n|---|---|---|\n| `--a <R\\|u>` | 8 \\| 9 | A |\n| `<CONFIG>` |  | C |\n";
    let s = sections(doc);
    assert_eq!(s["x run"].get("--a").map(String::as_str), Some("8 | 9"));
    assert!(s["x run"].contains_key("<CONFIG>"));
    let help = "Usage: x run\n\nArguments:\n  <CONFIG>\n          The config\n\nOptions:\n      --a <R>\n          A thing\n          \n          [default: 8]\n\n  -q, --quiet  Say less\n  -h, --help   Print help\n";
    let o = options(help);
    assert_eq!(o.keys().cloned().collect::<Vec<_>>(), ["--a", "--quiet", "<CONFIG>"]);
    assert_eq!(o["--a"], "8");
}
