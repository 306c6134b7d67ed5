#include "proto/byte_io.h"

#include <cstdint>
#include <limits>
#include <vector>

#include <gtest/gtest.h>

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

TEST(ByteIoTest, FixedWidthFieldsAreLittleEndian) {
  ByteWriter w;
  w.PutU8(0xAB);
  w.PutU16(0x0102);
  w.PutU32(0x01020304);
  w.PutU64(0x0102030405060708ull);
  w.PutI16(-2);
  w.PutF32(1.0f);  // IEEE-754: 0x3F800000
  w.PutF64(-2.0);  // 0xC000000000000000
  const Bytes expected = {0xAB, 0x02, 0x01, 0x04, 0x03, 0x02, 0x01, 0x08, 0x07, 0x06,
                          0x05, 0x04, 0x03, 0x02, 0x01, 0xFE, 0xFF, 0x00, 0x00, 0x80,
                          0x3F, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0xC0};
  EXPECT_EQ(w.Take(), expected);
}

TEST(ByteIoTest, FixedWidthRoundTrip) {
  ByteWriter w;
  w.PutU8(200);
  w.PutU16(65535);
  w.PutU32(4000000000u);
  w.PutU64(std::numeric_limits<std::uint64_t>::max());
  w.PutI8(-128);
  w.PutI16(-32768);
  w.PutI32(std::numeric_limits<std::int32_t>::min());
  w.PutI64(std::numeric_limits<std::int64_t>::min());
  w.PutF32(3.25f);
  w.PutF64(1305031453.359684);
  const Bytes bytes = w.Take();
  ByteReader r(bytes);
  std::uint8_t u8;
  std::uint16_t u16;
  std::uint32_t u32;
  std::uint64_t u64;
  std::int8_t i8;
  std::int16_t i16;
  std::int32_t i32;
  std::int64_t i64;
  float f;
  double d;
  ASSERT_TRUE(r.ReadU8(&u8).ok());
  ASSERT_TRUE(r.ReadU16(&u16).ok());
  ASSERT_TRUE(r.ReadU32(&u32).ok());
  ASSERT_TRUE(r.ReadU64(&u64).ok());
  ASSERT_TRUE(r.ReadI8(&i8).ok());
  ASSERT_TRUE(r.ReadI16(&i16).ok());
  ASSERT_TRUE(r.ReadI32(&i32).ok());
  ASSERT_TRUE(r.ReadI64(&i64).ok());
  ASSERT_TRUE(r.ReadF32(&f).ok());
  ASSERT_TRUE(r.ReadF64(&d).ok());
  EXPECT_TRUE(r.ExpectEnd().ok());
  EXPECT_EQ(u8, 200);
  EXPECT_EQ(u16, 65535);
  EXPECT_EQ(u32, 4000000000u);
  EXPECT_EQ(u64, std::numeric_limits<std::uint64_t>::max());
  EXPECT_EQ(i8, -128);
  EXPECT_EQ(i16, -32768);
  EXPECT_EQ(i32, std::numeric_limits<std::int32_t>::min());
  EXPECT_EQ(i64, std::numeric_limits<std::int64_t>::min());
  EXPECT_EQ(f, 3.25f);
  EXPECT_EQ(d, 1305031453.359684);
}

TEST(ByteIoTest, VarintKnownEncodings) {
  struct Case {
    std::uint64_t value;
    Bytes bytes;
  };
  const std::vector<Case> cases = {
      {0, {0x00}},
      {1, {0x01}},
      {127, {0x7F}},
      {128, {0x80, 0x01}},
      {300, {0xAC, 0x02}},
      {16384, {0x80, 0x80, 0x01}},
      {0xFFFFFFFFull, {0xFF, 0xFF, 0xFF, 0xFF, 0x0F}},
      {std::numeric_limits<std::uint64_t>::max(),
       {0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x01}},
  };
  for (const Case& c : cases) {
    ByteWriter w;
    w.PutVarint(c.value);
    EXPECT_EQ(w.bytes().size(), static_cast<std::size_t>(VarintSize(c.value)));
    const Bytes bytes = w.Take();
    EXPECT_EQ(bytes, c.bytes) << c.value;
    ByteReader r(bytes);
    std::uint64_t v = 0;
    ASSERT_TRUE(r.ReadVarint(&v).ok());
    EXPECT_EQ(v, c.value);
    EXPECT_TRUE(r.AtEnd());
  }
}

