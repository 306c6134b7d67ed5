#include "libccmd/features/feature_grid.h"

#include <algorithm>
#include <cmath>

namespace ccmd {

FeatureGrid::FeatureGrid(const std::vector<cv::KeyPoint>& keypoints, int width, int height,
                         int cell)
    : keypoints_(&keypoints), cell_(cell) {
  cols_ = std::max(1, (width + cell - 1) / cell);
  rows_ = std::max(1, (height + cell - 1) / cell);
  cells_.assign(static_cast<std::size_t>(cols_) * rows_, {});
  for (int i = 0; i < static_cast<int>(keypoints.size()); ++i) {
    const int cx = std::clamp(static_cast<int>(keypoints[i].pt.x) / cell_, 0, cols_ - 1);
    const int cy = std::clamp(static_cast<int>(keypoints[i].pt.y) / cell_, 0, rows_ - 1);
    cells_[static_cast<std::size_t>(cy) * cols_ + cx].push_back(i);
  }
}

std::vector<int> FeatureGrid::FeaturesInArea(float u, float v, float radius, int min_level,
                                             int max_level) const {
  std::vector<int> found;
  if (!keypoints_) return found;
  const int x0 = std::max(0, static_cast<int>(std::floor((u - radius) / cell_)));
  const int x1 = std::min(cols_ - 1, static_cast<int>(std::floor((u + radius) / cell_)));
  const int y0 = std::max(0, static_cast<int>(std::floor((v - radius) / cell_)));
  const int y1 = std::min(rows_ - 1, static_cast<int>(std::floor((v + radius) / cell_)));
  if (x0 > x1 || y0 > y1) return found;
  const float r2 = radius * radius;
  for (int cy = y0; cy <= y1; ++cy) {
    for (int cx = x0; cx <= x1; ++cx) {
      for (int i : cells_[static_cast<std::size_t>(cy) * cols_ + cx]) {
        const cv::KeyPoint& k = (*keypoints_)[i];
        if (k.octave < min_level || (max_level >= 0 && k.octave > max_level)) continue;
        const float dx = k.pt.x - u, dy = k.pt.y - v;
        if (dx * dx + dy * dy <= r2) found.push_back(i);
      }
    }
  }
  return found;
}

}  // namespace ccmd
