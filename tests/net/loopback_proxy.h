#pragma once

// The plumbing the test proxies share: a listener on 127.0.0.1:port(), one connection to the
// target per accepted client, one pump thread per pair (what it does is the subclass's),
// a target that can change while running (a restarted server on a new port). Every thread
// is owned and joined by Stop(), which a subclass's destructor must call.

#include <poll.h>
#include <sys/socket.h>

#include <atomic>
#include <cstdint>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include "libccmd/net/socket.h"

namespace ccmd::nettest {

class LoopbackProxy {
 public:
  LoopbackProxy() = default;
  virtual ~LoopbackProxy() = default;
  LoopbackProxy(const LoopbackProxy&) = delete;
  LoopbackProxy& operator=(const LoopbackProxy&) = delete;

  bool Start(std::uint16_t target_port) {
    target_.store(target_port);
    bool loopback;
    StatusOr<UniqueFd> fd = ListenTcp(HostPort{"127.0.0.1", 0}, 64, &loopback);
    if (!fd.ok()) return false;
    listener_ = std::move(*fd);
    port_ = LocalPort(listener_.get()).value();
    acceptor_ = std::thread([this] { AcceptLoop(); });
    return true;
  }
  void SetTarget(std::uint16_t port) { target_.store(port); }
  std::uint16_t port() const { return port_; }
  int connections() const { return connections_.load(); }

  void Stop() {
    stop_.store(true);
    wake_.Signal();
    if (acceptor_.joinable()) acceptor_.join();
    std::lock_guard<std::mutex> lock(mutex_);
    for (std::thread& t : pumps_) t.join();
    pumps_.clear();
  }

 protected:
  // Called on the accept thread for each new pair, one at a time: the work of its pump
  // thread. The pump returns (closing both sockets) when either side closes or stopping().
  virtual std::function<void()> NewPump(UniqueFd client, UniqueFd server) = 0;

  bool stopping() const { return stop_.load(); }
  int wake_fd() const { return wake_.fd(); }

  // Writes everything, waiting for room; false when the socket fails or the proxy stops.
  bool WriteFully(int fd, const std::uint8_t* data, std::size_t size) {
    while (size > 0 && !stop_.load()) {
      StatusOr<std::size_t> n = WriteSome(fd, data, size);
      if (!n.ok()) return false;
      data += *n;
      size -= *n;
      if (size > 0) {
        pollfd p{fd, POLLOUT, 0};
        ::poll(&p, 1, 100);
      }
    }
    return size == 0;
  }

 private:
  void AcceptLoop() {
    while (!stop_.load()) {
      pollfd fds[2] = {{listener_.get(), POLLIN, 0}, {wake_.fd(), POLLIN, 0}};
      ::poll(fds, 2, -1);
      if (stop_.load()) return;
      const int fd = ::accept4(listener_.get(), nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
      if (fd < 0) continue;
      UniqueFd client(fd);
      StatusOr<UniqueFd> server = ConnectTcp(HostPort{"127.0.0.1", target_.load()}, 2.0);
      if (!server.ok()) continue;  // target down: the client sees a closed connection
      ++connections_;
      std::lock_guard<std::mutex> lock(mutex_);
      pumps_.emplace_back(NewPump(std::move(client), std::move(*server)));
    }
  }

  std::mutex mutex_;
  UniqueFd listener_;
  std::uint16_t port_ = 0;
  std::atomic<std::uint16_t> target_{0};
  WakeFd wake_;
  std::atomic<bool> stop_{false};
  std::atomic<int> connections_{0};
  std::thread acceptor_;
  std::vector<std::thread> pumps_;
};

}  // namespace ccmd::nettest
