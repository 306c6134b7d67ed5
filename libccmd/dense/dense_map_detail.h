#pragma once

// Constants and helpers shared by the files of DenseMap (dense_map*.cc); not an interface.

#include <cstddef>
#include <cstdint>
#include <string>

#include "libccmd/dense/dense_map.h"

namespace ccmd::dense_detail {

inline constexpr int kSegmentShift = 6;
static_assert((1 << kSegmentShift) == kSegmentKeyframes);
inline constexpr std::uint32_t kSlotMask = kSegmentKeyframes - 1;

// Long re-filters (a loop over a whole agent, a fusion) run in chunks of this many keyframes,
// each with its own W successors as context, so the scratch bricks stay small. Ranks within
// a chunk, plus one, must fit the bricks' uint16 values: 32 + W (<= 1000) + 1 does.
inline constexpr std::size_t kRefilterChunk = 32;

// Bytes a std::map / std::set node costs beyond its value: three pointers and a colour, plus
// the allocator's header.
inline constexpr std::size_t kTreeNodeOverhead = 48;

inline std::string IdText(const GlobalKeyframeId& id) {
  return "keyframe (agent " + std::to_string(id.agent.value()) + ", keyframe " +
         std::to_string(id.keyframe.value()) + ")";
}

}  // namespace ccmd::dense_detail
