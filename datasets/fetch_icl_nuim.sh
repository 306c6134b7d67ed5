#!/usr/bin/env bash
# Downloads ICL-NUIM living-room sequences (the TUM-compatible release), verifies them and
# turns them into the TUM layout ccmd reads:
#   datasets/fetch_icl_nuim.sh [--dest DIR] [TRAJ ...]     TRAJ in 0 1 2 3 (default: all)
# Each becomes DIR/living_room_traj<N>_frei_png/ with rgb/, depth/, rgb.txt, depth.txt and
# groundtruth.txt. The release names frames by index (0.png, 1.png, ...) and lists them in
# associations.txt with depth first; its ground truth (livingRoom<N>.gt.freiburg) also uses
# frame indices as timestamps. Both get timestamps index / 30 s (the renders are 30 Hz), so
# ground truth and frames stay matched by index. Use configs/icl_nuim.yaml (negative fy).
set -euo pipefail
SCRIPT_DIR=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=fetch_common.sh
. "$SCRIPT_DIR/fetch_common.sh"

DEST=data/icl_nuim
TRAJS=()
while (($#)); do
  case "$1" in
    --dest) DEST=$2; shift ;;
    -h|--help) sed -n '2,11p' "$0"; exit 0 ;;
    [0-3]) TRAJS+=("$1") ;;
    *) die "unknown argument $1 (trajectories are 0 1 2 3)" ;;
  esac
  shift
done
((${#TRAJS[@]})) || TRAJS=(0 1 2 3)
need sha256sum coreutils
need tar tar
command -v curl >/dev/null || need wget wget
mkdir -p "$DEST"

for n in "${TRAJS[@]}"; do
  name=living_room_traj${n}_frei_png
  dir="$DEST/$name"
  echo "== $name"
  if [ -f "$dir/rgb.txt" ] && [ -f "$dir/groundtruth.txt" ]; then
    echo "   already prepared in $dir"; continue
  fi
  archive="$DEST/$name.tar.gz"
  download "https://www.doc.ic.ac.uk/~ahanda/$name.tar.gz" "$archive"
  verify "$archive" "$DEST"
  mkdir -p "$dir"
  unpack "$archive" "$dir"
  # Some copies unpack into a subfolder of the same name.
  if [ ! -f "$dir/associations.txt" ] && [ -f "$dir/$name/associations.txt" ]; then
    mv "$dir/$name"/* "$dir/" && rmdir "$dir/$name"
  fi
  [ -f "$dir/associations.txt" ] || die "$name: associations.txt missing after unpacking"
  gt="$dir/livingRoom$n.gt.freiburg"
  download "https://www.doc.ic.ac.uk/~ahanda/VaFRIC/livingRoom$n.gt.freiburg" "$gt"
  verify "$gt" "$DEST"

  # associations.txt lines: "i depth/i.png i rgb/i.png" (the depth column told by its path).
  awk '!/^#/ && NF >= 4 {
         d = ($2 ~ /depth/) ? $2 : $4; r = ($2 ~ /depth/) ? $4 : $2;
         printf "%.6f %s\n", $1 / 30.0, r > "'"$dir"'/rgb.txt";
         printf "%.6f %s\n", $1 / 30.0, d > "'"$dir"'/depth.txt" }' "$dir/associations.txt"
  awk '!/^#/ && NF == 8 { printf "%.6f %s %s %s %s %s %s %s\n", $1 / 30.0, $2, $3, $4, $5, $6, $7, $8 }' \
      "$gt" > "$dir/groundtruth.txt"
  echo "   $(wc -l < "$dir/rgb.txt") frames, $(wc -l < "$dir/groundtruth.txt") poses in $dir"
  rm -f "$archive"
done
