#include "libccmd/sensors/depth_registration.h"

#include <algorithm>
#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

namespace ccmd {

StatusOr<cv::Mat> RegisterDepth(const cv::Mat& depth_mm, const DepthToColorCalibration& calibration,
                                const PinholeCamera& color_camera) {
  const PinholeCamera& depth = calibration.depth;
  if (depth_mm.cols != depth.width || depth_mm.rows != depth.height) {
    return InvalidArgument("depth image is " + std::to_string(depth_mm.cols) + "x" +
                           std::to_string(depth_mm.rows) + ", the config's Depth block describes " +
                           std::to_string(depth.width) + "x" + std::to_string(depth.height));
  }
  return RegisterDepthToColor(depth_mm, depth, color_camera, calibration.T_color_depth);
}

namespace {

// std::ceil / std::floor / std::lround are library calls on the baseline x86-64 target (no
// SSE4.1 rounding instruction), several per depth pixel. These are exact for |x| < 2^31;
// callers keep x within +-1e9.
int CeilToInt(double x) {
  const int i = static_cast<int>(x);  // towards zero
  return i + (static_cast<double>(i) < x);
}
int FloorToInt(double x) {
  const int i = static_cast<int>(x);
  return i - (static_cast<double>(i) > x);
}
int RoundToInt(double x) {  // halves away from zero, as std::lround
  return x >= 0 ? FloorToInt(x + 0.5) : -FloorToInt(0.5 - x);
}
// A projected coordinate kept where the conversions are exact: a point just in front of the
// camera projects arbitrarily far out, and clamped it stays out of the image (as does a NaN,
// which a distortion model pushed past its range could give).
double Clamped(double x) { return x > -1e9 ? (x < 1e9 ? x : 1e9) : -1e9; }

}  // namespace

cv::Mat RegisterDepthToColor(const cv::Mat& depth_mm, const PinholeCamera& depth_camera,
                             const PinholeCamera& color_camera, const Pose& T_color_depth,
                             int max_footprint) {
  cv::Mat out(color_camera.height, color_camera.width, CV_16UC1, cv::Scalar(0));
  const Eigen::Matrix3d R = T_color_depth.linear();
  const Eigen::Vector3d t = T_color_depth.translation();
  const int out_w = out.cols, out_h = out.rows;
  // A depth pixel (u, v) at depth z is z * ray(u, v) in the depth frame, and its footprint's
  // corners are z * (ray -/+ half), half = (0.5 / fx, 0.5 / fy, 0). Rotated once here, the
  // per-pixel work is a few multiply-adds: R z (ray +- half) + t.
  const Eigen::Vector3d half = R * Eigen::Vector3d(0.5 / depth_camera.fx, 0.5 / depth_camera.fy, 0);
  const Eigen::Vector3d column_step = R * Eigen::Vector3d(1.0 / depth_camera.fx, 0, 0);
  const bool distorted = color_camera.HasDistortion();
  const double fx = color_camera.fx, fy = color_camera.fy;
  const double cx = color_camera.cx, cy = color_camera.cy;
  auto project = [&](const Eigen::Vector3d& p) {
    const double inverse_z = 1.0 / p.z();  // one division, not two
    const Eigen::Vector2d ideal(fx * p.x() * inverse_z + cx, fy * p.y() * inverse_z + cy);
    return distorted ? color_camera.DistortPixel(ideal) : ideal;
  };
  for (int v = 0; v < depth_mm.rows; ++v) {
    const std::uint16_t* row = depth_mm.ptr<std::uint16_t>(v);
    // Rotated ray of pixel (0, v); each column adds column_step.
    const Eigen::Vector3d row_start =
        R * Eigen::Vector3d(-depth_camera.cx / depth_camera.fx,
                            (v - depth_camera.cy) / depth_camera.fy, 1.0);
    for (int u = 0; u < depth_mm.cols; ++u) {
      if (row[u] == 0) continue;
      const double z = row[u] * 1e-3;
      const Eigen::Vector3d ray = row_start + u * column_step;
      const Eigen::Vector3d centre = z * ray + t;
      const Eigen::Vector3d a = z * (ray - half) + t;
      const Eigen::Vector3d b = z * (ray + half) + t;
      if (centre.z() <= 1e-6 || a.z() <= 1e-6 || b.z() <= 1e-6) continue;
      const Eigen::Vector2d pa = project(a);
      const Eigen::Vector2d pb = project(b);
      // Colour pixels whose centres lie inside the footprint; at least the one under the
      // projected centre (a footprint smaller than a pixel may hold no centre).
      int x0 = CeilToInt(Clamped(std::min(pa.x(), pb.x())));
      int x1 = FloorToInt(Clamped(std::max(pa.x(), pb.x())));
      int y0 = CeilToInt(Clamped(std::min(pa.y(), pb.y())));
      int y1 = FloorToInt(Clamped(std::max(pa.y(), pb.y())));
      if (x1 < x0 || y1 < y0) {
        const Eigen::Vector2d pc = project(centre);
        if (x1 < x0) x0 = x1 = RoundToInt(Clamped(pc.x()));
        if (y1 < y0) y0 = y1 = RoundToInt(Clamped(pc.y()));
      }
      if (x1 - x0 >= max_footprint || y1 - y0 >= max_footprint) continue;
      x0 = std::max(x0, 0);
      y0 = std::max(y0, 0);
      x1 = std::min(x1, out_w - 1);
      y1 = std::min(y1, out_h - 1);
      if (x1 < x0 || y1 < y0) continue;
      const double z_mm = centre.z() * 1e3;
      if (z_mm < 0.5 || z_mm >= 65535.5) continue;
      const auto value = static_cast<std::uint16_t>(RoundToInt(z_mm));
      for (int y = y0; y <= y1; ++y) {
        std::uint16_t* target = out.ptr<std::uint16_t>(y);
        for (int x = x0; x <= x1; ++x) {
          if (target[x] == 0 || value < target[x]) target[x] = value;  // nearest wins
        }
      }
    }
  }
  return out;
}

double EdgeAlignmentScore(const cv::Mat& bgr, const cv::Mat& depth_mm) {
  if (bgr.empty() || bgr.size() != depth_mm.size() || depth_mm.type() != CV_16UC1) return 0;
  cv::Mat gray, gx, gy, magnitude;
  cv::cvtColor(bgr, gray, cv::COLOR_BGR2GRAY);
  cv::GaussianBlur(gray, gray, cv::Size(5, 5), 1.5);
  cv::Sobel(gray, gx, CV_32F, 1, 0, 3);
  cv::Sobel(gray, gy, CV_32F, 0, 1, 3);
  cv::magnitude(gx, gy, magnitude);
  double sum = 0;
  long count = 0;
  for (int y = 1; y + 1 < depth_mm.rows; ++y) {
    for (int x = 1; x + 1 < depth_mm.cols; ++x) {
      const int d = depth_mm.at<std::uint16_t>(y, x);
      if (d == 0) continue;
      const int neighbours[4] = {
          depth_mm.at<std::uint16_t>(y, x - 1), depth_mm.at<std::uint16_t>(y, x + 1),
          depth_mm.at<std::uint16_t>(y - 1, x), depth_mm.at<std::uint16_t>(y + 1, x)};
      bool edge = false;
      for (int n : neighbours) edge |= n == 0 || n - d > d / 20;
      if (!edge) continue;
      sum += magnitude.at<float>(y, x);
      ++count;
    }
  }
  return count ? sum / count : 0;
}

}  // namespace ccmd
