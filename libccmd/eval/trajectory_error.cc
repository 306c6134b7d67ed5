#include "libccmd/eval/trajectory_error.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Eigenvalues>

#include "libccmd/io/tum_dataset.h"

namespace ccmd {

Status AteOptions::Validate() const {
  if (!(max_time_difference >= 0) || !std::isfinite(max_time_difference)) {
    return InvalidArgument("max time difference must be >= 0");
  }
  if (!(pose_alignment_below_spread_m >= 0)) {
    return InvalidArgument("pose alignment spread must be >= 0");
  }
  if (!(pose_alignment_arm_m > 0) || !std::isfinite(pose_alignment_arm_m)) {
    return InvalidArgument("pose alignment arm must be finite and > 0");
  }
  return Status::Ok();
}

void AteOptions::Describe(OptionsWriter* out) const {
  out->Add("max_time_difference", max_time_difference);
  out->Add("align", align);
  out->Add("correct_scale", correct_scale);
  out->Add("pose_alignment_below_spread_m", pose_alignment_below_spread_m);
  out->Add("pose_alignment_arm_m", pose_alignment_arm_m);
}

Status RpeOptions::Validate() const {
  if (!(max_time_difference >= 0) || !std::isfinite(max_time_difference)) {
    return InvalidArgument("max time difference must be >= 0");
  }
  if (delta_frames < 1) return InvalidArgument("RPE delta must be at least 1 frame");
  return Status::Ok();
}

void RpeOptions::Describe(OptionsWriter* out) const {
  out->Add("max_time_difference", max_time_difference);
  out->Add("delta_frames", delta_frames);
}

ErrorStatistics ComputeStatistics(std::vector<double> errors) {
  ErrorStatistics s;
  if (errors.empty()) return s;
  const double n = static_cast<double>(errors.size());
  double sum = 0, sum_sq = 0;
  for (double e : errors) {
    sum += e;
    sum_sq += e * e;
  }
  s.mean = sum / n;
  s.rmse = std::sqrt(sum_sq / n);
  s.std = std::sqrt(std::max(0.0, sum_sq / n - s.mean * s.mean));
  std::sort(errors.begin(), errors.end());
  s.min = errors.front();
  s.max = errors.back();
  const std::size_t mid = errors.size() / 2;
  s.median = errors.size() % 2 ? errors[mid] : 0.5 * (errors[mid - 1] + errors[mid]);
  return s;
}

namespace {

std::vector<std::pair<std::size_t, std::size_t>> MatchByTime(const Trajectory& groundtruth,
                                                             const Trajectory& estimate,
                                                             double max_difference) {
  std::vector<double> te, tg;
  for (const auto& p : estimate) te.push_back(p.timestamp);
  for (const auto& p : groundtruth) tg.push_back(p.timestamp);
  return AssociateTimestamps(te, tg, max_difference);  // (estimate index, gt index)
}

// Standard deviation of the points along their second principal direction.
double SecondSpread(const std::vector<Eigen::Vector3d>& points) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& p : points) mean += p;
  mean /= static_cast<double>(points.size());
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Zero();
  for (const auto& p : points) covariance += (p - mean) * (p - mean).transpose();
  covariance /= static_cast<double>(points.size());
  const Eigen::Vector3d eigenvalues =
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(covariance).eigenvalues();
  return std::sqrt(std::max(0.0, eigenvalues(1)));  // ascending: (1) is the middle one
}

}  // namespace

StatusOr<AteResult> ComputeAte(const Trajectory& groundtruth, const Trajectory& estimate,
                               const AteOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  const auto matches = MatchByTime(groundtruth, estimate, options.max_time_difference);
  const bool may_use_poses = options.align && options.pose_alignment_below_spread_m > 0;
  const std::size_t needed = options.align && !may_use_poses ? 3 : 1;
  if (matches.size() < needed) {
    return InvalidArgument("only " + std::to_string(matches.size()) +
                           " poses match the ground truth in time (need " + std::to_string(needed) +
                           ")");
  }
  std::vector<Eigen::Vector3d> est, gt;
  AteResult result;
  for (const auto& [ie, ig] : matches) {
    est.push_back(estimate[ie].T_world_cam.translation());
    gt.push_back(groundtruth[ig].T_world_cam.translation());
    result.timestamps.push_back(estimate[ie].timestamp);
    result.groundtruth_indices.push_back(ig);
  }
  if (options.align) {
    result.aligned_by_poses =
        may_use_poses &&
        (est.size() < 3 || SecondSpread(est) < options.pose_alignment_below_spread_m);
    std::vector<Eigen::Vector3d> est_fit = est, gt_fit = gt;
    if (result.aligned_by_poses) {
      const double arm = options.pose_alignment_arm_m;
      for (const auto& [ie, ig] : matches) {
        for (int axis = 0; axis < 3; ++axis) {
          est_fit.push_back(estimate[ie].T_world_cam * (arm * Eigen::Vector3d::Unit(axis)));
          gt_fit.push_back(groundtruth[ig].T_world_cam * (arm * Eigen::Vector3d::Unit(axis)));
        }
      }
    }
    auto alignment = AlignPoints(est_fit, gt_fit, options.correct_scale);
    if (!alignment.ok()) return alignment.status().WithContext("aligning the trajectories");
    result.alignment = *alignment;
  }
  result.matched = matches.size();
  for (std::size_t i = 0; i < est.size(); ++i) {
    result.error_vectors.push_back(result.alignment * est[i] - gt[i]);
    result.errors.push_back(result.error_vectors.back().norm());
  }
  result.error = ComputeStatistics(result.errors);
  return result;
}

