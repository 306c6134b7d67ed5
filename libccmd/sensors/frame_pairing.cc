#include "libccmd/sensors/frame_pairing.h"

#include <cmath>

namespace ccmd {

PairStep NextPairStep(double color_time, double depth_time, double tolerance) {
  if (std::fabs(color_time - depth_time) <= tolerance) return PairStep::kPair;
  return color_time < depth_time ? PairStep::kAdvanceColor : PairStep::kAdvanceDepth;
}

double DefaultPairTolerance(double fps) { return fps > 0 ? 0.5 / fps : 1.0 / 60.0; }

}  // namespace ccmd
