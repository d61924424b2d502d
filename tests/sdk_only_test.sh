#!/usr/bin/env bash
# The client SDK built alone, as on a device: `cmake -DPRISM_SDK_ONLY=ON` with PCL and OpenCV hidden
# from CMake, built, installed into a fresh prefix, and used three ways: the installed example built
# with find_package(prism_client) and run against a real prism-server of BUILD_DIR, a program built
# with pkg-config alone (LoadRig, DecodeChunk), and the installed .proto compiled by protoc.
# usage: sdk_only_test.sh SOURCE_DIR BUILD_DIR
set -euo pipefail
SRC=$1
BUILD=$2
WORK=$(mktemp -d /tmp/prism_sdk_only_XXXXXX)
SERVER_PID=
cleanup() {
  [ -n "$SERVER_PID" ] && kill -TERM "$SERVER_PID" 2>/dev/null && wait "$SERVER_PID" 2>/dev/null || true
  rm -rf "$WORK"
}
trap cleanup EXIT
fail() { echo "sdk_only_test: $*"; exit 1; }

# Configure and build the SDK alone. A dependency it must not need is hidden, so asking for it fails.
cmake -S "$SRC" -B "$WORK/build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DPRISM_SDK_ONLY=ON \
  -DCMAKE_DISABLE_FIND_PACKAGE_PCL=ON -DCMAKE_DISABLE_FIND_PACKAGE_OpenCV=ON \
  -DCMAKE_DISABLE_FIND_PACKAGE_GTest=ON -DCMAKE_DISABLE_FIND_PACKAGE_CLI11=ON \
  > "$WORK/configure.log" 2>&1 || { cat "$WORK/configure.log"; fail "configure failed"; }
cmake --build "$WORK/build" > "$WORK/build.log" 2>&1 || { tail -50 "$WORK/build.log"; fail "build failed"; }
cmake --install "$WORK/build" --prefix "$WORK/prefix" > "$WORK/install.log"

# What a device gets: the library, its header, the CMake package, the pkg-config file, the .proto.
P="$WORK/prefix"
LIBDIR=$(dirname "$(find "$P" -name 'libprism_client.so' | head -n 1)")
[ -n "$LIBDIR" ] || fail "no libprism_client.so installed"
for f in "$P/include/prism/client/client.h" "$P/include/prism/v1/session.proto" \
         "$LIBDIR/cmake/prism_client/prism_clientConfig.cmake" "$LIBDIR/pkgconfig/prism_client.pc"; do
  [ -f "$f" ] || fail "not installed: $f"
done
if find "$P" -name '*prism-*' -o -name 'libprism_codec*' | grep -q .; then fail "more than the SDK was installed"; fi
# The library needs neither OpenCV nor PCL (nor VTK, libmicrohttpd).
NEEDED=$(readelf -d "$LIBDIR/libprism_client.so" | sed -n 's/.*Shared library: \[\(.*\)\]/\1/p')
if echo "$NEEDED" | grep -E 'opencv|pcl|vtk|microhttpd'; then fail "libprism_client.so needs the above"; fi
echo "libprism_client.so needs: $(echo $NEEDED)"

# 1. find_package(prism_client): the installed example, run against a real prism-server.
cmake -S "$P/share/prism_client/example" -B "$WORK/example-build" -G Ninja -DCMAKE_PREFIX_PATH="$P" \
  > "$WORK/example-configure.log" 2>&1 || { cat "$WORK/example-configure.log"; fail "example configure failed"; }
cmake --build "$WORK/example-build" > "$WORK/example-build.log" 2>&1 || { cat "$WORK/example-build.log"; fail "example build failed"; }
"$BUILD/bin/prism-server" --bind 'tcp://127.0.0.1:*' --data-dir "$WORK/data" --metrics off > "$WORK/server.json" 2> "$WORK/server.log" &
SERVER_PID=$!
for _ in $(seq 100); do [ -s "$WORK/server.json" ] && break; sleep 0.1; done
ENDPOINT=$(sed -n 's/.*"endpoint": "\([^"]*\)".*/\1/p' "$WORK/server.json")
[ -n "$ENDPOINT" ] || { cat "$WORK/server.log"; fail "prism-server did not start"; }
LD_LIBRARY_PATH="$LIBDIR" "$WORK/example-build/prism_client_example" "$ENDPOINT" 5 > "$WORK/example.out"
# Grey test frames give no pose; the server must have received all five and closed the session.
grep -q "^summary: 5 frames received" "$WORK/example.out" || { cat "$WORK/example.out"; fail "the session did not round-trip"; }

# 2. pkg-config alone: the SDK's camera.yaml reader and chunk decoder.
cat > "$WORK/camera.yaml" <<'YAML'
%YAML:1.0
---
width: 160
height: 120
fx: 150.
fy: 150.
cx: 80.
cy: 60.
distortion: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.1, 0.01, 0., 0., 0. ]
lights:
   - { name: red, type: point, position: [ -0.2, 0., 0. ], color: [ 1., 0., 0. ], intensity: 0.25 }
   - { name: green, type: point, position: [ 0.2, 0., 0. ], color: [ 0., 1., 0. ], intensity: 0.25 }
   - { name: blue, type: point, position: [ 0., -0.2, 0. ], color: [ 0., 0., 1. ], intensity: 0.25 }
YAML
cat > "$WORK/use.cc" <<'CC'
#include <prism/client/client.h>
#include <cstdio>
int main(int, char** argv) {
  prism::client::Rig rig;
  prism::client::Status s = prism::client::LoadRig(argv[1], &rig);
  if (!s.ok()) { std::printf("LoadRig: %s\n", s.ToString().c_str()); return 1; }
  std::vector<prism::client::Point> points;
  const uint8_t junk[16] = {'n', 'o', 't', ' ', 'd', 'r', 'a', 'c', 'o'};
  s = prism::client::DecodeChunk(junk, sizeof(junk), &points);
  std::printf("%dx%d k1 %g %s %s\n", rig.camera.width, rig.camera.height, rig.camera.distortion[0],
              rig.lights[2].name.c_str(), prism::client::CodeName(s.code));
  return s.code == prism::client::Code::kDataLoss ? 0 : 1;
}
CC
export PKG_CONFIG_PATH="$LIBDIR/pkgconfig"
# shellcheck disable=SC2046
g++ -std=c++17 -o "$WORK/use" "$WORK/use.cc" $(pkg-config --cflags --libs prism_client)
OUT=$(LD_LIBRARY_PATH="$LIBDIR" "$WORK/use" "$WORK/camera.yaml")
[ "$OUT" = "160x120 k1 -0.1 blue DATA_LOSS" ] || fail "pkg-config program said: $OUT"

# 3. The installed wire contract, for a client in another language.
protoc -I "$(pkg-config --variable=protodir prism_client)" --python_out="$WORK" prism/v1/session.proto
[ -f "$WORK/prism/v1/session_pb2.py" ] || fail "protoc did not compile the installed session.proto"
echo "SDK alone (no PCL, no OpenCV): built, installed, used by find_package, pkg-config and protoc: ok"
