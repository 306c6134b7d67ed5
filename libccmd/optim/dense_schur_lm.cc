#include "libccmd/optim/dense_schur_lm.h"

#include <ceres/autodiff_cost_function.h>

#include <algorithm>
#include <cmath>
#include <deque>

#include <Eigen/Cholesky>

namespace ccmd {
namespace {

using Mat36 = Eigen::Matrix<double, 3, 6>;
using Mat63 = Eigen::Matrix<double, 6, 3>;
using Mat66 = Eigen::Matrix<double, 6, 6>;
using RowMajor33 = Eigen::Matrix<double, 3, 3, Eigen::RowMajor>;
using RowMajor34 = Eigen::Matrix<double, 3, 4, Eigen::RowMajor>;
using RowMajor63 = Eigen::Matrix<double, 6, 3, Eigen::RowMajor>;
using RowMajor64 = Eigen::Matrix<double, 6, 4, Eigen::RowMajor>;
using RelativePoseCost = ceres::AutoDiffCostFunction<RelativePoseResidual, 6, 4, 3, 4, 3>;

// Ceres' Levenberg-Marquardt defaults.
constexpr double kMinDiagonal = 1e-6, kMaxDiagonal = 1e32, kMaxRadius = 1e16;
constexpr double kMinRelativeDecrease = 1e-3;
constexpr double kParameterTolerance = 1e-8, kGradientTolerance = 1e-10;

// d (exp(phi) * q) / d phi at phi = 0, for a quaternion q stored x, y, z, w (rows in that
// order): how a rotation applied on the left moves the four coordinates.
Eigen::Matrix<double, 4, 3> LeftPerturbation(const double* q) {
  Eigen::Matrix3d skew_u;
  skew_u << 0, -q[2], q[1], q[2], 0, -q[0], -q[1], q[0], 0;
  Eigen::Matrix<double, 4, 3> m;
  m.topRows<3>() = 0.5 * (q[3] * Eigen::Matrix3d::Identity() - skew_u);
  m.row(3) << -0.5 * q[0], -0.5 * q[1], -0.5 * q[2];
  return m;
}

double Clamp(double d) { return std::clamp(d, kMinDiagonal, kMaxDiagonal); }

class Pass {
 public:
  Pass(BaProblem* problem, double* cameras, const LmPassOptions& options)
      : problem_(*problem), cameras_(cameras), options_(options) {
    const int num_cameras = static_cast<int>(problem_.cameras.size());
    camera_var_.assign(num_cameras, -1);
    std::vector<bool> camera_used(num_cameras, false);
    std::vector<int> point_var(problem_.points.size(), -1);
    auto use_camera = [&](int c) {
      if (camera_used[c]) return;
      camera_used[c] = true;
      if (problem_.cameras[c].fixed) return;
      camera_var_[c] = static_cast<int>(free_cameras_.size());
      free_cameras_.push_back(c);
    };
    for (std::size_t i = 0; i < problem_.observations.size(); ++i) {
      if (options_.skip && (*options_.skip)[i]) continue;
      const BaObservation& o = problem_.observations[i];
      use_camera(o.camera);
      if (point_var[o.point] < 0) {
        point_var[o.point] = static_cast<int>(points_.size());
        points_.push_back(o.point);
        positions_.push_back(problem_.points[o.point].position);
      }
      const Intrinsics& k = problem_.calibrations[problem_.cameras[o.camera].calibration];
      obs_.push_back({o.camera, point_var[o.point], o.depth > 0 ? kChi2Stereo : kChi2Mono});
      residuals_.emplace_back(k, o.uv, o.depth, std::sqrt(o.information),
                              std::sqrt(o.depth_information));
    }
    for (const BaRelativePose& r : problem_.relative_poses) {
      if (problem_.cameras[r.camera_a].fixed && problem_.cameras[r.camera_b].fixed) continue;
      use_camera(r.camera_a);
      use_camera(r.camera_b);
      relatives_.push_back({r.camera_a, r.camera_b});
      relative_costs_.emplace_back(new RelativePoseResidual(r.T_b_a, r.sqrt_information));
    }
    // Each point's observations, in observation order.
    point_begin_.assign(points_.size() + 1, 0);
    for (const Obs& o : obs_) ++point_begin_[o.point + 1];
    for (std::size_t p = 0; p < points_.size(); ++p) point_begin_[p + 1] += point_begin_[p];
    point_obs_.resize(obs_.size());
    std::vector<int> fill(point_begin_.begin(), point_begin_.end() - 1);
    for (std::size_t k = 0; k < obs_.size(); ++k) point_obs_[fill[obs_[k].point]++] = k;

    const int n = 6 * static_cast<int>(free_cameras_.size());
    hessian_.resize(n, n);
    gradient_.resize(n);
    point_hessian_.resize(points_.size());
    point_gradient_.resize(points_.size());
    point_inverse_.resize(points_.size());
    coupling_.resize(obs_.size());
  }

