#pragma once

// A TCP proxy for fault tests: forwards 127.0.0.1:port() to a target port, delays the
// agent-to-server direction by a random amount per chunk and cuts each connection after a
// random number of forwarded bytes (so mid-frame), both drawn from a seeded generator.
// The target can change while running (a restarted server on a new port). Every thread is
// owned and joined by Stop().

#include <poll.h>
#include <sys/socket.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <mutex>
#include <thread>
#include <vector>

#include "libccmd/net/socket.h"
#include "libccmd/util/random.h"

namespace ccmd::nettest {

struct FaultProxyOptions {
  std::uint64_t seed = 1;
  std::size_t min_cut_bytes = 0;  // 0 and 0: never cut
  std::size_t max_cut_bytes = 0;
  double max_delay_s = 0;  // per forwarded chunk of at most 4 KiB
};

class FaultProxy {
 public:
  explicit FaultProxy(FaultProxyOptions options) : options_(options), rng_(options.seed) {}
  ~FaultProxy() { Stop(); }

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
  int cuts() const { return cuts_.load(); }
  int connections() const { return connections_.load(); }

  void Stop() {
    stop_.store(true);
    wake_.Signal();
    if (acceptor_.joinable()) acceptor_.join();
    std::lock_guard<std::mutex> lock(mutex_);
    for (std::thread& t : pumps_) t.join();
    pumps_.clear();
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
      if (!server.ok()) continue;  // target down: the agent sees a closed connection
      ++connections_;
      std::size_t budget = SIZE_MAX;
      double delay_seed;
      {
        std::lock_guard<std::mutex> lock(mutex_);
        if (options_.max_cut_bytes > 0) {
          budget = options_.min_cut_bytes +
                   static_cast<std::size_t>(
                       rng_.Uniform() *
                       static_cast<double>(options_.max_cut_bytes - options_.min_cut_bytes));
        }
        delay_seed = rng_.Uniform();
        pumps_.emplace_back(
            [this, c = std::move(client), s = std::move(*server), budget, delay_seed]() mutable {
              Pump(std::move(c), std::move(s), budget, delay_seed);
            });
      }
    }
  }

  void Pump(UniqueFd client, UniqueFd server, std::size_t budget, double delay_seed) {
    Rng rng(static_cast<std::uint64_t>(delay_seed * 1e15));
    std::vector<std::uint8_t> buffer(4096);
    std::size_t forwarded = 0;
    while (!stop_.load()) {
      pollfd fds[3] = {
          {client.get(), POLLIN, 0}, {server.get(), POLLIN, 0}, {wake_.fd(), POLLIN, 0}};
      ::poll(fds, 3, -1);
      if (stop_.load()) return;
      if (fds[0].revents & (POLLIN | POLLHUP | POLLERR)) {
        StatusOr<std::size_t> n = ReadSome(client.get(), buffer.data(), buffer.size());
        if (!n.ok()) return;
        std::size_t count = *n;
        bool cut = false;
        if (forwarded + count >= budget) {
          count = budget - forwarded;
          cut = true;
        }
        if (options_.max_delay_s > 0) {
          // Simulated network latency (not synchronisation).
          std::this_thread::sleep_for(
              std::chrono::duration<double>(rng.Uniform() * options_.max_delay_s));
        }
        if (!WriteFully(server.get(), buffer.data(), count)) return;
        forwarded += count;
        if (cut) {
          ++cuts_;
          return;  // both sockets close here, in the middle of whatever was in flight
        }
      }
      if (fds[1].revents & (POLLIN | POLLHUP | POLLERR)) {
        StatusOr<std::size_t> n = ReadSome(server.get(), buffer.data(), buffer.size());
        if (!n.ok()) return;
        if (!WriteFully(client.get(), buffer.data(), *n)) return;
      }
    }
  }

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

  FaultProxyOptions options_;
  std::mutex mutex_;
  Rng rng_;
  UniqueFd listener_;
  std::uint16_t port_ = 0;
  std::atomic<std::uint16_t> target_{0};
  WakeFd wake_;
  std::atomic<bool> stop_{false};
  std::atomic<int> cuts_{0};
  std::atomic<int> connections_{0};
  std::thread acceptor_;
  std::vector<std::thread> pumps_;
};

}  // namespace ccmd::nettest
