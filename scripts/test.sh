#!/usr/bin/env bash
# Sets everything up (scripts/setup.sh) and runs the whole test suite with ctest.
#
#   scripts/test.sh              Release build in build/
#   scripts/test.sh --sanitize   AddressSanitizer + UndefinedBehaviorSanitizer build in build-asan/
#   scripts/test.sh --tsan       ThreadSanitizer build in build-tsan/ of the concurrent tests only:
#                                those labelled "concurrent" (ccmd_add_test's CONCURRENT list: stages
#                                and queues, back-end and loop closer, server, agent link and journal,
#                                asynchronous local mapping, dense export, map view, and the programs
#                                they start: ccmd_server, ccmd_agent, ccmd_replay). Builds only those
#                                test binaries and programs; suppressions in tests/tsan.supp (third-
#                                party libraries only); reports in build-tsan/tsan/ and summarised.
#                                The programs use build/'s trained vocabulary when it exists.
#   extra arguments after -- go to ctest, e.g. scripts/test.sh -- -R Codec
set -euo pipefail

cd "$(dirname "$0")/.."
SANITIZE=0
TSAN=0
CTEST_ARGS=()
while (($#)); do
  case "$1" in
    --sanitize) SANITIZE=1 ;;
    --tsan) TSAN=1 ;;
    --) shift; CTEST_ARGS=("$@"); break ;;
    -h|--help) sed -n '2,13p' "$0"; exit 0 ;;
    *) echo "test.sh: unknown option $1" >&2; exit 2 ;;
  esac
  shift
done
if ((SANITIZE && TSAN)); then
  echo "test.sh: --sanitize and --tsan are separate builds; run them one after the other" >&2
  exit 2
fi

if ((TSAN)); then
  # The test binaries that hold concurrent tests; building them builds the programs they start.
  TSAN_TARGETS=(util_test backend_test net_test tracking_test view_test apps_test dense_test bow_test)
  BUILD_DIR=build-tsan
  REPORTS="$PWD/$BUILD_DIR/tsan"
  scripts/setup.sh --no-build
  echo "== configuring ($BUILD_DIR, RelWithDebInfo, ThreadSanitizer)"
  # shellcheck disable=SC2086
  # The vocabulary is not trained again under ThreadSanitizer (minutes): the programs use the
  # one the Release build trained when there is one, else they train online.
  cmake -S . -B "$BUILD_DIR" -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCCMD_SANITIZE_THREAD=ON \
    -DCCMD_BUILD_VOCABULARY=OFF ${CCMD_CMAKE_ARGS:-} >/dev/null
  if [ -z "${CCMD_VOCABULARY:-}" ] && [ -f build/share/ccmd_vocabulary_default.bin ]; then
    export CCMD_VOCABULARY="$PWD/build/share/ccmd_vocabulary_default.bin"
  fi
  JOBS=${CCMD_JOBS:-$(nproc)}
  echo "== building ${TSAN_TARGETS[*]} with $JOBS jobs"
  cmake --build "$BUILD_DIR" -j "$JOBS" --target "${TSAN_TARGETS[@]}"
  rm -rf "$REPORTS" && mkdir -p "$REPORTS"
  # Every process (test binaries and the programs they start) writes its reports to its own
  # file; a report makes the process exit with 66, so the test fails.
  export TSAN_OPTIONS="suppressions=$PWD/tests/tsan.supp:log_path=$REPORTS/report:exitcode=66:second_deadlock_stack=1:history_size=4 ${TSAN_OPTIONS:-}"
  echo "== running the concurrent tests (TSAN_OPTIONS=$TSAN_OPTIONS)"
  status=0
  ctest --test-dir "$BUILD_DIR" --output-on-failure -j "$JOBS" --timeout 1800 -L concurrent \
    "${CTEST_ARGS[@]}" || status=$?
  reports=$(find "$REPORTS" -type f | wc -l)
  warnings=$(cat "$REPORTS"/* 2>/dev/null | grep -c '^WARNING: ThreadSanitizer' || true)
  echo "== ThreadSanitizer: $warnings warnings in $reports report files ($REPORTS)"
  grep -h -A3 '^WARNING: ThreadSanitizer' "$REPORTS"/* 2>/dev/null | head -40 || true
  if ((warnings > 0 && status == 0)); then status=1; fi
  exit "$status"
fi

if ((SANITIZE)); then
  export CCMD_BUILD_DIR=build-asan
  export CCMD_CMAKE_ARGS="-DCCMD_SANITIZE=ON -DCMAKE_BUILD_TYPE=RelWithDebInfo ${CCMD_CMAKE_ARGS:-}"
  export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:abort_on_error=1}
  export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}
fi
scripts/setup.sh
BUILD_DIR=${CCMD_BUILD_DIR:-build}
echo "== running tests"
ctest --test-dir "$BUILD_DIR" --output-on-failure -j "$(nproc)" --timeout 900 "${CTEST_ARGS[@]}"
