#include "libccmd/geometry/camera.h"

#include <gtest/gtest.h>

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
  std::string why;
  EXPECT_TRUE(c.IsValid(&why));
  c.fy = -480;  // ICL-NUIM's TUM release: allowed
  EXPECT_TRUE(c.IsValid(&why));
  c.fx = 0;
  EXPECT_FALSE(c.IsValid(&why));
  EXPECT_NE(why.find("focal"), std::string::npos);
}

}  // namespace
}  // namespace ccmd
