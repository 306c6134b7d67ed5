#include "libccmd/net/socket.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>

#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

std::string Errno(const std::string& what) { return what + ": " + std::strerror(errno); }

bool IsLoopback(const sockaddr* addr) {
  if (addr->sa_family == AF_INET) {
    const auto* in = reinterpret_cast<const sockaddr_in*>(addr);
    return (ntohl(in->sin_addr.s_addr) >> 24) == 127;
  }
  if (addr->sa_family == AF_INET6) {
    const auto* in6 = reinterpret_cast<const sockaddr_in6*>(addr);
    if (IN6_IS_ADDR_LOOPBACK(&in6->sin6_addr)) return true;
    // ::ffff:127.x.y.z
    if (IN6_IS_ADDR_V4MAPPED(&in6->sin6_addr)) return in6->sin6_addr.s6_addr[12] == 127;
  }
  return false;
}

struct AddrInfoList {
  addrinfo* list = nullptr;
  ~AddrInfoList() {
    if (list) freeaddrinfo(list);
  }
};

Status Resolve(const HostPort& address, bool passive, AddrInfoList* out) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = passive ? AI_PASSIVE : 0;
  const std::string port = std::to_string(address.port);
  const int rc = getaddrinfo(address.host.c_str(), port.c_str(), &hints, &out->list);
  if (rc != 0 || out->list == nullptr) {
    return NotFound("cannot resolve '" + address.host + "': " + gai_strerror(rc));
  }
  return Status::Ok();
}

}  // namespace

void UniqueFd::Reset(int fd) {
  if (fd_ >= 0) ::close(fd_);
  fd_ = fd;
}

StatusOr<HostPort> ParseHostPort(const std::string& text) {
  HostPort hp;
  std::string port_text;
  if (!text.empty() && text[0] == '[') {
    const std::size_t close = text.find(']');
    if (close == std::string::npos || close + 1 >= text.size() || text[close + 1] != ':') {
      return InvalidArgument("bad address '" + text + "' (expected [IPv6]:PORT)");
    }
    hp.host = text.substr(1, close - 1);
    port_text = text.substr(close + 2);
  } else {
    const std::size_t colon = text.rfind(':');
    if (colon == std::string::npos || colon == 0) {
      return InvalidArgument("bad address '" + text + "' (expected HOST:PORT)");
    }
    hp.host = text.substr(0, colon);
    port_text = text.substr(colon + 1);
    if (hp.host.find(':') != std::string::npos) {
      return InvalidArgument("bad address '" + text + "' (write IPv6 addresses as [ADDR]:PORT)");
    }
  }
  if (port_text.empty() || port_text.size() > 5 ||
      port_text.find_first_not_of("0123456789") != std::string::npos ||
      std::stoul(port_text) > 65535) {
    return InvalidArgument("bad port in '" + text + "' (expected 0..65535)");
  }
  hp.port = static_cast<std::uint16_t>(std::stoul(port_text));
  return hp;
}

