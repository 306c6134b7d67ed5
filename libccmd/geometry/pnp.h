#pragma once

// A camera's pose from 3D points and the pixels that see them, with no prior: EPnP inside
// RANSAC (OpenCV). Relocalisation, the tracker's start after a gap and loop verification use it.
// RANSAC draws from OpenCV's per-thread generator: a caller that needs the same answer every
// run seeds it (cv::setRNGSeed).

#include <optional>
#include <vector>

#include <opencv2/core/types.hpp>

#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"

namespace ccmd {

struct PnpRansacOptions {
  int iterations = 200;
  float reprojection_px = 4.0f;  // inlier threshold
  double confidence = 0.99;
  int min_inliers = 15;  // fewer: no pose
};

// T_cam_world for the ideal pinhole `camera` (pixels already undistorted), or nullopt when
// RANSAC finds no pose that at least `min_inliers` points agree with. `inliers`: the indices
// of the points that agree.
std::optional<Pose> SolvePnpRansac(const std::vector<cv::Point3f>& object,
                                   const std::vector<cv::Point2f>& image,
                                   const PinholeCamera& camera, const PnpRansacOptions& options,
                                   std::vector<int>* inliers = nullptr);

}  // namespace ccmd
