#pragma once

// The point label N of the paper: which keyframe a point came from, stored with every point
// of the dense map (PLY property "uint label"). Packing: agent << 24 | keyframe, so an agent
// id takes the top 8 bits (0..255) and a keyframe id the low 24 bits (0..16'777'215: more than
// 38 days of keyframes at 5 Hz). Within an agent a later keyframe has a larger label, and
// between agents the larger agent id is larger: "the largest label wins" in the voxel filter
// therefore prefers the newest keyframe of an agent.

#include <cstdint>
#include <string>

#include "libccmd/util/ids.h"
#include "libccmd/util/status.h"

namespace ccmd {

inline constexpr int kLabelKeyframeBits = 24;
inline constexpr std::uint32_t kMaxLabelAgent = (1u << (32 - kLabelKeyframeBits)) - 1;  // 255
inline constexpr std::uint32_t kMaxLabelKeyframe = (1u << kLabelKeyframeBits) - 1;

// True if the ids fit the label; `why` says which does not.
inline bool FitsLabel(const GlobalKeyframeId& id, std::string* why = nullptr) {
  if (id.agent.value() > kMaxLabelAgent) {
    if (why) *why = "agent id " + std::to_string(id.agent.value()) + " above the label limit 255";
    return false;
  }
  if (id.keyframe.value() > kMaxLabelKeyframe) {
    if (why) {
      *why =
          "keyframe id " + std::to_string(id.keyframe.value()) + " above the label limit 16777215";
    }
    return false;
  }
  return true;
}

inline StatusOr<std::uint32_t> EncodeLabel(const GlobalKeyframeId& id) {
  std::string why;
  if (!FitsLabel(id, &why)) return OutOfRange(why);
  return (static_cast<std::uint32_t>(id.agent.value()) << kLabelKeyframeBits) | id.keyframe.value();
}

inline GlobalKeyframeId DecodeLabel(std::uint32_t label) {
  return {AgentId(static_cast<std::uint16_t>(label >> kLabelKeyframeBits)),
          KeyframeId(label & kMaxLabelKeyframe)};
}

}  // namespace ccmd
