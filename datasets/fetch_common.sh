# Shared by fetch_tum.sh and fetch_icl_nuim.sh (sourced, not run).

die() { echo "error: $*" >&2; exit 1; }

need() { command -v "$1" >/dev/null || die "$1 is required (apt-get install $2)"; }

# download URL FILE: resumable download into FILE (via FILE.part).
download() {
  local url=$1 file=$2
  if [ -f "$file" ]; then echo "   have $(basename "$file")"; return; fi
  echo "   downloading $url"
  if command -v curl >/dev/null; then
    curl -fL --retry 3 -C - -o "$file.part" "$url" || die "download failed: $url"
  else
    wget -c -O "$file.part" "$url" || die "download failed: $url"
  fi
  mv "$file.part" "$file"
}

# verify FILE DEST_DIR: checks size and SHA-256 against checksums.sha256, or against the
# hash recorded at the first download (DEST_DIR/.checksums) when no published value exists.
verify() {
  local file=$1 dest=$2 name actual size expected expected_size
  name=$(basename "$file")
  actual=$(sha256sum "$file" | cut -d' ' -f1)
  size=$(stat -c %s "$file")
  read -r expected expected_size < <(grep -v '^#' "$SCRIPT_DIR/checksums.sha256" | awk -v n="$name" '$3 == n {print $1, $2}') || true
  if [ -n "${expected:-}" ]; then
    [ "$size" = "$expected_size" ] || die "$name is $size bytes, expected $expected_size (incomplete or changed download; delete it and retry)"
    [ "$actual" = "$expected" ] || die "$name SHA-256 $actual does not match $expected"
    echo "   verified $name (sha256 and size match checksums.sha256)"
    return
  fi
  local record="$dest/.checksums"
  expected=$(awk -v n="$name" '$2 == n {print $1}' "$record" 2>/dev/null || true)
  if [ -n "$expected" ]; then
    [ "$actual" = "$expected" ] || die "$name SHA-256 $actual differs from the first download's $expected"
    echo "   verified $name against the first download"
  else
    echo "$actual $name" >> "$record"
    echo "   note: no published checksum for $name; recorded $actual in $record"
  fi
}

# unpack ARCHIVE DEST_DIR: refuses absolute paths and '..' members before extracting.
unpack() {
  local archive=$1 dest=$2
  if tar -tzf "$archive" | grep -qE '(^/|(^|/)\.\.(/|$))'; then
    die "$archive contains unsafe paths"
  fi
  tar -xzf "$archive" -C "$dest"
}
