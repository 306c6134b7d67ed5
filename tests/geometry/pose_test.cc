#include "libccmd/geometry/pose.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

TEST(PoseTest, InterpolationHitsEndsAndMidpoint) {
  const Pose a = PoseFromTranslationQuaternion({0, 0, 0}, Eigen::Quaterniond::Identity());
  const Pose b = PoseFromTranslationQuaternion(
      {2, 0, 0}, Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ())));
  EXPECT_LT(TranslationDistance(InterpolatePose(a, b, 0), a), 1e-12);
  EXPECT_LT(RotationDistance(InterpolatePose(a, b, 1), b), 1e-9);
  const Pose mid = InterpolatePose(a, b, 0.5);
  EXPECT_NEAR(mid.translation().x(), 1.0, 1e-12);
  EXPECT_NEAR(RotationAngle(mid), M_PI / 4, 1e-9);
}

TEST(PoseTest, QuaternionHasNonNegativeW) {
  const Pose p = PoseFromTranslationQuaternion({1, 2, 3}, Eigen::Quaterniond(-0.5, 0.5, 0.5, 0.5));
  const Eigen::Quaterniond q = QuaternionOf(p);
  EXPECT_GE(q.w(), 0);
  EXPECT_LT((q.toRotationMatrix() - p.rotation()).norm(), 1e-12);
}

TEST(PoseTest, LookAtPointsOpticalAxisAtTarget) {
  const Eigen::Vector3d eye(1, 2, 1.5), target(3, -1, 0.5);
  const Pose T_world_cam = LookAt(eye, target, Eigen::Vector3d::UnitZ());
  const Eigen::Vector3d target_cam = T_world_cam.inverse() * target;
  EXPECT_NEAR(target_cam.x(), 0, 1e-12);
  EXPECT_NEAR(target_cam.y(), 0, 1e-12);
  EXPECT_GT(target_cam.z(), 0);
  // World up appears as image up, i.e. negative camera y.
  EXPECT_LT((T_world_cam.linear().transpose() * Eigen::Vector3d::UnitZ()).y(), 0);
}

TEST(PoseTest, OrthonormalizedRepairsDrift) {
  Pose p = Pose::Identity();
  p.linear() = Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitX()).toRotationMatrix();
  p.linear()(0, 1) += 1e-4;
  const Pose fixed = Orthonormalized(p);
  EXPECT_LT((fixed.linear() * fixed.linear().transpose() - Eigen::Matrix3d::Identity()).norm(),
            1e-12);
  EXPECT_LT((fixed.linear() - p.linear()).norm(), 1e-3);
}

// A screw motion taken twice is the motion composed with itself, and half of it twice is the
// whole: what scaling the translation apart from the rotation gets wrong (by 0.19 m here).
TEST(PoseMotionPowerTest, FractionsComposeAlongTheScrew) {
  Pose T = Pose::Identity();
  T.linear() = RotationFromAngleAxis(Eigen::Vector3d(0.1, 0.5, -0.2));
  T.translation() = Eigen::Vector3d(0.3, -0.1, 0.2);
  const Pose twice = MotionPower(T, 2);
  EXPECT_LT((twice.matrix() - (T * T).matrix()).norm(), 1e-12);
  const Pose half = MotionPower(T, 0.5);
  EXPECT_LT(((half * half).matrix() - T.matrix()).norm(), 1e-12);
  EXPECT_LT((MotionPower(T, 1).matrix() - T.matrix()).norm(), 1e-12);
  EXPECT_LT((MotionPower(T, 0).matrix() - Pose::Identity().matrix()).norm(), 1e-15);
  const Pose tiny = MotionPower(T, 1e-9);  // the small-angle series
  EXPECT_LT((MotionPower(tiny, 1e9).matrix() - T.matrix()).norm(), 1e-6);
}

}  // namespace
}  // namespace ccmd
