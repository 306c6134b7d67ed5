#include "libccmd/optim/bundle_adjuster.h"

#include <ceres/ceres.h>

#include <cmath>

#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

class AbortCallback : public ceres::IterationCallback {
 public:
  explicit AbortCallback(const std::atomic<bool>* abort) : abort_(abort) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary&) override {
    return abort_ && abort_->load() ? ceres::SOLVER_ABORT : ceres::SOLVER_CONTINUE;
  }

 private:
  const std::atomic<bool>* abort_;
};

bool IsOutlier(const BaObservation& o, const Intrinsics& k, const Pose& T, const Eigen::Vector3d& p) {
  const double chi2 = ReprojectionChi2(k, T, p, o.uv, o.depth, o.information, o.depth_information);
  return chi2 > (o.depth > 0 ? kChi2Stereo : kChi2Mono) || (T * p).z() <= 0;
}

}  // namespace

BaSummary BundleAdjust(BaProblem* problem, const BaOptions& options) {
  const Stopwatch watch;
  BaSummary summary;
  const std::size_t num_obs = problem->observations.size();
  summary.outlier.assign(num_obs, false);
  if (problem->cameras.empty() || problem->points.empty() || num_obs == 0) {
    summary.message = "empty problem";
    return summary;
  }
  for (const BaCamera& c : problem->cameras) {
    CCMD_CHECK(c.calibration >= 0 && c.calibration < static_cast<int>(problem->calibrations.size()))
        << "camera without calibration";
  }
  std::vector<Eigen::Quaterniond> q(problem->cameras.size());
  std::vector<Eigen::Vector3d> t(problem->cameras.size());
  for (std::size_t c = 0; c < problem->cameras.size(); ++c) {
    q[c] = Eigen::Quaterniond(problem->cameras[c].T_cam_world.linear()).normalized();
    t[c] = problem->cameras[c].T_cam_world.translation();
  }
  AbortCallback abort_callback(options.abort);

  for (int pass = 0; pass < 2; ++pass) {
    const int iterations = pass == 0 ? options.first_iterations : options.second_iterations;
    if (iterations <= 0) continue;
    ceres::Problem::Options problem_options;
    ceres::Problem ceres_problem(problem_options);
    ceres::ParameterBlockOrdering* ordering = new ceres::ParameterBlockOrdering;
    std::vector<bool> camera_added(problem->cameras.size(), false);
    std::vector<bool> point_added(problem->points.size(), false);
    int residuals = 0;
    for (std::size_t i = 0; i < num_obs; ++i) {
      if (summary.outlier[i]) continue;
      const BaObservation& o = problem->observations[i];
      const Intrinsics& intrinsics = problem->calibrations[problem->cameras[o.camera].calibration];
      const ReprojectionResidual residual(intrinsics, o.uv, o.depth, std::sqrt(o.information),
                                          std::sqrt(o.depth_information));
      ceres::CostFunction* cost =
          o.depth > 0
              ? static_cast<ceres::CostFunction*>(
                    new ceres::AutoDiffCostFunction<ReprojectionResidual, 3, 4, 3, 3>(new ReprojectionResidual(residual)))
              : new ceres::AutoDiffCostFunction<ReprojectionResidual, 2, 4, 3, 3>(new ReprojectionResidual(residual));
      ceres::LossFunction* loss =
          pass == 0 ? new ceres::HuberLoss(std::sqrt(o.depth > 0 ? kChi2Stereo : kChi2Mono)) : nullptr;
      double* qc = q[o.camera].coeffs().data();
      double* tc = t[o.camera].data();
      double* p = problem->points[o.point].position.data();
      ceres_problem.AddResidualBlock(cost, loss, qc, tc, p);
      ++residuals;
      if (!camera_added[o.camera]) {
        camera_added[o.camera] = true;
        ceres_problem.SetManifold(qc, new ceres::EigenQuaternionManifold);
        if (problem->cameras[o.camera].fixed) {
          ceres_problem.SetParameterBlockConstant(qc);
          ceres_problem.SetParameterBlockConstant(tc);
        }
        ordering->AddElementToGroup(qc, 1);
        ordering->AddElementToGroup(tc, 1);
      }
      if (!point_added[o.point]) {
        point_added[o.point] = true;
        ordering->AddElementToGroup(p, 0);  // eliminated first (Schur complement)
      }
    }
    if (residuals == 0) {
      delete ordering;
      break;
    }
    ceres::Solver::Options solver;
    solver.linear_solver_type =
        options.solver == BaLinearSolver::kSparseSchur ? ceres::SPARSE_SCHUR : ceres::DENSE_SCHUR;
    if (options.solver == BaLinearSolver::kSparseSchur) {
      solver.sparse_linear_algebra_library_type = ceres::SUITE_SPARSE;
    }
    solver.linear_solver_ordering.reset(ordering);
    solver.max_num_iterations = iterations;
    solver.num_threads = options.threads;
    solver.logging_type = ceres::SILENT;
    solver.callbacks.push_back(&abort_callback);
    ceres::Solver::Summary ceres_summary;
    ceres::Solve(solver, &ceres_problem, &ceres_summary);
    if (pass == 0) summary.initial_cost = ceres_summary.initial_cost;
    summary.final_cost = ceres_summary.final_cost;
    summary.iterations += static_cast<int>(ceres_summary.iterations.size());
    summary.message = ceres_summary.message;
    if (ceres_summary.termination_type == ceres::USER_FAILURE) {
      summary.aborted = true;
    }

    // Classify observations with the current estimate.
    summary.outliers = 0;
    for (std::size_t i = 0; i < num_obs; ++i) {
      const BaObservation& o = problem->observations[i];
      Pose T = Pose::Identity();
      T.linear() = q[o.camera].normalized().toRotationMatrix();
      T.translation() = t[o.camera];
      summary.outlier[i] = IsOutlier(o, problem->calibrations[problem->cameras[o.camera].calibration], T,
                                     problem->points[o.point].position);
      summary.outliers += summary.outlier[i];
    }
    if (summary.aborted) break;
  }
  for (std::size_t c = 0; c < problem->cameras.size(); ++c) {
    if (problem->cameras[c].fixed) continue;
    problem->cameras[c].T_cam_world.linear() = q[c].normalized().toRotationMatrix();
    problem->cameras[c].T_cam_world.translation() = t[c];
  }
  summary.seconds = watch.ElapsedSeconds();
  return summary;
}

}  // namespace ccmd
