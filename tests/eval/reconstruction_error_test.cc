#include "libccmd/eval/reconstruction_error.h"

#include <cmath>

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include "libccmd/util/random.h"

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

// Keyframes on a 14 cm path looking at a wall 2 m away, whose map is exact in its own frame
// while the keyframes' centres are 3 mm off (as a fusion's join or a ground truth's own
// error leaves them) and their orientations right. Fitted at the distance the wall is seen
// from, the orientations hold the map's rotation; with 10 cm arms the centres' noise tilts
// the wall.
TEST(ReconstructionErrorTest, MapIsAlignedByWhatItsKeyframesSee) {
  PointCloud wall;
  for (int i = -75; i <= 75; ++i) {
    for (int j = -50; j <= 50; ++j) {
      wall.points.emplace_back(i * 0.02f, j * 0.02f, 2.0f);
      wall.normals.emplace_back(0, 0, 1);
    }
  }
  Pose W = Pose::Identity();  // the map's world in the ground truth's
  W.linear() = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  W.translation() = Eigen::Vector3d(0.5, -0.3, 1.2);
  Rng rng(7);
  Trajectory gt, keyframes;
  for (int k = 0; k < 15; ++k) {
    Pose T = Pose::Identity();
    T.linear() = Eigen::AngleAxisd(0.05 * std::sin(k), Eigen::Vector3d::UnitY()).toRotationMatrix();
    T.translation() = Eigen::Vector3d(0.01 * k, 0, 0);
    gt.push_back({1.0 + 0.1 * k, T});
    Pose est = W.inverse() * T;
    est.translation() += 0.003 * Eigen::Vector3d(rng.Normal(), rng.Normal(), rng.Normal());
    keyframes.push_back({1.0 + 0.1 * k, est});
  }
  PointCloud map = wall;
  for (auto& p : map.points) p = (W.inverse() * p.cast<double>()).cast<float>();

  const double seen_from = MapViewingDistance(map, keyframes);
  EXPECT_GT(seen_from, 2.0);
  EXPECT_LT(seen_from, 2.6);
  auto mean_error = [&](const Similarity3& alignment) {
    PointCloud moved = map;
    for (auto& p : moved.points) p = (alignment * p.cast<double>()).cast<float>();
    auto e = ComputeReconstructionError(wall, moved);
    EXPECT_TRUE(e.ok());
    return e.ok() ? e->mean : 1.0;
  };
  auto aligned = AlignMap(gt, keyframes, map);
  ASSERT_TRUE(aligned.ok());
  EXPECT_LT(mean_error(aligned->alignment), 0.001);
  AteOptions short_arms;
  short_arms.pose_alignment_below_spread_m = 1e9;
  auto tilted = ComputeAte(gt, keyframes, short_arms);
  ASSERT_TRUE(tilted.ok());
  EXPECT_GT(mean_error(tilted->alignment), 0.003);
  // The errors given are the centres', whatever the fit.
  EXPECT_GT(aligned->error.rmse, 0.002);
}

TEST(ReconstructionErrorTest, MapViewingDistanceOfNothingIsZero) {
  EXPECT_EQ(MapViewingDistance(PointCloud{}, Trajectory{{1.0, Pose::Identity()}}), 0.0);
  EXPECT_EQ(MapViewingDistance(Grid(), Trajectory{}), 0.0);
}

// A room's corner (floor and two walls, 2 cm samples with their normals) moved by a known
// degree and two centimetres: ICP puts it back.
TEST(ReconstructionErrorTest, IcpPutsAMovedMapBackOnItsSurface) {
  PointCloud corner;
  for (int i = 0; i < 100; ++i) {
    for (int j = 0; j < 100; ++j) {
      const float a = i * 0.02f, b = j * 0.02f;
      corner.points.emplace_back(a, b, 0.0f);
      corner.normals.emplace_back(0, 0, 1);
      corner.points.emplace_back(a, 0.0f, b);
      corner.normals.emplace_back(0, 1, 0);
      corner.points.emplace_back(0.0f, a, b);
      corner.normals.emplace_back(1, 0, 0);
    }
  }
  Pose moved = Pose::Identity();
  moved.linear() =
      Eigen::AngleAxisd(M_PI / 180, Eigen::Vector3d(1, -2, 0.5).normalized()).toRotationMatrix();
  moved.translation() = Eigen::Vector3d(0.02, -0.01, 0.015);
  PointCloud map = corner;
  map.normals.clear();
  for (auto& p : map.points) p = (moved * p.cast<double>()).cast<float>();

  auto icp = AlignByIcp(corner, map);
  ASSERT_TRUE(icp.ok()) << icp.status().ToString();
  const Pose residual = icp->T_reference_map * moved;
  EXPECT_LT(Eigen::AngleAxisd(residual.linear()).angle(), 0.01 * M_PI / 180);
  EXPECT_LT(residual.translation().norm(), 0.0002);
  EXPECT_NEAR(icp->turn_deg, 1.0, 0.01);
  EXPECT_GT(icp->pairs, 20000u);

  PointCloud bare = corner;
  bare.normals.clear();
  EXPECT_FALSE(AlignByIcp(bare, map).ok());

  // A single wall holds the map only along its normal: the ICP takes the map back onto it and
  // does not slide it along the wall.
  PointCloud wall = Grid();
  PointCloud off = wall;
  for (auto& p : off.points) p += Eigen::Vector3f(0, 0, 0.01f);
  auto onto_wall = AlignByIcp(wall, off);
  ASSERT_TRUE(onto_wall.ok()) << onto_wall.status().ToString();
  EXPECT_NEAR(onto_wall->T_reference_map.translation().z(), -0.01, 1e-5);
  EXPECT_LT(onto_wall->T_reference_map.translation().head<2>().norm(), 1e-5);
  EXPECT_LT(onto_wall->turn_deg, 1e-3);
}

TEST(ReconstructionErrorTest, EmptyCloudsAreErrors) {
  EXPECT_FALSE(ComputeReconstructionError(PointCloud(), Grid()).ok());
  EXPECT_FALSE(ComputeReconstructionError(Grid(), PointCloud()).ok());
}

}  // namespace
}  // namespace ccmd
