#include "libccmd/features/bow_database.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <map>
#include <thread>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

GlobalKeyframeId Kf(int agent, int keyframe) {
  return {AgentId(static_cast<std::uint16_t>(agent)),
          KeyframeId(static_cast<std::uint32_t>(keyframe))};
}

BowVector Vec(std::vector<BowEntry> entries) { return BowVector::FromEntries(std::move(entries)); }

TEST(BowDatabaseTest, QueryScoresHandMadeVectors) {
  BowDatabase db;
  ASSERT_TRUE(db.Add(Kf(0, 1), MapId(0), Vec({{1, 0.5}, {2, 0.5}})).ok());
  ASSERT_TRUE(db.Add(Kf(0, 2), MapId(0), Vec({{2, 1.0}})).ok());
  ASSERT_TRUE(db.Add(Kf(1, 3), MapId(1), Vec({{3, 0.2}, {2, 0.2}, {1, 0.6}})).ok());
  ASSERT_TRUE(db.Add(Kf(1, 4), MapId(1), Vec({{9, 1.0}})).ok());
  // Query q = (w1 .25, w2 .5, w3 .25), weights given unnormalised (x4):
  //   kf1 (.5, .5, 0):  min-sum .25 + .5       = .75
  //   kf2 (0, 1, 0):    min-sum .5             = .5
  //   kf3 (.6, .2, .2): min-sum .25 + .2 + .2  = .65
  //   kf4 shares no word and is never visited.
  const auto result = db.Query(Vec({{1, 1.0}, {2, 2.0}, {3, 1.0}}));
  ASSERT_EQ(result.size(), 3u);
  EXPECT_EQ(result[0].keyframe, Kf(0, 1));
  EXPECT_NEAR(result[0].score, 0.75, 1e-6);
  EXPECT_EQ(result[0].common_words, 2);
  EXPECT_EQ(result[1].keyframe, Kf(1, 3));
  EXPECT_NEAR(result[1].score, 0.65, 1e-6);
  EXPECT_EQ(result[1].common_words, 3);
  EXPECT_EQ(result[1].map, MapId(1));
  EXPECT_EQ(result[2].keyframe, Kf(0, 2));
  EXPECT_NEAR(result[2].score, 0.5, 1e-6);

  PlaceQueryOptions top1;
  top1.max_results = 1;
  EXPECT_EQ(db.Query(Vec({{1, 1.0}, {2, 2.0}, {3, 1.0}}), top1).size(), 1u);
  PlaceQueryOptions min_score;
  min_score.min_score = 0.6;
  EXPECT_EQ(db.Query(Vec({{1, 1.0}, {2, 2.0}, {3, 1.0}}), min_score).size(), 2u);
  // Only candidates sharing at least 0.8 * 3 words: kf3.
  PlaceQueryOptions common;
  common.min_common_words_ratio = 0.8;
  const auto shared = db.Query(Vec({{1, 1.0}, {2, 2.0}, {3, 1.0}}), common);
  ASSERT_EQ(shared.size(), 1u);
  EXPECT_EQ(shared[0].keyframe, Kf(1, 3));
  EXPECT_TRUE(db.Query(BowVector()).empty());
}

TEST(BowDatabaseTest, Filters) {
  BowDatabase db;
  for (int agent = 0; agent < 3; ++agent) {
    for (int k = 0; k < 4; ++k) {
      ASSERT_TRUE(
          db.Add(Kf(agent, k), MapId(agent), Vec({{1, 1.0}, {static_cast<WordId>(10 + k), 1.0}}))
              .ok());
    }
  }
  const BowVector q = Vec({{1, 1.0}});
  PlaceQueryOptions all;
  all.max_results = 0;
  EXPECT_EQ(db.Query(q, all).size(), 12u);

  PlaceQueryOptions agents = all;
  agents.agents = {AgentId(2)};
  for (const auto& c : db.Query(q, agents)) EXPECT_EQ(c.keyframe.agent, AgentId(2));
  EXPECT_EQ(db.Query(q, agents).size(), 4u);

  PlaceQueryOptions maps = all;
  maps.maps = {MapId(0), MapId(1)};
  maps.exclude_maps = {MapId(1)};
  EXPECT_EQ(db.Query(q, maps).size(), 4u);

  PlaceQueryOptions exclude = all;
  exclude.exclude = {Kf(0, 0), Kf(1, 1)};
  const auto excluded = db.Query(q, exclude);
  EXPECT_EQ(excluded.size(), 10u);
  for (const auto& c : excluded) EXPECT_FALSE(exclude.exclude.count(c.keyframe));

  PlaceQueryOptions accept = all;
  accept.accept = [](const GlobalKeyframeId& id, MapId) { return id.keyframe.value() % 2 == 1; };
  EXPECT_EQ(db.Query(q, accept).size(), 6u);

  // Map fusion: map 2 becomes part of map 0.
  EXPECT_EQ(db.MoveMap(MapId(2), MapId(0)), 4);
  PlaceQueryOptions map0 = all;
  map0.maps = {MapId(0)};
  EXPECT_EQ(db.Query(q, map0).size(), 8u);
  EXPECT_TRUE(db.SetMap(Kf(1, 0), MapId(0)));
  EXPECT_EQ(db.Query(q, map0).size(), 9u);
  EXPECT_EQ(db.MapOf(Kf(1, 0)), MapId(0));
  EXPECT_FALSE(db.SetMap(Kf(7, 7), MapId(0)));
}

