#include "libccmd/codec/tans.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <string>

#include "libccmd/util/logging.h"
#include "proto/byte_io.h"

namespace ccmd {
namespace {

// Scales counts to frequencies summing to kTansSize, every used symbol at least 1.
void Normalize(const std::uint32_t* counts, int alphabet, std::uint32_t* freq) {
  std::uint64_t total = 0;
  for (int s = 0; s < alphabet; ++s) total += counts[s];
  std::fill(freq, freq + alphabet, 0);
  if (total == 0) return;
  std::int64_t sum = 0;
  int largest = 0;
  for (int s = 0; s < alphabet; ++s) {
    if (counts[s] == 0) continue;
    const std::uint64_t f =
        std::max<std::uint64_t>(1, counts[s] * std::uint64_t{kTansSize} / total);
    freq[s] = static_cast<std::uint32_t>(f);
    sum += static_cast<std::int64_t>(f);
    if (counts[s] > counts[largest]) largest = s;
  }
  std::int64_t diff = static_cast<std::int64_t>(kTansSize) - sum;
  if (diff >= 0) {
    freq[largest] += static_cast<std::uint32_t>(diff);
    return;
  }
  // Too many rare symbols were raised to 1: take the excess from the largest frequencies.
  while (diff < 0) {
    int top = 0;
    for (int s = 1; s < alphabet; ++s) {
      if (freq[s] > freq[top]) top = s;
    }
    CCMD_CHECK_GT(freq[top], 1u);
    --freq[top];
    ++diff;
  }
}

// Spreads each symbol's occurrences over the table (the step is odd, so every position is
// visited once); the same on both sides.
void Spread(const std::uint32_t* freq, int alphabet, std::uint8_t* symbol_at) {
  constexpr std::uint32_t kStep = (kTansSize >> 1) + (kTansSize >> 3) + 3;
  std::uint32_t position = 0;
  for (int s = 0; s < alphabet; ++s) {
    for (std::uint32_t i = 0; i < freq[s]; ++i) {
      symbol_at[position] = static_cast<std::uint8_t>(s);
      position = (position + kStep) & (kTansSize - 1);
    }
  }
}

// Frequencies travel as 5-bit log weights q (0 = absent): a symbol's weight is about
// 2^((q - 1) / 2), fixed here as integers (16 * 2^((q - 1) / 2), rounded) so that both
// sides normalise identically. Half-bit steps cost well under 1 % in coding efficiency and
// make a context's table a few bytes.
constexpr int kWeightBits = 5;  // q - 1 of a present symbol
constexpr int kMaxWeight = 1 << kWeightBits;
constexpr std::uint32_t kWeights[kMaxWeight + 1] = {
    0,     16,    23,    32,    45,    64,     91,     128,    181,    256,    362,
    512,   724,   1024,  1448,  2048,  2896,   4096,   5793,   8192,   11585,  16384,
    23170, 32768, 46341, 65536, 92682, 131072, 185364, 262144, 370728, 524288, 741455};
constexpr int kSizeBits = 7;  // symbols in a context's table, 0..64

// The log weight closest to count / largest (the largest count gets kMaxWeight).
int LogWeight(std::uint32_t count, std::uint32_t largest) {
  if (count == 0) return 0;
  const double steps = 2.0 * std::log2(static_cast<double>(largest) / count);
  return std::max(1, kMaxWeight - static_cast<int>(std::lround(steps)));
}

class TableBitWriter {
 public:
  void Put(std::uint32_t v, int n) {
    acc_ |= static_cast<std::uint64_t>(v) << count_;
    count_ += n;
    while (count_ >= 8) {
      bytes_.push_back(static_cast<std::uint8_t>(acc_));
      acc_ >>= 8;
      count_ -= 8;
    }
  }
  std::vector<std::uint8_t> Finish() {
    if (count_ > 0) bytes_.push_back(static_cast<std::uint8_t>(acc_));
    return std::move(bytes_);
  }