  int observations() const { return static_cast<int>(obs_.size()); }

  LmPassSummary Run() {
    LmPassSummary summary;
    if (obs_.empty() && relatives_.empty()) {
      summary.message = "no residuals";
      return summary;
    }
    double cost = Linearize();
    summary.initial_cost = summary.final_cost = cost;
    double radius = options_.initial_radius, decrease = 2;
    std::vector<double> candidate_cameras(cameras_, cameras_ + 7 * problem_.cameras.size());
    std::vector<Eigen::Vector3d> candidate_points(positions_.size());
    Eigen::VectorXd step_cameras;
    std::vector<Eigen::Vector3d> step_points;
    summary.message = "iteration limit";
    // As Ceres: a step that meets a tolerance ends the pass without being taken or counted.
    while (!Aborted(&summary) && summary.iterations < options_.max_iterations) {
      if (GradientMaxNorm() <= kGradientTolerance) {
        summary.message = "gradient tolerance reached";
        break;
      }
      double model_change = 0;
      if (!Step(radius, &step_cameras, &step_points, &model_change) || !(model_change > 0)) {
        ++summary.iterations;
        radius /= decrease;  // as a rejected step
        decrease *= 2;
        continue;
      }
      if (StepNorm(step_cameras, step_points) <=
          kParameterTolerance * (Norm() + kParameterTolerance)) {
        summary.message = "parameter tolerance reached";
        break;
      }
      Apply(step_cameras, step_points, candidate_cameras.data(), &candidate_points);
      const double new_cost = Cost(candidate_cameras.data(), candidate_points);
      const double change = cost - new_cost;
      if (std::abs(change) <= options_.function_tolerance * cost) {
        summary.message = "function tolerance reached";
        break;
      }
      ++summary.iterations;
      const double relative_decrease = change / model_change;
      if (!(std::isfinite(new_cost) && relative_decrease > kMinRelativeDecrease)) {
        radius /= decrease;
        decrease *= 2;
        continue;
      }
      std::copy(candidate_cameras.begin(), candidate_cameras.end(), cameras_);
      positions_.swap(candidate_points);
      radius = std::min(kMaxRadius,
                        radius / std::max(1.0 / 3, 1 - std::pow(2 * relative_decrease - 1, 3)));
      decrease = 2;
      summary.radius = radius;
      cost = new_cost;
      // The next step needs the Jacobians here; after the last one nothing does.
      if (summary.iterations < options_.max_iterations) cost = Linearize();
    }
    summary.final_cost = cost;
    for (std::size_t p = 0; p < points_.size(); ++p)
      problem_.points[points_[p]].position = positions_[p];
    return summary;
  }

 private:
  struct Obs {
    int camera;     // index into problem.cameras
    int point;      // index into points_
    double robust;  // Huber threshold on the squared normalised residual
  };

  bool Aborted(LmPassSummary* summary) const {
    if (options_.abort && options_.abort->load()) summary->aborted = true;
    if (summary->aborted) summary->message = "aborted";
    return summary->aborted;
  }

  const double* q(const double* cameras, int c) const { return cameras + 7 * c; }
  const double* t(const double* cameras, int c) const { return cameras + 7 * c + 4; }

