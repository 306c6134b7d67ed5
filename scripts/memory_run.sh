#!/usr/bin/env bash
# The server's memory over a long run in one room (docs/benchmarks/server_load.md): one agent
# on the synthetic room circled for --frames frames, against the first --short frames of the
# same sequence (the same seed renders the same frames). Prints the server's peak memory of
# both, their ratio (the plateau), keyframes, and reconstruction error and completeness;
# each run's report, results.json (server_memory: memory against keyframes) and
# plots/server_memory.png are in OUT/run<frames>/.
#
#   scripts/memory_run.sh [--frames 3000] [--short 1000] [--seed 3] [--out runs/memory]
#                         [--replay-arg ARG]...
set -euo pipefail

cd "$(dirname "$0")/.."
FRAMES=3000
SHORT=1000
SEED=3
OUT=runs/memory
REPLAY_ARGS=()
while [ $# -gt 0 ]; do
  case "$1" in
    --frames) FRAMES=$2; shift 2 ;;
    --short) SHORT=$2; shift 2 ;;
    --seed) SEED=$2; shift 2 ;;
    --out) OUT=$2; shift 2 ;;
    --replay-arg) REPLAY_ARGS+=("$2"); shift 2 ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "memory_run.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
BIN=${CCMD_BUILD_DIR:-build}/bin
for p in ccmd_synth ccmd_replay ccmd_server ccmd_agent; do
  [ -x "$BIN/$p" ] || { echo "memory_run.sh: $BIN/$p missing (scripts/setup.sh builds it)" >&2; exit 1; }
done
mkdir -p "$OUT"
uptime > "$OUT/load_average.txt"

# A number from a results.json ("" when absent).
figure() { grep -o "\"$2\": *[-0-9.e+]*" "$1" | head -1 | sed 's/.*: *//'; }

for n in "$SHORT" "$FRAMES"; do
  seq="$OUT/seq$n"
  [ -f "$seq/groundtruth.txt" ] || "$BIN/ccmd_synth" --out "$seq" --frames "$n" --seed "$SEED" > /dev/null
  echo "== one agent, $n frames"
  rm -rf "$OUT/run$n"
  "$BIN/ccmd_replay" --dataset "$seq" --agents 1 --out "$OUT/run$n" "${REPLAY_ARGS[@]}" > "$OUT/run$n.log"
done
uptime >> "$OUT/load_average.txt"

short="$OUT/run$SHORT/results.json"
long="$OUT/run$FRAMES/results.json"
echo "| frames | keyframes | server peak MB | recon mean mm | completeness |"
echo "|---|---|---|---|---|"
for r in "$short" "$long"; do
  n=$(basename "$(dirname "$r")" | sed 's/run//')
  printf '| %s | %s | %s | %s | %s |\n' "$n" "$(figure "$r" fused_keyframes)" "$(figure "$r" server_peak_rss_mb)" \
    "$(awk -v m="$(figure "$r" recon_mean_m)" 'BEGIN { printf "%.2f", m * 1000 }')" "$(figure "$r" recon_completeness)"
done
awk -v a="$(figure "$short" server_peak_rss_mb)" -v b="$(figure "$long" server_peak_rss_mb)" \
  'BEGIN { printf "peak memory, %s frames / %s frames: %.2f (target <= 1.25)\n", "'"$FRAMES"'", "'"$SHORT"'", b / a }'