 private:
  std::vector<std::uint8_t> bytes_;
  std::uint64_t acc_ = 0;
  int count_ = 0;
};

}  // namespace

void TansEncode(std::span<const std::uint16_t> items, int num_contexts, int alphabet,
                const std::uint32_t* given_counts, std::vector<std::uint8_t>* out,
                std::size_t* table_bytes) {
  CCMD_CHECK(num_contexts >= 1 && num_contexts <= kTansMaxContexts && alphabet >= 1 &&
             alphabet <= kTansMaxAlphabet);
  const std::size_t entries = static_cast<std::size_t>(num_contexts) * kTansMaxAlphabet;
  std::vector<std::uint32_t> counts;
  if (!given_counts) {
    counts.assign(entries, 0);
    for (std::uint16_t item : items) ++counts[item];
    given_counts = counts.data();
  }

  // Per (context, symbol): how to encode from a state X in [L, 2L): with f the symbol's
  // frequency and nb0 = log2 L - floor(log2 f), emit nb = nb0 - (X < f << nb0) bits so that
  // X >> nb lands in [f, 2f), then the next state is next_state[offset + (X >> nb)].
  struct Entry {
    std::uint32_t threshold;  // f << nb0
    std::int32_t offset;      // start of the symbol's states in next_state, minus f
    std::uint8_t nb0;
  };
  std::vector<Entry> encode(entries, Entry{0, 0, 0});
  std::vector<std::uint16_t> next_state(static_cast<std::size_t>(num_contexts) * kTansSize);
  std::vector<std::uint32_t> freq(alphabet);
  std::vector<std::uint8_t> symbol_at(kTansSize);
  std::vector<std::uint32_t> cumulative(alphabet);
  TableBitWriter table_bits;
  std::vector<std::uint32_t> weights(alphabet);
  for (int c = 0; c < num_contexts; ++c) {
    const std::uint32_t* ctx_counts = given_counts + static_cast<std::size_t>(c) * kTansMaxAlphabet;
    std::uint32_t largest = 0;
    int size = 0;
    for (int s = 0; s < alphabet; ++s) {
      largest = std::max(largest, ctx_counts[s]);
      if (ctx_counts[s]) size = s + 1;
    }
    table_bits.Put(static_cast<std::uint32_t>(size), kSizeBits);
    if (size == 0) continue;
    for (int s = 0; s < alphabet; ++s) {
      const int q = s < size ? LogWeight(ctx_counts[s], largest) : 0;
      if (s < size) {
        table_bits.Put(q ? 1 : 0, 1);  // present?
        if (q) table_bits.Put(static_cast<std::uint32_t>(q - 1), kWeightBits);
      }
      weights[s] = kWeights[q];
    }
    Normalize(weights.data(), alphabet, freq.data());
    std::uint32_t total = 0;
    for (int s = 0; s < alphabet; ++s) {
      cumulative[s] = total;
      total += freq[s];
    }
    Spread(freq.data(), alphabet, symbol_at.data());
    std::uint16_t* states = &next_state[static_cast<std::size_t>(c) * kTansSize];
    std::vector<std::uint32_t> seen(cumulative);
    for (std::uint32_t u = 0; u < kTansSize; ++u) {
      states[seen[symbol_at[u]]++] = static_cast<std::uint16_t>(kTansSize + u);
    }
    for (int s = 0; s < alphabet; ++s) {
      if (!freq[s]) continue;
      Entry& e = encode[static_cast<std::size_t>(c) * kTansMaxAlphabet + s];
      e.nb0 = static_cast<std::uint8_t>(kTansLog - (std::bit_width(freq[s]) - 1));
      e.threshold = freq[s] << e.nb0;
      e.offset =
          static_cast<std::int32_t>(static_cast<std::size_t>(c) * kTansSize + cumulative[s]) -
          static_cast<std::int32_t>(freq[s]);
    }
  }
  const std::vector<std::uint8_t> table_section = table_bits.Finish();
  if (table_bytes) *table_bytes = table_section.size();
  ByteWriter w;
  w.PutBytes(table_section.data(), table_section.size());

  // Backwards over the items, bits written forwards (the decoder reads them back to front).
  std::vector<std::uint8_t> bits(items.size() * 2 + 16);
  std::uint8_t* const bit_out = bits.data();
  std::size_t byte_pos = 0;
  std::uint64_t acc = 0;
  int count = 0;
  std::uint32_t x[2] = {kTansSize, kTansSize};
  auto put = [&](std::uint16_t item, std::uint32_t& state) {
    const Entry& e = encode[item];
    const int nb = e.nb0 - (state < e.threshold);
    acc |= static_cast<std::uint64_t>(state & ((1u << nb) - 1)) << count;
    count += nb;
    std::memcpy(bit_out + byte_pos, &acc, 8);
    byte_pos += static_cast<std::size_t>(count >> 3);
    acc >>= count & ~7;
    count &= 7;
    state = next_state[static_cast<std::size_t>(e.offset + static_cast<std::int32_t>(state >> nb))];
  };
  std::uint32_t x0 = x[0], x1 = x[1];
  std::size_t i = items.size();
  if (i % 2) {
    --i;
    put(items[i], x0);
  }
  while (i > 0) {
    i -= 2;
    put(items[i + 1], x1);
    put(items[i], x0);
  }
  const std::uint64_t total_bits = 8 * static_cast<std::uint64_t>(byte_pos) + count;
  if (count > 0) bit_out[byte_pos++] = static_cast<std::uint8_t>(acc);
  w.PutU16(static_cast<std::uint16_t>(x0 - kTansSize));
  w.PutU16(static_cast<std::uint16_t>(x1 - kTansSize));
  w.PutVarint(total_bits);
  w.PutBytes(bit_out, byte_pos);
  out->insert(out->end(), w.data(), w.data() + w.size());
}

Status TansDecoder::Init(std::span<const std::uint8_t> in, int num_contexts, int alphabet,
                         std::size_t* consumed) {
  if (num_contexts < 1 || num_contexts > kTansMaxContexts || alphabet < 1 ||
      alphabet > kTansMaxAlphabet) {
    return InvalidArgument("tANS: bad context or alphabet size");
  }
  // The table section: bit fields, least significant first, padded to a whole byte.
  std::size_t bit = 0;
  auto take = [&](int n, std::uint32_t* v) -> Status {
    if (bit + n > 8 * in.size()) return Corrupt("tANS tables truncated");
    std::uint32_t value = 0;
    for (int i = 0; i < n; ++i, ++bit) value |= ((in[bit >> 3] >> (bit & 7)) & 1u) << i;
    *v = value;
    return Status::Ok();
  };
  table_.assign(static_cast<std::size_t>(num_contexts) << kTansLog, 0);
  std::vector<std::uint32_t> weights(alphabet), freq(alphabet), next(alphabet);
  std::vector<std::uint8_t> symbol_at(kTansSize);
  for (int c = 0; c < num_contexts; ++c) {
    std::uint32_t size;
    CCMD_RETURN_IF_ERROR(take(kSizeBits, &size));
    if (size > static_cast<std::uint32_t>(alphabet))
      return Corrupt("tANS table beyond the alphabet");
    if (size == 0) continue;  // all zero: symbol 0, no bits; only a corrupt stream uses it
    std::fill(weights.begin(), weights.end(), 0);
    for (std::uint32_t s = 0; s < size; ++s) {
      std::uint32_t present, q = 0;
      CCMD_RETURN_IF_ERROR(take(1, &present));
      if (present) {
        CCMD_RETURN_IF_ERROR(take(kWeightBits, &q));
        ++q;
      }
      weights[s] = kWeights[q];
    }
    if (weights[size - 1] == 0) return Corrupt("tANS table ends with an absent symbol");
    Normalize(weights.data(), alphabet, freq.data());
    Spread(freq.data(), alphabet, symbol_at.data());
    std::copy(freq.begin(), freq.end(), next.begin());
    std::uint32_t* t = &table_[static_cast<std::size_t>(c) << kTansLog];
    for (std::uint32_t u = 0; u < kTansSize; ++u) {
      const int s = symbol_at[u];
      const std::uint32_t xs = next[s]++;  // in [f, 2f)
      const int nb = kTansLog - (static_cast<int>(std::bit_width(xs)) - 1);
      const std::uint32_t base = (xs << nb) - kTansSize;
      t[u] = (base << 16) | (static_cast<std::uint32_t>(nb) << 8) | static_cast<std::uint32_t>(s);
    }
  }
  ByteReader r(in);
  CCMD_RETURN_IF_ERROR(r.Skip((bit + 7) / 8));
  std::uint16_t s0, s1;
  CCMD_RETURN_IF_ERROR(r.ReadU16(&s0));
  CCMD_RETURN_IF_ERROR(r.ReadU16(&s1));
  if (s0 >= kTansSize || s1 >= kTansSize) return Corrupt("tANS state out of range");
  std::uint64_t total_bits;
  CCMD_RETURN_IF_ERROR(
      r.ReadVarintAtMost(8 * static_cast<std::uint64_t>(r.remaining()), &total_bits, "tANS bits"));
  const std::size_t bytes = static_cast<std::size_t>((total_bits + 7) / 8);
  std::span<const std::uint8_t> data;
  CCMD_RETURN_IF_ERROR(r.ReadBytes(bytes, &data));
  bits_.assign(bytes + 16, 0);
  if (bytes) std::memcpy(bits_.data() + 8, data.data(), bytes);
  cursor_.table = table_.data();
  cursor_.data = bits_.data() + 8;
  cursor_.pos = static_cast<std::int64_t>(total_bits);
  cursor_.u0 = s0;
  cursor_.u1 = s1;
  if (consumed) *consumed = r.position();
  return Status::Ok();
}

Status TansDecoder::Finish() const {
  if (cursor_.pos != 0) {
    return Corrupt(cursor_.pos < 0 ? "entropy-coded bits end early" : "unused entropy-coded bits");
  }
  if (cursor_.u0 != 0 || cursor_.u1 != 0) {
    return Corrupt("entropy-coded data is inconsistent (final state check failed)");
  }
  return Status::Ok();
}

}  // namespace ccmd
