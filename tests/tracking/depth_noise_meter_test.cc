// The depth noise measured from a camera's own frames (DepthNoiseMeter) and the front-end's
// check of its config's model against it.

#include "libccmd/tracking/depth_noise_meter.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <random>

#include "libccmd/sensors/synthetic_source.h"
#include "libccmd/tracking/frontend.h"

namespace ccmd {
namespace {

// A D435-like model: 1 mm + 4 mm/m^2 z^2 (5 mm at 1 m, 17 mm at 2 m).
DepthNoise D435Noise() {
  DepthNoise noise;
  noise.sigma_0 = 0.001;
  noise.sigma_2 = 0.004;
  return noise;
}

// A plane seen steeply slanted (depth 0.8 m at the top row to 3.2 m at the bottom: up to 2 cm
// a pixel row), with box faces in front of it over a third of the image (inverse depth
// 0.15/m higher: 10 cm closer at 0.8 m, 1.1 m at 3.2 m), noisy by `noise` independently per
// pixel, in millimetres. Inverse depth is linear in the pixel coordinates on a plane.
cv::Mat SlantedPlaneWithBoxes(const DepthNoise& noise, std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> gauss(0.0, 1.0);
  cv::Mat depth(480, 640, CV_16UC1);
  for (int v = 0; v < depth.rows; ++v) {
    for (int u = 0; u < depth.cols; ++u) {
      double inverse = 1.0 / 0.8 - (1.0 / 0.8 - 1.0 / 3.2) * v / 479.0 + 0.0001 * u;
      const bool box = ((u / 37) % 3 == 0) && ((v / 29) % 2 == 0);
      if (box) inverse += 0.15;
      double z = 1.0 / inverse;
      z += noise.Sigma(z) * gauss(rng);
      depth.at<std::uint16_t>(v, u) = static_cast<std::uint16_t>(std::lround(1000 * z));
    }
  }
  return depth;
}

TEST(DepthNoiseMeterTest, MeasuresTheNoiseOfASlantedSurfaceAcrossItsEdges) {
  const DepthNoise truth = D435Noise();
  DepthNoiseMeter meter;
  for (std::uint32_t seed = 1; seed <= 3; ++seed) meter.Add(SlantedPlaneWithBoxes(truth, seed));
  const DepthNoiseMeasurement m = meter.Measure();
  ASSERT_TRUE(m.Enough());
  EXPECT_GE(m.bins.size(), 6u);  // 0.5 .. 3.2 m in 25 cm ranges
  // The slope and the box edges are not noise.
  for (const DepthNoiseBin& bin : m.bins) {
    EXPECT_NEAR(bin.sigma / truth.Sigma(bin.depth), 1.0, 0.12) << "at " << bin.depth << " m";
  }
  EXPECT_NEAR(m.fitted.Sigma(1.0), truth.Sigma(1.0), 0.1 * truth.Sigma(1.0));
  EXPECT_NEAR(m.fitted.Sigma(3.0), truth.Sigma(3.0), 0.1 * truth.Sigma(3.0));
  EXPECT_NEAR(m.RatioTo(truth), 1.0, 0.08);
  DepthNoise half = truth;
  half.sigma_0 /= 2;
  half.sigma_2 /= 2;
  EXPECT_NEAR(m.RatioTo(half), 2.0, 0.16);
}

TEST(DepthNoiseMeterTest, BlocksWithoutEveryDepthAreNotMeasured) {
  cv::Mat depth = SlantedPlaneWithBoxes(D435Noise(), 7);
  for (int v = 0; v < depth.rows; ++v) {
    for (int u = (v % 8) * 8 + 3; u < depth.cols; u += 64) depth.at<std::uint16_t>(v, u) = 0;
  }
  DepthNoiseMeter meter;
  meter.Add(depth);
  const DepthNoiseMeasurement m = meter.Measure();
  // Every 8x8 block has a hole in one of its rows.
  EXPECT_EQ(m.blocks, 0);
  EXPECT_FALSE(m.Enough());
  EXPECT_EQ(m.RatioTo(D435Noise()), 0.0);
  // Nor is an image that is not depth in millimetres, nor an empty one.
  meter.Add(cv::Mat(480, 640, CV_32FC1, cv::Scalar(1.0f)));
  meter.Add(cv::Mat());
  EXPECT_EQ(meter.frames(), 1);
  // Images of any size: only whole blocks count (none under 8 pixels, 2 in 17x9).
  DepthNoiseMeter odd;
  odd.Add(cv::Mat(7, 1000, CV_16UC1, cv::Scalar(1000)));
  odd.Add(cv::Mat(1000, 1, CV_16UC1, cv::Scalar(1000)));
  odd.Add(cv::Mat(9, 17, CV_16UC1, cv::Scalar(65535)));
  EXPECT_EQ(odd.frames(), 3);
  EXPECT_EQ(odd.Measure().blocks, 2);
}

// The advice: nothing while the model is within the ratios, the keys when it is not.
TEST(DepthNoiseMeterTest, AdvisesOnlyAModelFarFromTheDepth) {
  const DepthNoise truth = D435Noise();
  DepthNoiseMeter meter;
  meter.Add(SlantedPlaneWithBoxes(truth, 11));
  const DepthNoiseMeasurement m = meter.Measure();
  ASSERT_TRUE(m.Enough());
  EXPECT_EQ(DepthNoiseAdvice(m, truth), "");
  DepthNoise tight = truth, loose = truth;
  tight.sigma_0 /= 2;
  tight.sigma_2 /= 2;
  loose.sigma_0 *= 10;
  loose.sigma_2 *= 10;
  const std::string noisier = DepthNoiseAdvice(m, tight);
  EXPECT_NE(noisier.find("2.0 times as noisy"), std::string::npos) << noisier;
  EXPECT_NE(noisier.find("more precise than it is"), std::string::npos) << noisier;
  const std::size_t keys = noisier.find("DepthNoise.sigma2: ");
  ASSERT_NE(keys, std::string::npos) << noisier;
  EXPECT_NEAR(std::atof(noisier.c_str() + keys + 19), truth.sigma_2, 0.1 * truth.sigma_2);
  const std::string preciser = DepthNoiseAdvice(m, loose);
  EXPECT_NE(preciser.find("0.10 times as noisy"), std::string::npos) << preciser;
  EXPECT_NE(preciser.find("less precise than it is"), std::string::npos) << preciser;
  EXPECT_EQ(DepthNoiseAdvice(DepthNoiseMeasurement(), truth), "");
}

// The front-end measures the first frames of a rendered room and compares them with the model
// it was configured with: twice the model's noise reads as about 2, the model's own as 1.
double RatioOfFrontend(double rendered_noise_scale) {
  SyntheticSequenceOptions sequence;
  sequence.frames = 100;
  sequence.seed = 5;
  sequence.depth_sigma_0 = D435Noise().sigma_0;
  sequence.depth_sigma_2 = D435Noise().sigma_2;
  sequence.noise_scale = rendered_noise_scale;
  SyntheticSource source(sequence);
  TrackingOptions options;
  options.depth_noise = D435Noise();
  options.synchronous_mapping = true;
  auto frontend = Frontend::Create(source.camera(), options, nullptr);
  EXPECT_TRUE(frontend.ok()) << frontend.status().ToString();
  if (!frontend.ok()) return -1;
  RgbdFrame frame;
  while (source.Read(&frame).ok()) (*frontend)->ProcessFrame(frame);
  (*frontend)->Finish();
  return (*frontend)->stats().depth_noise_ratio;
}

TEST(DepthNoiseMeterTest, TheFrontendTellsACameraNoisierThanItsConfig) {
  const double as_configured = RatioOfFrontend(1.0);
  const double twice = RatioOfFrontend(2.0);
  EXPECT_NEAR(as_configured, 1.0, 0.12);
  EXPECT_LT(as_configured, kNoisierThanModel);
  EXPECT_NEAR(twice, 2.0, 0.25);
  EXPECT_GT(twice, kNoisierThanModel);
}

}  // namespace
}  // namespace ccmd
