#include "libccmd/codec/predictive_coder.h"

#include <algorithm>
#include <bit>
#include <cstdlib>
#include <string>

#include "libccmd/codec/bit_io.h"
#include "libccmd/codec/tans.h"
#include "proto/byte_io.h"

namespace ccmd {
namespace {

constexpr int kActivityClasses = 8;
// Contexts: an activity class in each of four groups: left and up valid, only left valid,
// only up valid, neither valid.
constexpr int kContexts = 4 * kActivityClasses;
constexpr int kAlphabet = 43;  // invalid, 16 direct residuals, 2 per bit length 4..16
constexpr int kInvalidSymbol = 0;
constexpr int kDirect = 16;

// The median of a, b and a + b - c; ternaries so that the compiler emits conditional moves.
inline int Med(int a, int b, int c) {
  const int lo = a < b ? a : b;
  const int hi = a < b ? b : a;
  const int p = a + b - c;
  const int q = p < hi ? p : hi;
  return q > lo ? q : lo;
}

inline std::uint32_t Zigzag(int v) {
  return (static_cast<std::uint32_t>(v) << 1) ^ static_cast<std::uint32_t>(v >> 31);
}
inline int Unzigzag(std::uint32_t m) { return static_cast<int>(m >> 1) ^ -static_cast<int>(m & 1); }

// Activity class: the bit length of the gradient sum, at most kActivityClasses - 1.
inline int ActivityClass(int g) {
  static_assert(kActivityClasses == 8);
  return (g >= 1) + (g >= 2) + (g >= 4) + (g >= 8) + (g >= 16) + (g >= 32) + (g >= 64);
}

struct SymbolCode {
  int symbol;
  int bits;  // raw bits after the symbol (the low bits of m)
};

inline SymbolCode CodeOf(std::uint32_t m) {
  if (m < kDirect) return {1 + static_cast<int>(m), 0};
  const int e = static_cast<int>(std::bit_width(m)) - 1;  // 4..17
  return {1 + kDirect + 2 * (e - 4) + static_cast<int>((m >> (e - 1)) & 1), e - 1};
}

// Per symbol: the signed residual of a direct symbol (0 for invalid); for the others the
// first zigzagged residual of the range and the number of raw bits after it.
struct SymbolTable {
  int residual[kAlphabet];
  std::uint32_t base[kAlphabet];
  int bits[kAlphabet];
  SymbolTable() {
    for (int s = 0; s < kAlphabet; ++s) {
      residual[s] = 0;
      base[s] = 0;
      bits[s] = 0;
      if (s >= 1 && s <= kDirect) {
        residual[s] = Unzigzag(static_cast<std::uint32_t>(s - 1));
      } else if (s > kDirect) {
        const int k = s - 1 - kDirect;
        const int e = 4 + k / 2;
        base[s] = (2u | static_cast<std::uint32_t>(k & 1)) << (e - 1);
        bits[s] = e - 1;
      }
    }
  }
};

const SymbolTable& Symbols() {
  static const SymbolTable table;
  return table;
}

// Row buffers: filled values (an invalid pixel holds its prediction) and validity of the
// row above and the current row, padded by one pixel on each side (the pads repeat the edge
// pixels); before the first row everything is zero and invalid. For the coming row,
// Prepare() precomputes the parts of the contexts that come from the row above.
class Rows {
 public:
  explicit Rows(int width)
      : width_(width),
        up_(width + 2, 0),
        cur_(width + 2, 0),
        up_valid_(width + 2, 0),
        cur_valid_(width + 2, 0),
        gradient_(width, 0),
        group_{std::vector<int>(width, 0), std::vector<int>(width, 0)} {
    Prepare();
  }
  const int* up() const { return up_.data() + 1; }
  const std::uint8_t* up_valid() const { return up_valid_.data() + 1; }
  int* cur() { return cur_.data() + 1; }
  std::uint8_t* cur_valid() { return cur_valid_.data() + 1; }

  // Context of pixel x with left neighbour a (valid: va) and upper-left neighbour c.
  int Context(int x, int a, int c, int va) const {
    return group_[va][x] + ActivityClass(gradient_[x] + std::abs(a - c));
  }

