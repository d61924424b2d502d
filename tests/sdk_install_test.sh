#!/usr/bin/env bash
# The client SDK as a user gets it: `cmake --install` the build into a fresh prefix, build the
# installed example with find_package(prism_client) in a separate CMake project, and run it against
# a real prism-server from this build; the pkg-config file and the .proto are installed, and the
# Python package lands where Debian's /usr/bin/python3 imports from and imports from there.
# usage: sdk_install_test.sh BUILD_DIR
set -euo pipefail
BUILD=$1
WORK=$(mktemp -d /tmp/prism_sdk_install_XXXXXX)
SERVER_PID=
cleanup() {
  [ -n "$SERVER_PID" ] && kill -TERM "$SERVER_PID" 2>/dev/null && wait "$SERVER_PID" 2>/dev/null || true
  rm -rf "$WORK"
}
trap cleanup EXIT
cmake --install "$BUILD" --prefix "$WORK/prefix" > "$WORK/install.log"
test -f "$WORK/prefix/include/prism/client/client.h"
EXAMPLE="$WORK/prefix/share/prism_client/example"
test -f "$EXAMPLE/CMakeLists.txt"
# No zmq, protobuf or project-internal header may leak into the public header.
if grep -E '#include ["<](zmq|google/protobuf|core/)' "$WORK/prefix/include/prism/client/client.h"; then
  echo "the public header includes an internal dependency"; exit 1
fi
test -f "$WORK/prefix/include/prism/v1/session.proto"
test -n "$(find "$WORK/prefix" -path '*/pkgconfig/prism_client.pc')"
# The Python package: in the configured prefix's dist-packages that Debian's python3 searches (for
# /usr/local: lib/python3.X/dist-packages), importable from there with no other path set.
cache_value() { sed -n "s/^$1:[A-Z]*=//p" "$BUILD/CMakeCache.txt"; }
PYDIR=$(cache_value PRISM_PYTHON_INSTALL_DIR)
if [ -n "$PYDIR" ]; then
  test -f "$WORK/prefix/$PYDIR/prism_client/__init__.py"
  CONFIGURED=$(cache_value CMAKE_INSTALL_PREFIX)
  if [ "$CONFIGURED" = /usr/local ] || [ "$CONFIGURED" = /usr ]; then
    /usr/bin/python3 -c "import sys; assert '$CONFIGURED/$PYDIR' in sys.path, sys.path"
  fi
  if [ -z "${PRISM_SANITIZE:-}" ]; then  # a sanitized module needs its runtime preloaded (python_client_test)
    PYTHONPATH="$WORK/prefix/$PYDIR" /usr/bin/python3 -c "
import prism_client
doc = prism_client.Session.push_frame.__doc__
assert 'push_frame(self: prism_client._native.Session, timestamp_ns: int, rgb:' in doc, doc
assert prism_client.__file__.startswith('$WORK/prefix/'), prism_client.__file__"
  fi
fi
# In a sanitizer build the SDK is instrumented, so its consumer must be too (PRISM_SANITIZE, set by
# CTest from the build's option).
SANITIZE_FLAGS=""
if [ -n "${PRISM_SANITIZE:-}" ]; then SANITIZE_FLAGS="-fsanitize=$PRISM_SANITIZE"; fi
cmake -S "$EXAMPLE" -B "$WORK/example-build" -G Ninja -DCMAKE_PREFIX_PATH="$WORK/prefix" \
  -DCMAKE_CXX_FLAGS="$SANITIZE_FLAGS" -DCMAKE_EXE_LINKER_FLAGS="$SANITIZE_FLAGS" > "$WORK/configure.log"
cmake --build "$WORK/example-build" > "$WORK/build.log"
"$BUILD/bin/prism-server" --bind 'tcp://127.0.0.1:*' --data-dir "$WORK/data" --metrics off > "$WORK/server.json" 2> "$WORK/server.log" &
SERVER_PID=$!
for _ in $(seq 100); do [ -s "$WORK/server.json" ] && break; sleep 0.1; done
ENDPOINT=$(sed -n 's/.*"endpoint": "\([^"]*\)".*/\1/p' "$WORK/server.json")
[ -n "$ENDPOINT" ] || { echo "prism-server did not start"; cat "$WORK/server.log"; exit 1; }
LD_LIBRARY_PATH="$WORK/prefix/lib:$WORK/prefix/lib/x86_64-linux-gnu" "$WORK/example-build/prism_client_example" "$ENDPOINT" 5
echo "installed SDK: find_package, build and a session against prism-server: ok"
