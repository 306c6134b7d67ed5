#pragma once

// When a depth camera's measured noise over its config's DepthNoise model (DepthNoiseMeasurement::
// RatioTo) says the model is worth changing. Header-only, so that reports reading the agents'
// statistics share the bounds without linking the tracking library.

namespace ccmd {

// Outside these ratios of measured to modelled noise the model is worth changing: depth noisier
// than its model is weighed as more precise than it is (a D435 at twice its config's noise:
// 12-15 mm instead of 5 mm); depth far more precise than its model is under-used (ICL-NUIM's
// rendered depth with a Kinect's model: over twice the error). The measurement misses slowly
// varying errors, so a model a little above it is right (a Kinect v1 reads about 0.65).
constexpr double kNoisierThanModel = 1.5;
constexpr double kPreciserThanModel = 0.25;

// Whether `ratio` leaves the model as it is: within the bounds above, or 0 (nothing measured).
constexpr bool DepthNoiseModelFits(double ratio) {
  return ratio == 0 || (ratio >= kPreciserThanModel && ratio <= kNoisierThanModel);
}

}  // namespace ccmd
