#include "libccmd/features/bow_vector.h"

#include <gtest/gtest.h>

#include <cmath>
#include <map>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

TEST(BowVectorTest, FromEntriesSortsMergesAndDropsNonPositive) {
  const BowVector v = BowVector::FromEntries({{7, 0.5}, {2, 0.25}, {7, 0.25}, {4, 0.0}, {9, -1.0}});
  ASSERT_EQ(v.size(), 2u);
  EXPECT_EQ(v.entries()[0], (BowEntry{2, 0.25}));
  EXPECT_EQ(v.entries()[1], (BowEntry{7, 0.75}));
  EXPECT_DOUBLE_EQ(v.Weight(7), 0.75);
  EXPECT_DOUBLE_EQ(v.Weight(4), 0.0);
  EXPECT_DOUBLE_EQ(v.L1Norm(), 1.0);
}

TEST(BowVectorTest, NormalizeL1) {
  BowVector v = BowVector::FromEntries({{1, 2.0}, {3, 6.0}});
  v.NormalizeL1();
  EXPECT_DOUBLE_EQ(v.Weight(1), 0.25);
  EXPECT_DOUBLE_EQ(v.Weight(3), 0.75);
  BowVector empty;
  empty.NormalizeL1();
  EXPECT_TRUE(empty.empty());
}

TEST(L1ScoreTest, HandComputedExample) {
  // a = (w1 .5, w2 .3, w3 .2), b = (w2 .6, w4 .4):
  // |a - b|_1 = .5 + .3 + .2 + .4 = 1.4, so s = 1 - 1.4 / 2 = 0.3.
  const BowVector a = BowVector::FromEntries({{1, 0.5}, {2, 0.3}, {3, 0.2}});
  const BowVector b = BowVector::FromEntries({{2, 0.6}, {4, 0.4}});
  EXPECT_NEAR(L1Score(a, b), 0.3, 1e-12);
  EXPECT_NEAR(L1Score(b, a), 0.3, 1e-12);
  // The score normalises: scaling either vector changes nothing.
  const BowVector a3 = BowVector::FromEntries({{1, 1.5}, {2, 0.9}, {3, 0.6}});
  EXPECT_NEAR(L1Score(a3, b), 0.3, 1e-12);
}

TEST(L1ScoreTest, Extremes) {
  const BowVector a = BowVector::FromEntries({{1, 0.5}, {2, 0.5}});
  const BowVector c = BowVector::FromEntries({{5, 1.0}});
  EXPECT_DOUBLE_EQ(L1Score(a, a), 1.0);
  EXPECT_DOUBLE_EQ(L1Score(a, c), 0.0);
  EXPECT_DOUBLE_EQ(L1Score(a, BowVector()), 0.0);
  EXPECT_DOUBLE_EQ(L1Score(BowVector(), BowVector()), 0.0);
}

// Against the definition evaluated densely: 1 - 0.5 * sum_w |a_w/|a| - b_w/|b||.
TEST(L1ScoreTest, MatchesDenseDefinitionOnRandomVectors) {
  Rng rng(11);
  for (int trial = 0; trial < 200; ++trial) {
    std::vector<BowEntry> ea, eb;
    for (int i = 0; i < 30; ++i)
      ea.push_back({static_cast<WordId>(rng.UniformInt(0, 60)), rng.Uniform(0.01, 2)});
    for (int i = 0; i < 25; ++i)
      eb.push_back({static_cast<WordId>(rng.UniformInt(0, 60)), rng.Uniform(0.01, 2)});
    std::map<WordId, double> da, db;
    double na = 0, nb = 0;
    for (const auto& e : ea) da[e.word] += e.weight, na += e.weight;
    for (const auto& e : eb) db[e.word] += e.weight, nb += e.weight;
    double l1 = 0;
    for (WordId w = 0; w <= 60; ++w) l1 += std::abs(da[w] / na - db[w] / nb);
    const double expected = 1.0 - 0.5 * l1;
    EXPECT_NEAR(L1Score(BowVector::FromEntries(ea), BowVector::FromEntries(eb)), expected, 1e-12);
  }
}

TEST(FeatureVectorTest, GroupsFeaturesByNode) {
  const FeatureVector fv = FeatureVector::FromAssignments({5, 3, 5, 9, 3, 5});
  ASSERT_EQ(fv.size(), 3u);
  EXPECT_EQ(fv.groups()[0].first, 3u);
  EXPECT_EQ(fv.groups()[0].second, (std::vector<int>{1, 4}));
  EXPECT_EQ(fv.Features(5), (std::vector<int>{0, 2, 5}));
  EXPECT_EQ(fv.Features(9), (std::vector<int>{3}));
  EXPECT_TRUE(fv.Features(4).empty());
}

}  // namespace
}  // namespace ccmd
