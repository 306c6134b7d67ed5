#pragma once

// Error handling for everything that can fail on input the program does not control
// (files, network bytes, devices, user options). Broken internal invariants use
// CCMD_CHECK (logging.h) instead.

#include <optional>
#include <string>
#include <utility>
#include <variant>

namespace ccmd {

enum class StatusCode {
  kOk = 0,
  kInvalidArgument,   // bad option or API use
  kNotFound,          // missing file, device, key
  kIoError,           // read/write/socket failure
  kCorrupt,           // malformed data: bad magic, CRC, truncated, inconsistent fields
  kOutOfRange,        // a value or size beyond a configured limit
  kUnsupported,       // valid but not handled: protocol version, pixel format
  kUnavailable,       // temporarily unavailable: device busy, peer gone; may retry
  kEndOfStream,       // orderly end of a source or connection
  kPermissionDenied,  // authentication failed
  kTimeout,
  kCancelled,
  kInternal,
};

const char* StatusCodeName(StatusCode code);

class [[nodiscard]] Status {
 public:
  Status() = default;
  Status(StatusCode code, std::string message) : code_(code), message_(std::move(message)) {}

  static Status Ok() { return Status(); }

  bool ok() const { return code_ == StatusCode::kOk; }
  StatusCode code() const { return code_; }
  const std::string& message() const { return message_; }

  // "corrupt: frame CRC mismatch" — for logs and user-facing errors.
  std::string ToString() const;

  // Adds context in front of the message: "reading rgb.txt: line 4: bad timestamp".
  Status WithContext(const std::string& context) const;

  // Silences [[nodiscard]] where an error is deliberately ignored.
  void IgnoreError() const {}

 private:
  StatusCode code_ = StatusCode::kOk;
  std::string message_;
};

inline Status InvalidArgument(std::string m) {
  return {StatusCode::kInvalidArgument, std::move(m)};
}
inline Status NotFound(std::string m) { return {StatusCode::kNotFound, std::move(m)}; }
inline Status IoError(std::string m) { return {StatusCode::kIoError, std::move(m)}; }
inline Status Corrupt(std::string m) { return {StatusCode::kCorrupt, std::move(m)}; }
inline Status OutOfRange(std::string m) { return {StatusCode::kOutOfRange, std::move(m)}; }
inline Status Unsupported(std::string m) { return {StatusCode::kUnsupported, std::move(m)}; }
inline Status Unavailable(std::string m) { return {StatusCode::kUnavailable, std::move(m)}; }
inline Status EndOfStream(std::string m = "end of stream") {
  return {StatusCode::kEndOfStream, std::move(m)};
}
inline Status PermissionDenied(std::string m) {
  return {StatusCode::kPermissionDenied, std::move(m)};
}
inline Status Timeout(std::string m) { return {StatusCode::kTimeout, std::move(m)}; }
inline Status Cancelled(std::string m) { return {StatusCode::kCancelled, std::move(m)}; }
inline Status Internal(std::string m) { return {StatusCode::kInternal, std::move(m)}; }

// A value or the error that prevented it.
template <typename T>
class [[nodiscard]] StatusOr {
 public:
  StatusOr(T value) : data_(std::move(value)) {}        // NOLINT: implicit by design
  StatusOr(Status status) : data_(std::move(status)) {  // NOLINT: implicit by design
    if (std::get<Status>(data_).ok()) data_ = Status(StatusCode::kInternal, "StatusOr from Ok");
  }

  bool ok() const { return std::holds_alternative<T>(data_); }
  Status status() const { return ok() ? Status::Ok() : std::get<Status>(data_); }

  // Precondition: ok(). Checked: calling these on an error is a programming error.
  const T& value() const& { return std::get<T>(data_); }
  T& value() & { return std::get<T>(data_); }
  T&& value() && { return std::get<T>(std::move(data_)); }
  const T& operator*() const& { return value(); }
  T& operator*() & { return value(); }
  const T* operator->() const { return &value(); }
  T* operator->() { return &value(); }

 private:
  std::variant<Status, T> data_;
};

}  // namespace ccmd

#define CCMD_STATUS_CONCAT_INNER(a, b) a##b
#define CCMD_STATUS_CONCAT(a, b) CCMD_STATUS_CONCAT_INNER(a, b)

// Returns the status from the enclosing function if it is an error.
#define CCMD_RETURN_IF_ERROR(expr)                       \
  do {                                                   \
    ::ccmd::Status ccmd_status_tmp_ = (expr);            \
    if (!ccmd_status_tmp_.ok()) return ccmd_status_tmp_; \
  } while (0)

// CCMD_ASSIGN_OR_RETURN(auto x, MakeX()); declares/assigns x or returns the error.
#define CCMD_ASSIGN_OR_RETURN(lhs, expr) \
  CCMD_ASSIGN_OR_RETURN_IMPL(CCMD_STATUS_CONCAT(ccmd_statusor_, __LINE__), lhs, expr)
#define CCMD_ASSIGN_OR_RETURN_IMPL(tmp, lhs, expr) \
  auto tmp = (expr);                               \
  if (!tmp.ok()) return tmp.status();              \
  lhs = std::move(tmp).value()
