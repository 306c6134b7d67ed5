// Fuzz target: a keyframe's RGB-D payload as the server unpacks it, the JPEG colour
// (libjpeg-turbo behind the header's size check) and the depth bitstream together. The input
// is the payload's two header bytes, a 16-bit length of the JPEG, the JPEG, then the depth.
// An accepted payload must give a colour image of the depth's size.

#include <opencv2/core.hpp>

#include "libccmd/codec/rgbd_payload.h"
#include "tests/fuzz/fuzz_target.h"

namespace ccmd::fuzz {

namespace {

std::vector<std::uint8_t> Serialize(const RgbdPayload& p) {
  std::vector<std::uint8_t> out = {p.downsample, p.depth_mode,
                                   static_cast<std::uint8_t>(p.colour_jpeg.size() & 0xff),
                                   static_cast<std::uint8_t>(p.colour_jpeg.size() >> 8)};
  out.insert(out.end(), p.colour_jpeg.begin(), p.colour_jpeg.end());
  out.insert(out.end(), p.depth.begin(), p.depth.end());
  return out;
}

}  // namespace

std::vector<std::vector<std::uint8_t>> FuzzSeeds() {
  RgbdFrame frame;
  frame.bgr.create(48, 64, CV_8UC3);
  frame.depth_mm.create(48, 64, CV_16UC1);
  for (int y = 0; y < 48; ++y) {
    for (int x = 0; x < 64; ++x) {
      frame.bgr.at<cv::Vec3b>(y, x) =
          cv::Vec3b(static_cast<std::uint8_t>(4 * x), static_cast<std::uint8_t>(5 * y),
                    static_cast<std::uint8_t>((x * y) % 256));
      frame.depth_mm.at<std::uint16_t>(y, x) =
          (x + y) % 11 == 0 ? 0 : static_cast<std::uint16_t>(900 + 13 * ((x + 2 * y) % 30));
    }
  }
  std::vector<std::vector<std::uint8_t>> seeds;
  for (int downsample : {1, 2, 4}) {
    RgbdEncodeOptions o;
    o.downsample = downsample;
    auto payload = EncodeRgbdPayload(frame, o);
    if (payload.ok() && payload->colour_jpeg.size() < 65536) seeds.push_back(Serialize(*payload));
  }
  return seeds;
}

}  // namespace ccmd::fuzz

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ccmd;
  if (size < 4) return 0;
  RgbdPayload payload;
  payload.downsample = data[0];
  payload.depth_mode = data[1];
  const std::size_t jpeg = std::min<std::size_t>(data[2] | (data[3] << 8), size - 4);
  payload.colour_jpeg.assign(data + 4, data + 4 + jpeg);
  payload.depth.assign(data + 4 + jpeg, data + size);
  RgbdDecodeOptions options;
  options.max_pixels = 1u << 18;  // keeps every allocation small
  auto decoded = DecodeRgbdPayload(payload, options);
  if (decoded.ok() && (decoded->bgr.size() != decoded->depth_mm.size() ||
                       decoded->bgr.type() != CV_8UC3 || decoded->depth_mm.type() != CV_16UC1)) {
    fuzz::FuzzFail("decoded colour and depth differ in size or type");
  }
  return 0;
}
