#!/usr/bin/env bash
# Sets everything up (scripts/setup.sh) and runs the whole test suite with ctest.
#
#   scripts/test.sh              Release build in build/
#   scripts/test.sh --sanitize   AddressSanitizer + UndefinedBehaviorSanitizer build in build-asan/
#   extra arguments after -- go to ctest, e.g. scripts/test.sh -- -R Codec
set -euo pipefail

cd "$(dirname "$0")/.."
SANITIZE=0
CTEST_ARGS=()
while (($#)); do
  case "$1" in
    --sanitize) SANITIZE=1 ;;
    --) shift; CTEST_ARGS=("$@"); break ;;
    -h|--help) sed -n '2,7p' "$0"; exit 0 ;;
    *) echo "test.sh: unknown option $1" >&2; exit 2 ;;
  esac
  shift
done

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
