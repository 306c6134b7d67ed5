#include "libccmd/eval/depth_agreement.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace ccmd {

DepthAgreement CompareDepthByGroundTruth(const cv::Mat& depth_a_mm, const cv::Mat& depth_b_mm,
                                         const PinholeCamera& depth_camera, const Pose& T_world_a,
                                         const Pose& T_world_b, const Pose& T_pose_depth,
                                         const DepthAgreementOptions& options) {
  DepthAgreement out;
  if (depth_a_mm.type() != CV_16UC1 || depth_b_mm.type() != CV_16UC1) return out;
  const Pose T_b_a = (T_world_b * T_pose_depth).inverse() * (T_world_a * T_pose_depth);
  const int step = std::max(1, options.step);
  std::vector<double> errors;
  for (int v = 0; v < depth_a_mm.rows; v += step) {
    for (int u = 0; u < depth_a_mm.cols; u += step) {
      const double z = depth_a_mm.at<std::uint16_t>(v, u) * 1e-3;
      if (z <= 0) continue;
      const Eigen::Vector3d p = T_b_a * depth_camera.BackProject(u, v, z);
      if (p.z() <= 0) continue;
      const Eigen::Vector2d uv = depth_camera.Project(p);
      if (!depth_camera.InImage(uv)) continue;
      // The nearest pixel (integer coordinates are pixel centres).
      const int ub = static_cast<int>(std::lround(uv.x())),
                vb = static_cast<int>(std::lround(uv.y()));
      if (ub < 0 || vb < 0 || ub >= depth_b_mm.cols || vb >= depth_b_mm.rows) continue;
      const double zb = depth_b_mm.at<std::uint16_t>(vb, ub) * 1e-3;
      if (zb <= 0) continue;
      errors.push_back(std::abs(zb - p.z()));
      out.agreeing += errors.back() < options.max_error;
    }
  }
  out.compared = static_cast<int>(errors.size());
  if (!errors.empty()) {
    std::nth_element(errors.begin(), errors.begin() + errors.size() / 2, errors.end());
    out.median_error = errors[errors.size() / 2];
  }
  return out;
}

}  // namespace ccmd
