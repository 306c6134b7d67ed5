#include "libccmd/dense/backprojection.h"

#include <gtest/gtest.h>

#include <cmath>
#include <set>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/dense/label.h"
#include "tests/support/test_cameras.h"

namespace ccmd {
namespace {

PinholeCamera SmallCamera() {
  PinholeCamera c;
  c.width = 4;
  c.height = 3;
  c.fx = 100.0;
  c.fy = 200.0;
  c.cx = 1.5;
  c.cy = 1.0;
  return c;
}

TEST(BackProjectionTest, PixelsFollowThePinholeModelWithColoursAsRgb) {
  const PinholeCamera camera = SmallCamera();
  cv::Mat depth(3, 4, CV_16UC1, cv::Scalar(0));
  cv::Mat bgr(3, 4, CV_8UC3, cv::Scalar(0, 0, 0));
  depth.at<std::uint16_t>(0, 0) = 2000;  // u=0, v=0 at 2 m
  depth.at<std::uint16_t>(2, 3) = 500;   // u=3, v=2 at 0.5 m
  bgr.at<cv::Vec3b>(0, 0) = cv::Vec3b(10, 20, 30);
  bgr.at<cv::Vec3b>(2, 3) = cv::Vec3b(1, 2, 3);
  auto cloud = BackProjectKeyframe(depth, bgr, camera);
  ASSERT_TRUE(cloud.ok()) << cloud.status().ToString();
  ASSERT_EQ(cloud->size(), 2u);
  // X = Z (u - cx) / fx, Y = Z (v - cy) / fy by hand.
  EXPECT_NEAR(cloud->points[0].x(), 2.0 * (0 - 1.5) / 100.0, 1e-6);  // -0.03
  EXPECT_NEAR(cloud->points[0].y(), 2.0 * (0 - 1.0) / 200.0, 1e-6);  // -0.01
  EXPECT_NEAR(cloud->points[0].z(), 2.0, 1e-6);
  EXPECT_NEAR(cloud->points[1].x(), 0.5 * 1.5 / 100.0, 1e-6);
  EXPECT_NEAR(cloud->points[1].y(), 0.5 * 1.0 / 200.0, 1e-6);
  EXPECT_NEAR(cloud->points[1].z(), 0.5, 1e-6);
  EXPECT_EQ(cloud->colors[0], (std::array<std::uint8_t, 3>{30, 20, 10}));
  EXPECT_EQ(cloud->colors[1], (std::array<std::uint8_t, 3>{3, 2, 1}));
}

// With lens distortion a pixel of the image as recorded is back-projected along its
// undistorted ray: the point lands back on that pixel through the lens model (TUM fr1, whose
// corners move by 9 pixels), and a negative fy (ICL-NUIM) puts rows below the centre at y < 0.
TEST(BackProjectionTest, RecordedPixelsGoAlongTheirUndistortedRays) {
  const PinholeCamera camera = testing::TumFr1Camera();
  const cv::Mat depth(480, 640, CV_16UC1, cv::Scalar(2000));
  const cv::Mat bgr(480, 640, CV_8UC3, cv::Scalar(0, 0, 0));
  BackProjectionOptions options;
  options.max_incidence_deg = 90;
  auto cloud = BackProjectKeyframe(depth, bgr, camera, options);
  ASSERT_TRUE(cloud.ok()) << cloud.status().ToString();
  ASSERT_EQ(cloud->size(), 640u * 480u);
  for (const auto& [u, v] :
       std::vector<std::pair<int, int>>{{0, 0}, {639, 0}, {320, 240}, {17, 401}, {639, 479}}) {
    const Eigen::Vector3f& p = cloud->points[static_cast<std::size_t>(v) * 640 + u];
    EXPECT_FLOAT_EQ(p.z(), 2.0f);
    const Eigen::Vector2d uv = camera.ProjectToImage(p.cast<double>());
    EXPECT_NEAR(uv.x(), u, 0.02) << u << "," << v;
    EXPECT_NEAR(uv.y(), v, 0.02) << u << "," << v;
  }
  // The pinhole model would put the corner pixel's point 3 cm away.
  EXPECT_GT((cloud->points[0].cast<double>() - camera.BackProject(0, 0, 2.0)).norm(), 0.03);

  PinholeCamera flipped = SmallCamera();
  flipped.fy = -flipped.fy;
  cv::Mat small(3, 4, CV_16UC1, cv::Scalar(0));
  small.at<std::uint16_t>(2, 1) = 1000;  // the row below the centre row (cy = 1)
  auto below = BackProjectKeyframe(small, cv::Mat(3, 4, CV_8UC3, cv::Scalar(0, 0, 0)), flipped);
  ASSERT_TRUE(below.ok());
  ASSERT_EQ(below->size(), 1u);
  EXPECT_NEAR(below->points[0].y(), 1.0 * (2 - 1.0) / -200.0, 1e-6);
}

TEST(BackProjectionTest, DepthRangeLimitsAreInclusiveAndZeroIsInvalid) {
  const PinholeCamera camera = SmallCamera();
  cv::Mat depth(3, 4, CV_16UC1, cv::Scalar(0));
  const std::uint16_t values[] = {0, 299, 300, 1000, 3000, 3001, 65535};
  for (int i = 0; i < 7; ++i) depth.at<std::uint16_t>(i / 4, i % 4) = values[i];
  const cv::Mat bgr(3, 4, CV_8UC3, cv::Scalar(0, 0, 0));
  BackProjectionOptions options;
  options.min_depth_m = 0.3;
  options.max_depth_m = 3.0;
  auto cloud = BackProjectKeyframe(depth, bgr, camera, options);
  ASSERT_TRUE(cloud.ok());
  ASSERT_EQ(cloud->size(), 3u);  // 300, 1000 and 3000 mm
  EXPECT_FLOAT_EQ(cloud->points[0].z(), 0.3f);
  EXPECT_FLOAT_EQ(cloud->points[1].z(), 1.0f);
  EXPECT_FLOAT_EQ(cloud->points[2].z(), 3.0f);
}

PinholeCamera WideCamera() {
  PinholeCamera c;
  c.width = 32;
  c.height = 24;
  c.fx = c.fy = 30.0;
  c.cx = 15.5;
  c.cy = 11.5;
  return c;
}

TEST(BackProjectionTest, DropsPixelsSeenMoreObliquelyThanTheIncidenceLimit) {
  // A plane through (0, 0, 1) m with normal (sin 65deg, 0, cos 65deg): across the image the
  // viewing ray meets it between about 38 and 90 degrees from its normal.
  PinholeCamera camera;
  camera.width = 128;
  camera.height = 96;
  camera.fx = camera.fy = 120.0;
  camera.cx = 63.5;
  camera.cy = 47.5;
  const int w = camera.width, h = camera.height;
  const double theta = 65.0 * M_PI / 180.0;
  const Eigen::Vector3d normal(std::sin(theta), 0, std::cos(theta));
  cv::Mat depth(h, w, CV_16UC1, cv::Scalar(0));
  std::vector<double> incidence(w * h, -1);
  for (int v = 0; v < h; ++v) {
    for (int u = 0; u < w; ++u) {
      const Eigen::Vector3d ray = camera.BackProject(u, v, 1.0);  // (x, y, 1)
      const double z = normal.z() / normal.dot(ray);              // n . (z ray) = n . (0, 0, 1)
      if (!(z > 0.3 && z < 9.0)) continue;
      depth.at<std::uint16_t>(v, u) = static_cast<std::uint16_t>(std::lround(z * 1000));
      incidence[v * w + u] = std::acos(std::abs(normal.dot(ray)) / ray.norm()) * 180.0 / M_PI;
    }
  }
  const cv::Mat bgr(h, w, CV_8UC3, cv::Scalar(0, 0, 0));
  BackProjectionOptions options;
  options.max_depth_m = 10.0;
  options.max_incidence_deg = 75.0;
  auto cloud = BackProjectKeyframe(depth, bgr, camera, options);
  ASSERT_TRUE(cloud.ok());
  std::set<int> kept;
  for (const auto& p : cloud->points) {
    const int u = static_cast<int>(std::lround(p.x() / p.z() * camera.fx + camera.cx));
    const int v = static_cast<int>(std::lround(p.y() / p.z() * camera.fy + camera.cy));
    kept.insert(v * w + u);
  }
  int below = 0, above = 0;
  for (int i = 0; i < w * h; ++i) {
    // Within a degree of the limit the finite-difference normal may decide either way.
    if (incidence[i] < 0 || std::abs(incidence[i] - 75.0) < 1.0) continue;
    const bool expect_kept = incidence[i] < 75.0;
    EXPECT_EQ(kept.count(i) == 1, expect_kept)
        << "pixel " << i % w << "," << i / w << " at " << incidence[i] << " degrees";
    (expect_kept ? below : above) += 1;
  }
  EXPECT_GT(below, 2000);
  EXPECT_GT(above, 1000);
  options.max_incidence_deg = 90.0;  // off: every valid pixel
  EXPECT_EQ(BackProjectKeyframe(depth, bgr, camera, options)->size(),
            static_cast<std::size_t>(cv::countNonZero(depth)));
}

TEST(BackProjectionTest, DropsFlyingPixelsButKeepsBothEdgesOfADepthStep) {
  // Frontal planes at 1 m (columns 0-14) and 3 m (16-31) with a column at 2 m between them,
  // as sensors produce at depth edges.
  const PinholeCamera camera = WideCamera();
  cv::Mat depth(24, 32, CV_16UC1, cv::Scalar(3000));
  depth.colRange(0, 15).setTo(1000);
  depth.col(15).setTo(2000);
  const cv::Mat bgr(24, 32, CV_8UC3, cv::Scalar(0, 0, 0));
  BackProjectionOptions options;
  options.max_depth_m = 5.0;
  auto cloud = BackProjectKeyframe(depth, bgr, camera, options);
  ASSERT_TRUE(cloud.ok());
  ASSERT_EQ(cloud->size(), 32u * 24 - 24);
  for (const auto& p : cloud->points) EXPECT_NE(p.z(), 2.0f);
}

TEST(BackProjectionTest, ReadsImagesThatAreViewsOfLargerOnes) {
  const PinholeCamera camera = SmallCamera();
  cv::Mat big_depth(10, 10, CV_16UC1, cv::Scalar(1000));
  cv::Mat big_bgr(10, 10, CV_8UC3, cv::Scalar(5, 6, 7));
  const cv::Rect roi(2, 3, 4, 3);
  auto cloud = BackProjectKeyframe(big_depth(roi), big_bgr(roi), camera);
  ASSERT_TRUE(cloud.ok());
  EXPECT_EQ(cloud->size(), 12u);
}

TEST(BackProjectionTest, BadImagesAndCamerasAreErrors) {
  const PinholeCamera camera = SmallCamera();
  const cv::Mat depth(3, 4, CV_16UC1, cv::Scalar(1000));
  const cv::Mat bgr(3, 4, CV_8UC3, cv::Scalar(0, 0, 0));
  EXPECT_TRUE(BackProjectKeyframe(depth, bgr, camera).ok());
  const auto code = [&](const cv::Mat& d, const cv::Mat& c, const PinholeCamera& cam) {
    return BackProjectKeyframe(d, c, cam).status().code();
  };
  EXPECT_EQ(code(cv::Mat(3, 4, CV_32FC1, cv::Scalar(1)), bgr, camera),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(code(depth, cv::Mat(3, 4, CV_8UC1, cv::Scalar(0)), camera),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(code(cv::Mat(), bgr, camera), StatusCode::kInvalidArgument);
  EXPECT_EQ(code(depth, cv::Mat(), camera), StatusCode::kInvalidArgument);
  // Sizes that disagree with the camera or with each other.
  EXPECT_EQ(code(cv::Mat(6, 8, CV_16UC1, cv::Scalar(1)), cv::Mat(6, 8, CV_8UC3), camera),
            StatusCode::kInvalidArgument);
  EXPECT_EQ(code(depth, cv::Mat(4, 3, CV_8UC3), camera), StatusCode::kInvalidArgument);
  PinholeCamera broken = camera;
  broken.fx = 0;
  EXPECT_EQ(code(depth, bgr, broken), StatusCode::kInvalidArgument);
  BackProjectionOptions no_angle;
  no_angle.max_incidence_deg = 0;
  EXPECT_EQ(BackProjectKeyframe(depth, bgr, camera, no_angle).status().code(),
            StatusCode::kInvalidArgument);
  BackProjectionOptions inverted;
  inverted.min_depth_m = 2.0;
  inverted.max_depth_m = 1.0;
  EXPECT_EQ(BackProjectKeyframe(depth, bgr, camera, inverted).status().code(),
            StatusCode::kInvalidArgument);
}

TEST(LabelTest, PacksAgentAboveKeyframeAndChecksLimits) {
  auto label = EncodeLabel({AgentId(3), KeyframeId(5)});
  ASSERT_TRUE(label.ok());
  EXPECT_EQ(*label, 0x03000005u);
  EXPECT_EQ(*EncodeLabel({AgentId(255), KeyframeId(0xFFFFFF)}), 0xFFFFFFFFu);
  const GlobalKeyframeId back = DecodeLabel(0x02ABCDEFu);
  EXPECT_EQ(back.agent, AgentId(2));
  EXPECT_EQ(back.keyframe, KeyframeId(0xABCDEF));
  EXPECT_EQ(EncodeLabel({AgentId(256), KeyframeId(0)}).status().code(), StatusCode::kOutOfRange);
  EXPECT_EQ(EncodeLabel({AgentId(0), KeyframeId(1u << 24)}).status().code(),
            StatusCode::kOutOfRange);
  // A later keyframe of an agent, or any keyframe of a larger agent, has a larger label.
  EXPECT_LT(*EncodeLabel({AgentId(1), KeyframeId(9)}), *EncodeLabel({AgentId(1), KeyframeId(10)}));
  EXPECT_LT(*EncodeLabel({AgentId(1), KeyframeId(0xFFFFFF)}),
            *EncodeLabel({AgentId(2), KeyframeId(0)}));
}

}  // namespace
}  // namespace ccmd
