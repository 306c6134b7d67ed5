// The update paths (local BA, pose graph, global BA) and map fusion: after any of them the
// store equals a from-scratch build with the new poses.

#include <gtest/gtest.h>

#include <set>

#include "libccmd/dense/dense_map.h"
#include "libccmd/util/random.h"
#include "tests/dense/dense_test_util.h"

namespace ccmd {
namespace {

using dense_testing::MakeMap;
using dense_testing::PlaneKeyframe;
using dense_testing::SameCloud;
using dense_testing::StripPose;
using dense_testing::TestOptions;

const AgentId kAgent1(1);
const AgentId kAgent2(2);
constexpr int kKeyframes = 10;

// A pose moved by a few centimetres and a few degrees, different for every seed.
Pose Perturbed(const Pose& pose, std::uint64_t seed) {
  Rng rng(seed);
  Pose delta = Pose::Identity();
  delta.translation() =
      Eigen::Vector3d(rng.Uniform(-0.05, 0.05), rng.Uniform(-0.05, 0.05), rng.Uniform(-0.05, 0.05));
  delta.linear() = RotationFromAngleAxis(Eigen::Vector3d(
      rng.Uniform(-0.05, 0.05), rng.Uniform(-0.05, 0.05), rng.Uniform(-0.05, 0.05)));
  return delta * pose;
}

// Agents 1 and 2 each with kKeyframes keyframes at the given poses (keyframe id = index).
std::unique_ptr<DenseMap> Build(const std::vector<Pose>& poses1, const std::vector<Pose>& poses2) {
  auto map = MakeMap(TestOptions(3));
  for (std::uint32_t id = 0; id < poses1.size(); ++id) {
    DenseKeyframe k = PlaneKeyframe(kAgent1, id, StripPose(id), 21);
    k.T_world_cam = poses1[id];  // the same images, another pose
    EXPECT_TRUE(map->AddKeyframe(k).ok());
  }
  for (std::uint32_t id = 0; id < poses2.size(); ++id) {
    DenseKeyframe k = PlaneKeyframe(kAgent2, id, StripPose(id + 3), 22);
    k.T_world_cam = poses2[id];
    EXPECT_TRUE(map->AddKeyframe(k).ok());
  }
  return map;
}

std::vector<Pose> StripPoses(int offset) {
  std::vector<Pose> poses;
  for (int i = 0; i < kKeyframes; ++i) poses.push_back(StripPose(i + offset));
  return poses;
}

std::set<std::uint64_t> OccupiedVoxels(const PointCloud& cloud) {
  const VoxelGrid grid(0.05);
  std::set<std::uint64_t> voxels;
  for (const auto& p : cloud.points) voxels.insert(grid.Key(p));
  return voxels;
}

// Unfiltered points, window-filtered points, and the global filter all equal.
void ExpectSameStore(DenseMap& store, DenseMap& scratch) {
  const auto all = DenseSelection::Global();
  EXPECT_TRUE(SameCloud(*store.Extract(all, DenseFilter::kNone),
                        *scratch.Extract(all, DenseFilter::kNone)));
  const PointCloud kept = *store.Extract(all, DenseFilter::kWindow);
  EXPECT_TRUE(SameCloud(kept, *scratch.Extract(all, DenseFilter::kWindow)));
  EXPECT_EQ(OccupiedVoxels(kept), OccupiedVoxels(*scratch.Extract(all, DenseFilter::kWindow)));
  EXPECT_TRUE(SameCloud(*store.Extract(all, DenseFilter::kGlobal),
                        *scratch.Extract(all, DenseFilter::kGlobal)));
}

TEST(DenseUpdateTest, LocalBaUpdateEqualsAFromScratchBuild) {
  std::vector<Pose> p1 = StripPoses(0), p2 = StripPoses(3);
  auto store = Build(p1, p2);
  const GlobalKeyframeId moved{kAgent1, KeyframeId(5)};
  const PointCloud before = *store->ExtractKeyframe(moved);
  p1[5] = Perturbed(p1[5], 1);
  ASSERT_TRUE(store->UpdateKeyframePose(moved, p1[5]).ok());
  EXPECT_EQ(store->Stats().pending_keyframes, 1u);

  // Point for point before filtering: new pose times the old pose's inverse, independently.
  const PointCloud after = *store->ExtractKeyframe(moved);
  ASSERT_EQ(after.size(), before.size());
  const Pose change = p1[5] * StripPose(5).inverse();
  for (std::size_t i = 0; i < after.size(); ++i) {
    const Eigen::Vector3d expected = change * before.points[i].cast<double>();
    ASSERT_LT((after.points[i].cast<double>() - expected).norm(), 1e-5);
  }
  EXPECT_EQ(store->KeyframePoseOf(moved)->matrix(), p1[5].matrix());

  // Keyframe 5 with W = 3 changes the filter of keyframes 2..5 (an export would also do this).
  EXPECT_EQ(store->Maintain(), 4u);
  EXPECT_EQ(store->Stats().pending_keyframes, 0u);
  auto scratch = Build(p1, p2);
  ExpectSameStore(*store, *scratch);
}

TEST(DenseUpdateTest, MaintainRefiltersOnlyTheWindowsOfMovedKeyframes) {
  std::vector<Pose> p1 = StripPoses(0);
  auto store = Build(p1, {});
  ASSERT_TRUE(store->UpdateKeyframePose({kAgent1, KeyframeId(1)}, Perturbed(p1[1], 2)).ok());
  EXPECT_EQ(store->Maintain(), 2u);  // keyframes 0 and 1
  EXPECT_EQ(store->Maintain(), 0u);
  // Two moves with overlapping windows are one run: 3..8 for keyframes 6 and 8.
  ASSERT_TRUE(store->UpdateKeyframePose({kAgent1, KeyframeId(8)}, Perturbed(p1[8], 3)).ok());
  ASSERT_TRUE(store->UpdateKeyframePose({kAgent1, KeyframeId(6)}, Perturbed(p1[6], 4)).ok());
  EXPECT_EQ(store->Maintain(), 6u);
}

TEST(DenseUpdateTest, LoopUpdateRefiltersAtOnceAndEqualsAFromScratchBuild) {
  std::vector<Pose> p1 = StripPoses(0), p2 = StripPoses(3);
  auto store = Build(p1, p2);
  std::vector<KeyframePose> loop;
  for (std::uint32_t id = 2; id <= 7; ++id) {
    p1[id] = Perturbed(p1[id], 10 + id);
    loop.push_back({{kAgent1, KeyframeId(id)}, p1[id]});
  }
  p2[9] = Perturbed(p2[9], 30);
  loop.push_back({{kAgent2, KeyframeId(9)}, p2[9]});
  ASSERT_TRUE(store->UpdateLoopPoses(loop).ok());
  EXPECT_EQ(store->Stats().pending_keyframes, 0u);
  auto scratch = Build(p1, p2);
  ExpectSameStore(*store, *scratch);
}

TEST(DenseUpdateTest, GlobalBaTouchesOnlyKeyframesThatMoved) {
  std::vector<Pose> p1 = StripPoses(0), p2 = StripPoses(3);
  auto store = Build(p1, p2);
  p1[0] = Perturbed(p1[0], 40);
  p1[9] = Perturbed(p1[9], 41);
  p2[4] = Perturbed(p2[4], 42);
  std::vector<KeyframePose> all;
  for (std::uint32_t id = 0; id < kKeyframes; ++id) {
    all.push_back({{kAgent1, KeyframeId(id)}, p1[id]});
    all.push_back({{kAgent2, KeyframeId(id)}, p2[id]});
  }
  auto moved = store->UpdateGlobalPoses(all);
  ASSERT_TRUE(moved.ok());
  EXPECT_EQ(*moved, 3u);
  auto scratch = Build(p1, p2);
  ExpectSameStore(*store, *scratch);
}

TEST(DenseUpdateTest, ManyInterleavedUpdatesAndAddsEqualAFromScratchBuild) {
  std::vector<Pose> p1, p2;
  auto store = MakeMap(TestOptions(3));
  Rng rng(99);
  for (std::uint32_t id = 0; id < kKeyframes; ++id) {
    p1.push_back(StripPose(id));
    ASSERT_TRUE(store->AddKeyframe(PlaneKeyframe(kAgent1, id, StripPose(id), 21)).ok());
    p2.push_back(StripPose(id + 3));
    ASSERT_TRUE(store->AddKeyframe(PlaneKeyframe(kAgent2, id, StripPose(id + 3), 22)).ok());
    for (int u = 0; u < 3; ++u) {  // local BA moves some earlier keyframes
      const auto k = static_cast<std::uint32_t>(rng.UniformInt(0, static_cast<int>(id)));
      std::vector<Pose>& poses = u == 2 ? p2 : p1;
      poses[k] = Perturbed(poses[k], rng.Next());
      ASSERT_TRUE(
          store->UpdateKeyframePose({u == 2 ? kAgent2 : kAgent1, KeyframeId(k)}, poses[k]).ok());
    }
    if (id % 4 == 3) store->Maintain();  // sometimes idle, sometimes not
  }
  auto scratch = Build(p1, p2);
  ExpectSameStore(*store, *scratch);
}

TEST(DenseUpdateTest, FusionTransformMovesEveryPointOfTheAgent) {
  std::vector<Pose> p1 = StripPoses(0), p2 = StripPoses(3);
  auto store = Build(p1, p2);
  const PointCloud agent1_before =
      *store->Extract(DenseSelection::Agent(kAgent1), DenseFilter::kNone);
  const PointCloud agent2_before =
      *store->Extract(DenseSelection::Agent(kAgent2), DenseFilter::kNone);
  Pose t = Pose::Identity();
  t.linear() = RotationFromAngleAxis(Eigen::Vector3d(0.1, -0.3, 0.7));
  t.translation() = Eigen::Vector3d(1.5, -2.0, 0.25);
  ASSERT_TRUE(store->TransformAgent(kAgent1, t).ok());

  const PointCloud agent1_after =
      *store->Extract(DenseSelection::Agent(kAgent1), DenseFilter::kNone);
  ASSERT_EQ(agent1_after.size(), agent1_before.size());
  for (std::size_t i = 0; i < agent1_after.size(); ++i) {
    const Eigen::Vector3d expected = t * agent1_before.points[i].cast<double>();
    ASSERT_LT((agent1_after.points[i].cast<double>() - expected).norm(), 2e-5);
    ASSERT_EQ(agent1_after.labels[i], agent1_before.labels[i]);
  }
  EXPECT_TRUE(SameCloud(*store->Extract(DenseSelection::Agent(kAgent2), DenseFilter::kNone),
                        agent2_before));
  for (Pose& p : p1) p = t * p;
  auto scratch = Build(p1, p2);
  ExpectSameStore(*store, *scratch);
}

TEST(DenseUpdateTest, MergeMapsMovesEveryAgentOfTheSourceMap) {
  std::vector<Pose> p1 = StripPoses(0), p2 = StripPoses(3);
  auto store = Build(p1, p2);
  ASSERT_EQ(store->Maps(), (std::vector<MapId>{MapId(1), MapId(2)}));
  const PointCloud agent2_before =
      *store->Extract(DenseSelection::Agent(kAgent2), DenseFilter::kNone);
  Pose t = Pose::Identity();
  t.linear() = RotationFromAngleAxis(Eigen::Vector3d(0.0, 0.0, 1.2));
  t.translation() = Eigen::Vector3d(0.3, 0.2, -0.1);
  ASSERT_TRUE(store->MergeMaps(MapId(2), MapId(1), t).ok());
  EXPECT_EQ(store->Maps(), (std::vector<MapId>{MapId(1)}));
  EXPECT_EQ(*store->MapOf(kAgent2), MapId(1));
  const PointCloud agent2_after =
      *store->Extract(DenseSelection::Agent(kAgent2), DenseFilter::kNone);
  ASSERT_EQ(agent2_after.size(), agent2_before.size());
  for (std::size_t i = 0; i < agent2_after.size(); ++i) {
    ASSERT_LT(
        (agent2_after.points[i].cast<double>() - t * agent2_before.points[i].cast<double>()).norm(),
        2e-5);
  }
  // The fused map holds both agents.
  EXPECT_EQ(store->Extract(DenseSelection::Map(MapId(1)), DenseFilter::kNone)->size(),
            store->Extract(DenseSelection::Global(), DenseFilter::kNone)->size());
  EXPECT_EQ(store->Extract(DenseSelection::Map(MapId(2))).status().code(), StatusCode::kNotFound);
  for (Pose& p : p2) p = t * p;
  auto scratch = Build(p1, p2);  // agent 2 in map 2 there: the global order is the same
  ExpectSameStore(*store, *scratch);
  EXPECT_EQ(store->MergeMaps(MapId(1), MapId(1), t).code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(store->MergeMaps(MapId(2), MapId(1), t).code(), StatusCode::kNotFound);
}

TEST(DenseUpdateTest, BadPosesAreErrorsAndChangeNothing) {
  std::vector<Pose> p1 = StripPoses(0);
  auto store = Build(p1, {});
  const PointCloud before = *store->Extract(DenseSelection::Global(), DenseFilter::kNone);
  Pose scaled = p1[0];
  scaled.linear() *= 1.01;
  EXPECT_EQ(store->UpdateKeyframePose({kAgent1, KeyframeId(0)}, scaled).code(),
            StatusCode::kInvalidArgument);
  // One bad pose in a loop update: nothing moves.
  const std::vector<KeyframePose> loop = {{{kAgent1, KeyframeId(1)}, Perturbed(p1[1], 5)},
                                          {{kAgent1, KeyframeId(2)}, scaled}};
  EXPECT_EQ(store->UpdateLoopPoses(loop).code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(store->UpdateGlobalPoses(loop).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(store->TransformAgent(kAgent2, Pose::Identity()).code(), StatusCode::kNotFound);
  EXPECT_TRUE(SameCloud(*store->Extract(DenseSelection::Global(), DenseFilter::kNone), before));
  EXPECT_EQ(store->Stats().pending_keyframes, 0u);
}

// The back-end names keyframes the store may have released (DenseMap::TakeReleased): those
// are skipped and counted, the others move as they would alone.
TEST(DenseUpdateTest, UpdatesOfKeyframesNotHeldAreSkipped) {
  std::vector<Pose> p1 = StripPoses(0);
  auto store = Build(p1, {});
  auto reference = Build(p1, {});
  const Pose moved = Perturbed(p1[1], 5);
  EXPECT_TRUE(store->UpdateKeyframePose({kAgent1, KeyframeId(77)}, p1[0]).ok());
  EXPECT_TRUE(store->UpdateKeyframePose({kAgent2, KeyframeId(0)}, p1[0]).ok());
  const std::vector<KeyframePose> loop = {{{kAgent1, KeyframeId(1)}, moved},
                                          {{kAgent1, KeyframeId(50)}, p1[0]}};
  EXPECT_TRUE(store->UpdateLoopPoses(loop).ok());
  ASSERT_TRUE(reference->UpdateLoopPoses({loop[0]}).ok());
  EXPECT_EQ(*store->UpdateGlobalPoses(loop), 0u);  // keyframe 1 is there already
  EXPECT_EQ(store->Stats().absent_updates, 4u);
  ExpectSameStore(*store, *reference);
}

}  // namespace
}  // namespace ccmd
