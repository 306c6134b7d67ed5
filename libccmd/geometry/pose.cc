#include "libccmd/geometry/pose.h"

#include <Eigen/SVD>
#include <algorithm>
#include <cmath>

namespace ccmd {

Pose PoseFromTranslationQuaternion(const Eigen::Vector3d& t, const Eigen::Quaterniond& q) {
  Pose pose = Pose::Identity();
  pose.linear() = q.normalized().toRotationMatrix();
  pose.translation() = t;
  return pose;
}

Eigen::Quaterniond QuaternionOf(const Pose& pose) {
  Eigen::Quaterniond q(pose.rotation());
  q.normalize();
  if (q.w() < 0) q.coeffs() = -q.coeffs();
  return q;
}

Pose Orthonormalized(const Pose& pose) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(pose.linear(), Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d R = svd.matrixU() * svd.matrixV().transpose();
  if (R.determinant() < 0) {
    Eigen::Matrix3d U = svd.matrixU();
    U.col(2) *= -1;
    R = U * svd.matrixV().transpose();
  }
  Pose result = pose;
  result.linear() = R;
  return result;
}

Pose InterpolatePose(const Pose& a, const Pose& b, double alpha) {
  const Eigen::Quaterniond qa = QuaternionOf(a);
  const Eigen::Quaterniond qb = QuaternionOf(b);
  return PoseFromTranslationQuaternion((1.0 - alpha) * a.translation() + alpha * b.translation(),
                                       qa.slerp(alpha, qb));
}

double RotationAngle(const Pose& pose) {
  // atan2 of sin and cos parts stays accurate near 0 and pi, where acos of the trace is not.
  const Eigen::Matrix3d& R = pose.linear();
  const double s =
      0.5 * Eigen::Vector3d(R(2, 1) - R(1, 2), R(0, 2) - R(2, 0), R(1, 0) - R(0, 1)).norm();
  const double c = 0.5 * (R.trace() - 1.0);
  return std::atan2(s, c);
}

double RotationDistance(const Pose& a, const Pose& b) { return RotationAngle(a.inverse() * b); }

double TranslationDistance(const Pose& a, const Pose& b) {
  return (a.translation() - b.translation()).norm();
}

Eigen::Matrix3d RotationFromAngleAxis(const Eigen::Vector3d& omega) {
  const double angle = omega.norm();
  if (angle < 1e-12) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(angle, omega / angle).toRotationMatrix();
}

Eigen::Vector3d AngleAxisFromRotation(const Eigen::Matrix3d& R) {
  const Eigen::AngleAxisd aa(R);
  return aa.axis() * aa.angle();
}

namespace {

// V(omega) of the SE(3) exponential: t = V(omega) * rho for the twist (omega, rho).
Eigen::Matrix3d ExpJacobian(const Eigen::Vector3d& omega) {
  const double theta = omega.norm();
  Eigen::Matrix3d K;
  K << 0, -omega.z(), omega.y(), omega.z(), 0, -omega.x(), -omega.y(), omega.x(), 0;
  double a = 0.5, b = 1.0 / 6;  // series at small angles
  if (theta > 1e-6) {
    a = (1 - std::cos(theta)) / (theta * theta);
    b = (theta - std::sin(theta)) / (theta * theta * theta);
  }
  return Eigen::Matrix3d::Identity() + a * K + b * K * K;
}

}  // namespace

Pose MotionPower(const Pose& motion, double fraction) {
  const Eigen::Vector3d omega = AngleAxisFromRotation(motion.linear());
  const Eigen::Vector3d rho = ExpJacobian(omega).inverse() * motion.translation();
  Pose result = Pose::Identity();
  result.linear() = RotationFromAngleAxis(fraction * omega);
  result.translation() = ExpJacobian(fraction * omega) * (fraction * rho);
  return result;
}

Pose LookAt(const Eigen::Vector3d& eye, const Eigen::Vector3d& target, const Eigen::Vector3d& up) {
  const Eigen::Vector3d z = (target - eye).normalized();
  Eigen::Vector3d x = z.cross(up);
  if (x.norm() < 1e-9) x = z.unitOrthogonal();
  x.normalize();
  const Eigen::Vector3d y = z.cross(x);
  Pose pose = Pose::Identity();
  pose.linear().col(0) = x;
  pose.linear().col(1) = y;
  pose.linear().col(2) = z;
  pose.translation() = eye;
  return pose;
}

}  // namespace ccmd
