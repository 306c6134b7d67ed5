#include "libccmd/backend/ingest.h"
#include "libccmd/backend/map_manager.h"
#include "libccmd/backend/map_optimization.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

Pose MakePose(double yaw, const Eigen::Vector3d& t) {
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  T.translation() = t;
  return T;
}

WirePose ToWire(const Pose& T) {
  const Eigen::Quaterniond q = QuaternionOf(T);
  WirePose w;
  w.q_xyzw = {q.x(), q.y(), q.z(), q.w()};
  w.t = {T.translation().x(), T.translation().y(), T.translation().z()};
  return w;
}

// A keyframe message with one new map point 2 m in front of the camera.
KeyframeMessage Message(std::uint32_t id, const Pose& T_world_cam,
                        std::optional<std::uint32_t> parent) {
  KeyframeMessage m;
  m.id = KeyframeId(id);
  m.timestamp = id;
  m.T_world_cam = ToWire(T_world_cam);
  if (parent) m.parent = KeyframeId(*parent);
  WireKeypoint k;
  k.u = 320;
  k.v = 240;
  k.depth_m = 2.0f;
  k.map_point = MapPointId(100 + id);
  m.keypoints.push_back(k);
  NewMapPoint p;
  p.id = MapPointId(100 + id);
  p.p_cam = {0, 0, 2};
  m.new_map_points.push_back(p);
  return m;
}

TEST(ServerMapTest, KeyframesFollowTheAgentsRelativeMotionAndPoseUpdates) {
  ServerMap map(MapId(1));
  const AgentId agent(1);
  const Pose T0 = MakePose(0.1, {1, 2, 0}), T1 = MakePose(0.3, {1.5, 2, 0.1});
  auto k0 = AddKeyframeMessage(&map, agent, Message(0, T0, std::nullopt), Pose::Identity());
  ASSERT_TRUE(k0.ok());
  // The server corrects keyframe 0 (as a loop closure would): keyframe 1 must be placed by the
  // agent's relative motion from keyframe 0's corrected pose, not at the agent's raw pose.
  const Pose correction = MakePose(0.05, {0.2, 0, 0});
  (*k0)->T_map_cam = correction * (*k0)->T_map_cam;
  auto k1 = AddKeyframeMessage(&map, agent, Message(1, T1, 0), Pose::Identity());
  ASSERT_TRUE(k1.ok());
  const Pose expected1 = (*k0)->T_map_cam * T0.inverse() * T1;
  EXPECT_LT(TranslationDistance((*k1)->T_map_cam, expected1), 1e-9);
  // The new map point is anchored: it moves with its keyframe.
  ServerMapPoint* point = map.point({agent, MapPointId(101)});
  ASSERT_NE(point, nullptr);
  EXPECT_LT((point->World() - expected1 * Eigen::Vector3d(0, 0, 2)).norm(), 1e-6);
  // A pose update (local BA on the agent) applies the agent's change on top of the server's pose.
  const Pose T1_refined = T1 * MakePose(0.01, {0.03, 0, 0});
  PoseUpdateMessage update;
  update.entries.push_back({KeyframeId(1), ToWire(T1_refined)});
  const auto moved = ApplyPoseUpdates(&map, agent, update);
  ASSERT_EQ(moved.size(), 1u);
  EXPECT_LT(TranslationDistance((*k1)->T_map_cam, expected1 * MakePose(0.01, {0.03, 0, 0})), 1e-6);
  EXPECT_LT((point->World() - (*k1)->T_map_cam * Eigen::Vector3d(0, 0, 2)).norm(), 1e-6);
  // Duplicate keyframe ids are refused.
  EXPECT_FALSE(AddKeyframeMessage(&map, agent, Message(1, T1, 0), Pose::Identity()).ok());
}

// Keyframes `first` to `last` of agent 1 at poses along a line, each the child of the one
// before; `first`, unless it is keyframe 0, starts a restarted segment (no parent), a reset
// with `reset`.
std::vector<ServerKeyframe*> AddChain(ServerMap* map, std::uint32_t first, std::uint32_t last,
                                      bool reset = false) {
  std::vector<ServerKeyframe*> chain;
  for (std::uint32_t i = first; i <= last; ++i) {
    KeyframeMessage m = Message(i, MakePose(0.05 * i, {0.1 * i, 0, 0}),
                                i == first ? std::nullopt : std::optional<std::uint32_t>(i - 1));
    m.restart = i == first && first > 0;
    m.reset = m.restart && reset;
    auto added = AddKeyframeMessage(map, AgentId(1), m, Pose::Identity());
    EXPECT_TRUE(added.ok());
    chain.push_back(added.ok() ? *added : nullptr);
  }
  return chain;
}

