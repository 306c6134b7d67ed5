#!/usr/bin/env bash
# Downloads ICL-NUIM sequences (the TUM-compatible release), verifies them and turns them into
# the TUM layout ccmd reads:
#   datasets/fetch_icl_nuim.sh [--dest DIR] [--scene living_room|office] [TRAJ ...]
# TRAJ in 0 1 2 3 (default: all); --scene living_room (default) or office (the office room,
# which the CCMD-SLAM paper evaluates). Each becomes DIR/<scene>_traj<N>_frei_png/ with rgb/,
# depth/, rgb.txt, depth.txt and groundtruth.txt. The release names frames by index (0.png,
# 1.png, ...) and lists them in associations.txt with depth first; its ground truth
# (livingRoom<N>.gt.freiburg, traj<N>.gt.freiburg for the office) also uses frame indices as
# timestamps. Both get timestamps index / 30 s (the renders are 30 Hz), so ground truth and
# frames stay matched by index. Use configs/icl_nuim.yaml (negative fy).
# CCMD_ICL_NUIM_URL replaces the download site (default https://www.doc.ic.ac.uk/~ahanda).
set -euo pipefail
SCRIPT_DIR=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=fetch_common.sh
. "$SCRIPT_DIR/fetch_common.sh"

DEST=data/icl_nuim
SCENE=living_room
SITE=${CCMD_ICL_NUIM_URL:-https://www.doc.ic.ac.uk/~ahanda}
TRAJS=()
while (($#)); do
  case "$1" in
    --dest) DEST=$2; shift ;;
    --scene) SCENE=$2; shift ;;
    -h|--help) sed -n '2,12p' "$0"; exit 0 ;;
    [0-3]) TRAJS+=("$1") ;;
    *) die "unknown argument $1 (trajectories are 0 1 2 3)" ;;
  esac
  shift
done
case "$SCENE" in
  living_room|office) ;;
  *) die "unknown scene $SCENE (living_room or office)" ;;
esac
((${#TRAJS[@]})) || TRAJS=(0 1 2 3)
need sha256sum coreutils
need tar tar
command -v curl >/dev/null || need wget wget
mkdir -p "$DEST"

for n in "${TRAJS[@]}"; do
  # The folder names the scene (which is how programs choose configs/icl_nuim.yaml for it).
  if [ "$SCENE" = living_room ]; then
    archive_name=living_room_traj${n}_frei_png
    gt_name=livingRoom$n.gt.freiburg
    name=$archive_name
  else
    archive_name=traj${n}_frei_png  # the release's name for the office room's archives
    gt_name=traj$n.gt.freiburg
    name=office_room_traj${n}_frei_png
  fi
  dir="$DEST/$name"
  echo "== $name"
  if [ -f "$dir/rgb.txt" ] && [ -f "$dir/groundtruth.txt" ]; then
    echo "   already prepared in $dir"; continue
  fi
  archive="$DEST/$archive_name.tar.gz"
  download "$SITE/$archive_name.tar.gz" "$archive"
  verify "$archive" "$DEST"
  mkdir -p "$dir"
  unpack "$archive" "$dir"
  # Some copies unpack into a subfolder of the archive's name.
  if [ ! -f "$dir/associations.txt" ] && [ -f "$dir/$archive_name/associations.txt" ]; then
    mv "$dir/$archive_name"/* "$dir/" && rmdir "$dir/$archive_name"
  fi
  [ -f "$dir/associations.txt" ] || die "$name: associations.txt missing after unpacking"
  gt="$dir/$gt_name"
  if [ ! -f "$gt" ]; then  # not in the archive: published beside it
    download "$SITE/VaFRIC/$gt_name" "$gt"
    verify "$gt" "$DEST"
  fi

  # associations.txt lines: "i depth/i.png i rgb/i.png" (the depth column told by its path).
  awk '!/^#/ && NF >= 4 {
         d = ($2 ~ /depth/) ? $2 : $4; r = ($2 ~ /depth/) ? $4 : $2;
         printf "%.6f %s\n", $1 / 30.0, r > "'"$dir"'/rgb.txt";
         printf "%.6f %s\n", $1 / 30.0, d > "'"$dir"'/depth.txt" }' "$dir/associations.txt"
  awk '!/^#/ && NF == 8 { printf "%.6f %s %s %s %s %s %s %s\n", $1 / 30.0, $2, $3, $4, $5, $6, $7, $8 }' \
      "$gt" > "$dir/groundtruth.txt"
  [ -s "$dir/rgb.txt" ] || die "$name: no frames in associations.txt"
  [ -s "$dir/groundtruth.txt" ] || die "$name: no poses in $gt_name"
  echo "   $(wc -l < "$dir/rgb.txt") frames, $(wc -l < "$dir/groundtruth.txt") poses in $dir"
  rm -f "$archive"
done
