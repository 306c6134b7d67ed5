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
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "libccmd/net/socket.h"
#include "libccmd/util/random.h"
#include "tests/net/loopback_proxy.h"

namespace ccmd::nettest {

struct FaultProxyOptions {
  std::uint64_t seed = 1;
  std::size_t min_cut_bytes = 0;  // 0 and 0: never cut
  std::size_t max_cut_bytes = 0;
  double max_delay_s = 0;  // per forwarded chunk of at most 4 KiB
};

class FaultProxy : public LoopbackProxy {
 public:
  explicit FaultProxy(FaultProxyOptions options) : options_(options), rng_(options.seed) {}
  ~FaultProxy() override { Stop(); }
  int cuts() const { return cuts_.load(); }

 protected:
  std::function<void()> NewPump(UniqueFd client, UniqueFd server) override {
    std::size_t budget = SIZE_MAX;
    if (options_.max_cut_bytes > 0) {
      budget =
          options_.min_cut_bytes +
          static_cast<std::size_t>(rng_.Uniform() * static_cast<double>(options_.max_cut_bytes -
                                                                        options_.min_cut_bytes));
    }
    const double delay_seed = rng_.Uniform();
    auto pair =
        std::make_shared<std::pair<UniqueFd, UniqueFd>>(std::move(client), std::move(server));
    return [this, pair, budget, delay_seed] {
      Pump(std::move(pair->first), std::move(pair->second), budget, delay_seed);
    };
  }

 private:
  void Pump(UniqueFd client, UniqueFd server, std::size_t budget, double delay_seed) {
    Rng rng(static_cast<std::uint64_t>(delay_seed * 1e15));
    std::vector<std::uint8_t> buffer(4096);
    std::size_t forwarded = 0;
    while (!stopping()) {
      pollfd fds[3] = {
          {client.get(), POLLIN, 0}, {server.get(), POLLIN, 0}, {wake_fd(), POLLIN, 0}};
      ::poll(fds, 3, -1);
      if (stopping()) return;
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

  FaultProxyOptions options_;
  Rng rng_;  // accept thread only
  std::atomic<int> cuts_{0};
};

}  // namespace ccmd::nettest
