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
  libjpeg-dev
  libgtest-dev libgmock-dev libbenchmark-dev
  clang  # libFuzzer targets (PRISM_FUZZ) and the sanitizer builds
  clang-format  # the format_check test
  libcgal-demo
  python3 python3-numpy python3-dev pybind11-dev python3-yaml
  python3-zmq python3-protobuf  # tests/protocol_contract_test.py: a client from the .proto alone
  python3-open3d docker-compose
)

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ "${#missing[@]}" -eq 0 ]; then
  echo "setup: all ${#PACKAGES[@]} packages already installed"
  exit 0
fi

echo "setup: installing ${#missing[@]} packages: ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
echo "setup: done"
