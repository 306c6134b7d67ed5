#pragma once

// Keypoints of one image bucketed on a coarse grid, for fast "features near (u, v)" queries
// during projection search.

#include <vector>

#include <opencv2/core.hpp>

namespace ccmd {

class FeatureGrid {
 public:
  FeatureGrid() = default;
  FeatureGrid(const std::vector<cv::KeyPoint>& keypoints, int width, int height, int cell = 10);

  // Indices of keypoints within `radius` pixels of (u, v) (square window, then exact circle),
  // restricted to octaves [min_level, max_level] (max_level < 0: no upper limit).
  std::vector<int> FeaturesInArea(float u, float v, float radius, int min_level = 0,
                                  int max_level = -1) const;

 private:
  const std::vector<cv::KeyPoint>* keypoints_ = nullptr;
  int cell_ = 10, cols_ = 0, rows_ = 0;
  std::vector<std::vector<int>> cells_;
};

}  // namespace ccmd
