#!/usr/bin/env bash
# The main job end to end: set up, generate a synthetic RGB-D sequence with exact ground
# truth, and evaluate it split into segments for three agents.
#
#   scripts/demo.sh [OUT_DIR]      default out/demo
set -euo pipefail

cd "$(dirname "$0")/.."
OUT=${1:-out/demo}
scripts/setup.sh
BIN=${CCMD_BUILD_DIR:-build}/bin

mkdir -p "$OUT"
if [ ! -f "$OUT/sequence/groundtruth.txt" ]; then
  echo "== generating the synthetic sequence (600 frames, 640x480)"
  "$BIN/ccmd_synth" --out "$OUT/sequence" --frames 600 --seed 1
else
  echo "== reusing $OUT/sequence"
fi

echo "== split-replay segments for 3 agents (10% overlap)"
"$BIN/ccmd_eval" split --dataset "$OUT/sequence" --agents 3 | tee "$OUT/segments.txt"

echo
echo "sequence:  $OUT/sequence (TUM layout, groundtruth.txt, surface.ply)"
echo "segments:  $OUT/segments.txt"
