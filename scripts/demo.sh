#!/usr/bin/env bash
# The main job: sets up this machine, builds Prism, renders the demo sequence (the first preset,
# with ground truth), starts prism-server, streams the sequence to it with prism-client (the real
# round trip: PNG frames up, poses and Draco map chunks down), then scores what came back against
# the ground truth and renders a picture of the map.
# Output (out/demo/): map.ply (the dense map the server streamed back), map.png (a picture of it),
# trajectory.txt (TUM, every tracked frame), chunks/*.drc (the Draco chunks as received),
# eval_traj.json / eval_map.json (against ground truth), sequence/ (the rendered input, TUM layout),
# gt_cloud.ply (the true surface), server.log.
# Environment: FRAMES (default 300), OUT (default out/demo), REFERENCE=1 also runs the dense stage
# alone with ground-truth poses (prism-fuse) into $OUT/reference/ for comparison, VIEW=HOST:PORT where
# prism-client serves the live 3D view while it streams (default 127.0.0.1 on a free port; the URL is
# printed; VIEW=off for none).
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
$BIN/prism-synth --preset "$PRESET" --out "$OUT/sequence" --frames "$FRAMES" --gt-cloud "$OUT/gt_cloud.ply" > "$OUT/synth.json"

echo "== starting prism-server on a free port"
$BIN/prism-server --bind 'tcp://127.0.0.1:*' --data-dir "$OUT/server-data" --input-policy upload \
  --keyframe-queue 64 > "$OUT/server.json" 2> "$OUT/server.log" &
SERVER_PID=$!
trap 'kill -TERM $SERVER_PID 2>/dev/null || true' EXIT
for _ in $(seq 100); do [ -s "$OUT/server.json" ] && break; sleep 0.1; done
ENDPOINT=$(sed -n 's/.*"endpoint": "\([^"]*\)".*/\1/p' "$OUT/server.json")
[ -n "$ENDPOINT" ] || { echo "prism-server did not start; see $OUT/server.log"; exit 1; }
echo "   listening on $ENDPOINT"

echo "== streaming the sequence with prism-client"
VIEW=${VIEW:-127.0.0.1:0}
VIEW_FLAGS=()
if [ "$VIEW" != off ]; then
  VIEW_FLAGS=(--view "$VIEW")
  echo "   watch the map grow in a browser at the 'live view' URL prism-client prints below"
fi
$BIN/prism-client stream --server "$ENDPOINT" --sequence "$OUT/sequence" --out "$OUT" "${VIEW_FLAGS[@]}" \
  | tee "$OUT/client_summary.json"
kill -TERM $SERVER_PID
wait $SERVER_PID || true
trap - EXIT

echo "== trajectory against ground truth (Sim(3)-aligned)"
$BIN/prism-eval traj --gt "$OUT/sequence/groundtruth.txt" --est "$OUT/trajectory.txt" --align sim3 | tee "$OUT/eval_traj.json"
echo "== the streamed map against the ground-truth object surface"
$BIN/prism-eval cloud --sequence "$OUT/sequence" --cloud "$OUT/map.ply" --align-trajectory "$OUT/trajectory.txt" --object-only | tee "$OUT/eval_map.json"
$BIN/prism-preview --cloud "$OUT/map.ply" --trajectory "$OUT/trajectory.txt" --out "$OUT/map.png" > /dev/null

if [ "${REFERENCE:-0}" = 1 ]; then
  echo "== reference: the dense stage alone with ground-truth poses and simulated SLAM depth (prism-fuse)"
  $BIN/prism-fuse --sequence "$OUT/sequence" --out "$OUT/reference" > "$OUT/reference_summary.json"
  $BIN/prism-eval cloud --sequence "$OUT/sequence" --cloud "$OUT/reference/map.ply" --object-only | tee "$OUT/eval_reference_map.json"
fi
echo
echo "Done. Open $OUT/map.ply in any PLY viewer (MeshLab, CloudCompare, Open3D) or look at $OUT/map.png;"
echo "$OUT/gt_cloud.ply is the true surface. In a browser: $BIN/prism-client view $OUT (it prints the URL)."
