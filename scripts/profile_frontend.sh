#!/usr/bin/env bash
# Instruction counts of the agent front-end per stage, for a fixed number of frames: runs
# ccmd_frontend_bench --stage frontend --synchronous under callgrind (local mapping in the
# tracking thread, so every run executes the same instructions) and reads each stage's
# inclusive count. Counts are repeatable on a machine shared with other work, where times are
# not; compare changes by them.
#
#   scripts/profile_frontend.sh                      7-Scenes redkitchen, 100 frames
#   scripts/profile_frontend.sh --frames 60 --source tum:DIR --config configs/icl_nuim.yaml
#   scripts/profile_frontend.sh --bin DIR            another build's binaries (e.g. a baseline)
#   scripts/profile_frontend.sh --keep FILE          also keep the callgrind output (and FILE.json)
#   scripts/profile_frontend.sh --from FILE          only report on a kept output
#
# Needs valgrind (scripts/setup.sh installs it). 100 frames take a few minutes.
set -euo pipefail

cd "$(dirname "$0")/.."
FRAMES=100
SOURCE=tum:../shared/datasets/7scenes_redkitchen_0000_0599
CONFIG=configs/7scenes.yaml
BIN=build/bin
KEEP=""
FROM=""
while (($#)); do
  case "$1" in
    --frames) FRAMES=$2; shift ;;
    --source) SOURCE=$2; shift ;;
    --config) CONFIG=$2; shift ;;
    --bin) BIN=$2; shift ;;
    --keep) KEEP=$2; shift ;;
    --from) FROM=$2; shift ;;
    -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
    *) echo "profile_frontend.sh: unknown option $1" >&2; exit 2 ;;
  esac
  shift
done
if ! command -v valgrind >/dev/null || ! command -v callgrind_annotate >/dev/null; then
  echo "profile_frontend.sh: valgrind is needed (scripts/setup.sh installs it)" >&2
  exit 1
fi

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
if [ -n "$FROM" ]; then
  cp "$FROM" "$work/callgrind.out"
  cp "$FROM.json" "$work/result.json"
else
  config_args=()
  [ -n "$CONFIG" ] && config_args=(--config "$CONFIG")
  # A build from before --stage existed (a baseline) runs the same front-end with --skip-baseline.
  stage_args=(--stage frontend)
  "$BIN/ccmd_frontend_bench" --help | grep -q -- --stage || stage_args=(--skip-baseline)
  echo "== callgrind: $BIN/ccmd_frontend_bench ${stage_args[*]} --synchronous --frames $FRAMES --source $SOURCE ${config_args[*]}"
  valgrind --tool=callgrind --callgrind-out-file="$work/callgrind.out" \
    "$BIN/ccmd_frontend_bench" "${stage_args[@]}" --synchronous --frames "$FRAMES" --source "$SOURCE" \
    "${config_args[@]}" --json "$work/result.json" >"$work/bench.log" 2>&1 ||
    { cat "$work/bench.log" >&2; exit 1; }
  if [ -n "$KEEP" ]; then
    cp "$work/callgrind.out" "$KEEP"
    cp "$work/result.json" "$KEEP.json"
  fi
fi
callgrind_annotate --inclusive=yes --threshold=100 "$work/callgrind.out" >"$work/annotate.txt" 2>/dev/null

# Inclusive instructions of the first function whose name starts with $1 (0 if absent).
count() {
  grep -F "$1" "$work/annotate.txt" | head -1 | awk '{gsub(",", "", $1); printf "%.0f\n", $1}' || echo 0
}
# A number from the bench's JSON.
field() {
  { grep -E "^  \"$1\":" "$work/result.json" || true; } | head -1 | sed -E 's/.*: *([0-9.eE+-]+).*/\1/'
}

frames=$(field frames)
keyframes=$(field mapping_keyframes)
ba_runs=$(field local_ba_runs)
# A build older than these counters: with synchronous mapping every keyframe is mapped and
# gets its local BA.
[ -n "$keyframes" ] || keyframes=$(field keyframes)
[ -n "$ba_runs" ] || ba_runs=$keyframes
make_frame=$(count "ccmd::MakeFrame(")
extract=$(count "ccmd::OrbExtractor::Extract(")
track=$(count "ccmd::Tracker::Track(")
pose=$(count "ccmd::OptimizePose(")
mapping=$(count "ccmd::LocalMapper::Process(")
ba=$(count "ccmd::LocalMapper::LocalBundleAdjustment(")
align=$(count "ccmd::LocalMapper::AlignWithNeighbours(")

awk -v frames="$frames" -v keyframes="$keyframes" -v ba_runs="$ba_runs" -v make_frame="$make_frame" \
    -v extract="$extract" -v track="$track" -v pose="$pose" -v mapping="$mapping" -v ba="$ba" \
    -v align="$align" 'BEGIN {
  printf "%d frames, %d keyframes, %d local BA runs (synchronous mapping)\n", frames, keyframes, ba_runs
  printf "%-44s %16s %14s\n", "stage", "instructions", "millions per"
  row("extraction (ORB + keypoint depth) / frame", make_frame, frames)
  row("  of which ORB extraction / frame", extract, frames)
  row("tracking / frame", track - make_frame, frames)
  row("  of which pose optimisation / frame", pose, frames)
  row("extraction + tracking / frame", track, frames)
  row("local mapping / keyframe", mapping, keyframes)
  row("  of which local BA / run", ba, ba_runs)
  row("  of which depth alignment / keyframe", align, keyframes)
  row("whole front-end / frame", track + mapping, frames)
}
function row(name, total, n) {
  printf "%-44s %16.0f %14.2f\n", name, total, (n > 0 ? total / n / 1e6 : 0)
}'
