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
