#include "tests/support/test_support.h"

#include <unistd.h>

#include <array>
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <filesystem>

namespace ccmd::testing {

std::string SharedDatasetPath(const std::string& name) {
  const char* env = std::getenv("CCMD_DATASETS");
  const std::filesystem::path root = env ? env : CCMD_SHARED_DATASETS;
  std::error_code ec;
  const auto path = root / name;
  if (!std::filesystem::is_directory(path, ec)) return "";
  return std::filesystem::weakly_canonical(path, ec).string();
}

TempDir::TempDir() {
  static std::atomic<int> counter{0};
  const auto base = std::filesystem::temp_directory_path();
  for (int attempt = 0;; ++attempt) {
    const auto candidate =
        base / ("ccmd_test_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
    std::error_code ec;
    if (std::filesystem::create_directory(candidate, ec)) {
      path_ = candidate.string();
      return;
    }
    if (attempt > 1000) std::abort();
  }
}

TempDir::~TempDir() {
  std::error_code ec;
  std::filesystem::remove_all(path_, ec);
}

std::string ProgramPath(const std::string& name) {
  const char* env = std::getenv("CCMD_BIN_DIR");
  return std::string(env ? env : CCMD_TEST_BIN_DIR) + "/" + name;
}

int RunCommand(const std::string& command, std::string* output) {
  const std::string full = command + " 2>&1";
  FILE* pipe = ::popen(full.c_str(), "r");
  if (!pipe) return -1;
  std::array<char, 4096> buffer;
  std::string captured;
  std::size_t n;
  while ((n = std::fread(buffer.data(), 1, buffer.size(), pipe)) > 0)
    captured.append(buffer.data(), n);
  const int status = ::pclose(pipe);
  if (output) *output = captured;
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

}  // namespace ccmd::testing