// A restarted segment's first keyframe comes without a parent and with the restart flag: it
// is posed where its agent put it, relative to the agent's latest keyframe (so the server's
// corrections carry over), and starts a segment that its children join and that nothing
// places against the rest of the map yet.
TEST(ServerMapTest, ARestartStartsAnUnplacedSegmentPosedFromTheAgentsLatestKeyframe) {
  ServerMap map(MapId(1));
  const std::vector<ServerKeyframe*> before = AddChain(&map, 0, 4);
  const Pose correction = MakePose(0.05, {0.2, 0, 0});
  before[4]->T_map_cam = correction * before[4]->T_map_cam;
  const std::vector<ServerKeyframe*> after = AddChain(&map, 5, 6);
  ASSERT_EQ(after.size(), 2u);
  EXPECT_LT(TranslationDistance(after[0]->T_map_cam, correction * MakePose(0.25, {0.5, 0, 0})),
            1e-9);
  EXPECT_FALSE(before[4]->restart);
  EXPECT_TRUE(after[0]->restart);
  EXPECT_FALSE(after[1]->restart);
  EXPECT_EQ(before[4]->segment, KeyframeId(0));
  EXPECT_EQ(after[0]->segment, KeyframeId(5));
  EXPECT_EQ(after[1]->segment, KeyframeId(5));
  EXPECT_TRUE(map.Placed(*before[4]));
  EXPECT_FALSE(map.Placed(*after[0]));
  EXPECT_FALSE(map.Placed(*after[1]));
}

// A reset (a restart at once after a young segment) is posed as tracking would have: placed as
// the segment before it is (placed, or in its unplaced group).
TEST(ServerMapTest, AResetIsPlacedAsTheSegmentBeforeIt) {
  ServerMap map(MapId(1));
  AddChain(&map, 0, 4);
  const std::vector<ServerKeyframe*> reset = AddChain(&map, 5, 6, /*reset=*/true);
  EXPECT_TRUE(reset[0]->restart);
  EXPECT_TRUE(map.Placed(*reset[0]) && map.Placed(*reset[1]));
  EXPECT_EQ(map.num_unplaced_segments(), 0u);
  const std::vector<ServerKeyframe*> lost = AddChain(&map, 7, 8);
  const std::vector<ServerKeyframe*> again = AddChain(&map, 9, 10, /*reset=*/true);
  EXPECT_FALSE(map.Placed(*again[0]));
  EXPECT_EQ(map.UnplacedGroup(*again[1]), map.UnplacedGroup(*lost[0]));
}

// Where the map holds fewer keyframes than a young segment, those few are kept apart instead
// of the restarted segment, which is the map from now on.
TEST(ServerMapTest, ARestartAfterAnAlmostEmptyMapKeepsTheFewBeforeItApart) {
  ServerMap map(MapId(1));
  const std::vector<ServerKeyframe*> before = AddChain(&map, 0, kYoungSegmentKeyframes - 2);
  const std::vector<ServerKeyframe*> after =
      AddChain(&map, kYoungSegmentKeyframes - 1, kYoungSegmentKeyframes + 3);
  EXPECT_TRUE(after[0]->restart);
  EXPECT_TRUE(map.Placed(*after[0]) && map.Placed(*after[4]));
  for (ServerKeyframe* kf : before) EXPECT_FALSE(map.Placed(*kf));
}

// Loops link segments: two unplaced ones become one group, and a loop of either with the
// placed part places both, returning all their keyframes.
TEST(ServerMapTest, ALoopWithThePlacedPartPlacesTheWholeGroupOfSegments) {
  ServerMap map(MapId(1));
  const std::vector<ServerKeyframe*> a = AddChain(&map, 0, 4), b = AddChain(&map, 5, 9),
                                     c = AddChain(&map, 10, 14);
  ASSERT_EQ(map.num_unplaced_segments(), 2u);
  EXPECT_NE(map.UnplacedGroup(*b[2]), map.UnplacedGroup(*c[4]));
  EXPECT_TRUE(map.LinkSegments(*a[0], *a[3]).empty());  // both placed
  EXPECT_TRUE(map.LinkSegments(*c[4], *b[2]).empty());  // two unplaced: one group now
  EXPECT_EQ(map.UnplacedGroup(*b[2]), map.UnplacedGroup(*c[4]));
  EXPECT_FALSE(map.Placed(*b[0]));
  std::vector<ServerKeyframe*> expected = b;
  expected.insert(expected.end(), c.begin(), c.end());
  EXPECT_EQ(map.LinkSegments(*c[0], *a[1]), expected);
  for (const auto& [id, kf] : map.keyframes()) EXPECT_TRUE(map.Placed(*kf));
  EXPECT_EQ(map.num_unplaced_segments(), 0u);
}

