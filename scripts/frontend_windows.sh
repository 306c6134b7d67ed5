#!/usr/bin/env bash
# Judges a front-end change by 13 deterministic runs over parts of one recording
# (docs/benchmarks/frontend.md, "Coarse octaves where their pixels are"): ccmd_frontend_bench
# --synchronous on the whole sequence, backwards, every 2nd and 3rd frame (both ways), four
# windows of two thirds of it and three more starts. On 7-Scenes any change to the front-end
# moves a single run by up to +-1.5 mm; the mean over the windows is what the change does.
# With --compare, a second build's bench runs on the same windows and the table gives both.
#
#   scripts/frontend_windows.sh --dataset DIR --config FILE [--bench BIN] [--compare BIN]
set -euo pipefail

cd "$(dirname "$0")/.."
DATASET=
CONFIG=
BENCH=${CCMD_BUILD_DIR:-build}/bin/ccmd_frontend_bench
COMPARE=
while [ $# -gt 0 ]; do
  case "$1" in
    --dataset) DATASET=$2; shift 2 ;;
    --config) CONFIG=$2; shift 2 ;;
    --bench) BENCH=$2; shift 2 ;;
    --compare) COMPARE=$2; shift 2 ;;
    -h|--help) sed -n '2,9p' "$0"; exit 0 ;;
    *) echo "frontend_windows.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
if [ -z "$DATASET" ] || [ -z "$CONFIG" ]; then
  echo "frontend_windows.sh: --dataset and --config are required (--help)" >&2
  exit 2
fi
for b in "$BENCH" $COMPARE; do
  [ -x "$b" ] || { echo "frontend_windows.sh: no benchmark program at $b (build first)" >&2; exit 2; }
done
[ -f "$DATASET/rgb.txt" ] || { echo "frontend_windows.sh: $DATASET has no rgb.txt" >&2; exit 2; }
N=$(grep -vc '^#' "$DATASET/rgb.txt")
if [ "$N" -lt 60 ]; then
  echo "frontend_windows.sh: $N frames; the windows need at least 60" >&2
  exit 2
fi
W=$((2 * N / 3))
WINDOWS=(
  ""
  "--reverse"
  "--step 2"
  "--step 3"
  "--frames $W"
  "--first $((N / 6)) --frames $W"
  "--first $((N / 4)) --frames $W"
  "--first $((N / 3)) --frames $W"
  "--first $((N / 24)) --frames $((5 * N / 6))"
  "--first $((N / 12))"
  "--first $((N / 2))"
  "--step 2 --reverse"
  "--step 3 --reverse"
)

# ATE RMSE in mm of one synchronous run, or "lost" when the tool printed none.
ate_mm() {
  local bench=$1; shift
  local line
  line=$("$bench" --source "tum:$DATASET" --config "$CONFIG" --synchronous --skip-baseline "$@" \
         2>/dev/null | grep -m1 '^  ATE rmse' || true)
  if [ -z "$line" ]; then echo lost; else echo "$line" | awk '{printf "%.1f", $3 * 1000}'; fi
}

echo "$N frames of $DATASET, config $CONFIG"
if [ -n "$COMPARE" ]; then
  echo "| window | $BENCH mm | $COMPARE mm |"
  echo "|---|---:|---:|"
else
  echo "| window | ATE RMSE mm |"
  echo "|---|---:|"
fi
PAIRS=()  # "a b" per window both runs tracked ("a" alone without --compare)
for w in "${WINDOWS[@]}"; do
  # shellcheck disable=SC2086  # each window is a list of options
  a=$(ate_mm "$BENCH" $w)
  label=${w:-all}
  if [ -n "$COMPARE" ]; then
    # shellcheck disable=SC2086
    b=$(ate_mm "$COMPARE" $w)
    echo "| $label | $a | $b |"
    if [ "$a" != lost ] && [ "$b" != lost ]; then PAIRS+=("$a $b"); fi
  else
    echo "| $label | $a |"
    if [ "$a" != lost ]; then PAIRS+=("$a"); fi
  fi
done
if [ ${#PAIRS[@]} -eq 0 ]; then
  echo "no window was tracked to the end" >&2
  exit 1
fi
printf '%s\n' "${PAIRS[@]}" | awk -v compare="$COMPARE" -v bench="$BENCH" '
  { a += $1; b += $2; lower += ($1 < $2); n++ }
  END {
    if (compare == "") printf "mean over %d windows: %.2f mm\n", n, a / n
    else printf "mean over %d windows: %.2f mm against %.2f mm; %d of them lower with %s\n",
                n, a / n, b / n, lower, bench
  }'
