//! `isowall check-config FILE`: reads and validates a wall config. Every problem is printed to
//! stderr as `FILE:LINE:COL: message` and the exit status is 1; a valid config prints a short
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
    match WallConfig::load(&a.file) {
        Ok(config) => {
            println!("{}: ok", a.file.display());
            println!("{}", config.summary());
            Ok(())
        }
        Err(errors) => {
            eprintln!("{errors}");
            let n = errors.problems.len();
            anyhow::bail!("{}: {n} problem{}", a.file.display(), if n == 1 { "" } else { "s" })
        }
    }
}
