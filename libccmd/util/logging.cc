#include "libccmd/util/logging.h"

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <mutex>

namespace ccmd {
namespace {

LogLevel InitialLevel() {
  LogLevel level = LogLevel::INFO;
  if (const char* env = std::getenv("CCMD_LOG_LEVEL")) ParseLogLevel(env, &level);
  return level;
}

std::atomic<int>& MinLevelStorage() {
  static std::atomic<int> level{static_cast<int>(InitialLevel())};
  return level;
}

std::mutex& LogMutex() {
  static std::mutex mutex;
  return mutex;
}

std::string& LogTag() {
  static std::string tag;
  return tag;
}

const char* LevelLetter(LogLevel level) {
  switch (level) {
    case LogLevel::DEBUG:
      return "D";
    case LogLevel::INFO:
      return "I";
    case LogLevel::WARNING:
      return "W";
    case LogLevel::ERROR:
      return "E";
    case LogLevel::FATAL:
      return "F";
  }
  return "?";
}

}  // namespace

void SetMinLogLevel(LogLevel level) { MinLevelStorage() = static_cast<int>(level); }
LogLevel MinLogLevel() { return static_cast<LogLevel>(MinLevelStorage().load()); }

bool ParseLogLevel(const std::string& text, LogLevel* level) {
  if (text == "debug")
    *level = LogLevel::DEBUG;
  else if (text == "info")
    *level = LogLevel::INFO;
  else if (text == "warning")
    *level = LogLevel::WARNING;
  else if (text == "error")
    *level = LogLevel::ERROR;
  else
    return false;
  return true;
}

void SetLogTag(const std::string& tag) {
  std::lock_guard<std::mutex> lock(LogMutex());
  LogTag() = tag;
}

namespace internal {

LogMessage::LogMessage(LogLevel level, const char* file, int line)
    : level_(level), file_(file), line_(line) {}

LogMessage::~LogMessage() {
  const auto now = std::chrono::system_clock::now();
  const std::time_t seconds = std::chrono::system_clock::to_time_t(now);
  const int millis = static_cast<int>(
      std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000);
  std::tm local{};
  localtime_r(&seconds, &local);
  char when[32];
  std::strftime(when, sizeof(when), "%H:%M:%S", &local);
  const char* base = std::strrchr(file_, '/');
  base = base ? base + 1 : file_;
  {
    std::lock_guard<std::mutex> lock(LogMutex());
    const std::string prefix = LogTag().empty() ? "" : "[" + LogTag() + "] ";
    std::fprintf(stderr, "%s %s.%03d %s%s:%d] %s\n", LevelLetter(level_), when, millis,
                 prefix.c_str(), base, line_, stream_.str().c_str());
    std::fflush(stderr);
  }
  if (level_ == LogLevel::FATAL) std::abort();
}

}  // namespace internal
}  // namespace ccmd
