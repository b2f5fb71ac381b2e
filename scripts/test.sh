#!/usr/bin/env bash
# The whole test suite. GPU tests run on whatever Vulkan driver is present (lavapipe without a GPU);
# with CI=true a missing adapter fails them instead of skipping them.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/setup.sh
cargo test --workspace --no-fail-fast "$@"
