#pragma once

// Thin POSIX socket helpers for the transport: addresses, a listening socket, a connect with
// a time-out, non-blocking reads and writes, and a wake-up descriptor that lets another
// thread interrupt a poll().

#include <cstdint>
#include <functional>
#include <string>

#include "libccmd/util/status.h"

namespace ccmd {

// Owns a file descriptor; closes it on destruction.
class UniqueFd {
 public:
  UniqueFd() = default;
  explicit UniqueFd(int fd) : fd_(fd) {}
  ~UniqueFd() { Reset(); }
  UniqueFd(UniqueFd&& other) noexcept : fd_(other.Release()) {}
  UniqueFd& operator=(UniqueFd&& other) noexcept {
    if (this != &other) Reset(other.Release());
    return *this;
  }
  UniqueFd(const UniqueFd&) = delete;
  UniqueFd& operator=(const UniqueFd&) = delete;

  int get() const { return fd_; }
  bool valid() const { return fd_ >= 0; }
  int Release() {
    const int fd = fd_;
    fd_ = -1;
    return fd;
  }
  void Reset(int fd = -1);

 private:
  int fd_ = -1;
};

struct HostPort {
  std::string host;  // name or numeric address; IPv6 without brackets
  std::uint16_t port = 0;
};

// "127.0.0.1:7420", "0.0.0.0:7420", "[::1]:7420", "robot-server:7420". Port 0 is allowed
// (a listener then gets a free port from the system).
StatusOr<HostPort> ParseHostPort(const std::string& text);

// A non-blocking listening TCP socket bound to host:port (SO_REUSEADDR, so a restarted
// server can bind at once). *loopback tells whether the bound address is a loopback one.
StatusOr<UniqueFd> ListenTcp(const HostPort& address, int backlog, bool* loopback);

// The port a bound socket got (for port 0).
StatusOr<std::uint16_t> LocalPort(int fd);

// "address:port" of the peer, for logs.
std::string PeerName(int fd);

// Connects to host:port within timeout_s; the socket is non-blocking with TCP_NODELAY.
// When `wake_fd` (>= 0) becomes readable, it is drained and `cancelled()` asked: true
// returns kCancelled at once.
StatusOr<UniqueFd> ConnectTcp(const HostPort& address, double timeout_s, int wake_fd = -1,
                              const std::function<bool()>& cancelled = {});

Status SetNonBlocking(int fd);
void SetNoDelay(int fd);

// Non-blocking I/O results: bytes moved (0 = would block) or an error. ReadSome returns
// kEndOfStream when the peer closed the connection.
StatusOr<std::size_t> ReadSome(int fd, void* buffer, std::size_t size);
StatusOr<std::size_t> WriteSome(int fd, const void* data, std::size_t size);

// An eventfd that another thread signals to wake a poll() on this side.
class WakeFd {
 public:
  WakeFd();
  int fd() const { return fd_.get(); }
  bool valid() const { return fd_.valid(); }
  void Signal();
  void Drain();

 private:
  UniqueFd fd_;
};

}  // namespace ccmd
