#include "libccmd/tracking/keyframe_selector.h"

#include <algorithm>
#include <cmath>

namespace ccmd {

Status RgbdSelectionOptions::Validate() const {
  auto fail = [](const char* reason) { return InvalidArgument(reason); };
  if (!(threshold_ratio >= 0 && threshold_ratio <= 1))
    return fail("RGB-D threshold ratio must be in [0, 1]");
  if (threshold_min_points < 0 || min_threshold < 0) return fail("RGB-D thresholds must be >= 0");
  if (!(decrement_ratio >= 0 && decrement_ratio <= 1))
    return fail("RGB-D decrement ratio must be in [0, 1]");
  if (required_covering < 1) return fail("RGB-D required covering keyframes must be >= 1");
  return Status::Ok();
}

void RgbdSelectionOptions::Describe(OptionsWriter* out) const {
  out->Add("enabled", enabled);
  out->Add("threshold_ratio", threshold_ratio);
  out->Add("threshold_min_points", threshold_min_points);
  out->Add("decrement_ratio", decrement_ratio);
  out->Add("min_threshold", min_threshold);
  out->Add("required_covering", required_covering);
}

RgbdDecision RgbdSelector::Decide(KeyframeId keyframe, int tracked_points,
                                  std::vector<std::pair<KeyframeId, int>> neighbours,
                                  const RgbdRequest& request) const {
  RgbdDecision d;
  d.keyframe = keyframe;
  d.tracked_points = tracked_points;
  d.request = request;
  // Strongest links first (ties: older keyframe first, for a stable order).
  std::sort(neighbours.begin(), neighbours.end(), [](const auto& a, const auto& b) {
    return a.second != b.second ? a.second > b.second : a.first < b.first;
  });
  d.considered = neighbours;
  const double scale = request.threshold_scale;
  double threshold = scale * std::max<double>(options_.threshold_min_points,
                                              options_.threshold_ratio * tracked_points);
  d.threshold = static_cast<int>(std::lround(threshold));
  if (!request.allow) {
    d.transmit = false;
    return d;
  }
  if (!options_.enabled || request.every_keyframe) {
    d.transmit = true;
    return d;
  }
  const double decrement = scale * options_.decrement_ratio * tracked_points;
  for (const auto& [id, weight] : neighbours) {
    if (weight > threshold) {
      ++d.covering;
      threshold = std::max<double>(scale * options_.min_threshold, threshold - decrement);
    }
  }
  d.transmit = d.covering < options_.required_covering;
  return d;
}

}  // namespace ccmd
