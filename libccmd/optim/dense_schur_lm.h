#pragma once

// Levenberg-Marquardt for a bundle adjustment the size of a local BA window (tens of cameras,
// thousands of points): the points are eliminated per point (3x3 blocks), and the reduced
// camera system is solved dense. It works in the 6-dimensional tangent of each camera pose
// (rotation vector applied on the left, translation) and accumulates the normal equations
// straight from each observation's Jacobian, so a local BA pays for its arithmetic and not
// for a general solver's per-residual-block bookkeeping. The step control follows Ceres'
// Levenberg-Marquardt (the damping is the Hessian's diagonal over the trust-region radius,
// the same radius updates, the same stopping tests), so both solvers converge alike;
// BundleAdjust uses this one for BaLinearSolver::kDenseSchur and Ceres for the others.

#include <atomic>
#include <string>
#include <vector>

#include "libccmd/optim/bundle_adjuster.h"

namespace ccmd {

struct LmPassOptions {
  int max_iterations = 10;
  double function_tolerance = 1e-6;  // stop when a step changes the cost by less than this fraction
  double initial_radius = 1e4;       // trust region (1 / damping) at the start; Ceres' default
  bool robust = true;                // Huber kernels on the reprojection residuals
  const std::vector<bool>* skip = nullptr;   // per observation: left out (null: none)
  const std::atomic<bool>* abort = nullptr;  // checked after every iteration
};

struct LmPassSummary {
  int observations = 0;                     // observations in the pass (those not skipped)
  int iterations = 0;                       // steps tried, accepted or not
  double initial_cost = 0, final_cost = 0;  // 1/2 sum of (robustified) squared residuals
  double radius = 0;  // trust region after the last accepted step (0: none accepted)
  bool aborted = false;
  std::string message;
};

// One pass over `problem`. `camera_values` holds 7 values per camera of problem->cameras: the
// rotation of T_cam_world as a unit quaternion (x, y, z, w), then its translation. Free
// cameras there and every observed point in problem->points are updated in place.
LmPassSummary DenseSchurLmPass(BaProblem* problem, double* camera_values,
                               const LmPassOptions& options);

}  // namespace ccmd
