#pragma once

// Depth quantisers (depth in uint16 millimetres, 0 = invalid; code 0 = invalid).
//
// Eq6: the CCMD-SLAM paper's eq. 6 with its typo corrected (fourth branch 6000, not 1500),
// as in the project's design notes. Integer division rounds down, so every code is a bin of
// consecutive depths:
//   d <= 200                -> 0 (invalid)
//   200 < d <= 3000         -> d - 200                      bins of 1 mm  (codes 1..2800)
//   3000 < d <= 6000        -> 2800 + (d - 3000) / 2        bins of 2 mm  (codes 2800..4300)
//   6000 < d <= 12000       -> 4300 + (d - 6000) / 4        bins of 4 mm  (codes 4300..5800)
//   12000 < d <= 24000      -> 5800 + (d - 12000) / 8       bins of 8 mm  (codes 5800..7300)
//   d > 24000               -> 0 (invalid)
// Codes fit in 13 bits (at most 7300). The boundary depths 3000, 6000, 12000 share a code
// with the next one or three depths above them (e.g. code 2800 is {3000, 3001}), so the bins
// are [lo, lo + w) with lo = 3000 + 2 (c - 2800) etc., and code 7300 is {24000} alone.
// Decoding returns the bin's centre, lo + w / 2 for even widths (the upper of the two middle
// depths): the error is 0 below 3000 mm and at most w / 2 = 1, 2, 4 mm from 3000, 6000,
// 12000 mm on (each boundary depth shares its bin with the depths just above it).
//
// Relative: a grid of representative depths whose spacing grows with depth, and for every
// depth d the interval of grid codes whose representative lies within bound * d of it
// (integer arithmetic, so encoder and decoder build identical grids). The grid spacing is
// about `step` (relative) but never so wide that a depth has no admissible code; with
// step = bound each depth has about two admissible codes, which lets the encoder pick the
// one its predictor expects (see predictive_coder.h). The bound is in units of 0.01 %
// (100 = 1 %, the RealSense D435's typical accuracy).

#include <cstdint>
#include <utility>
#include <vector>

namespace ccmd {

constexpr std::uint16_t kEq6MaxCode = 7300;

std::uint16_t QuantizeEq6(std::uint16_t depth_mm);
// Precondition: code <= kEq6MaxCode (callers decoding untrusted codes check first).
std::uint16_t DequantizeEq6(std::uint16_t code);
// The depths [first, last] mapped to `code` (code 1..7300).
std::pair<std::uint16_t, std::uint16_t> Eq6Bin(std::uint16_t code);

class RelativeQuantizer {
 public:
  // bound_e4: relative bound in units of 1e-4, 1..2000 (0.01 % .. 20 %); step_e4: the grid's
  // relative spacing, 1..2 * bound_e4 (0: the default, 1.3 times the bound).
  explicit RelativeQuantizer(int bound_e4, int step_e4 = 0);

  int bound_e4() const { return bound_e4_; }
  // Codes are 0 (invalid) .. num_codes() - 1.
  int num_codes() const { return static_cast<int>(values_.size()); }
  std::uint16_t Dequantize(std::uint16_t code) const { return values_[code]; }
  const std::uint16_t* value_table() const { return values_.data(); }  // num_codes() entries
  // The admissible codes of a depth (0, 0 for depth 0): every code c in [first, last] has
  // |Dequantize(c) - depth| <= bound * depth.
  std::uint16_t FirstAdmissible(std::uint16_t depth_mm) const { return first_[depth_mm]; }
  std::uint16_t LastAdmissible(std::uint16_t depth_mm) const { return last_[depth_mm]; }
  // The admissible code nearest to the depth.
  std::uint16_t Quantize(std::uint16_t depth_mm) const { return nearest_[depth_mm]; }

  // Shared instance per bound with the default step (tables of 400 kB, built once,
  // thread-safe).
  static const RelativeQuantizer& ForBound(int bound_e4);

 private:
  int bound_e4_;
  std::vector<std::uint16_t> values_;                  // code -> representative depth
  std::vector<std::uint16_t> first_, last_, nearest_;  // depth -> codes
};

}  // namespace ccmd
