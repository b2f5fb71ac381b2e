//! The Debian package `isowall` (cargo-deb, `[package.metadata.deb]` in controller/Cargo.toml),
//! made from the binaries this test suite built (the debug profile: no second, release build;
//! they stand in a temporary target folder's `release/`, where cargo-deb's assets look, and
//! `cargo deb --no-build` builds nothing), then checked:
//! (a) `dpkg-deb -c`: exactly the files it should hold, binaries in /usr/bin, units in
//!     /usr/lib/systemd/system, the docs the units' `Documentation=` names;
//! (b) `dpkg-deb -I`: the dependencies dpkg-shlibdeps cannot see (the Vulkan loader, a driver, the
//!     X11 libraries winit opens), the maintainer scripts;
//! (c) the packaged units are wall-configs/systemd/'s, byte for byte, point at /usr/bin, and pass
//!     `systemd-analyze verify` (not one warning) and, the node's, `security` at <= 2.0, with the
//!     unpacked package as the root (so ExecStart= names the packaged binaries);
//! (d) `lintian`: no error or warning but those accepted below, each with its reason.
//!
//! Tools: cargo-deb, lintian and systemd-analyze (scripts/setup.sh installs them for the suite);
//! under CI=true a missing one fails the test, elsewhere it skips with a message.

use isowall_e2e::{bin, in_ci, repo_root};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The units of wall-configs/systemd/, all of them packaged.
const UNITS: [&str; 3] = ["isowalld.service", "isowall-demo.service", "isowall-console.service"];

/// Lintian's findings at warning level or above accepted for this package, and why; any other
/// fails the test. (At info level it also says: hardening-no-fortify-functions, there being no C
/// code to fortify; no-md5sums-control-file, which cargo-deb does not write;
/// package-supports-alternative-init-but-no-init.d-script, the units being systemd's alone; and
/// spelling-error-in-binary, byte runs in the binaries that read as misspelt words.)
const ACCEPTED: [(&str, &str); 2] = [
    // Debian's changelog.Debian.gz is for packages uploaded to Debian; this one is built from the
    // repository, whose history is its changelog (an entry kept by hand would fall behind).
    ("no-changelog", "built from the repository, whose git history is its changelog"),
    // The commands' reference is `--help` and docs/reference.md (installed with the package),
    // which a test holds to the binaries; man pages would be a third copy.
    ("no-manual-page", "--help and /usr/share/doc/isowall/reference.md are the reference"),
];

/// Whether `command` runs; under CI its absence fails the test, elsewhere it is a skip.
fn tool(command: &[&str]) -> bool {
    match Command::new(command[0]).args(&command[1..]).output() {
        Ok(out) if out.status.success() => true,
        _ => {
            let why = format!(
                "`{}` does not run (scripts/setup.sh installs it with isowall_tests=yes)",
                command.join(" ")
            );
            assert!(!in_ci(), "{why}");
            eprintln!("skipping: {why}");
            false
        }
    }
}