  // Before a row: the left pad takes the value above (a = b at x = 0).
  void StartRow() {
    cur()[-1] = up()[0];
    cur_valid()[-1] = up_valid()[0];
  }
  // After a row: it becomes the row above.
  void EndRow() {
    std::swap(up_, cur_);
    std::swap(up_valid_, cur_valid_);
    int* u = up_.data() + 1;
    std::uint8_t* v = up_valid_.data() + 1;
    u[-1] = u[0];
    u[width_] = u[width_ - 1];
    v[-1] = v[0];
    v[width_] = v[width_ - 1];
    Prepare();
  }

 private:
  // Groups (left valid, up valid): (1, 1) -> 0, (1, 0) -> 1, (0, 1) -> 2, (0, 0) -> 3, each
  // kActivityClasses contexts wide.
  void Prepare() {
    const int n = width_;
    const int* __restrict b = up();
    const std::uint8_t* __restrict vb = up_valid();
    int* __restrict gradient = gradient_.data();
    int* __restrict left_invalid = group_[0].data();
    int* __restrict left_valid = group_[1].data();
    for (int x = 0; x < n; ++x) {
      gradient[x] = std::abs(b[x] - b[x - 1]) + std::abs(b[x + 1] - b[x]);
      const int up_invalid = vb[x] == 0;
      left_valid[x] = up_invalid * kActivityClasses;
      left_invalid[x] = (2 + up_invalid) * kActivityClasses;
    }
  }

