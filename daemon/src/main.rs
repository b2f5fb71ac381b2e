//! `isowalld`, the Isowall node daemon: `run` serves a wall node, `render` renders single frames to
//! files, `bench` measures the renderer, `check-config` checks a wall config.

mod args;
mod balanced;
mod bench;
mod bricked;
mod convert;
mod display;
mod identify;
mod info;
mod notify;
mod object;
mod peer_addr;
mod pixel_links;
mod presenter;
mod progress;
mod realtime;
mod render;
mod render_thread;
mod run;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "isowalld",
    version,
    about = "Isowall node daemon: ray-casts the isosurface of a 3D volume on the GPU (wgpu/Vulkan).",
    long_about = "Isowall node daemon: ray-casts the isosurface of a 3D volume on the GPU (wgpu/Vulkan; \
                  Mesa's lavapipe where there is no GPU).\n\nWith no arguments it renders the built-in \
                  engine-like volume to isowall.png.",
    after_help = "Logging: set RUST_LOG (e.g. RUST_LOG=debug) for more detail; logs go to stderr."
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
#[expect(clippy::large_enum_variant, reason = "parsed once, at start")]
enum Command {
    /// Render one frame of a volume, headless, to a file (PNG for colour, PFM for other AOVs).
    Render(render::RenderArgs),
    /// Run as a wall node: listen for the controller, render this node's tiles each frame, swap
    /// with the rest of the wall (`isowall up` starts local nodes this way).
    Run(run::RunArgs),
    /// Benchmarks (medians of repeated frames; speed with its error, never alone).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Check a wall config: print every problem as FILE:LINE:COL (exit 1), or a summary.
    CheckConfig(isowall_model::check_config::CheckConfigArgs),
    /// What a volume holds: format, grid, orientation, value range, percentiles, a histogram,
    /// and suggested iso values with how they were found.
    Info(info::InfoArgs),
    /// Write any volume Isowall reads as an OME-Zarr pyramid (NGFF 0.5, Zarr v3): levels of 2x2x2
    /// means, chunks of 64^3, orientation and per-brick min/max kept.
    Convert(convert::ConvertArgs),
}

fn main() -> std::process::ExitCode {
    display::quiet_vulkan_without_wayland();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| {
            tracing_subscriber::EnvFilter::new("info,wgpu_core=warn,wgpu_hal=warn,naga=warn,winit=error")
        }))
        .with_writer(std::io::stderr)
        // Colour only on a terminal: redirected to a node's log or journald, codes would be noise.
        .with_ansi(colour_logs())
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        None => render::run(&render::RenderArgs::default()),
        Some(Command::Render(args)) => render::run(&args),
        Some(Command::Info(args)) => info::run(&args),
        Some(Command::Convert(args)) => convert::run(&args),
        Some(Command::Run(args)) => run::run(&args),
        Some(Command::Bench(cmd)) => bench::run(&cmd),
        Some(Command::CheckConfig(args)) => isowall_model::check_config::run(
            &args,
            isowall_model::check_config::CheckedOn::Node,
            &isowall_net::tls::check_wall_certificates,
        )
        .map_err(anyhow::Error::from),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("isowalld: error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Whether log lines carry ANSI colour: only where stderr is a terminal and `NO_COLOR` is unset.
fn colour_logs() -> bool {
    use std::io::IsTerminal;
    std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}
