#pragma once

// ccmd-lossless: exact depth coding built for speed (encode plus decode several times
// faster than PNG) and size (well below zstd).
//
// 1. Histogram packing. Depth sensors that measure disparity (Kinect, RealSense) produce
//    only a few hundred distinct millimetre values per frame, spaced wider with range (about
//    7 mm at 1.5 m for the Kinect). When a frame's values are that sparse they are replaced
//    by their index in the sorted table of used values, which shrinks the residuals below
//    several-fold; the table travels in front.
// 2. Prediction: the median edge detector of LOCO-I / JPEG-LS on the left, upper and
//    upper-left neighbours; an invalid pixel is filled with its prediction for its
//    neighbours' sake.
// 3. Each pixel becomes one byte: 0 invalid, 1..254 the zigzagged residual plus one, 255 an
//    escape whose residual follows in a side stream (varint).
// 4. The bytes are Huffman-coded in four interleaved streams (huffman.h).
//
// Payload:
//   u8      1 = packed, 0 = plain depths
//   [packed: varint K, then K varints: first value, then gaps (value - previous - 1)]
//   varint  escape stream size, then the escape varints
//   Huffman-coded pixel bytes (width * height of them)

#include <cstdint>
#include <span>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

// depth: width * height millimetre values, 0 = invalid.
void EncodeDepthLossless(const std::uint16_t* depth, int width, int height,
                         std::vector<std::uint8_t>* out);

// Decodes exactly width * height values into depth; the payload must be used entirely.
Status DecodeDepthLossless(std::span<const std::uint8_t> in, int width, int height,
                           std::uint16_t* depth);

}  // namespace ccmd
