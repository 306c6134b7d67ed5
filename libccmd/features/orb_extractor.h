#pragma once

// ORB features spread over the image, as the ORB-SLAM front-ends extract them: FAST corners
// on an image pyramid, a per-level budget, spatial distribution so that textured corners of
// the image do not take all the features, intensity-centroid orientation, and the rotated
// BRIEF descriptor (computed by OpenCV's ORB on each blurred level for the keypoints we
// choose). Every step runs once per level, and only where it is needed: the Harris measure
// that ranks FAST corners is evaluated at the corners, not over the whole image.

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct OrbOptions {
  int features = 1000;
  float scale_factor = 1.2f;
  int levels = 8;
  int fast_threshold = 20;     // preferred corners
  int min_fast_threshold = 7;  // accepted where nothing stronger exists
  int edge = 19;               // keypoints keep this far from each level's border (pixels)

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct OrbFeatures {
  std::vector<cv::KeyPoint> keypoints;  // level-0 pixel coordinates; octave = pyramid level
  cv::Mat descriptors;                  // N x 32, CV_8U, row i for keypoints[i]
};

class OrbExtractor {
 public:
  explicit OrbExtractor(const OrbOptions& options = {});

  // Extracts from an 8-bit grey image. Thread-safe: no state changes; each calling thread keeps
  // its own pyramid and gradient buffers (about 5 MB at 640x480) for its next call.
  OrbFeatures Extract(const cv::Mat& gray) const;

  const OrbOptions& options() const { return options_; }
  // Scale of each level relative to level 0 (1, 1.2, 1.44, ...) and its square.
  const std::vector<float>& scale() const { return scale_; }
  const std::vector<float>& sigma2() const { return sigma2_; }
  const std::vector<float>& inv_sigma2() const { return inv_sigma2_; }
  float log_scale_factor() const { return log_scale_factor_; }

  // Budget of features per level (sums to options.features).
  const std::vector<int>& level_budget() const { return level_budget_; }

 private:
  // FAST corners of one level that the distribution of `count` keypoints may choose
  // (response: FAST score), in raster order, level coordinates.
  std::vector<cv::KeyPoint> FindCorners(const cv::Mat& image, int count) const;
  // FAST corners of one level, ranked and distributed, with orientation; level coordinates.
  std::vector<cv::KeyPoint> DetectLevel(const cv::Mat& image, int level) const;
  // Intensity-centroid angle (degrees) of the patch around (x, y).
  float Orientation(const cv::Mat& image, int x, int y) const;

  OrbOptions options_;
  std::vector<float> scale_, sigma2_, inv_sigma2_;
  std::vector<int> level_budget_;
  float log_scale_factor_ = 0;
  std::vector<int> circle_extent_;  // half-width of the orientation patch per row offset
};

// Keeps `count` keypoints spread over a width x height area: the strongest keypoint of each
// grid cell first, then the second strongest of each cell, and so on (cells sized so that
// there are about `count` of them). Exposed for tests.
std::vector<cv::KeyPoint> DistributeKeypoints(std::vector<cv::KeyPoint> candidates, int width,
                                              int height, int count);

}  // namespace ccmd
