#pragma once

// RGB-D keyframe selection (the CCMD-SLAM paper's Algorithm 1; see RgbdSelectionOptions).

#include <vector>

#include "libccmd/tracking/keyframe_sink.h"
#include "libccmd/tracking/options.h"

namespace ccmd {

class RgbdSelector {
 public:
  explicit RgbdSelector(const RgbdSelectionOptions& options) : options_(options) {}

  // `transmitted_neighbours`: covisible keyframes whose RGB-D data was sent, with the number
  // of map points they share with the keyframe; `tracked_points`: the keyframe's map points.
  // `request` (from the sink) scales S_min, forces the data on or off.
  RgbdDecision Decide(KeyframeId keyframe, int tracked_points,
                      std::vector<std::pair<KeyframeId, int>> transmitted_neighbours,
                      const RgbdRequest& request = {}) const;

 private:
  RgbdSelectionOptions options_;
};

}  // namespace ccmd
