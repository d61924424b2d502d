#!/usr/bin/env bash
# prism-calibrate on boards rendered with known truth (prism-synth --charuco-board: the default rig,
# 640x480 unless --size, 10 intrinsics views and 8 poses per light folder unless --light-views): per seed and lens, the focal-length
# error (%), the worst light-position error (mm) beside the largest reported standard deviation, the
# worst intensity error (%) and the worst crosstalk error; then the maxima.
#
#   scripts/calibration_accuracy.sh [--seeds "1 2 3"] [--size WxH] [--light-views N] [--lenses "pinhole barrel"]
#
# Needs prism-synth and prism-calibrate in BUILD_DIR (default build).
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${BUILD_DIR:-build}
seeds="1 2 3 4 5 6 7 8 9 10"
size=640x480
light_views=8
lenses="pinhole barrel"
while [[ $# -gt 0 ]]; do
  case $1 in
    --seeds) seeds=$2; shift 2 ;;
    --size) size=$2; shift 2 ;;
    --light-views) light_views=$2; shift 2 ;;
    --lenses) lenses=$2; shift 2 ;;
    *) echo "usage: scripts/calibration_accuracy.sh [--seeds \"1 2 3\"] [--size WxH] [--light-views N] [--lenses \"pinhole barrel\"]" >&2; exit 2 ;;
  esac
done
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
echo "# $(date -u +%F) $(uname -n) $(nproc) cores, $size, $light_views poses per light"
printf "lens\tseed\tfocal_%%\tposition_mm\tposition_std_mm\tintensity_%%\tcrosstalk\n"
for lens in $lenses; do
  for seed in $seeds; do
    args=()
    if [[ $lens == barrel ]]; then args=(--distortion -0.25,0.08,0,0,0); fi
    "$BUILD_DIR/bin/prism-synth" --charuco-board "$work/$seed" --size "$size" --supersampling 2 --seed "$seed" \
        --light-views "$light_views" "${args[@]}" > /dev/null
    "$BUILD_DIR/bin/prism-calibrate" "$work/$seed" --white-albedo 0.85 > "$work/report.json"
    python3 - "$work/report.json" "$work/$seed/truth.yaml" "$lens" "$seed" <<'PY'
import json, math, re, sys
r = json.load(open(sys.argv[1]))
truth = open(sys.argv[2]).read().replace("\n", " ")
def numbers(key):
    return [float(x) for x in re.findall(r"[-+0-9.e]+", re.search(key + r".*?\[([^\]]*)\]", truth).group(1))]
fx = float(re.search(r"fx: ([-+0-9.e]+)", truth).group(1))
crosstalk = numbers(r"crosstalk:.*?data:")
positions = [numbers(r"name: " + n + r".*?position:") for n in ("red", "green", "blue")]
intensities = [float(x) for x in re.findall(r"intensity: ([-+0-9.e]+)", truth)]
i = r["intrinsics"]
focal = 100 * max(abs(i["fx"] / fx - 1), abs(i["fy"] / fx - 1))
position = max(1000 * math.dist(l["position_m"], p) for l, p in zip(r["lights"], positions))
std = max(max(l["position_std_mm"]) for l in r["lights"])
intensity = max(100 * abs(l["intensity"] / t - 1) for l, t in zip(r["lights"], intensities))
xt = max(abs(r["crosstalk"][a][b] - crosstalk[3 * a + b]) for a in range(3) for b in range(3))
print(f"{sys.argv[3]}\t{sys.argv[4]}\t{focal:.3f}\t{position:.2f}\t{std:.2f}\t{intensity:.2f}\t{xt:.4f}")
PY
    rm -rf "${work:?}/$seed"
  done
done | tee "$work/table.tsv"
awk -F'\t' '{for (c = 3; c <= 7; ++c) if ($c > m[c]) m[c] = $c}
  END {printf "max\t\t%.3f\t%.2f\t%.2f\t%.2f\t%.4f\n", m[3], m[4], m[5], m[6], m[7]}' "$work/table.tsv"
