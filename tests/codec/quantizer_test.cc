#include "libccmd/codec/depth_quantizer.h"

#include <cstdint>
#include <cstdlib>

#include <gtest/gtest.h>

namespace ccmd {
namespace {

// Values at the bin edges, computed by hand from eq. 6 (corrected), integer division.
TEST(QuantizerTest, Eq6CodesAtTheBinEdges) {
  EXPECT_EQ(QuantizeEq6(0), 0);
  EXPECT_EQ(QuantizeEq6(200), 0);  // d <= 200: invalid
  EXPECT_EQ(QuantizeEq6(201), 1);  // 201 - 200
  EXPECT_EQ(QuantizeEq6(2999), 2799);
  EXPECT_EQ(QuantizeEq6(3000), 2800);   // 3000 - 200
  EXPECT_EQ(QuantizeEq6(3001), 2800);   // 2800 + 1/2
  EXPECT_EQ(QuantizeEq6(3002), 2801);   // 2800 + 2/2
  EXPECT_EQ(QuantizeEq6(5999), 4299);   // 2800 + 2999/2
  EXPECT_EQ(QuantizeEq6(6000), 4300);   // 2800 + 3000/2
  EXPECT_EQ(QuantizeEq6(6003), 4300);   // 4300 + 3/4
  EXPECT_EQ(QuantizeEq6(6004), 4301);   // 4300 + 4/4
  EXPECT_EQ(QuantizeEq6(12000), 5800);  // 4300 + 6000/4
  EXPECT_EQ(QuantizeEq6(12007), 5800);  // 5800 + 7/8
  EXPECT_EQ(QuantizeEq6(12008), 5801);
  EXPECT_EQ(QuantizeEq6(23999), 7299);  // 5800 + 11999/8
  EXPECT_EQ(QuantizeEq6(24000), 7300);  // 5800 + 12000/8: the largest code, 13 bits
  EXPECT_EQ(QuantizeEq6(24001), 0);     // beyond range: invalid
  EXPECT_EQ(QuantizeEq6(65535), 0);
}

TEST(QuantizerTest, Eq6DecodesToTheBinCentre) {
  EXPECT_EQ(DequantizeEq6(0), 0);
  EXPECT_EQ(DequantizeEq6(1), 201);
  EXPECT_EQ(DequantizeEq6(2799), 2999);
  EXPECT_EQ(DequantizeEq6(2800), 3001);   // bin {3000, 3001}
  EXPECT_EQ(DequantizeEq6(2801), 3003);   // bin {3002, 3003}
  EXPECT_EQ(DequantizeEq6(4300), 6002);   // bin 6000..6003
  EXPECT_EQ(DequantizeEq6(5800), 12004);  // bin 12000..12007
  EXPECT_EQ(DequantizeEq6(7299), 23996);  // bin 23992..23999
  EXPECT_EQ(DequantizeEq6(7300), 24000);  // bin {24000}
  EXPECT_EQ(Eq6Bin(4301), (std::pair<std::uint16_t, std::uint16_t>{6004, 6007}));
}

TEST(QuantizerTest, Eq6ErrorBoundOnEveryDepth) {
  for (int d = 201; d <= 24000; ++d) {
    const std::uint16_t code = QuantizeEq6(static_cast<std::uint16_t>(d));
    ASSERT_GE(code, 1);
    ASSERT_LE(code, 7300);
    const int error = std::abs(DequantizeEq6(code) - d);
    // Half the bin width: bins of 1, 2, 4, 8 mm in the four ranges.
    // The boundary depths 3000, 6000, 12000 share a bin with the depths above them.
    const int bound = d < 3000 ? 0 : d < 6000 ? 1 : d < 12000 ? 2 : 4;
    ASSERT_LE(error, bound) << "d = " << d;
    const auto [first, last] = Eq6Bin(code);
    ASSERT_LE(first, d);
    ASSERT_GE(last, d);
  }
}

class RelativeQuantizerTest : public ::testing::TestWithParam<int> {};

TEST_P(RelativeQuantizerTest, EveryAdmissibleCodeIsWithinTheBound) {
  const int e = GetParam();
  const RelativeQuantizer q(e);
  EXPECT_EQ(q.FirstAdmissible(0), 0);
  EXPECT_EQ(q.Dequantize(0), 0);
  int previous_first = 1;
  for (int d = 1; d <= 65535; ++d) {
    const auto depth = static_cast<std::uint16_t>(d);
    const int first = q.FirstAdmissible(depth), last = q.LastAdmissible(depth);
    ASSERT_GE(first, 1);
    ASSERT_LE(first, last);
    ASSERT_LT(last, q.num_codes());
    ASSERT_GE(first, previous_first);  // intervals move up with depth
    previous_first = first;
    for (int c = first; c <= last; ++c) {
      // |value - d| <= e / 1e4 * d, in integers.
      ASSERT_LE(10000LL * std::abs(q.Dequantize(static_cast<std::uint16_t>(c)) - d),
                static_cast<long long>(e) * d)
          << "d = " << d << " code " << c;
    }
    const int nearest = q.Quantize(depth);
    ASSERT_GE(nearest, first);
    ASSERT_LE(nearest, last);
  }
}

INSTANTIATE_TEST_SUITE_P(Bounds, RelativeQuantizerTest, ::testing::Values(50, 100, 200, 500));

TEST(QuantizerTest, RelativeGridIsExactBelowTheBoundsResolution) {
  // At 1 %, a depth below 100 mm has a tolerance under 1 mm: it must be kept exactly.
  const RelativeQuantizer& q = RelativeQuantizer::ForBound(100);
  for (int d = 1; d < 100; ++d) {
    EXPECT_EQ(q.Dequantize(q.Quantize(static_cast<std::uint16_t>(d))), d);
  }
  // The grid is much coarser than millimetres at range: about 1.3 % steps.
  EXPECT_LT(q.num_codes(), 1200);
}

}  // namespace
}  // namespace ccmd