fn run(cmd: &mut Command) -> Output {
    let out = cmd.output().unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
    assert!(
        out.status.success(),
        "{cmd:?} failed ({}):\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn text(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Makes the package from the suite's binaries; returns its path (in `dir`).
fn package(dir: &Path) -> PathBuf {
    let (isowalld, isowall) = (bin("isowalld"), bin("isowall"));
    // cargo-deb reads `target/release/NAME` in the assets as "NAME in the target folder's release
    // profile": a folder whose release/ holds the suite's binaries, hard links where the file
    // system allows (they are hundreds of MB), is that target folder.
    let profile = dir.join("target/release");
    std::fs::create_dir_all(&profile).unwrap();
    for b in [&isowalld, &isowall] {
        let to = profile.join(b.file_name().unwrap());
        if std::fs::hard_link(b, &to).is_err() {
            std::fs::copy(b, &to).unwrap();
        }
    }
    let deb = dir.join("isowall.deb");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.current_dir(repo_root())
        .env("CARGO_TARGET_DIR", dir.join("target"))
        // --strip: the debug profile keeps line tables (as the release profile does), which a
        // package leaves out (lintian: unstripped-binary-or-object); --fast: quicker compression.
        .args(["deb", "-p", "isowall", "--no-build", "--strip", "--fast", "--output"])
        .arg(&deb);
    // What `cargo test` sets for this package is not cargo-deb's to read (it runs cargo metadata).
    for (key, _) in std::env::vars_os() {
        if key.to_str().is_some_and(|k| k.starts_with("CARGO_PKG_") || k == "CARGO_MANIFEST_DIR") {
            cmd.env_remove(key);
        }
    }
    run(&mut cmd);
    deb
}

#[test]
fn the_debian_package_holds_both_binaries_the_units_and_their_docs_and_passes_lintian() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    if !(tool(&[&cargo, "deb", "--version"])
        && tool(&["dpkg-deb", "--version"])
        && tool(&["lintian", "--version"])
        && tool(&["systemd-analyze", "--version"]))
    {
        return;
    }
    let dir = tempfile::tempdir_in(bin("isowall").parent().unwrap()).unwrap();
    let deb = package(dir.path());

    // (a) The files, each with its mode and owner.
    let listing = text(&run(Command::new("dpkg-deb").arg("-c").arg(&deb)));
    eprintln!("dpkg-deb -c:\n{listing}");
    let mut files = BTreeSet::new();
    for line in listing.lines() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        let (mode, owner, path) = (fields[0], fields[1], fields[fields.len() - 1]);
        assert!(owner == "0/0" || owner == "root/root", "not root's: {line}");
        if mode.starts_with('d') {
            continue;
        }
        let path = path.trim_start_matches('.').to_string();
        let want = if path.starts_with("/usr/bin/") { "-rwxr-xr-x" } else { "-rw-r--r--" };
        assert_eq!(mode, want, "{line}");
        files.insert(path);
    }
    let mut expected: BTreeSet<String> = [
        "/usr/bin/isowall",
        "/usr/bin/isowalld",
        "/usr/share/doc/isowall/README.md",
        "/usr/share/doc/isowall/operating.md",
        "/usr/share/doc/isowall/reference.md",
        "/usr/share/doc/isowall/wall.md",
        "/usr/share/doc/isowall/copyright",
        "/usr/share/doc/isowall/examples/local-2x2.toml",
        "/usr/share/doc/isowall/examples/sva-4.toml",
        "/usr/share/doc/isowall/examples/object-2x2-hd.toml",
        "/usr/share/doc/isowall/examples/demos/engine.toml",
    ]
    .into_iter()
    .map(String::from)
    .collect();
    expected.extend(UNITS.iter().map(|u| format!("/usr/lib/systemd/system/{u}")));
    assert_eq!(files, expected, "the package's files");

    // (b) The control file: what is loaded at run time, and the maintainer scripts.
    let info = text(&run(Command::new("dpkg-deb").arg("-I").arg(&deb)));
    eprintln!("dpkg-deb -I:\n{info}");
    let field = |name: &str| {
        info.lines()
            .find_map(|l| l.trim_start().strip_prefix(&format!("{name}: ")).map(str::to_string))
            .unwrap_or_else(|| panic!("no {name}: in\n{info}"))
    };
    assert_eq!(field("Package"), "isowall");
    let depends = field("Depends");
    // libudev1 and libc6 are dpkg-shlibdeps' ($auto); the others are not linked.
    for dep in ["libvulkan1", "adduser", "libudev1", "libc6"] {
        assert!(depends.split(", ").any(|d| d.starts_with(dep)), "Depends lacks {dep}: {depends}");
    }
    let recommends = field("Recommends");
    for dep in
        ["mesa-vulkan-drivers | vulkan-icd", "libx11-xcb1", "libxcursor1", "libxi6", "libxkbcommon-x11-0"]
    {
        assert!(recommends.split(", ").any(|d| d == dep), "Recommends lacks {dep}: {recommends}");
    }
    for script in ["postinst", "prerm", "postrm"] {
        assert!(info.lines().any(|l| l.split_whitespace().any(|w| w == script)), "no {script} in\n{info}");
    }

    // (c) The units: the repository's, verified from the unpacked package as the root.
    let root = dir.path().join("root");
    run(Command::new("dpkg-deb").arg("-x").arg(&deb).arg(&root));
    let control = dir.path().join("control");
    run(Command::new("dpkg-deb").arg("-e").arg(&deb).arg(&control));
    let postrm = std::fs::read_to_string(control.join("postrm")).unwrap();
    assert!(
        !postrm.lines().any(|l| l.contains("rm ") && l.contains("/etc/isowall")),
        "purge must not delete the wall's keys:\n{postrm}"
    );
    let mut paths = Vec::new();
    for unit in UNITS {
        let packaged = root.join("usr/lib/systemd/system").join(unit);
        let source = repo_root().join("wall-configs/systemd").join(unit);
        assert_eq!(
            std::fs::read_to_string(&packaged).unwrap(),
            std::fs::read_to_string(&source).unwrap(),
            "{unit}: the packaged unit is not wall-configs/systemd's"
        );
        let unit_text = std::fs::read_to_string(&packaged).unwrap();
        for line in unit_text.lines() {
            let named = if let Some(cmd) = line.strip_prefix("ExecStart=") {
                cmd.split_whitespace().next().unwrap().to_string()
            } else if let Some(url) = line.strip_prefix("Documentation=") {
                url.strip_prefix("file:").unwrap_or_else(|| panic!("{unit}: {line}")).to_string()
            } else {
                continue;
            };
            assert!(named.starts_with("/usr/"), "{unit}: {line}");
            let file = root.join(named.trim_start_matches('/'));
            assert!(file.is_file(), "{unit}: {line} names a file the package does not install");
        }
        paths.push(packaged);
    }
    // Verified with the unpacked package as the root, so that ExecStart= names the packaged
    // binaries; the units they need (sysinit.target, ...) are the host's, copied beside them.
    let system = root.join("usr/lib/systemd/system");
    run(Command::new("cp").args(["-rn", "--no-dereference", "/usr/lib/systemd/system/."]).arg(&system));
    let out =
        Command::new("systemd-analyze").arg("verify").arg("--root").arg(&root).args(&paths).output().unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "systemd-analyze verify failed:\n{stdout}{stderr}");
    assert!(
        stdout.trim().is_empty() && stderr.trim().is_empty(),
        "systemd-analyze verify warned:\n{stdout}{stderr}"
    );
    let out = run(Command::new("systemd-analyze")
        .args(["security", "--offline=yes", "--no-pager", "--root"])
        .arg(&root)
        .arg(&paths[0]));
    let security = text(&out);
    let level = security
        .lines()
        .find_map(|l| l.split("Overall exposure level for isowalld.service:").nth(1))
        .and_then(|rest| rest.split_whitespace().next()?.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no exposure level in:\n{security}"));
    assert!(level <= 2.0, "the packaged isowalld.service's exposure is {level}");

    // (d) Lintian.
    let out = Command::new("lintian")
        .args(["--tag-display-limit", "0", "--display-level", ">=warning", "--suppress-tags"])
        .arg(ACCEPTED.iter().map(|(tag, _)| *tag).collect::<Vec<_>>().join(","))
        .arg(&deb)
        .output()
        .unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    eprintln!("lintian (accepted: {}):\n{said}", ACCEPTED.map(|(t, why)| format!("{t}: {why}")).join("; "));
    let findings: Vec<&str> = said.lines().filter(|l| l.starts_with("E: ") || l.starts_with("W: ")).collect();
    assert!(findings.is_empty(), "lintian:\n{}", findings.join("\n"));
}
