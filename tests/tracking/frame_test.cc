// Depth of a keypoint and its standard deviation.

#include "libccmd/tracking/frame.h"

#include <gtest/gtest.h>

#include <cmath>

namespace ccmd {
namespace {

// A depth image (uint16 mm) of z = z0 + slope_x * x + slope_y * y (mm per pixel).
cv::Mat DepthRamp(double z0_mm, double slope_x, double slope_y) {
  cv::Mat depth(60, 80, CV_16UC1);
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) {
      depth.at<std::uint16_t>(y, x) = static_cast<std::uint16_t>(std::lround(z0_mm + slope_x * x + slope_y * y));
    }
  }
  return depth;
}

TEST(KeypointDepthSigmaTest, FacingPlaneGivesTheSensorNoise) {
  DepthNoise noise;
  noise.sigma_0 = 0.002;
  noise.sigma_2 = 0.003;
  const cv::Mat depth = DepthRamp(2000, 0, 0);
  // 2 mm + 3 mm * 4 = 14 mm, however uncertain the keypoint's position.
  EXPECT_NEAR(KeypointDepthSigma(depth, 40, 30, 2.0, 1.0, noise), 0.014, 1e-9);
  EXPECT_NEAR(KeypointDepthSigma(depth, 40, 30, 2.0, 4.0, noise), 0.014, 1e-9);
}

TEST(KeypointDepthSigmaTest, SlopeTimesPositionUncertaintyAddsInQuadrature) {
  DepthNoise noise;
  noise.sigma_0 = 0.001;
  noise.sigma_2 = 0.0;
  // Depth rises 3 mm per pixel to the right and 4 mm per pixel downwards: 5 mm per pixel
  // along the gradient. A keypoint uncertain by 2 pixels reads depth uncertain by 10 mm.
  const cv::Mat depth = DepthRamp(1500, 3, 4);
  const double z = 1e-3 * depth.at<std::uint16_t>(30, 40);
  EXPECT_NEAR(KeypointDepthSigma(depth, 40, 30, z, 2.0, noise), std::sqrt(0.001 * 0.001 + 0.010 * 0.010), 1e-9);
  // The finer the keypoint's octave, the less its depth is in doubt.
  EXPECT_LT(KeypointDepthSigma(depth, 40, 30, z, 1.0, noise), KeypointDepthSigma(depth, 40, 30, z, 2.0, noise));
}

TEST(KeypointDepthSigmaTest, DepthInformationIsOneOverVariance) {
  FrameFeatures f;
  f.depth = {0.0f, 2.0f};
  f.depth_sigma = {0.0f, 0.01f};
  EXPECT_EQ(f.DepthInformation(0), 0.0);  // no depth: no information
  EXPECT_NEAR(f.DepthInformation(1), 1e4, 1e-3 * 1e4);
}

}  // namespace
}  // namespace ccmd
