#!/usr/bin/env bash
# Prints the tables docs/ shows, each with the command, machine and date that made it. Usage:
#   scripts/report.sh metrics [--write]   the metrics prism-server exports (docs/operations.md)
#   scripts/report.sh abuse [--write]     prism-bench-abuse: a session beside each misbehaving peer (~12 min)
#   scripts/report.sh slam [--write]      prism-slam on the standard presets, seeds 1-6 and held-out 7-9 (~50 min)
#   scripts/report.sh maps [--write]      prism-slam --dense on the standard presets, seed 1: map accuracy (~30 min)
#   scripts/report.sh generalisation [--write]  prism-slam --dense on 40 held-out family scenes (~60 min)
#   scripts/report.sh e2e [--write]       prism-bench-e2e: unpaced per codec, a live camera at 30 frames/s, 2 and 4 at 15 (~6 min)
#   scripts/report.sh speed [--write]     slam_benchmark: tracking and mapping per frame per preset (~15 min)
#   scripts/report.sh parts [--write]     the dense stage's parts and the codecs, medians of 5 (~5 min)
#   scripts/report.sh slam-options [--write]  the SLAM options a user sets, with defaults (docs/method.md)
# --write also replaces the table in its document: the lines between "<!-- report.sh NAME -->" and
# "<!-- end report.sh NAME -->". BUILD_DIR (default build) holds the binaries.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BUILD_DIR:-build}/bin
if [ "${2:-}" = "--write" ]; then
  doc=""
  case "$1" in
    metrics | abuse) doc=docs/operations.md ;;
    slam | maps | generalisation | e2e | speed | parts) doc=docs/benchmarks.md ;;
    slam-options) doc=docs/method.md ;;
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
machine() {
  echo "$(nproc) cores, $(awk -F': ' '/model name/{print $2; exit}' /proc/cpuinfo), $(date -u +%Y-%m-%d)," \
    "commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
}
# Google Benchmark JSON (repetitions) -> "| name | median ms |" rows of the medians.
benchmark_medians() {
  python3 - "$1" <<'PY'
import json, sys
for b in json.load(open(sys.argv[1]))["benchmarks"]:
    if b.get("aggregate_name") == "median":
        unit = {"ns": 1e-6, "us": 1e-3, "ms": 1.0, "s": 1e3}[b.get("time_unit", "ns")]
        extra = "".join(f", {k} {v:.3g}" for k, v in b.items() if k.endswith("_per_point") or k.endswith("_ms"))
        print(f"| `{b['run_name']}` | {b['real_time'] * unit:.2f}{extra} |")
PY
}

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
  slam)
    dir=$(mktemp -d)
    echo "| runs | within 1% ATE | ATE, geometric mean | within 3% depth | depth error, median |"
    echo "|---|---|---|---|---|"
    for seeds in "1 2 3 4 5 6" "7 8 9"; do
      bash scripts/slam_presets.sh "$dir/$seeds" --seeds "$seeds" "${@:2}" > "$dir/out.txt"
      python3 - "$dir/$seeds/results.tsv" "$seeds" <<'PY'
import csv, math, statistics, sys
rows = list(csv.DictReader(open(sys.argv[1]), delimiter="\t"))
ate = [float(r["ate_percent"]) for r in rows]
depth = [100 * float(r["depth_median_rel"]) for r in rows]
ok = [a for a in ate if not math.isnan(a)]
geo = math.exp(sum(math.log(max(a, 1e-6)) for a in ok) / len(ok)) if ok else math.nan
label = "9 standard presets, seeds " + sys.argv[2].replace(" ", ",") + (" (held out)" if sys.argv[2] == "7 8 9" else "")
print(f"| {label} | {sum(a <= 1 for a in ok)} of {len(rows)} | {geo:.3f}% | {sum(d <= 3 for d in depth)} of {len(rows)} | "
      f"{statistics.median(d for d in depth if not math.isnan(d)):.2f}% |")
