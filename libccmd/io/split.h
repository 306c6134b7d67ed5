#pragma once

// Split-replay segmentation (the partitioned-dataset protocol of the CCMD-SLAM evaluation):
// a sequence of N frames is cut into K contiguous segments of equal length, each sharing
// `overlap` (a fraction of the segment length, 10% by default) with its neighbour, so that
// neighbouring agents see a common stretch of the scene and their maps can be fused.

#include <string>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

struct FrameRange {
  int first = 0;  // 0-based, inclusive
  int last = 0;   // inclusive
  int size() const { return last - first + 1; }
};

// Segment length L = ceil(N / (K - f (K - 1))) and overlap O = ceil(f L), so that K
// segments with O frames shared between neighbours cover exactly N frames; the last
// segment ends at frame N - 1. Errors when the sequence is too short to give every segment
// at least 2 frames of its own.
StatusOr<std::vector<FrameRange>> SplitWithOverlap(int num_frames, int num_segments,
                                                   double overlap_fraction = 0.1);

// Parses "i/k" (1-based segment i of k), as used by `ccmd_agent --segment`.
StatusOr<std::pair<int, int>> ParseSegmentSpec(const std::string& spec);

}  // namespace ccmd
