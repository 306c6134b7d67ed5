#pragma once

// What a shaped evaluation link does, from a spec such as
// "rate=2.4mbit,delay=50ms,jitter=10ms,loss=0.02":
//   rate    bottleneck rate in each direction (tc units: bit, kbit, mbit, gbit = 10^3 steps
//           of bits per second; bps, kbps, mbps = bytes per second); absent: unlimited
//   delay   one-way delay added in each direction (us, ms, s; a bare number is seconds)
//   jitter  each packet's delay varies uniformly in [delay - jitter, delay + jitter]
//           (packets keep their order)
//   loss    probability that a packet is lost, in each direction (0.02 or 2%)
//   queue   how long packets may wait at the rate limiter before it drops them (tbf's
//           latency; default 100ms)
//   seed    seeds the loss and jitter draws (default 1)
// The same spec always describes the same link; the text is echoed in results.

#include <cstdint>
#include <string>

#include "libccmd/util/status.h"

namespace ccmd {

struct LinkSpec {
  double rate_bytes_per_s = 0;  // 0 = unlimited
  double delay_s = 0;
  double jitter_s = 0;
  double loss = 0;
  double queue_s = 0.1;
  std::uint64_t seed = 1;

  Status Validate() const;
  // Canonical text ("rate=300000bps,delay=0.05s,..."): parses back to the same spec.
  std::string ToString() const;
  bool shapes_rate() const { return rate_bytes_per_s > 0; }
};

StatusOr<LinkSpec> ParseLinkSpec(const std::string& text);

// "2.4mbit" -> 300000 bytes/s. Exposed for tests and for options that take one rate.
StatusOr<double> ParseRateBytesPerSecond(const std::string& text);
// "50ms" -> 0.05.
StatusOr<double> ParseDurationSeconds(const std::string& text);

}  // namespace ccmd
