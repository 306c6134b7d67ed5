#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

// Reads a whole file. Refuses files larger than `max_bytes`.
StatusOr<std::string> ReadFileToString(const std::string& path,
                                       std::uint64_t max_bytes = 1ull << 32);

// Writes `path` so that readers see either the old file or the complete new one, never
// a partial file: the data goes to a temporary file in the same folder, is flushed to
// disk, then renamed over `path`.
Status WriteFileAtomic(const std::string& path, std::string_view data);

// Like WriteFileAtomic, for writers that stream: `write` is given the temporary path.
template <typename WriteFn>
Status WriteFileAtomicWith(const std::string& path, WriteFn&& write);

// Creates a folder and its parents; succeeds if it exists already.
Status MakeDirectories(const std::string& path);

bool FileExists(const std::string& path);
bool IsDirectory(const std::string& path);

// Joins path parts with exactly one '/' between them.
std::string JoinPath(const std::string& a, const std::string& b);

// Flushes the file's data to disk and renames it into place (the second half of the
// atomic write, for code that wrote the temporary file itself).
Status CommitTemporaryFile(const std::string& temp_path, const std::string& final_path);
std::string TemporaryPathFor(const std::string& final_path);

template <typename WriteFn>
Status WriteFileAtomicWith(const std::string& path, WriteFn&& write) {
  const std::string temp = TemporaryPathFor(path);
  Status status = write(temp);
  if (!status.ok()) return status;
  return CommitTemporaryFile(temp, path);
}

}  // namespace ccmd
