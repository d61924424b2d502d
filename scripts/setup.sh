#!/usr/bin/env bash
# Installs every Debian 12 package Prism needs to build, test and run. Idempotent: packages that are
# already present are skipped by apt-get. Needs root (or sudo).
set -euo pipefail

PACKAGES=(
  build-essential cmake ninja-build ccache pkg-config git
  libeigen3-dev
  libopencv-dev libopencv-contrib-dev
  libpcl-dev
  libzmq3-dev cppzmq-dev
  libmicrohttpd-dev nlohmann-json3-dev libcli11-dev
  libprotobuf-dev protobuf-compiler
  libdraco-dev draco
  libjpeg-dev libpng-dev libyaml-cpp-dev  # the client SDK's encoders and camera.yaml reader
  libgtest-dev libgmock-dev libbenchmark-dev
  clang  # libFuzzer targets (PRISM_FUZZ) and the sanitizer builds
  clang-format  # the format_check test
  libcgal-demo
  python3 python3-numpy python3-dev pybind11-dev python3-yaml
  python3-zmq python3-protobuf  # tests/protocol_contract_test.py: a client from the .proto alone
  python3-open3d docker-compose
  gstreamer1.0-plugins-base  # live_capture_test: a live GStreamer test source through OpenCV's VideoCapture
  chromium  # live_view_test: prism-client's live 3D view in a real (headless) browser
)

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

export DEBIAN_FRONTEND=noninteractive
if [ "${#missing[@]}" -eq 0 ]; then
  echo "setup: all ${#PACKAGES[@]} packages already installed"
else
  echo "setup: installing ${#missing[@]} packages: ${missing[*]}"
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

# The live 3D view's page (prism-client --view): three.js and the draco3d decoder from npm, and
# playwright-core that drives chromium in live_view_test, at the versions web/package-lock.json pins,
# into web/node_modules; the build copies the page's libraries into build/share/prism/web. Node.js and
# npm come from Debian when the machine has none.
WEB_DIR="$(cd "$(dirname "$0")/.." && pwd)/web"
if [ -f "$WEB_DIR/package.json" ]; then
  if ! command -v npm >/dev/null; then
    echo "setup: installing Node.js and npm"
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq --no-install-recommends nodejs npm
  fi
  if [ ! -f "$WEB_DIR/node_modules/.package-lock.json" ] || \
     [ "$WEB_DIR/package-lock.json" -nt "$WEB_DIR/node_modules/.package-lock.json" ]; then
    echo "setup: npm ci in web/ (three.js, draco3d, playwright-core)"
    (cd "$WEB_DIR" && npm ci --no-audit --no-fund --loglevel=error)
  fi
else
  echo "setup: no web/package.json beside this script; the live view's libraries are not installed"
fi
echo "setup: done"
