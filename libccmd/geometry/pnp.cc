#include "libccmd/geometry/pnp.h"

#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>

namespace ccmd {

std::optional<Pose> SolvePnpRansac(const std::vector<cv::Point3f>& object,
                                   const std::vector<cv::Point2f>& image,
                                   const PinholeCamera& camera, const PnpRansacOptions& options,
                                   std::vector<int>* inliers) {
  const cv::Mat K =
      (cv::Mat_<double>(3, 3) << camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1);
  cv::Mat rvec, tvec;
  std::vector<int> agree;
  const bool solved =
      cv::solvePnPRansac(object, image, K, cv::noArray(), rvec, tvec, false, options.iterations,
                         options.reprojection_px, options.confidence, agree, cv::SOLVEPNP_EPNP);
  if (!solved || static_cast<int>(agree.size()) < options.min_inliers) return std::nullopt;
  cv::Mat R;
  cv::Rodrigues(rvec, R);
  Eigen::Matrix3d Re;
  cv::cv2eigen(R, Re);
  Pose T = Pose::Identity();
  T.linear() = Re;
  T.translation() = Eigen::Vector3d(tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2));
  if (inliers) *inliers = std::move(agree);
  return T;
}

}  // namespace ccmd
