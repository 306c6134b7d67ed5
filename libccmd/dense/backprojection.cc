#include "libccmd/dense/backprojection.h"

#include <algorithm>
#include <cmath>

#include <opencv2/core.hpp>

namespace ccmd {

Status BackProjectionOptions::Validate() const {
  if (!std::isfinite(min_depth_m) || !std::isfinite(max_depth_m) || min_depth_m < 0 ||
      max_depth_m <= min_depth_m) {
    return InvalidArgument("depth range must satisfy 0 <= min_depth_m < max_depth_m (got " +
                           std::to_string(min_depth_m) + ", " + std::to_string(max_depth_m) + ")");
  }
  return Status::Ok();
}

namespace {

std::string SizeText(int width, int height) {
  return std::to_string(width) + "x" + std::to_string(height);
}

}  // namespace

Status CheckRgbdImages(const cv::Mat& depth_mm, const cv::Mat& bgr, const PinholeCamera& camera) {
  std::string why;
  if (!camera.IsValid(&why)) return InvalidArgument("camera: " + why);
  if (depth_mm.empty()) return InvalidArgument("depth image is empty");
  if (depth_mm.dims != 2 || depth_mm.type() != CV_16UC1) {
    return InvalidArgument("depth image must be CV_16UC1 millimetres (type " +
                           std::to_string(depth_mm.type()) + ")");
  }
  if (bgr.empty()) return InvalidArgument("colour image is empty");
  if (bgr.dims != 2 || bgr.type() != CV_8UC3) {
    return InvalidArgument("colour image must be CV_8UC3 BGR (type " + std::to_string(bgr.type()) +
                           ")");
  }
  if (depth_mm.cols != camera.width || depth_mm.rows != camera.height) {
    return InvalidArgument("depth image is " + SizeText(depth_mm.cols, depth_mm.rows) +
                           " but the camera is " + SizeText(camera.width, camera.height));
  }
  if (bgr.cols != depth_mm.cols || bgr.rows != depth_mm.rows) {
    return InvalidArgument("colour image is " + SizeText(bgr.cols, bgr.rows) +
                           " but the depth image is " + SizeText(depth_mm.cols, depth_mm.rows));
  }
  return Status::Ok();
}

StatusOr<CameraCloud> BackProjectKeyframe(const cv::Mat& depth_mm, const cv::Mat& bgr,
                                          const PinholeCamera& camera,
                                          const BackProjectionOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  CCMD_RETURN_IF_ERROR(CheckRgbdImages(depth_mm, bgr, camera));
  // Integer millimetre bounds: a depth d (mm) is used iff lo <= d <= hi.
  const double lo_mm = std::max(1.0, std::ceil(options.min_depth_m * 1000.0 - 1e-9));
  const double hi_mm = std::min(65535.0, std::floor(options.max_depth_m * 1000.0 + 1e-9));
  if (hi_mm < lo_mm) return CameraCloud{};
  const auto lo = static_cast<std::uint16_t>(lo_mm);
  const auto hi = static_cast<std::uint16_t>(hi_mm);
  const int width = camera.width, height = camera.height;

  // Counting first sizes the vectors exactly: the store keeps them for the whole run.
  std::size_t count = 0;
  for (int v = 0; v < height; ++v) {
    const auto* d = depth_mm.ptr<std::uint16_t>(v);
    for (int u = 0; u < width; ++u) count += (d[u] >= lo && d[u] <= hi);
  }
  CameraCloud cloud;
  cloud.points.resize(count);
  cloud.colors.resize(count);

  std::vector<float> x_of_u(width);
  for (int u = 0; u < width; ++u) x_of_u[u] = static_cast<float>((u - camera.cx) / camera.fx);
  std::size_t i = 0;
  for (int v = 0; v < height; ++v) {
    const auto* d = depth_mm.ptr<std::uint16_t>(v);
    const auto* c = bgr.ptr<std::uint8_t>(v);
    const float y_of_v = static_cast<float>((v - camera.cy) / camera.fy);
    for (int u = 0; u < width; ++u) {
      if (d[u] < lo || d[u] > hi) continue;
      const float z = d[u] * 0.001f;
      cloud.points[i] = Eigen::Vector3f(x_of_u[u] * z, y_of_v * z, z);
      cloud.colors[i] = {c[3 * u + 2], c[3 * u + 1], c[3 * u]};
      ++i;
    }
  }
  return cloud;
}

}  // namespace ccmd
