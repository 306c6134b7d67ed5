#include "libccmd/eval/reconstruction_error.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

// A 1 m x 1 m grid in the z = 0 plane with 1 cm spacing, normals +z.
PointCloud Grid(const Eigen::Vector3f& offset = Eigen::Vector3f::Zero()) {
  PointCloud c;
  for (int i = 0; i <= 100; ++i) {
    for (int j = 0; j <= 100; ++j) {
      c.points.push_back(Eigen::Vector3f(i * 0.01f, j * 0.01f, 0) + offset);
      c.normals.emplace_back(0, 0, 1);
    }
  }
  return c;
}

TEST(ReconstructionErrorTest, OffsetAlongTheNormalIsMeasuredExactly) {
  const PointCloud ref = Grid();
  const PointCloud rec = Grid({0, 0, 0.005f});
  for (bool plane : {true, false}) {
    ReconstructionOptions o;
    o.point_to_plane = plane;
    auto e = ComputeReconstructionError(ref, rec, o);
    ASSERT_TRUE(e.ok());
    EXPECT_NEAR(e->mean, 0.005, 1e-6);
    EXPECT_NEAR(e->max, 0.005, 1e-6);
    EXPECT_NEAR(e->mean_reverse, 0.005, 1e-6);
    EXPECT_NEAR(e->hausdorff, 0.005, 1e-6);
    EXPECT_DOUBLE_EQ(e->completeness, 1.0);
  }
}

TEST(ReconstructionErrorTest, InPlaneOffsetIsSamplingNotErrorWithNormals) {
  // Shifted half a spacing within the plane: every point is still on the surface.
  const PointCloud ref = Grid();
  const PointCloud rec = Grid({0.005f, 0, 0});
  ReconstructionOptions plane;
  auto with_normals = ComputeReconstructionError(ref, rec, plane);
  ASSERT_TRUE(with_normals.ok());
  EXPECT_TRUE(with_normals->point_to_plane);
  EXPECT_LT(with_normals->mean, 1e-6);
  ReconstructionOptions point;
  point.point_to_plane = false;
  auto without = ComputeReconstructionError(ref, rec, point);
  EXPECT_NEAR(without->mean, 0.005, 1e-6);
}

TEST(ReconstructionErrorTest, MissingPartShowsInCompletenessAndHausdorff) {
  const PointCloud ref = Grid();
  PointCloud rec;
  for (std::size_t i = 0; i < ref.size(); ++i) {
    if (ref.points[i].x() <= 0.5f) rec.points.push_back(ref.points[i]);  // left half only
  }
  auto e = ComputeReconstructionError(ref, rec);
  ASSERT_TRUE(e.ok());
  EXPECT_LT(e->mean, 1e-6);                // what exists is exact
  EXPECT_NEAR(e->max_reverse, 0.5, 1e-5);  // the far edge is 0.5 m from the nearest point
  EXPECT_NEAR(e->hausdorff, 0.5, 1e-5);
  EXPECT_NEAR(e->completeness, 53.0 / 101.0, 0.01);  // columns x <= 0.52 are within 2 cm
}

TEST(ReconstructionErrorTest, EmptyCloudsAreErrors) {
  EXPECT_FALSE(ComputeReconstructionError(PointCloud(), Grid()).ok());
  EXPECT_FALSE(ComputeReconstructionError(Grid(), PointCloud()).ok());
}

}  // namespace
}  // namespace ccmd
