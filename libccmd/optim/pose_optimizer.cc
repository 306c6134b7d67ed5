#include "libccmd/optim/pose_optimizer.h"

#include <ceres/jet.h>

#include <cmath>

namespace ccmd {
namespace {

// One camera pose has six degrees of freedom and a frame has a few hundred observations: a
// general solver spends most of its time building and tearing down its problem (it did, at
// 90% of tracking). This is Levenberg-Marquardt on the 6x6 normal equations, with the
// Jacobians of the shared ReprojectionResidual taken by automatic differentiation with
// respect to a left perturbation of the pose: T = (exp(dr), dt) * T0.
using Jet = ceres::Jet<double, 6>;
using Matrix6 = Eigen::Matrix<double, 6, 6>;
using Vector6 = Eigen::Matrix<double, 6, 1>;

struct Linear {
  double cost = 0;  // sum of the (robust) losses
  Matrix6 H = Matrix6::Zero();
  Vector6 g = Vector6::Zero();
};

ReprojectionResidual MakeResidual(const PoseObservation& o, const Intrinsics& k) {
  return ReprojectionResidual(k, o.uv, o.depth, std::sqrt(o.information),
                              std::sqrt(o.depth_information));
}

double Threshold(const PoseObservation& o) { return o.depth > 0 ? kChi2Stereo : kChi2Mono; }

double SquaredResidual(const PoseObservation& o, const Intrinsics& k, const Eigen::Quaterniond& q,
                       const Eigen::Vector3d& t) {
  double r[3] = {0, 0, 0};
  MakeResidual(o, k)(q.coeffs().data(), t.data(), o.point_world.data(), r);
  return r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
}

// The prior's residual at (q, t), for doubles or Jets.
template <typename T>
Eigen::Matrix<T, 6, 1> PriorResidual(const PosePrior& prior, const Eigen::Quaternion<T>& q,
                                     const Eigen::Matrix<T, 3, 1>& t) {
  const Eigen::Quaternion<T> qb(prior.T_b_world.linear().cast<T>());
  const Eigen::Matrix<T, 3, 1> tb = prior.T_b_world.translation().cast<T>();
  Eigen::Matrix<T, 6, 1> r;
  RelativePoseResidual(prior.T_b_a, prior.sqrt_information)(
      q.coeffs().data(), t.data(), qb.coeffs().data(), tb.data(), r.data());
  return r;
}

double Cost(const std::vector<PoseObservation>& observations, const std::vector<bool>& active,
            bool robust, const Intrinsics& k, const PosePrior* prior, const Eigen::Quaterniond& q,
            const Eigen::Vector3d& t) {
  double cost = prior ? PriorResidual(*prior, q, t).squaredNorm() : 0.0;
  for (std::size_t i = 0; i < observations.size(); ++i) {
    if (!active[i]) continue;
    const double s = SquaredResidual(observations[i], k, q, t);
    if (!std::isfinite(s)) continue;  // on the camera centre: no residual either way
    cost += Huber(s, robust ? Threshold(observations[i]) : 0.0).rho;
  }
  return cost;
}

Linear Linearize(const std::vector<PoseObservation>& observations, const std::vector<bool>& active,
                 bool robust, const Intrinsics& k, const PosePrior* prior,
                 const Eigen::Quaterniond& q0, const Eigen::Vector3d& t0) {
  // q = exp(dr) * q0: d(q.vec)/d(dr) = I / 2 at dr = 0, d(q.w)/d(dr) = 0.
  const auto half = [](int i) { return Jet(0.0, i) * 0.5; };
  const Eigen::Quaternion<Jet> dq(Jet(1.0), half(0), half(1), half(2));
  const Eigen::Quaternion<Jet> q = dq * q0.cast<Jet>();
  const Eigen::Matrix<Jet, 3, 1> t(Jet(t0.x(), 3), Jet(t0.y(), 4), Jet(t0.z(), 5));
  Linear linear;
  if (prior) {
    const Eigen::Matrix<Jet, 6, 1> r = PriorResidual(*prior, q, t);
    for (int j = 0; j < 6; ++j) {
      linear.cost += r[j].a * r[j].a;
      linear.H.noalias() += r[j].v * r[j].v.transpose();
      linear.g.noalias() += r[j].a * r[j].v;
    }
  }
  for (std::size_t i = 0; i < observations.size(); ++i) {
    if (!active[i]) continue;
    const PoseObservation& o = observations[i];
    const Eigen::Matrix<Jet, 3, 1> p = o.point_world.cast<Jet>();
    Jet r[3] = {Jet(0.0), Jet(0.0), Jet(0.0)};
    MakeResidual(o, k)(q.coeffs().data(), t.data(), p.data(), r);
    const int n = o.depth > 0 ? 3 : 2;
    double s = 0;
    for (int j = 0; j < n; ++j) s += r[j].a * r[j].a;
    if (!std::isfinite(s)) continue;
    const RobustValue h = Huber(s, robust ? Threshold(o) : 0.0);
    const double weight = h.derivative;
    linear.cost += h.rho;
    for (int j = 0; j < n; ++j) {
      linear.H.noalias() += weight * r[j].v * r[j].v.transpose();
      linear.g.noalias() += weight * r[j].a * r[j].v;
    }
  }
  return linear;
}

void ApplyStep(const Vector6& step, Eigen::Quaterniond* q, Eigen::Vector3d* t) {
  const Eigen::Vector3d dr = step.head<3>();
  const double angle = dr.norm();
  const Eigen::Quaterniond dq = angle > 1e-12
                                    ? Eigen::Quaterniond(Eigen::AngleAxisd(angle, dr / angle))
                                    : Eigen::Quaterniond::Identity();
  *q = (dq * *q).normalized();
  *t += step.tail<3>();
}

// Levenberg-Marquardt from (q, t); stops as Ceres' defaults do, on a relative cost decrease
// under 1e-6 or a step under 1e-8 of the parameters.
void Minimize(const std::vector<PoseObservation>& observations, const std::vector<bool>& active,
              bool robust, const Intrinsics& k, const PosePrior* prior, int max_iterations,
              Eigen::Quaterniond* q, Eigen::Vector3d* t) {
  double lambda = 1e-4;
  Linear linear = Linearize(observations, active, robust, k, prior, *q, *t);
  for (int iteration = 0; iteration < max_iterations; ++iteration) {
    Matrix6 A = linear.H;
    A.diagonal() += lambda * linear.H.diagonal().cwiseMax(1e-9);
    const Vector6 step = A.ldlt().solve(-linear.g);
    if (!step.allFinite()) return;
    Eigen::Quaterniond q_new = *q;
    Eigen::Vector3d t_new = *t;
    ApplyStep(step, &q_new, &t_new);
    const double cost = Cost(observations, active, robust, k, prior, q_new, t_new);
    if (!(cost < linear.cost)) {
      lambda *= 10;
      if (lambda > 1e8) return;
      continue;
    }
    const double decrease = (linear.cost - cost) / std::max(linear.cost, 1e-300);
    *q = q_new;
    *t = t_new;
    lambda = std::max(lambda / 10, 1e-9);
    if (decrease < 1e-6 || step.norm() < 1e-8 * (t->norm() + 1.0)) return;
    linear = Linearize(observations, active, robust, k, prior, *q, *t);
  }
}

}  // namespace

PoseOptimizationResult OptimizePose(const Pose& T_cam_world_initial,
                                    const std::vector<PoseObservation>& observations,
                                    const Intrinsics& intrinsics,
                                    const PoseOptimizationOptions& options,
                                    const PosePrior* prior) {
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
    int used = 0;
    for (bool a : active) used += a;
    if (used < 3) break;
    // Robust in the first rounds; the last rounds fit the inliers exactly (ORB-SLAM drops the
    // kernel once the outliers are out).
    Minimize(observations, active, /*robust=*/round < 2, intrinsics, prior,
             options.iterations_per_round, &q, &t);

    Pose T = Pose::Identity();
    T.linear() = q.normalized().toRotationMatrix();
    T.translation() = t;
    // Reclassify every observation, including earlier outliers.
    int inliers = 0;
    for (std::size_t i = 0; i < observations.size(); ++i) {
      const PoseObservation& o = observations[i];
      const double chi2 = ReprojectionChi2(intrinsics, T, o.point_world, o.uv, o.depth,
                                           o.information, o.depth_information);
      active[i] = chi2 <= Threshold(o);
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
