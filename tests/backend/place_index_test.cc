// The back-end's place index on generated places: each place is a set of random descriptors
// and a keyframe of it sees them with a few bits flipped.

#include "libccmd/backend/place_index.h"

#include <gtest/gtest.h>

#include <algorithm>

#include "libccmd/backend/loop_verification.h"
#include "tests/backend/generated_map.h"

namespace ccmd {
namespace {

using testing::FlipBits;
using testing::RandomDescriptor;

constexpr int kPlaces = 10;
constexpr int kPerPlace = 300;

std::vector<std::vector<Descriptor>> MakePlaces(Rng* rng) {
  std::vector<std::vector<Descriptor>> places(kPlaces);
  for (auto& place : places) {
    for (int i = 0; i < kPerPlace; ++i) place.push_back(RandomDescriptor(rng));
  }
  return places;
}

// A keyframe of a place: 80 % of its descriptors, each with 8 bits flipped.
std::vector<Descriptor> View(const std::vector<Descriptor>& place, Rng* rng) {
  std::vector<Descriptor> view;
  for (const Descriptor& d : place) {
    if (rng->Bernoulli(0.8)) view.push_back(FlipBits(d, 8, rng));
  }
  return view;
}

cv::Mat ToMat(const std::vector<Descriptor>& descriptors) {
  cv::Mat m(static_cast<int>(descriptors.size()), 32, CV_8U);
  for (std::size_t i = 0; i < descriptors.size(); ++i) {
    std::copy(descriptors[i].begin(), descriptors[i].end(), m.ptr(static_cast<int>(i)));
  }
  return m;
}

// A fixed vocabulary trained on one view of each place (no online training).
PlaceIndexOptions TrainedOn(const std::vector<std::vector<Descriptor>>& places, Rng* rng) {
  std::vector<cv::Mat> training;
  for (const auto& place : places) training.push_back(ToMat(View(place, rng)));
  VocabularyOptions vocabulary;
  vocabulary.depth = 3;
  auto trained = Vocabulary::Train(training, vocabulary);
  PlaceIndexOptions options;
  if (trained.ok())
    options.vocabulary = std::make_shared<const Vocabulary>(std::move(trained).value());
  options.online_training = false;
  return options;
}

GlobalKeyframeId Kf(int keyframe) {
  return {AgentId(1), KeyframeId(static_cast<std::uint32_t>(keyframe))};
}

const auto kAcceptAll = [](const GlobalKeyframeId&) { return true; };

TEST(PlaceIndexTest, AQueryFindsTheKeyframeOfItsPlaceAndHonoursTheFilter) {
  Rng rng(3);
  const auto places = MakePlaces(&rng);
  const PlaceIndexOptions options = TrainedOn(places, &rng);
  ASSERT_TRUE(options.vocabulary);
  PlaceIndex index(options);
  ASSERT_TRUE(index.ready());
  for (int p = 0; p < kPlaces; ++p) EXPECT_TRUE(index.Add(Kf(p), View(places[p], &rng)).empty());
  EXPECT_TRUE(index.Add(Kf(14), View(places[4], &rng)).empty());  // place 4 seen again

  for (int p = 0; p < kPlaces; ++p) {
    const std::vector<PlaceHit> hits = index.Query(View(places[p], &rng), 3, kAcceptAll);
    ASSERT_FALSE(hits.empty());
    if (p == 4) {
      EXPECT_TRUE(hits[0].keyframe == Kf(4) || hits[0].keyframe == Kf(14));
      ASSERT_GE(hits.size(), 2u);
      EXPECT_TRUE(hits[1].keyframe == Kf(4) || hits[1].keyframe == Kf(14));
    } else {
      EXPECT_EQ(hits[0].keyframe, Kf(p));
    }
    for (std::size_t i = 1; i < hits.size(); ++i) EXPECT_LE(hits[i].score, hits[i - 1].score);
  }
  // The filter removes keyframes before they are ranked.
  const std::vector<PlaceHit> filtered =
      index.Query(View(places[7], &rng), 3, [](const GlobalKeyframeId& id) { return id != Kf(7); });
  for (const PlaceHit& hit : filtered) EXPECT_NE(hit.keyframe, Kf(7));
  // Scores between stored keyframes: the same place scores above any other pair.
  const double same = index.Score(Kf(4), Kf(14));
  EXPECT_DOUBLE_EQ(same, index.Score(Kf(14), Kf(4)));
  for (int p = 0; p < kPlaces; ++p) {
    if (p == 4) continue;
    EXPECT_GT(same, 2 * index.Score(Kf(4), Kf(p))) << p;
  }
  EXPECT_EQ(index.Score(Kf(4), Kf(99)), 0.0);  // not stored
}

// A map that many agents share holds a place many times over: its copies fill every slot of
// a query, and the other map's keyframe of the place is found only by a query that leaves the
// crowded map's agents out (what the loop closer asks when the first query found no other map).
TEST(PlaceIndexTest, AnotherMapsKeyframeIsFoundWhenTheQuerysAgentsAreLeftOut) {
  Rng rng(5);
  const auto places = MakePlaces(&rng);
  const PlaceIndexOptions options = TrainedOn(places, &rng);
  ASSERT_TRUE(options.vocabulary);
  PlaceIndex index(options);
  const auto Id = [](int agent, int keyframe) {
    return GlobalKeyframeId{AgentId(static_cast<std::uint16_t>(agent)),
                            KeyframeId(static_cast<std::uint32_t>(keyframe))};
  };
  // Agents 1-4 (one map) hold place 2 as the query sees it, three keyframes each; agent 5
  // (another map) holds its own view of it; other places fill the index.
  const std::vector<Descriptor> seen = View(places[2], &rng);
  for (int agent = 1; agent <= 4; ++agent) {
    for (int k = 0; k < 3; ++k) index.Add(Id(agent, k), seen);
  }
  index.Add(Id(5, 0), View(places[2], &rng));
  for (int p = 0; p < kPlaces; ++p) {
    if (p != 2) index.Add(Id(6, p), View(places[p], &rng));
  }
  LoopCandidateRule rule;
  rule.query = Id(1, 50);
  const std::vector<PlaceHit> crowded = QueryLoopCandidates(index, seen, rule, 12);
  ASSERT_EQ(crowded.size(), 12u);
  for (const PlaceHit& hit : crowded) EXPECT_LE(hit.keyframe.agent.value(), 4) << hit.score;
  rule.excluded_agents = {AgentId(1), AgentId(2), AgentId(3), AgentId(4)};
  const std::vector<PlaceHit> others = QueryLoopCandidates(index, seen, rule, 4);
  ASSERT_FALSE(others.empty());
  EXPECT_EQ(others[0].keyframe, Id(5, 0));
  for (const PlaceHit& hit : others) EXPECT_GT(hit.keyframe.agent.value(), 4);
}

TEST(PlaceIndexTest, OnlineTrainingMakesTheEarlierKeyframesLateQueries) {
  Rng rng(4);
  const auto places = MakePlaces(&rng);
  PlaceIndexOptions options;
  options.online.first_training = 5;
  options.online.vocabulary.depth = 3;
  PlaceIndex index(options);
  for (int p = 0; p < 4; ++p) {
    EXPECT_TRUE(index.Add(Kf(p), View(places[p], &rng)).empty());
    EXPECT_FALSE(index.ready());
    EXPECT_TRUE(index.Query(View(places[p], &rng), 3, kAcceptAll).empty());
  }
  // The fifth keyframe triggers the first training: the four before it were never queried.
  const std::vector<GlobalKeyframeId> late = index.Add(Kf(4), View(places[4], &rng));
  EXPECT_EQ(late, (std::vector<GlobalKeyframeId>{Kf(0), Kf(1), Kf(2), Kf(3)}));
  EXPECT_TRUE(index.ready());
  EXPECT_EQ(index.trainings(), 1);
  for (int p = 0; p < 5; ++p) {
    const std::vector<PlaceHit> hits = index.Query(View(places[p], &rng), 1, kAcceptAll);
    ASSERT_EQ(hits.size(), 1u);
    EXPECT_EQ(hits[0].keyframe, Kf(p));
  }
  EXPECT_TRUE(index.Add(Kf(5), View(places[5], &rng)).empty());  // nothing late any more
}

}  // namespace
}  // namespace ccmd
