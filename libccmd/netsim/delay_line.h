#pragma once

// One direction of the emulated link's delay stage: decides for each packet whether it is
// lost and when it may leave. Each packet's delay is drawn uniformly in
// [delay - jitter, delay + jitter] from a seeded generator, and a packet never leaves before
// the one ahead of it (order is kept, as on a single radio link). Bounded: beyond
// max_packets or max_bytes waiting, arrivals are dropped and counted. No clock of its own:
// callers pass the time, so tests are exact.

#include <cstdint>
#include <deque>
#include <limits>
#include <vector>

#include "libccmd/util/options_writer.h"
#include "libccmd/util/random.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct DelayLineOptions {
  double delay_s = 0;
  double jitter_s = 0;
  double loss = 0;
  std::uint64_t seed = 1;
  std::size_t max_packets = 20000;
  std::size_t max_bytes = 32u << 20;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct DelayLineStats {
  std::uint64_t arrived = 0, arrived_bytes = 0;
  std::uint64_t lost = 0;      // dropped by the loss draw
  std::uint64_t overflow = 0;  // dropped because the line was full
  std::uint64_t left = 0, left_bytes = 0;
};

class DelayLine {
 public:
  explicit DelayLine(const DelayLineOptions& options) : options_(options), rng_(options.seed) {}

  // A packet arrives at `now`: false if it is lost or the line is full, else it waits.
  bool Push(double now, std::vector<std::uint8_t> packet);
  // When the first waiting packet is due; +infinity when none waits.
  double NextDue() const {
    return queue_.empty() ? std::numeric_limits<double>::infinity() : queue_.front().due;
  }
  // Moves the first packet out if it is due at `now`.
  bool PopDue(double now, std::vector<std::uint8_t>* packet);
  std::size_t waiting() const { return queue_.size(); }
  const DelayLineStats& stats() const { return stats_; }

 private:
  struct Waiting {
    double due;
    std::vector<std::uint8_t> packet;
  };
  DelayLineOptions options_;
  Rng rng_;
  std::deque<Waiting> queue_;
  std::size_t bytes_ = 0;
  double last_due_ = -std::numeric_limits<double>::infinity();
  DelayLineStats stats_;
};

}  // namespace ccmd
