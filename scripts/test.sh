#!/usr/bin/env bash
# The whole test suite. GPU tests run on whatever Vulkan driver is present (lavapipe without a GPU);
# with CI=true a missing adapter fails them instead of skipping them.
set -euo pipefail
cd "$(dirname "$0")/.."
isowall_tests=yes   # setup.sh adds what the window test needs (Xvfb, xwd)
. scripts/setup.sh
cargo test --workspace --no-fail-fast "$@"
