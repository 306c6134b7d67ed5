#include "libccmd/optim/bundle_adjuster.h"

#include <ceres/ceres.h>

#include <algorithm>
#include <cmath>
#include <deque>
#include <memory>

#include <Eigen/Eigenvalues>

#include "libccmd/optim/dense_schur_lm.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

bool IsOutlier(const BaObservation& o, const Intrinsics& k, const Pose& T,
               const Eigen::Vector3d& p) {
  const double chi2 = ReprojectionChi2(k, T, p, o.uv, o.depth, o.information, o.depth_information);
  return chi2 > (o.depth > 0 ? kChi2Stereo : kChi2Mono) || (T * p).z() <= 0;
}

}  // namespace

Eigen::Matrix<double, 6, 6> SqrtInformation(const Eigen::Matrix<double, 6, 6>& information) {
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> eigen(information);
  const Eigen::Matrix<double, 6, 1> d = eigen.eigenvalues().cwiseMax(0.0).cwiseSqrt();
  return d.asDiagonal() * eigen.eigenvectors().transpose();
}

namespace {

// Every observation has three residual rows; without a measured depth the third is zero.
// Rows of one size (with 3-parameter points and 3-dimensional pose tangents) let Ceres use
// its Schur eliminator compiled for 3x3x3 blocks instead of the dynamic one, which took
// half of a local BA's time. The Jacobians are written out (ReprojectionResidual::Evaluate):
// with automatic differentiation of the same formula a local BA took 5 % longer.
class ReprojectionCost : public ceres::SizedCostFunction<3, 4, 3, 3> {
 public:
  explicit ReprojectionCost(const ReprojectionResidual& r) : residual_(r) {}
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    residual_.Evaluate(parameters[0], parameters[1], parameters[2], residuals,
                       jacobians ? jacobians[0] : nullptr, jacobians ? jacobians[1] : nullptr,
                       jacobians ? jacobians[2] : nullptr);
    return true;
  }

 private:
  ReprojectionResidual residual_;
};

class IterationRecorder : public ceres::IterationCallback {
 public:
  explicit IterationRecorder(const std::atomic<bool>* abort) : abort_(abort) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary& s) override {
    if (s.step_is_successful) radius_ = s.trust_region_radius;
    return abort_ && abort_->load() ? ceres::SOLVER_ABORT : ceres::SOLVER_CONTINUE;
  }
  double radius() const { return radius_; }

 private:
  const std::atomic<bool>* abort_;
  double radius_ = 0;
};

// Camera parameters of a problem, in Ceres' layout: per camera its quaternion (x y z w) and
// then its translation, all cameras in one array. Ceres orders the blocks of an elimination
// group by their addresses, so this keeps the cameras in their order whatever the heap
// looks like; with the quaternions and translations in two arrays, which came first
// depended on where the allocator put them, and an offline run's trajectory changed in the
// last digits with, for instance, the length of a path given on the command line.
struct Parameters {
  explicit Parameters(const BaProblem& problem) : values(7 * problem.cameras.size()) {
    for (std::size_t c = 0; c < problem.cameras.size(); ++c) {
      const int i = static_cast<int>(c);
      q(i) = Eigen::Quaterniond(problem.cameras[c].T_cam_world.linear()).normalized();
      t(i) = problem.cameras[c].T_cam_world.translation();
    }
  }
  Eigen::Map<Eigen::Quaterniond> q(int c) { return Eigen::Map<Eigen::Quaterniond>(&values[7 * c]); }
  Eigen::Map<Eigen::Vector3d> t(int c) { return Eigen::Map<Eigen::Vector3d>(&values[7 * c + 4]); }
  Pose T_cam_world(int c) const {
    Pose T = Pose::Identity();
    T.linear() =
        Eigen::Map<const Eigen::Quaterniond>(&values[7 * c]).normalized().toRotationMatrix();
    T.translation() = Eigen::Map<const Eigen::Vector3d>(&values[7 * c + 4]);
    return T;
  }
  std::vector<double> values;
};

