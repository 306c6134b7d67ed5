// The store's structure, labels, and the sliding-window voxel filter against a direct
// implementation of its definition.

#include "libccmd/dense/dense_map.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <set>

#include "libccmd/dense/label.h"
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

using Voxel = std::array<int, 3>;

Voxel VoxelOf(const Eigen::Vector3f& p, double size) {
  const float inverse = static_cast<float>(1.0 / size);
  return {static_cast<int>(std::floor(p.x() * inverse)),
          static_cast<int>(std::floor(p.y() * inverse)),
          static_cast<int>(std::floor(p.z() * inverse))};
}

// The definition, written directly: point i of keyframe k (clouds in id order) is kept iff it
// is the first of k in its voxel and none of keyframes k+1..k+W has a point in that voxel.
PointCloud ReferenceWindowFilter(const std::vector<PointCloud>& clouds, double size, int window) {
  PointCloud kept;
  for (std::size_t k = 0; k < clouds.size(); ++k) {
    std::set<Voxel> later;
    for (std::size_t j = k + 1; j < clouds.size() && j <= k + window; ++j) {
      for (const auto& p : clouds[j].points) later.insert(VoxelOf(p, size));
    }
    std::set<Voxel> seen;
    for (std::size_t i = 0; i < clouds[k].size(); ++i) {
      const Voxel v = VoxelOf(clouds[k].points[i], size);
      if (seen.insert(v).second && later.count(v) == 0) {
        kept.points.push_back(clouds[k].points[i]);
        kept.colors.push_back(clouds[k].colors[i]);
        kept.labels.push_back(clouds[k].labels[i]);
      }
    }
  }
  return kept;
}

std::vector<PointCloud> KeyframeClouds(DenseMap& map, AgentId agent) {
  std::vector<PointCloud> clouds;
  for (const KeyframeId k : map.Keyframes(agent))
    clouds.push_back(*map.ExtractKeyframe({agent, k}));
  return clouds;
}

TEST(DenseMapTest, WorldPointsAreTheBackProjectedPixelsUnderThePose) {
  auto map = MakeMap(TestOptions());
  ASSERT_NE(map, nullptr);
  const DenseKeyframe k = PlaneKeyframe(kAgent1, 7, StripPose(3), 11);
  ASSERT_TRUE(map->AddKeyframe(k).ok());
  auto cloud = map->ExtractKeyframe(k.id);
  ASSERT_TRUE(cloud.ok());
  // Independently, in double precision, in raster order of the valid pixels.
  std::size_t i = 0;
  for (int v = 0; v < k.camera.height; ++v) {
    for (int u = 0; u < k.camera.width; ++u) {
      const std::uint16_t d = k.depth_mm.at<std::uint16_t>(v, u);
      if (d == 0) continue;
      ASSERT_LT(i, cloud->size());
      const Eigen::Vector3d expected = k.T_world_cam * k.camera.BackProject(u, v, d / 1000.0);
      EXPECT_LT((cloud->points[i].cast<double>() - expected).norm(), 1e-5)
          << "pixel " << u << "," << v;
      const cv::Vec3b bgr = k.bgr.at<cv::Vec3b>(v, u);
      EXPECT_EQ(cloud->colors[i], (std::array<std::uint8_t, 3>{bgr[2], bgr[1], bgr[0]}));
      EXPECT_EQ(cloud->labels[i], 0x01000007u);
      ++i;
    }
  }
  EXPECT_EQ(i, cloud->size());
  EXPECT_EQ(i, static_cast<std::size_t>(cv::countNonZero(k.depth_mm)));
}

