#pragma once

// Pinhole camera with a depth scale, in the ORB-SLAM convention.
//
// Lens distortion: TUM lists distortion coefficients for fr1/fr2, but its depth images
// (and the colour images most RGB-D systems use) are used as if undistorted; like
// ORB-SLAM's RGB-D examples we keep the coefficients for reference and ignore them.

#include <array>
#include <string>

#include <Eigen/Core>

namespace ccmd {

struct PinholeCamera {
  int width = 640;
  int height = 480;
  double fx = 525.0;
  double fy = 525.0;
  double cx = 319.5;
  double cy = 239.5;
  double fps = 30.0;
  // Units per metre in depth image files (TUM: 5000). In memory depth is always
  // uint16 millimetres; this factor is only used when reading and writing files.
  double depth_map_factor = 5000.0;
  // fx times the depth sensor's baseline (ORB-SLAM's Camera.bf): weights depth in bundle
  // adjustment through the virtual right-image coordinate u - bf / z.
  double bf = 40.0;
  // Depth beyond this (metres) is treated as far: ORB-SLAM's ThDepth * bf / fx.
  double far_depth_m = 4.0;
  // k1 k2 p1 p2 k3, recorded but not applied (see above).
  std::array<double, 5> distortion{0, 0, 0, 0, 0};

  // True if sizes and focal lengths are usable. `why` gets the first problem found.
  bool IsValid(std::string* why = nullptr) const;

  Eigen::Vector2d Project(const Eigen::Vector3d& p_cam) const {
    return {fx * p_cam.x() / p_cam.z() + cx, fy * p_cam.y() / p_cam.z() + cy};
  }
  Eigen::Vector3d BackProject(double u, double v, double depth) const {
    return {(u - cx) / fx * depth, (v - cy) / fy * depth, depth};
  }
  bool InImage(const Eigen::Vector2d& uv, double border = 0.0) const {
    return uv.x() >= border && uv.y() >= border && uv.x() < width - border &&
           uv.y() < height - border;
  }
  Eigen::Matrix3d K() const;

  // The camera of the image resized by `factor` (0.5 halves both sides). Pixel centres
  // are kept consistent: a pixel's centre (u + 0.5) scales with the image.
  PinholeCamera Scaled(double factor) const;
  PinholeCamera Resized(int new_width, int new_height) const;

  std::string ToString() const;
};

}  // namespace ccmd