// A keyframe's depth links reach the global BA as relative poses between the right cameras,
// with the information the agent sent; a link to a keyframe the map does not hold is dropped.
TEST(ServerMapTest, DepthLinksBecomeRelativePosesInTheGlobalBa) {
  ServerMap map(MapId(1));
  const AgentId agent(1);
  const Pose T0 = MakePose(0.1, {1, 2, 0}), T1 = MakePose(0.3, {1.5, 2, 0.1});
  ASSERT_TRUE(AddKeyframeMessage(&map, agent, Message(0, T0, std::nullopt), Pose::Identity()).ok());
  KeyframeMessage m1 = Message(1, T1, 0);
  Eigen::Matrix<double, 6, 6> information = Eigen::Matrix<double, 6, 6>::Zero();
  for (int i = 0; i < 6; ++i) information(i, i) = 100.0 * (i + 1);
  information(0, 3) = information(3, 0) = 20.0;
  DepthLink link;
  link.keyframe = KeyframeId(0);
  link.T_this_other = ToWire(T1.inverse() * T0);
  int k = 0;
  for (int r = 0; r < 6; ++r) {
    for (int c = r; c < 6; ++c) link.information[k++] = static_cast<float>(information(r, c));
  }
  DepthLink missing = link;
  missing.keyframe = KeyframeId(7);
  m1.depth_links = {link, missing};
  auto k1 = AddKeyframeMessage(&map, agent, m1, Pose::Identity());
  ASSERT_TRUE(k1.ok());
  ASSERT_EQ((*k1)->depth_links.size(), 2u);
  const auto& stored = (*k1)->depth_links[0];
  EXPECT_LT(((stored.sqrt_information.transpose() * stored.sqrt_information) - information).norm(),
            1e-3);

  const GlobalBaProblem g = BuildGlobalBa(map, {{agent, PinholeCamera()}}, DepthNoise());
  ASSERT_EQ(g.problem.relative_poses.size(), 1u);
  const BaRelativePose& r = g.problem.relative_poses[0];
  EXPECT_EQ(g.keyframes[r.camera_a], (GlobalKeyframeId{agent, KeyframeId(0)}));
  EXPECT_EQ(g.keyframes[r.camera_b], (GlobalKeyframeId{agent, KeyframeId(1)}));
  EXPECT_LT(TranslationDistance(r.T_b_a, T1.inverse() * T0), 1e-6);
}

TEST(MapManagerTest, FusionPlacesTheOtherMapByTheTransform) {
  MapManager maps;
  const AgentId a(1), b(2);
  std::vector<Pose> poses_b;
  {
    auto guard = maps.CheckOutAgent(a);
    ASSERT_TRUE(AddKeyframeMessage(guard.get(), a, Message(0, Pose::Identity(), std::nullopt),
                                   Pose::Identity())
                    .ok());
  }
  {
    auto guard = maps.CheckOutAgent(b);
    for (std::uint32_t i = 0; i < 3; ++i) {
      poses_b.push_back(MakePose(0.2 * i, {0.5 * i, 0, 0}));
      ASSERT_TRUE(
          AddKeyframeMessage(
              guard.get(), b,
              Message(i, poses_b.back(), i ? std::optional<std::uint32_t>(i - 1) : std::nullopt),
              Pose::Identity())
              .ok());
    }
  }
  EXPECT_EQ(*maps.primary(), MapId(1));
  const Pose T_a_b = MakePose(1.2, {3, -1, 0.5});
  auto [ga, gb] = maps.CheckOutPair(MapId(1), MapId(2));
  MapManager::Guard fused = maps.Fuse(&ga, &gb, T_a_b);
  ASSERT_TRUE(fused);
  EXPECT_FALSE(ga);  // the old maps are gone
  EXPECT_EQ(fused->keyframes().size(), 4u);
  for (std::uint32_t i = 0; i < 3; ++i) {
    const ServerKeyframe* kf = fused->keyframe({b, KeyframeId(i)});
    ASSERT_NE(kf, nullptr);
    EXPECT_LT(TranslationDistance(kf->T_map_cam, T_a_b * poses_b[i]), 1e-9);
    // Points moved along with their anchors.
    const ServerMapPoint* p = fused->point({b, MapPointId(100 + i)});
    ASSERT_NE(p, nullptr);
    EXPECT_LT((p->World() - T_a_b * poses_b[i] * Eigen::Vector3d(0, 0, 2)).norm(), 1e-6);
  }
  EXPECT_EQ(fused->origin()->agent, a);  // the kept (primary) map's gauge
  const MapId fused_id = fused->id();
  fused = MapManager::Guard();
  EXPECT_EQ(*maps.primary(), fused_id);
  EXPECT_EQ(*maps.MapOfAgent(b), fused_id);
  EXPECT_EQ(maps.Maps().size(), 1u);
}

}  // namespace
}  // namespace ccmd
