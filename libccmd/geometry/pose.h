#pragma once

// Pose conventions used across the project:
//  * A pose is an Eigen::Isometry3d named by the frames it maps between:
//    T_world_cam maps points from camera coordinates into world coordinates
//    (p_world = T_world_cam * p_cam), which is also the camera's pose in the world.
//  * Camera frame: x right, y down, z forward (optical axis), as in OpenCV and TUM.
//  * TUM trajectory lines store T_world_cam as "t tx ty tz qx qy qz qw".

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace ccmd {

using Pose = Eigen::Isometry3d;

// Builds a pose from a translation and a (not necessarily normalised) quaternion.
Pose PoseFromTranslationQuaternion(const Eigen::Vector3d& t, const Eigen::Quaterniond& q);

// Rotation of the pose as a unit quaternion with w >= 0.
Eigen::Quaterniond QuaternionOf(const Pose& pose);

// Projects the linear part onto SO(3) (SVD); repairs drift from repeated products.
Pose Orthonormalized(const Pose& pose);

// Interpolates between a (alpha = 0) and b (alpha = 1): linear in translation,
// spherical-linear in rotation.
Pose InterpolatePose(const Pose& a, const Pose& b, double alpha);

// Angle of the rotation of `pose`, in radians, in [0, pi].
double RotationAngle(const Pose& pose);

// Angle and distance between two poses (of a ^-1 * b).
double RotationDistance(const Pose& a, const Pose& b);
double TranslationDistance(const Pose& a, const Pose& b);

// Rotation from a rotation vector (axis * angle, radians) and back.
Eigen::Matrix3d RotationFromAngleAxis(const Eigen::Vector3d& omega);
Eigen::Vector3d AngleAxisFromRotation(const Eigen::Matrix3d& R);

// `motion` taken `fraction` times as a screw motion (exp(fraction * log(motion)) on SE(3)): the
// same axis, that fraction of its turn and of its advance along the axis, so
// MotionPower(T, 2) = T * T. A motion's translation scaled apart from its rotation would point
// off by half the turn.
Pose MotionPower(const Pose& motion, double fraction);

// Camera looking from `eye` towards `target`, with image "up" as close to `up` as
// possible (camera y points down, so y = -up projected). Returns T_world_cam.
Pose LookAt(const Eigen::Vector3d& eye, const Eigen::Vector3d& target, const Eigen::Vector3d& up);

}  // namespace ccmd