TEST(BowDatabaseTest, EraseAndReplace) {
  BowDatabase db;
  ASSERT_TRUE(db.Add(Kf(0, 1), MapId(0), Vec({{1, 1.0}, {2, 1.0}})).ok());
  ASSERT_TRUE(db.Add(Kf(0, 2), MapId(0), Vec({{2, 1.0}})).ok());
  EXPECT_EQ(db.size(), 2u);
  EXPECT_EQ(db.PostingCount(), 3u);
  EXPECT_TRUE(db.Erase(Kf(0, 1)));
  EXPECT_FALSE(db.Erase(Kf(0, 1)));
  EXPECT_FALSE(db.Contains(Kf(0, 1)));
  EXPECT_EQ(db.PostingCount(), 1u);
  EXPECT_TRUE(db.Query(Vec({{1, 1.0}})).empty());
  // Adding an id again replaces its vector.
  ASSERT_TRUE(db.Add(Kf(0, 2), MapId(3), Vec({{5, 1.0}})).ok());
  EXPECT_EQ(db.size(), 1u);
  EXPECT_EQ(db.PostingCount(), 1u);
  EXPECT_TRUE(db.Query(Vec({{2, 1.0}})).empty());
  ASSERT_EQ(db.Query(Vec({{5, 1.0}})).size(), 1u);
  EXPECT_EQ(db.Get(Kf(0, 2)), Vec({{5, 1.0}}));
  EXPECT_EQ(db.MapOf(Kf(0, 2)), MapId(3));
  db.Clear();
  EXPECT_EQ(db.size(), 0u);
  EXPECT_TRUE(db.Query(Vec({{5, 1.0}})).empty());
}

TEST(BowDatabaseTest, RefusesWordsBeyondLimit) {
  BowDatabase db;
  EXPECT_EQ(db.Add(Kf(0, 1), MapId(0), Vec({{1, 1.0}, {BowDatabase::kMaxWords, 1.0}})).code(),
            StatusCode::kOutOfRange);
  EXPECT_EQ(db.size(), 0u);
}

// Random adds, replacements and erasures; after each step every query must equal a brute-force
// L1 score over the keyframes present (the reference).
TEST(BowDatabaseTest, RandomOperationsMatchBruteForce) {
  Rng rng(17);
  BowDatabase db;
  std::map<GlobalKeyframeId, BowVector> reference;
  auto random_vector = [&] {
    std::vector<BowEntry> e;
    const int n = rng.UniformInt(1, 12);
    for (int i = 0; i < n; ++i)
      e.push_back({static_cast<WordId>(rng.UniformInt(0, 40)), rng.Uniform(0.1, 1)});
    return Vec(e);
  };
  for (int step = 0; step < 400; ++step) {
    const GlobalKeyframeId id = Kf(rng.UniformInt(0, 2), rng.UniformInt(0, 30));
    if (rng.Bernoulli(0.3)) {
      EXPECT_EQ(db.Erase(id), reference.erase(id) == 1);
    } else {
      BowVector v = random_vector();
      ASSERT_TRUE(db.Add(id, MapId(0), v).ok());
      reference[id] = v;
    }
    ASSERT_EQ(db.size(), reference.size());
    std::size_t postings = 0;
    for (const auto& [kf, v] : reference) postings += v.size();
    ASSERT_EQ(db.PostingCount(), postings);
    if (step % 10 != 0) continue;
    const BowVector q = random_vector();
    PlaceQueryOptions all;
    all.max_results = 0;
    const auto result = db.Query(q, all);
    std::map<GlobalKeyframeId, double> expected;
    for (const auto& [kf, v] : reference) {
      const double s = L1Score(q, v);
      if (s > 0) expected[kf] = s;
    }
    ASSERT_EQ(result.size(), expected.size());
    for (std::size_t i = 0; i < result.size(); ++i) {
      EXPECT_NEAR(result[i].score, expected.at(result[i].keyframe), 1e-6);
      if (i > 0) {
        EXPECT_GE(result[i - 1].score, result[i].score);
      }
    }
  }
}

// One thread adds while another queries (the server's pattern). Every query sees a
// consistent database: scores of what it returns match the vectors added.
TEST(BowDatabaseTest, ConcurrentAddAndQuery) {
  BowDatabase db;
  constexpr int kCount = 2000;
  std::thread writer([&] {
    for (int i = 0; i < kCount; ++i) {
      ASSERT_TRUE(
          db.Add(Kf(0, i), MapId(0), Vec({{static_cast<WordId>(i % 50), 1.0}, {1000, 1.0}})).ok());
      if (i % 7 == 0) db.Erase(Kf(0, i / 2));
    }
  });
  for (int query = 0; query < 300; ++query) {
    PlaceQueryOptions options;
    options.max_results = 5;
    for (const auto& c : db.Query(Vec({{1000, 1.0}, {7, 1.0}}), options)) {
      // A keyframe holding word 7 scores 1.0; any other 0.5.
      EXPECT_NEAR(c.score, c.keyframe.keyframe.value() % 50 == 7 ? 1.0 : 0.5, 1e-6);
    }
  }
  writer.join();
  std::size_t expected = 0;
  std::vector<bool> present(kCount, false);
  for (int i = 0; i < kCount; ++i) {
    present[i] = true;
    if (i % 7 == 0) present[i / 2] = false;
  }
  expected = std::count(present.begin(), present.end(), true);
  EXPECT_EQ(db.size(), expected);
}

}  // namespace
}  // namespace ccmd
