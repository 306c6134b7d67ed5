#pragma once

// Minimal thread-safe logging to stderr, and CHECK macros for broken invariants.
//   CCMD_LOG(INFO) << "agent " << id << " connected";
//   CCMD_CHECK(queue_capacity > 0) << "capacity must be positive";
// A failed CHECK prints file:line and the message, then aborts. It is for
// programming errors only; bad input returns a Status.

#include <sstream>
#include <string>

namespace ccmd {

enum class LogLevel { DEBUG = 0, INFO = 1, WARNING = 2, ERROR = 3, FATAL = 4 };

// Messages below this level are dropped. Default INFO; CCMD_LOG_LEVEL=debug|info|warning|error
// in the environment overrides it at start-up.
void SetMinLogLevel(LogLevel level);
LogLevel MinLogLevel();
bool ParseLogLevel(const std::string& text, LogLevel* level);

// Prefix every line with a tag (e.g. "agent 2"), useful when several processes share a terminal.
void SetLogTag(const std::string& tag);

namespace internal {

class LogMessage {
 public:
  LogMessage(LogLevel level, const char* file, int line);
  ~LogMessage();
  std::ostream& stream() { return stream_; }

 private:
  LogLevel level_;
  const char* file_;
  int line_;
  std::ostringstream stream_;
};

// Swallows the stream expression when a message is disabled.
struct LogVoidify {
  void operator&(std::ostream&) {}
};

}  // namespace internal
}  // namespace ccmd

#define CCMD_LOG(level)                               \
  !(::ccmd::LogLevel::level >= ::ccmd::MinLogLevel()) \
      ? (void)0                                       \
      : ::ccmd::internal::LogVoidify() &              \
            ::ccmd::internal::LogMessage(::ccmd::LogLevel::level, __FILE__, __LINE__).stream()

#define CCMD_CHECK(cond)                                                                          \
  (cond) ? (void)0                                                                                \
         : ::ccmd::internal::LogVoidify() &                                                       \
               ::ccmd::internal::LogMessage(::ccmd::LogLevel::FATAL, __FILE__, __LINE__).stream() \
                   << "check failed: " #cond " "

#define CCMD_CHECK_OP(a, op, b) CCMD_CHECK((a)op(b)) << "(" << (a) << " vs " << (b) << ") "
#define CCMD_CHECK_EQ(a, b) CCMD_CHECK_OP(a, ==, b)
#define CCMD_CHECK_NE(a, b) CCMD_CHECK_OP(a, !=, b)
#define CCMD_CHECK_LT(a, b) CCMD_CHECK_OP(a, <, b)
#define CCMD_CHECK_LE(a, b) CCMD_CHECK_OP(a, <=, b)
#define CCMD_CHECK_GT(a, b) CCMD_CHECK_OP(a, >, b)
#define CCMD_CHECK_GE(a, b) CCMD_CHECK_OP(a, >=, b)
