#include "libccmd/backend/keyframe_culling.h"

#include <gtest/gtest.h>

#include "libccmd/backend/map_optimization.h"
#include "libccmd/tracking/options.h"
#include "tests/backend/generated_map.h"

namespace ccmd {
namespace {

using testing::AddGeneratedKeyframe;
using testing::CirclePose;
using testing::MakeRingWorld;
using testing::TestCamera;

const AgentId kAgent(1);

const PinholeCamera* CameraOf(AgentId) {
  static const PinholeCamera camera = TestCamera();
  return &camera;
}

// A keyframe of kAgent with nothing but its id (keypoints are appended by the test).
ServerKeyframe* AddBareKeyframe(ServerMap* map, std::uint32_t id) {
  auto kf = std::make_unique<ServerKeyframe>();
  kf->id = {kAgent, KeyframeId(id)};
  return map->AddKeyframe(std::move(kf));
}

// Runs the culler over the keyframes of `map` in id order, as the back-end does on arrival.
CullingStats CullInOrder(ServerMap* map, const KeyframeCullingOptions& options) {
  KeyframeCuller culler(options);
  std::vector<GlobalKeyframeId> ids;
  for (const auto& [id, kf] : map->keyframes()) ids.push_back(id);
  for (const GlobalKeyframeId& id : ids) {
    if (const auto old = culler.Arrived(id)) {
      culler.Check(map, *old, CameraOf, [](const GlobalKeyframeId&) { return true; });
    }
  }
  return culler.stats();
}

// Two laps of the circle, `steps` keyframes each; the second lap makes its points again (an
// agent's front-end does not remember the first lap).
ServerMap TwoLaps(int steps, std::uint64_t seed) {
  Rng rng(seed);
  const auto world = MakeRingWorld(3000, &rng);
  ServerMap map(MapId(1));
  for (int i = 0; i < 2 * steps; ++i) {
    const Pose T = CirclePose(i, steps);
    std::optional<std::uint32_t> window;
    if (i >= steps) window = static_cast<std::uint32_t>(std::max(0, i - 5));
    AddGeneratedKeyframe(&map, world, kAgent, static_cast<std::uint32_t>(i), T, T, &rng, window);
  }
  return map;
}

// Four keyframes 3 degrees apart on the circle, each seeing most of what the next sees.
std::vector<ServerKeyframe*> FourNeighbours(ServerMap* map) {
  Rng rng(5);
  const auto world = MakeRingWorld(2000, &rng);
  std::vector<ServerKeyframe*> kfs;
  for (int i = 0; i < 4; ++i) {
    const Pose T = CirclePose(i, 120);
    kfs.push_back(
        AddGeneratedKeyframe(map, world, kAgent, static_cast<std::uint32_t>(i), T, T, &rng));
  }
  return kfs;
}

// An agent links points of every keyframe its local map still holds: the server must not
// cull (and drop the points of) a keyframe that recent. With a window shorter than the
// agent's map, 7-Scenes replays lost the agents' later links to culled keyframes' points.
TEST(KeyframeCullingTest, TheRecentWindowCoversTheAgentsLocalMap) {
  EXPECT_GE(KeyframeCullingOptions().keep_recent, TrackingOptions().max_keyframes);
}

TEST(KeyframeCullingTest, SecondPassOverAPlaceIsCulledFirstPassKept) {
  const int steps = 24;  // 15 degrees apart: neighbours overlap, but not by 90 %
  ServerMap map = TwoLaps(steps, 7);
  const std::size_t points_before = map.num_points();
  KeyframeCullingOptions options;
  options.keep_recent = 5;
  const CullingStats stats = CullInOrder(&map, options);
  // A culled keyframe leaves the map's keyframes; its leader holds what remains of it.
  const auto culled = [&](int i) {
    return map.keyframe({kAgent, KeyframeId(static_cast<std::uint32_t>(i))}) == nullptr;
  };
  int first_culled = 0, second_culled = 0, second_checked = 0;
  for (int i = 0; i < 2 * steps; ++i) {
    if (i < steps) {
      if (i < steps - 1) first_culled += culled(i);
    } else if (culled(i) || map.keyframe({kAgent, KeyframeId(i)})->cull_checked) {
      ++second_checked;
      second_culled += culled(i);
    }
  }
  EXPECT_EQ(first_culled, 0);
  // The first lap's last keyframe lies between its predecessor and the first keyframe, which
  // see all of it together: the lap has closed.
  EXPECT_TRUE(culled(steps - 1));
  ASSERT_EQ(second_checked, steps - options.keep_recent);
  // The second lap sees exactly what the first saw, from the same places.
  EXPECT_EQ(second_culled, second_checked);
  EXPECT_EQ(stats.culled, static_cast<std::size_t>(second_culled) + 1);
  // The second lap's own points go with its keyframes (those the recent keyframes still see
  // stay).
  EXPECT_GT(stats.points_removed, 0u);
  EXPECT_EQ(map.num_points(), points_before - stats.points_removed);
  EXPECT_EQ(map.num_culled(), stats.culled);
  EXPECT_EQ(map.keyframes().size() + map.num_culled(), static_cast<std::size_t>(2 * steps));
  for (int i = 0; i < 2 * steps; ++i) {
    if (!culled(i)) continue;
    const ServerKeyframe* leader = map.LeaderOf({kAgent, KeyframeId(i)});
    ASSERT_NE(leader, nullptr);
    EXPECT_LT(leader->id.keyframe.value(), static_cast<std::uint32_t>(steps));
  }
  // Every remaining point is observed, by kept keyframes only.
  for (const auto& [id, kf] : map.keyframes()) {
    for (const ServerMapPoint* p : kf->points) {
      if (!p) continue;
      ASSERT_FALSE(p->observations.empty());
      EXPECT_EQ(map.keyframe(p->anchor->id), p->anchor);
      for (const auto& o : p->observations) EXPECT_EQ(map.keyframe(o.keyframe->id), o.keyframe);
    }
  }
}

// The trajectories are written from every keyframe, culled ones through their leaders: the
// culling must not move or lose any.
TEST(KeyframeCullingTest, EveryKeyframeKeepsItsPoseAndTime) {
  const int steps = 24;
  ServerMap map = TwoLaps(steps, 7);
  std::map<GlobalKeyframeId, std::pair<double, Pose>> before;
  for (auto& [id, kf] : map.keyframes()) {
    kf->timestamp = 1.0 + 0.1 * id.keyframe.value();
    before[id] = {kf->timestamp, kf->T_map_cam};
  }
  KeyframeCullingOptions options;
  options.keep_recent = 5;
  ASSERT_GT(CullInOrder(&map, options).culled, 10u);
  const std::vector<ServerMap::KeyframeSample> all = map.AllKeyframes();
  ASSERT_EQ(all.size(), before.size());
  for (std::size_t i = 0; i < all.size(); ++i) {
    const auto& [timestamp, T] = before.at(all[i].id);
    EXPECT_EQ(all[i].id.keyframe.value(), i);  // in id order
    EXPECT_EQ(all[i].timestamp, timestamp);
    EXPECT_TRUE(all[i].placed);
    // A culled one's pose is its leader's times a single-precision relative pose.
    EXPECT_LT(TranslationDistance(all[i].T_map_cam, T), 1e-6);
    EXPECT_LT(RotationDistance(all[i].T_map_cam, T), 1e-6);
  }
  EXPECT_EQ(map.AllKeyframes(AgentId(2)).size(), 0u);
  EXPECT_EQ(map.CountPlacedKeyframes(kAgent), all.size());
  EXPECT_EQ(map.CountPlacedKeyframes(AgentId(2)), 0u);
}

// A restarted segment's first keyframe carries the loose tie to the segment before it: the
// culling keeps it even where the rest of its pass goes.
TEST(KeyframeCullingTest, ARestartedSegmentsFirstKeyframeIsKept) {
  const int steps = 24;
  ServerMap map = TwoLaps(steps, 7);
  map.keyframe({kAgent, KeyframeId(steps + 3)})->restart = true;
  KeyframeCullingOptions options;
  options.keep_recent = 5;
  CullInOrder(&map, options);
  EXPECT_NE(map.keyframe({kAgent, KeyframeId(steps + 3)}), nullptr);
  EXPECT_EQ(map.keyframe({kAgent, KeyframeId(steps + 2)}), nullptr);
  EXPECT_EQ(map.keyframe({kAgent, KeyframeId(steps + 4)}), nullptr);
}

TEST(KeyframeCullingTest, DenseKeyframesOfOnePassAreThinnedSparseOnesKept) {
  // 120 keyframes per lap (3 degrees apart): the previous keyframe sees over 90 % of each.
  Rng rng(3);
  const auto world = MakeRingWorld(3000, &rng);
  ServerMap dense(MapId(1)), sparse(MapId(2));
  for (int i = 0; i < 60; ++i) {
    const Pose T = CirclePose(i, 120);
    AddGeneratedKeyframe(&dense, world, kAgent, static_cast<std::uint32_t>(i), T, T, &rng);
  }
  for (int i = 0; i < 12; ++i) {
    const Pose T = CirclePose(i, 12);  // 30 degrees apart: about half of each view is new
    AddGeneratedKeyframe(&sparse, world, kAgent, static_cast<std::uint32_t>(i), T, T, &rng);
  }
  KeyframeCullingOptions options;
  options.keep_recent = 3;
  const CullingStats dense_stats = CullInOrder(&dense, options);
  const CullingStats sparse_stats = CullInOrder(&sparse, options);
  EXPECT_GT(dense_stats.culled, dense_stats.checked / 3);
  EXPECT_LT(dense_stats.culled, dense_stats.checked);  // the kept ones cover the others
  EXPECT_EQ(sparse_stats.culled, 0u);
  EXPECT_EQ(sparse_stats.checked, 9u);
}

TEST(KeyframeCullingTest, CoverageNeedsTheSameViewAtAboutTheSameDistance) {
  Rng rng(11);
  const auto world = MakeRingWorld(3000, &rng);
  ServerMap map(MapId(1));
  const Pose T = CirclePose(0, 24);
  ServerKeyframe* kept = AddGeneratedKeyframe(&map, world, kAgent, 0, T, T, &rng);
  kept->cull_checked = true;
  KeyframeCullingOptions options;
  const auto coverage_of = [&](const Pose& pose, std::uint32_t id) {
    ServerKeyframe* kf = AddGeneratedKeyframe(&map, world, kAgent, id, pose, pose, &rng);
    return MeasureCoverage(*kf, CoveringCandidates(map, *kf, options), CameraOf, options);
  };
  // 2 cm to the side: the same view.
  Pose beside = T;
  beside.translation() += 0.02 * T.linear().col(0);
  const Coverage same = coverage_of(beside, 1);
  EXPECT_GT(same.fraction, 0.95);
  EXPECT_EQ(same.best, kept);
  // Turned by 40 degrees: not a candidate (viewing direction), nothing covered.
  Pose turned = T;
  turned.linear() = T.linear() * Eigen::AngleAxisd(40 * M_PI / 180, Eigen::Vector3d::UnitY());
  EXPECT_EQ(coverage_of(turned, 2).fraction, 0.0);
  // 0.8 m closer to the wall (2.5 m away at the centre): the kept keyframe sees the same
  // surface from 1.5x as far, too coarse to stand for this view, though it lies in its image.
  Pose closer = T;
  closer.translation() += 0.8 * T.linear().col(2);
  std::vector<ServerKeyframe*> only_kept = {kept};
  ServerKeyframe* near = AddGeneratedKeyframe(&map, world, kAgent, 3, closer, closer, &rng);
  EXPECT_LT(MeasureCoverage(*near, only_kept, CameraOf, options).fraction, 0.2);
  // ... and it is too far from it to be a candidate at all.
  EXPECT_TRUE(CoveringCandidates(map, *near, options).empty());
}

// The culler's list of kept keyframes gives the candidates a scan of the whole map gives,
// without walking the culled ones; ids in the list that are not in this map are skipped.
TEST(KeyframeCullingTest, TheKeptListGivesTheCandidatesTheWholeMapGives) {
  Rng rng(12);
  const auto world = MakeRingWorld(3000, &rng);
  ServerMap map(MapId(1));
  std::vector<GlobalKeyframeId> kept;
  for (std::uint32_t i = 0; i < 6; ++i) {
    Pose T = CirclePose(0, 24);
    T.translation() += 0.01 * i * T.linear().col(0);
    ServerKeyframe* kf = AddGeneratedKeyframe(&map, world, kAgent, i, T, T, &rng);
    kf->cull_checked = true;
    if (i % 2 == 0) kept.push_back(kf->id);  // the odd ones: looked at, then culled
  }
  for (std::uint32_t i = 1; i < 6; i += 2) {
    ServerKeyframe* kf = map.keyframe({kAgent, KeyframeId(i)});
    map.Cull(kf, map.keyframe({kAgent, KeyframeId(i - 1)}));
  }
  kept.push_back({AgentId(9), KeyframeId(1)});  // another map's
  Pose T = CirclePose(0, 24);
  T.translation() += 0.005 * T.linear().col(0);
  ServerKeyframe* query = AddGeneratedKeyframe(&map, world, kAgent, 10, T, T, &rng);
  KeyframeCullingOptions options;
  const std::vector<ServerKeyframe*> all = CoveringCandidates(map, *query, options);
  const std::vector<ServerKeyframe*> listed = CoveringCandidates(map, *query, options, &kept);
  ASSERT_EQ(all.size(), 3u);  // keyframes 0, 2, 4, nearest first
  EXPECT_EQ(all, listed);
  EXPECT_EQ(all[0]->id.keyframe, KeyframeId(0));
}

TEST(KeyframeCullingTest, CullKeepsPointsWhereTheyWereAndMovesLoopEdges) {
  ServerMap map(MapId(1));
  const std::vector<ServerKeyframe*> kfs = FourNeighbours(&map);
  ServerKeyframe* victim = kfs[1];
  ServerKeyframe* leader = kfs[0];
  // Both wait with their coded RGB-D for their map to join the primary map.
  victim->rgbd = std::make_shared<const RgbdPayload>();
  leader->rgbd = std::make_shared<const RgbdPayload>();
  // A loop edge from keyframe 3 to the victim, measured as their true relative pose.
  map.AddLoopEdge({kfs[3]->id, victim->id, kfs[3]->T_map_cam.inverse() * victim->T_map_cam});
  std::map<GlobalMapPointId, Eigen::Vector3d> before;
  int anchored = 0;
  for (const ServerMapPoint* p : victim->points) {
    if (!p) continue;
    before[p->id] = p->World();
    anchored += p->anchor == victim;
  }
  ASSERT_GT(anchored, 0);  // points first seen by the victim (the ring turns into view)
  const GlobalKeyframeId victim_id = victim->id;
  const Pose victim_before = victim->T_map_cam;
  map.Cull(victim, leader);
  EXPECT_EQ(map.keyframe(victim_id), nullptr);
  ASSERT_EQ(leader->followers.size(), 1u);
  const CulledKeyframe& record = leader->followers[0];
  EXPECT_EQ(record.id, victim_id);
  EXPECT_EQ(record.rgbd, nullptr);  // the leader's RGB-D covers its view
  for (const auto& [id, world_before] : before) {
    const ServerMapPoint* p = map.point(id);
    ASSERT_NE(p, nullptr);  // all are still seen by a neighbour
    EXPECT_NE(p->anchor->id, victim_id);
    EXPECT_LT((p->World() - world_before).norm(), 1e-9);
  }
  ASSERT_EQ(map.loop_edges().size(), 1u);
  const LoopEdge& edge = map.loop_edges()[0];
  EXPECT_EQ(edge.b, leader->id);
  EXPECT_LT(TranslationDistance(edge.T_a_b, kfs[3]->T_map_cam.inverse() * leader->T_map_cam), 1e-9);
  // The victim follows its leader from now on.
  EXPECT_LT(TranslationDistance(leader->FollowerPose(record), victim_before), 1e-6);
  Pose correction = Pose::Identity();
  correction.translation() = Eigen::Vector3d(0.3, -0.1, 0.05);
  correction.linear() = Eigen::AngleAxisd(0.1, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  const Pose leader_before = leader->T_map_cam;
  leader->T_map_cam = correction * leader->T_map_cam;
  const Pose expected = leader->T_map_cam * leader_before.inverse() * victim_before;
  EXPECT_LT(TranslationDistance(leader->FollowerPose(record), expected), 1e-6);
  EXPECT_LT(RotationDistance(leader->FollowerPose(record), expected), 1e-6);
  // Under a leader without RGB-D a culled keyframe keeps its own.
  kfs[2]->rgbd = std::make_shared<const RgbdPayload>();
  map.Cull(kfs[2], kfs[3]);
  ASSERT_EQ(kfs[3]->followers.size(), 1u);
  EXPECT_NE(kfs[3]->followers[0].rgbd, nullptr);
}

// An agent passing a place again closes the same loop again; the loop edges (the pose graph's
// constraints) must not grow with the passes, also when culling moves edges to a leader.
TEST(KeyframeCullingTest, APairOfKeyframesHasOneLoopEdge) {
  ServerMap map(MapId(1));
  const std::vector<ServerKeyframe*> kfs = FourNeighbours(&map);
  const auto relative = [](const ServerKeyframe* a, const ServerKeyframe* b) {
    return a->T_map_cam.inverse() * b->T_map_cam;
  };
  Pose measured = relative(kfs[3], kfs[0]);
  measured.translation().x() += 0.01;
  map.AddLoopEdge({kfs[3]->id, kfs[0]->id, relative(kfs[3], kfs[0])});
  map.AddLoopEdge({kfs[0]->id, kfs[3]->id, measured.inverse()});  // the same pair, measured again
  ASSERT_EQ(map.loop_edges().size(), 1u);
  EXPECT_LT(TranslationDistance(map.loop_edges()[0].T_a_b, measured), 1e-9);  // the newer one
  // Culling keyframe 1 into keyframe 0 would give keyframe 0 a second edge with keyframe 3.
  map.AddLoopEdge({kfs[3]->id, kfs[1]->id, relative(kfs[3], kfs[1])});
  ASSERT_EQ(map.loop_edges().size(), 2u);
  map.Cull(kfs[1], kfs[0]);
  ASSERT_EQ(map.loop_edges().size(), 1u);
  EXPECT_LT(TranslationDistance(map.loop_edges()[0].T_a_b, measured), 1e-9);  // its own stays
}

TEST(KeyframeCullingTest, AliasesOfRemovedPointsAreForgotten) {
  // Points merged by loops leave aliases (the agent may still name the old id); once the
  // merged point itself is removed with a culled keyframe, its aliases must go too, or they
  // would pile up for as long as agents revisit places.
  ServerMap map(MapId(1));
  const auto make = [&](std::uint32_t id) { return AddBareKeyframe(&map, id); };
  ServerKeyframe* leader = make(0);
  ServerKeyframe* victim = make(1);
  ServerKeyframe* other = make(2);
  constexpr std::uint32_t kPoints = 3000;
  for (std::uint32_t j = 0; j < kPoints; ++j) {
    victim->AppendKeypoint({cv::Point2f(1, 1), 0, 1.0f}, Descriptor{});
    other->AppendKeypoint({cv::Point2f(1, 1), 0, 1.0f}, Descriptor{});
    ServerMapPoint* kept = map.AddPoint(std::make_unique<ServerMapPoint>(
        GlobalMapPointId{kAgent, MapPointId(j)}, victim, Eigen::Vector3d(0, 0, 1), Descriptor{}));
    map.AddObservation(kept, victim, static_cast<int>(j));
    // A duplicate of it that a loop merged, seen by no one else after the merge.
    ServerMapPoint* duplicate = map.AddPoint(
        std::make_unique<ServerMapPoint>(GlobalMapPointId{kAgent, MapPointId(kPoints + j)}, other,
                                         Eigen::Vector3d(0, 0, 1), Descriptor{}));
    map.AddObservation(duplicate, other, static_cast<int>(j));
    map.MergePoints(duplicate, kept);
  }
  ASSERT_EQ(map.num_merge_aliases(), kPoints);
  ASSERT_EQ(map.point({kAgent, MapPointId(kPoints + 5)}), map.point({kAgent, MapPointId(5)}));
  // `other` still sees every point after the merge: culling the victim removes none.
  EXPECT_EQ(map.Cull(victim, leader), 0u);
  EXPECT_EQ(map.num_merge_aliases(), kPoints);
  EXPECT_NE(map.point({kAgent, MapPointId(kPoints + 5)}), nullptr);
  // Culling `other` removes them all: their aliases resolve to nothing, and the next sweep
  // (when merges have doubled the aliases since the last) forgets them.
  EXPECT_EQ(map.Cull(other, leader), kPoints);
  EXPECT_EQ(map.num_points(), 0u);
  EXPECT_EQ(map.point({kAgent, MapPointId(kPoints + 5)}), nullptr);
  for (std::uint32_t j = 0; j < 100; ++j) {
    leader->AppendKeypoint({cv::Point2f(1, 1), 0, 1.0f}, Descriptor{});
    ServerMapPoint* kept = map.AddPoint(
        std::make_unique<ServerMapPoint>(GlobalMapPointId{kAgent, MapPointId(2 * kPoints + 2 * j)},
                                         leader, Eigen::Vector3d(0, 0, 1), Descriptor{}));
    map.AddObservation(kept, leader, static_cast<int>(j));
    map.MergePoints(map.AddPoint(std::make_unique<ServerMapPoint>(
                        GlobalMapPointId{kAgent, MapPointId(2 * kPoints + 2 * j + 1)}, leader,
                        Eigen::Vector3d(0, 0, 1), Descriptor{})),
                    kept);
  }
  EXPECT_EQ(map.num_merge_aliases(), 100u);
}

TEST(KeyframeCullingTest, AliasesLiveAsLongAsTheirAgentMayNameThem) {
  ServerMap map(MapId(1));
  const auto add_keyframe = [&](std::uint32_t id) { return AddBareKeyframe(&map, id); };
  ServerKeyframe* seer = add_keyframe(0);
  std::uint32_t next_point = 0;
  // Merges `n` new duplicates into a point `seer` keeps seeing.
  auto merge = [&](std::uint32_t n) {
    std::vector<std::uint32_t> ids;
    for (std::uint32_t j = 0; j < n; ++j) {
      seer->AppendKeypoint({cv::Point2f(1, 1), 0, 1.0f}, Descriptor{});
      const auto k = static_cast<int>(seer->keypoints.size()) - 1;
      ServerMapPoint* kept = map.AddPoint(
          std::make_unique<ServerMapPoint>(GlobalMapPointId{kAgent, MapPointId(next_point++)}, seer,
                                           Eigen::Vector3d(0, 0, 1), Descriptor{}));
      map.AddObservation(kept, seer, k);
      ServerMapPoint* duplicate = map.AddPoint(
          std::make_unique<ServerMapPoint>(GlobalMapPointId{kAgent, MapPointId(next_point)}, seer,
                                           Eigen::Vector3d(0, 0, 1), Descriptor{}));
      ids.push_back(next_point++);
      map.MergePoints(duplicate, kept);
    }
    return ids;
  };
  const std::vector<std::uint32_t> old_ids = merge(3000);
  EXPECT_EQ(map.num_merge_aliases(), 3000u);  // young: all kept through a sweep
  for (std::uint32_t id = 1; id <= ServerMap::kMergeAliasKeyframes + 10; ++id) add_keyframe(id);
  const std::vector<std::uint32_t> new_ids = merge(200);
  // The sweep that the new merges started forgot the old aliases, not the new ones.
  EXPECT_EQ(map.num_merge_aliases(), 200u);
  EXPECT_EQ(map.point({kAgent, MapPointId(old_ids[0])}), nullptr);
  EXPECT_NE(map.point({kAgent, MapPointId(new_ids[0])}), nullptr);
}

TEST(KeyframeCullingTest, PoseGraphAndGlobalBaCarryCulledKeyframes) {
  ServerMap map = TwoLaps(24, 13);
  KeyframeCullingOptions options;
  options.keep_recent = 5;
  ASSERT_GT(CullInOrder(&map, options).culled, 5u);
  // Culled keyframes in the map before, and their leaders' poses then.
  std::map<GlobalKeyframeId, std::pair<const ServerKeyframe*, Pose>> leader_before;
  std::map<GlobalKeyframeId, Pose> culled_before;
  for (const auto& [id, kf] : map.keyframes()) {
    for (const CulledKeyframe& f : kf->followers) {
      leader_before[f.id] = {kf.get(), kf->T_map_cam};
      culled_before[f.id] = kf->FollowerPose(f);
    }
  }
  // A loop edge that disagrees with the map by 10 cm bends it.
  const ServerKeyframe* last = map.keyframes().rbegin()->second.get();
  const ServerKeyframe* first = map.keyframes().begin()->second.get();
  Pose T_first_last = first->T_map_cam.inverse() * last->T_map_cam;
  T_first_last.translation() += Eigen::Vector3d(0.1, 0, 0);
  map.AddLoopEdge({first->id, last->id, T_first_last});
  auto moved = OptimizeMapPoseGraph(&map);
  ASSERT_TRUE(moved.ok());
  int leaders_moved = 0;
  for (const ServerKeyframe* kf : *moved) {
    EXPECT_EQ(map.keyframe(kf->id), kf);
    leaders_moved += !kf->followers.empty();
  }
  EXPECT_GT(leaders_moved, 0);
  // Each culled keyframe moved rigidly with its leader.
  for (const auto& [id, before] : culled_before) {
    const auto& [leader, T_leader_before] = leader_before.at(id);
    const Pose expected = leader->T_map_cam * T_leader_before.inverse() * before;
    const auto record = std::find_if(leader->followers.begin(), leader->followers.end(),
                                     [&](const CulledKeyframe& f) { return f.id == id; });
    ASSERT_NE(record, leader->followers.end());
    EXPECT_LT(TranslationDistance(leader->FollowerPose(*record), expected), 1e-6);
    EXPECT_LT(RotationDistance(leader->FollowerPose(*record), expected), 1e-6);
  }
  const std::map<AgentId, PinholeCamera> cameras = {{kAgent, TestCamera()}};
  const GlobalBaProblem problem = BuildGlobalBa(map, cameras, DepthNoise());
  for (const GlobalKeyframeId& id : problem.keyframes) EXPECT_NE(map.keyframe(id), nullptr);
  EXPECT_EQ(problem.keyframes.size(), map.keyframes().size());
}

}  // namespace
}  // namespace ccmd