  int width_;
  std::vector<int> up_, cur_;
  std::vector<std::uint8_t> up_valid_, cur_valid_;
  std::vector<int> gradient_;  // |b - c| + |d - b| per x
  std::vector<int> group_[2];  // [left valid][x]: first context of the pixel's group
};

struct Halves {
  int split;   // first pixel of the right half
  int pairs;   // pixels coded as (left, right) pairs
  bool extra;  // the right half has one more pixel, coded after the pairs
};

inline Halves SplitRow(int width) {
  const int split = width / 2;
  return {split, split, (width - split) > split};
}

// Calls visit(x, first_of_half) for the pixels of a row in coding order.
template <typename Visit>
void ForEachInCodingOrder(const Halves& halves, int width, Visit&& visit) {
  for (int k = 0; k < halves.pairs; ++k) {
    visit(k, k == 0);
    visit(halves.split + k, k == 0);
  }
  if (halves.extra) visit(width - 1, width - 1 == halves.split);
}

}  // namespace

void EncodePredictive(const std::uint16_t* first, const std::uint16_t* last, int width, int height,
                      std::vector<std::uint8_t>* out, std::uint16_t* chosen) {
  const std::size_t n = static_cast<std::size_t>(width) * height;
  std::vector<std::uint16_t> items;
  items.reserve(n);
  std::vector<std::uint32_t> counts(static_cast<std::size_t>(kContexts) * kTansMaxAlphabet, 0);
  std::vector<std::uint32_t> escapes;  // raw bits of large residuals, in coding order
  std::vector<std::uint8_t> escape_bits;
  const Halves halves = SplitRow(width);
  Rows rows(width);
  for (int y = 0; y < height; ++y) {
    const std::size_t row_start = static_cast<std::size_t>(y) * width;
    rows.StartRow();
    const int* up = rows.up();
    const std::uint8_t* up_valid = rows.up_valid();
    int* cur = rows.cur();
    std::uint8_t* cur_valid = rows.cur_valid();
    ForEachInCodingOrder(halves, width, [&](int x, bool first_of_half) {
      // The left neighbour; the right half starts like a row, from the pixel above.
      const int a = first_of_half ? up[x] : cur[x - 1];
      const int va = first_of_half ? up_valid[x] : cur_valid[x - 1];
      const int b = up[x], c = up[x - 1];
      const int context = rows.Context(x, a, c, va);
      const int predict = Med(a, b, c);
      const int lo = first[row_start + x];
      int symbol = kInvalidSymbol;
      int value = predict;  // the filled value of an invalid pixel
      if (lo != 0) {
        value = std::clamp(predict, lo, static_cast<int>(last[row_start + x]));
        const std::uint32_t m = Zigzag(value - predict);
        const SymbolCode code = CodeOf(m);
        symbol = code.symbol;
        if (code.bits) {
          escapes.push_back(m);
          escape_bits.push_back(static_cast<std::uint8_t>(code.bits));
        }
      }
      if (chosen) chosen[row_start + x] = static_cast<std::uint16_t>(lo ? value : 0);
      const std::uint16_t item = TansItem(context, symbol);
      items.push_back(item);
      ++counts[item];
      cur[x] = value;
      cur_valid[x] = lo != 0;
    });
    rows.EndRow();
  }
  TansEncode(items, kContexts, kAlphabet, counts.data(), out);
  BitWriter bits;
  bits.PutAll(escapes.data(), escape_bits.data(), escapes.size());
  const std::vector<std::uint8_t> raw = bits.Finish();
  ByteWriter w;
  w.PutVarint(raw.size());
  out->insert(out->end(), w.data(), w.data() + w.size());
  out->insert(out->end(), raw.begin(), raw.end());
}

Status DecodePredictive(std::span<const std::uint8_t> in, int width, int height, int max_code,
                        std::uint16_t* codes, std::size_t* consumed) {
  if (width <= 0 || height <= 0) return InvalidArgument("empty image");
  TansDecoder dec;
  std::size_t used = 0;
  CCMD_RETURN_IF_ERROR(dec.Init(in, kContexts, kAlphabet, &used));
  ByteReader r(in.subspan(used));
  std::uint64_t raw_size;
  CCMD_RETURN_IF_ERROR(r.ReadVarint(&raw_size));
  std::span<const std::uint8_t> raw;
  CCMD_RETURN_IF_ERROR(r.ReadBytes(raw_size, &raw));  // checks the bytes are there
  BitReader bit_reader(raw.data(), raw.size());
  TansDecoder::Cursor tans = dec.cursor();
  BitReader::Cursor bits = bit_reader.cursor();
  const SymbolTable& symbols = Symbols();
  const Halves halves = SplitRow(width);
  Rows rows(width);
  // Filled values of invalid pixels are predictions, so they stay within the range of the
  // valid ones; one unsigned comparison per pixel catches residuals that leave the range.
  unsigned outside = 0;
  for (int y = 0; y < height; ++y) {
    rows.StartRow();
    const int* up = rows.up();
    const std::uint8_t* up_valid = rows.up_valid();
    int* cur = rows.cur();
    std::uint8_t* cur_valid = rows.cur_valid();
    // Decodes pixel x of a half whose previous pixel is a / va, and updates them.
    auto pixel = [&](int x, int& a, int& va) {
      const int b = up[x], c = up[x - 1];
      const int symbol = tans.Get(rows.Context(x, a, c, va));
      int residual = symbols.residual[symbol];
      if (symbol > kDirect) [[unlikely]] {
        residual = Unzigzag(symbols.base[symbol] | bits.Get(symbols.bits[symbol]));
      }
      va = symbol != kInvalidSymbol;
      a = Med(a, b, c) + residual;
      outside |= static_cast<unsigned>(a) > static_cast<unsigned>(max_code);
      cur[x] = a;
      cur_valid[x] = static_cast<std::uint8_t>(va);
    };
    int a0 = cur[-1], va0 = cur_valid[-1];
    int a1 = up[halves.split], va1 = up_valid[halves.split];
    for (int k = 0; k < halves.pairs; ++k) {
      pixel(k, a0, va0);
      pixel(halves.split + k, a1, va1);
    }
    if (halves.extra) pixel(width - 1, a1, va1);
    if (outside) {
      return Corrupt("depth residuals decode outside 0.." + std::to_string(max_code) + " in row " +
                     std::to_string(y));
    }
    std::uint16_t* dst = codes + static_cast<std::size_t>(y) * width;
    for (int x = 0; x < width; ++x) {
      dst[x] = static_cast<std::uint16_t>(cur_valid[x] ? cur[x] : 0);
    }
    rows.EndRow();
  }
  dec.set_cursor(tans);
  bit_reader.set_cursor(bits);
  CCMD_RETURN_IF_ERROR(dec.Finish());
  if (!bit_reader.ConsumedExactly()) {
    return Corrupt("raw bits of the depth residuals do not match");
  }
  if (consumed) *consumed = used + r.position();
  return Status::Ok();
}

}  // namespace ccmd
