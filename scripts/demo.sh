#!/usr/bin/env bash
# The main job end to end: set up, generate a synthetic RGB-D sequence with exact ground truth
# (a textured room, 600 frames), split it into three overlapping segments, and replay them with
# three agents talking to one server over TCP on loopback. The server fuses the three maps,
# builds the dense point cloud, and the report compares everything with the ground truth.
#
#   scripts/demo.sh [OUT_DIR [ccmd_replay options...]]   default out/demo
#   scripts/demo.sh out/demo --ablation    also the r / keyframe-selection grid (six runs, ~4 min)
set -euo pipefail

cd "$(dirname "$0")/.."
OUT=${1:-out/demo}
shift || true
scripts/setup.sh
BIN=${CCMD_BUILD_DIR:-build}/bin

mkdir -p "$OUT"
# A sequence is reused only if the generator has not been rebuilt since: a changed renderer
# would leave images and ground-truth surface that no longer match the current code.
if [ ! -f "$OUT/sequence/groundtruth.txt" ] || [ "$BIN/ccmd_synth" -nt "$OUT/sequence/surface.ply" ]; then
  echo "== generating the synthetic sequence (600 frames, 640x480)"
  rm -rf "$OUT/sequence"
  "$BIN/ccmd_synth" --out "$OUT/sequence" --frames 600 --seed 1
else
  echo "== reusing $OUT/sequence"
fi

RUN="$OUT/run-$(date +%Y%m%d-%H%M%S)"
echo "== split replay: 3 agents and a server over TCP"
"$BIN/ccmd_replay" --dataset "$OUT/sequence" --agents 3 --out "$RUN" "$@"

echo
echo "report:      $RUN/report.md"
echo "results:     $RUN/results.json"
echo "dense map:   $RUN/map.ply (pictures in the report: $RUN/plots/map_top.png, map_view.png)"
echo "trajectories $RUN/trajectory_fused.txt, trajectory_agent1..3.txt (TUM format)"
