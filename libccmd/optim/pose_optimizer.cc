#include "libccmd/optim/pose_optimizer.h"

#include <ceres/ceres.h>

#include <cmath>

namespace ccmd {
namespace {

// The reprojection residual with the point held fixed inside the functor.
struct FixedPointResidual {
  FixedPointResidual(const ReprojectionResidual& residual, const Eigen::Vector3d& point)
      : residual_(residual), point_(point) {}
  template <typename T>
  bool operator()(const T* q_cw, const T* t_cw, T* out) const {
    const T p[3] = {T(point_.x()), T(point_.y()), T(point_.z())};
    return residual_(q_cw, t_cw, p, out);
  }
  ReprojectionResidual residual_;
  Eigen::Vector3d point_;
};

}  // namespace

PoseOptimizationResult OptimizePose(const Pose& T_cam_world_initial,
                                    const std::vector<PoseObservation>& observations,
                                    const Intrinsics& intrinsics,
                                    const PoseOptimizationOptions& options) {
  PoseOptimizationResult result;
  result.T_cam_world = T_cam_world_initial;
  result.inlier.assign(observations.size(), true);
  if (observations.size() < 3) {
    result.inliers = 0;
    std::fill(result.inlier.begin(), result.inlier.end(), false);
    return result;
  }
  Eigen::Quaterniond q(T_cam_world_initial.linear());
  q.normalize();
  Eigen::Vector3d t = T_cam_world_initial.translation();
  std::vector<bool> active(observations.size(), true);

  for (int round = 0; round < options.rounds; ++round) {
    ceres::Problem::Options problem_options;
    problem_options.manifold_ownership = ceres::TAKE_OWNERSHIP;
    ceres::Problem problem(problem_options);
    problem.AddParameterBlock(q.coeffs().data(), 4, new ceres::EigenQuaternionManifold);
    problem.AddParameterBlock(t.data(), 3);
    int used = 0;
    for (std::size_t i = 0; i < observations.size(); ++i) {
      if (!active[i]) continue;
      const PoseObservation& o = observations[i];
      const FixedPointResidual residual(
          ReprojectionResidual(intrinsics, o.uv, o.depth, std::sqrt(o.information),
                               std::sqrt(o.depth_information)),
          o.point_world);
      ceres::CostFunction* cost =
          o.depth > 0
              ? static_cast<ceres::CostFunction*>(
                    new ceres::AutoDiffCostFunction<FixedPointResidual, 3, 4, 3>(new FixedPointResidual(residual)))
              : new ceres::AutoDiffCostFunction<FixedPointResidual, 2, 4, 3>(new FixedPointResidual(residual));
      // Robust in the first rounds; the last rounds fit the inliers exactly (ORB-SLAM drops
      // the kernel once the outliers are out).
      ceres::LossFunction* loss =
          round < 2 ? new ceres::HuberLoss(std::sqrt(o.depth > 0 ? kChi2Stereo : kChi2Mono)) : nullptr;
      problem.AddResidualBlock(cost, loss, q.coeffs().data(), t.data());
      ++used;
    }
    if (used < 3) break;
    ceres::Solver::Options solver;
    solver.linear_solver_type = ceres::DENSE_QR;
    solver.max_num_iterations = options.iterations_per_round;
    solver.logging_type = ceres::SILENT;
    solver.num_threads = 1;
    ceres::Solver::Summary summary;
    ceres::Solve(solver, &problem, &summary);

    Pose T = Pose::Identity();
    T.linear() = q.normalized().toRotationMatrix();
    T.translation() = t;
    // Reclassify every observation, including earlier outliers.
    int inliers = 0;
    for (std::size_t i = 0; i < observations.size(); ++i) {
      const PoseObservation& o = observations[i];
      const double chi2 = ReprojectionChi2(intrinsics, T, o.point_world, o.uv, o.depth,
                                           o.information, o.depth_information);
      active[i] = chi2 <= (o.depth > 0 ? kChi2Stereo : kChi2Mono);
      inliers += active[i];
    }
    result.T_cam_world = T;
    result.inliers = inliers;
    if (inliers < 10) break;
  }
  result.inlier = active;
  return result;
}

Status PoseOptimizationOptions::Validate() const {
  if (rounds < 1 || iterations_per_round < 1) {
    return InvalidArgument("pose optimisation needs at least one round and one iteration");
  }
  return Status::Ok();
}

void PoseOptimizationOptions::Describe(OptionsWriter* out) const {
  out->Add("rounds", rounds);
  out->Add("iterations_per_round", iterations_per_round);
}

}  // namespace ccmd
