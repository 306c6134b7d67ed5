#pragma once

// Pairing of two free-running streams (colour and depth) by their timestamps.
//
// Cameras that expose colour and depth as separate streams (V4L2 nodes of a RealSense,
// OpenNI2 devices without hardware sync) deliver each at its own pace. A reader keeps the
// latest frame of each stream; if their times are within the tolerance they form a pair,
// otherwise the stream that is behind is read again. Reading the older side is what makes
// this converge: the newer frame may still find its partner, the older one cannot.

namespace ccmd {

enum class PairStep {
  kPair,          // the two latest frames belong together
  kAdvanceColor,  // colour is older: drop it and read the next colour frame
  kAdvanceDepth,  // depth is older: drop it and read the next depth frame
};

PairStep NextPairStep(double color_time, double depth_time, double tolerance);

// Default tolerance for streams at `fps`: half a frame period, so at most one frame of the
// other stream can be within it.
double DefaultPairTolerance(double fps);

}  // namespace ccmd
