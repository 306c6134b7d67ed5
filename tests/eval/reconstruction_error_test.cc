#include "libccmd/eval/reconstruction_error.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

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

// Points of a plane through the origin with normal `n`, on a grid of `spacing`.
PointCloud TiltedPlane(const Eigen::Vector3f& n, float spacing, float size) {
  const Eigen::Vector3f u = n.unitOrthogonal(), v = n.cross(u);
  PointCloud c;
  for (float a = -size / 2; a <= size / 2; a += spacing) {
    for (float b = -size / 2; b <= size / 2; b += spacing) c.points.push_back(a * u + b * v);
  }
  return c;
}

TEST(ReconstructionErrorTest, EstimatedNormalsAreThePlanes) {
  const Eigen::Vector3f n = Eigen::Vector3f(1, 2, 3).normalized();
  PointCloud plane = TiltedPlane(n, 0.01f, 0.5f);
  EstimateNormals(&plane);
  ASSERT_EQ(plane.normals.size(), plane.size());
  for (const Eigen::Vector3f& m : plane.normals) EXPECT_NEAR(std::abs(m.dot(n)), 1.0, 1e-4);
}

// Three faces of a box meeting at a corner: points where two faces meet have no plane (zero
// normal), points well inside a face have the face's.
TEST(ReconstructionErrorTest, EdgesGetNoNormal) {
  PointCloud box;
  for (int i = 0; i <= 30; ++i) {
    for (int j = 0; j <= 30; ++j) {
      const float a = i * 0.01f, b = j * 0.01f;
      box.points.emplace_back(a, b, 0);
      if (i > 0) box.points.emplace_back(a, 0, b);
      if (i > 0 && j > 0) box.points.emplace_back(0, a, b);
    }
  }
  EstimateNormals(&box);
  int edge_without = 0, edge_points = 0;
  for (std::size_t k = 0; k < box.size(); ++k) {
    const Eigen::Vector3f& p = box.points[k];
    const int on_faces = (p.x() < 1e-6f) + (p.y() < 1e-6f) + (p.z() < 1e-6f);
    if (on_faces >= 2) {
      ++edge_points;
      edge_without += box.normals[k].squaredNorm() == 0;
    }
    const bool inside_z = p.z() < 1e-6f && p.x() > 0.05f && p.y() > 0.05f;
    if (inside_z) {
      EXPECT_NEAR(std::abs(box.normals[k].z()), 1.0, 1e-4);
    }
  }
  EXPECT_EQ(edge_without, edge_points);
}

// A reference sampled every 1 cm without normals, against a map lying on the same plane half
// a spacing away from the samples: point distances read the sampling (5 mm), the fitted
// planes read the map's true error (none); a map 3 mm off the plane reads 3 mm either way.
TEST(ReconstructionErrorTest, FittedNormalsMeasureTheSurfaceNotTheSampling) {
  const Eigen::Vector3f n = Eigen::Vector3f(0.3f, -0.2f, 1).normalized();
  PointCloud reference = TiltedPlane(n, 0.01f, 1.0f);
  const Eigen::Vector3f along = 0.005f * n.unitOrthogonal();
  PointCloud on_surface = reference, off_surface = reference;
  for (auto& p : on_surface.points) p += along;
  for (auto& p : off_surface.points) p += along + 0.003f * n;
  ASSERT_FALSE(reference.HasNormals());
  auto unfitted = ComputeReconstructionError(reference, on_surface);
  ASSERT_TRUE(unfitted.ok());
  EXPECT_FALSE(unfitted->point_to_plane);
  EXPECT_NEAR(unfitted->mean, 0.005, 1e-4);

  EstimateNormals(&reference);
  auto on = ComputeReconstructionError(reference, on_surface);
  auto off = ComputeReconstructionError(reference, off_surface);
  ASSERT_TRUE(on.ok() && off.ok());
  EXPECT_TRUE(on->point_to_plane);
  EXPECT_LT(on->mean, 1e-4);
  EXPECT_NEAR(on->mean_point_to_point, 0.005, 1e-4);
  EXPECT_NEAR(off->mean, 0.003, 1e-4);

  // Where the nearest sample has no normal (not flat there), the point distance counts.
  for (auto& m : reference.normals) m.setZero();
  auto without = ComputeReconstructionError(reference, on_surface);
  ASSERT_TRUE(without.ok());
  EXPECT_NEAR(without->mean, 0.005, 1e-4);
}

TEST(ReconstructionErrorTest, EmptyCloudsAreErrors) {
  EXPECT_FALSE(ComputeReconstructionError(PointCloud(), Grid()).ok());
  EXPECT_FALSE(ComputeReconstructionError(Grid(), PointCloud()).ok());
}

}  // namespace
}  // namespace ccmd
