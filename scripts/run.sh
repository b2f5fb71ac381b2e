#!/usr/bin/env bash
# The main job on the embedded default: brings up a local 2x2 wall on this machine (four
# `isowalld` nodes on loopback), orbits the built-in engine-like volume with ambient occlusion and
# sky lighting, prints the frame statistics and writes a whole-wall snapshot to isowall-wall.png.
# Extra arguments go to `isowall up` (see `isowall up --help`), e.g. --frames 90.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/setup.sh
cargo build --quiet -p isowalld -p isowall
config=wall-configs/local-2x2.toml
if [ ! -f wall-configs/keys/ca.pem ]; then
    target/debug/isowall keygen --config "$config"
fi
exec target/debug/isowall up "$config" --frames 24 --snapshot isowall-wall.png "$@"
