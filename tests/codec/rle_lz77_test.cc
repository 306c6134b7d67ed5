#include <cstdint>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/codec/lz77.h"
#include "libccmd/codec/rle.h"
#include "libccmd/util/random.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;
using Samples = std::vector<std::uint16_t>;

Samples RleRoundTrip(const Samples& in) {
  Bytes coded;
  RleEncode(in, &coded);
  Samples out;
  const Status s = RleDecode(coded, in.size(), &out);
  EXPECT_TRUE(s.ok()) << s.ToString();
  return out;
}

TEST(RleTest, LayoutByHand) {
  Bytes coded;
  RleEncode(Samples{7, 7, 7, 7, 7}, &coded);
  // One run token: ((5 - 1) << 1) | 1 = 9, then the sample 7 little-endian.
  EXPECT_EQ(coded, (Bytes{9, 7, 0}));
  coded.clear();
  RleEncode(Samples{1, 2, 2, 0x0304}, &coded);
  // A run of 2 is not worth a token: one literal group of 4: (3 << 1) = 6.
  EXPECT_EQ(coded, (Bytes{6, 1, 0, 2, 0, 2, 0, 4, 3}));
  coded.clear();
  RleEncode(Samples{}, &coded);
  EXPECT_TRUE(coded.empty());
}

TEST(RleTest, RoundTrips) {
  EXPECT_EQ(RleRoundTrip({}), Samples{});
  EXPECT_EQ(RleRoundTrip(Samples(100000, 1234)), Samples(100000, 1234));
  Rng rng(3);
  Samples mixed;
  for (int i = 0; i < 5000; ++i) {
    const auto v = static_cast<std::uint16_t>(rng.UniformInt(0, 65535));
    mixed.insert(mixed.end(), rng.Bernoulli(0.3) ? rng.UniformInt(1, 300) : 1, v);
  }
  EXPECT_EQ(RleRoundTrip(mixed), mixed);
}

TEST(RleTest, CorruptInputIsAnError) {
  Samples out;
  // A run of 5 into a 4-sample image.
  EXPECT_EQ(RleDecode(Bytes{9, 7, 0}, 4, &out).code(), StatusCode::kCorrupt);
  // Truncated literal group and truncated run value.
  EXPECT_EQ(RleDecode(Bytes{6, 1, 0, 2}, 4, &out).code(), StatusCode::kCorrupt);
  EXPECT_EQ(RleDecode(Bytes{9, 7}, 5, &out).code(), StatusCode::kCorrupt);
  // Trailing bytes, and a count near 2^64.
  EXPECT_EQ(RleDecode(Bytes{9, 7, 0, 0}, 5, &out).code(), StatusCode::kCorrupt);
  const Bytes huge = {0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x01, 7, 0};
  EXPECT_EQ(RleDecode(huge, 5, &out).code(), StatusCode::kCorrupt);
}

Bytes Lz77RoundTrip(const Bytes& in, int chain = 8) {
  Bytes coded;
  Lz77Compress(in, &coded, {chain});
  Bytes out;
  const Status s = Lz77Decompress(coded, in.size(), &out);
  EXPECT_TRUE(s.ok()) << s.ToString();
  return out;
}

TEST(Lz77Test, DecodesAHandBuiltStream) {
  // "abababab": 2 literals then a match of 6 at offset 2 (overlapping its own output).
  // token: literal count 2 in the high nibble, match length 6 - 4 = 2 in the low nibble.
  const Bytes stream = {8, 0x22, 'a', 'b', 2, 0};
  Bytes out;
  ASSERT_TRUE(Lz77Decompress(stream, 100, &out).ok());
  EXPECT_EQ(std::string(out.begin(), out.end()), "abababab");
  // Extended lengths: 4 + 15 + 255 + 3 = 277 copies of 'x' after one literal.
  Bytes longer = {0x96, 0x02, 0x1F, 'x', 1, 0, 255, 3};  // raw size 278 = varint 96 02
  ASSERT_TRUE(Lz77Decompress(longer, 1000, &out).ok());
  EXPECT_EQ(out, Bytes(278, 'x'));
}

