#include "libccmd/optim/pose_graph.h"

#include <cmath>

#include <ceres/ceres.h>

#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

// Residual of T_a^-1 T_b against the measurement: rotation error as twice the vector part of
// the error quaternion (~ angle-axis for small errors), translation error in a's frame.
struct RelativePoseResidual {
  RelativePoseResidual(const Pose& T_a_b, double w_rotation, double w_translation)
      : q_ab_(Eigen::Quaterniond(T_a_b.linear()).normalized()),
        t_ab_(T_a_b.translation()),
        w_r_(w_rotation),
        w_t_(w_translation) {}

  template <typename T>
  bool operator()(const T* t_a_ptr, const T* q_a_ptr, const T* t_b_ptr, const T* q_b_ptr,
                  T* r) const {
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> t_a(t_a_ptr), t_b(t_b_ptr);
    const Eigen::Map<const Eigen::Quaternion<T>> q_a(q_a_ptr), q_b(q_b_ptr);
    const Eigen::Quaternion<T> q_a_inv = q_a.conjugate();
    const Eigen::Quaternion<T> q_ab_est = q_a_inv * q_b;
    const Eigen::Matrix<T, 3, 1> t_ab_est = q_a_inv * (t_b - t_a);
    const Eigen::Quaternion<T> dq = q_ab_.template cast<T>() * q_ab_est.conjugate();
    Eigen::Map<Eigen::Matrix<T, 6, 1>> residual(r);
    residual.template head<3>() = T(2.0 * w_r_) * dq.vec();
    residual.template tail<3>() = T(w_t_) * (t_ab_est - t_ab_.template cast<T>());
    return true;
  }

 private:
  Eigen::Quaterniond q_ab_;
  Eigen::Vector3d t_ab_;
  double w_r_, w_t_;
};

}  // namespace

StatusOr<PoseGraphSummary> OptimizePoseGraph(std::vector<PoseGraphNode>* nodes,
                                             const std::vector<PoseGraphEdge>& edges,
                                             const PoseGraphOptions& options) {
  const Stopwatch watch;
  const int n = static_cast<int>(nodes->size());
  bool any_fixed = false;
  for (const auto& node : *nodes) any_fixed |= node.fixed;
  if (!any_fixed) return InvalidArgument("pose graph needs a fixed node");
  std::vector<Eigen::Vector3d> t(n);
  std::vector<Eigen::Quaterniond> q(n);
  for (int i = 0; i < n; ++i) {
    t[i] = (*nodes)[i].T_world_node.translation();
    q[i] = Eigen::Quaterniond((*nodes)[i].T_world_node.linear()).normalized();
  }
  ceres::Problem problem;
  std::vector<bool> added(n, false);
  for (const PoseGraphEdge& e : edges) {
    if (e.a < 0 || e.b < 0 || e.a >= n || e.b >= n || e.a == e.b) {
      return InvalidArgument("pose graph edge with a bad node index");
    }
    auto* cost = new ceres::AutoDiffCostFunction<RelativePoseResidual, 6, 3, 4, 3, 4>(
        new RelativePoseResidual(e.T_a_b, e.sqrt_info_rotation, e.sqrt_info_translation));
    ceres::LossFunction* loss =
        options.huber_delta > 0 ? new ceres::HuberLoss(options.huber_delta) : nullptr;
    problem.AddResidualBlock(cost, loss, t[e.a].data(), q[e.a].coeffs().data(), t[e.b].data(),
                             q[e.b].coeffs().data());
    for (int k : {e.a, e.b}) {
      if (added[k]) continue;
      added[k] = true;
      problem.SetManifold(q[k].coeffs().data(), new ceres::EigenQuaternionManifold);
      if ((*nodes)[k].fixed) {
        problem.SetParameterBlockConstant(t[k].data());
        problem.SetParameterBlockConstant(q[k].coeffs().data());
      }
    }
  }
  PoseGraphSummary summary;
  if (edges.empty()) return summary;
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  solver.sparse_linear_algebra_library_type = ceres::SUITE_SPARSE;
  solver.max_num_iterations = options.max_iterations;
  solver.logging_type = ceres::SILENT;
  ceres::Solver::Summary ceres_summary;
  ceres::Solve(solver, &problem, &ceres_summary);
  for (int i = 0; i < n; ++i) {
    if ((*nodes)[i].fixed || !added[i]) continue;
    (*nodes)[i].T_world_node = PoseFromTranslationQuaternion(t[i], q[i]);
  }
  summary.iterations = static_cast<int>(ceres_summary.iterations.size());
  summary.initial_cost = ceres_summary.initial_cost;
  summary.final_cost = ceres_summary.final_cost;
  summary.seconds = watch.ElapsedSeconds();
  return summary;
}

Status PoseGraphOptions::Validate() const {
  if (max_iterations < 1) return InvalidArgument("pose graph max_iterations must be at least 1");
  if (!(huber_delta >= 0) || !std::isfinite(huber_delta)) {
    return InvalidArgument("pose graph huber_delta must be >= 0 (0: none)");
  }
  return Status::Ok();
}

void PoseGraphOptions::Describe(OptionsWriter* out) const {
  out->Add("max_iterations", max_iterations);
  out->Add("huber_delta", huber_delta);
}

}  // namespace ccmd
