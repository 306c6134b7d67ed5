#!/usr/bin/env bash
# Downloads TUM RGB-D sequences, verifies them and unpacks them where ccmd reads them:
#   datasets/fetch_tum.sh [--dest DIR] [SEQUENCE ...]
# SEQUENCE is a TUM name such as freiburg1_desk (default: the paper's freiburg1_desk,
# freiburg2_xyz, freiburg3_long_office_household, freiburg2_desk, freiburg2_360_hemisphere).
# Each becomes DIR/rgbd_dataset_<SEQUENCE>/ with rgb/, depth/, rgb.txt, depth.txt,
# groundtruth.txt: pass it to ccmd as tum:DIR/rgbd_dataset_<SEQUENCE> (the camera config
# tum_fr1/2/3.yaml is picked from the name).
set -euo pipefail
SCRIPT_DIR=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=fetch_common.sh
. "$SCRIPT_DIR/fetch_common.sh"

DEST=data/tum
SEQUENCES=()
while (($#)); do
  case "$1" in
    --dest) DEST=$2; shift ;;
    -h|--help) sed -n '2,9p' "$0"; exit 0 ;;
    *) SEQUENCES+=("$1") ;;
  esac
  shift
done
((${#SEQUENCES[@]})) || SEQUENCES=(freiburg1_desk freiburg2_xyz freiburg3_long_office_household
                                  freiburg2_desk freiburg2_360_hemisphere)
need sha256sum coreutils
need tar tar
command -v curl >/dev/null || need wget wget
mkdir -p "$DEST"

for seq in "${SEQUENCES[@]}"; do
  [[ "$seq" =~ ^freiburg([123])_[a-z0-9_]+$ ]] || die "not a TUM sequence name: $seq (e.g. freiburg1_desk)"
  fr=${BASH_REMATCH[1]}
  name=rgbd_dataset_$seq
  echo "== $name"
  if [ -f "$DEST/$name/groundtruth.txt" ] && [ -f "$DEST/$name/rgb.txt" ]; then
    echo "   already unpacked in $DEST/$name"; continue
  fi
  archive="$DEST/$name.tgz"
  download "https://cvg.cit.tum.de/rgbd/dataset/freiburg$fr/$name.tgz" "$archive"
  verify "$archive" "$DEST"
  unpack "$archive" "$DEST"
  for f in rgb.txt depth.txt groundtruth.txt; do
    [ -f "$DEST/$name/$f" ] || die "$name: $f missing after unpacking"
  done
  rgb=$(grep -vc '^#' "$DEST/$name/rgb.txt"); depth=$(grep -vc '^#' "$DEST/$name/depth.txt")
  echo "   $rgb colour and $depth depth images in $DEST/$name"
  rm -f "$archive"
done
