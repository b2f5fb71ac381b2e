//! `isowall`, the controller CLI: checks configs, makes the wall's certificates, brings a wall up
//! (local daemons for loopback nodes), drives it (an orbit), and gathers whole-wall snapshots.
//! It never links wgpu: the daemons render.

mod bench;
mod console;
mod controls;
mod demo;
mod drive;
mod local;
mod metrics;
mod path;
mod picture;
mod progress;
mod report;
mod session;
mod start;
mod wall;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "isowall",
    version,
    about = "Isowall controller: brings a display wall up from a config and drives it.",
    long_about = "Isowall controller: brings a display wall up from a config and drives it.\n\n\
                  First `isowall keygen --config WALL.toml` (once), then `isowall up WALL.toml` \
                  starts a daemon for every node on this machine's loopback, orbits the volume and \
                  stops them on exit. Render single frames with `isowalld render`.",
    after_help = "Logging: RUST_LOG=debug for more; local daemons log to FOLDER-OF-CONFIG/logs/NODE.log."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Check a wall config: print every problem as FILE:LINE:COL (exit 1), or a summary.
    CheckConfig(isowall_model::check_config::CheckConfigArgs),
    /// Make the wall's certificate authority and a certificate per node and for the controller.
    Keygen(drive::KeygenArgs),
    /// Start a local daemon for every loopback node, drive an orbit, optionally snapshot, stop them.
    Up(drive::UpArgs),
    /// Drive an orbit of N frames on a running wall and print frame statistics.
    Orbit(drive::OrbitArgs),
    /// Gather every tile's last frame of a running wall into one image (bezels dark).
    Snapshot(drive::SnapshotArgs),
    /// Benchmarks: `--table` is the report's table (AO samples x nodes, fps, 2008 beside ours).
    Bench(bench::BenchArgs),
    /// Drive the wall interactively: terminal keyboard and gamepad, with a live status line.
    Session(session::SessionArgs),
    /// Play a scripted camera path (keyframes in TOML) on the wall; --loop, --record DIR.
    Demo(demo::DemoArgs),
    /// Serve the operator console: a web page and a JSON API (status, thumbnail, controls).
    Console(console::ConsoleArgs),
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        // Colour only on a terminal: redirected to a node's log or journald, codes would be noise.
        .with_ansi(colour_logs())
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::CheckConfig(args) => isowall_model::check_config::run(
            &args,
            isowall_model::check_config::CheckedOn::Controller,
            &isowall_net::tls::check_wall_certificates,
        )
        .map_err(anyhow::Error::from),
        Command::Keygen(args) => drive::keygen(&args),
        Command::Up(args) => drive::up(&args),
        Command::Orbit(args) => drive::orbit(&args),
        Command::Snapshot(args) => drive::snapshot(&args),
        Command::Demo(args) => demo::demo(&args),
        Command::Bench(args) => bench::bench(&args),
        Command::Session(args) => session::session(&args),
        Command::Console(args) => console::console(&args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("isowall: error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Whether log lines carry ANSI colour: only where stderr is a terminal and `NO_COLOR` is unset.
fn colour_logs() -> bool {
    use std::io::IsTerminal;
    std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}