StatusOr<SharedErrorResult> ComputeSharedError(const Trajectory& groundtruth, const Trajectory& a,
                                               const Trajectory& b, const AteOptions& options) {
  CCMD_ASSIGN_OR_RETURN(const AteResult ate_a, ComputeAte(groundtruth, a, options));
  CCMD_ASSIGN_OR_RETURN(const AteResult ate_b, ComputeAte(groundtruth, b, options));
  // Where each ground-truth pose stands among b's matched poses (-1: not matched).
  std::vector<std::ptrdiff_t> in_b(groundtruth.size(), -1);
  for (std::size_t k = 0; k < ate_b.groundtruth_indices.size(); ++k) {
    in_b[ate_b.groundtruth_indices[k]] = static_cast<std::ptrdiff_t>(k);
  }
  double aa = 0, bb = 0, ab = 0, shared = 0, apart = 0;
  SharedErrorResult result;
  for (std::size_t k = 0; k < ate_a.groundtruth_indices.size(); ++k) {
    const std::ptrdiff_t j = in_b[ate_a.groundtruth_indices[k]];
    if (j < 0) continue;
    const Eigen::Vector3d& ea = ate_a.error_vectors[k];
    const Eigen::Vector3d& eb = ate_b.error_vectors[j];
    aa += ea.squaredNorm();
    bb += eb.squaredNorm();
    ab += ea.dot(eb);
    shared += (0.5 * (ea + eb)).squaredNorm();
    apart += (0.5 * (ea - eb)).squaredNorm();
    ++result.matched;
  }
  if (result.matched == 0) {
    return InvalidArgument("the two estimates match no ground-truth pose in common");
  }
  const double n = static_cast<double>(result.matched);
  result.rmse_a = std::sqrt(aa / n);
  result.rmse_b = std::sqrt(bb / n);
  result.shared_rmse = std::sqrt(shared / n);
  result.apart_rmse = std::sqrt(apart / n);
  result.correlation = aa > 0 && bb > 0 ? ab / std::sqrt(aa * bb) : 0;
  return result;
}

StatusOr<RpeResult> ComputeRpe(const Trajectory& groundtruth, const Trajectory& estimate,
                               const RpeOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  const auto matches = MatchByTime(groundtruth, estimate, options.max_time_difference);
  if (matches.size() <= static_cast<std::size_t>(options.delta_frames)) {
    return InvalidArgument("too few matched poses for RPE");
  }
  std::vector<double> translation, rotation;
  for (std::size_t i = 0; i + options.delta_frames < matches.size(); ++i) {
    const auto& [e0, g0] = matches[i];
    const auto& [e1, g1] = matches[i + options.delta_frames];
    const Pose gt_delta = groundtruth[g0].T_world_cam.inverse() * groundtruth[g1].T_world_cam;
    const Pose est_delta = estimate[e0].T_world_cam.inverse() * estimate[e1].T_world_cam;
    const Pose error = gt_delta.inverse() * est_delta;
    translation.push_back(error.translation().norm());
    rotation.push_back(RotationAngle(error) * 180.0 / M_PI);
  }
  RpeResult result;
  result.pairs = translation.size();
  result.translation = ComputeStatistics(translation);
  result.rotation = ComputeStatistics(rotation);
  return result;
}

std::vector<double> NeighbourDeviations(const Trajectory& trajectory) {
  std::vector<double> deviations(trajectory.size(), 0.0);
  for (std::size_t i = 1; i + 1 < trajectory.size(); ++i) {
    const StampedPose& before = trajectory[i - 1];
    const StampedPose& after = trajectory[i + 1];
    const double span = after.timestamp - before.timestamp;
    const double s = span > 0 ? (trajectory[i].timestamp - before.timestamp) / span : 0.5;
    const Eigen::Vector3d line =
        (1 - s) * before.T_world_cam.translation() + s * after.T_world_cam.translation();
    deviations[i] = (trajectory[i].T_world_cam.translation() - line).norm();
  }
  return deviations;
}

Trajectory TransformTrajectory(const Trajectory& trajectory, const Similarity3& transform) {
  Trajectory out = trajectory;
  for (StampedPose& p : out) {
    Pose pose = Pose::Identity();
    pose.linear() = transform.R * p.T_world_cam.linear();
    pose.translation() = transform * p.T_world_cam.translation();
    p.T_world_cam = pose;
  }
  return out;
}

}  // namespace ccmd