  // 1/2 the sum of (robustified) squared residuals with the given parameters.
  double Cost(const double* cameras, const std::vector<Eigen::Vector3d>& points) const {
    double cost = 0;
    for (std::size_t k = 0; k < obs_.size(); ++k) {
      const Obs& o = obs_[k];
      Eigen::Vector3d r;
      residuals_[k].Evaluate(q(cameras, o.camera), t(cameras, o.camera), points[o.point].data(),
                             r.data(), nullptr, nullptr, nullptr);
      const double s = r.squaredNorm();
      cost += 0.5 * (options_.robust ? Huber(s, o.robust).rho : s);
    }
    for (std::size_t i = 0; i < relatives_.size(); ++i) {
      const auto [a, b] = relatives_[i];
      const double* parameters[4] = {q(cameras, a), t(cameras, a), q(cameras, b), t(cameras, b)};
      Eigen::Matrix<double, 6, 1> r;
      relative_costs_[i].Evaluate(parameters, r.data(), nullptr);
      cost += 0.5 * r.squaredNorm();
    }
    return cost;
  }

  // The normal equations at the current estimate: the cameras' block (hessian_, gradient_),
  // each point's 3x3 block and gradient, and each observation's camera-point block. Returns
  // the cost there.
  double Linearize() {
    hessian_.setZero();
    gradient_.setZero();
    for (std::size_t p = 0; p < points_.size(); ++p) {
      point_hessian_[p].setZero();
      point_gradient_[p].setZero();
    }
    std::vector<Eigen::Matrix<double, 4, 3>> perturbation(free_cameras_.size());
    for (std::size_t v = 0; v < free_cameras_.size(); ++v)
      perturbation[v] = LeftPerturbation(q(cameras_, free_cameras_[v]));
    double cost = 0;
    for (std::size_t k = 0; k < obs_.size(); ++k) {
      const Obs& o = obs_[k];
      const int v = camera_var_[o.camera];
      Eigen::Vector3d r;
      RowMajor34 J_q;
      RowMajor33 J_t, J_p;
      residuals_[k].Evaluate(q(cameras_, o.camera), t(cameras_, o.camera),
                             positions_[o.point].data(), r.data(), v >= 0 ? J_q.data() : nullptr,
                             v >= 0 ? J_t.data() : nullptr, J_p.data());
      const double s = r.squaredNorm();
      double scale = 1;
      if (options_.robust) {
        // Huber's second derivative is never > 0, so Ceres' corrector scales residual and
        // Jacobian by sqrt(rho').
        const RobustValue h = Huber(s, o.robust);
        cost += 0.5 * h.rho;
        scale = std::sqrt(h.derivative);
      } else {
        cost += 0.5 * s;
      }
      r *= scale;
      const Eigen::Matrix3d Jp = scale * J_p;
      point_hessian_[o.point].noalias() += Jp.transpose() * Jp;
      point_gradient_[o.point].noalias() += Jp.transpose() * r;
      if (v < 0) continue;
      Mat36 Jc;
      Jc.leftCols<3>().noalias() = scale * J_q * perturbation[v];
      Jc.rightCols<3>() = scale * J_t;
      hessian_.block<6, 6>(6 * v, 6 * v).noalias() += Jc.transpose() * Jc;
      gradient_.segment<6>(6 * v).noalias() += Jc.transpose() * r;
      coupling_[k].noalias() = Jc.transpose() * Jp;
    }
    for (std::size_t i = 0; i < relatives_.size(); ++i) {
      const auto [a, b] = relatives_[i];
      const double* parameters[4] = {q(cameras_, a), t(cameras_, a), q(cameras_, b),
                                     t(cameras_, b)};
      Eigen::Matrix<double, 6, 1> r;
      RowMajor64 J_qa, J_qb;
      RowMajor63 J_ta, J_tb;
      double* jacobians[4] = {J_qa.data(), J_ta.data(), J_qb.data(), J_tb.data()};
      relative_costs_[i].Evaluate(parameters, r.data(), jacobians);
      cost += 0.5 * r.squaredNorm();
      const int vs[2] = {camera_var_[a], camera_var_[b]};
      Mat66 J[2];
      if (vs[0] >= 0) J[0] << J_qa * LeftPerturbation(parameters[0]), J_ta;
      if (vs[1] >= 0) J[1] << J_qb * LeftPerturbation(parameters[2]), J_tb;
      for (int x = 0; x < 2; ++x) {
        if (vs[x] < 0) continue;
        gradient_.segment<6>(6 * vs[x]).noalias() += J[x].transpose() * r;
        for (int y = 0; y < 2; ++y) {
          if (vs[y] >= vs[x]) hessian_.block<6, 6>(6 * vs[x], 6 * vs[y]) += J[x].transpose() * J[y];
        }
      }
    }
    return cost;
  }

