#include "libccmd/codec/depth_lossless.h"

#include <algorithm>
#include <bit>
#include <cstring>
#include <string>

#include "libccmd/codec/huffman.h"
#include "libccmd/codec/residual_bytes.h"
#include "proto/byte_io.h"

namespace ccmd {
namespace {

// Returns the sorted table of values present, or an empty table when they are not sparse
// enough for packing to pay off.
std::vector<std::uint16_t> ValueTable(const std::uint16_t* depth, std::size_t n) {
  int lo = 65535, hi = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const int v = depth[i];
    if (v) {
      lo = std::min(lo, v);
      hi = std::max(hi, v);
    }
  }
  if (hi == 0) return {};
  std::vector<std::uint8_t> used(static_cast<std::size_t>(hi - lo + 1), 0);
  for (std::size_t i = 0; i < n; ++i) {
    if (depth[i]) used[depth[i] - lo] = 1;
  }
  std::vector<std::uint16_t> table;
  for (std::size_t k = 0; k < used.size(); ++k) {
    if (used[k]) table.push_back(static_cast<std::uint16_t>(lo + k));
  }
  if (2 * table.size() > used.size()) return {};
  return table;
}

}  // namespace

void EncodeDepthLossless(const std::uint16_t* depth, int width, int height,
                         std::vector<std::uint8_t>* out) {
  const std::size_t n = static_cast<std::size_t>(width) * height;
  const std::vector<std::uint16_t> table = ValueTable(depth, n);
  ByteWriter w;
  w.PutU8(table.empty() ? 0 : 1);
  // Value -> index + 1 over the table's range, or the identity (lo = 0, no table).
  int lo = 0;
  std::vector<std::uint16_t> index;
  if (!table.empty()) {
    w.PutVarint(table.size());
    int previous = -1;
    for (std::uint16_t v : table) {
      w.PutVarint(static_cast<std::uint64_t>(v - previous - 1));
      previous = v;
    }
    lo = table.front();
    index.assign(static_cast<std::size_t>(table.back() - lo + 1), 0);
    for (std::size_t k = 0; k < table.size(); ++k) {
      index[table[k] - lo] = static_cast<std::uint16_t>(k + 1);
    }
  }
  const std::uint16_t* to_code = index.empty() ? nullptr : index.data();

  std::vector<std::uint8_t> bytes(n);
  ByteWriter escapes;
  if (to_code) {
    CodesToResidualBytes(
        width, height,
        [&](int x, int y) {
          const int v = depth[static_cast<std::size_t>(y) * width + x];
          return v ? static_cast<int>(to_code[v - lo]) : 0;
        },
        bytes.data(), &escapes);
  } else {
    CodesToResidualBytes(
        width, height,
        [&](int x, int y) {
          return static_cast<int>(depth[static_cast<std::size_t>(y) * width + x]);
        },
        bytes.data(), &escapes);
  }
  w.PutVarint(escapes.size());
  w.PutBytes(escapes.bytes());
  out->insert(out->end(), w.data(), w.data() + w.size());
  HuffmanEncodeImage(bytes, width, height, out);
}

Status DecodeDepthLossless(std::span<const std::uint8_t> in, int width, int height,
                           std::uint16_t* depth) {
  const std::size_t n = static_cast<std::size_t>(width) * height;
  ByteReader r(in);
  std::uint8_t packed;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&packed));
  if (packed > 1) return Corrupt("lossless depth: unknown value-table flag");
  std::vector<std::uint16_t> table(1, 0);  // index 0: invalid
  if (packed) {
    std::uint64_t count;
    CCMD_RETURN_IF_ERROR(r.ReadVarintAtMost(65535, &count, "value table size"));
    if (count == 0) return Corrupt("empty value table");
    table.resize(count + 1);
    std::int64_t previous = -1;
    for (std::uint64_t k = 1; k <= count; ++k) {
      std::uint64_t gap;
      CCMD_RETURN_IF_ERROR(r.ReadVarintAtMost(65535, &gap, "value table gap"));
      previous += static_cast<std::int64_t>(gap) + 1;
      if (previous > 65535) return Corrupt("value table beyond 65535 mm");
      table[k] = static_cast<std::uint16_t>(previous);
    }
  }
  const int max_code = packed ? static_cast<int>(table.size() - 1) : 65535;
  std::uint64_t escape_size;
  CCMD_RETURN_IF_ERROR(r.ReadVarintAtMost(r.remaining(), &escape_size, "escape stream size"));
  std::span<const std::uint8_t> escape_bytes;
  CCMD_RETURN_IF_ERROR(r.ReadBytes(escape_size, &escape_bytes));
  ByteReader escapes(escape_bytes);
  std::vector<std::uint8_t> bytes;
  std::size_t used = 0;
  CCMD_RETURN_IF_ERROR(HuffmanDecodeImage(in.subspan(r.position()), width, height, &bytes, &used));
  if (bytes.size() != n) return Corrupt("lossless depth: wrong number of pixels");
  if (r.position() + used != in.size()) return Corrupt("trailing bytes after the depth data");

  // Code -> depth: the value table, or the identity for plain depths, padded to a power of
  // two so that a masked index is always in bounds (a corrupt row is caught after it).
  std::vector<std::uint16_t> to_value;
  if (packed) {
    to_value.assign(std::bit_ceil(table.size()), 0);
    std::copy(table.begin(), table.end(), to_value.begin());
  } else {
    to_value.resize(65536);
    for (int v = 0; v < 65536; ++v) to_value[v] = static_cast<std::uint16_t>(v);
  }
  const int mask = static_cast<int>(to_value.size() - 1);
  return ResidualBytesToValues(bytes.data(), width, height, &escapes, max_code, to_value.data(),
                               mask, depth);
}

}  // namespace ccmd
