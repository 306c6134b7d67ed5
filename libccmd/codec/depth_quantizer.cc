#include "libccmd/codec/depth_quantizer.h"

#include <algorithm>
#include <cstdlib>
#include <map>
#include <memory>
#include <mutex>

#include "libccmd/util/logging.h"

namespace ccmd {

std::uint16_t QuantizeEq6(std::uint16_t d) {
  if (d <= 200) return 0;
  if (d <= 3000) return d - 200;
  if (d <= 6000) return static_cast<std::uint16_t>(2800 + (d - 3000) / 2);
  if (d <= 12000) return static_cast<std::uint16_t>(4300 + (d - 6000) / 4);
  if (d <= 24000) return static_cast<std::uint16_t>(5800 + (d - 12000) / 8);
  return 0;
}

std::pair<std::uint16_t, std::uint16_t> Eq6Bin(std::uint16_t c) {
  if (c == 0) return {0, 0};
  if (c < 2800) return {static_cast<std::uint16_t>(c + 200), static_cast<std::uint16_t>(c + 200)};
  int lo, width;
  if (c < 4300) {
    lo = 3000 + 2 * (c - 2800);
    width = 2;
  } else if (c < 5800) {
    lo = 6000 + 4 * (c - 4300);
    width = 4;
  } else if (c < 7300) {
    lo = 12000 + 8 * (c - 5800);
    width = 8;
  } else {
    return {24000, 24000};
  }
  return {static_cast<std::uint16_t>(lo), static_cast<std::uint16_t>(lo + width - 1)};
}

std::uint16_t DequantizeEq6(std::uint16_t code) {
  const auto [first, last] = Eq6Bin(code);
  return static_cast<std::uint16_t>(first + (last - first + 1) / 2);
}

RelativeQuantizer::RelativeQuantizer(int bound_e4, int step_e4) : bound_e4_(bound_e4) {
  CCMD_CHECK(bound_e4 >= 1 && bound_e4 <= 2000) << bound_e4;
  // A grid a little wider than the bound compresses best on real depth (measured: 1.3 x
  // bound beats 1.0 x by 3 % and 1.6 x by 2 % on the 7-Scenes and TUM frames).
  if (step_e4 == 0) step_e4 = std::max(1, 13 * bound_e4 / 10);
  CCMD_CHECK(step_e4 >= 1 && step_e4 <= 2 * bound_e4) << step_e4;
  const std::int64_t e = bound_e4;
  // d is admissible to a representative g iff 1e4 * |g - d| <= e * d. Above g that holds up
  // to Up(g); a larger representative g' covers from Down(g') on. Consecutive
  // representatives must leave no depth uncovered: Down(g') <= Up(g) + 1.
  auto up = [e](std::int64_t g) { return 10000 * g / (10000 - e); };
  values_.push_back(0);  // code 0: invalid
  std::int64_t g = 1;
  while (true) {
    values_.push_back(static_cast<std::uint16_t>(g));
    if (up(g) >= 65535 || g == 65535) break;
    const std::int64_t widest = (up(g) + 1) * (10000 + e) / 10000;
    const std::int64_t wanted = std::max(g + 1, g + g * step_e4 / 10000);
    g = std::min<std::int64_t>({widest, wanted, 65535});
  }
  first_.assign(65536, 0);
  last_.assign(65536, 0);
  nearest_.assign(65536, 0);
  const std::int64_t n = static_cast<std::int64_t>(values_.size());
  std::int64_t lo = 1, hi = 1;
  for (std::int64_t d = 1; d <= 65535; ++d) {
    // Both ends only move up as d grows.
    while (lo < n && 10000 * (d - values_[lo]) > e * d) ++lo;
    if (hi < lo) hi = lo;
    while (hi + 1 < n && 10000 * (values_[hi + 1] - d) <= e * d) ++hi;
    CCMD_CHECK(lo < n && 10000 * std::abs(values_[lo] - d) <= e * d) << "grid gap at " << d;
    first_[d] = static_cast<std::uint16_t>(lo);
    last_[d] = static_cast<std::uint16_t>(hi);
    std::int64_t best = lo;
    for (std::int64_t c = lo + 1; c <= hi; ++c) {
      if (std::abs(values_[c] - d) < std::abs(values_[best] - d)) best = c;
    }
    nearest_[d] = static_cast<std::uint16_t>(best);
  }
}

const RelativeQuantizer& RelativeQuantizer::ForBound(int bound_e4) {
  static std::mutex mutex;
  static std::map<int, std::unique_ptr<RelativeQuantizer>> cache;
  std::lock_guard<std::mutex> lock(mutex);
  auto& slot = cache[bound_e4];
  if (!slot) slot = std::make_unique<RelativeQuantizer>(bound_e4);
  return *slot;
}

}  // namespace ccmd
