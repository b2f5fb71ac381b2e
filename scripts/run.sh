#!/usr/bin/env bash
# The main job on the embedded default: renders the built-in engine-like volume to isowall.png.
# Extra arguments go to `isowalld render` (see `isowalld render --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/setup.sh
cargo build --quiet -p isowalld
exec target/debug/isowalld render "$@"
