#!/usr/bin/env bash
# Builds the libFuzzer targets of tests/fuzz/ with clang (AddressSanitizer and
# UndefinedBehaviorSanitizer, every library instrumented for coverage) in a separate build
# folder and runs each for a bounded time, starting from valid seed inputs.
#
#   scripts/fuzz.sh [seconds per target]     (default 60)
#   CCMD_FUZZ_RUNS=10000000 scripts/fuzz.sh   (a number of inputs per target instead of a time)
#   CCMD_FUZZ_BUILD_DIR=dir scripts/fuzz.sh  (default build-fuzz)
#   CCMD_FUZZ_TARGETS="depth lz77" scripts/fuzz.sh
#
# A target with a dictionary (tests/fuzz/<target>.dict: tokens such as config keys) is given
# it. A target fails on a crash, a sanitizer report, an input taking more than 10 s, or an
# allocation above 512 MB. The log of each run is kept in the build folder; the last lines
# say how many inputs were executed.
set -euo pipefail

cd "$(dirname "$0")/.."
SECONDS_EACH=${1:-60}
BUILD_DIR=${CCMD_FUZZ_BUILD_DIR:-build-fuzz}
TARGETS=${CCMD_FUZZ_TARGETS:-frame keyframe depth rgbd lz77 session auth config trajectory ply}
JOBS=$(( $(nproc) < 2 ? $(nproc) : 2 ))

if ! command -v clang++ >/dev/null; then
  echo "fuzz.sh: clang++ is needed (scripts/setup.sh installs it)" >&2
  exit 1
fi

SANITIZE="-fsanitize=fuzzer-no-link,address,undefined -fno-sanitize-recover=undefined -fno-omit-frame-pointer"
echo "== configuring $BUILD_DIR (clang, libFuzzer, ASan, UBSan)"
CC=clang CXX=clang++ cmake -S . -B "$BUILD_DIR" -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCCMD_FUZZ=ON -DCCMD_BUILD_BENCHMARKS=OFF \
  -DCMAKE_C_FLAGS="$SANITIZE" -DCMAKE_CXX_FLAGS="$SANITIZE" \
  -DCMAKE_EXE_LINKER_FLAGS="-fsanitize=address,undefined" >/dev/null

build_targets=()
for t in $TARGETS; do build_targets+=("fuzz_$t" "fuzz_${t}_driver"); done
echo "== building ${build_targets[*]}"
cmake --build "$BUILD_DIR" -j "$JOBS" --target "${build_targets[@]}" >/dev/null

status=0
for t in $TARGETS; do
  corpus="$BUILD_DIR/fuzz_corpus/$t"
  log="$BUILD_DIR/fuzz_$t.log"
  mkdir -p "$corpus"
  "$BUILD_DIR/tests/fuzz_${t}_driver" --write-seeds "$corpus"
  if [ -n "${CCMD_FUZZ_RUNS:-}" ]; then
    budget="-runs=$CCMD_FUZZ_RUNS"
    echo "== fuzz_$t for $CCMD_FUZZ_RUNS inputs"
  else
    budget="-max_total_time=$SECONDS_EACH"
    echo "== fuzz_$t for ${SECONDS_EACH}s"
  fi
  dict=()
  if [ -f "tests/fuzz/$t.dict" ]; then dict=("-dict=tests/fuzz/$t.dict"); fi
  if "$BUILD_DIR/tests/fuzz_$t" "$budget" ${dict[@]+"${dict[@]}"} -timeout=10 \
      -rss_limit_mb=2048 -malloc_limit_mb=512 -print_final_stats=1 \
      -artifact_prefix="$BUILD_DIR/fuzz_${t}_" "$corpus" >"$log" 2>&1; then
    runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo "?")
    echo "   ok: $runs inputs executed, no failure (log: $log)"
  else
    echo "   FAILED (log: $log):" >&2
    grep -E "ERROR|SUMMARY|Test unit written" "$log" | head -5 >&2 || true
    status=1
  fi
done
exit $status