// The Ceres problem of one pass. The first pass has robust kernels; the second is built
// again without them and without the first pass's outliers: removing residual blocks from a
// built problem needs Ceres' fast-removal index, three hash-set entries per observation,
// which with the cost functions' own allocations (now held here, a few large blocks instead
// of three small allocations per observation) took a fifth of a global BA's memory.
class CeresBundle {
 public:
  // `skip`: observations left out (empty: none). `robust`: Huber kernels on reprojections.
  CeresBundle(BaProblem* problem, Parameters* x, const std::vector<bool>& skip, bool robust)
      : ceres_(MakeOptions()), ordering_(std::make_shared<ceres::ParameterBlockOrdering>()) {
    if (robust) {
      huber_mono_ = std::make_unique<ceres::HuberLoss>(std::sqrt(kChi2Mono));
      huber_stereo_ = std::make_unique<ceres::HuberLoss>(std::sqrt(kChi2Stereo));
    }
    std::vector<bool> camera_added(problem->cameras.size(), false);
    std::vector<bool> point_added(problem->points.size(), false);
    auto add_camera = [&](int c) {
      if (camera_added[c]) return;
      camera_added[c] = true;
      ceres_.AddParameterBlock(x->q(c).coeffs().data(), 4, &quaternion_);
      ceres_.AddParameterBlock(x->t(c).data(), 3);
      if (problem->cameras[c].fixed) {
        ceres_.SetParameterBlockConstant(x->q(c).coeffs().data());
        ceres_.SetParameterBlockConstant(x->t(c).data());
      }
      ordering_->AddElementToGroup(x->q(c).coeffs().data(), 1);
      ordering_->AddElementToGroup(x->t(c).data(), 1);
    };
    for (std::size_t i = 0; i < problem->observations.size(); ++i) {
      if (!skip.empty() && skip[i]) continue;
      const BaObservation& o = problem->observations[i];
      const Intrinsics& k = problem->calibrations[problem->cameras[o.camera].calibration];
      double* p = problem->points[o.point].position.data();
      add_camera(o.camera);
      if (!point_added[o.point]) {
        point_added[o.point] = true;
        ordering_->AddElementToGroup(p, 0);  // eliminated first (Schur complement)
      }
      reprojection_costs_.emplace_back(ReprojectionResidual(
          k, o.uv, o.depth, std::sqrt(o.information), std::sqrt(o.depth_information)));
      ceres_.AddResidualBlock(&reprojection_costs_.back(),
                              o.depth > 0 ? huber_stereo_.get() : huber_mono_.get(),
                              x->q(o.camera).coeffs().data(), x->t(o.camera).data(), p);
      ++observations_;
    }
    for (const BaRelativePose& r : problem->relative_poses) {
      if (problem->cameras[r.camera_a].fixed && problem->cameras[r.camera_b].fixed) continue;
      add_camera(r.camera_a);
      add_camera(r.camera_b);
      relative_costs_.emplace_back(new RelativePoseResidual(r.T_b_a, r.sqrt_information));
      ceres_.AddResidualBlock(&relative_costs_.back(), nullptr, x->q(r.camera_a).coeffs().data(),
                              x->t(r.camera_a).data(), x->q(r.camera_b).coeffs().data(),
                              x->t(r.camera_b).data());
    }
  }

  int observations() const { return observations_; }
  ceres::Problem* problem() { return &ceres_; }
  const std::shared_ptr<ceres::ParameterBlockOrdering>& ordering() const { return ordering_; }

 private:
  static ceres::Problem::Options MakeOptions() {
    ceres::Problem::Options o;
    // Everything below outlives the problem (declared before it).
    o.cost_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
    o.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
    o.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
    return o;
  }

  using RelativePoseCost = ceres::AutoDiffCostFunction<RelativePoseResidual, 6, 4, 3, 4, 3>;
  std::unique_ptr<ceres::LossFunction> huber_mono_, huber_stereo_;
  ceres::EigenQuaternionManifold quaternion_;
  std::deque<ReprojectionCost> reprojection_costs_;  // deques: elements never move
  std::deque<RelativePoseCost> relative_costs_;      // each owns its functor
  ceres::Problem ceres_;
  std::shared_ptr<ceres::ParameterBlockOrdering> ordering_;
  int observations_ = 0;
};

ceres::Solver::Options SolverOptions(const BaOptions& options, int iterations) {
  ceres::Solver::Options solver;
  switch (options.solver) {
    case BaLinearSolver::kDenseSchur:
      solver.linear_solver_type = ceres::DENSE_SCHUR;
      break;
    case BaLinearSolver::kSparseSchur:
      solver.linear_solver_type = ceres::SPARSE_SCHUR;
      solver.sparse_linear_algebra_library_type = ceres::SUITE_SPARSE;
      break;
    case BaLinearSolver::kIterativeSchur:
      solver.linear_solver_type = ceres::ITERATIVE_SCHUR;
      solver.preconditioner_type = ceres::SCHUR_JACOBI;
      break;
  }
  solver.max_num_iterations = iterations;
  solver.function_tolerance = options.function_tolerance;
  solver.num_threads = options.threads;
  solver.logging_type = ceres::SILENT;
  return solver;
}

