#pragma once

// Small helpers shared by the command-line programs.

#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <string>

namespace ccmd::app {

// Folder of the shipped camera configs: $CCMD_CONFIG_DIR, else the source tree's configs/.
inline std::string ConfigDir() {
  if (const char* env = std::getenv("CCMD_CONFIG_DIR")) return env;
  return CCMD_CONFIG_DIR;
}

// The default place-recognition vocabulary: $CCMD_VOCABULARY, else the one the build trains
// from synthetic rooms (apps/ccmd_vocab.cmake; docs/place_recognition.md). The file may be
// missing (built with -DCCMD_BUILD_VOCABULARY=OFF): callers then train online.
inline std::string DefaultVocabularyPath() {
  if (const char* env = std::getenv("CCMD_VOCABULARY")) return env;
#ifdef CCMD_DEFAULT_VOCABULARY
  return CCMD_DEFAULT_VOCABULARY;
#else
  return "";
#endif
}

// Folder of the live map view's page and three.js: $CCMD_WEB_DIR, else the build's
// share/ccmd/web (libccmd/view/CMakeLists.txt copies them there).
inline std::string WebDir() {
  if (const char* env = std::getenv("CCMD_WEB_DIR")) return env;
  return CCMD_WEB_DIR;
}

// One-line progress on a terminal ("\r" updates), a line per 10% otherwise.
class Progress {
 public:
  explicit Progress(std::string label) : label_(std::move(label)), tty_(::isatty(2)) {}
  void Update(long done, long total) {
    const int percent = total > 0 ? static_cast<int>(100 * done / total) : 0;
    if (tty_) {
      std::fprintf(stderr, "\r%s %ld/%ld (%d%%)", label_.c_str(), done, total, percent);
      if (done == total) std::fprintf(stderr, "\n");
    } else if (percent / 10 != last_decile_ || done == total) {
      last_decile_ = percent / 10;
      std::fprintf(stderr, "%s %ld/%ld (%d%%)\n", label_.c_str(), done, total, percent);
    }
    std::fflush(stderr);
  }

 private:
  std::string label_;
  bool tty_;
  int last_decile_ = -1;
};

}  // namespace ccmd::app