PY
    done
    rm -rf "$dir"
    echo
    echo "Made by \`scripts/report.sh slam\` (\`scripts/slam_presets.sh\`, prism-slam with one thread per run, two" \
      "runs at a time) on $(machine)."
    ;;
  maps)
    dir=$(mktemp -d)
    presets="bunny-multicolor-forward sphere-multicolor-sideways dragon-multicolor-sideways sphere-uniform-sideways
      relief-uniform-sideways boxes-multicolor-forward bunny-uniform-sideways armadillo-textured-forward
      torus-textured-forward"
    one_map() {
      local p=$1 d=$2
      "$BIN/prism-synth" --preset "$p" --frames 150 --seed 1 --out "$d/seq-$p" > /dev/null
      "$BIN/prism-slam" --sequence "$d/seq-$p" --dense --threads 1 --out "$d/out-$p" > "$d/$p.log" 2>&1 || return 0
      "$BIN/prism-eval" cloud --sequence "$d/seq-$p" --cloud "$d/out-$p/map.ply" --object-only \
        --align-trajectory "$d/out-$p/trajectory_metres.txt" > "$d/$p.json"
      python3 -c 'import json, sys; s = json.load(open(sys.argv[1])); print(s["ate_percent_of_path"])' \
        "$d/out-$p/summary.json" > "$d/$p.ate"
      rm -rf "$d/seq-$p" "$d/out-$p"
    }
    export -f one_map
    export BIN
    echo $presets | tr ' ' '\n' | xargs -P 2 -I{} bash -c 'one_map {} '"$dir"
    echo "| preset | F-score | precision | completeness | accuracy, median mm | ATE % of path |"
    echo "|---|---|---|---|---|---|"
    for p in $presets; do
      python3 - "$dir" "$p" <<'PY'
import json, os, sys
d, p = sys.argv[1], sys.argv[2]
f = os.path.join(d, p + ".json")
if not os.path.exists(f) or not os.path.getsize(f):
    print(f"| {p} | failed (see prism-slam's log) | | | | |")
else:
    e = json.load(open(f))
    ate = float(open(os.path.join(d, p + ".ate")).read())
    print(f"| {p} | {e['fscore']:.3f} | {e['precision']:.3f} | {e['completeness']:.3f} | "
          f"{1000 * e['accuracy_median_m']:.2f} | {ate:.3f} |")
PY
    done
    rm -rf "$dir"
    echo
    echo "Made by \`scripts/report.sh maps\` (prism-slam --dense, 150 frames at 512x512, one thread per run, two runs" \
      "at a time; prism-eval cloud --object-only, tau 1% of the object's size) on $(machine)."
    ;;
  generalisation)
    dir=$(mktemp -d)
    python3 scripts/generalisation.py "$dir" --bin "$BIN" "${@:2}" | sed -n '/^family /,$p'
    rm -rf "$dir"
    echo
    echo "Made by \`scripts/report.sh generalisation\` (\`scripts/generalisation.py\`) on $(machine)."
    ;;
  e2e)
    dir=$(mktemp -d)
    "$BIN/prism-bench-e2e" --codecs png,jpeg "${@:2}" > "$dir/unpaced.json"
    "$BIN/prism-bench-e2e" --codecs jpeg --fps 30 --live "${@:2}" > "$dir/live.json"
    "$BIN/prism-bench-e2e" --codecs jpeg --fps 15 --live --sessions 2 "${@:2}" > "$dir/load2.json"
    "$BIN/prism-bench-e2e" --codecs jpeg --fps 15 --live --sessions 4 "${@:2}" > "$dir/load4.json"
    echo "| run | poses, frames/s | map, frames/s | frame to pose p50 / p95, ms | keyframe to chunk p50 / p95, s |" \
      "map complete / rebuilt after the last pose, s | chunk bits per point | ATE, % of path | map F (precision / completeness) |" \
      "server peak RSS, MB |"
    echo "|---|---|---|---|---|---|---|---|---|---|"
    python3 - "$dir/unpaced.json" "$dir/live.json" "$dir/load2.json" "$dir/load4.json" <<'PY'
import json, sys
def score(c):
    m = c.get("map") or {}
    return f"{m['fscore']:.2f} ({m['precision']:.2f} / {m['completeness']:.2f})" if "fscore" in m else "-"
for path, mode in ((sys.argv[1], "as fast as credits allow"), (sys.argv[2], "live camera, 30 frames/s")):
    d = json.load(open(path))
    for codec, c in d["codecs"].items():
        print(f"| {codec.upper()}, {mode} | {c['frames_per_s']:.1f} | {c['map_frames_per_s']:.1f} | "
              f"{c['frame_to_pose_ms_p50']:.0f} / {c['frame_to_pose_ms_p95']:.0f} | "
              f"{c['keyframe_to_chunk_ms_p50'] / 1000:.2f} / {c['keyframe_to_chunk_ms_p95'] / 1000:.2f} | "
              f"{c['map_complete_after_last_pose_s']:.1f} / {c['map_done_after_last_pose_s']:.1f} | {c['chunk_bits_per_point']:.1f} | {c['ate_percent_of_path']:.2f} | "
              f"{score(c)} | {d['server_peak_rss_mb']:.0f} |")
