#include "libccmd/codec/residual_bytes.h"

#include <string>

namespace ccmd {
namespace {

// Residual of each byte (0 for invalid and escape).
struct ByteResiduals {
  int residual[256];
  ByteResiduals() {
    residual[kInvalidResidualByte] = 0;
    for (int b = 1; b < 255; ++b) {
      const auto m = static_cast<std::uint32_t>(b - 1);
      residual[b] = static_cast<int>(m >> 1) ^ -static_cast<int>(m & 1);
    }
    residual[kEscapeResidualByte] = 0;
  }
};

}  // namespace

Status ResidualBytesToValues(const std::uint8_t* bytes, int width, int height, ByteReader* escapes,
                             int max_code, const std::uint16_t* to_value, int mask,
                             std::uint16_t* out) {
  static const ByteResiduals residuals;
  std::vector<int> up(width + 1, 0), cur(width + 1, 0);
  // Filled values of invalid pixels are predictions, so they stay within the range of the
  // valid ones; one unsigned comparison per pixel catches residuals that leave the range.
  unsigned outside = 0;
  for (int y = 0; y < height; ++y) {
    const std::uint8_t* in_row = bytes + static_cast<std::size_t>(y) * width;
    std::uint16_t* out_row = out + static_cast<std::size_t>(y) * width;
    up[0] = up[1];
    int a = up[1];
    for (int x = 0; x < width; ++x) {
      const std::uint8_t byte = in_row[x];
      int residual = residuals.residual[byte];
      if (byte == kEscapeResidualByte) [[unlikely]] {
        std::uint64_t m;
        CCMD_RETURN_IF_ERROR(escapes->ReadVarintAtMost(0xFFFFFFFFu, &m, "escaped residual"));
        const auto m32 = static_cast<std::uint32_t>(m);
        residual = static_cast<int>(m32 >> 1) ^ -static_cast<int>(m32 & 1);
      }
      a = MedianPredict(a, up[x + 1], up[x]) + residual;
      outside |= static_cast<unsigned>(a) > static_cast<unsigned>(max_code);
      cur[x + 1] = a;
      const std::uint16_t value = to_value[a & mask];
      out_row[x] = byte ? value : 0;
    }
    if (outside) {
      return Corrupt("depth decodes outside 0.." + std::to_string(max_code) + " in row " +
                     std::to_string(y));
    }
    std::swap(up, cur);
  }
  return escapes->ExpectEnd();
}

}  // namespace ccmd