TEST(DenseMapTest, TreeHoldsMapsAgentsSegmentsAndKeyframes) {
  auto map = MakeMap(TestOptions());
  for (std::uint32_t id : {0u, 5u, 63u, 64u, 200u}) {
    ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent1, id, StripPose(id % 7), 1)).ok());
  }
  ASSERT_TRUE(map->SetAgentMap(kAgent2, MapId(9)).ok());
  ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent2, 0, StripPose(0), 2)).ok());
  const DenseMapStats stats = map->Stats();
  EXPECT_EQ(stats.maps, 2u);
  EXPECT_EQ(stats.agents, 2u);
  EXPECT_EQ(stats.keyframes, 6u);
  EXPECT_EQ(stats.segments, 4u);  // agent 1: ids 0-63, 64-127, 192-255; agent 2: 0-63
  EXPECT_GT(stats.memory_bytes, stats.points * 28);  // camera + map xyz, colour, flag
  EXPECT_EQ(map->Keyframes(kAgent1),
            (std::vector<KeyframeId>{KeyframeId(0), KeyframeId(5), KeyframeId(63), KeyframeId(64),
                                     KeyframeId(200)}));
  EXPECT_EQ(*map->MapOf(kAgent1), MapId(1));  // an agent starts in the map of its own id
  EXPECT_EQ(*map->MapOf(kAgent2), MapId(9));
  EXPECT_EQ(map->Maps(), (std::vector<MapId>{MapId(1), MapId(9)}));
  auto found = map->FindLabel(0x010000C8u);  // agent 1, keyframe 200
  ASSERT_TRUE(found.ok());
  EXPECT_EQ(found->keyframe, KeyframeId(200));
  EXPECT_EQ(map->FindLabel(0x010000C9u).status().code(), StatusCode::kNotFound);
}

TEST(DenseMapTest, LabelsRetrieveExactlyOneKeyframesPoints) {
  auto map = MakeMap(TestOptions());
  for (std::uint32_t id = 0; id < 6; ++id) {
    ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent1, id, StripPose(id), 3)).ok());
    ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent2, id, StripPose(id), 4)).ok());
  }
  auto all = map->Extract(DenseSelection::Global(), DenseFilter::kNone);
  ASSERT_TRUE(all.ok());
  for (const AgentId agent : {kAgent1, kAgent2}) {
    for (std::uint32_t id = 0; id < 6; ++id) {
      const GlobalKeyframeId kf{agent, KeyframeId(id)};
      const std::uint32_t label = *EncodeLabel(kf);
      PointCloud selected;
      for (std::size_t i = 0; i < all->size(); ++i) {
        if (all->labels[i] != label) continue;
        selected.points.push_back(all->points[i]);
        selected.colors.push_back(all->colors[i]);
        selected.labels.push_back(label);
      }
      auto own = map->ExtractKeyframe(kf);
      ASSERT_TRUE(own.ok());
      EXPECT_TRUE(SameCloud(selected, *own)) << "agent " << agent << " keyframe " << id;
      EXPECT_GT(own->size(), 600u);
    }
  }
}

TEST(DenseMapTest, WindowFilterFollowsItsDefinition) {
  for (int window : {0, 1, 3, 20}) {
    auto map = MakeMap(TestOptions(window));
    for (std::uint32_t id = 0; id < 12; ++id) {
      ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent1, id, StripPose(id), 5)).ok());
    }
    auto kept = map->Extract(DenseSelection::Global(), DenseFilter::kWindow);
    ASSERT_TRUE(kept.ok());
    const PointCloud expected = ReferenceWindowFilter(KeyframeClouds(*map, kAgent1), 0.05, window);
    EXPECT_TRUE(SameCloud(*kept, expected)) << "window " << window;
    EXPECT_EQ(map->Stats().kept_points, expected.size());
  }
}

TEST(DenseMapTest, WindowCountsStoredKeyframesAcrossIdGapsAndSegments) {
  auto map = MakeMap(TestOptions(2));
  const std::vector<std::uint32_t> ids = {0, 1, 63, 64, 65, 300, 4000, 4001};
  for (std::size_t i = 0; i < ids.size(); ++i) {
    ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent1, ids[i], StripPose(i), 6)).ok());
  }
  auto kept = map->Extract(DenseSelection::Global(), DenseFilter::kWindow);
  ASSERT_TRUE(kept.ok());
  EXPECT_TRUE(SameCloud(*kept, ReferenceWindowFilter(KeyframeClouds(*map, kAgent1), 0.05, 2)));
}