print()
print("Where a keyframe's time goes on the server (means per keyframe, ms, from its /metrics):")
print()
print("| run | wait in the keyframe queue | dense stage | photometric stereo | fusion | cloud and merge | Draco |")
print("|---|---|---|---|---|---|---|")
for path, mode in ((sys.argv[1], "as fast as credits allow"), (sys.argv[2], "live camera, 30 frames/s")):
    d = json.load(open(path))
    for codec, c in d["codecs"].items():
        b = c["server_ms_per_keyframe"]
        print(f"| {codec.upper()}, {mode} | {b['queue_wait']:.0f} | {b['dense_total']:.0f} | {b['photometric']:.0f} | "
              f"{b['fusion']:.0f} | {b['map']:.0f} | {b['encode']:.0f} |")
print()
print("Sessions at once, each a live camera at 15 frames/s (JPEG), one row per session:")
print()
print("| sessions | session | poses, frames/s | frame to pose p50 / p95, ms | keyframe to chunk p50 / p95, s | "
      "map complete after the last pose, s | keyframes (dropped) | ATE, % of path | map F (precision / completeness) |")
print("|---|---|---|---|---|---|---|---|---|")
for path in sys.argv[3:]:
    sessions = json.load(open(path))["codecs"]["jpeg"]["sessions"]
    for i, c in enumerate(sessions):
        print(f"| {len(sessions)} | {i + 1} | {c['frames_per_s']:.1f} | "
              f"{c['frame_to_pose_ms_p50']:.0f} / {c['frame_to_pose_ms_p95']:.0f} | "
              f"{c['keyframe_to_chunk_ms_p50'] / 1000:.1f} / {c['keyframe_to_chunk_ms_p95'] / 1000:.1f} | "
              f"{c['map_complete_after_last_pose_s']:.1f} | {c['keyframes']} ({c['keyframes_dropped']}) | "
              f"{c['ate_percent_of_path']:.2f} | {score(c)} |")
PY
    rm -rf "$dir"
    echo
    echo "Made by \`scripts/report.sh e2e\` (\`prism-bench-e2e\`: bunny-multicolor-forward, 150 frames of 512x512," \
      "one session per row in the first two tables) on $(machine)."
    ;;
  speed)
    dir=$(mktemp -d)
    "$BIN/slam_benchmark" --benchmark_filter='SlamSequence/(async|paced)_' --benchmark_repetitions=3 \
      --benchmark_report_aggregates_only=true --benchmark_out="$dir/speed.json" --benchmark_out_format=json > /dev/null
    echo "| preset | tracking, ms | mapping, ms | adjustment thread, ms | 95th-percentile frame, ms |" \
      "paced: tracking / mapping / 95th, ms |"
    echo "|---|---|---|---|---|---|"
    python3 - "$dir/speed.json" <<'PY'
import json, sys
rows = {}
for b in json.load(open(sys.argv[1]))["benchmarks"]:
    if b.get("aggregate_name") != "median":
        continue
    mode, preset = b["run_name"].split("/")[1].split("_", 1)
    rows.setdefault(preset, {})[mode] = b
def cell(b, k):
    return f"{b.get(k, float('nan')):.1f}"
for preset, m in rows.items():
    a, p = m.get("async", {}), m.get("paced", {})
    print(f"| {preset} | {cell(a, 'tracking_ms')} | {cell(a, 'mapping_ms')} | {cell(a, 'adjustment_thread_ms')} | "
          f"{cell(a, 'p95_frame_ms')} | {cell(p, 'tracking_ms')} / {cell(p, 'mapping_ms')} / {cell(p, 'p95_frame_ms')} |")
PY
    rm -rf "$dir"
    echo
    echo "Made by \`scripts/report.sh speed\` (\`slam_benchmark\`, 150 frames, seed 1, medians of 3) on $(machine)."
    ;;
  parts)
    dir=$(mktemp -d)
    echo "| benchmark | median, ms |"
    echo "|---|---|"
    for b in photometric_benchmark fusion_benchmark mapping_benchmark codec_benchmark; do
      "$BIN/$b" --benchmark_repetitions=5 --benchmark_report_aggregates_only=true \
        --benchmark_out="$dir/$b.json" --benchmark_out_format=json > /dev/null
      benchmark_medians "$dir/$b.json"
    done
    rm -rf "$dir"
    echo
    echo "Made by \`scripts/report.sh parts\` (Google Benchmark, 512x512, medians of 5) on $(machine)."
    ;;
  slam-options)
    python3 scripts/slam_options_table.py "$BIN/prism-slam"
    echo
    echo "Made by \`scripts/report.sh slam-options\` (\`prism-slam --print-config\` and the options' comments in core/slam)."
    ;;
  *)
    echo "usage: scripts/report.sh metrics|abuse|slam|generalisation|e2e|speed|parts|slam-options [--write]" >&2
    exit 2
    ;;
esac
