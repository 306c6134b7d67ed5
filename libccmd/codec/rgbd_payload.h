#pragma once

// Packing a keyframe's colour and depth into the wire format's RGB-D payload
// (proto/messages.h) and unpacking it: the depth bitstream of depth_codec.h and the JPEG of
// colour_codec.h, both at the same sampling rate r.

#include <string>

#include "libccmd/codec/colour_codec.h"
#include "libccmd/codec/depth_codec.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/util/status.h"
#include "proto/messages.h"

namespace ccmd {

// The agent's defaults. Depth: ccmd-bounded at 0.5 % (not the codec's 1 %): on the
// synthetic room with true poses it raises the dense map's mean error from 1.8 mm
// (lossless) to 2.6 mm and keeps the 95th percentile at 7 mm, under the map's 1 cm voxels,
// where 1 % gives 4.7 mm and 12.5 mm; it costs 8.3 kB per 320x240 real frame against 4.6 kB
// at 1 % and 17 kB lossless (docs/benchmarks/codec.md).
struct RgbdEncodeOptions {
  int downsample = 2;  // 1, 2, 4: r = 1, 0.5, 0.25 for both images
  DepthMode depth_mode = DepthMode::kBounded;
  int bound_e4 = 50;  // ccmd-bounded: 0.5 % of depth
  int jpeg_quality = 75;
  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct RgbdDecodeOptions {
  std::uint32_t max_pixels = 4096u * 4096u;  // per image

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// frame.depth_mm must be CV_16UC1 and frame.bgr CV_8UC3 (any size; resized to the depth's).
StatusOr<RgbdPayload> EncodeRgbdPayload(const RgbdFrame& frame, const RgbdEncodeOptions& options);

struct DecodedRgbd {
  cv::Mat bgr;       // CV_8UC3, the depth's size
  cv::Mat depth_mm;  // CV_16UC1
  int downsample = 1;
};

// Checks that the two images agree in size and with the payload's sampling rate and mode.
StatusOr<DecodedRgbd> DecodeRgbdPayload(const RgbdPayload& payload,
                                        const RgbdDecodeOptions& options = {});

}  // namespace ccmd
