#include "libccmd/codec/depth_downsample.h"

#include <algorithm>
#include <cstdint>
#include <string>

namespace ccmd {

const char* DownsampleMethodName(DownsampleMethod method) {
  switch (method) {
    case DownsampleMethod::kMedianValid:
      return "median-valid";
    case DownsampleMethod::kNearestValid:
      return "nearest-valid";
    case DownsampleMethod::kTopLeft:
      return "top-left";
  }
  return "?";
}

int DownsampleFactorForRate(double r) {
  if (r == 1.0) return 1;
  if (r == 0.5) return 2;
  if (r == 0.25) return 4;
  return 0;
}

namespace {

// Sorts up to 16 values in place (insertion sort: tiny inputs, branch-predictable).
void SortSmall(std::uint16_t* v, int n) {
  for (int i = 1; i < n; ++i) {
    const std::uint16_t x = v[i];
    int j = i - 1;
    while (j >= 0 && v[j] > x) {
      v[j + 1] = v[j];
      --j;
    }
    v[j + 1] = x;
  }
}

// The median of n sorted depths. With an even count the two middle depths are averaged when
// they lie on one surface: on a plane the block's depths are symmetric about the depth at its
// centre, where the output pixel's ray passes, so their mean is that depth, while either of
// them alone is off by up to half a pixel's depth step (3 mm on a floor seen at 2 m). Middle
// depths more than 3 % apart straddle an edge (a plane seen at 75 degrees by a 640-pixel-wide
// camera changes by about 1 % per pixel): the nearer is kept. Halves round to even, so that
// rounding adds no bias.
std::uint16_t MedianOfSorted(const std::uint16_t* v, int n) {
  const int lower = v[(n - 1) / 2];
  if (n % 2) return static_cast<std::uint16_t>(lower);
  const int upper = v[n / 2];
  if ((upper - lower) * 100 > 3 * lower) return static_cast<std::uint16_t>(lower);
  const int sum = lower + upper;
  return static_cast<std::uint16_t>((sum >> 1) + (sum & (sum >> 1) & 1));
}

}  // namespace

StatusOr<cv::Mat> DownsampleDepth(const cv::Mat& depth_mm, int factor, DownsampleMethod method) {
  if (depth_mm.type() != CV_16UC1) return InvalidArgument("depth must be CV_16UC1 millimetres");
  if (factor != 1 && factor != 2 && factor != 4) {
    return InvalidArgument("downsample factor must be 1, 2 or 4, not " + std::to_string(factor));
  }
  if (factor == 1) return depth_mm.clone();
  const int out_w = depth_mm.cols / factor;
  const int out_h = depth_mm.rows / factor;
  cv::Mat out(out_h, out_w, CV_16UC1);
  std::uint16_t block[16];
  for (int y = 0; y < out_h; ++y) {
    std::uint16_t* dst = out.ptr<std::uint16_t>(y);
    for (int x = 0; x < out_w; ++x) {
      if (method == DownsampleMethod::kTopLeft) {
        dst[x] = depth_mm.ptr<std::uint16_t>(y * factor)[x * factor];
        continue;
      }
      int n = 0;
      for (int dy = 0; dy < factor; ++dy) {
        const std::uint16_t* src = depth_mm.ptr<std::uint16_t>(y * factor + dy) + x * factor;
        for (int dx = 0; dx < factor; ++dx) {
          if (src[dx] != 0) block[n++] = src[dx];
        }
      }
      if (n == 0) {
        dst[x] = 0;
      } else if (method == DownsampleMethod::kNearestValid) {
        dst[x] = *std::min_element(block, block + n);
      } else {
        SortSmall(block, n);
        dst[x] = MedianOfSorted(block, n);
      }
    }
  }
  return out;
}

}  // namespace ccmd
