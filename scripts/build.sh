#!/usr/bin/env bash
# Configures and builds Prism into build/ (Ninja, ccache, Release). Binaries land in build/bin/.
# Environment: BUILD_DIR (default build), PRISM_WERROR=ON to fail on warnings (CI sets it),
# JOBS (default: number of cores).
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${BUILD_DIR:-build}
JOBS=${JOBS:-$(nproc)}
WERROR=${PRISM_WERROR:-OFF}
if [ "${CI:-}" = "true" ]; then WERROR=ON; fi
cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE=Release -DPRISM_WERROR="$WERROR" >/dev/null
cmake --build "$BUILD_DIR" -j "$JOBS"
