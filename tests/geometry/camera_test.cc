#include "libccmd/geometry/camera.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <opencv2/calib3d.hpp>

#include "tests/support/test_cameras.h"

namespace ccmd {
namespace {

TEST(CameraTest, BackProjectInvertsProject) {
  PinholeCamera c;
  c.fx = 517.3;
  c.fy = 516.5;
  c.cx = 318.6;
  c.cy = 255.3;
  const Eigen::Vector3d p(0.3, -0.2, 1.7);
  const Eigen::Vector2d uv = c.Project(p);
  EXPECT_LT((c.BackProject(uv.x(), uv.y(), p.z()) - p).norm(), 1e-12);
}

TEST(CameraTest, HalvingKeepsPixelCentresConsistent) {
  PinholeCamera c;  // 640x480, cx 319.5: the exact image centre
  const PinholeCamera half = c.Scaled(0.5);
  EXPECT_EQ(half.width, 320);
  EXPECT_EQ(half.height, 240);
  EXPECT_DOUBLE_EQ(half.fx, c.fx / 2);
  EXPECT_DOUBLE_EQ(half.cx, 159.5);  // still the centre of a 320-wide image
  // A ray through the full-resolution pixel block (2u..2u+1) centre hits half-res pixel u.
  const Eigen::Vector3d p = c.BackProject(100.5, 50.5, 2.0);
  const Eigen::Vector2d uv = half.Project(p);
  EXPECT_NEAR(uv.x(), 50.0, 1e-9);
  EXPECT_NEAR(uv.y(), 25.0, 1e-9);
}

TEST(CameraTest, ValidityChecksExplainTheProblem) {
  PinholeCamera c;
  EXPECT_TRUE(c.Validate().ok());
  c.fy = -480;  // ICL-NUIM's TUM release: allowed
  EXPECT_TRUE(c.Validate().ok());
  c.fx = 0;
  EXPECT_NE(c.Validate().message().find("focal"), std::string::npos);
}

TEST(CameraTest, DistortionFollowsTheBrownConradyFormula) {
  PinholeCamera c;
  c.distortion = {0.1, 0, 0, 0, 0};
  // Radial only: x (1 + k1 r^2).
  EXPECT_NEAR(c.Distort({0.5, 0}).x(), 0.5 * (1 + 0.1 * 0.25), 1e-15);
  c.distortion = {0, 0, 0.01, 0, 0};
  // Tangential p1: x + 2 p1 x y, y + p1 (r^2 + 2 y^2).
  const Eigen::Vector2d d = c.Distort({0.2, 0.3});
  EXPECT_NEAR(d.x(), 0.2 + 2 * 0.01 * 0.2 * 0.3, 1e-15);
  EXPECT_NEAR(d.y(), 0.3 + 0.01 * (0.13 + 2 * 0.09), 1e-15);
}

TEST(CameraTest, DistortionMatchesOpenCv) {
  const PinholeCamera c = testing::TumFr1Camera();
  const cv::Mat K = (cv::Mat_<double>(3, 3) << c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1);
  const cv::Mat dist = (cv::Mat_<double>(1, 5) << c.distortion[0], c.distortion[1], c.distortion[2],
                        c.distortion[3], c.distortion[4]);
  std::vector<cv::Point3d> points;
  for (double x = -0.6; x <= 0.6; x += 0.15) {
    for (double y = -0.45; y <= 0.45; y += 0.15) points.emplace_back(x, y, 1.0);
  }
  std::vector<cv::Point2d> projected;
  cv::projectPoints(points, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, dist, projected);
  for (std::size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector2d raw = c.ProjectToImage({points[i].x, points[i].y, 1.0});
    EXPECT_NEAR(raw.x(), projected[i].x, 1e-9);
    EXPECT_NEAR(raw.y(), projected[i].y, 1e-9);
  }
}

TEST(CameraTest, UndistortInvertsDistortOverTheImage) {
  for (PinholeCamera c : {testing::TumFr1Camera(), [] {
                            PinholeCamera n = testing::TumFr1Camera();
                            n.fy = -n.fy;  // the model works on signed normalised coordinates
                            return n;
                          }()}) {
    ASSERT_TRUE(c.ValidateInvertible().ok());
    double worst = 0;
    for (int v = 0; v < c.height; v += 7) {
      for (int u = 0; u < c.width; u += 7) {
        const Eigen::Vector2d raw(u, v);
        worst = std::max(worst, (c.DistortPixel(c.UndistortPixel(raw)) - raw).norm());
      }
    }
    EXPECT_LT(worst, 1e-8);
    // The corner moves by several pixels: the test above is not trivially the identity.
    EXPECT_GT((c.UndistortPixel({0, 0}) - Eigen::Vector2d(0, 0)).norm(), 3.0);
  }
}

TEST(CameraTest, PixelRaysAreTheUndistortedRays) {
  const PinholeCamera c = testing::TumFr1Camera();
  const PixelRays rays(c);
  auto plain_ray = [&](int u, int v) {
    return Eigen::Vector3d((u - c.cx) / c.fx, (v - c.cy) / c.fy, 1.0);
  };
  ASSERT_EQ(rays.width(), 640);
  ASSERT_EQ(rays.height(), 480);
  double worst = 0;
  for (int v = 0; v < c.height; ++v) {
    for (int u = 0; u < c.width; ++u) {
      // The ray projects back onto the pixel it belongs to.
      const Eigen::Vector2d raw = c.ProjectToImage(rays.Ray(u, v));
      worst = std::max(worst, (raw - Eigen::Vector2d(u, v)).norm());
    }
  }
  EXPECT_LT(worst, 0.02);  // pixels: the table interpolates between exact nodes
  const PixelRays exact(c, /*exact=*/true);
  worst = 0;
  for (int v = 0; v < c.height; v += 3) {
    for (int u = 0; u < c.width; u += 3) {
      worst = std::max(worst, (c.ProjectToImage(exact.Ray(u, v)) - Eigen::Vector2d(u, v)).norm());
    }
  }
  EXPECT_LT(worst, 1e-3);                                            // float rounding only
  EXPECT_GT((rays.Ray(0, 0) - plain_ray(0, 0)).norm() * c.fx, 3.0);  // and it is not the pinhole's
  PinholeCamera plain = c;
  plain.distortion = {0, 0, 0, 0, 0};
  const PixelRays pinhole(plain);
  EXPECT_FLOAT_EQ(pinhole.x_row(7)[100], static_cast<float>((100 - c.cx) / c.fx));
  EXPECT_FLOAT_EQ(pinhole.y_row(7)[100], static_cast<float>((7 - c.cy) / c.fy));
}

TEST(CameraTest, UnusableValuesAreRefusedWithAReason) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  PinholeCamera c = testing::TumFr1Camera();
  EXPECT_TRUE(c.ValidateInvertible().ok()) << c.ValidateInvertible().message();
  c.distortion[1] = nan;
  EXPECT_NE(c.Validate().message().find("distortion"), std::string::npos);
  c = testing::TumFr1Camera();
  c.cx = inf;
  EXPECT_FALSE(c.Validate().ok());
  c = testing::TumFr1Camera();
  c.fy = nan;
  EXPECT_FALSE(c.Validate().ok());
  c = testing::TumFr1Camera();
  c.depth_map_factor = 0;
  EXPECT_FALSE(c.Validate().ok());
  // x (1 - r^2) turns back at r = 1/sqrt(3) = 0.58, inside a 640-wide image with fx 300.
  c = PinholeCamera();
  c.fx = c.fy = 300;
  c.distortion = {-1.0, 0, 0, 0, 0};
  EXPECT_TRUE(c.Validate().ok());
  const Status invertible = c.ValidateInvertible();
  EXPECT_FALSE(invertible.ok());
  EXPECT_NE(invertible.message().find("folds"), std::string::npos) << invertible.message();
}

TEST(CameraTest, ResizingKeepsTheDistortionOfNormalisedCoordinates) {
  const PinholeCamera c = testing::TumFr1Camera();
  const PinholeCamera half = c.Scaled(0.5);
  EXPECT_EQ(half.distortion, c.distortion);
  // The same 3D point lands on the same spot of the (halved) recorded image.
  const Eigen::Vector3d p(0.5, -0.3, 1.2);
  const Eigen::Vector2d full = c.ProjectToImage(p), small = half.ProjectToImage(p);
  EXPECT_NEAR((full.x() + 0.5) / 2 - 0.5, small.x(), 1e-9);
  EXPECT_NEAR((full.y() + 0.5) / 2 - 0.5, small.y(), 1e-9);
}

}  // namespace
}  // namespace ccmd