TEST(DenseMapTest, LargestLabelWinsInTheWindowAndInTheGlobalFilter) {
  auto map = MakeMap(TestOptions(3));
  // Keyframes 4 and 9 of agent 1 are the same image from the same pose.
  ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent1, 4, StripPose(0), 8)).ok());
  DenseKeyframe later = PlaneKeyframe(kAgent1, 4, StripPose(0), 8);
  later.id.keyframe = KeyframeId(9);
  ASSERT_TRUE(map->AddKeyframe(later).ok());
  auto kept = map->Extract(DenseSelection::Global(), DenseFilter::kWindow);
  ASSERT_TRUE(kept.ok());
  ASSERT_GT(kept->size(), 0u);
  for (const std::uint32_t label : kept->labels) EXPECT_EQ(label, 0x01000009u);
  std::set<Voxel> voxels;
  const PointCloud later_points = *map->ExtractKeyframe(later.id);
  for (const auto& p : later_points.points) voxels.insert(VoxelOf(p, 0.05));
  EXPECT_EQ(kept->size(), voxels.size());

  // Agent 2 sees the same: the window does not compare agents, the global filter does.
  DenseKeyframe other = later;
  other.id = {kAgent2, KeyframeId(0)};
  ASSERT_TRUE(map->AddKeyframe(other).ok());
  auto window = map->Extract(DenseSelection::Global(), DenseFilter::kWindow);
  EXPECT_EQ(window->size(), 2 * voxels.size());
  auto global = map->Extract(DenseSelection::Global(), DenseFilter::kGlobal);
  ASSERT_EQ(global->size(), voxels.size());
  for (const std::uint32_t label : global->labels) EXPECT_EQ(label, 0x02000000u);
}

TEST(DenseMapTest, OnlyKeyframesInsideTheWindowCompete) {
  // Keyframes 0 and 2 are the same view; keyframe 1 looks at a far-away part of the plane.
  for (int window : {1, 2}) {
    auto map = MakeMap(TestOptions(window));
    ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent1, 0, StripPose(0), 9)).ok());
    ASSERT_TRUE(map->AddKeyframe(PlaneKeyframe(kAgent1, 1, StripPose(100), 9)).ok());
    DenseKeyframe again = PlaneKeyframe(kAgent1, 0, StripPose(0), 9);
    again.id.keyframe = KeyframeId(2);
    ASSERT_TRUE(map->AddKeyframe(again).ok());
    auto kept = map->Extract(DenseSelection::Global(), DenseFilter::kWindow);
    std::size_t from_first = 0;
    for (const std::uint32_t label : kept->labels) from_first += label == 0x01000000u;
    std::set<Voxel> voxels;
    const PointCloud first = *map->ExtractKeyframe({kAgent1, KeyframeId(0)});
    for (const auto& p : first.points) voxels.insert(VoxelOf(p, 0.05));
    // W = 1: keyframe 2 is outside keyframe 0's window, so 0 keeps one point per voxel.
    EXPECT_EQ(from_first, window == 1 ? voxels.size() : 0u) << "window " << window;
  }
}

TEST(DenseMapTest, InsertionOrderDoesNotMatter) {
  auto in_order = MakeMap(TestOptions(3));
  auto shuffled = MakeMap(TestOptions(3));
  for (std::uint32_t id = 0; id < 10; ++id) {
    ASSERT_TRUE(in_order->AddKeyframe(PlaneKeyframe(kAgent1, id, StripPose(id), 12)).ok());
  }
  for (std::uint32_t id : {4u, 0u, 9u, 2u, 7u, 1u, 8u, 3u, 6u, 5u}) {
    ASSERT_TRUE(shuffled->AddKeyframe(PlaneKeyframe(kAgent1, id, StripPose(id), 12)).ok());
  }
  EXPECT_TRUE(SameCloud(*in_order->Extract(DenseSelection::Global(), DenseFilter::kWindow),
                        *shuffled->Extract(DenseSelection::Global(), DenseFilter::kWindow)));
}

