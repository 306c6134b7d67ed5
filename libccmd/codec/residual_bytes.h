#pragma once

// Prediction residuals as one byte per pixel, shared by ccmd-lossless and ccmd-quantised.
// Codes (0 = invalid pixel, else a depth or a quantiser code) are predicted with the
// median edge detector of LOCO-I / JPEG-LS on the left (a), upper (b) and upper-left (c)
// neighbours; an invalid pixel is "filled" with its prediction for its neighbours' sake.
// Each pixel becomes one byte:
//   0        invalid
//   1..254   zigzagged residual + 1 (residuals -127..126)
//   255      escape: the zigzagged residual follows as a varint in a side stream
// The left neighbour of a row's first pixel is the pixel above; the row above the first
// is all zero.

#include <cstdint>
#include <vector>

#include "libccmd/util/status.h"
#include "proto/byte_io.h"

namespace ccmd {

constexpr std::uint8_t kInvalidResidualByte = 0;
constexpr std::uint8_t kEscapeResidualByte = 255;

// The median of a, b and a + b - c; ternaries so that the compiler emits conditional moves.
inline int MedianPredict(int a, int b, int c) {
  const int lo = a < b ? a : b;
  const int hi = a < b ? b : a;
  const int p = a + b - c;
  const int q = p < hi ? p : hi;
  return q > lo ? q : lo;
}

// code_of(x, y) gives each pixel's code; bytes gets width * height bytes; escaped residuals
// are appended to *escapes.
template <typename CodeOf>
void CodesToResidualBytes(int width, int height, CodeOf&& code_of, std::uint8_t* bytes,
                          ByteWriter* escapes) {
  std::vector<int> up(width + 1, 0), cur(width + 1, 0);  // filled values at x + 1
  for (int y = 0; y < height; ++y) {
    std::uint8_t* out = bytes + static_cast<std::size_t>(y) * width;
    up[0] = up[1];  // the left neighbour of x = 0 is the pixel above
    int a = up[1];
    for (int x = 0; x < width; ++x) {
      const int predict = MedianPredict(a, up[x + 1], up[x]);
      const int v = code_of(x, y);
      std::uint8_t byte = kInvalidResidualByte;
      if (v) {
        const int r = v - predict;
        const std::uint32_t m =
            (static_cast<std::uint32_t>(r) << 1) ^ static_cast<std::uint32_t>(r >> 31);
        if (m < 254) {
          byte = static_cast<std::uint8_t>(m + 1);
        } else {
          byte = kEscapeResidualByte;
          escapes->PutVarint(m);
        }
      }
      out[x] = byte;
      a = v ? v : predict;
      cur[x + 1] = a;
    }
    std::swap(up, cur);
  }
}

// The inverse: codes from bytes and escapes, each code mapped through to_value[code & mask]
// (to_value has mask + 1 entries, e.g. a value table or dequantiser). Fails with kCorrupt
// if a code leaves 0..max_code, an escape is missing, or escapes are left over.
Status ResidualBytesToValues(const std::uint8_t* bytes, int width, int height, ByteReader* escapes,
                             int max_code, const std::uint16_t* to_value, int mask,
                             std::uint16_t* out);

}  // namespace ccmd
