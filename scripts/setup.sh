#!/usr/bin/env bash
# Installs every Debian package CCMD needs (apt-get, non-interactive) and builds it in
# Release with all cores. Safe to run again: packages already present are not reinstalled,
# and the build is incremental.
#
#   scripts/setup.sh               install what is missing, configure, build (build/)
#   scripts/setup.sh --no-build    only install packages
#   CCMD_BUILD_DIR=dir scripts/setup.sh   build somewhere else
#   CCMD_CMAKE_ARGS="-DCCMD_SANITIZE=ON" scripts/setup.sh   extra CMake options
set -euo pipefail

cd "$(dirname "$0")/.."
BUILD_DIR=${CCMD_BUILD_DIR:-build}
DO_BUILD=1
for arg in "$@"; do
  case "$arg" in
    --no-build) DO_BUILD=0 ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "setup.sh: unknown option $arg" >&2; exit 2 ;;
  esac
done

PACKAGES=(
  # toolchain
  build-essential cmake pkg-config git ca-certificates
  # core libraries
  libeigen3-dev libopencv-dev libopencv-contrib-dev libceres-dev libsuitesparse-dev
  libcli11-dev libnanoflann-dev libssl-dev libturbojpeg0-dev libjpeg62-turbo-dev
  # live cameras
  libopenni2-dev libv4l-dev
  # tests and benchmarks (zstd and lz4 are codec-benchmark peers only)
  libgtest-dev libgmock-dev libbenchmark-dev libzstd-dev liblz4-dev
  # instruction counts per front-end stage (scripts/profile_frontend.sh)
  valgrind
  # fuzzing (libFuzzer) and sanitizer runtimes; the format check (scripts/check_format.sh)
  clang libclang-rt-14-dev clang-format
  # shaped evaluation links (ccmd_replay --link): ip netns, veth, tc tbf
  iproute2
  # the server's live map view: HTTP server, three.js served to the browser, and the headless
  # browser its test and benchmark drive
  libcpp-httplib-dev libjs-three chromium
)

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if ((${#missing[@]})); then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null; then SUDO="sudo"; else
      echo "setup.sh: need root (or sudo) to install: ${missing[*]}" >&2; exit 1
    fi
  fi
  echo "== installing ${#missing[@]} packages: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -q
  $SUDO apt-get install -y -q --no-install-recommends "${PACKAGES[@]}"
else
  echo "== all ${#PACKAGES[@]} packages already installed"
fi

if ((DO_BUILD)); then
  JOBS=$(nproc)
  echo "== configuring ($BUILD_DIR, Release)"
  # shellcheck disable=SC2086
  cmake -S . -B "$BUILD_DIR" -DCMAKE_BUILD_TYPE=Release ${CCMD_CMAKE_ARGS:-} >/dev/null
  echo "== building with $JOBS jobs"
  cmake --build "$BUILD_DIR" -j "$JOBS"
  echo "== built: $BUILD_DIR/bin"
fi