TEST(Lz77Test, RoundTripsEdgeCases) {
  EXPECT_EQ(Lz77RoundTrip({}), Bytes{});
  EXPECT_EQ(Lz77RoundTrip({42}), Bytes{42});
  EXPECT_EQ(Lz77RoundTrip(Bytes(1 << 20, 0)), Bytes(1 << 20, 0));
  Rng rng(5);
  Bytes random(100000);
  for (auto& b : random) b = static_cast<std::uint8_t>(rng.Next());
  EXPECT_EQ(Lz77RoundTrip(random), random);
  // Long matches at every offset class: a random block repeated with changes.
  Bytes repeated;
  for (int k = 0; k < 50; ++k) {
    repeated.insert(repeated.end(), random.begin(), random.begin() + 3000 + k);
    repeated.push_back(static_cast<std::uint8_t>(k));
  }
  for (int chain : {1, 8, 64}) EXPECT_EQ(Lz77RoundTrip(repeated, chain), repeated);
  // Short periodic patterns (offsets 1..7 take the byte-wise copy path).
  for (int period = 1; period <= 9; ++period) {
    Bytes pattern;
    for (int i = 0; i < 5000; ++i) pattern.push_back(static_cast<std::uint8_t>(i % period * 37));
    EXPECT_EQ(Lz77RoundTrip(pattern), pattern) << period;
  }
}

TEST(Lz77Test, CompressesRepetitionAndNotNoise) {
  Bytes coded;
  Lz77Compress(Bytes(100000, 9), &coded);
  EXPECT_LT(coded.size(), 500u);  // 100000 / 255 length bytes at most
  Rng rng(6);
  Bytes random(10000);
  for (auto& b : random) b = static_cast<std::uint8_t>(rng.Next());
  coded.clear();
  Lz77Compress(random, &coded);
  EXPECT_LT(coded.size(), random.size() + random.size() / 200 + 16);  // bounded expansion
}

TEST(Lz77Test, CorruptInputIsAnError) {
  Bytes out;
  // Claimed size above the caller's limit: rejected before allocating.
  EXPECT_EQ(Lz77Decompress(Bytes{0xFF, 0xFF, 0xFF, 0x7F, 0x00}, 1000, &out).code(),
            StatusCode::kOutOfRange);
  // Claimed size far beyond what the input could expand to.
  EXPECT_EQ(Lz77Decompress(Bytes{0xFF, 0xFF, 0x03, 0x00}, 1 << 20, &out).code(),
            StatusCode::kCorrupt);
  // Offset 0, and an offset before the start of the output.
  EXPECT_EQ(Lz77Decompress(Bytes{8, 0x22, 'a', 'b', 0, 0}, 100, &out).code(), StatusCode::kCorrupt);
  EXPECT_EQ(Lz77Decompress(Bytes{8, 0x22, 'a', 'b', 3, 0}, 100, &out).code(), StatusCode::kCorrupt);
  // A match longer than the output, truncation and trailing bytes.
  EXPECT_EQ(Lz77Decompress(Bytes{7, 0x22, 'a', 'b', 2, 0}, 100, &out).code(), StatusCode::kCorrupt);
  const Bytes good = {8, 0x22, 'a', 'b', 2, 0};
  for (std::size_t n = 0; n < good.size(); ++n) {
    EXPECT_FALSE(Lz77Decompress(Bytes(good.begin(), good.begin() + n), 100, &out).ok()) << n;
  }
  Bytes trailing = good;
  trailing.push_back(0);
  EXPECT_EQ(Lz77Decompress(trailing, 100, &out).code(), StatusCode::kCorrupt);
}

}  // namespace
}  // namespace ccmd
