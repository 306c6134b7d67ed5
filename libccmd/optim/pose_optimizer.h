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

struct PoseOptimizationResult {
  Pose T_cam_world = Pose::Identity();
  std::vector<bool> inlier;  // per observation
  int inliers = 0;
};

PoseOptimizationResult OptimizePose(const Pose& T_cam_world_initial,
                                    const std::vector<PoseObservation>& observations,
                                    const Intrinsics& intrinsics,
                                    const PoseOptimizationOptions& options = {});

}  // namespace ccmd