TEST(DenseMapTest, RemovingAKeyframeEqualsNeverAddingIt) {
  auto with = MakeMap(TestOptions(3));
  auto without = MakeMap(TestOptions(3));
  for (std::uint32_t id = 0; id < 10; ++id) {
    ASSERT_TRUE(with->AddKeyframe(PlaneKeyframe(kAgent1, id, StripPose(id), 13)).ok());
    if (id != 6) {
      ASSERT_TRUE(without->AddKeyframe(PlaneKeyframe(kAgent1, id, StripPose(id), 13)).ok());
    }
  }
  ASSERT_TRUE(with->RemoveKeyframe({kAgent1, KeyframeId(6)}).ok());
  EXPECT_TRUE(SameCloud(*with->Extract(DenseSelection::Global(), DenseFilter::kWindow),
                        *without->Extract(DenseSelection::Global(), DenseFilter::kWindow)));
  EXPECT_EQ(with->RemoveKeyframe({kAgent1, KeyframeId(6)}).code(), StatusCode::kNotFound);
}

TEST(DenseMapTest, BadInputIsAnErrorAndChangesNothing) {
  auto map = MakeMap(TestOptions());
  const DenseKeyframe good = PlaneKeyframe(kAgent1, 1, StripPose(0), 14);
  ASSERT_TRUE(map->AddKeyframe(good).ok());
  const auto code = [&](const DenseKeyframe& k) { return map->AddKeyframe(k).code(); };

  DenseKeyframe k = PlaneKeyframe(kAgent1, 2, StripPose(1), 14);
  DenseKeyframe bad = k;
  k.depth_mm.convertTo(bad.depth_mm, CV_32F);
  EXPECT_EQ(code(bad), StatusCode::kInvalidArgument);
  bad = k;
  bad.bgr = cv::Mat(k.bgr.rows, k.bgr.cols, CV_8UC1, cv::Scalar(0));
  EXPECT_EQ(code(bad), StatusCode::kInvalidArgument);
  bad = k;
  bad.camera = k.camera.Scaled(2.0);  // the images are not at the camera's resolution
  EXPECT_EQ(code(bad), StatusCode::kInvalidArgument);
  bad = k;
  bad.depth_mm = cv::Mat();
  EXPECT_EQ(code(bad), StatusCode::kInvalidArgument);
  bad = k;
  bad.id.agent = AgentId(256);
  EXPECT_EQ(code(bad), StatusCode::kOutOfRange);
  bad = k;
  bad.id.keyframe = KeyframeId(1u << 24);
  EXPECT_EQ(code(bad), StatusCode::kOutOfRange);
  bad = k;
  bad.T_world_cam.linear() *= 2.0;  // not rigid
  EXPECT_EQ(code(bad), StatusCode::kInvalidArgument);
  bad = k;
  bad.T_world_cam.translation().x() = std::nan("");
  EXPECT_EQ(code(bad), StatusCode::kInvalidArgument);
  EXPECT_EQ(code(good), StatusCode::kInvalidArgument);  // already present
  CameraCloud mismatched;
  mismatched.points.resize(3);
  EXPECT_EQ(map->AddKeyframeCloud({kAgent1, KeyframeId(3)}, Pose::Identity(), mismatched).code(),
            StatusCode::kInvalidArgument);

  EXPECT_EQ(map->Stats().keyframes, 1u);
  EXPECT_EQ(map->ExtractKeyframe({kAgent1, KeyframeId(2)}).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(map->ExtractKeyframe({kAgent2, KeyframeId(1)}).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(map->Extract(DenseSelection::Agent(kAgent2)).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(map->Extract(DenseSelection::Map(MapId(5))).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(map->KeyframePoseOf({kAgent1, KeyframeId(9)}).status().code(), StatusCode::kNotFound);
  EXPECT_EQ(map->MapOf(kAgent2).status().code(), StatusCode::kNotFound);
  EXPECT_TRUE(map->Keyframes(kAgent2).empty());
}

TEST(DenseMapTest, InvalidOptionsAreRefused) {
  DenseMapOptions o;
  EXPECT_TRUE(DenseMap::Create(o).ok());
  o.voxel_size_m = 0;
  EXPECT_EQ(DenseMap::Create(o).status().code(), StatusCode::kInvalidArgument);
  o = {};
  o.voxel_size_m = std::nan("");
  EXPECT_FALSE(DenseMap::Create(o).ok());
  o = {};
  o.window_keyframes = -1;
  EXPECT_FALSE(DenseMap::Create(o).ok());
  o = {};
  o.projection.max_depth_m = 0.1;  // below min
  EXPECT_FALSE(DenseMap::Create(o).ok());
}

}  // namespace
}  // namespace ccmd
