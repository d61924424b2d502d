#!/usr/bin/env bash
# The main job: sets up this machine, builds Prism, renders the demo sequence (the first preset)
# with ground truth, evaluates it and writes a dense ground-truth cloud you can open.
# Output: out/demo/sequence/ (TUM layout), out/demo/gt_cloud.ply, out/demo/eval_*.json
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
echo "== cloud: the ground-truth cloud against the ground-truth surface"
$BIN/prism-eval cloud --sequence "$OUT/sequence" --cloud "$OUT/gt_cloud.ply" | tee "$OUT/eval_cloud.json"
echo
echo "Done. Open $OUT/gt_cloud.ply in any PLY viewer (MeshLab, CloudCompare, Open3D); the sequence is in $OUT/sequence."
