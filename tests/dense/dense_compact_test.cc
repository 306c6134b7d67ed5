// Compaction of keyframes that have left the filter window: the compact encoding, what a
// compacted keyframe keeps, memory that plateaus when a place is revisited, pose updates that
// move compacted points exactly, and the map after corrections against a from-scratch build.

#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <set>

#include "libccmd/dense/compact_cloud.h"
#include "libccmd/dense/dense_map.h"
#include "libccmd/util/random.h"
#include "tests/dense/dense_test_util.h"

namespace ccmd {
namespace {

using dense_testing::MakeMap;
using dense_testing::PlaneKeyframe;
using dense_testing::StripPose;
using dense_testing::TestOptions;

const AgentId kAgent(1);
constexpr double kVoxel = 0.05;  // TestOptions

DenseMapOptions CompactOptions() {
  DenseMapOptions o = TestOptions(3);
  o.compact_keyframes = true;
  // These keyframes back-project about 700 points (a 320x240 one, tens of thousands): only
  // empty ones are released unless a test asks for more.
  o.release_below_points = 0;
  return o;
}

TEST(CompactCloudTest, KeepsChosenPointsWithinHalfAStepInNineBytesEach) {
  Rng rng(5);
  CameraCloud cloud;
  for (int i = 0; i < 1000; ++i) {
    cloud.points.emplace_back(rng.Uniform(-2, 2), rng.Uniform(-1.5, 1.5), rng.Uniform(0.3, 3.0));
    cloud.colors.push_back({static_cast<std::uint8_t>(i), static_cast<std::uint8_t>(i / 4), 7});
  }
  std::vector<std::uint32_t> chosen;
  for (std::uint32_t i = 0; i < 1000; i += 3) chosen.push_back(i);
  CompactCloud compact = CompactCloud::Encode(cloud, chosen);
  ASSERT_EQ(compact.size(), chosen.size());
  EXPECT_LE(compact.step(), 3.0f / 32767 * 1.0001f);
  EXPECT_EQ(compact.MemoryBytes(), 9 * chosen.size());
  const CameraCloud decoded = compact.Decode();
  for (std::size_t k = 0; k < chosen.size(); ++k) {
    EXPECT_LE((decoded.points[k] - cloud.points[chosen[k]]).cwiseAbs().maxCoeff(),
              0.5f * compact.step() * 1.001f);
    EXPECT_EQ(decoded.colors[k], cloud.colors[chosen[k]]);
  }
  // Transform is the pose applied to the decoded points.
  Pose T = StripPose(3);
  T.translation() += Eigen::Vector3d(1, -2, 0.5);
  std::vector<Eigen::Vector3f> world;
  compact.Transform(T, &world);
  for (std::size_t k = 0; k < chosen.size(); ++k) {
    EXPECT_LT((world[k] - (T.cast<float>() * decoded.points[k])).norm(), 1e-5f);
  }
  // Keep drops the others.
  compact.Keep({0, 5, 10});
  ASSERT_EQ(compact.size(), 3u);
  EXPECT_EQ(compact.colors()[2], cloud.colors[chosen[10]]);
  EXPECT_EQ(compact.MemoryBytes(), 27u);
}

std::set<std::uint64_t> Voxels(const PointCloud& cloud) {
  const VoxelGrid grid(kVoxel);
  std::set<std::uint64_t> voxels;
  for (const auto& p : cloud.points) voxels.insert(grid.Key(p));
  return voxels;
}

// The voxels of a store's map.
std::set<std::uint64_t> MapVoxels(DenseMap* store) {
  auto map = store->Extract(DenseSelection::Global());
  EXPECT_TRUE(map.ok());
  return map.ok() ? Voxels(*map) : std::set<std::uint64_t>();
}

// How many voxels of `of` are not in `in`.
std::size_t Missing(const std::set<std::uint64_t>& of, const std::set<std::uint64_t>& in) {
  std::size_t missing = 0;
  for (std::uint64_t v : of) missing += !in.count(v);
  return missing;
}

// The maps of two stores cover the same voxels, but for one in 500.
void ExpectSameVoxels(DenseMap* a, DenseMap* b) {
  const std::set<std::uint64_t> va = MapVoxels(a), vb = MapVoxels(b);
  EXPECT_LE(Missing(vb, va) + Missing(va, vb), vb.size() / 500) << vb.size();
}

// Share of `a`'s points with a point of `b` closer than `distance`.
double Covered(const PointCloud& a, const PointCloud& b, double distance) {
  std::size_t covered = 0;
  for (const auto& p : a.points) {
    for (const auto& q : b.points) {
      if ((p - q).norm() < distance) {
        ++covered;
        break;
      }
    }
  }
  return a.points.empty() ? 1.0 : static_cast<double>(covered) / a.points.size();
}

// `n` keyframes of the strip (images of StripPose(image_of(i))) at the poses given.
void AddStrip(DenseMap* map, int first, int n, const std::function<int(int)>& image_of,
              const std::function<Pose(int)>& pose_of) {
  for (int i = first; i < first + n; ++i) {
    DenseKeyframe k =
        PlaneKeyframe(kAgent, static_cast<std::uint32_t>(i), StripPose(image_of(i)), 31);
    k.T_world_cam = pose_of(i);
    ASSERT_TRUE(map->AddKeyframe(k).ok());
  }
}

TEST(DenseCompactTest, KeyframesThatLeftTheWindowKeepOnlyWhatTheMapNeeds) {
  auto compact = MakeMap(CompactOptions());
  auto full = MakeMap(TestOptions(3));
  const auto image = [](int i) { return i; };
  const auto pose = [](int i) { return StripPose(i); };
  AddStrip(compact.get(), 0, 12, image, pose);
  AddStrip(full.get(), 0, 12, image, pose);

  const DenseMapStats c = compact->Stats(), f = full->Stats();
  EXPECT_EQ(c.keyframes, 12u);
  EXPECT_EQ(c.compact_keyframes, 9u);  // all but the W = 3 newest
  EXPECT_EQ(f.compact_keyframes, 0u);
  EXPECT_LT(c.kept_points, f.kept_points);  // the held voxels dropped some the window filter kept
  EXPECT_LT(c.points, 0.6 * f.points);
  // A compacted keyframe stores a subset of what the window filter kept of it.
  for (std::uint32_t id = 0; id < 9; ++id) {
    auto stored = compact->ExtractKeyframe({kAgent, KeyframeId(id)});
    auto all = full->ExtractKeyframe({kAgent, KeyframeId(id)});
    ASSERT_TRUE(stored.ok() && all.ok());
    EXPECT_LT(stored->size(), all->size());
    EXPECT_GT(Covered(*stored, *all, 1e-3), 0.999) << id;
  }
  // The map covers the same voxels: a point is dropped only where another stored point is.
  ExpectSameVoxels(compact.get(), full.get());
  // In camera frame, with colours, for viewers.
  auto cloud = compact->KeyframeCloud({kAgent, KeyframeId(2)});
  ASSERT_TRUE(cloud.ok());
  EXPECT_EQ(cloud->size(), compact->ExtractKeyframe({kAgent, KeyframeId(2)})->size());
}

TEST(DenseCompactTest, RevisitingAPlaceAddsAlmostNothing) {
  auto compact = MakeMap(CompactOptions());
  auto full = MakeMap(TestOptions(3));
  // Back and forth over the same 8 views, 6 times (48 keyframes).
  const auto image = [](int i) { return (i / 8) % 2 == 0 ? i % 8 : 7 - i % 8; };
  const auto pose = [&](int i) { return StripPose(image(i)); };
  AddStrip(compact.get(), 0, 16, image, pose);
  AddStrip(full.get(), 0, 16, image, pose);
  const std::size_t compact_after_two = compact->Stats().points,
                    full_after_two = full->Stats().kept_points;
  AddStrip(compact.get(), 16, 32, image, pose);
  AddStrip(full.get(), 16, 32, image, pose);
  EXPECT_LT(compact->Stats().points, 1.15 * compact_after_two);
  EXPECT_GT(full->Stats().kept_points, 2.5 * full_after_two);
}

// A camera going back and forth over the same views, recording the same images again: once
// compacted, a keyframe whose every voxel an earlier one holds has nothing to store and leaves
// the store, so the keyframes kept stop growing with the passes while the map covers what a
// store keeping everything covers.
TEST(DenseCompactTest, KeyframesLeftWithNothingToStoreAreReleased) {
  auto compact = MakeMap(CompactOptions());
  auto full = MakeMap(TestOptions(3));
  std::vector<DenseKeyframe> views;
  for (std::uint32_t v = 0; v < 8; ++v) views.push_back(PlaneKeyframe(kAgent, v, StripPose(v), 31));
  const auto add = [&](int first, int n) {
    for (int i = first; i < first + n; ++i) {
      DenseKeyframe k = views[(i / 8) % 2 == 0 ? i % 8 : 7 - i % 8];
      k.id = {kAgent, KeyframeId(static_cast<std::uint32_t>(i))};
      ASSERT_TRUE(compact->AddKeyframe(k).ok());
      ASSERT_TRUE(full->AddKeyframe(k).ok());
    }
  };
  add(0, 16);
  const std::size_t after_two = compact->Stats().keyframes;
  compact->TakeReleased();
  add(16, 32);
  const DenseMapStats stats = compact->Stats();
  EXPECT_LE(stats.keyframes, after_two + 1);
  EXPECT_EQ(stats.keyframes + stats.released_keyframes, 48u);
  EXPECT_EQ(stats.released_points, 0u);
  const std::vector<GlobalKeyframeId> released = compact->TakeReleased();
  EXPECT_GT(released.size(), 25u);
  EXPECT_TRUE(compact->TakeReleased().empty());
  for (const GlobalKeyframeId& id : released) {
    EXPECT_EQ(compact->ExtractKeyframe(id).status().code(), StatusCode::kNotFound);
  }
  // The newest W keyframes are still in the window: none of them is released.
  for (std::uint32_t id = 45; id < 48; ++id)
    EXPECT_TRUE(compact->ExtractKeyframe({kAgent, KeyframeId(id)}).ok());
  ExpectSameVoxels(compact.get(), full.get());
  // A loop correction naming a released keyframe moves the others.
  std::vector<KeyframePose> loop;
  for (const GlobalKeyframeId& id : {released[0], GlobalKeyframeId{kAgent, KeyframeId(46)}}) {
    Pose p = *compact->KeyframePoseOf({kAgent, KeyframeId(46)});
    p.translation().x() += 0.02;
    loop.push_back({id, p});
  }
  ASSERT_TRUE(compact->UpdateLoopPoses(loop).ok());
  EXPECT_EQ(compact->Stats().absent_updates, 1u);
  EXPECT_LT(TranslationDistance(*compact->KeyframePoseOf(loop[1].id), loop[1].T_world_cam), 1e-12);
}

// Images recorded again carry new depth noise, which reaches a few voxels beyond what the map
// holds on every pass: keyframes storing fewer points than release_below_points release them,
// and the map loses at most those points' voxels.
TEST(DenseCompactTest, KeyframesWithFewerPointsThanTheThresholdAreReleasedWithThem) {
  DenseMapOptions options = CompactOptions();
  options.release_below_points = 30;
  auto compact = MakeMap(options);
  auto full = MakeMap(TestOptions(3));
  const auto image = [](int i) { return (i / 8) % 2 == 0 ? i % 8 : 7 - i % 8; };
  const auto pose = [&](int i) { return StripPose(image(i)); };
  AddStrip(compact.get(), 0, 48, image, pose);
  AddStrip(full.get(), 0, 48, image, pose);
  const DenseMapStats stats = compact->Stats();
  EXPECT_GT(stats.released_keyframes, 5u);
  EXPECT_GT(stats.released_points, 0u);
  EXPECT_EQ(stats.keyframes + stats.released_keyframes, 48u);
  for (std::uint32_t id = 0; id < 45; ++id) {  // the compacted ones that stay hold enough
    auto stored = compact->ExtractKeyframe({kAgent, KeyframeId(id)});
    if (stored.ok()) {
      EXPECT_GE(stored->size(), 30u) << id;
    }
  }
  const std::set<std::uint64_t> vc = MapVoxels(compact.get()), vf = MapVoxels(full.get());
  EXPECT_LE(Missing(vf, vc), stats.released_points + vf.size() / 500);
}

TEST(DenseCompactTest, PoseUpdatesMoveCompactedPointsExactly) {
  auto map = MakeMap(CompactOptions());
  AddStrip(
      map.get(), 0, 8, [](int i) { return i; }, [](int i) { return StripPose(i); });
  const GlobalKeyframeId id{kAgent, KeyframeId(1)};
  auto before = map->ExtractKeyframe(id);
  auto camera = map->KeyframeCloud(id);
  ASSERT_TRUE(before.ok() && camera.ok());
  Pose moved = StripPose(1);
  moved.translation() += Eigen::Vector3d(0.3, -0.2, 0.1);
  moved.linear() = moved.linear() * RotationFromAngleAxis(Eigen::Vector3d(0.1, 0.2, -0.1));
  ASSERT_TRUE(map->UpdateKeyframePose(id, moved).ok());
  auto after = map->ExtractKeyframe(id);
  ASSERT_TRUE(after.ok());
  ASSERT_EQ(after->size(), before->size());
  const Pose delta = moved * StripPose(1).inverse();
  for (std::size_t i = 0; i < after->size(); ++i) {
    EXPECT_LT((after->points[i] - delta.cast<float>() * before->points[i]).norm(), 1e-4f);
    EXPECT_LT((after->points[i] - moved.cast<float>() * camera->points[i]).norm(), 1e-5f);
  }
  // Its held voxels follow at Maintain(); nothing is lost in the map.
  map->Maintain();
  EXPECT_EQ(map->ExtractKeyframe(id)->size(), before->size());
}

// Drift: each pass over the strip is 12 cm further along z than the one before; a loop
// correction (then a global BA) puts it back. The corrected map must be a from-scratch build
// with the final poses within the voxel size, and the doubled surface is stored once again.
TEST(DenseCompactTest, AfterALoopCorrectionTheMapIsAFromScratchBuildWithinAVoxel) {
  auto map = MakeMap(CompactOptions());
  const auto image = [](int i) { return i % 10; };
  const auto drifted = [](int i) {
    Pose p = StripPose(i % 10);
    p.translation().z() += 0.12 * (i / 10);
    return p;
  };
  AddStrip(map.get(), 0, 30, image, drifted);
  const std::size_t doubled = map->Stats().compact_points;
  // The loop update: every drifted keyframe to its true pose.
  std::vector<KeyframePose> corrected;
  for (int i = 10; i < 30; ++i) corrected.push_back({{kAgent, KeyframeId(i)}, StripPose(i % 10)});
  ASSERT_TRUE(map->UpdateLoopPoses(corrected).ok());
  // A global BA nudges everything by a millimetre.
  std::vector<KeyframePose> nudged;
  for (int i = 0; i < 30; ++i) {
    Pose p = StripPose(i % 10);
    p.translation().x() += 0.001;
    nudged.push_back({{kAgent, KeyframeId(i)}, p});
  }
  ASSERT_TRUE(map->UpdateGlobalPoses(nudged).ok());
  map->Maintain();
  EXPECT_LT(map->Stats().compact_points, 0.65 * doubled);  // the three layers became one

  auto scratch = MakeMap(TestOptions(3));
  AddStrip(scratch.get(), 0, 30, image, [&](int i) { return nudged[i].T_world_cam; });
  auto ours = map->Extract(DenseSelection::Global());
  auto reference = scratch->Extract(DenseSelection::Global());
  ASSERT_TRUE(ours.ok() && reference.ok());
  EXPECT_GT(Covered(*reference, *ours, kVoxel), 0.99);  // coverage
  EXPECT_GT(Covered(*ours, *reference, kVoxel), 0.99);  // nothing where the reference has nothing
  EXPECT_LT(std::abs(static_cast<double>(ours->size()) - reference->size()),
            0.05 * reference->size());
}

TEST(DenseCompactTest, RemovingAndFusingKeepTheHeldVoxelsRight) {
  auto map = MakeMap(CompactOptions());
  AddStrip(
      map.get(), 0, 10, [](int i) { return i; }, [](int i) { return StripPose(i); });
  // Removing a compacted keyframe frees its voxels: the same view added again is stored again.
  const std::size_t before = map->Stats().points;
  const std::size_t two = map->ExtractKeyframe({kAgent, KeyframeId(2)})->size();
  ASSERT_TRUE(map->RemoveKeyframe({kAgent, KeyframeId(2)}).ok());
  EXPECT_EQ(map->Stats().points, before - two);
  // Fusion: agent 2 saw the same strip in its own map; merged, its later keyframes find the
  // voxels held.
  ASSERT_TRUE(map->SetAgentMap(AgentId(2), MapId(2)).ok());
  for (std::uint32_t i = 0; i < 6; ++i) {
    DenseKeyframe k = PlaneKeyframe(AgentId(2), i, StripPose(i), 32);
    ASSERT_TRUE(map->AddKeyframe(k).ok());
  }
  const std::size_t agent2_alone = map->Stats().points - (before - two);
  ASSERT_TRUE(map->MergeMaps(MapId(2), MapId(1), Pose::Identity()).ok());
  map->Maintain();
  EXPECT_LT(map->Stats().points - (before - two),
            agent2_alone);  // its duplicates of agent 1 are gone
  auto global = map->Extract(DenseSelection::Map(MapId(1)));
  ASSERT_TRUE(global.ok());
  EXPECT_GT(global->size(), 0u);
}

}  // namespace
}  // namespace ccmd
