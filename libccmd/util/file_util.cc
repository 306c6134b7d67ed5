#include "libccmd/util/file_util.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>

namespace ccmd {

StatusOr<std::string> ReadFileToString(const std::string& path, std::uint64_t max_bytes) {
  std::error_code ec;
  const auto size = std::filesystem::file_size(path, ec);
  if (ec) return NotFound("cannot open " + path + ": " + ec.message());
  if (size > max_bytes) {
    return OutOfRange(path + " is " + std::to_string(size) + " bytes, more than the limit " +
                      std::to_string(max_bytes));
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) return NotFound("cannot open " + path);
  std::string data(size, '\0');
  in.read(data.data(), static_cast<std::streamsize>(size));
  if (static_cast<std::uint64_t>(in.gcount()) != size) return IoError("short read from " + path);
  return data;
}

std::string TemporaryPathFor(const std::string& final_path) {
  static std::atomic<unsigned> counter{0};
  return final_path + ".tmp." + std::to_string(::getpid()) + "." + std::to_string(counter++);
}

Status CommitTemporaryFile(const std::string& temp_path, const std::string& final_path) {
  const int fd = ::open(temp_path.c_str(), O_RDONLY);
  if (fd < 0) return IoError("cannot reopen " + temp_path + ": " + std::strerror(errno));
  const int sync_result = ::fsync(fd);
  ::close(fd);
  if (sync_result != 0) {
    std::remove(temp_path.c_str());
    return IoError("fsync " + temp_path + ": " + std::strerror(errno));
  }
  if (std::rename(temp_path.c_str(), final_path.c_str()) != 0) {
    const std::string reason = std::strerror(errno);
    std::remove(temp_path.c_str());
    return IoError("rename " + temp_path + " -> " + final_path + ": " + reason);
  }
  return Status::Ok();
}

Status WriteFileAtomic(const std::string& path, std::string_view data) {
  return WriteFileAtomicWith(path, [&](const std::string& temp) -> Status {
    std::ofstream out(temp, std::ios::binary | std::ios::trunc);
    if (!out) return IoError("cannot create " + temp + ": " + std::strerror(errno));
    out.write(data.data(), static_cast<std::streamsize>(data.size()));
    out.close();
    if (!out) {
      std::remove(temp.c_str());
      return IoError("write failed for " + temp);
    }
    return Status::Ok();
  });
}

Status MakeDirectories(const std::string& path) {
  std::error_code ec;
  std::filesystem::create_directories(path, ec);
  if (ec) return IoError("cannot create folder " + path + ": " + ec.message());
  return Status::Ok();
}

bool FileExists(const std::string& path) {
  std::error_code ec;
  return std::filesystem::exists(path, ec);
}

bool IsDirectory(const std::string& path) {
  std::error_code ec;
  return std::filesystem::is_directory(path, ec);
}

std::string JoinPath(const std::string& a, const std::string& b) {
  if (a.empty()) return b;
  if (b.empty()) return a;
  if (b.front() == '/') return b;
  if (a.back() == '/') return a + b;
  return a + "/" + b;
}

}  // namespace ccmd
