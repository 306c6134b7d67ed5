#include "libccmd/codec/huffman.h"

#include <algorithm>
#include <array>
#include <cstring>
#include <string>

#include "proto/byte_io.h"

namespace ccmd {
namespace {

constexpr int kAlphabet = 256;
constexpr int kStreams = 4;
constexpr std::uint32_t kTableSize = 1u << kHuffmanMaxBits;

std::uint32_t ReverseBits(std::uint32_t code, int length) {
  std::uint32_t r = 0;
  for (int i = 0; i < length; ++i) r |= ((code >> i) & 1u) << (length - 1 - i);
  return r;
}

// Canonical codes from lengths, bit-reversed because streams are read least significant
// bit first.
std::array<std::uint32_t, kAlphabet> CanonicalCodes(const std::vector<int>& lengths) {
  std::array<int, kHuffmanMaxBits + 1> per_length{};
  for (int l : lengths) {
    if (l) ++per_length[l];
  }
  std::array<std::uint32_t, kHuffmanMaxBits + 2> next{};
  std::uint32_t code = 0;
  for (int l = 1; l <= kHuffmanMaxBits; ++l) {
    code = (code + per_length[l - 1]) << 1;
    next[l] = code;
  }
  std::array<std::uint32_t, kAlphabet> codes{};
  for (int s = 0; s < kAlphabet; ++s) {
    const int l = lengths[s];
    if (l) codes[s] = ReverseBits(next[l]++, l);
  }
  return codes;
}

// Sizes of the four quarters of n symbols.
std::array<std::size_t, kStreams> Quarters(std::size_t n) {
  const std::size_t q = (n + kStreams - 1) / kStreams;
  std::array<std::size_t, kStreams> sizes{};
  std::size_t left = n;
  for (int k = 0; k < kStreams; ++k) {
    sizes[k] = std::min(q, left);
    left -= sizes[k];
  }
  return sizes;
}

}  // namespace

std::vector<int> HuffmanCodeLengths(const std::uint32_t* counts, int alphabet, int max_bits) {
  std::vector<int> lengths(alphabet, 0);
  std::vector<int> used;
  for (int s = 0; s < alphabet; ++s) {
    if (counts[s]) used.push_back(s);
  }
  if (used.empty()) return lengths;
  if (used.size() == 1) {
    lengths[used[0]] = 1;
    return lengths;
  }
  // Huffman's construction with two queues: leaves sorted by weight, and the internal
  // nodes, which are created in non-decreasing weight order.
  std::sort(used.begin(), used.end(),
            [&](int a, int b) { return counts[a] != counts[b] ? counts[a] < counts[b] : a < b; });
  const std::size_t leaves = used.size();
  std::vector<std::uint64_t> weight(2 * leaves);
  std::vector<int> parent(2 * leaves, -1);
  for (std::size_t i = 0; i < leaves; ++i) weight[i] = counts[used[i]];
  std::size_t next_leaf = 0, next_node = leaves, end_node = leaves;
  auto take = [&]() {
    if (next_leaf < leaves && (next_node >= end_node || weight[next_leaf] <= weight[next_node])) {
      return next_leaf++;
    }
    return next_node++;
  };
  while (end_node < 2 * leaves - 1) {
    const std::size_t a = take(), b = take();
    weight[end_node] = weight[a] + weight[b];
    parent[a] = parent[b] = static_cast<int>(end_node);
    ++end_node;
  }
  std::vector<int> depth(2 * leaves - 1, 0);
  for (std::size_t i = 2 * leaves - 1; i-- > 0;) {
    if (parent[i] >= 0) depth[i] = depth[parent[i]] + 1;
  }
  for (std::size_t i = 0; i < leaves; ++i) lengths[used[i]] = depth[i];

  // Length limit: clamp, then lengthen the least frequent codes that are still short until
  // the Kraft sum fits (in units of 2^-max_bits it must not exceed 2^max_bits).
  bool over = false;
  for (int s : used) over |= lengths[s] > max_bits;
  if (!over) return lengths;
  std::uint64_t kraft = 0;
  for (int s : used) {
    lengths[s] = std::min(lengths[s], max_bits);
    kraft += std::uint64_t{1} << (max_bits - lengths[s]);
  }
  const std::uint64_t budget = std::uint64_t{1} << max_bits;
  while (kraft > budget) {
    for (int s : used) {  // least frequent first
      if (lengths[s] < max_bits) {
        kraft -= std::uint64_t{1} << (max_bits - lengths[s] - 1);
        ++lengths[s];
        break;
      }
    }
  }
  return lengths;
}

namespace {

// Writes a code table (the largest value, then the code lengths two to a byte) and returns
// each value's code and length in one word, code | length << 24. A table of one value gives
// it no bits at all.
std::array<std::uint32_t, kAlphabet> WriteCodeTable(const std::uint32_t* counts, ByteWriter* w) {
  int largest = kAlphabet - 1;
  while (largest > 0 && counts[largest] == 0) --largest;
  std::vector<int> lengths = HuffmanCodeLengths(counts, kAlphabet, kHuffmanMaxBits);
  int distinct = 0;
  for (int v = 0; v < kAlphabet; ++v) distinct += counts[v] > 0;
  if (distinct <= 1) std::fill(lengths.begin(), lengths.end(), 0);
  w->PutU8(static_cast<std::uint8_t>(largest));
  for (int v = 0; v <= largest; v += 2) {
    const int high = v + 1 <= largest ? lengths[v + 1] : 0;
    w->PutU8(static_cast<std::uint8_t>(lengths[v] | (high << 4)));
  }
  const std::array<std::uint32_t, kAlphabet> codes = CanonicalCodes(lengths);
  std::array<std::uint32_t, kAlphabet> packed{};
  for (int v = 0; v < kAlphabet; ++v) {
    packed[v] = codes[v] | (static_cast<std::uint32_t>(lengths[v]) << 24);
  }
  return packed;
}

// One stream of `count` symbols, `code_of(i)` the packed code of the i-th, written least
// significant bit first through a 64-bit accumulator.
template <typename CodeOf>
std::vector<std::uint8_t> PackStream(std::size_t count, const CodeOf& code_of) {
  std::vector<std::uint8_t> bytes(count * kHuffmanMaxBits / 8 + 16);
  std::uint8_t* p = bytes.data();
  std::size_t pos = 0;
  std::uint64_t acc = 0;
  int bits = 0;
  for (std::size_t i = 0; i < count; ++i) {
    const std::uint32_t c = code_of(i);
    acc |= static_cast<std::uint64_t>(c & 0xFFFFFF) << bits;
    bits += static_cast<int>(c >> 24);
    std::memcpy(p + pos, &acc, 8);
    pos += static_cast<std::size_t>(bits >> 3);
    acc >>= bits & ~7;
    bits &= 7;
  }
  if (bits > 0) p[pos++] = static_cast<std::uint8_t>(acc);
  bytes.resize(pos);
  return bytes;
}

// The sizes of all streams but the last, then the streams.
void WriteStreams(const std::array<std::vector<std::uint8_t>, kStreams>& streams, ByteWriter* w) {
  for (int k = 0; k + 1 < kStreams; ++k) w->PutVarint(streams[k].size());
  for (const auto& stream : streams) w->PutBytes(stream.data(), stream.size());
}

}  // namespace

void HuffmanEncode(std::span<const std::uint8_t> in, std::vector<std::uint8_t>* out) {
  ByteWriter w;
  w.PutVarint(in.size());
  if (in.empty()) {
    out->insert(out->end(), w.data(), w.data() + w.size());
    return;
  }
  std::array<std::uint32_t, kAlphabet> counts{};
  for (std::uint8_t b : in) ++counts[b];
  const std::array<std::uint32_t, kAlphabet> packed = WriteCodeTable(counts.data(), &w);
  const std::array<std::size_t, kStreams> sizes = Quarters(in.size());
  std::array<std::vector<std::uint8_t>, kStreams> streams;
  std::size_t begin = 0;
  for (int k = 0; k < kStreams; ++k) {
    const std::uint8_t* src = in.data() + begin;
    streams[k] = PackStream(sizes[k], [&](std::size_t i) { return packed[src[i]]; });
    begin += sizes[k];
  }
  WriteStreams(streams, &w);
  out->insert(out->end(), w.data(), w.data() + w.size());
}

namespace {

// One of the interleaved bit streams, read through a 64-bit accumulator.
struct Reader {
  const std::uint8_t* data;
  std::size_t size;
  std::size_t pos;
  std::uint64_t acc;
  int count;
};

// Every stream must end where its symbols did (within its last byte).
Status CheckStreamsUsed(const std::array<Reader, kStreams>& readers) {
  for (const Reader& rd : readers) {
    const std::uint64_t used = 8 * static_cast<std::uint64_t>(rd.pos) - rd.count;
    if (used > 8 * static_cast<std::uint64_t>(rd.size) || (used + 7) / 8 != rd.size) {
      return Corrupt("Huffman stream length does not match its symbols");
    }
  }
  return Status::Ok();
}

// The streams that follow the sizes of all but the last (which takes the rest of the input),
// copied into `padded` with 8 zero bytes after each, so refills may load 8 bytes at a clamped
// position.
Status SplitStreams(ByteReader* r, std::array<std::uint64_t, kStreams> stream_size,
                    std::vector<std::uint8_t>* padded, std::array<Reader, kStreams>* readers) {
  std::uint64_t total = 0;
  for (int k = 0; k + 1 < kStreams; ++k) total += stream_size[k];
  if (total > r->remaining()) return Corrupt("Huffman streams exceed the input");
  stream_size[kStreams - 1] = r->remaining() - total;
  padded->assign(r->remaining() + 8 * kStreams + 8, 0);
  std::size_t offset = 0;
  for (int k = 0; k < kStreams; ++k) {
    std::span<const std::uint8_t> bytes;
    CCMD_RETURN_IF_ERROR(r->ReadBytes(stream_size[k], &bytes));
    std::uint8_t* dst = padded->data() + offset;
    if (!bytes.empty()) std::memcpy(dst, bytes.data(), bytes.size());
    (*readers)[k] = Reader{dst, bytes.size(), 0, 0, 0};
    offset += bytes.size() + 8;
  }
  return Status::Ok();
}

}  // namespace

Status HuffmanDecode(std::span<const std::uint8_t> in, std::size_t max_output,
                     std::vector<std::uint8_t>* out, std::size_t* consumed) {
  ByteReader r(in);
  std::uint64_t n;
  CCMD_RETURN_IF_ERROR(r.ReadVarint(&n));
  if (n > max_output) {
    return OutOfRange("Huffman stream claims " + std::to_string(n) + " bytes, more than " +
                      std::to_string(max_output));
  }
  if (n == 0) {
    out->clear();
    if (consumed) *consumed = r.position();
    return Status::Ok();
  }
  std::uint8_t largest;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&largest));
  std::vector<int> lengths(kAlphabet, 0);
  for (int s = 0; s <= largest; s += 2) {
    std::uint8_t b;
    CCMD_RETURN_IF_ERROR(r.ReadU8(&b));
    lengths[s] = b & 15;
    if (s + 1 <= largest) lengths[s + 1] = b >> 4;
    if (lengths[s] > kHuffmanMaxBits || (s + 1 <= largest && lengths[s + 1] > kHuffmanMaxBits)) {
      return Corrupt("Huffman code length above " + std::to_string(kHuffmanMaxBits));
    }
  }
  std::uint64_t kraft = 0;
  int coded = 0;
  for (int l : lengths) {
    if (l) {
      kraft += std::uint64_t{1} << (kHuffmanMaxBits - l);
      ++coded;
    }
  }
  std::array<std::uint64_t, kStreams> stream_size{};
  for (int k = 0; k + 1 < kStreams; ++k) {
    CCMD_RETURN_IF_ERROR(r.ReadVarintAtMost(r.remaining(), &stream_size[k], "Huffman stream"));
  }
  if (coded == 0) {
    // One distinct value (the largest present) and no bits.
    for (int k = 0; k + 1 < kStreams; ++k) {
      if (stream_size[k]) return Corrupt("Huffman stream without codes has bits");
    }
    out->assign(n, largest);
    if (consumed) *consumed = r.position();
    return Status::Ok();
  }
  if (kraft > kTableSize || coded < 2) return Corrupt("Huffman code lengths are not a prefix code");
  // A code of n symbols needs at least one bit per symbol.
  if (n > 8 * static_cast<std::uint64_t>(r.remaining())) {
    return Corrupt("Huffman stream too short for " + std::to_string(n) + " symbols");
  }

  // table[next 11 bits] = value << 4 | code length. Bit patterns no code starts with
  // (possible when the code is incomplete) decode as value 0 of length 1; only corrupt
  // input reaches them, and the stream length check at the end catches it.
  std::vector<std::uint16_t> table(kTableSize, 1);
  const std::array<std::uint32_t, kAlphabet> codes = CanonicalCodes(lengths);
  for (int s = 0; s < kAlphabet; ++s) {
    const int l = lengths[s];
    if (!l) continue;
    for (std::uint32_t fill = codes[s]; fill < kTableSize; fill += 1u << l) {
      table[fill] = static_cast<std::uint16_t>((s << 4) | l);
    }
  }

  std::vector<std::uint8_t> padded;
  std::array<Reader, kStreams> readers;
  CCMD_RETURN_IF_ERROR(SplitStreams(&r, stream_size, &padded, &readers));

  out->resize(n);
  const std::array<std::size_t, kStreams> sizes = Quarters(n);
  std::array<std::uint8_t*, kStreams> dst;
  std::size_t begin = 0;
  for (int k = 0; k < kStreams; ++k) {
    dst[k] = out->data() + begin;
    begin += sizes[k];
  }
  const std::uint16_t* t = table.data();
  auto decode_one = [&](Reader& rd, std::uint8_t* o) {
    if (rd.count < kHuffmanMaxBits) {
      std::uint64_t word;
      std::memcpy(&word, rd.data + std::min(rd.pos, rd.size), 8);
      rd.acc |= word << rd.count;
      rd.pos += static_cast<std::size_t>((63 - rd.count) >> 3);
      rd.count |= 56;
    }
    const std::uint32_t e = t[rd.acc & (kTableSize - 1)];
    const int l = static_cast<int>(e & 15);
    rd.acc >>= l;
    rd.count -= l;
    *o = static_cast<std::uint8_t>(e >> 4);
  };
  // The first three quarters have the same size; the last may be shorter.
  std::size_t i = 0;
  for (; i < sizes[3]; ++i) {
    decode_one(readers[0], dst[0] + i);
    decode_one(readers[1], dst[1] + i);
    decode_one(readers[2], dst[2] + i);
    decode_one(readers[3], dst[3] + i);
  }
  for (; i < sizes[0]; ++i) {
    for (int k = 0; k < kStreams - 1; ++k) {
      if (i < sizes[k]) decode_one(readers[k], dst[k] + i);
    }
  }
  CCMD_RETURN_IF_ERROR(CheckStreamsUsed(readers));
  if (consumed) *consumed = r.position();
  return Status::Ok();
}

