#!/usr/bin/env bash
# Checks that every C++ file the repository tracks is formatted by clang-format (.clang-format:
# Google style, 100 columns). Prints the files that are not and exits 1; `--fix` formats them.
#
#   scripts/check_format.sh          check (CI)
#   scripts/check_format.sh --fix    format in place
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v clang-format >/dev/null; then
  echo "check_format.sh: clang-format is missing (scripts/setup.sh installs it)" >&2
  exit 2
fi
mapfile -t files < <(git ls-files '*.cc' '*.h')
if [ "${1:-}" = "--fix" ]; then
  clang-format -i "${files[@]}"
  exit 0
fi
bad=()
for f in "${files[@]}"; do
  if ! clang-format --dry-run --Werror "$f" >/dev/null 2>&1; then bad+=("$f"); fi
done
if ((${#bad[@]})); then
  echo "check_format.sh: ${#bad[@]} files are not clang-formatted (scripts/check_format.sh --fix):" >&2
  printf '  %s\n' "${bad[@]}" >&2
  exit 1
fi
echo "== all ${#files[@]} C++ files clang-formatted"
