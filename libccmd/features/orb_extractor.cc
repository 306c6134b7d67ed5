#include "libccmd/features/orb_extractor.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/util/logging.h"

namespace ccmd {
namespace {

constexpr int kPatchRadius = 15;  // orientation patch (the 31-pixel ORB patch)
constexpr int kHarrisRadius = 3;  // 7x7 block for the Harris measure
constexpr double kHarrisK = 0.04;

}  // namespace

Status OrbOptions::Validate() const {
  if (features < 50 || features > 20000)
    return InvalidArgument("ORB features must be in [50, 20000]");
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
    circle_extent_[dy] = static_cast<int>(
        std::floor(std::sqrt((kPatchRadius + 0.5) * (kPatchRadius + 0.5) - dy * dy)));
  }
}

namespace {

// The grid DistributeKeypoints spreads keypoints over: about `count` square cells.
struct CellGrid {
  CellGrid(int width, int height, int count)
      : cell(std::max(8.0, std::sqrt(static_cast<double>(width) * height / count))),
        cols(std::max(1, static_cast<int>(std::ceil(width / cell)))),
        rows(std::max(1, static_cast<int>(std::ceil(height / cell)))) {}
  int Column(float x) const { return std::clamp(static_cast<int>(x / cell), 0, cols - 1); }
  int Row(float y) const { return std::clamp(static_cast<int>(y / cell), 0, rows - 1); }
  int Index(const cv::Point2f& p) const { return Row(p.y) * cols + Column(p.x); }
  int size() const { return cols * rows; }

  double cell;
  int cols, rows;
};

}  // namespace

