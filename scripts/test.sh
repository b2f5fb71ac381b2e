#!/usr/bin/env bash
# The whole test suite. GPU tests run on whatever Vulkan driver is present (lavapipe without a GPU);
# with CI=true a missing adapter fails them instead of skipping them.
set -euo pipefail
cd "$(dirname "$0")/.."
isowall_tests=yes   # setup.sh adds what the window test needs (Xvfb, xwd)
. scripts/setup.sh
# The house's formatting (rustfmt.toml) and lints (Cargo.toml's [workspace.lints]) first: both are
# quick, and a finding fails the run before the tests start.
cargo fmt --all --check || { echo "isowall: formatting differs: run cargo fmt" >&2; exit 1; }
if [ "$clippy_strict" = yes ]; then
    cargo clippy --workspace --all-targets --quiet -- -D warnings
else
    cargo clippy --workspace --all-targets --quiet
fi
cargo test --workspace --no-fail-fast "$@"
