#include <gtest/gtest.h>

#include "libccmd/io/tum_dataset.h"

namespace ccmd {
namespace {

using Pairs = std::vector<std::pair<std::size_t, std::size_t>>;

TEST(AssociationTest, PairsWithinToleranceOnly) {
  // rgb 1.000 pairs with depth 1.010 (10 ms), rgb 1.033 with 1.045 (12 ms); rgb 1.066 is
  // 21 ms from 1.045 and too far from 1.2: unmatched.
  const Pairs pairs = AssociateTimestamps({1.000, 1.033, 1.066}, {1.010, 1.045, 1.200}, 0.02);
  EXPECT_EQ(pairs, (Pairs{{0, 0}, {1, 1}}));
}

TEST(AssociationTest, GreedyClosestFirstEachFileOnce) {
  // One depth frame between two colour frames goes to the closer one (5 ms), not to the
  // first one that is in tolerance (10 ms), as in TUM's associate.py.
  EXPECT_EQ(AssociateTimestamps({1.000, 1.015}, {1.010}, 0.02), (Pairs{{1, 0}}));
}

TEST(AssociationTest, OffsetShiftsTheSecondList) {
  EXPECT_EQ(AssociateTimestamps({2.0}, {1.0}, 0.02, /*offset=*/1.0), (Pairs{{0, 0}}));
  EXPECT_TRUE(AssociateTimestamps({2.0}, {1.0}, 0.02).empty());
}

TEST(AssociationTest, UnsortedInputGivesTheSamePairs) {
  const Pairs sorted = AssociateTimestamps({1.0, 2.0, 3.0}, {1.001, 2.002, 3.003}, 0.02);
  const Pairs shuffled = AssociateTimestamps({3.0, 1.0, 2.0}, {2.002, 3.003, 1.001}, 0.02);
  EXPECT_EQ(sorted, (Pairs{{0, 0}, {1, 1}, {2, 2}}));
  EXPECT_EQ(shuffled, (Pairs{{0, 1}, {1, 2}, {2, 0}}));
}

}  // namespace
}  // namespace ccmd
