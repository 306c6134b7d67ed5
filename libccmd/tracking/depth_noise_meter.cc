#include "libccmd/tracking/depth_noise_meter.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <utility>

namespace ccmd {
namespace {

constexpr int kBlock = 8;
constexpr int kPixels = kBlock * kBlock;
constexpr int kDegreesOfFreedom = kPixels - 3;  // a plane has three parameters
constexpr double kBinWidth = 0.25;              // metres
constexpr int kMinBlocksPerBin = 30;
constexpr double kQuantile = 0.25;
constexpr double kQuantileNormal = -0.6745;  // the standard normal's 25 % quantile

// Where the kQuantile quantile of a block's rms falls, in sigmas, when the block holds nothing
// but independent noise: sqrt(chi-square(k) / k) by the Wilson-Hilferty approximation.
double PureNoiseQuantile() {
  const double k = kDegreesOfFreedom;
  const double s = std::sqrt(2.0 / (9.0 * k));
  const double cube = 1.0 - 2.0 / (9.0 * k) + kQuantileNormal * s;
  return std::sqrt(cube * cube * cube);
}

// Offsets of a block's pixels from its centre: -3.5 .. 3.5. Their squares summed over the
// block's 64 pixels (8 rows of 42), the normal equation of a plane's slope.
constexpr double kSumOfSquaredOffsets = kBlock * 42.0;

DepthNoise FitModel(const std::vector<DepthNoiseBin>& bins) {
  // Relative residuals: minimise sum n ((s0 + s2 z^2) / sigma - 1)^2.
  double a11 = 0, a12 = 0, a22 = 0, b1 = 0, b2 = 0;
  for (const DepthNoiseBin& bin : bins) {
    const double x1 = 1.0 / bin.sigma;
    const double x2 = bin.depth * bin.depth / bin.sigma;
    a11 += bin.blocks * x1 * x1;
    a12 += bin.blocks * x1 * x2;
    a22 += bin.blocks * x2 * x2;
    b1 += bin.blocks * x1;
    b2 += bin.blocks * x2;
  }
  DepthNoise fitted;
  const double det = a11 * a22 - a12 * a12;
  fitted.sigma_0 = det > 1e-9 * a11 * a22 ? (b1 * a22 - b2 * a12) / det : -1;
  fitted.sigma_2 = det > 1e-9 * a11 * a22 ? (a11 * b2 - a12 * b1) / det : -1;
  if (fitted.sigma_0 < 0) {  // one term alone: whichever describes the bins without the other
    fitted.sigma_0 = 0;
    fitted.sigma_2 = b2 / a22;
  }
  if (fitted.sigma_2 < 0) {
    fitted.sigma_0 = b1 / a11;
    fitted.sigma_2 = 0;
  }
  return fitted;
}

}  // namespace

void DepthNoiseMeter::Add(const cv::Mat& depth) {
  if (depth.type() != CV_16UC1) return;  // not a depth image a source delivers
  ++frames_;
  float inverse[kPixels];
  for (int y0 = 0; y0 + kBlock <= depth.rows; y0 += kBlock) {
    for (int x0 = 0; x0 + kBlock <= depth.cols; x0 += kBlock) {
      // Inverse depth is linear in the pixel coordinates on a plane: fit it, compare depths.
      bool complete = true;
      double sum = 0, sum_u = 0, sum_v = 0;
      for (int v = 0; v < kBlock && complete; ++v) {
        const std::uint16_t* row = depth.ptr<std::uint16_t>(y0 + v) + x0;
        for (int u = 0; u < kBlock; ++u) {
          if (row[u] == 0) {
            complete = false;
            break;
          }
          const float w = 1000.0f / row[u];
          inverse[v * kBlock + u] = w;
          sum += w;
          sum_u += (u - 3.5) * w;
          sum_v += (v - 3.5) * w;
        }
      }
      if (!complete) continue;
      const double mean = sum / kPixels;
      const double slope_u = sum_u / kSumOfSquaredOffsets;
      const double slope_v = sum_v / kSumOfSquaredOffsets;
      double squared = 0;
      for (int v = 0; v < kBlock && complete; ++v) {
        for (int u = 0; u < kBlock; ++u) {
          const double fitted = mean + slope_u * (u - 3.5) + slope_v * (v - 3.5);
          if (fitted <= 0) {
            complete = false;
            break;
          }
          const double r = 1.0 / inverse[v * kBlock + u] - 1.0 / fitted;
          squared += r * r;
        }
      }
      if (!complete) continue;
      blocks_.push_back({static_cast<float>(1.0 / mean),
                         static_cast<float>(std::sqrt(squared / kDegreesOfFreedom))});
    }
  }
}

DepthNoiseMeasurement DepthNoiseMeter::Measure() const {
  DepthNoiseMeasurement out;
  out.blocks = static_cast<int>(blocks_.size());
  std::vector<std::vector<Block>> ranges;
  for (const Block& b : blocks_) {
    const std::size_t bin = static_cast<std::size_t>(b.depth / kBinWidth);
    if (bin >= ranges.size()) ranges.resize(bin + 1);
    ranges[bin].push_back(b);
  }
  const double pure_noise = PureNoiseQuantile();
  for (std::vector<Block>& range : ranges) {
    const int n = static_cast<int>(range.size());
    if (n < kMinBlocksPerBin) continue;
    const int q = static_cast<int>(kQuantile * (n - 1));
    std::nth_element(range.begin(), range.begin() + q, range.end(),
                     [](const Block& a, const Block& b) { return a.rms < b.rms; });
    const double rms = range[q].rms;
    std::nth_element(range.begin(), range.begin() + n / 2, range.end(),
                     [](const Block& a, const Block& b) { return a.depth < b.depth; });
    if (rms <= 0) continue;  // exactly planar: quantised depth with no noise at all
    out.bins.push_back({range[n / 2].depth, rms / pure_noise, n});
  }
  if (out.Enough()) out.fitted = FitModel(out.bins);
  return out;
}

double DepthNoiseMeasurement::RatioTo(const DepthNoise& model) const {
  std::vector<std::pair<double, int>> ratios;  // (ratio, blocks)
  int total = 0;
  for (const DepthNoiseBin& bin : bins) {
    ratios.push_back({bin.sigma / model.Sigma(bin.depth), bin.blocks});
    total += bin.blocks;
  }
  if (ratios.empty()) return 0;
  std::sort(ratios.begin(), ratios.end());
  int seen = 0;
  for (const auto& [ratio, blocks] : ratios) {
    seen += blocks;
    if (2 * seen >= total) return ratio;
  }
  return ratios.back().first;
}

std::string DepthNoiseAdvice(const DepthNoiseMeasurement& measured, const DepthNoise& model) {
  const double ratio = measured.RatioTo(model);
  if (DepthNoiseModelFits(ratio)) return {};
  char text[400];
  const char* what = ratio > kNoisierThanModel
                         ? "%.1f times as noisy as the config's DepthNoise model says: its depth "
                           "is weighed as more precise than it is"
                         : "%.2f times as noisy as the config's DepthNoise model says (rendered "
                           "or exact depth?): its depth is weighed as less precise than it is";
  int n = std::snprintf(text, sizeof text, what, ratio);
  std::snprintf(text + n, sizeof text - n,
                ". Unless the config chose its model knowingly, keys that describe this depth: "
                "DepthNoise.sigma0: %.2g  DepthNoise.sigma2: %.2g (ccmd_camera --check-noise "
                "measures it per range)",
                measured.fitted.sigma_0, measured.fitted.sigma_2);
  return std::string("the depth is ") + text;
}

}  // namespace ccmd