namespace {

constexpr int kClasses = 4;
constexpr int kContexts = kClasses * kClasses;

// invalid, exact, small (|residual| <= 2), large; and the same times kClasses (the
// upper neighbour's part of a context).
struct ByteClasses {
  std::uint8_t of[256];
  std::uint8_t up[256];
  ByteClasses() {
    for (int b = 0; b < 256; ++b) {
      of[b] = static_cast<std::uint8_t>(b == 0 ? 0 : b == 1 ? 1 : b <= 5 ? 2 : 3);
      up[b] = static_cast<std::uint8_t>(of[b] * kClasses);
    }
  }
};
const ByteClasses& Classes() {
  static const ByteClasses classes;
  return classes;
}

// Rows of each of the four bands.
std::array<int, kStreams> Bands(int height) {
  std::array<int, kStreams> rows{};
  int left = height;
  const int per = (height + kStreams - 1) / kStreams;
  for (int k = 0; k < kStreams; ++k) {
    rows[k] = std::min(per, left);
    left -= rows[k];
  }
  return rows;
}

// Context of pixel x in a row, given the row above (null for a band's first row).
inline int ContextAt(const std::uint8_t* row, const std::uint8_t* above, int x,
                     const std::uint8_t* classes) {
  const int up = above ? classes[above[x]] : 0;
  const int left = x ? classes[row[x - 1]] : 0;
  return up * kClasses + left;
}

}  // namespace

