#pragma once

// Depth downsampling by r = 1, 1/2, 1/4 (factor 1, 2, 4) that never invents depths between
// surfaces: a block that straddles a depth edge yields a depth of one surface, not a value
// floating between the two (which averaging or bilinear resizing would produce). Within one
// surface the median gives the depth at the block's centre, where the output pixel looks.

#include <opencv2/core/mat.hpp>

#include "libccmd/util/status.h"

namespace ccmd {

enum class DownsampleMethod {
  kMedianValid,   // median of the block's valid depths; of two middle ones their mean, or
                  // the nearer across an edge (default: robust to speckle)
  kNearestValid,  // smallest valid depth (keeps thin foreground objects)
  kTopLeft,       // the block's top-left sample, valid or not (plain decimation)
};

const char* DownsampleMethodName(DownsampleMethod method);

// The sampling rate r as an integer factor: 1.0 -> 1, 0.5 -> 2, 0.25 -> 4; 0 for others.
int DownsampleFactorForRate(double r);

// depth_mm: CV_16UC1, 0 = invalid. factor: 1, 2 or 4. Output size (cols / factor,
// rows / factor) rounded down; output pixel (x, y) covers input [factor x, factor x +
// factor) x [factor y, factor y + factor). A block without a valid depth gives 0.
StatusOr<cv::Mat> DownsampleDepth(const cv::Mat& depth_mm, int factor,
                                  DownsampleMethod method = DownsampleMethod::kMedianValid);

}  // namespace ccmd