StatusOr<UniqueFd> ListenTcp(const HostPort& address, int backlog, bool* loopback) {
  AddrInfoList ai;
  CCMD_RETURN_IF_ERROR(Resolve(address, /*passive=*/true, &ai));
  Status last = IoError("no usable address");
  for (addrinfo* p = ai.list; p != nullptr; p = p->ai_next) {
    UniqueFd fd(
        ::socket(p->ai_family, p->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, p->ai_protocol));
    if (!fd.valid()) {
      last = IoError(Errno("socket"));
      continue;
    }
    const int one = 1;
    ::setsockopt(fd.get(), SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
    if (::bind(fd.get(), p->ai_addr, p->ai_addrlen) != 0) {
      last = IoError(Errno("bind " + address.host + ":" + std::to_string(address.port)));
      continue;
    }
    if (::listen(fd.get(), backlog) != 0) {
      last = IoError(Errno("listen"));
      continue;
    }
    if (loopback) *loopback = IsLoopback(p->ai_addr);
    return fd;
  }
  return last;
}

StatusOr<std::uint16_t> LocalPort(int fd) {
  sockaddr_storage ss{};
  socklen_t len = sizeof(ss);
  if (::getsockname(fd, reinterpret_cast<sockaddr*>(&ss), &len) != 0) {
    return IoError(Errno("getsockname"));
  }
  if (ss.ss_family == AF_INET) return ntohs(reinterpret_cast<sockaddr_in*>(&ss)->sin_port);
  if (ss.ss_family == AF_INET6) return ntohs(reinterpret_cast<sockaddr_in6*>(&ss)->sin6_port);
  return Internal("unexpected socket family");
}

std::string PeerName(int fd) {
  sockaddr_storage ss{};
  socklen_t len = sizeof(ss);
  if (::getpeername(fd, reinterpret_cast<sockaddr*>(&ss), &len) != 0) return "?";
  char host[INET6_ADDRSTRLEN] = "?";
  char text[INET6_ADDRSTRLEN + 16];
  if (ss.ss_family == AF_INET) {
    auto* in = reinterpret_cast<sockaddr_in*>(&ss);
    inet_ntop(AF_INET, &in->sin_addr, host, sizeof(host));
    std::snprintf(text, sizeof(text), "%s:%u", host, unsigned{ntohs(in->sin_port)});
    return text;
  }
  if (ss.ss_family == AF_INET6) {
    auto* in6 = reinterpret_cast<sockaddr_in6*>(&ss);
    inet_ntop(AF_INET6, &in6->sin6_addr, host, sizeof(host));
    std::snprintf(text, sizeof(text), "[%s]:%u", host, unsigned{ntohs(in6->sin6_port)});
    return text;
  }
  return "?";
}

Status SetNonBlocking(int fd) {
  const int flags = ::fcntl(fd, F_GETFL, 0);
  if (flags < 0 || ::fcntl(fd, F_SETFL, flags | O_NONBLOCK) != 0) {
    return IoError(Errno("fcntl O_NONBLOCK"));
  }
  return Status::Ok();
}

void SetNoDelay(int fd) {
  // Acks and handshake messages are small and latency matters more than packet count.
  const int one = 1;
  ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
}

StatusOr<UniqueFd> ConnectTcp(const HostPort& address, double timeout_s, int wake_fd,
                              const std::function<bool()>& cancelled) {
  AddrInfoList ai;
  CCMD_RETURN_IF_ERROR(Resolve(address, /*passive=*/false, &ai));
  const double deadline = MonotonicSeconds() + timeout_s;
  Status last = IoError("no usable address");
  const std::string where = address.host + ":" + std::to_string(address.port);
  for (addrinfo* p = ai.list; p != nullptr; p = p->ai_next) {
    UniqueFd fd(
        ::socket(p->ai_family, p->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, p->ai_protocol));
    if (!fd.valid()) {
      last = IoError(Errno("socket"));
      continue;
    }
    SetNoDelay(fd.get());
    if (::connect(fd.get(), p->ai_addr, p->ai_addrlen) != 0 && errno != EINPROGRESS) {
      last = Unavailable(Errno("connect to " + where));
      continue;
    }
    while (true) {
      const double left = deadline - MonotonicSeconds();
      if (left <= 0) return Timeout("connecting to " + where + " timed out");
      pollfd fds[2] = {{fd.get(), POLLOUT, 0}, {wake_fd, POLLIN, 0}};
      const int n = ::poll(fds, wake_fd >= 0 ? 2 : 1, static_cast<int>(std::ceil(left * 1e3)));
      if (n < 0) {
        if (errno == EINTR) continue;
        return IoError(Errno("poll"));
      }
      if (wake_fd >= 0 && (fds[1].revents & POLLIN)) {
        std::uint64_t value;
        [[maybe_unused]] ssize_t r = ::read(wake_fd, &value, sizeof(value));
        if (cancelled && cancelled()) return Cancelled("connect interrupted");
      }
      if (!(fds[0].revents & (POLLOUT | POLLERR | POLLHUP))) continue;
      int error = 0;
      socklen_t len = sizeof(error);
      ::getsockopt(fd.get(), SOL_SOCKET, SO_ERROR, &error, &len);
      if (error != 0) {
        errno = error;
        last = Unavailable(Errno("connect to " + where));
        break;
      }
      return fd;
    }
  }
  return last;
}

StatusOr<std::size_t> ReadSome(int fd, void* buffer, std::size_t size) {
  while (true) {
    const ssize_t n = ::recv(fd, buffer, size, 0);
    if (n > 0) return static_cast<std::size_t>(n);
    if (n == 0) return EndOfStream("connection closed by the peer");
    if (errno == EINTR) continue;
    if (errno == EAGAIN || errno == EWOULDBLOCK) return std::size_t{0};
    return Unavailable(Errno("read"));
  }
}

StatusOr<std::size_t> WriteSome(int fd, const void* data, std::size_t size) {
  while (true) {
    // MSG_NOSIGNAL: a peer that went away is an error Status, not a SIGPIPE.
    const ssize_t n = ::send(fd, data, size, MSG_NOSIGNAL);
    if (n >= 0) return static_cast<std::size_t>(n);
    if (errno == EINTR) continue;
    if (errno == EAGAIN || errno == EWOULDBLOCK) return std::size_t{0};
    return Unavailable(Errno("write"));
  }
}

WakeFd::WakeFd() : fd_(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC)) {}

void WakeFd::Signal() {
  const std::uint64_t one = 1;
  // A full counter still wakes the poller, so a failed write needs no handling.
  [[maybe_unused]] ssize_t n = ::write(fd_.get(), &one, sizeof(one));
}

void WakeFd::Drain() {
  std::uint64_t value;
  [[maybe_unused]] ssize_t n = ::read(fd_.get(), &value, sizeof(value));
}

}  // namespace ccmd