void HuffmanEncodeImage(std::span<const std::uint8_t> in, int width, int height,
                        std::vector<std::uint8_t>* out) {
  const std::uint8_t* classes = Classes().of;
  const std::array<int, kStreams> bands = Bands(height);
  std::vector<std::uint32_t> counts(kContexts * kAlphabet, 0);
  std::vector<std::uint8_t> contexts(in.size());
  {
    int y = 0;
    for (int k = 0; k < kStreams; ++k) {
      for (int r = 0; r < bands[k]; ++r, ++y) {
        const std::uint8_t* row = in.data() + static_cast<std::size_t>(y) * width;
        const std::uint8_t* above = r ? row - width : nullptr;
        std::uint8_t* ctx = contexts.data() + static_cast<std::size_t>(y) * width;
        for (int x = 0; x < width; ++x) {
          ctx[x] = static_cast<std::uint8_t>(ContextAt(row, above, x, classes));
          ++counts[ctx[x] * kAlphabet + row[x]];
        }
      }
    }
  }
  ByteWriter w;
  // code | length << 24 per (context, value)
  std::vector<std::uint32_t> packed(kContexts * kAlphabet, 0);
  for (int c = 0; c < kContexts; ++c) {
    const std::array<std::uint32_t, kAlphabet> table = WriteCodeTable(&counts[c * kAlphabet], &w);
    std::copy(table.begin(), table.end(), packed.begin() + c * kAlphabet);
  }
  std::array<std::vector<std::uint8_t>, kStreams> streams;
  std::size_t begin = 0;
  for (int k = 0; k < kStreams; ++k) {
    const std::size_t count = static_cast<std::size_t>(bands[k]) * width;
    const std::uint8_t* ctx = contexts.data() + begin;
    const std::uint8_t* src = in.data() + begin;
    streams[k] =
        PackStream(count, [&](std::size_t i) { return packed[ctx[i] * kAlphabet + src[i]]; });
    begin += count;
  }
  WriteStreams(streams, &w);
  out->insert(out->end(), w.data(), w.data() + w.size());
}

