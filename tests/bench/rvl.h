#pragma once

// RVL depth compression (A. D. Wilson, "Fast Lossless Depth Image Compression", ISS 2017),
// implemented from the paper's description as a benchmark peer: runs of zeros and of
// valid pixels, and the zigzagged differences between successive valid pixels, each
// written with a variable-length code of 3-bit groups and a continuation bit, packed
// eight nibbles to a 32-bit word.

#include <cstdint>
#include <span>
#include <vector>

namespace ccmd::bench {

std::vector<std::uint8_t> RvlEncode(std::span<const std::uint16_t> depth);
// Returns false on malformed input. Decodes exactly out.size() pixels.
bool RvlDecode(std::span<const std::uint8_t> bytes, std::span<std::uint16_t> out);

}  // namespace ccmd::bench
