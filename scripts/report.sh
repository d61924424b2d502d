#!/usr/bin/env bash
# Prints the tables docs/ shows, each with the command, machine and date that made it. Usage:
#   scripts/report.sh metrics [--write]   the metrics prism-server exports (docs/operations.md)
#   scripts/report.sh abuse [--write]     prism-bench-abuse: a session beside each misbehaving peer (~12 min)
# --write also replaces the table in its document: the lines between "<!-- report.sh NAME -->" and
# "<!-- end report.sh NAME -->". BUILD_DIR (default build) holds the binaries.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BUILD_DIR:-build}/bin
if [ "${2:-}" = "--write" ]; then
  doc=""
  case "$1" in
    metrics | abuse) doc=docs/operations.md ;;
  esac
  table=$(mktemp)
  bash "$0" "$1" "${@:3}" | tee "$table"
  python3 - "$doc" "$1" "$table" <<'PY'
import sys
doc, name, table = sys.argv[1], sys.argv[2], open(sys.argv[3]).read().rstrip("\n")
text = open(doc).read()
begin, end = f"<!-- report.sh {name} -->", f"<!-- end report.sh {name} -->"
a, b = text.index(begin) + len(begin), text.index(end)
open(doc, "w").write(text[:a] + "\n" + table + "\n" + text[b:])
PY
  rm -f "$table"
  exit 0
fi
machine() { echo "$(nproc) cores, $(awk -F': ' '/model name/{print $2; exit}' /proc/cpuinfo), $(date -u +%Y-%m-%d)"; }

case "${1:-}" in
  metrics)
    dir=$(mktemp -d)
    "$BIN/prism-server" --bind 'tcp://127.0.0.1:*' --data-dir "$dir" --metrics 127.0.0.1:0 --log-level error \
      > "$dir/out.json" &
    pid=$!
    for _ in $(seq 100); do [ -s "$dir/out.json" ] && break; sleep 0.05; done
    url=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["metrics"])' "$dir/out.json")
    "$BIN/prism-probe" "$url/metrics" > "$dir/metrics.txt"
    kill "$pid"; wait "$pid" || true
    echo "Made by \`scripts/report.sh metrics\` (prism-server's /metrics HELP and TYPE lines)."
    echo
    echo "| metric | type | meaning |"
    echo "|---|---|---|"
    python3 - "$dir/metrics.txt" <<'PY'
import sys
help_, type_ = {}, {}
for line in open(sys.argv[1]):
    if line.startswith("# HELP "):
        name, text = line[7:].rstrip("\n").split(" ", 1)
        help_[name] = text
    elif line.startswith("# TYPE "):
        name, t = line[7:].split()
        type_[name] = t
for name in sorted(help_):
    print(f"| `{name}` | {type_.get(name, '')} | {help_[name]} |")
PY
    rm -rf "$dir"
    ;;
  abuse)
    "$BIN/prism-bench-abuse" "${@:2}"
    echo
    echo "Made by \`scripts/report.sh abuse\` (\`prism-bench-abuse\`) on $(machine)."
    ;;
  *)
    echo "usage: scripts/report.sh metrics|abuse" >&2
    exit 2
    ;;
esac
