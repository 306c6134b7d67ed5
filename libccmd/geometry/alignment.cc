#include "libccmd/geometry/alignment.h"

#include <Eigen/SVD>

namespace ccmd {

Eigen::Isometry3d Similarity3::Rigid() const {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = t;
  return T;
}

StatusOr<Similarity3> AlignPoints(const std::vector<Eigen::Vector3d>& src,
                                  const std::vector<Eigen::Vector3d>& dst, bool with_scale) {
  if (src.size() != dst.size()) return InvalidArgument("point sets differ in size");
  const std::size_t n = src.size();
  if (n < 3) return InvalidArgument("need at least 3 point pairs to align");

  Eigen::Vector3d mean_src = Eigen::Vector3d::Zero();
  Eigen::Vector3d mean_dst = Eigen::Vector3d::Zero();
  for (std::size_t i = 0; i < n; ++i) {
    mean_src += src[i];
    mean_dst += dst[i];
  }
  mean_src /= static_cast<double>(n);
  mean_dst /= static_cast<double>(n);

  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  double var_src = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d a = src[i] - mean_src;
    const Eigen::Vector3d b = dst[i] - mean_dst;
    cov += b * a.transpose();
    var_src += a.squaredNorm();
  }
  cov /= static_cast<double>(n);
  var_src /= static_cast<double>(n);

  Eigen::JacobiSVD<Eigen::Matrix3d> svd(cov, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Vector3d sv = svd.singularValues();
  // Rank < 2 means the points are collinear (or coincide): rotation is not determined.
  if (sv(1) <= 1e-12 * std::max(1.0, sv(0))) {
    return InvalidArgument("points are degenerate (collinear or coincident)");
  }
  Eigen::Matrix3d S = Eigen::Matrix3d::Identity();
  if (svd.matrixU().determinant() * svd.matrixV().determinant() < 0) S(2, 2) = -1;

  Similarity3 result;
  result.R = svd.matrixU() * S * svd.matrixV().transpose();
  result.scale = with_scale ? (sv.asDiagonal() * S).trace() / var_src : 1.0;
  result.t = mean_dst - result.scale * result.R * mean_src;
  return result;
}

}  // namespace ccmd
