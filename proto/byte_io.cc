#include "proto/byte_io.h"

#include <bit>

namespace ccmd {

int VarintSize(std::uint64_t v) {
  int n = 1;
  while (v >= 0x80) {
    v >>= 7;
    ++n;
  }
  return n;
}

void ByteWriter::PutF32(float v) { PutU32(std::bit_cast<std::uint32_t>(v)); }
void ByteWriter::PutF64(double v) { PutU64(std::bit_cast<std::uint64_t>(v)); }

void ByteWriter::PutVarint(std::uint64_t v) {
  while (v >= 0x80) {
    buffer_.push_back(static_cast<std::uint8_t>(v | 0x80));
    v >>= 7;
  }
  buffer_.push_back(static_cast<std::uint8_t>(v));
}

void ByteWriter::PutBytes(ByteSpan bytes) {
  if (bytes.empty()) return;
  const std::size_t at = buffer_.size();
  buffer_.resize(at + bytes.size());
  std::memcpy(buffer_.data() + at, bytes.data(), bytes.size());
}

void ByteWriter::PatchU32(std::size_t offset, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) buffer_.at(offset + i) = static_cast<std::uint8_t>(v >> (8 * i));
}

Status ByteReader::Truncated(std::size_t need) const {
  return Corrupt("truncated: need " + std::to_string(need) + " bytes at offset " +
                 std::to_string(pos_) + ", " + std::to_string(remaining()) + " left");
}

#define CCMD_DEFINE_READ_LE(Name, Type, N)       \
  Status ByteReader::Name(Type* v) {             \
    if (remaining() < (N)) return Truncated(N);  \
    *v = static_cast<Type>(LoadLittleEndian(N)); \
    pos_ += (N);                                 \
    return Status::Ok();                         \
  }
CCMD_DEFINE_READ_LE(ReadU8, std::uint8_t, 1)
CCMD_DEFINE_READ_LE(ReadU16, std::uint16_t, 2)
CCMD_DEFINE_READ_LE(ReadU32, std::uint32_t, 4)
CCMD_DEFINE_READ_LE(ReadU64, std::uint64_t, 8)
CCMD_DEFINE_READ_LE(ReadI8, std::int8_t, 1)
CCMD_DEFINE_READ_LE(ReadI16, std::int16_t, 2)
CCMD_DEFINE_READ_LE(ReadI32, std::int32_t, 4)
CCMD_DEFINE_READ_LE(ReadI64, std::int64_t, 8)
#undef CCMD_DEFINE_READ_LE

Status ByteReader::ReadF32(float* v) {
  std::uint32_t bits = 0;
  CCMD_RETURN_IF_ERROR(ReadU32(&bits));
  *v = std::bit_cast<float>(bits);
  return Status::Ok();
}

Status ByteReader::ReadF64(double* v) {
  std::uint64_t bits = 0;
  CCMD_RETURN_IF_ERROR(ReadU64(&bits));
  *v = std::bit_cast<double>(bits);
  return Status::Ok();
}

Status ByteReader::ReadVarint(std::uint64_t* v) {
  std::uint64_t value = 0;
  // 10 bytes carry 70 bits; the tenth may only hold the 64th bit.
  for (std::size_t i = 0; i < 10; ++i) {
    if (pos_ + i >= data_.size()) return Truncated(i + 1);
    const std::uint8_t byte = data_[pos_ + i];
    if (i == 9 && byte > 1)
      return Corrupt("varint overflows 64 bits at offset " + std::to_string(pos_));
    value |= static_cast<std::uint64_t>(byte & 0x7F) << (7 * i);
    if (!(byte & 0x80)) {
      pos_ += i + 1;
      *v = value;
      return Status::Ok();
    }
  }
  return Corrupt("varint longer than 10 bytes at offset " + std::to_string(pos_));
}

Status ByteReader::ReadVarint32(std::uint32_t* v) {
  const std::size_t start = pos_;
  std::uint64_t value;
  CCMD_RETURN_IF_ERROR(ReadVarint(&value));
  if (value > 0xFFFFFFFFull) {
    pos_ = start;
    return Corrupt("varint at offset " + std::to_string(start) + " overflows 32 bits");
  }
  *v = static_cast<std::uint32_t>(value);
  return Status::Ok();
}

Status ByteReader::ReadSignedVarint(std::int64_t* v) {
  std::uint64_t value;
  CCMD_RETURN_IF_ERROR(ReadVarint(&value));
  *v = ZigzagDecode(value);
  return Status::Ok();
}

Status ByteReader::ReadVarintAtMost(std::uint64_t max, std::uint64_t* v, const char* what) {
  const std::size_t start = pos_;
  std::uint64_t value;
  CCMD_RETURN_IF_ERROR(ReadVarint(&value));
  if (value > max) {
    pos_ = start;
    return OutOfRange(std::string(what) + " " + std::to_string(value) + " exceeds the limit " +
                      std::to_string(max));
  }
  *v = value;
  return Status::Ok();
}

Status ByteReader::ReadBytes(std::size_t n, ByteSpan* out) {
  if (remaining() < n) return Truncated(n);
  *out = data_.subspan(pos_, n);
  pos_ += n;
  return Status::Ok();
}

Status ByteReader::ReadBytes(std::size_t n, void* out) {
  if (remaining() < n) return Truncated(n);
  if (n > 0) std::memcpy(out, data_.data() + pos_, n);
  pos_ += n;
  return Status::Ok();
}

Status ByteReader::Skip(std::size_t n) {
  if (remaining() < n) return Truncated(n);
  pos_ += n;
  return Status::Ok();
}

Status ByteReader::ExpectEnd() const {
  if (AtEnd()) return Status::Ok();
  return Corrupt(std::to_string(remaining()) + " unexpected trailing bytes at offset " +
                 std::to_string(pos_));
}

}  // namespace ccmd