  // The Levenberg-Marquardt step for the trust region `radius`: the damped normal equations
  // with the points eliminated, solved for the cameras, then each point from them. False when
  // the damped system is not positive definite. `model_change`: the cost decrease the
  // linearisation predicts for the step.
  bool Step(double radius, Eigen::VectorXd* step_cameras, std::vector<Eigen::Vector3d>* step_points,
            double* model_change) {
    // Only the upper triangle of the reduced system is filled and read.
    Eigen::MatrixXd reduced = hessian_;
    Eigen::VectorXd rhs = gradient_;
    double damping_energy = 0;  // step' D step / radius, D the damping diagonal
    for (int i = 0; i < reduced.rows(); ++i) reduced(i, i) += Clamp(hessian_(i, i)) / radius;
    for (std::size_t p = 0; p < points_.size(); ++p) {
      Eigen::Matrix3d damped = point_hessian_[p];
      for (int i = 0; i < 3; ++i) damped(i, i) += Clamp(point_hessian_[p](i, i)) / radius;
      const Eigen::LLT<Eigen::Matrix3d> llt(damped);
      if (llt.info() != Eigen::Success) return false;
      point_inverse_[p] = llt.solve(Eigen::Matrix3d::Identity());
      for (int a = point_begin_[p]; a < point_begin_[p + 1]; ++a) {
        const int ka = point_obs_[a];
        const int va = camera_var_[obs_[ka].camera];
        if (va < 0) continue;
        const Mat63 Y = coupling_[ka] * point_inverse_[p];
        rhs.segment<6>(6 * va).noalias() -= Y * point_gradient_[p];
        for (int b = a; b < point_begin_[p + 1]; ++b) {
          const int kb = point_obs_[b];
          const int vb = camera_var_[obs_[kb].camera];
          if (vb < 0) continue;
          const Mat66 block = Y * coupling_[kb].transpose();
          if (va < vb) {
            reduced.block<6, 6>(6 * va, 6 * vb) -= block;
          } else if (va > vb) {
            reduced.block<6, 6>(6 * vb, 6 * va) -= block.transpose();
          } else if (a == b) {
            reduced.block<6, 6>(6 * va, 6 * va) -= block;
          } else {  // one camera observing the point twice
            reduced.block<6, 6>(6 * va, 6 * va) -= block + block.transpose();
          }
        }
      }
    }
    const Eigen::LLT<Eigen::MatrixXd, Eigen::Upper> llt(reduced);
    if (llt.info() != Eigen::Success) return false;
    *step_cameras = -llt.solve(rhs);
    if (!step_cameras->allFinite()) return false;
    double gradient_dot_step = gradient_.dot(*step_cameras);
    for (int i = 0; i < step_cameras->size(); ++i)
      damping_energy += Clamp(hessian_(i, i)) / radius * (*step_cameras)(i) * (*step_cameras)(i);
    step_points->resize(points_.size());
    for (std::size_t p = 0; p < points_.size(); ++p) {
      Eigen::Vector3d g = point_gradient_[p];
      for (int a = point_begin_[p]; a < point_begin_[p + 1]; ++a) {
        const int k = point_obs_[a];
        const int v = camera_var_[obs_[k].camera];
        if (v >= 0) g.noalias() += coupling_[k].transpose() * step_cameras->segment<6>(6 * v);
      }
      const Eigen::Vector3d dp = -point_inverse_[p] * g;
      (*step_points)[p] = dp;
      gradient_dot_step += point_gradient_[p].dot(dp);
      for (int i = 0; i < 3; ++i)
        damping_energy += Clamp(point_hessian_[p](i, i)) / radius * dp(i) * dp(i);
    }
    // With (H + D / radius) step = -g: cost - model(step) = -g'step - step'H step / 2
    // = (-g'step + step'D step / radius) / 2.
    *model_change = 0.5 * (damping_energy - gradient_dot_step);
    return std::isfinite(*model_change);
  }

