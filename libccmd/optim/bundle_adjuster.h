#pragma once

// Bundle adjustment: camera poses and map points refined together from their image
// observations (reprojection + measured depth residuals), robust Huber kernel, outlier
// observations removed between two optimisation passes. Used for the agent's local BA (a
// bounded window of keyframes, the rest fixed: BaLinearSolver::kDenseSchur, the in-tree
// Levenberg-Marquardt of dense_schur_lm.h) and the server's global BA (Ceres, sparse Schur with
// SuiteSparse). A flag can interrupt it between iterations when newer work arrives.

#include <atomic>
#include <string>
#include <vector>

#include "libccmd/geometry/pose.h"
#include "libccmd/optim/reprojection.h"

namespace ccmd {

struct BaCamera {
  Pose T_cam_world = Pose::Identity();
  bool fixed = false;
  int calibration = 0;  // index into BaProblem::calibrations (agents may differ)
};

struct BaPoint {
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // world
};

struct BaObservation {
  int camera = 0;
  int point = 0;
  Eigen::Vector2d uv = Eigen::Vector2d::Zero();
  double depth = 0;                // measured depth (m), <= 0: none
  double information = 1.0;        // 1 / pixel sigma^2 of the keypoint's octave
  double depth_information = 0.0;  // 1 / depth sigma^2 at that depth
};

// A measured relative pose between two cameras (from dense depth alignment):
// T_b_a = T_cam_world[b] * T_cam_world[a]^-1. Its residual is sqrt_information * xi, where
// xi = (rotation vector, translation) of T_b_a_estimate * T_b_a^-1.
struct BaRelativePose {
  int camera_a = 0, camera_b = 0;
  Pose T_b_a = Pose::Identity();
  Eigen::Matrix<double, 6, 6> sqrt_information = Eigen::Matrix<double, 6, 6>::Identity();
};

// D^(1/2) V^T of an information matrix V D V^T, negative eigenvalues (round-off) clamped to
// zero: the sqrt_information of a BaRelativePose. Directions without information stay free.
Eigen::Matrix<double, 6, 6> SqrtInformation(const Eigen::Matrix<double, 6, 6>& information);

struct BaProblem {
  std::vector<Intrinsics> calibrations;  // at least one
  std::vector<BaCamera> cameras;
  std::vector<BaPoint> points;
  std::vector<BaObservation> observations;
  std::vector<BaRelativePose> relative_poses;
};

// kDenseSchur: the in-tree solver, for tens of free cameras (it holds the reduced camera
// system dense); the others: Ceres, for the server's thousands.
enum class BaLinearSolver { kDenseSchur, kSparseSchur, kIterativeSchur };

struct BaOptions {
  int first_iterations = 5;    // robust pass
  int second_iterations = 10;  // after removing outliers
  // A pass stops early when an iteration lowers the cost by less than this fraction (Ceres'
  // function tolerance; its default is 1e-6).
  double function_tolerance = 1e-6;
  // The second pass starts from the trust region the first one ended with.
  bool warm_start = true;
  BaLinearSolver solver = BaLinearSolver::kDenseSchur;
  int threads = 1;  // Ceres solvers only; the in-tree dense solver runs in the calling thread
  // When set and it becomes true, the solver stops after the current iteration.
  const std::atomic<bool>* abort = nullptr;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct BaSummary {
  bool aborted = false;
  int iterations = 0;
  int pass_iterations[2] = {0, 0};  // robust pass, then without outliers
  // Ceres' block sizes ("3,3,3"; "d,d,d": dynamic); "3,3,6 dense" for the in-tree solver.
  std::string schur_structure;
  double initial_cost = 0, final_cost = 0;
  double seconds = 0;
  std::vector<bool> outlier;  // per observation, after the final classification
  int outliers = 0;
  std::string message;
};

// Optimises problem->cameras (non-fixed) and problem->points in place.
BaSummary BundleAdjust(BaProblem* problem, const BaOptions& options);

}  // namespace ccmd
