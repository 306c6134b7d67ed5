#include <cmath>
#include <cstdint>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/codec/huffman.h"
#include "libccmd/codec/tans.h"
#include "libccmd/util/random.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

TEST(HuffmanTest, CodeLengthsOfAKnownHistogram) {
  // Counts 1, 1, 2, 4: Huffman merges 1+1, then 2+2, then 4+4: lengths 3, 3, 2, 1.
  const std::uint32_t counts[4] = {1, 1, 2, 4};
  EXPECT_EQ(HuffmanCodeLengths(counts, 4, 11), (std::vector<int>{3, 3, 2, 1}));
  const std::uint32_t one[3] = {0, 5, 0};
  EXPECT_EQ(HuffmanCodeLengths(one, 3, 11), (std::vector<int>{0, 1, 0}));
}

TEST(HuffmanTest, LengthLimitKeepsAPrefixCode) {
  // Fibonacci counts make the deepest possible tree (depth 29 for 30 symbols).
  std::vector<std::uint32_t> counts(30);
  counts[0] = counts[1] = 1;
  for (int i = 2; i < 30; ++i) counts[i] = counts[i - 1] + counts[i - 2];
  const std::vector<int> lengths = HuffmanCodeLengths(counts.data(), 30, 11);
  double kraft = 0;
  for (int l : lengths) {
    ASSERT_GE(l, 1);
    ASSERT_LE(l, 11);
    kraft += std::ldexp(1.0, -l);
  }
  EXPECT_LE(kraft, 1.0);
}

Bytes HuffmanRoundTrip(const Bytes& in) {
  Bytes coded;
  HuffmanEncode(in, &coded);
  Bytes out;
  std::size_t used = 0;
  const Status s = HuffmanDecode(coded, in.size(), &out, &used);
  EXPECT_TRUE(s.ok()) << s.ToString();
  EXPECT_EQ(used, coded.size());
  return out;
}

TEST(HuffmanTest, RoundTrips) {
  EXPECT_EQ(HuffmanRoundTrip({}), Bytes{});
  EXPECT_EQ(HuffmanRoundTrip(Bytes(1000, 7)), Bytes(1000, 7));  // one value: no bits
  EXPECT_EQ(HuffmanRoundTrip({1, 2, 3}), (Bytes{1, 2, 3}));     // fewer symbols than streams
  Rng rng(8);
  Bytes skewed(100001);
  for (auto& b : skewed)
    b = static_cast<std::uint8_t>(std::min(255.0, -std::log(rng.Uniform() + 1e-12) * 3));
  EXPECT_EQ(HuffmanRoundTrip(skewed), skewed);
  Bytes uniform(65537);
  for (auto& b : uniform) b = static_cast<std::uint8_t>(rng.Next());
  EXPECT_EQ(HuffmanRoundTrip(uniform), uniform);
}

TEST(HuffmanTest, ImageRoundTripAndCorruption) {
  Rng rng(9);
  const int w = 37, h = 23;
  Bytes image(w * h);
  for (auto& b : image)
    b = static_cast<std::uint8_t>(rng.Bernoulli(0.6) ? 1 : rng.UniformInt(0, 40));
  Bytes coded;
  HuffmanEncodeImage(image, w, h, &coded);
  Bytes out;
  ASSERT_TRUE(HuffmanDecodeImage(coded, w, h, &out).ok());
  EXPECT_EQ(out, image);
  for (std::size_t n = 0; n + 1 < coded.size(); n += 7) {
    EXPECT_FALSE(HuffmanDecodeImage(Bytes(coded.begin(), coded.begin() + n), w, h, &out).ok()) << n;
  }
  Bytes small;
  EXPECT_EQ(HuffmanDecode(Bytes{0xFF, 0xFF, 0x0F}, 1000, &small).code(), StatusCode::kOutOfRange);
}

TEST(TansTest, RoundTripWithContexts) {
  Rng rng(10);
  std::vector<std::uint16_t> items;
  for (int i = 0; i < 50001; ++i) {
    const int context = rng.UniformInt(0, 5);
    // Context c favours symbol c; context 5 holds a single symbol (costs no bits).
    const int symbol = context == 5 ? 3 : rng.Bernoulli(0.8) ? context : rng.UniformInt(0, 20);
    items.push_back(TansItem(context, symbol));
  }
  Bytes coded;
  TansEncode(items, 6, 21, nullptr, &coded);
  TansDecoder dec;
  std::size_t used = 0;
  ASSERT_TRUE(dec.Init(coded, 6, 21, &used).ok());
  EXPECT_EQ(used, coded.size());
  TansDecoder::Cursor cursor = dec.cursor();
  for (std::uint16_t item : items) ASSERT_EQ(cursor.Get(item >> 6), item & 63);
  dec.set_cursor(cursor);
  EXPECT_TRUE(dec.Finish().ok());
  // Near the entropy: about 0.8 bits of "which" plus the rest; far below 5 bits per item.
  EXPECT_LT(coded.size() * 8.0 / items.size(), 2.5);
}

TEST(TansTest, DetectsAWrongSymbolCount) {
  std::vector<std::uint16_t> items(1000, TansItem(0, 1));
  for (int i = 0; i < 1000; i += 3) items[i] = TansItem(0, 2);
  Bytes coded;
  TansEncode(items, 1, 4, nullptr, &coded);
  TansDecoder dec;
  ASSERT_TRUE(dec.Init(coded, 1, 4, nullptr).ok());
  TansDecoder::Cursor cursor = dec.cursor();
  for (int i = 0; i < 900; ++i) cursor.Get(0);  // stop early
  dec.set_cursor(cursor);
  EXPECT_EQ(dec.Finish().code(), StatusCode::kCorrupt);
}

}  // namespace
}  // namespace ccmd
