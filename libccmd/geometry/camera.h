#pragma once

// Pinhole camera with a depth scale and lens distortion, in the ORB-SLAM convention.
//
// Focal lengths may be negative: ICL-NUIM's TUM-format release has fy < 0, meaning image
// rows run opposite to the camera's y axis (the images are a mirror image of what a camera
// with fy > 0 at the same pose would see). Every formula here uses the signed values, so
// such a camera is handled like any other; only zero or non-finite values are errors.
//
// Distortion is the Brown-Conrady model of OpenCV and ORB-SLAM (k1 k2 p1 p2 k3) on
// normalised coordinates x = (u - cx) / fx, y = (v - cy) / fy. Images are used as recorded
// ("raw"); geometry works on undistorted coordinates, i.e. the pixel an ideal pinhole camera
// with the same fx fy cx cy would see: Project/BackProject are that ideal camera,
// UndistortPixel/DistortPixel convert between raw and ideal pixels, and PixelRays holds the
// undistorted ray of every raw pixel for dense work.

#include <array>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

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
  // k1 k2 p1 p2 k3 (see above); all zero for an undistorted camera.
  std::array<double, 5> distortion{0, 0, 0, 0, 0};
  // Camera.RGB: true (1, the usual case) when colour files hold their channels in the
  // standard order; false (0) when red and blue are swapped in the files (a recorder that
  // wrote BGR bytes as RGB). Readers swap them back, so colour in memory is always BGR.
  bool rgb = true;

  // Ok if sizes, focal lengths, principal point, distortion and depth scale are usable
  // (finite, non-zero focal lengths of either sign); otherwise the first problem found.
  Status Validate() const;
  // Validate, and the distortion can be inverted over the whole image (the model does not
  // fold back on itself inside it). Costs a few thousand evaluations: for loading a config
  // or registering an agent, not per frame.
  Status ValidateInvertible() const;
  void Describe(OptionsWriter* out) const;

  bool HasDistortion() const {
    return distortion[0] != 0 || distortion[1] != 0 || distortion[2] != 0 || distortion[3] != 0 ||
           distortion[4] != 0;
  }
  // Normalised coordinates (x / z, y / z) to their distorted position, and back (Newton;
  // exact to 1e-12 wherever the model is invertible).
  Eigen::Vector2d Distort(const Eigen::Vector2d& xy) const;
  Eigen::Vector2d Undistort(const Eigen::Vector2d& xy_distorted) const;
  // A pixel of the image as recorded to the pixel of the ideal pinhole image, and back.
  // Both are the identity without distortion.
  Eigen::Vector2d UndistortPixel(const Eigen::Vector2d& raw) const;
  Eigen::Vector2d DistortPixel(const Eigen::Vector2d& ideal) const;
  // Where a camera-frame point appears in the image as recorded (distortion applied).
  Eigen::Vector2d ProjectToImage(const Eigen::Vector3d& p_cam) const {
    return HasDistortion() ? DistortPixel(Project(p_cam)) : Project(p_cam);
  }

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

// The undistorted viewing ray (x, y, 1) of every pixel of a camera's image as recorded:
// a point at depth z seen at raw pixel (u, v) is z * (x(u, v), y(u, v), 1). Without
// distortion x depends on u only and y on v only, as (u - cx) / fx and (v - cy) / fy.
class PixelRays {
 public:
  // With distortion the rays are solved exactly on a 4-pixel grid and interpolated between
  // (within 0.02 px for TUM fr1's lens), or with `exact` solved at every pixel (a few times
  // slower: for rendering ground truth).
  explicit PixelRays(const PinholeCamera& camera, bool exact = false);
  int width() const { return width_; }
  int height() const { return height_; }
  // Row v of the x and y tables (width() values each).
  const float* x_row(int v) const { return x_.data() + static_cast<std::size_t>(v) * width_; }
  const float* y_row(int v) const { return y_.data() + static_cast<std::size_t>(v) * width_; }
  Eigen::Vector3d Ray(int u, int v) const { return {x_row(v)[u], y_row(v)[u], 1.0}; }

 private:
  int width_ = 0, height_ = 0;
  std::vector<float> x_, y_;
};

}  // namespace ccmd
