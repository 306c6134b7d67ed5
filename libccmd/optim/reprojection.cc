#include "libccmd/optim/reprojection.h"

#include <cmath>

namespace ccmd {

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

Status DepthNoise::Validate() const {
  if (!(sigma_0 > 0) || !std::isfinite(sigma_0) || !(sigma_2 >= 0) || !std::isfinite(sigma_2)) {
    return InvalidArgument("depth noise sigmas must be finite, sigma_0 > 0 and sigma_2 >= 0");
  }
  return Status::Ok();
}

void DepthNoise::Describe(OptionsWriter* out) const {
  out->Add("sigma_0", sigma_0);
  out->Add("sigma_2", sigma_2);
}

}  // namespace ccmd
