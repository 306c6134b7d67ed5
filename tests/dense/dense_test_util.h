#pragma once

// Small RGB-D keyframes with known geometry for the dense map tests: a camera looking at the
// world plane z = 2 m (camera z forward along world z), moving along x, so that consecutive
// keyframes overlap by most of their view.

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <memory>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/dense/dense_map.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/io/ply.h"
#include "libccmd/util/random.h"

namespace ccmd::dense_testing {

inline PinholeCamera TestCamera() {
  PinholeCamera c;
  c.width = 32;
  c.height = 24;
  c.fx = c.fy = 30.0;
  c.cx = 15.5;
  c.cy = 11.5;
  return c;
}

// Camera i of a strip: x = 0.07 i metres, a slight yaw that varies with i.
inline Pose StripPose(int i) {
  Pose pose = Pose::Identity();
  pose.translation() = Eigen::Vector3d(0.07 * i, 0.01 * std::sin(i), 0.0);
  pose.linear() =
      Eigen::AngleAxisd(0.03 * std::cos(1.7 * i), Eigen::Vector3d::UnitY()).toRotationMatrix();
  return pose;
}

// Depth of the plane z = 2 seen from `pose` (millimetres, with +-3 mm seeded jitter), some
// pixels invalid, colours from the pixel position and the seed.
inline DenseKeyframe PlaneKeyframe(AgentId agent, std::uint32_t id, const Pose& pose,
                                   std::uint64_t seed) {
  DenseKeyframe k;
  k.id = {agent, KeyframeId(id)};
  k.T_world_cam = pose;
  k.camera = TestCamera();
  k.depth_mm = cv::Mat(k.camera.height, k.camera.width, CV_16UC1, cv::Scalar(0));
  k.bgr = cv::Mat(k.camera.height, k.camera.width, CV_8UC3, cv::Scalar(0, 0, 0));
  Rng rng(MixSeed(seed, id));
  const Eigen::Matrix3d r = pose.linear();
  for (int v = 0; v < k.camera.height; ++v) {
    for (int u = 0; u < k.camera.width; ++u) {
      const Eigen::Vector3d ray_world = r * k.camera.BackProject(u, v, 1.0);
      const double z = (2.0 - pose.translation().z()) / ray_world.z();  // camera depth
      if (rng.Bernoulli(0.05)) continue;                                // invalid pixel
      k.depth_mm.at<std::uint16_t>(v, u) =
          static_cast<std::uint16_t>(std::lround(z * 1000.0) + rng.UniformInt(-3, 3));
      k.bgr.at<cv::Vec3b>(v, u) =
          cv::Vec3b(static_cast<std::uint8_t>(u * 7), static_cast<std::uint8_t>(v * 9),
                    static_cast<std::uint8_t>(rng.UniformInt(0, 255)));
    }
  }
  return k;
}

// Keyframes are kept whole (no compaction), so that the store follows the window filter's
// definition exactly; dense_compact_test.cc tests what compaction changes.
inline DenseMapOptions TestOptions(int window = 3) {
  DenseMapOptions o;
  o.voxel_size_m = 0.05;
  o.window_keyframes = window;
  o.compact_keyframes = false;
  o.projection.min_depth_m = 0.3;
  o.projection.max_depth_m = 5.0;
  return o;
}

}  // namespace ccmd::dense_testing

namespace ccmd::dense_testing {

// Point for point: same order, same values.
inline ::testing::AssertionResult SameCloud(const PointCloud& a, const PointCloud& b) {
  if (a.size() != b.size()) {
    return ::testing::AssertionFailure() << "sizes differ: " << a.size() << " vs " << b.size();
  }
  for (std::size_t i = 0; i < a.size(); ++i) {
    if (a.points[i] != b.points[i] || a.colors[i] != b.colors[i] || a.labels[i] != b.labels[i]) {
      return ::testing::AssertionFailure() << "point " << i << " differs";
    }
  }
  return ::testing::AssertionSuccess();
}

inline std::unique_ptr<DenseMap> MakeMap(const DenseMapOptions& options) {
  auto map = DenseMap::Create(options);
  return map.ok() ? std::move(map).value() : nullptr;
}

}  // namespace ccmd::dense_testing
