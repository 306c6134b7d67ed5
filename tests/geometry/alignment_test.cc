#include "libccmd/geometry/alignment.h"

#include <gtest/gtest.h>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

std::vector<Eigen::Vector3d> RandomPoints(int n, Rng* rng) {
  std::vector<Eigen::Vector3d> points;
  for (int i = 0; i < n; ++i)
    points.emplace_back(rng->Uniform(-2, 2), rng->Uniform(-1, 1), rng->Uniform(0, 3));
  return points;
}

TEST(AlignmentTest, RecoversKnownRigidTransform) {
  Rng rng(3);
  const auto src = RandomPoints(50, &rng);
  const Eigen::Matrix3d R =
      Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, -2, 0.5).normalized()).toRotationMatrix();
  const Eigen::Vector3d t(0.3, -1.2, 2.0);
  std::vector<Eigen::Vector3d> dst;
  for (const auto& p : src) dst.push_back(R * p + t);
  auto result = AlignPoints(src, dst, /*with_scale=*/false);
  ASSERT_TRUE(result.ok());
  EXPECT_LT((result->R - R).norm(), 1e-9);
  EXPECT_LT((result->t - t).norm(), 1e-9);
  EXPECT_DOUBLE_EQ(result->scale, 1.0);
}

TEST(AlignmentTest, RecoversKnownSimilarity) {
  Rng rng(4);
  const auto src = RandomPoints(30, &rng);
  const Eigen::Matrix3d R = Eigen::AngleAxisd(-2.1, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  const Eigen::Vector3d t(5, 0, -1);
  const double s = 2.5;
  std::vector<Eigen::Vector3d> dst;
  for (const auto& p : src) dst.push_back(s * (R * p) + t);
  auto result = AlignPoints(src, dst, /*with_scale=*/true);
  ASSERT_TRUE(result.ok());
  EXPECT_NEAR(result->scale, s, 1e-9);
  EXPECT_LT((result->R - R).norm(), 1e-9);
  EXPECT_LT((result->t - t).norm(), 1e-9);
}

TEST(AlignmentTest, ReflectionIsNeverReturned) {
  // A mirrored copy is best fit by a reflection; Umeyama's sign correction must give a rotation.
  Rng rng(5);
  const auto src = RandomPoints(20, &rng);
  std::vector<Eigen::Vector3d> dst;
  for (const auto& p : src) dst.emplace_back(-p.x(), p.y(), p.z());
  auto result = AlignPoints(src, dst, false);
  ASSERT_TRUE(result.ok());
  EXPECT_NEAR(result->R.determinant(), 1.0, 1e-9);
}

TEST(AlignmentTest, DegenerateInputIsAnError) {
  std::vector<Eigen::Vector3d> line = {{0, 0, 0}, {1, 0, 0}, {2, 0, 0}, {3, 0, 0}};
  EXPECT_FALSE(AlignPoints(line, line, false).ok());
  EXPECT_FALSE(AlignPoints({{0, 0, 0}, {1, 0, 0}}, {{0, 0, 0}, {1, 0, 0}}, false).ok());
  EXPECT_FALSE(AlignPoints(line, {{0, 0, 0}}, false).ok());
}

}  // namespace
}  // namespace ccmd
