// Clouds as the browser gets them: one point per viewing voxel, millimetres in the keyframe's
// own frame, colours kept, in a fixed shuffled order, every record readable back.

#include <gtest/gtest.h>

#include <cmath>
#include <map>
#include <set>
#include <tuple>

#include "libccmd/view/view_cloud.h"

namespace ccmd {
namespace {

// A 1 cm grid on a plane 1.5 m in front of the camera (half a centimetre off the 2 cm voxel
// boundaries); each point its own colour.
CameraCloud Grid(int n, double z = 1.5) {
  CameraCloud cloud;
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < n; ++j) {
      cloud.points.emplace_back(-0.495f + 0.01f * i, -0.495f + 0.01f * j, static_cast<float>(z));
      cloud.colors.push_back({static_cast<std::uint8_t>(i), static_cast<std::uint8_t>(j), 7});
    }
  }
  return cloud;
}

const GlobalKeyframeId kId{AgentId(3), KeyframeId(42)};

TEST(ViewCloudTest, OnePointPerVoxelInMillimetresWithItsColour) {
  const CameraCloud cloud = Grid(100);
  ViewCloudOptions options;
  options.voxel_m = 0.02;
  std::string bytes;
  AppendViewCloud(kId, &cloud, options, &bytes);
  EXPECT_EQ(bytes.size() % 4, 0u);
  auto parsed = ParseViewClouds(bytes);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  ASSERT_EQ(parsed->size(), 1u);
  const ViewCloud& c = parsed->front();
  EXPECT_EQ(c.id, kId);
  EXPECT_TRUE(c.found);
  // Independently: the voxels the grid occupies.
  std::set<std::tuple<long, long, long>> voxels;
  std::map<std::tuple<int, int, int>, std::array<std::uint8_t, 3>> by_mm;
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    const Eigen::Vector3f& p = cloud.points[i];
    voxels.insert({std::lround(std::floor(p.x() / 0.02)), std::lround(std::floor(p.y() / 0.02)),
                   std::lround(std::floor(p.z() / 0.02))});
    by_mm[{static_cast<int>(std::lround(p.x() * 1e3)), static_cast<int>(std::lround(p.y() * 1e3)),
           static_cast<int>(std::lround(p.z() * 1e3))}] = cloud.colors[i];
  }
  ASSERT_EQ(c.points_mm.size(), voxels.size());
  std::set<std::tuple<long, long, long>> seen;
  for (std::size_t i = 0; i < c.points_mm.size(); ++i) {
    const auto& p = c.points_mm[i];
    const auto it = by_mm.find({p[0], p[1], p[2]});
    ASSERT_NE(it, by_mm.end()) << "a point that is not in the cloud";
    EXPECT_EQ(it->second, c.colors[i]);
    seen.insert({static_cast<long>(std::floor(p[0] / 20.0)),
                 static_cast<long>(std::floor(p[1] / 20.0)),
                 static_cast<long>(std::floor(p[2] / 20.0))});
  }
  EXPECT_EQ(seen.size(), voxels.size());  // one per voxel
  // Shuffled, not in raster order: the first few points are spread over the plane.
  int increasing = 0;
  for (int i = 1; i < 50; ++i)
    increasing += c.points_mm[i][0] * 1000 + c.points_mm[i][1] >
                  c.points_mm[i - 1][0] * 1000 + c.points_mm[i - 1][1];
  EXPECT_GT(increasing, 10);
  EXPECT_LT(increasing, 40);
  // The same keyframe always gets the same order; another keyframe another one.
  std::string again, other;
  AppendViewCloud(kId, &cloud, options, &again);
  AppendViewCloud({AgentId(3), KeyframeId(43)}, &cloud, options, &other);
  EXPECT_EQ(bytes, again);
  EXPECT_NE(bytes.substr(kViewCloudHeaderBytes), other.substr(kViewCloudHeaderBytes));
}

TEST(ViewCloudTest, AtMostMaxPointsAndOnlyWhatFitsMillimetres) {
  CameraCloud cloud = Grid(50);
  cloud.points.emplace_back(0.0f, 0.0f, 40.0f);  // beyond 32.767 m: left out
  cloud.colors.push_back({1, 2, 3});
  ViewCloudOptions options;
  options.voxel_m = 0.005;
  options.max_points = 100;
  std::string bytes;
  AppendViewCloud(kId, &cloud, options, &bytes);
  auto parsed = ParseViewClouds(bytes);
  ASSERT_TRUE(parsed.ok());
  EXPECT_EQ(parsed->front().points_mm.size(), 100u);
  options.max_points = 100000;
  bytes.clear();
  AppendViewCloud(kId, &cloud, options, &bytes);
  parsed = ParseViewClouds(bytes);
  ASSERT_TRUE(parsed.ok());
  EXPECT_EQ(parsed->front().points_mm.size(), 2500u);
}

TEST(ViewCloudTest, MissingKeyframesAndDamagedBytes) {
  std::string bytes;
  const CameraCloud cloud = Grid(10);
  AppendViewCloud(kId, nullptr, ViewCloudOptions(), &bytes);
  AppendViewCloud(kId, &cloud, ViewCloudOptions(), &bytes);
  auto parsed = ParseViewClouds(bytes);
  ASSERT_TRUE(parsed.ok());
  ASSERT_EQ(parsed->size(), 2u);
  EXPECT_FALSE((*parsed)[0].found);
  EXPECT_TRUE((*parsed)[0].points_mm.empty());
  EXPECT_TRUE((*parsed)[1].found);
  for (std::size_t cut : {std::size_t{5}, kViewCloudHeaderBytes + 3, bytes.size() - 4}) {
    EXPECT_FALSE(ParseViewClouds(bytes.substr(0, cut)).ok()) << cut;
  }
  ViewCloudOptions bad;
  bad.voxel_m = 0;
  EXPECT_FALSE(bad.Validate().ok());
}

}  // namespace
}  // namespace ccmd