TEST(ByteIoTest, ZigzagMapsSmallMagnitudesToSmallCodes) {
  EXPECT_EQ(ZigzagEncode(0), 0u);
  EXPECT_EQ(ZigzagEncode(-1), 1u);
  EXPECT_EQ(ZigzagEncode(1), 2u);
  EXPECT_EQ(ZigzagEncode(-2), 3u);
  EXPECT_EQ(ZigzagEncode(std::numeric_limits<std::int64_t>::max()),
            std::numeric_limits<std::uint64_t>::max() - 1);
  EXPECT_EQ(ZigzagEncode(std::numeric_limits<std::int64_t>::min()),
            std::numeric_limits<std::uint64_t>::max());
  const std::int64_t values[] = {0,    -1,        1,
                                 -300, 123456789, std::numeric_limits<std::int64_t>::min()};
  for (std::int64_t v : values) {
    EXPECT_EQ(ZigzagDecode(ZigzagEncode(v)), v);
    ByteWriter w;
    w.PutSignedVarint(v);
    ByteReader r(w.bytes());
    std::int64_t back = 0;
    ASSERT_TRUE(r.ReadSignedVarint(&back).ok());
    EXPECT_EQ(back, v);
  }
}

TEST(ByteIoTest, VarintOverflowIsRejected) {
  // Ten bytes whose last carries more than the 64th bit.
  const Bytes too_big = {0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x02};
  std::uint64_t v = 7;
  ByteReader r1(too_big);
  EXPECT_EQ(r1.ReadVarint(&v).code(), StatusCode::kCorrupt);
  EXPECT_EQ(v, 7u);
  EXPECT_EQ(r1.position(), 0u);
  // Eleven bytes with continuation bits.
  const Bytes too_long(11, 0x80);
  ByteReader r2(too_long);
  EXPECT_EQ(r2.ReadVarint(&v).code(), StatusCode::kCorrupt);
  // 2^32 does not fit a 32-bit varint.
  const Bytes two_to_32 = {0x80, 0x80, 0x80, 0x80, 0x10};
  ByteReader r3(two_to_32);
  std::uint32_t v32 = 0;
  EXPECT_EQ(r3.ReadVarint32(&v32).code(), StatusCode::kCorrupt);
  EXPECT_EQ(r3.position(), 0u);
  // Limits on counts.
  const Bytes thousand = {0xE8, 0x07};
  ByteReader r4(thousand);
  EXPECT_EQ(r4.ReadVarintAtMost(999, &v, "count").code(), StatusCode::kOutOfRange);
  EXPECT_TRUE(r4.ReadVarintAtMost(1000, &v, "count").ok());
  EXPECT_EQ(v, 1000u);
}

TEST(ByteIoTest, EveryReadFailsCleanlyOnTruncation) {
  const Bytes three = {1, 2, 3};
  ByteReader r(three);
  std::uint32_t u32;
  std::uint64_t u64;
  double d;
  float f;
  ASSERT_TRUE(r.Skip(1).ok());
  EXPECT_EQ(r.ReadU32(&u32).code(), StatusCode::kCorrupt);
  EXPECT_EQ(r.ReadU64(&u64).code(), StatusCode::kCorrupt);
  EXPECT_EQ(r.ReadF64(&d).code(), StatusCode::kCorrupt);
  EXPECT_EQ(r.ReadF32(&f).code(), StatusCode::kCorrupt);
  ByteSpan span;
  EXPECT_EQ(r.ReadBytes(3, &span).code(), StatusCode::kCorrupt);
  EXPECT_EQ(r.Skip(3).code(), StatusCode::kCorrupt);
  EXPECT_EQ(r.position(), 1u);  // failed reads do not advance
  EXPECT_NE(r.ReadU32(&u32).message().find("truncated"), std::string::npos);
  std::uint16_t u16 = 0;
  ASSERT_TRUE(r.ReadU16(&u16).ok());
  EXPECT_EQ(u16, 0x0302);
  std::uint8_t u8;
  EXPECT_EQ(r.ReadU8(&u8).code(), StatusCode::kCorrupt);
  // A varint cut in the middle.
  const Bytes cut = {0x80, 0x80};
  ByteReader rv(cut);
  EXPECT_EQ(rv.ReadVarint(&u64).code(), StatusCode::kCorrupt);
  ByteReader empty;
  EXPECT_EQ(empty.ReadU8(&u8).code(), StatusCode::kCorrupt);
  EXPECT_TRUE(empty.ExpectEnd().ok());
}

TEST(ByteIoTest, TrailingBytesAreReported) {
  const Bytes bytes = {1, 2};
  ByteReader r(bytes);
  std::uint8_t v;
  ASSERT_TRUE(r.ReadU8(&v).ok());
  EXPECT_EQ(r.ExpectEnd().code(), StatusCode::kCorrupt);
}

TEST(ByteIoTest, PatchOverwritesALengthWrittenEarlier) {
  ByteWriter w;
  w.PutU32(0);
  w.PutBytes("hello", 5);
  w.PatchU32(0, 5);
  const Bytes expected = {5, 0, 0, 0, 'h', 'e', 'l', 'l', 'o'};
  EXPECT_EQ(w.Take(), expected);
}

}  // namespace
}  // namespace ccmd