std::vector<cv::KeyPoint> DistributeKeypoints(std::vector<cv::KeyPoint> candidates, int width,
                                              int height, int count) {
  if (count <= 0 || candidates.empty()) return {};
  if (static_cast<int>(candidates.size()) <= count) return candidates;
  const CellGrid grid(width, height, count);
  // Strongest first, so the first keypoint seen in a cell is its best.
  std::stable_sort(
      candidates.begin(), candidates.end(),
      [](const cv::KeyPoint& a, const cv::KeyPoint& b) { return a.response > b.response; });
  std::vector<int> taken(grid.size(), 0);
  std::vector<int> rank(candidates.size());
  for (std::size_t i = 0; i < candidates.size(); ++i)
    rank[i] = taken[grid.Index(candidates[i].pt)]++;
  std::vector<std::size_t> order(candidates.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  // Rank within the cell first, strength second (order is already by strength).
  std::stable_sort(order.begin(), order.end(),
                   [&](std::size_t a, std::size_t b) { return rank[a] < rank[b]; });
  std::vector<cv::KeyPoint> kept;
  kept.reserve(count);
  for (int i = 0; i < count; ++i) kept.push_back(candidates[order[i]]);
  return kept;
}

namespace {

// The Harris measure of cv::cornerHarris(blockSize 7, ksize 3, k) at one pixel, from the
// image's Sobel derivatives (CV_16S): the same value, computed only where FAST found a
// corner instead of over the whole level.
float HarrisAt(const cv::Mat& dx, const cv::Mat& dy, int x, int y, double k) {
  std::int32_t a = 0, b = 0, c = 0;  // at most 49 * 1020^2, which fits
  for (int v = -kHarrisRadius; v <= kHarrisRadius; ++v) {
    const std::int16_t* gx = dx.ptr<std::int16_t>(y + v) + x;
    const std::int16_t* gy = dy.ptr<std::int16_t>(y + v) + x;
    for (int u = -kHarrisRadius; u <= kHarrisRadius; ++u) {
      const std::int32_t ix = gx[u], iy = gy[u];
      a += ix * ix;
      b += ix * iy;
      c += iy * iy;
    }
  }
  // cv::cornerHarris scales the derivatives of 8-bit images by 1 / (4 * blockSize * 255).
  constexpr double kScale = 1.0 / (4.0 * (2 * kHarrisRadius + 1) * 255.0);
  constexpr double kScale2 = kScale * kScale;
  const double A = a * kScale2, B = b * kScale2, C = c * kScale2;
  return static_cast<float>(A * C - B * B - k * (A + C) * (A + C));
}

// A level's image-sized buffers (its image, its derivatives), kept by each thread from frame to
// frame. Made afresh for every frame they are new pages each time wherever the allocator hands
// blocks of their size back to the system: over a megabyte of page faults per frame, which made
// the first 600 frames' extraction 1.6 times slower than the same frames extracted again.
struct LevelBuffers {
  cv::Mat image, dx, dy;
};

LevelBuffers& ThreadBuffers(int level) {
  static thread_local std::vector<LevelBuffers> buffers;
  if (buffers.size() <= static_cast<std::size_t>(level)) buffers.resize(level + 1);
  return buffers[level];
}

}  // namespace

std::vector<cv::KeyPoint> OrbExtractor::FindCorners(const cv::Mat& image, int count) const {
  const int e = options_.edge;
  const cv::Rect inner(e - 3, e - 3, image.cols - 2 * e + 6, image.rows - 2 * e + 6);
  // FAST with non-maximum suppression in `roi`; keeps the corners `edge` pixels inside the
  // level for which keep(corner) holds, in level coordinates.
  auto fast = [&](const cv::Rect& roi, int threshold, std::vector<cv::KeyPoint>* out,
                  const auto& keep) {
    std::vector<cv::KeyPoint> found;
    cv::FAST(image(roi), found, threshold, /*nonmaxSuppression=*/true);
    for (cv::KeyPoint& k : found) {
      k.pt.x += roi.x;
      k.pt.y += roi.y;
      if (k.pt.x < e || k.pt.y < e || k.pt.x >= image.cols - e || k.pt.y >= image.rows - e)
        continue;
      if (keep(k)) out->push_back(k);
    }
  };
  const auto all = [](const cv::KeyPoint&) { return true; };
  std::vector<cv::KeyPoint> corners;
  const int strong_threshold = options_.fast_threshold,
            weak_threshold = options_.min_fast_threshold;
  fast(inner, strong_threshold, &corners, all);
  if (static_cast<int>(corners.size()) <= count || weak_threshold == strong_threshold) {
    if (weak_threshold < strong_threshold) {
      corners.clear();
      fast(inner, weak_threshold, &corners, all);
    }
    return corners;
  }
  // The distribution takes the best corner of every cell, then the second best, and so on,
  // strong corners before weak ones at each rank. Let `cutoff` be the first rank by which the
  // strong corners alone fill the budget: a weak corner of rank r comes after all strong
  // corners of ranks up to r, so it is never chosen when r >= cutoff - 1, and a cell's weak
  // corners rank after its strong ones. FAST runs again at the low threshold only in cells
  // with fewer than cutoff - 1 strong corners. A corner's score and suppression do not depend
  // on the threshold, and each pass sees 4 pixels around its cells, so the keypoints chosen
  // are those one low-threshold pass over the whole level gives.
  const CellGrid grid(image.cols, image.rows, count);
  std::vector<int> strong(grid.size(), 0);
  for (const cv::KeyPoint& k : corners) strong[grid.Index(k.pt)]++;
  int cutoff = 0;
  for (int filled = 0; filled < count; ++cutoff) {
    filled = 0;
    for (int n : strong) filled += std::min(n, cutoff + 1);
  }
  constexpr int kMargin = 4;  // the 3-pixel FAST circle and the suppression neighbours
  for (int row = 0; row < grid.rows; ++row) {
    for (int col = 0; col < grid.cols;) {
      if (strong[row * grid.cols + col] >= cutoff - 1) {
        ++col;
        continue;
      }
      const int first = col;
      while (col < grid.cols && strong[row * grid.cols + col] < cutoff - 1) ++col;
      const int x0 = static_cast<int>(std::floor(first * grid.cell)) - kMargin;
      const int x1 = static_cast<int>(std::ceil(col * grid.cell)) + kMargin;
      const int y0 = static_cast<int>(std::floor(row * grid.cell)) - kMargin;
      const int y1 = static_cast<int>(std::ceil((row + 1) * grid.cell)) + kMargin;
      const cv::Rect roi = cv::Rect(x0, y0, x1 - x0, y1 - y0) & inner;
      if (roi.width < 7 || roi.height < 7) continue;
      fast(roi, weak_threshold, &corners, [&](const cv::KeyPoint& k) {
        const int c = grid.Column(k.pt.x);
        return k.response < strong_threshold && grid.Row(k.pt.y) == row && c >= first && c < col;
      });
    }
  }
  // Raster order, as one pass gives them (the distribution's sort is stable).
  std::vector<std::pair<int, int>> raster(corners.size());
  for (std::size_t i = 0; i < corners.size(); ++i) {
    raster[i] = {cvRound(corners[i].pt.y) * image.cols + cvRound(corners[i].pt.x),
                 static_cast<int>(i)};
  }
  std::sort(raster.begin(), raster.end());
  std::vector<cv::KeyPoint> ordered;
  ordered.reserve(corners.size());
  for (const auto& [key, i] : raster) ordered.push_back(corners[i]);
  return ordered;
}

std::vector<cv::KeyPoint> OrbExtractor::DetectLevel(const cv::Mat& image, int level) const {
  const int e = options_.edge;
  const int count = level_budget_[level];
  if (image.cols <= 2 * e || image.rows <= 2 * e || count <= 0) return {};
  std::vector<cv::KeyPoint> corners = FindCorners(image, count);
  // Rank by the Harris measure, which is far more stable from frame to frame than the FAST
  // score (OpenCV's ORB makes the same choice): selection repeatability is what lets the next
  // frame find the same map points.
  LevelBuffers& buffers = ThreadBuffers(level);
  const cv::Mat& dx = buffers.dx;
  const cv::Mat& dy = buffers.dy;
  cv::spatialGradient(image, buffers.dx, buffers.dy, 3);
  for (cv::KeyPoint& k : corners) {
    const bool strong = k.response >= options_.fast_threshold;
    k.response = HarrisAt(dx, dy, cvRound(k.pt.x), cvRound(k.pt.y), kHarrisK);
    // Corners under the preferred FAST threshold rank after all stronger ones.
    if (!strong) k.response -= 1e9f;
  }
  std::vector<cv::KeyPoint> kept =
      DistributeKeypoints(std::move(corners), image.cols, image.rows, count);
  for (cv::KeyPoint& k : kept) {
    k.angle = Orientation(image, cvRound(k.pt.x), cvRound(k.pt.y));
    k.octave = level;
    k.size = 31.0f * scale_[level];
    if (k.response < -1e8f) k.response += 1e9f;
  }
  return kept;
}

float OrbExtractor::Orientation(const cv::Mat& image, int x0, int y0) const {
  // Intensity centroid of the circular patch; rows dy and -dy share their half-width, so
  // they are summed together.
  const uchar* centre = image.ptr<uchar>(y0) + x0;
  const std::size_t step = image.step1();
  int m10 = 0, m01 = 0;
  for (int dx = -kPatchRadius; dx <= kPatchRadius; ++dx) m10 += dx * centre[dx];
  for (int dy = 1; dy <= kPatchRadius; ++dy) {
    const uchar* below = centre + dy * step;
    const uchar* above = centre - dy * step;
    const int w = circle_extent_[dy];
    int sum = 0, difference = 0;
    for (int dx = -w; dx <= w; ++dx) {
      const int b = below[dx], a = above[dx];
      sum += dx * (b + a);
      difference += b - a;
    }
    m10 += sum;
    m01 += dy * difference;
  }
  float angle = static_cast<float>(std::atan2(static_cast<double>(m01), static_cast<double>(m10)) *
                                   180.0 / CV_PI);
  if (angle < 0) angle += 360.0f;
  return angle;
}

OrbFeatures OrbExtractor::Extract(const cv::Mat& gray) const {
  CCMD_CHECK(gray.type() == CV_8UC1) << "ORB extraction needs an 8-bit grey image";
  const int L = options_.levels;
  // OpenCV's ORB computes the rotated-BRIEF descriptors (32 bytes) from each level image as
  // given, blurring it once; keypoints are passed in level coordinates with octave 0, so it
  // neither rebuilds the pyramid nor moves them. It drops keypoints closer to the border than
  // its edge threshold; ours keep `edge` pixels away on every level.
  static thread_local cv::Ptr<cv::ORB> orb;
  if (!orb || orb->getEdgeThreshold() != options_.edge) {
    orb = cv::ORB::create(options_.features, options_.scale_factor, 1, options_.edge, 0, 2,
                          cv::ORB::HARRIS_SCORE, 31, options_.fast_threshold);
  }
  OrbFeatures features;
  std::vector<cv::Mat> descriptors;
  cv::Mat image = gray;
  for (int level = 0; level < L; ++level) {
    if (level > 0) {
      const cv::Size size(cvRound(gray.cols / scale_[level]), cvRound(gray.rows / scale_[level]));
      cv::Mat& smaller = ThreadBuffers(level).image;
      cv::resize(image, smaller, size, 0, 0, cv::INTER_LINEAR);
      image = smaller;
    }
    std::vector<cv::KeyPoint> keypoints = DetectLevel(image, level);
    if (keypoints.empty()) continue;
    for (cv::KeyPoint& k : keypoints) k.octave = 0;
    cv::Mat level_descriptors;
    orb->compute(image, keypoints, level_descriptors);
    // Level pixel centres map to level-0 coordinates as (x + 0.5) * s - 0.5 (the pyramid
    // resizes area-consistently); plain x * s would shift coarse octaves by up to a pixel. s is
    // the level's own size ratio, per axis: its size is rounded to whole pixels, so it differs
    // from the nominal scale_[level] by up to 0.2 % (640 / 179 = 3.575 for 1.2^7 = 3.583), over
    // a pixel at the far side of the image.
    const float sx = static_cast<float>(gray.cols) / static_cast<float>(image.cols);
    const float sy = static_cast<float>(gray.rows) / static_cast<float>(image.rows);
    for (cv::KeyPoint& k : keypoints) {
      k.octave = level;
      k.pt.x = (k.pt.x + 0.5f) * sx - 0.5f;
      k.pt.y = (k.pt.y + 0.5f) * sy - 0.5f;
      features.keypoints.push_back(k);
    }
    descriptors.push_back(level_descriptors);
  }
  if (descriptors.empty()) {
    features.descriptors = cv::Mat(0, 32, CV_8U);
  } else {
    cv::vconcat(descriptors, features.descriptors);
  }
  return features;
}

}  // namespace ccmd
