#include "libccmd/codec/rle.h"

#include <algorithm>
#include <cstring>
#include <string>

#include "proto/byte_io.h"

namespace ccmd {
namespace {

constexpr std::size_t kMinRun = 3;

void PutSample(std::uint16_t v, std::vector<std::uint8_t>* out) {
  out->push_back(static_cast<std::uint8_t>(v));
  out->push_back(static_cast<std::uint8_t>(v >> 8));
}

void PutVarint(std::uint64_t v, std::vector<std::uint8_t>* out) {
  while (v >= 0x80) {
    out->push_back(static_cast<std::uint8_t>(v | 0x80));
    v >>= 7;
  }
  out->push_back(static_cast<std::uint8_t>(v));
}

}  // namespace

void RleEncode(std::span<const std::uint16_t> s, std::vector<std::uint8_t>* out) {
  const std::size_t n = s.size();
  out->reserve(out->size() + n + 16);
  std::size_t literal_start = 0;
  std::size_t i = 0;
  auto flush_literals = [&](std::size_t end) {
    if (end == literal_start) return;
    PutVarint((end - literal_start - 1) << 1, out);
    for (std::size_t k = literal_start; k < end; ++k) PutSample(s[k], out);
  };
  while (i < n) {
    std::size_t run = 1;
    while (i + run < n && s[i + run] == s[i]) ++run;
    if (run >= kMinRun) {
      flush_literals(i);
      PutVarint(((run - 1) << 1) | 1, out);
      PutSample(s[i], out);
      i += run;
      literal_start = i;
    } else {
      i += run;
    }
  }
  flush_literals(n);
}

Status RleDecode(std::span<const std::uint8_t> in, std::size_t num_samples,
                 std::vector<std::uint16_t>* out) {
  out->resize(num_samples);
  std::uint16_t* dst = out->data();
  std::size_t produced = 0;
  ByteReader r(in);
  while (produced < num_samples) {
    std::uint64_t token;
    CCMD_RETURN_IF_ERROR(r.ReadVarint(&token));
    const std::uint64_t count = (token >> 1) + 1;
    if (count > num_samples - produced) {
      return Corrupt("run-length token of " + std::to_string(count) + " samples overshoots the " +
                     std::to_string(num_samples) + "-sample image");
    }
    if (token & 1) {
      std::uint16_t v;
      CCMD_RETURN_IF_ERROR(r.ReadU16(&v));
      std::fill(dst + produced, dst + produced + count, v);
    } else {
      if (r.remaining() / 2 < count) return Corrupt("run-length literals truncated");
      const std::uint8_t* p = r.current();
      for (std::uint64_t k = 0; k < count; ++k) {
        dst[produced + k] = static_cast<std::uint16_t>(p[2 * k] | (p[2 * k + 1] << 8));
      }
      CCMD_RETURN_IF_ERROR(r.Skip(2 * count));
    }
    produced += count;
  }
  return r.ExpectEnd();
}

}  // namespace ccmd
