#pragma once

// Pose-only optimisation: refines one camera pose against fixed 3D points from their image
// observations, with a robust kernel and outlier rejection in rounds (an outlier can come back
// when the pose improves), as in ORB-SLAM's tracking.

#include <vector>

#include "libccmd/geometry/pose.h"
#include "libccmd/optim/reprojection.h"

namespace ccmd {

struct PoseObservation {
  Eigen::Vector3d point_world;
  Eigen::Vector2d uv;
  double depth = 0;                // measured depth (m), <= 0: none
  double information = 1.0;        // 1 / pixel sigma^2 of the keypoint's octave
  double depth_information = 0.0;  // 1 / depth sigma^2 at that depth
};

struct PoseOptimizationOptions {
  int rounds = 4;
  int iterations_per_round = 10;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// A measured pose of the camera relative to a fixed one (a dense depth alignment with a
// keyframe), weighed in beside the observations: residual RelativePoseResidual with the
// optimised camera as a and the fixed camera as b.
struct PosePrior {
  Pose T_b_world = Pose::Identity();  // the fixed camera
  Pose T_b_a = Pose::Identity();      // measured
  Eigen::Matrix<double, 6, 6> sqrt_information = Eigen::Matrix<double, 6, 6>::Zero();
};

struct PoseOptimizationResult {
  Pose T_cam_world = Pose::Identity();
  std::vector<bool> inlier;  // per observation
  int inliers = 0;
};

PoseOptimizationResult OptimizePose(const Pose& T_cam_world_initial,
                                    const std::vector<PoseObservation>& observations,
                                    const Intrinsics& intrinsics,
                                    const PoseOptimizationOptions& options = {},
                                    const PosePrior* prior = nullptr);

}  // namespace ccmd