  void Apply(const Eigen::VectorXd& step_cameras, const std::vector<Eigen::Vector3d>& step_points,
             double* cameras, std::vector<Eigen::Vector3d>* points) const {
    for (std::size_t v = 0; v < free_cameras_.size(); ++v) {
      const int c = free_cameras_[v];
      const Eigen::Vector3d phi = step_cameras.segment<3>(6 * v);
      const double angle = phi.norm();
      const Eigen::Quaterniond dq =
          angle > 1e-12 ? Eigen::Quaterniond(Eigen::AngleAxisd(angle, phi / angle))
                        : Eigen::Quaterniond(1, 0.5 * phi.x(), 0.5 * phi.y(), 0.5 * phi.z());
      Eigen::Map<Eigen::Quaterniond>(cameras + 7 * c) =
          (dq * Eigen::Map<const Eigen::Quaterniond>(cameras_ + 7 * c)).normalized();
      Eigen::Map<Eigen::Vector3d>(cameras + 7 * c + 4) =
          Eigen::Map<const Eigen::Vector3d>(cameras_ + 7 * c + 4) +
          step_cameras.segment<3>(6 * v + 3);
    }
    for (std::size_t p = 0; p < points_.size(); ++p) (*points)[p] = positions_[p] + step_points[p];
  }

  double GradientMaxNorm() const {
    double m = gradient_.size() ? gradient_.cwiseAbs().maxCoeff() : 0.0;
    for (const Eigen::Vector3d& g : point_gradient_) m = std::max(m, g.cwiseAbs().maxCoeff());
    return m;
  }

  double Norm() const {
    double s = 0;
    for (int c : free_cameras_)
      s += Eigen::Map<const Eigen::Matrix<double, 7, 1>>(cameras_ + 7 * c).squaredNorm();
    for (const Eigen::Vector3d& p : positions_) s += p.squaredNorm();
    return std::sqrt(s);
  }

  static double StepNorm(const Eigen::VectorXd& cameras,
                         const std::vector<Eigen::Vector3d>& points) {
    double s = cameras.squaredNorm();
    for (const Eigen::Vector3d& p : points) s += p.squaredNorm();
    return std::sqrt(s);
  }

  BaProblem& problem_;
  double* cameras_;
  const LmPassOptions& options_;
  std::vector<int> camera_var_;    // per camera: its index among the free ones, or -1
  std::vector<int> free_cameras_;  // camera index per free camera
  std::vector<int> points_;        // problem point index per optimised point
  std::vector<Eigen::Vector3d> positions_;
  std::vector<Obs> obs_;
  std::vector<ReprojectionResidual> residuals_;
  std::vector<std::pair<int, int>> relatives_;
  std::deque<RelativePoseCost> relative_costs_;
  std::vector<int> point_begin_, point_obs_;  // each point's observations (indices into obs_)
  Eigen::MatrixXd hessian_;                   // cameras x cameras, upper triangle
  Eigen::VectorXd gradient_;
  std::vector<Eigen::Matrix3d> point_hessian_, point_inverse_;
  std::vector<Eigen::Vector3d> point_gradient_;
  std::vector<Mat63> coupling_;  // per observation: d camera' d point block (free cameras only)
};

}  // namespace

LmPassSummary DenseSchurLmPass(BaProblem* problem, double* camera_values,
                               const LmPassOptions& options) {
  Pass pass(problem, camera_values, options);
  LmPassSummary summary = pass.Run();
  summary.observations = pass.observations();
  return summary;
}

}  // namespace ccmd
