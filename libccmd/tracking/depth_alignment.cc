#include "libccmd/tracking/depth_alignment.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>

namespace ccmd {

DepthModel DepthModel::FromDepth(const cv::Mat& depth_mm, const PinholeCamera& camera, int step,
                                 double min_depth, double max_depth) {
  DepthModel m;
  if (depth_mm.empty() || depth_mm.type() != CV_16UC1 || step < 1) return m;
  m.step_ = step;
  m.width_ = depth_mm.cols / step;
  m.height_ = depth_mm.rows / step;
  m.camera_ = camera;
  const Eigen::Vector3f none = Eigen::Vector3f::Zero();
  m.vertex_.assign(static_cast<std::size_t>(m.width_) * m.height_, none);
  m.normal_.assign(m.vertex_.size(), none);
  // A cell's depth is the mean of its block when the block is valid and smooth (edges and
  // holes give no vertex), which also averages the sensor's noise.
  for (int y = 0; y < m.height_; ++y) {
    for (int x = 0; x < m.width_; ++x) {
      int lo = 65535, hi = 0, sum = 0;
      for (int dy = 0; dy < step; ++dy) {
        const std::uint16_t* row = depth_mm.ptr<std::uint16_t>(y * step + dy) + x * step;
        for (int dx = 0; dx < step; ++dx) {
          lo = std::min<int>(lo, row[dx]);
          hi = std::max<int>(hi, row[dx]);
          sum += row[dx];
        }
      }
      const double z = 1e-3 * sum / (step * step);
      if (lo == 0 || z < min_depth || z > max_depth || (hi - lo) * 1e-3 > 0.005 + 0.02 * z)
        continue;
      // The block centre as recorded; with distortion, its ray is that of the ideal pixel.
      const Eigen::Vector2d uv =
          camera.UndistortPixel({x * step + 0.5 * (step - 1), y * step + 0.5 * (step - 1)});
      m.vertex_[y * m.width_ + x] = camera.BackProject(uv.x(), uv.y(), z).cast<float>();
    }
  }
  for (int y = 1; y + 1 < m.height_; ++y) {
    for (int x = 1; x + 1 < m.width_; ++x) {
      const Eigen::Vector3f& c = m.vertex(x, y);
      const Eigen::Vector3f &l = m.vertex(x - 1, y), &r = m.vertex(x + 1, y);
      const Eigen::Vector3f &u = m.vertex(x, y - 1), &d = m.vertex(x, y + 1);
      if (c.z() == 0 || l.z() == 0 || r.z() == 0 || u.z() == 0 || d.z() == 0) continue;
      const float jump = 0.05f * c.z();
      if ((r - l).norm() > 2 * jump || (d - u).norm() > 2 * jump) continue;
      Eigen::Vector3f n = (r - l).cross(d - u);
      if (n.norm() < 1e-9f) continue;
      n.normalize();
      if (n.dot(c) > 0) n = -n;  // towards the camera
      m.normal_[y * m.width_ + x] = n;
      ++m.valid_;
    }
  }
  return m;
}

DepthModel DepthModel::Moved(const Pose& T_new_old) const {
  DepthModel m = *this;
  const Eigen::Matrix3f R = T_new_old.linear().cast<float>();
  const Eigen::Vector3f t = T_new_old.translation().cast<float>();
  for (std::size_t i = 0; i < m.vertex_.size(); ++i) {
    if (m.vertex_[i].z() == 0) continue;  // no vertex
    m.vertex_[i] = R * m.vertex_[i] + t;
    m.normal_[i] = R * m.normal_[i];
  }
  m.T_grid_model_ = T_grid_model_ * T_new_old.inverse();
  return m;
}

std::optional<std::pair<int, int>> DepthModel::Cell(const Eigen::Vector3d& point) const {
  const Eigen::Vector3d p = T_grid_model_ * point;
  if (p.z() <= 0) return std::nullopt;
  const Eigen::Vector2d uv = camera_.ProjectToImage(p);
  const double u = uv.x(), v = uv.y();
  // The pixel u falls in is round(u); block x holds pixels x * step .. x * step + step - 1.
  const int x = static_cast<int>(std::floor((u + 0.5) / step_)),
            y = static_cast<int>(std::floor((v + 0.5) / step_));
  if (x < 0 || y < 0 || x >= width_ || y >= height_) return std::nullopt;
  return std::make_pair(x, y);
}

Status DepthAlignmentOptions::Validate() const {
  if (iterations < 1) return InvalidArgument("depth alignment iterations must be at least 1");
  if (source_stride < 1) return InvalidArgument("depth alignment source stride must be at least 1");
  if (!(max_distance > 0) || !std::isfinite(max_distance)) {
    return InvalidArgument("depth alignment max distance must be positive");
  }
  if (!(min_normal_dot >= -1 && min_normal_dot <= 1)) {
    return InvalidArgument("depth alignment min normal dot must be in [-1, 1]");
  }
  if (!(min_inlier_fraction >= 0 && min_inlier_fraction <= 1)) {
    return InvalidArgument("depth alignment min inlier fraction must be in [0, 1]");
  }
  return Status::Ok();
}

void DepthAlignmentOptions::Describe(OptionsWriter* out) const {
  out->Add("iterations", iterations);
  out->Add("source_stride", source_stride);
  out->Add("max_distance", max_distance);
  out->Add("min_normal_dot", min_normal_dot);
  out->Add("min_inlier_fraction", min_inlier_fraction);
}

std::optional<DepthAlignment> AlignDepth(const DepthModel& source, const DepthModel& target,
                                         const Pose& T_target_source, const DepthNoise& noise,
                                         const DepthAlignmentOptions& options) {
  if (source.empty() || target.empty()) return std::nullopt;
  int source_points = 0;
  for (int y = 0; y < source.height(); y += options.source_stride) {
    for (int x = 0; x < source.width(); x += options.source_stride)
      source_points += source.normal(x, y).z() != 0;
  }
  const int min_inliers =
      std::max(50, static_cast<int>(options.min_inlier_fraction * source_points));
  Pose T = T_target_source;
  DepthAlignment result;
  bool settled = false;
  double last_rotation_step = 0, last_translation_step = 0;
  for (int it = 0; it < options.iterations; ++it) {
    const double max_distance =
        it < options.iterations / 2 ? options.max_distance : 0.5 * options.max_distance;
    Matrix6d H = Matrix6d::Zero();
    Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
    int inliers = 0;
    double sse = 0, range = 0;
    const Eigen::Matrix3d R = T.linear();
    for (int y = 0; y < source.height(); y += options.source_stride) {
      for (int x = 0; x < source.width(); x += options.source_stride) {
        const Eigen::Vector3f& ns = source.normal(x, y);
        if (ns.z() == 0) continue;
        const Eigen::Vector3d q = T * source.vertex(x, y).cast<double>();
        const auto cell = target.Cell(q);
        if (!cell) continue;
        const Eigen::Vector3d n = target.normal(cell->first, cell->second).cast<double>();
        if (n.z() == 0) continue;
        const Eigen::Vector3d v = target.vertex(cell->first, cell->second).cast<double>();
        if ((q - v).norm() > max_distance ||
            (R * ns.cast<double>()).dot(n) < options.min_normal_dot)
          continue;
        const double r = n.dot(q - v);
        const double sigma = noise.sigma_0 + noise.sigma_2 * v.z() * v.z();
        // Huber weight at 2 sigma: a few bad matches (moving things, edges) cannot dominate.
        const double a = std::abs(r) / sigma;
        const double w = (a <= 2 ? 1.0 : 2 / a) / (sigma * sigma);
        Eigen::Matrix<double, 6, 1> J;
        J << q.cross(n), n;
        H.noalias() += w * J * J.transpose();
        b.noalias() += w * r * J;
        sse += r * r;
        range += q.norm();
        ++inliers;
      }
    }
    if (inliers < min_inliers) return std::nullopt;
    result.information = H;
    result.inliers = inliers;
    result.rms = std::sqrt(sse / inliers);
    result.mean_range = range / inliers;
    // A little damping keeps the step finite where the geometry leaves a direction free
    // (a single plane); that direction then keeps the initial guess.
    const Matrix6d damped = H + 1e-9 * H.trace() * Matrix6d::Identity();
    const Eigen::Matrix<double, 6, 1> xi = damped.ldlt().solve(-b);
    if (!xi.allFinite()) return std::nullopt;
    Pose step = Pose::Identity();
    const double angle = xi.head<3>().norm();
    if (angle > 1e-12)
      step.linear() = Eigen::AngleAxisd(angle, xi.head<3>() / angle).toRotationMatrix();
    step.translation() = xi.tail<3>();
    T = step * T;
    last_rotation_step = xi.head<3>().norm();
    last_translation_step = xi.tail<3>().norm();
    if (last_rotation_step < 1e-5 && last_translation_step < 1e-5 && it >= options.iterations / 2) {
      settled = true;
      break;
    }
  }
  // Not settled in the iterations given: still sliding along a weakly constrained direction
  // is fine (its information is small), but a last step of more than 5 mm or 5 mrad means the
  // association has not converged.
  if (!settled && (last_translation_step > 0.005 || last_rotation_step > 0.005))
    return std::nullopt;
  result.T_target_source = T;
  return result;
}

bool StaysNearStart(const DepthAlignment& aligned, const Pose& T_target_source_start) {
  return TranslationDistance(aligned.T_target_source, T_target_source_start) <= 0.1 &&
         RotationDistance(aligned.T_target_source, T_target_source_start) <= 0.1;
}

double Conditioning(const DepthAlignment& aligned) {
  if (!(aligned.mean_range > 0)) return 0;
  Eigen::Matrix<double, 6, 1> scale;
  scale << Eigen::Vector3d::Constant(1 / aligned.mean_range), Eigen::Vector3d::Ones();
  const Matrix6d H = scale.asDiagonal() * aligned.information * scale.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<Matrix6d> solver(H, Eigen::EigenvaluesOnly);
  const Eigen::Matrix<double, 6, 1>& eig = solver.eigenvalues();  // ascending
  return eig(5) > 0 ? std::max(0.0, eig(0)) / eig(5) : 0;
}

}  // namespace ccmd
