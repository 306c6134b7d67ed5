#!/usr/bin/env bash
# Speed and accuracy of the agent front-end on each shared sequence, frames in memory: frames
# per second from the first frame until the mapper's last keyframe, CPU cores used, CPU time
# per frame, the per-stage split and the ATE. With --baseline DIR the same runs are made with
# another build's binaries (e.g. main before a change), alternating with this build's, so that
# before and after share the machine's load. Instruction counts per stage:
# scripts/profile_frontend.sh.
#
#   scripts/bench_frontend_speed.sh                          this build, one run per sequence
#   scripts/bench_frontend_speed.sh --baseline DIR --runs 2  before/after, two runs each
#   scripts/bench_frontend_speed.sh --cpu-budget 0           no CPU budget (default: 1 core, as ccmd_agent)
#   scripts/bench_frontend_speed.sh --only 7scenes           one sequence (7scenes, icl, synthetic, tum)
#   scripts/bench_frontend_speed.sh --keep DIR               keep each run's JSON and log in DIR
#   scripts/bench_frontend_speed.sh --agent                  ccmd_agent --offline instead: frames
#                                                            read from disk, the process as users run it
#
# A build without --cpu-budget (older than it) runs without one. Sequences missing from
# ../shared/datasets are skipped with a notice.
set -euo pipefail

cd "$(dirname "$0")/.."
BIN=build/bin
BASELINE=""
RUNS=1
BUDGET=1.0
ONLY=""
KEEP=""
AGENT=""
DATA=../shared/datasets
while (($#)); do
  case "$1" in
    --bin) BIN=$2; shift ;;
    --baseline) BASELINE=$2; shift ;;
    --runs) RUNS=$2; shift ;;
    --cpu-budget) BUDGET=$2; shift ;;
    --only) ONLY=$2; shift ;;
    --keep) KEEP=$2; shift ;;
    --agent) AGENT=1 ;;
    -h|--help) sed -n '2,19p' "$0"; exit 0 ;;
    *) echo "bench_frontend_speed.sh: unknown option $1" >&2; exit 2 ;;
  esac
  shift
done
program=ccmd_frontend_bench
[ -n "$AGENT" ] && program=ccmd_agent
for dir in "$BIN" $BASELINE; do
  [ -x "$dir/$program" ] || { echo "bench_frontend_speed.sh: no $dir/$program" >&2; exit 1; }
done

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
[ -n "$KEEP" ] && mkdir -p "$KEEP"

# name|source|config
sequences=(
  "7scenes|tum:$DATA/7scenes_redkitchen_0000_0599|configs/7scenes.yaml"
  "icl|tum:$DATA/iclnuim_office_traj0_0000_0449|configs/icl_nuim.yaml"
  "synthetic|synth:frames=600,seed=1|"
  "tum|tum:$DATA/tum_fr1_desk_9|configs/tum_fr1.yaml"
)

# A number from a bench JSON (top-level field), or "-".
field() {
  local v
  v=$(grep -E "^  \"$2\":" "$1" | head -1 | sed -E 's/.*: *([0-9.eE+-]+).*/\1/')
  echo "${v:--}"
}

printf "%-9s %-8s %3s %6s %5s %4s %6s %5s %7s %7s %7s %7s %8s %8s %5s %8s\n" sequence build run frames track kf \
  fps cores cpu_ms extr_ms track_ms ext+trk map_ms ba_ms ba_n ate_mm
for entry in "${sequences[@]}"; do
  IFS='|' read -r name source config <<<"$entry"
  [ -n "$ONLY" ] && [ "$ONLY" != "$name" ] && continue
  if [[ $source == tum:* ]] && [ ! -d "${source#tum:}" ]; then
    echo "skipping $name: ${source#tum:} not found"
    continue
  fi
  for ((run = 1; run <= RUNS; run++)); do
    builds=(after)
    [ -n "$BASELINE" ] && builds=(before after)
    for build in "${builds[@]}"; do
      bin=$BIN
      [ "$build" = before ] && bin=$BASELINE
      if [ -n "$AGENT" ]; then
        args=(--source "$source" --offline --stats "$work/r.json" --trajectory "$work/t.txt")
      else
        args=(--source "$source" --skip-baseline --json "$work/r.json")
      fi
      [ -n "$config" ] && args+=(--config "$config")
      "$bin/$program" --help | grep -q -- --cpu-budget && args+=(--cpu-budget "$BUDGET")
      "$bin/$program" "${args[@]}" >"$work/r.log" 2>&1 ||
        { echo "$name $build run $run failed:" >&2; cat "$work/r.log" >&2; exit 1; }
      ate_json=$work/r.json
      if [ -n "$AGENT" ]; then  # the agent does not evaluate itself: its ATE where there is a ground truth
        ate_json=$work/ate.json
        rm -f "$ate_json"
        if [ -f "${source#tum:}/groundtruth.txt" ]; then
          "$bin/ccmd_eval" ate --gt "${source#tum:}/groundtruth.txt" --est "$work/t.txt" \
            --json "$ate_json" >/dev/null 2>&1 || true
        fi
        [ -f "$ate_json" ] || echo '{}' >"$ate_json"
      fi
      if [ -n "$KEEP" ]; then
        cp "$work/r.json" "$KEEP/$name-$build-$run.json"
        cp "$work/r.log" "$KEEP/$name-$build-$run.log"
      fi
      j=$work/r.json
      awk -v name="$name" -v build="$build" -v run="$run" -v frames="$(field "$j" frames)" \
        -v tracked="$(field "$j" tracked_frames)" -v kf="$(field "$j" keyframes)" -v fps="$(field "$j" fps)" \
        -v cores="$(field "$j" cpu_cores_used)" -v extract="$(field "$j" extract_ms_mean)" \
        -v track="$(field "$j" track_ms_mean)" -v map="$(field "$j" mapping_ms_mean)" \
        -v ba="$(field "$j" local_ba_ms_mean)" -v ba_n="$(field "$j" local_ba_runs)" \
        -v ate="$(field "$ate_json" ate_rmse_m)" 'BEGIN {
        cpu = (fps > 0) ? 1000 * cores / fps : 0  # CPU milliseconds per frame, all threads
        printf "%-9s %-8s %3d %6d %5d %4d %6.1f %5.2f %7.1f %7.2f %7.2f %7.2f %8.1f %8.1f %5s %8s\n",
          name, build, run, frames, tracked, kf, fps, cores, cpu, extract, track, extract + track, map, ba, ba_n,
          (ate == "-") ? "-" : sprintf("%.2f", 1000 * ate)
      }'
    done
  done
done
echo "cpu_ms: the process's CPU time per frame (all threads); 1000 / cpu_ms is the frame rate one core sustains."
echo "ba_n: local BA runs (\"-\": a build that does not report them). load: $(cut -d' ' -f1-3 /proc/loadavg)"
