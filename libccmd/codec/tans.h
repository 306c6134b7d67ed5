#pragma once

// Entropy coding for the depth codecs: tabled asymmetric numeral systems (tANS, J. Duda,
// 2013, the method behind zstd's FSE), over small alphabets in several contexts.
//
// The encoder takes the whole message as (context, symbol) items, normalises each
// context's symbol counts to kTansSize, builds one tANS table per context and codes the
// items backwards with two interleaved states (even items on one, odd on the other); all
// tables share the state range [kTansSize, 2 kTansSize), so every symbol may use a
// different context. Decoding a symbol is one table lookup plus reading a few bits, which
// is what makes the lossless depth codec several times faster than PNG.
//
// Stream:
//   tables      bit fields, least significant bit first, padded to a byte: per context
//               7 bits n (0 = unused context, else the largest symbol used + 1), then for
//               symbols 0..n-1 a bit "present" and, if set, 5 bits q - 1 where q (1..32)
//               is a log weight, about 2^((q - 1) / 2) (integers in tans.cc); both sides
//               scale the weights to kTansSize the same way
//   u16 x2      the two final encoder states, minus kTansSize
//   varint      number of bits
//   bytes       the bits, least significant first, read back to front by the decoder
//
// Decoding never reads out of bounds (reads before the start see zero padding and are
// counted); Finish() checks that both states returned to their initial value and that
// exactly all bits were used.

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <span>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

constexpr int kTansLog = 10;
constexpr std::uint32_t kTansSize = 1u << kTansLog;
constexpr int kTansMaxAlphabet = 64;
constexpr int kTansMaxContexts = 256;

// A coded symbol: (context << 6) | symbol.
inline std::uint16_t TansItem(int context, int symbol) {
  return static_cast<std::uint16_t>((context << 6) | symbol);
}

// Appends tables and stream to *out. counts (optional): how often each item occurs,
// indexed by the item value, when the caller has counted already. *table_bytes (optional)
// gets the size of the tables.
void TansEncode(std::span<const std::uint16_t> items, int num_contexts, int alphabet,
                const std::uint32_t* counts, std::vector<std::uint8_t>* out,
                std::size_t* table_bytes = nullptr);

class TansDecoder {
 public:
  // Parses tables and stream; *consumed gets the bytes they take.
  Status Init(std::span<const std::uint8_t> in, int num_contexts, int alphabet,
              std::size_t* consumed);

  // The decoding state, copied into the caller's loop so that it stays in registers.
  struct Cursor {
    const std::uint32_t* table;  // [context << kTansLog | state]: base << 16 | bits << 8 | symbol
    const std::uint8_t* data;    // the bit bytes, with 8 bytes of zero padding on both sides
    std::int64_t pos;            // bits not yet read
    std::uint32_t u0, u1;        // states minus kTansSize; u0 decodes next

    int Get(int context) {
      const std::uint32_t e = table[(static_cast<std::size_t>(context) << kTansLog) | u0];
      const int nb = (e >> 8) & 0xFF;
      pos = pos - nb < -64 ? -64 : pos - nb;  // stays inside the front padding
      std::uint64_t word;
      std::memcpy(&word, data + (pos >> 3), 8);
      const auto bits = static_cast<std::uint32_t>((word >> (pos & 7)) & ((1u << nb) - 1));
      u0 = u1;
      u1 = (e >> 16) + bits;
      return static_cast<int>(e & 0xFF);
    }
  };

  Cursor cursor() const { return cursor_; }
  void set_cursor(const Cursor& c) { cursor_ = c; }

  // Checks that the stream was consumed exactly; call after the last symbol.
  Status Finish() const;

 private:
  std::vector<std::uint32_t> table_;
  std::vector<std::uint8_t> bits_;  // padded copy
  Cursor cursor_{};
};

}  // namespace ccmd
