#include "libccmd/io/split.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

TEST(SplitTest, ThreeSegmentsOf600) {
  // L = ceil(600 / 2.8) = 215, overlap ceil(21.5) = 22, stride 193.
  auto s = SplitWithOverlap(600, 3);
  ASSERT_TRUE(s.ok());
  ASSERT_EQ(s->size(), 3u);
  EXPECT_EQ((*s)[0].first, 0);
  EXPECT_EQ((*s)[0].last, 214);
  EXPECT_EQ((*s)[1].first, 193);
  EXPECT_EQ((*s)[1].last, 407);
  EXPECT_EQ((*s)[2].first, 386);
  EXPECT_EQ((*s)[2].last, 599);
}

TEST(SplitTest, CoversEverythingWithTenPercentOverlap) {
  for (int n : {50, 101, 600, 613, 2870}) {
    for (int k = 1; k <= 6; ++k) {
      auto s = SplitWithOverlap(n, k);
      ASSERT_TRUE(s.ok()) << n << " " << k;
      EXPECT_EQ(s->front().first, 0);
      EXPECT_EQ(s->back().last, n - 1);
      for (std::size_t i = 1; i < s->size(); ++i) {
        const int shared = (*s)[i - 1].last - (*s)[i].first + 1;
        EXPECT_GE(shared, 0.1 * (*s)[i - 1].size() - 1e-9) << n << " " << k << " " << i;
        EXPECT_LE(shared, 0.1 * (*s)[i - 1].size() + 1) << n << " " << k << " " << i;
        EXPECT_LT((*s)[i - 1].first, (*s)[i].first);
      }
    }
  }
}

TEST(SplitTest, RejectsImpossibleSplits) {
  EXPECT_FALSE(SplitWithOverlap(5, 4).ok());
  EXPECT_FALSE(SplitWithOverlap(100, 0).ok());
  EXPECT_FALSE(SplitWithOverlap(0, 2).ok());
  EXPECT_FALSE(SplitWithOverlap(100, 2, 0.6).ok());
}

TEST(SplitTest, SegmentSpec) {
  EXPECT_EQ(*ParseSegmentSpec("2/3"), std::make_pair(2, 3));
  EXPECT_FALSE(ParseSegmentSpec("0/3").ok());
  EXPECT_FALSE(ParseSegmentSpec("4/3").ok());
  EXPECT_FALSE(ParseSegmentSpec("2").ok());
}

}  // namespace
}  // namespace ccmd
