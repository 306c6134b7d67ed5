#pragma once

// Depth image coding for keyframes. A depth bitstream is self-describing (a 10-byte header
// gives mode, size, sampling rate and bound) and can be decoded on its own:
//
//   offset type field
//    0     u8   magic 0xD7
//    1     u8   bitstream version (1)
//    2     u8   mode (DepthMode)
//    3     u8   downsample factor applied before coding: 1, 2, 4 (r = 1, 0.5, 0.25)
//    4     u16  width of the coded (downsampled) image
//    6     u16  height
//    8     u16  relative error bound in units of 1e-4 (ccmd-bounded; 0 otherwise)
//   10     ...  mode payload
//
// Modes, named as in the benchmark:
//   ds              raw u16 samples (the paper's DS stage)                      exact
//   ds+rle          run-length (rle.h)                                          exact
//   ds+rle+lz77     run-length, then LZ77 (lz77.h)                              exact
//   ds+qt+rle       eq. 6 quantiser codes, run-length                          <= 4 mm
//   ds+qt+rle+lz77  eq. 6 quantiser codes, run-length, LZ77                    <= 4 mm
//   ccmd-lossless   histogram packing, prediction, contextual Huffman          exact
//                   (depth_lossless.h)
//   ccmd-quantised  eq. 6 quantiser, prediction residual bytes, LZ77 (whose   <= 4 mm
//                   matches code the runs), Huffman
//   ccmd-bounded    relative grid, in-loop choice within the bound,     <= bound * depth
//                   prediction, context tANS (predictive_coder.h)
// "Exact" and the error bounds hold on the downsampled image; the eq. 6 modes also set
// depths <= 200 mm or > 24 m to 0 (outside the quantiser's range).
//
// Decoding untrusted bytes returns an error (never crashes, never reads out of bounds, and
// allocates at most max_pixels samples, checked from the header before allocating).

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "libccmd/codec/depth_downsample.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

enum class DepthMode : std::uint8_t {
  kRaw = 0,
  kRle = 1,
  kRleLz77 = 2,
  kEq6Rle = 3,
  kEq6RleLz77 = 4,
  kLossless = 5,
  kQuantised = 6,
  kBounded = 7,
};
constexpr int kNumDepthModes = 8;

const char* DepthModeName(DepthMode mode);
StatusOr<DepthMode> ParseDepthMode(std::string_view name);
bool DepthModeIsLossless(DepthMode mode);

constexpr int kDefaultBoundE4 = 100;  // 1 % of depth

struct DepthEncodeOptions {
  DepthMode mode = DepthMode::kLossless;
  int downsample = 1;  // 1, 2 or 4, applied before coding
  DownsampleMethod downsample_method = DownsampleMethod::kMedianValid;
  int bound_e4 = kDefaultBoundE4;  // ccmd-bounded: 1..2000 (0.01 % .. 20 %)
  int lz77_chain = 64;             // LZ77 match search effort

  // Empty if valid, else the first problem.
  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct DepthDecodeOptions {
  std::uint32_t max_pixels = 4096u * 4096u;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct DepthHeader {
  DepthMode mode = DepthMode::kRaw;
  int downsample = 1;
  int width = 0;
  int height = 0;
  int bound_e4 = 0;
};
constexpr std::size_t kDepthHeaderSize = 10;

// depth_mm: CV_16UC1 millimetres, 0 = invalid; at most 65535 x 65535.
StatusOr<std::vector<std::uint8_t>> EncodeDepth(const cv::Mat& depth_mm,
                                                const DepthEncodeOptions& options);

// Returns the (downsampled) CV_16UC1 image; *header (optional) gets the header.
StatusOr<cv::Mat> DecodeDepth(std::span<const std::uint8_t> bytes,
                              const DepthDecodeOptions& options = {},
                              DepthHeader* header = nullptr);

StatusOr<DepthHeader> ParseDepthHeader(std::span<const std::uint8_t> bytes);

// The largest |decoded - original| a mode allows for an original depth d (mm), for depths
// the mode keeps; 0 for exact modes.
double DepthModeErrorBound(DepthMode mode, int bound_e4, std::uint16_t depth_mm);

}  // namespace ccmd
