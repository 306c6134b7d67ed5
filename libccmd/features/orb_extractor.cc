#include "libccmd/features/orb_extractor.h"

#include <algorithm>
#include <cmath>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/util/logging.h"

namespace ccmd {
namespace {

constexpr int kPatchRadius = 15;  // orientation patch (the 31-pixel ORB patch)

}  // namespace

Status OrbOptions::Validate() const {
  if (features < 50 || features > 20000) return InvalidArgument("ORB features must be in [50, 20000]");
  if (!(scale_factor > 1.0f && scale_factor < 2.0f)) {
    return InvalidArgument("ORB scale factor must be in (1, 2)");
  }
  if (levels < 1 || levels > 16) return InvalidArgument("ORB levels must be in [1, 16]");
  if (min_fast_threshold < 1 || fast_threshold < min_fast_threshold) {
    return InvalidArgument("FAST thresholds must satisfy 1 <= min <= preferred");
  }
  if (edge < 16) return InvalidArgument("edge must be at least 16 pixels for the 31-pixel patch");
  return Status::Ok();
}

void OrbOptions::Describe(OptionsWriter* out) const {
  out->Add("features", features);
  out->Add("scale_factor", scale_factor);
  out->Add("levels", levels);
  out->Add("fast_threshold", fast_threshold);
  out->Add("min_fast_threshold", min_fast_threshold);
  out->Add("edge", edge);
}

OrbExtractor::OrbExtractor(const OrbOptions& options) : options_(options) {
  const Status valid = options_.Validate();
  CCMD_CHECK(valid.ok()) << valid.message();
  const int L = options_.levels;
  scale_.resize(L);
  sigma2_.resize(L);
  inv_sigma2_.resize(L);
  for (int i = 0; i < L; ++i) {
    scale_[i] = std::pow(options_.scale_factor, static_cast<float>(i));
    sigma2_[i] = scale_[i] * scale_[i];
    inv_sigma2_[i] = 1.0f / sigma2_[i];
  }
  log_scale_factor_ = std::log(options_.scale_factor);
  // Geometric budget: each level gets 1/scale_factor of the previous one (its image is that
  // much smaller per side); the last level takes what is left.
  const double f = 1.0 / options_.scale_factor;
  double per_level = options_.features * (1 - f) / (1 - std::pow(f, L));
  int assigned = 0;
  level_budget_.resize(L);
  for (int i = 0; i < L - 1; ++i) {
    level_budget_[i] = static_cast<int>(std::round(per_level));
    assigned += level_budget_[i];
    per_level *= f;
  }
  level_budget_[L - 1] = std::max(0, options_.features - assigned);
  // Row half-widths of the circular orientation patch.
  circle_extent_.resize(kPatchRadius + 1);
  for (int dy = 0; dy <= kPatchRadius; ++dy) {
    circle_extent_[dy] = static_cast<int>(std::floor(std::sqrt((kPatchRadius + 0.5) * (kPatchRadius + 0.5) - dy * dy)));
  }
}

std::vector<cv::KeyPoint> DistributeKeypoints(std::vector<cv::KeyPoint> candidates, int width,
                                              int height, int count) {
  if (count <= 0 || candidates.empty()) return {};
  if (static_cast<int>(candidates.size()) <= count) return candidates;
  const double cell = std::max(8.0, std::sqrt(static_cast<double>(width) * height / count));
  const int cols = std::max(1, static_cast<int>(std::ceil(width / cell)));
  const int rows = std::max(1, static_cast<int>(std::ceil(height / cell)));
  // Strongest first, so the first keypoint seen in a cell is its best.
  std::stable_sort(candidates.begin(), candidates.end(),
                   [](const cv::KeyPoint& a, const cv::KeyPoint& b) { return a.response > b.response; });
  std::vector<int> taken(static_cast<std::size_t>(cols) * rows, 0);
  std::vector<int> rank(candidates.size());
  for (std::size_t i = 0; i < candidates.size(); ++i) {
    const int cx = std::clamp(static_cast<int>(candidates[i].pt.x / cell), 0, cols - 1);
    const int cy = std::clamp(static_cast<int>(candidates[i].pt.y / cell), 0, rows - 1);
    rank[i] = taken[static_cast<std::size_t>(cy) * cols + cx]++;
  }
  std::vector<std::size_t> order(candidates.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  // Rank within the cell first, strength second (order is already by strength).
  std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return rank[a] < rank[b]; });
  std::vector<cv::KeyPoint> kept;
  kept.reserve(count);
  for (int i = 0; i < count; ++i) kept.push_back(candidates[order[i]]);
  return kept;
}

