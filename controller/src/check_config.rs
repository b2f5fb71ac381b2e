//! `isowall check-config FILE` and `isowalld check-config FILE` (this one file is compiled into
//! both binaries): reads and validates a wall config
//! ([`WallConfig::check_report`](isowall_wall::WallConfig::check_report)). Every problem is printed
//! to stderr as `FILE:LINE:COL: message` and the exit status is 1; a valid config prints a short
//! summary (the wall, its image size and the tiles of every node) to stdout.

use isowall_wall::WallConfig;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct CheckConfigArgs {
    /// The wall config (TOML), e.g. wall-configs/local-2x2.toml
    #[arg(value_name = "FILE")]
    pub file: PathBuf,
}

pub fn run(a: &CheckConfigArgs) -> anyhow::Result<()> {
    let (problems, last) = match WallConfig::check_report(&a.file) {
        Ok(report) => {
            println!("{report}");
            return Ok(());
        }
        Err(e) => e,
    };
    eprintln!("{problems}");
    anyhow::bail!("{last}")
}
