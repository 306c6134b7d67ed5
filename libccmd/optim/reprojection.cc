#include "libccmd/optim/reprojection.h"

#include <cmath>

#include "libccmd/util/string_util.h"

namespace ccmd {

Status DepthNoise::Validate() const {
  if (!(sigma_0 > 0 && sigma_2 >= 0 && std::isfinite(sigma_0) && std::isfinite(sigma_2))) {
    return InvalidArgument("depth noise needs sigma0 > 0 and sigma2 >= 0 (finite)");
  }
  if (!(keypoint_offset >= 0 && keypoint_offset <= 10)) {
    return InvalidArgument("depth noise keypoint offset must be in [0, 10] pixel sigmas");
  }
  return Status::Ok();
}

StatusOr<DepthNoise> ReadDepthNoise(const ConfigFile& c, DepthNoise n) {
  CCMD_ASSIGN_OR_RETURN(n.sigma_0, c.GetDouble("DepthNoise.sigma0", n.sigma_0));
  CCMD_ASSIGN_OR_RETURN(n.sigma_2, c.GetDouble("DepthNoise.sigma2", n.sigma_2));
  CCMD_ASSIGN_OR_RETURN(n.keypoint_offset,
                        c.GetDouble("DepthNoise.keypointOffset", n.keypoint_offset));
  if (const Status s = n.Validate(); !s.ok()) return InvalidArgument(c.path() + ": " + s.message());
  return n;
}

std::string DepthNoiseConfigKeys(const DepthNoise& n) {
  return "DepthNoise.sigma0: " + ExactNumber(n.sigma_0) +
         "\nDepthNoise.sigma2: " + ExactNumber(n.sigma_2) +
         "\nDepthNoise.keypointOffset: " + ExactNumber(n.keypoint_offset) + "\n";
}

void ReprojectionResidual::Evaluate(const double* q_cw, const double* t_cw, const double* p_w,
                                    double* residual, double* J_q, double* J_t, double* J_p) const {
  // Eigen's q * p: p + w (2 u x p) + u x (2 u x p), u the vector part.
  const Eigen::Map<const Eigen::Vector3d> u(q_cw), p(p_w), t(t_cw);
  const double w = q_cw[3];
  const Eigen::Vector3d uxp2 = 2 * u.cross(p);
  const Eigen::Vector3d pc = p + w * uxp2 + u.cross(uxp2) + t;
  const double inv_z = 1.0 / pc.z();
  residual[0] = w_ * (k_.fx * pc.x() * inv_z + k_.cx - uv_.x());
  residual[1] = w_ * (k_.fy * pc.y() * inv_z + k_.cy - uv_.y());
  residual[2] = depth_ > 0 ? w_depth_ * (pc.z() - depth_) : 0.0;
  if (!J_q && !J_t && !J_p) return;
  // d residual / d pc.
  Eigen::Matrix3d D = Eigen::Matrix3d::Zero();
  D(0, 0) = w_ * k_.fx * inv_z;
  D(0, 2) = -w_ * k_.fx * pc.x() * inv_z * inv_z;
  D(1, 1) = w_ * k_.fy * inv_z;
  D(1, 2) = -w_ * k_.fy * pc.y() * inv_z * inv_z;
  if (depth_ > 0) D(2, 2) = w_depth_;
  using RowMajor3x3 = Eigen::Matrix<double, 3, 3, Eigen::RowMajor>;
  if (J_t) Eigen::Map<RowMajor3x3>{J_t} = D;
  auto skew = [](const Eigen::Vector3d& a) {
    Eigen::Matrix3d m;
    m << 0, -a.z(), a.y(), a.z(), 0, -a.x(), -a.y(), a.x(), 0;
    return m;
  };
  if (J_p) {
    // d pc / d p = I + 2 w [u]x + 2 [u]x [u]x (the rotation matrix when q is a unit).
    const Eigen::Matrix3d U = skew(u);
    Eigen::Map<RowMajor3x3>{J_p} = D * (Eigen::Matrix3d::Identity() + 2 * w * U + 2 * U * U);
  }
  if (J_q) {
    // d pc / d u = -2 w [p]x + 2 ((u . p) I + u p^T - 2 p u^T); d pc / d w = 2 u x p.
    Eigen::Matrix<double, 3, 4> dq;
    dq.leftCols<3>() = -2 * w * skew(p) + 2 * (u.dot(p) * Eigen::Matrix3d::Identity() +
                                               u * p.transpose() - 2 * p * u.transpose());
    dq.col(3) = uxp2;
    Eigen::Map<Eigen::Matrix<double, 3, 4, Eigen::RowMajor>>{J_q} = D * dq;
  }
}

double ReprojectionChi2(const Intrinsics& k, const Eigen::Isometry3d& T_cam_world,
                        const Eigen::Vector3d& p_w, const Eigen::Vector2d& uv, double depth,
                        double info_px, double info_depth) {
  const Eigen::Vector3d pc = T_cam_world * p_w;
  if (pc.z() <= 1e-6) return 1e12;
  const double u = k.fx * pc.x() / pc.z() + k.cx;
  const double v = k.fy * pc.y() / pc.z() + k.cy;
  double chi2 = ((u - uv.x()) * (u - uv.x()) + (v - uv.y()) * (v - uv.y())) * info_px;
  if (depth > 0) chi2 += (pc.z() - depth) * (pc.z() - depth) * info_depth;
  return chi2;
}

void DepthNoise::Describe(OptionsWriter* out) const {
  out->Add("sigma_0", sigma_0);
  out->Add("sigma_2", sigma_2);
  out->Add("keypoint_offset", keypoint_offset);
}

}  // namespace ccmd