OrbFeatures OrbExtractor::Extract(const cv::Mat& gray) const {
  CCMD_CHECK(gray.type() == CV_8UC1) << "ORB extraction needs an 8-bit grey image";
  const int L = options_.levels;
  std::vector<cv::Mat> pyramid(L);
  pyramid[0] = gray;
  for (int i = 1; i < L; ++i) {
    const cv::Size size(cvRound(gray.cols / scale_[i]), cvRound(gray.rows / scale_[i]));
    cv::resize(pyramid[i - 1], pyramid[i], size, 0, 0, cv::INTER_LINEAR);
  }

  std::vector<cv::KeyPoint> all;
  all.reserve(options_.features);
  const int e = options_.edge;
  for (int level = 0; level < L; ++level) {
    const cv::Mat& image = pyramid[level];
    if (image.cols <= 2 * e || image.rows <= 2 * e) continue;
    const cv::Mat inner = image(cv::Rect(e - 3, e - 3, image.cols - 2 * e + 6, image.rows - 2 * e + 6));
    std::vector<cv::KeyPoint> corners;
    // One pass at the low threshold; the distribution prefers strong corners where there are
    // any and accepts weak ones where there are not.
    cv::FAST(inner, corners, options_.min_fast_threshold, /*nonmaxSuppression=*/true);
    // Rank by the Harris measure, which is far more stable from frame to frame than the
    // FAST score (OpenCV's ORB makes the same choice): selection repeatability is what lets
    // the next frame find the same map points.
    cv::Mat harris;
    cv::cornerHarris(image, harris, 7, 3, 0.04);
    std::vector<cv::KeyPoint> inside;
    inside.reserve(corners.size());
    for (cv::KeyPoint& k : corners) {
      k.pt.x += e - 3;
      k.pt.y += e - 3;
      if (k.pt.x < e || k.pt.y < e || k.pt.x >= image.cols - e || k.pt.y >= image.rows - e) continue;
      const bool strong = k.response >= options_.fast_threshold;
      k.response = harris.at<float>(cvRound(k.pt.y), cvRound(k.pt.x));
      // Corners under the preferred FAST threshold rank after all stronger ones.
      if (!strong) k.response -= 1e9f;
      inside.push_back(k);
    }
    std::vector<cv::KeyPoint> kept = DistributeKeypoints(std::move(inside), image.cols, image.rows,
                                                         level_budget_[level]);
    for (cv::KeyPoint& k : kept) {
      // Intensity-centroid orientation on the level image.
      const int x0 = cvRound(k.pt.x), y0 = cvRound(k.pt.y);
      double m01 = 0, m10 = 0;
      for (int dy = -kPatchRadius; dy <= kPatchRadius; ++dy) {
        const uchar* row = image.ptr<uchar>(y0 + dy);
        const int w = circle_extent_[std::abs(dy)];
        for (int dx = -w; dx <= w; ++dx) {
          const int v = row[x0 + dx];
          m10 += dx * v;
          m01 += dy * v;
        }
      }
      float angle = static_cast<float>(std::atan2(m01, m10) * 180.0 / CV_PI);
      if (angle < 0) angle += 360.0f;
      k.angle = angle;
      k.octave = level;
      k.size = 31.0f * scale_[level];
      // Level pixel centres map to level-0 coordinates as (x + 0.5) * s - 0.5 (the pyramid
      // resizes area-consistently); plain x * s would shift coarse octaves by up to a pixel.
      k.pt.x = (k.pt.x + 0.5f) * scale_[level] - 0.5f;
      k.pt.y = (k.pt.y + 0.5f) * scale_[level] - 0.5f;
      if (k.response < -1e8f) k.response += 1e9f;
      all.push_back(k);
    }
  }

  OrbFeatures features;
  if (all.empty()) {
    features.descriptors = cv::Mat(0, 32, CV_8U);
    return features;
  }
  // OpenCV's ORB computes rotated-BRIEF descriptors for the given keypoints, using their
  // octave and angle. It groups keypoints by octave (ours already are, in order) and drops any
  // too close to the image border (ours keep `edge` pixels away on every level).
  static thread_local cv::Ptr<cv::ORB> orb;
  if (!orb || orb->getNLevels() != L || orb->getScaleFactor() != options_.scale_factor) {
    orb = cv::ORB::create(options_.features, options_.scale_factor, L, options_.edge, 0, 2,
                          cv::ORB::HARRIS_SCORE, 31, options_.fast_threshold);
  }
  features.keypoints = std::move(all);
  orb->compute(gray, features.keypoints, features.descriptors);
  return features;
}

}  // namespace ccmd