Status HuffmanDecodeImage(std::span<const std::uint8_t> in, int width, int height,
                          std::vector<std::uint8_t>* out, std::size_t* consumed) {
  if (width <= 0 || height <= 0) return InvalidArgument("empty image");
  ByteReader r(in);
  // table[context][next 11 bits] = value << 4 | code length. Patterns no code starts with
  // decode as value 0 of length 1 (only corrupt input reaches them; the stream length check
  // catches it).
  std::vector<std::uint16_t> table(static_cast<std::size_t>(kContexts) * kTableSize);
  std::vector<int> lengths(kAlphabet);
  for (int c = 0; c < kContexts; ++c) {
    std::uint8_t largest;
    CCMD_RETURN_IF_ERROR(r.ReadU8(&largest));
    std::fill(lengths.begin(), lengths.end(), 0);
    for (int v = 0; v <= largest; v += 2) {
      std::uint8_t b;
      CCMD_RETURN_IF_ERROR(r.ReadU8(&b));
      lengths[v] = b & 15;
      if (v + 1 <= largest) lengths[v + 1] = b >> 4;
    }
    std::uint64_t kraft = 0;
    int coded = 0;
    for (int l : lengths) {
      if (l > kHuffmanMaxBits) return Corrupt("Huffman code length above 11");
      if (l) {
        kraft += std::uint64_t{1} << (kHuffmanMaxBits - l);
        ++coded;
      }
    }
    std::uint16_t* t = &table[static_cast<std::size_t>(c) * kTableSize];
    if (coded == 0) {  // a single value, no bits
      std::fill(t, t + kTableSize, static_cast<std::uint16_t>(largest << 4));
      continue;
    }
    if (kraft > kTableSize || coded < 2)
      return Corrupt("Huffman code lengths are not a prefix code");
    std::fill(t, t + kTableSize, static_cast<std::uint16_t>(1));
    const std::array<std::uint32_t, kAlphabet> codes = CanonicalCodes(lengths);
    for (int v = 0; v < kAlphabet; ++v) {
      const int l = lengths[v];
      if (!l) continue;
      for (std::uint32_t fill = codes[v]; fill < kTableSize; fill += 1u << l) {
        t[fill] = static_cast<std::uint16_t>((v << 4) | l);
      }
    }
  }
  std::array<std::uint64_t, kStreams> stream_size{};
  for (int k = 0; k + 1 < kStreams; ++k) {
    CCMD_RETURN_IF_ERROR(r.ReadVarintAtMost(r.remaining(), &stream_size[k], "Huffman stream"));
  }
  std::vector<std::uint8_t> padded;
  std::array<Reader, kStreams> readers;
  CCMD_RETURN_IF_ERROR(SplitStreams(&r, stream_size, &padded, &readers));

  out->resize(static_cast<std::size_t>(width) * height);
  const std::array<int, kStreams> bands = Bands(height);
  std::array<std::uint8_t*, kStreams> band_start;
  {
    std::size_t begin = 0;
    for (int k = 0; k < kStreams; ++k) {
      band_start[k] = out->data() + begin;
      begin += static_cast<std::size_t>(bands[k]) * width;
    }
  }
  const ByteClasses& classes = Classes();
  const std::uint16_t* tables = table.data();
  const std::vector<std::uint8_t> zero_row(width, 0);  // "above" of a band's first row
  // Decodes pixel x of a row; left is the class of the pixel before it (0 at x = 0).
  auto decode_one = [&](Reader& rd, std::uint8_t* row, const std::uint8_t* above, int x,
                        int& left) {
    if (rd.count < kHuffmanMaxBits) {
      std::uint64_t word;
      std::memcpy(&word, rd.data + std::min(rd.pos, rd.size), 8);
      rd.acc |= word << rd.count;
      rd.pos += static_cast<std::size_t>((63 - rd.count) >> 3);
      rd.count |= 56;
    }
    const int context = classes.up[above[x]] + left;
    const std::uint32_t e = tables[(static_cast<std::size_t>(context) << kHuffmanMaxBits) |
                                   (rd.acc & (kTableSize - 1))];
    const int l = static_cast<int>(e & 15);
    rd.acc >>= l;
    rd.count -= l;
    const auto value = static_cast<std::uint8_t>(e >> 4);
    row[x] = value;
    left = classes.of[value];
  };
  // Rows of the four bands in lockstep (the last band may be shorter).
  for (int r = 0; r < bands[0]; ++r) {
    std::array<std::uint8_t*, kStreams> rows;
    std::array<const std::uint8_t*, kStreams> aboves;
    int active = 0;
    for (int k = 0; k < kStreams; ++k) {
      rows[k] = band_start[k] + static_cast<std::size_t>(r) * width;
      aboves[k] = r ? rows[k] - width : zero_row.data();
      active += r < bands[k];
    }
    if (active == kStreams) {
      int l0 = 0, l1 = 0, l2 = 0, l3 = 0;
      for (int x = 0; x < width; ++x) {
        decode_one(readers[0], rows[0], aboves[0], x, l0);
        decode_one(readers[1], rows[1], aboves[1], x, l1);
        decode_one(readers[2], rows[2], aboves[2], x, l2);
        decode_one(readers[3], rows[3], aboves[3], x, l3);
      }
    } else {
      for (int k = 0; k < kStreams; ++k) {
        if (r >= bands[k]) continue;
        int left = 0;
        for (int x = 0; x < width; ++x) decode_one(readers[k], rows[k], aboves[k], x, left);
      }
    }
  }
  CCMD_RETURN_IF_ERROR(CheckStreamsUsed(readers));
  if (consumed) *consumed = r.position();
  return Status::Ok();
}

}  // namespace ccmd
