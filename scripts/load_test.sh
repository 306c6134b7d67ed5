#!/usr/bin/env bash
# The server under load (docs/benchmarks/server_load.md). Records keyframe streams once (a
# split replay of the synthetic room: three agents, RGB-D with every keyframe), then starts a
# ccmd_server with a key and runs ccmd_load against it: N agents replaying the streams at a
# keyframe rate for a given time. Writes OUT/load.json, OUT/plots/ and the server's results.
#
#   scripts/load_test.sh [--agents 8] [--rate 5.5] [--seconds 600] [--out runs/load8]
#                        [--streams JOURNAL_DIR] [--server-arg ARG]...
#   scripts/load_test.sh --agents 16 --out runs/load16 --streams runs/load8/record/journal
set -euo pipefail

cd "$(dirname "$0")/.."
AGENTS=8
RATE=5.5
SECONDS_=600
OUT=runs/load
STREAMS=""
SERVER_ARGS=()
while [ $# -gt 0 ]; do
  case "$1" in
    --agents) AGENTS=$2; shift 2 ;;
    --rate) RATE=$2; shift 2 ;;
    --seconds) SECONDS_=$2; shift 2 ;;
    --out) OUT=$2; shift 2 ;;
    --streams) STREAMS=$2; shift 2 ;;
    --server-arg) SERVER_ARGS+=("$2"); shift 2 ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "load_test.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
BIN=${CCMD_BUILD_DIR:-build}/bin
for p in ccmd_synth ccmd_replay ccmd_server ccmd_load; do
  [ -x "$BIN/$p" ] || { echo "load_test.sh: $BIN/$p missing (scripts/setup.sh builds it)" >&2; exit 1; }
done
mkdir -p "$OUT"

if [ -z "$STREAMS" ]; then
  if [ ! -d "$OUT/record/journal" ]; then
    echo "== recording keyframe streams (synthetic room, 600 frames, 3 agents)"
    [ -f "$OUT/sequence/groundtruth.txt" ] || "$BIN/ccmd_synth" --out "$OUT/sequence" --frames 600 --seed 1 > /dev/null
    rm -rf "$OUT/record"
    "$BIN/ccmd_replay" --dataset "$OUT/sequence" --agents 3 --out "$OUT/record" \
      --agent-arg=--rgbd-every-keyframe --agent-arg=--jpeg-quality=95 > "$OUT/record.log"
  fi
  STREAMS="$OUT/record/journal"
fi

KEY="$OUT/key"
[ -f "$KEY" ] || head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n' > "$KEY"
RUN="$OUT/server"
rm -rf "$RUN" "$OUT/plots"
mkdir -p "$RUN"
uptime > "$OUT/load_average.txt"

"$BIN/ccmd_server" --listen 127.0.0.1:0 --journal "$RUN/journal" --out "$RUN/results" --psk-file "$KEY" \
  --stats-interval 1 "${SERVER_ARGS[@]}" > "$RUN/server.out" 2> "$RUN/server.log" &
SERVER=$!
trap 'kill -TERM $SERVER 2>/dev/null || true' EXIT
PORT=""
for _ in $(seq 1 600); do
  PORT=$(sed -n 's/^ccmd_server: listening on .*:\([0-9]*\)$/\1/p' "$RUN/server.out" | head -1)
  [ -n "$PORT" ] && break
  kill -0 $SERVER 2>/dev/null || { echo "load_test.sh: ccmd_server exited; see $RUN/server.log" >&2; exit 1; }
  sleep 0.1
done
[ -n "$PORT" ] || { echo "load_test.sh: ccmd_server did not start" >&2; exit 1; }

echo "== $AGENTS agents at $RATE keyframes/s for $SECONDS_ s against 127.0.0.1:$PORT"
status=0
"$BIN/ccmd_load" --server "127.0.0.1:$PORT" --journals "$STREAMS" --agents "$AGENTS" --rate "$RATE" \
  --seconds "$SECONDS_" --psk-file "$KEY" --server-stats "$RUN/results/server_stats.json" \
  --json "$OUT/load.json" --plots "$OUT/plots" || status=$?
uptime >> "$OUT/load_average.txt"
kill -TERM $SERVER
wait $SERVER || status=$?
trap - EXIT
echo "load:   $OUT/load.json, plots in $OUT/plots"
echo "server: $RUN/results (server_stats.json, map.ply), log $RUN/server.log"
exit $status
