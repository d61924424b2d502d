#!/usr/bin/env bash
# Runs prism-slam on the standard dark-room presets and prints the issue's figures per run and over all
# runs: ATE (% of path), keyframe depth error (median relative, through the trajectory's Sim(3) scale),
# keyframes, lost frames, and the time after the last frame.
#
#   scripts/slam_presets.sh OUT [--seeds "1 2 3"] [--presets "p1 p2"] [--jobs N] [--frames N] [--keep-outputs]
#                           [-- prism-slam args]
#
# --presets takes names, or "standard" (the 9 standard presets, the default), "extra" (the 150-frame
# presets outside them: the uniform sphere's forward start, the robustness sphere) or "all" (both).
#
# Sequences are rendered once into $SEQ_CACHE (default /tmp/prism-presets) and reused. Each run writes
# OUT/<preset>-<seed>/ (prism-slam's outputs) and OUT/results.tsv; the table is printed at the end.
# The keyframe depth maps and semidense.ply (about 50 MB per run at 512x512) are deleted once a run is
# scored unless --keep-outputs is given; summary.json, trajectory.txt and the rest stay.
# Needs a build (BUILD_DIR, default build).
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${BUILD_DIR:-build}
SEQ_CACHE=${SEQ_CACHE:-/tmp/prism-presets}
if [ $# -lt 1 ]; then
  sed -n '2,16p' "$0"
  exit 2
fi
OUT=$1
shift
SEEDS="1 2 3 4 5 6"
STANDARD="bunny-multicolor-forward sphere-multicolor-sideways dragon-multicolor-sideways sphere-uniform-sideways \
relief-uniform-sideways boxes-multicolor-forward bunny-uniform-sideways armadillo-textured-forward torus-textured-forward"
EXTRA="sphere-uniform-forward sphere-robust-sideways"
PRESETS=$STANDARD
JOBS=2
FRAMES=150
KEEP_OUTPUTS=0
while [ $# -gt 0 ]; do
  case "$1" in
    --seeds) SEEDS=$2; shift 2 ;;
    --presets) PRESETS=$2; shift 2 ;;
    --jobs) JOBS=$2; shift 2 ;;
    --frames) FRAMES=$2; shift 2 ;;
    --keep-outputs) KEEP_OUTPUTS=1; shift ;;
    --) shift; break ;;
    *) echo "slam_presets.sh: unknown argument $1" >&2; exit 2 ;;
  esac
done
SLAM_ARGS=("$@")
case "$PRESETS" in
  standard) PRESETS=$STANDARD ;;
  extra) PRESETS=$EXTRA ;;
  all) PRESETS="$STANDARD $EXTRA" ;;
esac
mkdir -p "$OUT" "$SEQ_CACHE"
BIN="$BUILD_DIR/bin"

run_one() {
  local preset=$1 seed=$2
  local seq="$SEQ_CACHE/$preset-$seed-$FRAMES"
  if [ ! -f "$seq/groundtruth.txt" ]; then
    "$BIN/prism-synth" --preset "$preset" --frames "$FRAMES" --seed "$seed" --threads 1 --out "$seq.tmp" >/dev/null
    rm -rf "$seq" && mv "$seq.tmp" "$seq"
  fi
  local out="$OUT/$preset-$seed"
  "$BIN/prism-slam" --sequence "$seq" --out "$out" --threads 1 "${SLAM_ARGS[@]}" >"$out.log" 2>&1 ||
    echo "slam_presets.sh: prism-slam failed on $preset seed $seed (see $out.log)" >&2
  if [ "$KEEP_OUTPUTS" = 0 ]; then
    rm -f "$out"/keyframes/*.tiff "$out/semidense.ply"
  fi
}

jobs_running=0
for seed in $SEEDS; do
  for preset in $PRESETS; do
    run_one "$preset" "$seed" &
    jobs_running=$((jobs_running + 1))
    if [ "$jobs_running" -ge "$JOBS" ]; then
      wait -n
      jobs_running=$((jobs_running - 1))
    fi
  done
done
wait

python3 - "$OUT" "$SEEDS" "$PRESETS" <<'EOF'
import json, math, os, sys
out, seeds, presets = sys.argv[1], sys.argv[2].split(), sys.argv[3].split()
rows = []
for p in presets:
    for s in seeds:
        path = os.path.join(out, f"{p}-{s}", "summary.json")
        try:
            d = json.load(open(path))
        except (OSError, ValueError):
            rows.append((p, s, None))
            continue
        rows.append((p, s, d))
with open(os.path.join(out, "results.tsv"), "w") as f:
    f.write("preset\tseed\tate_percent\tdepth_median_rel\tkeyframes\tlost\trefinement_ms\n")
    for p, s, d in rows:
        if d is None:
            f.write(f"{p}\t{s}\tnan\tnan\t0\t0\t0\n")
            continue
        f.write(f"{p}\t{s}\t{d.get('ate_percent_of_path', float('nan')):.4f}\t"
                f"{d.get('depth_median_rel_error', float('nan')):.5f}\t{d.get('keyframes', 0)}\t"
                f"{d.get('lost_frames', 0)}\t{d.get('depth_refinement_ms', 0):.0f}\n")
print(f"{'preset':32s} " + " ".join(f"{'s' + s:>14s}" for s in seeds) + "   (ATE % / depth %)")
ates, depths = [], []
for p in presets:
    cells = []
    for s in seeds:
        d = next(dd for pp, ss, dd in rows if pp == p and ss == s)
        if d is None or "ate_percent_of_path" not in d:
            cells.append(f"{'failed':>14s}")
            continue
        a, z = d["ate_percent_of_path"], 100 * d.get("depth_median_rel_error", float("nan"))
        ates.append(a)
        depths.append(z)
        cells.append(f"{a:6.2f} /{z:6.2f}")
    print(f"{p:32s} " + " ".join(cells))
n = len(ates)
if n:
    geo = math.exp(sum(math.log(max(a, 1e-6)) for a in ates) / n)
    med = sorted(depths)[n // 2] if n % 2 else 0.5 * (sorted(depths)[n // 2 - 1] + sorted(depths)[n // 2])
    print(f"runs {n}: within 1% ATE {sum(a <= 1 for a in ates)}, geometric mean ATE {geo:.3f}%, "
          f"depth within 3% {sum(z <= 3 for z in depths)}, within 5% {sum(z <= 5 for z in depths)}, "
          f"median depth {med:.2f}%")
EOF
