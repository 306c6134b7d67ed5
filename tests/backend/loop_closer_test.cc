// The loop closer's steps on generated data: the consistency rule, the cool-down, the choice
// of candidates, the correction inside a map and the fusion of two maps, and the whole
// LoopCloser on a generated revisit.

#include "libccmd/backend/loop_closer.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <set>

#include "libccmd/backend/loop_verification.h"
#include "libccmd/features/bow_vocabulary.h"
#include "tests/backend/generated_map.h"

namespace ccmd {
namespace {

using testing::AddGeneratedKeyframe;
using testing::CirclePose;
using testing::GeneratedWorld;
using testing::MakeRingWorld;

constexpr double kDegree = M_PI / 180;

Pose Offset(double metres, double degrees) {
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(degrees * kDegree, Eigen::Vector3d(0.3, 1, 0.2).normalized())
                   .toRotationMatrix();
  T.translation() = Eigen::Vector3d(metres, 0, 0);
  return T;
}

GlobalKeyframeId Kf(int agent, int keyframe) {
  return {AgentId(static_cast<std::uint16_t>(agent)),
          KeyframeId(static_cast<std::uint32_t>(keyframe))};
}

// A query at its map's origin: its pose in the candidate's map is the map-to-map transform.
const Pose kAtOrigin = Pose::Identity();

TEST(LoopConsistencyTest, TwoAgreeingKeyframesCloseALoopAndTheCountStartsAgain) {
  LoopConsistency rule{LoopCloserOptions()};
  const Pose T = Offset(0.8, 20);
  int count = 0;
  EXPECT_FALSE(rule.Confirm(Kf(1, 10), MapId(2), T, kAtOrigin, &count));
  EXPECT_EQ(count, 1);
  // 3 ids later, 4 cm and 2 degrees apart: within 5 cm and 3 degrees.
  EXPECT_TRUE(rule.Confirm(Kf(1, 13), MapId(2), T * Offset(0.04, 2), kAtOrigin, &count));
  EXPECT_EQ(count, 2);
  // Accepted: the next one starts a new count.
  EXPECT_FALSE(rule.Confirm(Kf(1, 14), MapId(2), T, kAtOrigin, &count));
  EXPECT_EQ(count, 1);
  EXPECT_TRUE(rule.Confirm(Kf(1, 15), MapId(2), T, kAtOrigin));
}

TEST(LoopConsistencyTest, AnAcceptedLoopNamesTheAgreeingLoopsBeforeIt) {
  // A fusion ties the maps at every place its group joined (CloseEarlierLoops):
  // the rule hands over the earlier loops of the group, and only those.
  LoopCloserOptions options;
  options.loop_consistency = 3;
  LoopConsistency rule{options};
  const Pose T = Offset(0.8, 20);
  std::vector<LoopConsistency::Pair> earlier = {{Kf(9, 9), Kf(9, 9)}};
  EXPECT_FALSE(
      rule.Confirm(Kf(1, 5), MapId(2), Offset(0.5, 0), kAtOrigin, nullptr, Kf(2, 1), &earlier));
  // A disagreeing loop starts the group again: keyframe 5's loop is not in it.
  EXPECT_FALSE(rule.Confirm(Kf(1, 6), MapId(2), T, kAtOrigin, nullptr, Kf(2, 3), &earlier));
  EXPECT_FALSE(rule.Confirm(Kf(1, 7), MapId(2), T, kAtOrigin, nullptr, Kf(2, 40), &earlier));
  EXPECT_TRUE(rule.Confirm(Kf(1, 8), MapId(2), T, kAtOrigin, nullptr, Kf(2, 41), &earlier));
  const std::vector<LoopConsistency::Pair> expected = {{Kf(1, 6), Kf(2, 3)}, {Kf(1, 7), Kf(2, 40)}};
  EXPECT_EQ(earlier, expected);
  // The next group starts empty.
  EXPECT_FALSE(rule.Confirm(Kf(1, 9), MapId(2), T, kAtOrigin, nullptr, Kf(2, 42), &earlier));
  EXPECT_FALSE(rule.Confirm(Kf(1, 10), MapId(2), T, kAtOrigin, nullptr, Kf(2, 43), &earlier));
  EXPECT_TRUE(rule.Confirm(Kf(1, 11), MapId(2), T, kAtOrigin, nullptr, Kf(2, 44), &earlier));
  const std::vector<LoopConsistency::Pair> next = {{Kf(1, 9), Kf(2, 42)}, {Kf(1, 10), Kf(2, 43)}};
  EXPECT_EQ(earlier, next);
}

TEST(LoopConsistencyTest, DisagreeingGappedOrOtherMapLoopsDoNotConfirm) {
  const Pose T = Offset(0.8, 20);
  struct Case {
    const char* what;
    GlobalKeyframeId second;
    MapId map;
    Pose T_second;
  };
  const Case cases[] = {
      {"6 cm apart", Kf(1, 11), MapId(2), T * Offset(0.06, 0)},
      {"4 degrees apart", Kf(1, 11), MapId(2), T * Offset(0, 4)},
      {"4 ids later", Kf(1, 14), MapId(2), T},
      {"another candidate map", Kf(1, 11), MapId(3), T},
      {"an older keyframe (late query)", Kf(1, 9), MapId(2), T},
  };
  for (const Case& c : cases) {
    LoopConsistency rule{LoopCloserOptions()};
    int count = 0;
    EXPECT_FALSE(rule.Confirm(Kf(1, 10), MapId(2), T, kAtOrigin));
    EXPECT_FALSE(rule.Confirm(c.second, c.map, c.T_second, kAtOrigin, &count)) << c.what;
    EXPECT_EQ(count, 1) << c.what;
    // The disagreeing loop is the new reference: one that agrees with it confirms.
    EXPECT_TRUE(rule.Confirm({AgentId(1), KeyframeId(c.second.keyframe.value() + 1)}, c.map,
                             c.T_second, kAtOrigin))
        << c.what;
  }
}

TEST(LoopConsistencyTest, LoopsAreComparedWhereTheQueryIsNotAtTheMapsOrigin) {
  // An agent 6 m from where its map starts; consecutive queries a few centimetres apart.
  Pose here = Offset(6, 30), next = here * Offset(0.03, 1);
  const Pose T = Offset(0.8, 20);  // the candidate's map from the query's
  // Two matches that put the queries where one transform does, up to 2 degrees about the
  // query's camera: their transforms differ by 21 cm at the maps' origin, and they agree.
  {
    LoopConsistency rule{LoopCloserOptions()};
    EXPECT_FALSE(rule.Confirm(Kf(1, 10), MapId(2), T * here, here));
    EXPECT_TRUE(rule.Confirm(Kf(1, 11), MapId(2), T * next * Offset(0, 2), next));
  }
  // Two transforms 0.6 degrees apart about the maps' origin (the same at the origin) put the
  // query 6 cm apart: they disagree.
  {
    Pose turn = Pose::Identity();
    turn.linear() = Eigen::AngleAxisd(0.6 * kDegree, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    here = Pose::Identity();
    here.translation() = Eigen::Vector3d(6, 0, 0);
    next = here * Offset(0.03, 1);
    LoopConsistency rule{LoopCloserOptions()};
    EXPECT_FALSE(rule.Confirm(Kf(1, 10), MapId(2), T * here, here));
    EXPECT_FALSE(rule.Confirm(Kf(1, 11), MapId(2), T * turn * next, next));
  }
}

TEST(LoopConsistencyTest, AgentsAreCountedApartAndTheRequiredCountIsAnOption) {
  LoopCloserOptions options;
  options.loop_consistency = 3;
  LoopConsistency rule(options);
  const Pose T = Offset(0.5, 10);
  EXPECT_FALSE(rule.Confirm(Kf(1, 10), MapId(5), T, kAtOrigin));
  EXPECT_FALSE(rule.Confirm(Kf(2, 40), MapId(5), Offset(2, 50),
                            kAtOrigin));  // another agent: no effect on agent 1
  EXPECT_FALSE(rule.Confirm(Kf(1, 11), MapId(5), T, kAtOrigin));
  EXPECT_TRUE(rule.Confirm(Kf(1, 12), MapId(5), T, kAtOrigin));
}

TEST(LoopCooldownTest, HoldsTheAgentsNextKeyframesOnly) {
  LoopCooldown cooldown(10);
  EXPECT_FALSE(cooldown.Active(Kf(1, 5)));
  cooldown.Start(Kf(1, 20));
  EXPECT_TRUE(cooldown.Active(Kf(1, 21)));
  EXPECT_TRUE(cooldown.Active(Kf(1, 30)));
  EXPECT_FALSE(cooldown.Active(Kf(1, 31)));
  EXPECT_FALSE(cooldown.Active(Kf(2, 21)));  // other agents are free
  cooldown.Start(Kf(1, 40));
  EXPECT_TRUE(cooldown.Active(Kf(1, 50)));
}

TEST(ComparedAgentsTest, APairIsComparedOnceInEitherOrderAndOnlyItself) {
  ComparedAgents compared;
  const AgentId a(1), b(2), c(3);
  EXPECT_TRUE(compared.Compared(a, a));  // an agent's loops with itself are never held back
  EXPECT_FALSE(compared.Compared(a, b));
  compared.Add(b, a);
  EXPECT_TRUE(compared.Compared(a, b));
  EXPECT_TRUE(compared.Compared(b, a));
  // Compared with b says nothing about c, joined to a only through b.
  compared.Add(b, c);
  EXPECT_TRUE(compared.Compared(c, b));
  EXPECT_FALSE(compared.Compared(a, c));
  compared.Add(a, a);  // no effect
  EXPECT_FALSE(compared.Compared(a, c));
}

TEST(LoopAlreadyClosedTest, BothTheTranslationAndTheRotationMustBeUnderTheThresholds) {
  ServerKeyframe query;
  query.T_map_cam = Offset(1.0, 30);
  LoopMatch match;
  match.query = &query;
  const LoopCloserOptions options;  // 5 mm, 0.25 degrees
  const auto moved_by = [&](double metres, double degrees) {
    match.T_candidate_map_query = query.T_map_cam * Offset(metres, degrees);
    return LoopAlreadyClosed(match, options);
  };
  EXPECT_TRUE(moved_by(0.003, 0.1));
  EXPECT_FALSE(moved_by(0.008, 0.1));
  EXPECT_FALSE(moved_by(0.003, 0.4));
}

TEST(SelectLoopCandidatesTest, CoolingDownDropsOnlyTheQuerysOwnMap) {
  // Agents 1 and 2 share map 7 (the query's), agent 3 is in map 8, agent 4 in no map.
  const auto map_of = [](AgentId agent) -> std::optional<MapId> {
    if (agent.value() == 4) return std::nullopt;
    return MapId(agent.value() == 3 ? 8 : 7);
  };
  const std::vector<PlaceHit> hits = {{Kf(1, 3), 0.9}, {Kf(3, 8), 0.8}, {Kf(2, 1), 0.7},
                                      {Kf(4, 2), 0.6}, {Kf(3, 9), 0.5}, {Kf(3, 10), 0.4}};
  const std::vector<PlaceHit> free = SelectLoopCandidates(hits, false, MapId(7), map_of, 4);
  ASSERT_EQ(free.size(), 4u);
  EXPECT_EQ(free[0].keyframe, Kf(1, 3));
  EXPECT_EQ(free[3].keyframe, Kf(4, 2));
  const std::vector<PlaceHit> cooling = SelectLoopCandidates(hits, true, MapId(7), map_of, 2);
  ASSERT_EQ(cooling.size(), 2u);
  EXPECT_EQ(cooling[0].keyframe, Kf(3, 8));
  EXPECT_EQ(cooling[1].keyframe, Kf(3, 9));
}

// A drifting agent: keyframe i at the true pose of step i of the circle, rotated by a drift
// that grows 0.15 degrees and 4 mm per keyframe.
Pose Drifted(int i, int steps) {
  Pose drift = Pose::Identity();
  drift.linear() =
      Eigen::AngleAxisd(0.15 * kDegree * i, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  drift.translation() = Eigen::Vector3d(0.004 * i, 0.002 * i, 0);
  return drift * CirclePose(i, steps);
}

// The matches verification would find between a revisit keyframe and the candidate: every
// keypoint whose wall point the candidate also observes.
LoopMatch TrueMatch(ServerKeyframe* query, ServerKeyframe* candidate,
                    const Pose& T_candidate_query_true) {
  LoopMatch match;
  match.query = query;
  match.candidate = candidate;
  match.T_candidate_map_query = candidate->T_map_cam * T_candidate_query_true;
  std::map<std::uint32_t, ServerMapPoint*> candidate_points;
  for (ServerMapPoint* p : candidate->points)
    candidate_points[p->id.point.value() % testing::kRevisitPointIds] = p;
  for (std::size_t k = 0; k < query->points.size(); ++k) {
    const auto it =
        candidate_points.find(query->points[k]->id.point.value() % testing::kRevisitPointIds);
    if (it != candidate_points.end()) match.matches.emplace_back(static_cast<int>(k), it->second);
  }
  match.inliers = static_cast<int>(match.matches.size());
  return match;
}

// Agent 1 walks the circle in `steps` keyframes with growing drift and is back at its start:
// the last keyframe (id `steps`, returned) sees what keyframe 0 saw, as new points.
ServerKeyframe* WalkTheDriftedCircle(ServerMap* map, const GeneratedWorld& world, int steps,
                                     Rng* rng) {
  for (int i = 0; i < steps; ++i) {
    AddGeneratedKeyframe(map, world, AgentId(1), i, CirclePose(i, steps), Drifted(i, steps), rng);
  }
  return AddGeneratedKeyframe(map, world, AgentId(1), steps, CirclePose(0, steps),
                              Drifted(steps, steps), rng, /*local_window=*/steps - 5);
}

TEST(LoopCorrectionTest, ALoopInsideAMapRemovesTheDriftAndMergesTheMatches) {
  Rng rng(7);
  const GeneratedWorld world = MakeRingWorld(3000, &rng);
  constexpr int kSteps = 36;
  ServerMap map(MapId(1));
  ServerKeyframe* query = WalkTheDriftedCircle(&map, world, kSteps, &rng);
  ServerKeyframe* candidate = map.keyframe(Kf(1, 0));
  const double drift_before = TranslationDistance(query->T_map_cam, CirclePose(0, kSteps));
  ASSERT_GT(drift_before, 0.1);
  const LoopMatch match = TrueMatch(query, candidate, Pose::Identity());
  ASSERT_GT(match.inliers, 50);
  const std::size_t points_before = map.num_points();
  std::size_t own_copies = 0;  // points the query made again, to be merged into the candidate's
  for (const auto& [keypoint, point] : match.matches)
    own_copies += query->points[keypoint] != point;
  ASSERT_GT(own_copies, 50u);

  const std::vector<ServerKeyframe*> moved = CloseLoopInMap(&map, match, MapPoseGraphOptions());
  ASSERT_EQ(map.loop_edges().size(), 1u);
  EXPECT_EQ(map.loop_edges()[0].a, candidate->id);
  EXPECT_EQ(map.num_points(), points_before - own_copies);
  for (const auto& [keypoint, point] : match.matches) EXPECT_EQ(query->points[keypoint], point);
  EXPECT_EQ(query->covisibility.at(candidate->id), match.inliers);
  // The query moved most of the way back to keyframe 0 (map_optimization_test.cc: the pose
  // graph leaves part of a large correction to the global BA); the origin stays; the second
  // half moved.
  EXPECT_LT(TranslationDistance(query->T_map_cam, CirclePose(0, kSteps)), 0.6 * drift_before);
  EXPECT_EQ(std::count(moved.begin(), moved.end(), candidate), 0);
  EXPECT_EQ(std::count(moved.begin(), moved.end(), query), 1);
  EXPECT_GE(moved.size(), static_cast<std::size_t>(kSteps / 2));
  // Halfway round, the correction is about half the drift: the error is spread.
  const double halfway = TranslationDistance(map.keyframe(Kf(1, kSteps / 2))->T_map_cam,
                                             CirclePose(kSteps / 2, kSteps));
  EXPECT_LT(halfway,
            TranslationDistance(Drifted(kSteps / 2, kSteps), CirclePose(kSteps / 2, kSteps)));
}

TEST(LoopCorrectionTest, ALoopsSeamIsSearchedFromTheVerifiedPoseNotFromTheDrift) {
  // The drifted circle of the test above, back at its start 14 cm off, and the loop verified
  // 2 cm and half a degree off: from where drift left the query, the seam's points would be
  // searched 14 cm away; placed at the verified pose, the seam is found and the pose refined
  // toward the truth (the query's neighbours, searched with it, drift against each other, so
  // not all the way).
  Rng rng(7);
  const GeneratedWorld world = MakeRingWorld(3000, &rng);
  constexpr int kSteps = 36;
  ServerMap map(MapId(1));
  ServerKeyframe* query = WalkTheDriftedCircle(&map, world, kSteps, &rng);
  ASSERT_GT(TranslationDistance(query->T_map_cam, CirclePose(0, kSteps)), 0.1);
  const LoopMatch match = TrueMatch(query, map.keyframe(Kf(1, 0)), Offset(0.02, 0.5));
  const Pose before = query->T_map_cam;
  const Pose refined = RefineLoopPose(&map, match, testing::TestCamera(), LoopCloserOptions());
  const Pose& verified = match.T_candidate_map_query;
  EXPECT_LT(TranslationDistance(refined, CirclePose(0, kSteps)),
            0.5 * TranslationDistance(verified, CirclePose(0, kSteps)));
  EXPECT_LT(RotationDistance(refined, CirclePose(0, kSteps)),
            0.75 * RotationDistance(verified, CirclePose(0, kSteps)));
  EXPECT_LT(TranslationDistance(query->T_map_cam, before), 1e-12);  // the map is unchanged
}

TEST(LoopCorrectionTest, FusionBringsTheOtherMapIntoThePrimaryMapsFrame) {
  Rng rng(8);
  const GeneratedWorld world = MakeRingWorld(2000, &rng);
  constexpr int kSteps = 24;
  MapManager maps;
  {
    MapManager::Guard first = maps.CheckOutAgent(AgentId(1));  // the primary map, world frame
    for (int i = 0; i < 8; ++i)
      AddGeneratedKeyframe(first.get(), world, AgentId(1), i, CirclePose(i, kSteps),
                           CirclePose(i, kSteps), &rng);
  }
  const Pose T_map2_world = Offset(2.0, 70);  // agent 2 starts its own map elsewhere
  {
    MapManager::Guard second = maps.CheckOutAgent(AgentId(2));
    for (int i = 0; i < 5; ++i) {
      AddGeneratedKeyframe(second.get(), world, AgentId(2), i, CirclePose(4 + i, kSteps),
                           T_map2_world * CirclePose(4 + i, kSteps), &rng);
    }
  }
  auto [query_guard, candidate_guard] = maps.CheckOutPair(MapId(2), MapId(1));
  ServerKeyframe* query = query_guard->keyframe(Kf(2, 2));  // step 6
  ServerKeyframe* candidate = candidate_guard->keyframe(Kf(1, 6));
  const LoopMatch match = TrueMatch(query, candidate, Pose::Identity());
  MapFusion fusion = FuseMapsByLoop(&maps, &query_guard, &candidate_guard, match);

  ASSERT_TRUE(fusion.map);
  EXPECT_FALSE(query_guard);
  EXPECT_FALSE(candidate_guard);
  EXPECT_EQ(maps.primary(), fusion.map->id());
  EXPECT_EQ(maps.MapOfAgent(AgentId(2)), fusion.map->id());
  ASSERT_TRUE(fusion.primary_before.has_value());
  EXPECT_EQ(*fusion.primary_before, MapId(1));
  EXPECT_EQ(fusion.joined_primary.size(), 5u);
  for (ServerKeyframe* kf : fusion.joined_primary) {
    EXPECT_EQ(kf->id.agent, AgentId(2));
    EXPECT_LT(TranslationDistance(kf->T_map_cam, CirclePose(4 + kf->id.keyframe.value(), kSteps)),
              1e-6);
  }
  EXPECT_EQ(fusion.map->keyframes().size(), 13u);
  EXPECT_EQ(fusion.map->loop_edges().size(), 1u);
  EXPECT_EQ(query->points[match.matches[0].first], match.matches[0].second);
}

TEST(LoopCorrectionTest, FusingTwoMapsThatAreNotPrimaryKeepsTheCandidatesFrame) {
  Rng rng(9);
  const GeneratedWorld world = MakeRingWorld(2000, &rng);
  MapManager maps;
  maps.CheckOutAgent(AgentId(1));  // primary, empty
  const Pose T_map3 = Offset(1.0, 30), T_map2 = Offset(-1.5, -40);
  {
    MapManager::Guard a = maps.CheckOutAgent(AgentId(2));
    for (int i = 0; i < 4; ++i)
      AddGeneratedKeyframe(a.get(), world, AgentId(2), i, CirclePose(i, 24),
                           T_map2 * CirclePose(i, 24), &rng);
  }
  {
    MapManager::Guard b = maps.CheckOutAgent(AgentId(3));
    for (int i = 0; i < 4; ++i)
      AddGeneratedKeyframe(b.get(), world, AgentId(3), i, CirclePose(i, 24),
                           T_map3 * CirclePose(i, 24), &rng);
  }
  auto [query_guard, candidate_guard] = maps.CheckOutPair(MapId(3), MapId(2));
  ServerKeyframe* query = query_guard->keyframe(Kf(3, 1));
  ServerKeyframe* candidate = candidate_guard->keyframe(Kf(2, 1));
  MapFusion fusion = FuseMapsByLoop(&maps, &query_guard, &candidate_guard,
                                    TrueMatch(query, candidate, Pose::Identity()));
  EXPECT_FALSE(fusion.primary_before.has_value());
  EXPECT_TRUE(fusion.joined_primary.empty());
  EXPECT_EQ(maps.primary(), MapId(1));
  EXPECT_LT(TranslationDistance(query->T_map_cam, T_map2 * CirclePose(1, 24)),
            1e-6);  // candidate's frame
}

// Keyframes 0-7 of `agent` on steps first..first+7 of a 24-step circle, in `map` at
// T_map * true pose; 4-7 are a restarted segment that the agent's guess put `guess` further
// off, unplaced.
void AddRestartedWalk(ServerMap* map, const GeneratedWorld& world, AgentId agent, int first,
                      const Pose& T_map, const Pose& guess, Rng* rng) {
  for (int i = 0; i < 8; ++i) {
    const Pose T_true = CirclePose(first + i, 24);
    ServerKeyframe* kf = AddGeneratedKeyframe(
        map, world, agent, i, T_true, (i >= 4 ? guess : Pose::Identity()) * T_map * T_true, rng,
        i >= 4 ? std::optional<std::uint32_t>(4) : std::nullopt);
    if (i < 4) continue;
    kf->segment = KeyframeId(4);
    if (i == 4) {
      kf->restart = true;
      map->AddUnplacedSegment(kf->id);
    }
  }
}

std::set<GlobalKeyframeId> Ids(const std::vector<ServerKeyframe*>& keyframes) {
  std::set<GlobalKeyframeId> ids;
  for (const ServerKeyframe* kf : keyframes) ids.insert(kf->id);
  return ids;
}

// An agent restarted in a map of its own and its new segment sees the primary map's places:
// the fusion places that segment in the primary map's frame, and the agent's earlier
// keyframes, which only its guess relates to the segment, wait unplaced for a loop.
TEST(LoopCorrectionTest, AFusionThroughARestartedSegmentPlacesItAndUnplacesTheGuess) {
  Rng rng(12);
  const GeneratedWorld world = MakeRingWorld(2000, &rng);
  MapManager maps;
  {
    MapManager::Guard first = maps.CheckOutAgent(AgentId(1));  // the primary map, world frame
    for (int i = 0; i < 6; ++i)
      AddGeneratedKeyframe(first.get(), world, AgentId(1), i, CirclePose(10 + i, 24),
                           CirclePose(10 + i, 24), &rng);
  }
  const Pose T_map2 = Offset(1.5, 50);
  {
    MapManager::Guard second = maps.CheckOutAgent(AgentId(2));
    AddRestartedWalk(second.get(), world, AgentId(2), 8, T_map2, Offset(0.4, 20), &rng);
  }
  auto [query_guard, candidate_guard] = maps.CheckOutPair(MapId(2), MapId(1));
  ServerKeyframe* query = query_guard->keyframe(Kf(2, 5));  // step 13, unplaced
  ServerKeyframe* candidate = candidate_guard->keyframe(Kf(1, 3));
  ASSERT_FALSE(query_guard->Placed(*query));
  MapFusion fusion = FuseMapsByLoop(&maps, &query_guard, &candidate_guard,
                                    TrueMatch(query, candidate, Pose::Identity()));
  ASSERT_TRUE(fusion.map);
  EXPECT_EQ(maps.primary(), fusion.map->id());
  const std::set<GlobalKeyframeId> segment = {Kf(2, 4), Kf(2, 5), Kf(2, 6), Kf(2, 7)},
                                   before = {Kf(2, 0), Kf(2, 1), Kf(2, 2), Kf(2, 3)};
  EXPECT_EQ(Ids(fusion.placed), segment);
  EXPECT_EQ(Ids(fusion.unplaced), before);
  for (int i = 0; i < 8; ++i) {
    const ServerKeyframe* kf = fusion.map->keyframe(Kf(2, i));
    EXPECT_EQ(fusion.map->Placed(*kf), i >= 4) << i;
    if (i >= 4) {
      EXPECT_LT(TranslationDistance(kf->T_map_cam, CirclePose(8 + i, 24)), 1e-6) << i;
    }
  }
  // A later loop between the earlier keyframes and the primary map's places them too.
  const std::vector<ServerKeyframe*> placed =
      fusion.map->LinkSegments(*fusion.map->keyframe(Kf(2, 2)), *fusion.map->keyframe(Kf(1, 0)));
  EXPECT_EQ(Ids(placed), before);
}

// The other way round: the primary map's agent restarted and another agent's map sees only
// its new segment. The fusion keeps the primary map's placed part as it was; the other map
// joins the segment's group, and a loop that places either places both.
TEST(LoopCorrectionTest, AFusionWithTheKeptMapsRestartedSegmentJoinsItsGroup) {
  Rng rng(13);
  const GeneratedWorld world = MakeRingWorld(2000, &rng);
  MapManager maps;
  {
    MapManager::Guard first = maps.CheckOutAgent(AgentId(1));  // the primary map
    AddRestartedWalk(first.get(), world, AgentId(1), 0, Pose::Identity(), Offset(0.3, -15), &rng);
  }
  const Pose T_map2 = Offset(-1.0, 35);
  {
    MapManager::Guard second = maps.CheckOutAgent(AgentId(2));
    for (int i = 0; i < 5; ++i)
      AddGeneratedKeyframe(second.get(), world, AgentId(2), i, CirclePose(5 + i, 24),
                           T_map2 * CirclePose(5 + i, 24), &rng);
  }
  auto [query_guard, candidate_guard] = maps.CheckOutPair(MapId(2), MapId(1));
  ServerKeyframe* query = query_guard->keyframe(Kf(2, 1));          // step 6
  ServerKeyframe* candidate = candidate_guard->keyframe(Kf(1, 6));  // step 6, unplaced
  MapFusion fusion = FuseMapsByLoop(&maps, &query_guard, &candidate_guard,
                                    TrueMatch(query, candidate, Pose::Identity()));
  ASSERT_TRUE(fusion.map);
  ServerMap& map = *fusion.map;
  EXPECT_TRUE(fusion.placed.empty());
  EXPECT_EQ(fusion.unplaced.size(), 5u);
  for (int i = 0; i < 4; ++i) EXPECT_TRUE(map.Placed(*map.keyframe(Kf(1, i)))) << i;
  const auto group = map.UnplacedGroup(*map.keyframe(Kf(1, 4)));
  ASSERT_TRUE(group.has_value());
  for (int i = 0; i < 5; ++i) EXPECT_EQ(map.UnplacedGroup(*map.keyframe(Kf(2, i))), group) << i;
  // Agent 2's keyframes lie where the segment's guess put them, together with it.
  EXPECT_LT(
      TranslationDistance(map.keyframe(Kf(2, 1))->T_map_cam, map.keyframe(Kf(1, 6))->T_map_cam),
      1e-6);
  const std::vector<ServerKeyframe*> placed =
      map.LinkSegments(*map.keyframe(Kf(2, 4)), *map.keyframe(Kf(1, 0)));
  EXPECT_EQ(placed.size(), 9u);
  EXPECT_EQ(map.num_unplaced_segments(), 0u);
}

// Two maps of the ring seen by two agents: agent 1's (the primary map, true poses) and agent
// 2's, in a frame of its own, overlapping agent 1's last steps. The loop between agent 2's
// keyframe 2 (step 6) and agent 1's keyframe 6 is verified with `error` on the query's pose,
// as one keyframe's matches measure it; the maps are fused with the seam options or without.
// The query is agent 2's keyframe (its map moves), or with `query_in_primary` agent 1's (the
// candidate's map moves).
struct SeamCase {
  MapManager maps;
  MapFusion fusion;
  ServerKeyframe* query = nullptr;
  // The largest distance of an agent 2 keyframe from its true pose after the fusion.
  double worst_m = 0, worst_deg = 0;
};

void FuseWithError(const Pose& error, const LoopCloserOptions* options, SeamCase* c,
                   bool query_in_primary = false, const Pose& T_map1_world = Pose::Identity()) {
  Rng rng(21);
  const GeneratedWorld world = MakeRingWorld(3000, &rng);
  constexpr int kSteps = 24;
  {
    MapManager::Guard first = c->maps.CheckOutAgent(AgentId(1));
    for (int i = 0; i < 8; ++i)
      AddGeneratedKeyframe(first.get(), world, AgentId(1), i, CirclePose(i, kSteps),
                           T_map1_world * CirclePose(i, kSteps), &rng);
  }
  const Pose T_map2_world = Offset(1.5, -50);
  {
    MapManager::Guard second = c->maps.CheckOutAgent(AgentId(2));
    for (int k = 0; k < 6; ++k) {
      AddGeneratedKeyframe(second.get(), world, AgentId(2), k, CirclePose(4 + k, kSteps),
                           T_map2_world * CirclePose(4 + k, kSteps), &rng);
    }
  }
  auto [query_guard, candidate_guard] = query_in_primary ? c->maps.CheckOutPair(MapId(1), MapId(2))
                                                         : c->maps.CheckOutPair(MapId(2), MapId(1));
  c->query = query_guard->keyframe(query_in_primary ? Kf(1, 6) : Kf(2, 2));
  ServerKeyframe* candidate = candidate_guard->keyframe(query_in_primary ? Kf(2, 2) : Kf(1, 6));
  const LoopMatch match = TrueMatch(c->query, candidate, error);
  const PinholeCamera camera = testing::TestCamera();
  c->fusion = FuseMapsByLoop(&c->maps, &query_guard, &candidate_guard, match, options, &camera);
  for (int k = 0; k < 6; ++k) {
    const Pose& T = c->fusion.map->keyframe(Kf(2, k))->T_map_cam;
    const Pose T_true = T_map1_world * CirclePose(4 + k, kSteps);
    c->worst_m = std::max(c->worst_m, TranslationDistance(T, T_true));
    c->worst_deg = std::max(c->worst_deg, RotationDistance(T, T_true) / kDegree);
  }
}

TEST(SeamTest, AFusionRefinesThePoorlyVerifiedTransformOnTheSeamAndTiesBothSides) {
  const Pose error = Offset(0.02, 0.5);  // 2 cm and half a degree on the query's pose
  const LoopCloserOptions options;
  SeamCase with;
  FuseWithError(error, &options, &with);
  ASSERT_TRUE(with.fusion.map);
  const SeamJoin& seam = with.fusion.seam;
  EXPECT_TRUE(seam.corrected);
  EXPECT_GT(seam.pair_inliers, 200);
  // Pixels carry 0.3 px of noise and depths 2 mm: hundreds of pairs put agent 2's map within
  // a millimetre and a few hundredths of a degree of the truth.
  EXPECT_LT(with.worst_m, 0.001);
  EXPECT_LT(with.worst_deg, 0.03);
  // Agent 1's map (primary) did not move.
  EXPECT_LT(TranslationDistance(with.fusion.map->keyframe(Kf(1, 6))->T_map_cam, CirclePose(6, 24)),
            1e-9);
  // Agent 2's keyframes around the query, not only the query, now observe agent 1's points.
  EXPECT_GT(seam.merged, 100);
  int tied_keyframes = 0;
  for (int k = 0; k < 6; ++k) {
    const ServerKeyframe* kf = with.fusion.map->keyframe(Kf(2, k));
    const bool tied =
        std::any_of(kf->points.begin(), kf->points.end(),
                    [](const ServerMapPoint* p) { return p && p->id.agent == AgentId(1); });
    const bool covisible =
        std::any_of(kf->covisibility.begin(), kf->covisibility.end(),
                    [](const auto& link) { return link.first.agent == AgentId(1); });
    if (kf != with.query && tied && covisible) ++tied_keyframes;
  }
  EXPECT_GE(tied_keyframes, 3);

  // The same with the query in the primary map: the candidate's map moves, by the inverse.
  SeamCase reverse;
  FuseWithError(error, &options, &reverse, /*query_in_primary=*/true);
  EXPECT_TRUE(reverse.fusion.seam.corrected);
  EXPECT_LT(reverse.worst_m, 0.001);
  EXPECT_LT(reverse.worst_deg, 0.03);

  // Without the seam the verified error stays: the map is off by about the error.
  SeamCase without;
  FuseWithError(error, nullptr, &without);
  EXPECT_GT(without.worst_m, 0.015);
  EXPECT_GT(without.worst_deg, 0.4);
  EXPECT_FALSE(without.fusion.seam.corrected);
}

TEST(SeamTest, ALargerRefinementIsTakenWhenASecondSearchFromItAgrees) {
  // 6 cm off (more than SeamOptions::max_correction_m, within the search's reach):
  // the first fit is not trusted on its own; searched again from it, the seam is found where
  // the fit put it, so the map ends within a millimetre of the truth.
  LoopCloserOptions options;
  SeamCase c;
  FuseWithError(Offset(0.06, 0), &options, &c);
  EXPECT_TRUE(c.fusion.seam.corrected);
  EXPECT_TRUE(c.fusion.seam.confirmed_by_refit);
  EXPECT_LT(c.worst_m, 0.001);
  EXPECT_LT(c.worst_deg, 0.03);
  SeamCase reverse;
  FuseWithError(Offset(0.06, 0), &options, &reverse, /*query_in_primary=*/true);
  EXPECT_TRUE(reverse.fusion.seam.confirmed_by_refit);
  EXPECT_LT(reverse.worst_m, 0.001);
  EXPECT_LT(reverse.worst_deg, 0.03);
}

TEST(SeamTest, ARefinementIsSizedAtTheQueryNotAtTheMapsOrigin) {
  // The primary map's frame 8 m from the ring (a large scene, a seam far from where the first
  // agent started) and the verified pose 1 degree off: the refinement turns the query by 1
  // degree about itself, which moves the map's origin by 14 cm but the query by millimetres.
  // It is a small correction, taken at once (no second search).
  Pose far = Pose::Identity();
  far.translation() = Eigen::Vector3d(8, 0, 0);
  LoopCloserOptions options;
  for (const bool query_in_primary : {false, true}) {
    SeamCase c;
    FuseWithError(Offset(0.0, 1.0), &options, &c, query_in_primary, far);
    EXPECT_TRUE(c.fusion.seam.corrected) << query_in_primary;
    EXPECT_FALSE(c.fusion.seam.confirmed_by_refit) << query_in_primary;
    EXPECT_LT(c.worst_m, 0.001) << query_in_primary;
    EXPECT_LT(c.worst_deg, 0.03) << query_in_primary;
  }
}

TEST(SeamTest, ARefinementLargerThanTrustedKeepsTheVerifiedTransform) {
  // 10 cm off (more than SeamOptions::max_correction_m): the projected points are searched
  // too far from where they are; whatever is found is not trusted to move the map.
  LoopCloserOptions options;
  SeamCase c;
  FuseWithError(Offset(0.10, 0), &options, &c);
  EXPECT_FALSE(c.fusion.seam.corrected);
  EXPECT_GT(c.worst_m, 0.09);
}

// A fusion confirmed at two places: agent 2 walked steps 4-18 of agent 1's circle with a
// drift of its own, and its group of agreeing loops met agent 1 at step 5 (its keyframe 1)
// before the fusion's loop at step 18 (its keyframe 14). Fused at the later place (with the
// seam), its map is off at the earlier one by what it drifted in between.
constexpr int kRingSteps = 24, kWalk = 15;

struct DriftedFusion {
  MapManager maps;
  MapFusion fusion;
  const LoopCloserOptions options;
  const PinholeCamera camera = testing::TestCamera();
  // Agent 2's keyframe k from its true pose in the fused map.
  double ErrorOf(int k) const {
    return TranslationDistance(fusion.map->keyframe(Kf(2, k))->T_map_cam,
                               CirclePose(4 + k, kRingSteps));
  }
};

// Both maps, not fused yet.
void WalkTheDriftedMaps(DriftedFusion* c) {
  Rng rng(31);
  const GeneratedWorld world = MakeRingWorld(3000, &rng);
  {
    MapManager::Guard first = c->maps.CheckOutAgent(AgentId(1));
    for (int i = 0; i < kRingSteps; ++i)
      AddGeneratedKeyframe(first.get(), world, AgentId(1), i, CirclePose(i, kRingSteps),
                           CirclePose(i, kRingSteps), &rng);
  }
  // Agent 2's keyframe k at step 4 + k: its own frame, and a drift growing from its start
  // (0.2 degrees and 4 mm per keyframe, about its first pose).
  const Pose T_map2_world = Offset(1.5, -50);
  const auto estimate = [&](int k) {
    const Pose start = CirclePose(4, kRingSteps);
    Pose drift = Pose::Identity();
    drift.linear() =
        Eigen::AngleAxisd(0.2 * kDegree * k, Eigen::Vector3d::UnitY()).toRotationMatrix();
    drift.translation() = Eigen::Vector3d(0.004 * k, 0, 0.002 * k);
    return T_map2_world * start * drift * start.inverse() * CirclePose(4 + k, kRingSteps);
  };
  {
    MapManager::Guard second = c->maps.CheckOutAgent(AgentId(2));
    for (int k = 0; k < kWalk; ++k)
      AddGeneratedKeyframe(second.get(), world, AgentId(2), k, CirclePose(4 + k, kRingSteps),
                           estimate(k), &rng);
  }
}

void FuseTheDriftedWalk(DriftedFusion* c) {
  WalkTheDriftedMaps(c);
  auto [query_guard, candidate_guard] = c->maps.CheckOutPair(MapId(2), MapId(1));
  ServerKeyframe* query = query_guard->keyframe(Kf(2, kWalk - 1));
  ServerKeyframe* candidate = candidate_guard->keyframe(Kf(1, 4 + kWalk - 1));
  c->fusion =
      FuseMapsByLoop(&c->maps, &query_guard, &candidate_guard,
                     TrueMatch(query, candidate, Pose::Identity()), &c->options, &c->camera);
}

// Closing the earlier loop in the fused map bends agent 2's path back there and keeps it at
// the later place.
TEST(LoopCorrectionTest, AFusionClosesTheEarlierLoopsOfItsGroupInTheFusedMap) {
  DriftedFusion c;
  FuseTheDriftedWalk(&c);
  ServerMap* fused = c.fusion.map.get();
  ASSERT_TRUE(fused);
  const double earlier_before = c.ErrorOf(1);
  ASSERT_LT(c.ErrorOf(kWalk - 1), 0.005);
  ASSERT_GT(earlier_before, 0.04);  // the drift between the places

  const std::vector<ServerKeyframe*> moved =
      CloseEarlierLoops(fused, {{Kf(2, 1), Kf(1, 5)}}, c.camera, c.options);
  // The loop is a loop edge of its own, beside the fusion's; the pose graph moved agent 2's
  // keyframe there, which is now much nearer the truth, and the fusion's place stays joined.
  EXPECT_EQ(fused->loop_edges().size(), 2u);
  EXPECT_EQ(std::count(moved.begin(), moved.end(), fused->keyframe(Kf(2, 1))), 1);
  EXPECT_LT(c.ErrorOf(1), 0.4 * earlier_before);
  EXPECT_LT(c.ErrorOf(kWalk - 1), 0.01);

  // Where the maps already agree, a loop only ties: nothing moves and no edge is added.
  EXPECT_TRUE(
      CloseEarlierLoops(fused, {{Kf(2, kWalk - 2), Kf(1, 4 + kWalk - 2)}}, c.camera, c.options)
          .empty());
  EXPECT_EQ(fused->loop_edges().size(), 2u);
  // A pair with a keyframe the map does not hold is skipped.
  EXPECT_TRUE(CloseEarlierLoops(fused, {{Kf(2, 99), Kf(1, 5)}}, c.camera, c.options).empty());
}

// The same fusion when no loop of its group met agent 1 at the earlier place: the fusion
// itself finds where agent 2's path lies beside agent 1's without sharing its points (the
// steps before the seam it tied), pairs each such keyframe with agent 1's at the same place,
// one pair per place, and closing them removes what agent 2 drifted there.
TEST(LoopCorrectionTest, AFusionFindsTheOverlapsNoLoopComparedAndClosesThem) {
  DriftedFusion c;
  FuseTheDriftedWalk(&c);
  ServerMap* fused = c.fusion.map.get();
  ASSERT_TRUE(fused);
  LoopMatch fused_at;  // the fusion's loop
  fused_at.query = fused->keyframe(Kf(2, kWalk - 1));
  fused_at.candidate = fused->keyframe(Kf(1, 4 + kWalk - 1));
  const double earlier_before = c.ErrorOf(1);
  ASSERT_GT(earlier_before, 0.04);

  const FusionOverlapOptions& overlap = c.options.overlap;
  const std::vector<LoopConsistency::Pair> pairs =
      UncomparedOverlaps(*fused, fused_at, c.fusion.moved, overlap);
  ASSERT_EQ(static_cast<int>(pairs.size()), overlap.max_pairs);
  // The place furthest along both paths from the fusion's first: agent 2's first keyframe.
  EXPECT_EQ(pairs[0].first, Kf(2, 0));
  for (std::size_t i = 0; i < pairs.size(); ++i) {
    const auto& [q, other] = pairs[i];
    ASSERT_EQ(q.agent, AgentId(2));
    // Agent 1's keyframe at the same step of the circle, and the fusion's neighbours last.
    EXPECT_EQ(other, Kf(1, 4 + static_cast<int>(q.keyframe.value())));
    if (i > 0) {
      EXPECT_GT(q.keyframe, pairs[i - 1].first.keyframe);
    }
    for (std::size_t j = 0; j < i; ++j) {
      EXPECT_GE(
          (fused->keyframe(q)->camera_center() - fused->keyframe(pairs[j].first)->camera_center())
              .norm(),
          overlap.spacing_m);
    }
  }

  CloseEarlierLoops(fused, pairs, c.camera, c.options);
  EXPECT_LT(c.ErrorOf(1), 0.4 * earlier_before);
  EXPECT_LT(c.ErrorOf(kWalk - 1), 0.01);
  // Closed, those places share points now: asked again, none of them is paired.
  for (const auto& [q, other] : UncomparedOverlaps(*fused, fused_at, c.fusion.moved, overlap)) {
    for (const auto& closed : pairs) {
      EXPECT_NE(q, closed.first);
    }
  }

  FusionOverlapOptions none = overlap;
  none.max_pairs = 0;
  EXPECT_TRUE(UncomparedOverlaps(*fused, fused_at, c.fusion.moved, none).empty());
}

// Before fusing, the places where agent 2's keyframes overlap agent 1's map by the
// confirming loop's transform are verified: when one holds more inliers than that loop (here
// cut to 30 matches), the maps are fused there, the start of agent 2's walk, and so agree
// there however far agent 2 drifted before the confirming loop's place.
TEST(LoopCorrectionTest, AFusionIsMadeWhereTheMapsOverlapWithTheMostInliers) {
  DriftedFusion c;
  WalkTheDriftedMaps(&c);
  auto [query_guard, candidate_guard] = c.maps.CheckOutPair(MapId(2), MapId(1));
  LoopMatch weak = TrueMatch(query_guard->keyframe(Kf(2, kWalk - 1)),
                             candidate_guard->keyframe(Kf(1, 4 + kWalk - 1)), Pose::Identity());
  ASSERT_GT(weak.matches.size(), 30u);
  weak.matches.resize(30);
  weak.inliers = 30;
  const std::optional<LoopMatch> stronger =
      StrongerFusionLoop(*query_guard, *candidate_guard, weak, c.camera, c.options);
  ASSERT_TRUE(stronger.has_value());
  EXPECT_GT(stronger->inliers, weak.inliers);
  ASSERT_EQ(stronger->query->id.agent, AgentId(2));
  const int k = static_cast<int>(stronger->query->id.keyframe.value());
  EXPECT_EQ(stronger->candidate->id, Kf(1, 4 + k));  // the same step of the circle
  EXPECT_LT(k, kWalk / 2);                           // far along the walk from the loop

  // A confirming loop with more inliers than any overlap keeps its place.
  LoopMatch strong = weak;
  strong.inliers = 100000;
  EXPECT_FALSE(StrongerFusionLoop(*query_guard, *candidate_guard, strong, c.camera, c.options));

  // Fused there, agent 2's keyframe at that place is where agent 1's map has it.
  c.fusion =
      FuseMapsByLoop(&c.maps, &query_guard, &candidate_guard, *stronger, &c.options, &c.camera);
  ASSERT_TRUE(c.fusion.map);
  EXPECT_LT(c.ErrorOf(k), 0.01);
}

// A keyframe an agent makes while it cools down after a fusion is checked against the other
// agents' nearest keyframes: agent 2's keyframe 1 finds agent 1's at the same step (nothing
// tied them), closing it there removes agent 2's drift; where no other agent has been, or
// where the seam tied the two, nothing is proposed.
TEST(LoopCorrectionTest, AKeyframeCoolingDownAfterAFusionMeetsTheOtherAgentsNearestKeyframe) {
  DriftedFusion c;
  FuseTheDriftedWalk(&c);
  ServerMap* fused = c.fusion.map.get();
  ASSERT_TRUE(fused);
  const double before = c.ErrorOf(1);
  ASSERT_GT(before, 0.04);
  const FusionOverlapOptions& overlap = c.options.overlap;

  const std::optional<LoopConsistency::Pair> pair =
      UncomparedNeighbour(*fused, *fused->keyframe(Kf(2, 1)), overlap);
  ASSERT_TRUE(pair.has_value());
  EXPECT_EQ(pair->first, Kf(2, 1));
  EXPECT_EQ(pair->second, Kf(1, 5));
  EXPECT_FALSE(UncomparedNeighbour(*fused, *fused->keyframe(Kf(1, 0)), overlap));  // step 0
  const std::optional<LoopConsistency::Pair> at_seam =
      UncomparedNeighbour(*fused, *fused->keyframe(Kf(2, kWalk - 2)), overlap);
  if (at_seam) {
    EXPECT_NE(at_seam->second, Kf(1, 4 + kWalk - 2));  // tied by the seam
  }

  const PairClosure closed = CloseLoopAt(fused, *pair, c.camera, c.options);
  EXPECT_GT(closed.inliers, 0);
  EXPECT_FALSE(closed.tied_only);
  EXPECT_FALSE(closed.moved.empty());
  EXPECT_LT(c.ErrorOf(1), 0.4 * before);
  // Closed, the two share points: the place is not proposed again.
  const std::optional<LoopConsistency::Pair> again =
      UncomparedNeighbour(*fused, *fused->keyframe(Kf(2, 1)), overlap);
  if (again) {
    EXPECT_NE(again->second, Kf(1, 5));
  }

  FusionOverlapOptions none = overlap;
  none.max_pairs = 0;
  EXPECT_FALSE(UncomparedNeighbour(*fused, *fused->keyframe(Kf(2, 1)), none));
}

// An earlier loop next to the fusion's own place, whose verification puts the query where
// the fused map has it (within LoopAlreadyClosed's 5 mm and 0.25 degrees): the two agree, so
// the loop is closed and only ties its matches. Refined on a seam first, it would be judged on
// what a search next to a freshly tied place finds (here 133 pairs at the edge of the
// candidate's window, which moved the verified pose by 10 mm and bent 38 keyframes).
TEST(LoopCorrectionTest, AnEarlierLoopThatAgreesWithTheFusedMapOnlyTies) {
  DriftedFusion c;
  FuseTheDriftedWalk(&c);
  ServerMap* fused = c.fusion.map.get();
  ASSERT_TRUE(fused);
  ServerKeyframe* query = fused->keyframe(Kf(2, kWalk - 2));
  ServerKeyframe* candidate = fused->keyframe(Kf(1, 4 + kWalk - 3));
  const std::optional<LoopMatch> verified =
      VerifyLoop(query, c.camera, candidate, *fused, c.options.verification);
  ASSERT_TRUE(verified.has_value());
  ASSERT_TRUE(LoopAlreadyClosed(*verified, c.options));
  const Pose before = query->T_map_cam;
  const std::size_t edges = fused->loop_edges().size();
  EXPECT_TRUE(CloseEarlierLoops(fused, {{query->id, candidate->id}}, c.camera, c.options).empty());
  EXPECT_EQ(fused->loop_edges().size(), edges);
  EXPECT_LT(TranslationDistance(query->T_map_cam, before), 1e-12);
  // Its matches merged: the query observes the candidate's points it matched.
  std::size_t shared = 0;
  for (const auto& [keypoint, point] : verified->matches)
    shared += query->points[keypoint] == point;
  EXPECT_EQ(shared, verified->matches.size());
}

// What LoopCloser::Process closed for one keyframe (the closure's map guard released at once).
struct ProcessResult {
  bool closed = false;
  LoopEvent event;
  std::size_t moved = 0;
  std::size_t joined = 0;    // keyframes the loop brought into the primary map's outputs
  std::size_t unplaced = 0;  // the map's keyframes not placed after the keyframe
};

// The whole loop stage on generated data: a vocabulary trained on the wall's descriptors, an
// agent walking the circle and on past its start (new map points: it does not know it has
// been there). With `restart_at`, the agent lost tracking there and restarted (new points, a
// segment 20 cm off). Returns what each keyframe closed.
// A place index whose vocabulary is trained on the wall's descriptors.
PlaceIndexOptions WallPlaceIndex(const GeneratedWorld& world) {
  // Training images: the wall in 40 parts (one image would give every word a zero weight).
  std::vector<cv::Mat> images(40, cv::Mat(0, 32, CV_8U));
  for (std::size_t j = 0; j < world.descriptors.size(); ++j) {
    images[j % 40].push_back(
        cv::Mat(1, 32, CV_8U, const_cast<std::uint8_t*>(world.descriptors[j].data())));
  }
  VocabularyOptions vocabulary_options;
  vocabulary_options.depth = 3;
  auto vocabulary = Vocabulary::Train(images, vocabulary_options);
  EXPECT_TRUE(vocabulary.ok());
  PlaceIndexOptions place;
  place.vocabulary = std::make_shared<const Vocabulary>(std::move(vocabulary).value());
  place.online_training = false;
  return place;
}

std::vector<ProcessResult> WalkPastTheStart(int cooldown_keyframes, int restart_at = -1) {
  Rng rng(11);
  const GeneratedWorld world = MakeRingWorld(4000, &rng);
  const PlaceIndexOptions place = WallPlaceIndex(world);
  LoopCloserOptions options;
  options.loop_cooldown_keyframes = cooldown_keyframes;

  MapManager maps;
  LoopCloser closer(options, place, &maps, 0.0);
  constexpr int kSteps = 36;
  std::vector<ProcessResult> results;
  Pose off = Pose::Identity();
  off.translation() = Eigen::Vector3d(0.2, -0.1, 0);
  for (int id = 0; id < kSteps + 8; ++id) {
    const bool restarted = restart_at >= 0 && id >= restart_at;
    std::optional<std::uint32_t> window;
    if (id >= kSteps) window = id - 5;
    if (restarted) window = std::max<std::uint32_t>(window.value_or(0), restart_at);
    {
      MapManager::Guard guard = maps.CheckOutAgent(AgentId(1));
      ServerKeyframe* kf = AddGeneratedKeyframe(
          guard.get(), world, AgentId(1), id, CirclePose(id % kSteps, kSteps),
          (restarted ? off : Pose::Identity()) * Drifted(id, kSteps), &rng, window);
      if (restarted) kf->segment = KeyframeId(restart_at);
      if (id == restart_at) {
        kf->restart = true;
        kf->parent.reset();
        guard->AddUnplacedSegment(kf->id);
      }
    }
    std::optional<LoopClosure> closure =
        closer.Process(Kf(1, id), testing::TestCamera(), DepthNoise(), /*stored=*/false);
    ProcessResult r;
    if (closure) r = {true, closure->event, closure->moved.size(), closure->joined_primary.size()};
    closure.reset();  // gives the map back
    MapManager::Guard guard = maps.CheckOutAgent(AgentId(1));
    for (const auto& [kid, kf] : guard->keyframes()) r.unplaced += !guard->Placed(*kf);
    results.push_back(r);
  }
  return results;
}

TEST(LoopCloserTest, ARevisitIsConfirmedAndClosedThenTheAgentCoolsDown) {
  const std::vector<ProcessResult> results = WalkPastTheStart(10);
  std::vector<int> closed;
  for (std::size_t id = 0; id < results.size(); ++id) {
    if (results[id].closed) closed.push_back(static_cast<int>(id));
  }
  // One loop, towards the end of the circle, with a keyframe of its start; then the next ten
  // keyframes seek no loop in their map.
  ASSERT_EQ(closed.size(), 1u);
  const ProcessResult& loop = results[closed[0]];
  EXPECT_GT(closed[0], 25);
  EXPECT_EQ(loop.event.query, Kf(1, closed[0]));
  EXPECT_GT(loop.event.query.keyframe.value() - loop.event.candidate.keyframe.value(), 25u);
  EXPECT_FALSE(loop.event.fusion);
  EXPECT_EQ(loop.event.map, MapId(1));
  EXPECT_GT(loop.moved, 0u);
  EXPECT_GE(static_cast<int>(results.size()), closed[0] + 11);

  // Without the cool-down the same keyframes close loops again: the rule is what held them.
  const std::vector<ProcessResult> eager = WalkPastTheStart(0);
  int eager_loops = 0;
  for (const ProcessResult& r : eager) eager_loops += r.closed;
  EXPECT_TRUE(eager[closed[0]].closed);
  EXPECT_GE(eager_loops, 2);
}

// An agent restarted at keyframe 20 (new points, 20 cm off) where it had just been: its new
// segment stays out of the outputs (unplaced) until a loop with the placed part, which its
// first keyframes may close with the keyframes just before the restart however recent. The
// second keyframe confirms the loop, which places the segment and hands it over.
TEST(LoopCloserTest, ALoopWithTheKeyframesBeforeARestartPlacesTheNewSegment) {
  const std::vector<ProcessResult> results = WalkPastTheStart(10, 20);
  int closed = -1;
  for (std::size_t id = 0; id < results.size(); ++id) {
    if (results[id].closed && closed < 0) closed = static_cast<int>(id);
  }
  ASSERT_EQ(closed, 21);
  const ProcessResult& loop = results[closed];
  EXPECT_LT(loop.event.candidate.keyframe.value(), 20u);
  EXPECT_FALSE(loop.event.fusion);
  EXPECT_TRUE(loop.event.placed_segment);
  EXPECT_EQ(loop.joined, 2u);
  EXPECT_EQ(results[19].unplaced, 0u);
  EXPECT_EQ(results[20].unplaced, 1u);
  for (std::size_t id = closed; id < results.size(); ++id) EXPECT_EQ(results[id].unplaced, 0u);
}

// Agent 1 has mapped the ring; agent 2 starts at step 4 in a map of its own, and its map is
// fused with agent 1's a keyframe or two later. It then cools down, and its next keyframe, at
// step 9 with points it never tracked before, queries no loop in what is now its own map:
// it is checked against agent 1's nearest keyframe instead, and the two tied. With no
// overlap pairs allowed, nothing is checked there.
std::vector<ProcessResult> FuseThenStepAside(int overlap_pairs) {
  Rng rng(17);
  const GeneratedWorld world = MakeRingWorld(4000, &rng);
  LoopCloserOptions options;
  options.overlap.max_pairs = overlap_pairs;
  MapManager maps;
  LoopCloser closer(options, WallPlaceIndex(world), &maps, 0.0);
  constexpr int kSteps = 24;
  const auto process = [&](AgentId agent, int id) {
    std::optional<LoopClosure> closure =
        closer.Process({agent, KeyframeId(id)}, testing::TestCamera(), DepthNoise(), false);
    ProcessResult r;
    if (closure) r = {true, closure->event, closure->moved.size(), closure->joined_primary.size()};
    return r;
  };
  for (int i = 0; i < kSteps; ++i) {
    {
      MapManager::Guard guard = maps.CheckOutAgent(AgentId(1));
      AddGeneratedKeyframe(guard.get(), world, AgentId(1), i, CirclePose(i, kSteps),
                           CirclePose(i, kSteps), &rng);
    }
    process(AgentId(1), i);
  }
  const Pose T_map2_world = Offset(1.0, 40);
  std::vector<ProcessResult> results;
  for (int k = 0; k < 4; ++k) {
    const int step = k < 3 ? 4 + k : 9;
    {
      MapManager::Guard guard = maps.CheckOutAgent(AgentId(2));
      // The last one, after the fusion, is in agent 1's frame (as ingest puts it) and sees
      // only points it has not tracked: a window starting at itself.
      const bool aside = k == 3;
      AddGeneratedKeyframe(guard.get(), world, AgentId(2), k, CirclePose(step, kSteps),
                           (aside ? Pose::Identity() : T_map2_world) * CirclePose(step, kSteps),
                           &rng, aside ? std::optional<std::uint32_t>(3) : std::nullopt);
    }
    results.push_back(process(AgentId(2), k));
  }
  return results;
}

TEST(LoopCloserTest, AKeyframeCoolingDownAfterAFusionIsCheckedAgainstTheOtherAgent) {
  const std::vector<ProcessResult> results = FuseThenStepAside(4);
  ASSERT_EQ(results.size(), 4u);
  int fused_at = -1;
  for (int k = 0; k < 3; ++k) {
    if (results[k].closed && results[k].event.fusion) fused_at = k;
  }
  ASSERT_GE(fused_at, 1);  // confirmed by a second keyframe
  const ProcessResult& aside = results[3];
  ASSERT_TRUE(aside.closed);
  EXPECT_FALSE(aside.event.fusion);
  EXPECT_EQ(aside.event.query, Kf(2, 3));
  EXPECT_EQ(aside.event.candidate, Kf(1, 9));  // agent 1's keyframe at the same step
  EXPECT_GT(aside.event.inliers, 0);

  const std::vector<ProcessResult> unchecked = FuseThenStepAside(0);
  ASSERT_TRUE(unchecked[fused_at].closed && unchecked[fused_at].event.fusion);
  EXPECT_FALSE(unchecked[3].closed);
}

// Agent 1 has mapped the ring; agent 2 made one keyframe, at step 4, in a map of its own, and
// its session ends there: a segment that only overlaps the other's end. Its loop with agent 1
// is verified but no next keyframe can agree with it. At the session's end agent 1's
// neighbours of the candidate are verified against it instead. `displace_neighbours` moves
// those neighbours 10 cm in agent 1's map (where the images put them stays the same): the
// transform then puts them elsewhere than they see themselves, and nothing is fused.
struct EndedSession {
  ProcessResult queried, ended;
  std::size_t maps_after = 0;
};
EndedSession EndTheSessionWithALoopWaiting(int neighbour_checks, bool displace_neighbours) {
  Rng rng(23);
  const GeneratedWorld world = MakeRingWorld(4000, &rng);
  LoopCloserOptions options;
  options.neighbour_checks = neighbour_checks;
  MapManager maps;
  LoopCloser closer(options, WallPlaceIndex(world), &maps, 0.0);
  constexpr int kSteps = 24;
  for (int i = 0; i < kSteps; ++i) {
    {
      MapManager::Guard guard = maps.CheckOutAgent(AgentId(1));
      AddGeneratedKeyframe(guard.get(), world, AgentId(1), i, CirclePose(i, kSteps),
                           CirclePose(i, kSteps), &rng);
    }
    EXPECT_FALSE(closer.Process(Kf(1, i), testing::TestCamera(), DepthNoise(), false));
  }
  {
    MapManager::Guard guard = maps.CheckOutAgent(AgentId(2));
    AddGeneratedKeyframe(guard.get(), world, AgentId(2), 0, CirclePose(4, kSteps),
                         Offset(1.0, 40) * CirclePose(4, kSteps), &rng);
  }
  const auto summary = [](std::optional<LoopClosure> closure) {
    ProcessResult r;
    if (closure) r = {true, closure->event, closure->moved.size(), closure->joined_primary.size()};
    return r;
  };
  EndedSession result;
  result.queried =
      summary(closer.Process(Kf(2, 0), testing::TestCamera(), DepthNoise(), /*stored=*/false));
  if (displace_neighbours) {
    MapManager::Guard guard = maps.CheckOutAgent(AgentId(1));
    for (const auto& [id, kf] : guard->keyframes()) {
      if (id.keyframe.value() != 4) kf->T_map_cam.translation() += Eigen::Vector3d(0.1, 0, 0);
    }
  }
  result.ended = summary(closer.AgentStopped(
      AgentId(2), [](AgentId) { return testing::TestCamera(); },
      [](AgentId) { return DepthNoise(); }));
  result.maps_after = maps.Maps().size();
  return result;
}

TEST(LoopCloserTest, ALoopWaitingWhenItsSessionEndsIsConfirmedFromTheOtherMap) {
  const EndedSession ended = EndTheSessionWithALoopWaiting(3, false);
  EXPECT_FALSE(ended.queried.closed);  // one keyframe is not enough on its own
  ASSERT_TRUE(ended.ended.closed);
  EXPECT_TRUE(ended.ended.event.fusion);
  EXPECT_EQ(ended.ended.event.query, Kf(2, 0));
  EXPECT_EQ(ended.ended.event.candidate.agent, AgentId(1));
  EXPECT_EQ(ended.maps_after, 1u);

  // Without the checks from the other side the loop stays waiting, and the maps apart.
  const EndedSession unchecked = EndTheSessionWithALoopWaiting(0, false);
  EXPECT_FALSE(unchecked.ended.closed);
  EXPECT_EQ(unchecked.maps_after, 2u);
}

TEST(LoopCloserTest, NeighboursThatDisagreeWithTheWaitingLoopDoNotConfirmIt) {
  const EndedSession ended = EndTheSessionWithALoopWaiting(3, true);
  EXPECT_FALSE(ended.queried.closed);
  EXPECT_FALSE(ended.ended.closed);
  EXPECT_EQ(ended.maps_after, 2u);
}

// The query's side: agent 1 has one keyframe (step 4), so the candidate has no neighbours.
// Agent 2's first keyframe (step 3) came before it and found nothing; its second (step 4)
// verifies a loop with it that no next keyframe confirms. When agent 2 stops, its first
// keyframe, verified against agent 1's, confirms the loop (with `neighbour_checks` 0 nothing
// does).
bool AQuerysNeighbourConfirms(int neighbour_checks) {
  Rng rng(29);
  const GeneratedWorld world = MakeRingWorld(4000, &rng);
  LoopCloserOptions options;
  options.neighbour_checks = neighbour_checks;
  MapManager maps;
  LoopCloser closer(options, WallPlaceIndex(world), &maps, 0.0);
  constexpr int kSteps = 24;
  const Pose T_map2_world = Offset(1.0, 40);
  const auto add = [&](int agent, int id, int step, const Pose& T_map_world) {
    MapManager::Guard guard = maps.CheckOutAgent(AgentId(static_cast<std::uint16_t>(agent)));
    AddGeneratedKeyframe(guard.get(), world, AgentId(static_cast<std::uint16_t>(agent)), id,
                         CirclePose(step, kSteps), T_map_world * CirclePose(step, kSteps), &rng);
  };
  add(2, 0, 3, T_map2_world);
  EXPECT_FALSE(closer.Process(Kf(2, 0), testing::TestCamera(), DepthNoise(), false));
  add(1, 0, 4, Pose::Identity());
  EXPECT_FALSE(closer.Process(Kf(1, 0), testing::TestCamera(), DepthNoise(), false));
  add(2, 1, 4, T_map2_world);
  EXPECT_FALSE(closer.Process(Kf(2, 1), testing::TestCamera(), DepthNoise(), false));
  std::optional<LoopClosure> closure = closer.AgentStopped(
      AgentId(2), [](AgentId) { return testing::TestCamera(); },
      [](AgentId) { return DepthNoise(); });
  const bool fused = closure && closure->event.fusion && closure->event.query == Kf(2, 1);
  closure.reset();
  EXPECT_EQ(maps.Maps().size(), fused ? 1u : 2u);
  return fused;
}

TEST(LoopCloserTest, AQuerysNeighbourConfirmsWhenTheCandidateHasNone) {
  EXPECT_TRUE(AQuerysNeighbourConfirms(3));
  EXPECT_FALSE(AQuerysNeighbourConfirms(0));
}

}  // namespace
}  // namespace ccmd
