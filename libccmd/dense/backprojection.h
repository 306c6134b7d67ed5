#pragma once

// Back-projection of an RGB-D keyframe into a coloured point cloud in the keyframe's own
// camera frame (the paper's eq. 8: X = Z (u - cx) / fx, Y = Z (v - cy) / fy, Z = d, with
// (u, v) undistorted when the camera has lens distortion).

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core/mat.hpp>

#include "libccmd/geometry/camera.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct BackProjectionOptions {
  // Depth outside [min, max] metres is dropped. Noise grows with the square of depth on
  // structured-light and stereo sensors (about 1.5 mm z^2 for the Kinect, Khoshelham and
  // Elberink 2012): beyond 3 m a point is more than a centimetre off, more than the voxel.
  double min_depth_m = 0.3;
  double max_depth_m = 3.0;
  // Pixels whose surface is seen more obliquely than this (angle between the viewing ray and
  // the normal estimated from neighbouring pixels) are dropped; 90 keeps them. Depth error
  // grows steeply beyond about 70 degrees on RGB-D sensors (Nguyen, Izadi and Lovell 2012),
  // and a pixel between a foreground and a background surface (a "flying" pixel) looks like
  // such a surface, so this removes both. The neighbour on each axis is the one closer in
  // depth, so the last pixel of a foreground object keeps the object's normal.
  double max_incidence_deg = 75.0;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// A keyframe's points in its camera frame (x right, y down, z forward; metres) with colours
// (R, G, B), in raster order of the valid pixels.
struct CameraCloud {
  std::vector<Eigen::Vector3f> points;
  std::vector<std::array<std::uint8_t, 3>> colors;
  std::size_t size() const { return points.size(); }
};

// Checks that `depth_mm` is CV_16UC1 and `bgr` CV_8UC3, both of the camera's size, and that
// the camera is valid. `camera` is the camera of the transmitted resolution
// (PinholeCamera::Scaled(rate) of the full-resolution camera).
Status CheckRgbdImages(const cv::Mat& depth_mm, const cv::Mat& bgr, const PinholeCamera& camera);

// Depth 0 is invalid. Pixels are those of the image as recorded: with lens distortion each is
// back-projected along its undistorted ray (PixelRays, computed for the call).
StatusOr<CameraCloud> BackProjectKeyframe(const cv::Mat& depth_mm, const cv::Mat& bgr,
                                          const PinholeCamera& camera,
                                          const BackProjectionOptions& options = {});

}  // namespace ccmd