// One pass with Ceres (BaLinearSolver::kSparseSchur and kIterativeSchur: the server's global
// BA, thousands of cameras).
LmPassSummary CeresPass(BaProblem* problem, Parameters* x, const BaOptions& options,
                        const LmPassOptions& lm, std::string* schur_structure) {
  CeresBundle bundle(problem, x, lm.skip ? *lm.skip : std::vector<bool>(), lm.robust);
  ceres::Solver::Options solver = SolverOptions(options, lm.max_iterations);
  solver.linear_solver_ordering = bundle.ordering();
  IterationRecorder recorder(lm.abort);
  solver.callbacks.push_back(&recorder);
  solver.initial_trust_region_radius = lm.initial_radius;
  ceres::Solver::Summary ceres_summary;
  ceres::Solve(solver, bundle.problem(), &ceres_summary);
  LmPassSummary done;
  done.observations = bundle.observations();
  done.iterations =
      std::max(0, static_cast<int>(ceres_summary.iterations.size()) - 1);  // [0]: start
  done.initial_cost = ceres_summary.initial_cost;
  done.final_cost = ceres_summary.final_cost;
  done.radius = recorder.radius();
  done.aborted = ceres_summary.termination_type == ceres::USER_FAILURE;
  done.message = ceres_summary.message;
  *schur_structure = ceres_summary.schur_structure_used;
  return done;
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
  Parameters x(*problem);
  double radius = 0;
  // An observation whose point is not in front of its camera at the start (a point that
  // drifted behind a keyframe, or onto its centre plane, where the residual divides by zero)
  // is an outlier whatever the robust pass does, and one non-finite residual would make the
  // solver refuse every step of that pass: it is left out from the start.
  std::vector<bool> behind(num_obs);
  for (std::size_t i = 0; i < num_obs; ++i) {
    const BaObservation& o = problem->observations[i];
    behind[i] =
        (problem->cameras[o.camera].T_cam_world * problem->points[o.point].position).z() <= 1e-6;
  }

  for (int pass = 0; pass < 2; ++pass) {
    const int iterations = pass == 0 ? options.first_iterations : options.second_iterations;
    if (iterations <= 0) continue;
    // The second pass: no robust kernel, and the outliers of the first pass left out.
    const std::vector<bool>& skip = pass == 0 ? behind : summary.outlier;
    if (std::count(skip.begin(), skip.end(), false) == 0) break;
    LmPassOptions lm;
    lm.max_iterations = iterations;
    lm.function_tolerance = options.function_tolerance;
    // Warm start: the second pass begins with the trust region the first one ended with.
    if (options.warm_start && radius > 0) lm.initial_radius = radius;
    lm.robust = pass == 0;
    lm.skip = &skip;
    lm.abort = options.abort;
    const LmPassSummary done = options.solver == BaLinearSolver::kDenseSchur
                                   ? DenseSchurLmPass(problem, x.values.data(), lm)
                                   : CeresPass(problem, &x, options, lm, &summary.schur_structure);
    if (options.solver == BaLinearSolver::kDenseSchur) summary.schur_structure = "3,3,6 dense";
    if (done.radius > 0) radius = done.radius;
    if (pass == 0) summary.initial_cost = done.initial_cost;
    summary.final_cost = done.final_cost;
    summary.iterations += done.iterations;
    summary.pass_iterations[pass] = done.iterations;
    summary.message = done.message;
    summary.aborted = done.aborted;

    // Classify observations with the current estimate.
    summary.outliers = 0;
    for (std::size_t i = 0; i < num_obs; ++i) {
      const BaObservation& o = problem->observations[i];
      summary.outlier[i] =
          IsOutlier(o, problem->calibrations[problem->cameras[o.camera].calibration],
                    x.T_cam_world(o.camera), problem->points[o.point].position);
      summary.outliers += summary.outlier[i];
    }
    if (summary.aborted) break;
  }
  for (std::size_t c = 0; c < problem->cameras.size(); ++c) {
    if (!problem->cameras[c].fixed)
      problem->cameras[c].T_cam_world = x.T_cam_world(static_cast<int>(c));
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
