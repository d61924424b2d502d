#!/usr/bin/env bash
# The main job: sets up this machine, builds Prism, renders the demo sequence (the first preset)
# with ground truth, runs the dense stage on it (photometric stereo + fusion + ICP map, with
# simulated semi-dense SLAM depth until the SLAM lands) and evaluates the result.
# Output: out/demo/map.ply (the dense reconstruction), out/demo/dense/ (per-keyframe normals,
# depth, clouds), out/demo/sequence/ (TUM layout), out/demo/gt_cloud.ply, out/demo/eval_*.json
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/build.sh
BIN=build/bin
OUT=${OUT:-out/demo}
FRAMES=${FRAMES:-300}
PRESET=$($BIN/prism-synth --list-presets | head -n 1)
rm -rf "$OUT"
mkdir -p "$OUT"
echo "== rendering preset '$PRESET' ($FRAMES frames, 512x512)"
$BIN/prism-synth --preset "$PRESET" --out "$OUT/sequence" --frames "$FRAMES" --gt-cloud "$OUT/gt_cloud.ply" | tee "$OUT/synth.json"
echo "== trajectory: ground truth against itself (all zeros)"
$BIN/prism-eval traj --gt "$OUT/sequence/groundtruth.txt" --est "$OUT/sequence/groundtruth.txt" --align sim3 | tee "$OUT/eval_traj.json"
echo "== normals: ground truth against itself (all zeros)"
$BIN/prism-eval normals --sequence "$OUT/sequence" --normals "$OUT/sequence/normals" | tee "$OUT/eval_normals.json"
echo "== dense stage: photometric stereo + fusion + ICP map (prism-fuse)"
$BIN/prism-fuse --sequence "$OUT/sequence" --out "$OUT/dense" > "$OUT/dense_summary.json"
cp "$OUT/dense/map.ply" "$OUT/map.ply"
head -n 12 "$OUT/dense_summary.json"
echo "== the reconstructed map against the ground-truth object surface"
$BIN/prism-eval cloud --sequence "$OUT/sequence" --cloud "$OUT/map.ply" --object-only | tee "$OUT/eval_map.json"
echo
echo "Done. Open $OUT/map.ply (reconstruction) or $OUT/gt_cloud.ply (ground truth) in any PLY viewer"
echo "(MeshLab, CloudCompare, Open3D); per-keyframe normal maps are in $OUT/dense/normals_vis/."
