#pragma once

// Raw bit streams for the codecs' extra bits: least significant bit first, whole bytes.
// Both sides are small value types meant to live in a hot loop's registers.

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <vector>

namespace ccmd {

class BitWriter {
 public:
  // Appends n bits (0 <= n <= 32) of each value, in order. Branch-free: the accumulator is
  // stored whole and the write position advances by the completed bytes.
  void PutAll(const std::uint32_t* values, const std::uint8_t* counts, std::size_t n) {
    std::size_t pos = bytes_.size();
    bytes_.resize(pos + 4 * n + kSlack);  // at most 32 bits each
    std::uint8_t* out = bytes_.data();
    std::uint64_t acc = acc_;
    int count = count_;
    for (std::size_t i = 0; i < n; ++i) {
      const int k = counts[i];
      acc |= static_cast<std::uint64_t>(values[i] & static_cast<std::uint32_t>((1ull << k) - 1))
             << count;
      count += k;
      std::memcpy(out + pos, &acc, 8);
      pos += count >> 3;
      acc >>= count & ~7;
      count &= 7;
    }
    acc_ = acc;
    count_ = count;
    bytes_.resize(pos);
  }
  // Flushes the last partial byte (zero padded) and returns the bytes.
  std::vector<std::uint8_t> Finish() {
    if (count_ > 0) bytes_.push_back(static_cast<std::uint8_t>(acc_));
    acc_ = 0;
    count_ = 0;
    return std::move(bytes_);
  }

 private:
  static constexpr std::size_t kSlack = 8;
  std::vector<std::uint8_t> bytes_;
  std::uint64_t acc_ = 0;
  int count_ = 0;
};

// Reads a copy of the bits with 8 bytes of zero padding, so that a refill is one unaligned
// 64-bit load. Past the end it reads zeros (the load address is clamped to the padding) and
// keeps counting, so that an overrun is detected at the end.
class BitReader {
 public:
  BitReader(const std::uint8_t* data, std::size_t size) : buffer_(size + 8, 0), size_(size) {
    if (size) std::memcpy(buffer_.data(), data, size);
    cursor_ = Cursor{buffer_.data(), size, 0, 0, 0};
  }
  BitReader(const BitReader&) = delete;
  BitReader& operator=(const BitReader&) = delete;

  // Hot-loop state, kept in registers by the caller (see RansDecoder::Cursor).
  struct Cursor {
    const std::uint8_t* data;
    std::size_t size;
    std::size_t pos;  // bytes loaded so far; may pass size on corrupt input
    std::uint64_t acc;
    int count;

    // n <= 32.
    std::uint32_t Get(int n) {
      if (count < n) {
        std::uint64_t word;
        std::memcpy(&word, data + std::min(pos, size), 8);
        acc |= word << count;
        pos += (63 - count) >> 3;
        count |= 56;
      }
      const auto v = static_cast<std::uint32_t>(acc & ((1ull << n) - 1));
      acc >>= n;
      count -= n;
      return v;
    }
  };
  Cursor cursor() const { return cursor_; }
  void set_cursor(const Cursor& c) { cursor_ = c; }

  // True if every bit read came from the stream and all its bytes were needed (at most 7
  // padding bits left unread).
  bool ConsumedExactly() const {
    const std::uint64_t consumed =
        8 * static_cast<std::uint64_t>(cursor_.pos) - static_cast<std::uint64_t>(cursor_.count);
    return consumed <= 8 * static_cast<std::uint64_t>(size_) && (consumed + 7) / 8 == size_;
  }

 private:
  std::vector<std::uint8_t> buffer_;
  std::size_t size_ = 0;
  Cursor cursor_{};
};

}  // namespace ccmd
