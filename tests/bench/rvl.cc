#include "tests/bench/rvl.h"

#include <cstring>

namespace ccmd::bench {
namespace {

class NibbleWriter {
 public:
  void Put(std::uint32_t value) {
    do {
      std::uint32_t nibble = value & 7;
      value >>= 3;
      if (value) nibble |= 8;
      word_ = (word_ << 4) | nibble;
      if (++count_ == 8) Flush();
    } while (value);
  }
  std::vector<std::uint8_t> Finish() {
    if (count_ > 0) {
      word_ <<= 4 * (8 - count_);
      Flush();
    }
    return std::move(bytes_);
  }

 private:
  void Flush() {
    for (int i = 0; i < 4; ++i) bytes_.push_back(static_cast<std::uint8_t>(word_ >> (8 * i)));
    word_ = 0;
    count_ = 0;
  }
  std::uint32_t word_ = 0;
  int count_ = 0;
  std::vector<std::uint8_t> bytes_;
};

class NibbleReader {
 public:
  explicit NibbleReader(std::span<const std::uint8_t> b) : bytes_(b) {}
  bool Get(std::uint32_t* value) {
    std::uint32_t v = 0;
    int shift = 0;
    std::uint32_t nibble;
    do {
      if (count_ == 0) {
        if (pos_ + 4 > bytes_.size() || shift > 30) return false;
        std::memcpy(&word_, bytes_.data() + pos_, 4);
        pos_ += 4;
        count_ = 8;
      }
      nibble = (word_ >> 28) & 0xF;
      word_ <<= 4;
      --count_;
      v |= (nibble & 7) << shift;
      shift += 3;
    } while (nibble & 8);
    *value = v;
    return true;
  }

 private:
  std::span<const std::uint8_t> bytes_;
  std::size_t pos_ = 0;
  std::uint32_t word_ = 0;
  int count_ = 0;
};

}  // namespace

std::vector<std::uint8_t> RvlEncode(std::span<const std::uint16_t> depth) {
  NibbleWriter w;
  std::size_t i = 0;
  int previous = 0;
  while (i < depth.size()) {
    std::size_t zeros = 0;
    while (i < depth.size() && depth[i] == 0) {
      ++zeros;
      ++i;
    }
    w.Put(static_cast<std::uint32_t>(zeros));
    std::size_t start = i;
    while (i < depth.size() && depth[i] != 0) ++i;
    w.Put(static_cast<std::uint32_t>(i - start));
    for (std::size_t k = start; k < i; ++k) {
      const int delta = depth[k] - previous;
      w.Put((static_cast<std::uint32_t>(delta) << 1) ^ static_cast<std::uint32_t>(delta >> 31));
      previous = depth[k];
    }
  }
  return w.Finish();
}

bool RvlDecode(std::span<const std::uint8_t> bytes, std::span<std::uint16_t> out) {
  NibbleReader r(bytes);
  std::size_t i = 0;
  int previous = 0;
  while (i < out.size()) {
    std::uint32_t zeros, valid;
    if (!r.Get(&zeros) || zeros > out.size() - i) return false;
    std::memset(out.data() + i, 0, zeros * sizeof(std::uint16_t));
    i += zeros;
    if (!r.Get(&valid) || valid > out.size() - i) return false;
    for (std::uint32_t k = 0; k < valid; ++k) {
      std::uint32_t m;
      if (!r.Get(&m)) return false;
      previous += static_cast<int>(m >> 1) ^ -static_cast<int>(m & 1);
      out[i++] = static_cast<std::uint16_t>(previous);
    }
  }
  return true;
}

}  // namespace ccmd::bench
