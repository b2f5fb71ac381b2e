//! `isowall`, the controller CLI. The wall issue gives it `up`, `orbit`, `snapshot`, `keygen` and
//! `check-config`; until then it only says so.

use clap::Parser;

#[derive(Parser)]
#[command(
    name = "isowall",
    version,
    about = "Isowall controller: brings a display wall up from a config and drives it.",
    long_about = "Isowall controller: brings a display wall up from a config and drives it. The wall \
                  commands (up, orbit, snapshot, keygen, check-config) are not built yet; render single \
                  frames with `isowalld render`."
)]
struct Cli {}

fn main() {
    let _ = Cli::parse();
    eprintln!("isowall: no wall commands yet; see `isowall --help`. Render a frame with `isowalld render`.");
    std::process::exit(2);
}
