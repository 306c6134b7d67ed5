#pragma once

// Helpers shared by the tests: the real datasets in ../shared/datasets (tests skip with a
// notice when they are absent), temporary folders, and running the project's programs.

#include <string>

namespace ccmd::testing {

// Absolute path of ../shared/datasets/<name> (or $CCMD_DATASETS/<name>), "" if missing.
std::string SharedDatasetPath(const std::string& name);

// A fresh folder under the system temp dir, removed with everything in it on destruction.
class TempDir {
 public:
  TempDir();
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const std::string& path() const { return path_; }
  std::string File(const std::string& name) const { return path_ + "/" + name; }

 private:
  std::string path_;
};

// Path of a built program (ccmd_eval, ccmd_synth, ...).
std::string ProgramPath(const std::string& name);

// Runs a shell command; returns its exit code and captures stdout+stderr into `output`.
int RunCommand(const std::string& command, std::string* output = nullptr);

}  // namespace ccmd::testing

// Skips the current test with a notice when a shared dataset is absent.
#define CCMD_REQUIRE_DATASET(var, name)                                                 \
  const std::string var = ::ccmd::testing::SharedDatasetPath(name);                     \
  if (var.empty()) {                                                                    \
    GTEST_SKIP() << "dataset " << name << " not found in ../shared/datasets; skipping"; \
  }

// Sanitizer builds bring their own allocator (and shadow memory): glibc's settings, page-fault
// counts and heap reuse do not apply there, in the test binary or the programs built with it.
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
#define CCMD_OWN_ALLOCATOR 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(thread_sanitizer)
#define CCMD_OWN_ALLOCATOR 1
#endif
#endif
