// Fuzz target: the depth bitstream decoder, every mode (run-length, LZ77, Huffman, tANS,
// the quantisers). A decoded image must have the size its header announced.

#include <opencv2/core/mat.hpp>

#include "libccmd/codec/depth_codec.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  cv::Mat depth(24, 32, CV_16UC1);
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) {
      depth.at<std::uint16_t>(y, x) =
          (x + y) % 9 == 0 ? 0 : static_cast<std::uint16_t>(800 + 7 * ((x * 3 + y * 5) % 40));
    }
  }
  std::vector<std::vector<std::uint8_t>> seeds;
  for (int m = 0; m < kNumDepthModes; ++m) {
    DepthEncodeOptions o;
    o.mode = static_cast<DepthMode>(m);
    seeds.push_back(*EncodeDepth(depth, o));
  }
  return seeds;
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  DepthDecodeOptions options;
  options.max_pixels = 1u << 18;  // keeps every allocation small
  DepthHeader header;
  auto image = DecodeDepth(std::span(data, size), options, &header);
  if (image.ok() &&
      (image->cols != header.width || image->rows != header.height || image->type() != CV_16UC1)) {
    fuzz::FuzzFail("decoded depth does not match its header");
  }
  return 0;
}
