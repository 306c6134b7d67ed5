#pragma once

// Bounds-checked little-endian byte writer and reader: the only way proto/ and the codecs
// turn values into wire bytes and back.
//
//   ByteWriter w;
//   w.PutU32(7);
//   w.PutVarint(300);                       // LEB128: 0xAC 0x02
//   std::vector<std::uint8_t> bytes = w.Take();
//
//   ByteReader r(bytes);
//   std::uint32_t a;
//   std::uint64_t b;
//   CCMD_RETURN_IF_ERROR(r.ReadU32(&a));
//   CCMD_RETURN_IF_ERROR(r.ReadVarint(&b));
//   CCMD_RETURN_IF_ERROR(r.ExpectEnd());     // trailing bytes are an error
//
// Every read checks the remaining length first and returns a kCorrupt Status ("truncated:
// ...") instead of reading past the end; on error the output is left unchanged and the
// reader does not advance. Varints are LEB128 (7 bits per byte, low groups first); a varint
// longer than its type allows, or whose last byte carries bits beyond the type, is kCorrupt.
// Signed varints use zigzag (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...).

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <span>
#include <string>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

using ByteSpan = std::span<const std::uint8_t>;

constexpr std::uint64_t ZigzagEncode(std::int64_t v) {
  return (static_cast<std::uint64_t>(v) << 1) ^ static_cast<std::uint64_t>(v >> 63);
}
constexpr std::int64_t ZigzagDecode(std::uint64_t v) {
  return static_cast<std::int64_t>(v >> 1) ^ -static_cast<std::int64_t>(v & 1);
}

// Number of bytes PutVarint(v) writes (1..10).
int VarintSize(std::uint64_t v);

class ByteWriter {
 public:
  ByteWriter() = default;
  explicit ByteWriter(std::size_t reserve) { buffer_.reserve(reserve); }

  void PutU8(std::uint8_t v) { buffer_.push_back(v); }
  void PutU16(std::uint16_t v) { PutLittleEndian(v, 2); }
  void PutU32(std::uint32_t v) { PutLittleEndian(v, 4); }
  void PutU64(std::uint64_t v) { PutLittleEndian(v, 8); }
  void PutI8(std::int8_t v) { PutU8(static_cast<std::uint8_t>(v)); }
  void PutI16(std::int16_t v) { PutU16(static_cast<std::uint16_t>(v)); }
  void PutI32(std::int32_t v) { PutU32(static_cast<std::uint32_t>(v)); }
  void PutI64(std::int64_t v) { PutU64(static_cast<std::uint64_t>(v)); }
  // IEEE-754 binary32/binary64, bit pattern little-endian.
  void PutF32(float v);
  void PutF64(double v);
  void PutVarint(std::uint64_t v);
  void PutSignedVarint(std::int64_t v) { PutVarint(ZigzagEncode(v)); }
  void PutBytes(ByteSpan bytes);
  void PutBytes(const void* data, std::size_t size) {
    PutBytes(ByteSpan(static_cast<const std::uint8_t*>(data), size));
  }

  // Overwrites 4 bytes written earlier (e.g. a length known only at the end).
  // Precondition: offset + 4 <= size().
  void PatchU32(std::size_t offset, std::uint32_t v);

  std::size_t size() const { return buffer_.size(); }
  const std::uint8_t* data() const { return buffer_.data(); }
  ByteSpan bytes() const { return ByteSpan(buffer_); }
  std::vector<std::uint8_t>& buffer() { return buffer_; }
  // Moves the bytes out; the writer is empty afterwards.
  std::vector<std::uint8_t> Take() { return std::move(buffer_); }

 private:
  void PutLittleEndian(std::uint64_t v, int n) {
    for (int i = 0; i < n; ++i) buffer_.push_back(static_cast<std::uint8_t>(v >> (8 * i)));
  }
  std::vector<std::uint8_t> buffer_;
};

class ByteReader {
 public:
  ByteReader() = default;
  explicit ByteReader(ByteSpan data) : data_(data) {}
  ByteReader(const void* data, std::size_t size)
      : data_(static_cast<const std::uint8_t*>(data), size) {}

  Status ReadU8(std::uint8_t* v);
  Status ReadU16(std::uint16_t* v);
  Status ReadU32(std::uint32_t* v);
  Status ReadU64(std::uint64_t* v);
  Status ReadI8(std::int8_t* v);
  Status ReadI16(std::int16_t* v);
  Status ReadI32(std::int32_t* v);
  Status ReadI64(std::int64_t* v);
  Status ReadF32(float* v);
  Status ReadF64(double* v);
  Status ReadVarint(std::uint64_t* v);
  // Fails (kCorrupt) if the value does not fit in 32 bits.
  Status ReadVarint32(std::uint32_t* v);
  Status ReadSignedVarint(std::int64_t* v);
  // Reads a varint that must be <= max (kOutOfRange otherwise): for counts and lengths.
  Status ReadVarintAtMost(std::uint64_t max, std::uint64_t* v, const char* what);
  // A view of the next n bytes (no copy; valid as long as the underlying data).
  Status ReadBytes(std::size_t n, ByteSpan* out);
  Status ReadBytes(std::size_t n, void* out);
  Status Skip(std::size_t n);

  // kCorrupt unless every byte has been consumed.
  Status ExpectEnd() const;

  std::size_t position() const { return pos_; }
  std::size_t remaining() const { return data_.size() - pos_; }
  std::size_t size() const { return data_.size(); }
  bool AtEnd() const { return pos_ == data_.size(); }
  const std::uint8_t* current() const { return data_.data() + pos_; }

 private:
  Status Truncated(std::size_t need) const;
  std::uint64_t LoadLittleEndian(int n) const {
    std::uint64_t v = 0;
    for (int i = 0; i < n; ++i) v |= static_cast<std::uint64_t>(data_[pos_ + i]) << (8 * i);
    return v;
  }

  ByteSpan data_;
  std::size_t pos_ = 0;
};

}  // namespace ccmd
