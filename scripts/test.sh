#!/usr/bin/env bash
# Sets up this machine (Debian 12 packages), builds Prism and runs the default test suites
# (CTest labels unit and integration; the slow label runs with scripts/test.sh --slow).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/build.sh
BUILD_DIR=${BUILD_DIR:-build}
if [ "${1:-}" = "--slow" ]; then
  LABELS="slow"
else
  LABELS="unit|integration"
fi
cd "$BUILD_DIR"
ctest -L "$LABELS" --output-on-failure -j "$(nproc)" --timeout 600
