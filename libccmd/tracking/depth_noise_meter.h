#pragma once

// A depth camera's noise measured from its own frames, to compare with the DepthNoise model
// a config gives. Every 8x8 block whose pixels all have a depth is fitted with a plane; the
// residual's rms is that block's noise. Blocks across an edge or on a curved surface read
// more than the noise, so each depth range takes a low quantile of its blocks (corrected for
// where that quantile of pure noise falls) rather than their mean: the flattest blocks of a
// room are its walls, floor and tables, which every scene has.

#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "libccmd/optim/reprojection.h"
#include "libccmd/tracking/depth_noise_ratio.h"

namespace ccmd {

struct DepthNoiseBin {
  double depth = 0;  // metres: the median depth of its blocks
  double sigma = 0;  // metres: the noise measured there
  int blocks = 0;    // planar blocks it is measured on
};

struct DepthNoiseMeasurement {
  std::vector<DepthNoiseBin> bins;  // the ranges with enough blocks, near to far
  int blocks = 0;                   // fully valid blocks, every range
  // sigma_0 + sigma_2 z^2 through the bins (relative least squares, both >= 0); the other
  // fields keep their defaults.
  DepthNoise fitted;

  bool Enough() const { return !bins.empty(); }
  // Measured noise over `model`'s sigma, the median over the blocks of every bin: about 1 when
  // the model describes the camera, 2 when the camera is twice as noisy. 0 without bins.
  double RatioTo(const DepthNoise& model) const;
};

// What to tell the user about `model` given `measured`: empty when the model fits
// (DepthNoiseModelFits), else a sentence with the keys that describe the depth.
std::string DepthNoiseAdvice(const DepthNoiseMeasurement& measured, const DepthNoise& model);

class DepthNoiseMeter {
 public:
  // One depth image (CV_16UC1 millimetres, 0 = no depth, as sources give it; other types are
  // not counted). Frames of a moving camera measure more surfaces.
  void Add(const cv::Mat& depth);
  int frames() const { return frames_; }
  DepthNoiseMeasurement Measure() const;

 private:
  struct Block {
    float depth;  // metres
    float rms;    // metres
  };
  int frames_ = 0;
  std::vector<Block> blocks_;
};

}  // namespace ccmd
