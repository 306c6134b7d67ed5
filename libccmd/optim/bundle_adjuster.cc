#include "libccmd/optim/bundle_adjuster.h"

#include <ceres/ceres.h>

#include <cmath>

#include <Eigen/Eigenvalues>

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

// Residual of a BaRelativePose; parameters: q_a, t_a, q_b, t_b (T_cam_world of each camera).
struct RelativePoseResidual {
  RelativePoseResidual(const Pose& T_b_a, const Eigen::Matrix<double, 6, 6>& sqrt_information)
      : q_m_(T_b_a.linear()), t_m_(T_b_a.translation()), sqrt_information_(sqrt_information) {}

  template <typename T>
  bool operator()(const T* qa_, const T* ta_, const T* qb_, const T* tb_, T* residual) const {
    using Vec3 = Eigen::Matrix<T, 3, 1>;
    const Eigen::Map<const Eigen::Quaternion<T>> qa(qa_), qb(qb_);
    const Eigen::Map<const Vec3> ta(ta_), tb(tb_);
    // Estimate T_b_a = T_b * T_a^-1, error E = T_b_a * T_measured^-1.
    const Eigen::Quaternion<T> q_ba = qb * qa.conjugate();
    const Vec3 t_ba = tb - q_ba * ta;
    Eigen::Quaternion<T> q_e = q_ba * q_m_.conjugate().cast<T>();
    if (q_e.w() < T(0)) q_e.coeffs() = -q_e.coeffs();
    const Vec3 t_e = t_ba - q_e * t_m_.cast<T>();
    Eigen::Matrix<T, 6, 1> xi;
    xi << T(2) * q_e.vec(), t_e;
    Eigen::Map<Eigen::Matrix<T, 6, 1>> out(residual);
    out = sqrt_information_.cast<T>() * xi;
    return true;
  }

 private:
  Eigen::Quaterniond q_m_;
  Eigen::Vector3d t_m_;
  Eigen::Matrix<double, 6, 6> sqrt_information_;
};

bool IsOutlier(const BaObservation& o, const Intrinsics& k, const Pose& T, const Eigen::Vector3d& p) {
  const double chi2 = ReprojectionChi2(k, T, p, o.uv, o.depth, o.information, o.depth_information);
  return chi2 > (o.depth > 0 ? kChi2Stereo : kChi2Mono) || (T * p).z() <= 0;
}

}  // namespace

Eigen::Matrix<double, 6, 6> SqrtInformation(const Eigen::Matrix<double, 6, 6>& information) {
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> eigen(information);
  const Eigen::Matrix<double, 6, 1> d = eigen.eigenvalues().cwiseMax(0.0).cwiseSqrt();
  return d.asDiagonal() * eigen.eigenvectors().transpose();
}

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
    auto add_camera = [&](int c) {
      if (camera_added[c]) return;
      camera_added[c] = true;
      double* qc = q[c].coeffs().data();
      double* tc = t[c].data();
      ceres_problem.SetManifold(qc, new ceres::EigenQuaternionManifold);
      if (problem->cameras[c].fixed) {
        ceres_problem.SetParameterBlockConstant(qc);
        ceres_problem.SetParameterBlockConstant(tc);
      }
      ordering->AddElementToGroup(qc, 1);
      ordering->AddElementToGroup(tc, 1);
    };
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
      add_camera(o.camera);
      if (!point_added[o.point]) {
        point_added[o.point] = true;
        ordering->AddElementToGroup(p, 0);  // eliminated first (Schur complement)
      }
    }
    for (const BaRelativePose& r : problem->relative_poses) {
      if (problem->cameras[r.camera_a].fixed && problem->cameras[r.camera_b].fixed) continue;
      ceres_problem.AddResidualBlock(
          new ceres::AutoDiffCostFunction<RelativePoseResidual, 6, 4, 3, 4, 3>(
              new RelativePoseResidual(r.T_b_a, r.sqrt_information)),
          nullptr, q[r.camera_a].coeffs().data(), t[r.camera_a].data(), q[r.camera_b].coeffs().data(),
          t[r.camera_b].data());
      add_camera(r.camera_a);
      add_camera(r.camera_b);
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

Status BaOptions::Validate() const {
  if (first_iterations < 0 || second_iterations < 0) {
    return InvalidArgument("bundle adjustment iterations must be >= 0");
  }
  if (first_iterations + second_iterations < 1) {
    return InvalidArgument("bundle adjustment needs at least one iteration");
  }
  if (threads < 1) return InvalidArgument("bundle adjustment threads must be at least 1");
  return Status::Ok();
}

void BaOptions::Describe(OptionsWriter* out) const {
  out->Add("first_iterations", first_iterations);
  out->Add("second_iterations", second_iterations);
  out->Add("solver", solver == BaLinearSolver::kDenseSchur ? "dense_schur" : "sparse_schur");
  out->Add("threads", threads);
}

}  // namespace ccmd
