#include "libccmd/io/split.h"

#include <algorithm>
#include <cmath>

#include "libccmd/util/string_util.h"

namespace ccmd {

StatusOr<std::vector<FrameRange>> SplitWithOverlap(int num_frames, int num_segments,
                                                   double overlap_fraction) {
  if (num_segments < 1) return InvalidArgument("number of segments must be at least 1");
  if (num_frames < 1) return InvalidArgument("sequence has no frames");
  if (!(overlap_fraction >= 0.0 && overlap_fraction < 0.5)) {
    return InvalidArgument("overlap fraction must be in [0, 0.5)");
  }
  if (num_segments == 1) return std::vector<FrameRange>{{0, num_frames - 1}};

  const double k = num_segments;
  int length = static_cast<int>(std::ceil(num_frames / (k - overlap_fraction * (k - 1)) - 1e-9));
  int overlap = static_cast<int>(std::ceil(overlap_fraction * length - 1e-9));
  // Grow the segments until K of them, sharing `overlap` frames, reach the end.
  while (num_segments * length - (num_segments - 1) * overlap < num_frames) {
    ++length;
    overlap = static_cast<int>(std::ceil(overlap_fraction * length - 1e-9));
  }
  const int stride = length - overlap;
  if (stride < 2) {
    return InvalidArgument(std::to_string(num_frames) + " frames are too few for " +
                           std::to_string(num_segments) + " segments");
  }
  std::vector<FrameRange> segments;
  for (int i = 0; i < num_segments; ++i) {
    const int first = i * stride;
    const int last =
        (i == num_segments - 1) ? num_frames - 1 : std::min(num_frames - 1, first + length - 1);
    segments.push_back({first, last});
  }
  return segments;
}

StatusOr<std::pair<int, int>> ParseSegmentSpec(const std::string& spec) {
  const auto parts = Split(spec, '/');
  if (parts.size() != 2) return InvalidArgument("segment must be written i/k, e.g. 2/3");
  auto i = ParseInt(parts[0]);
  auto k = ParseInt(parts[1]);
  if (!i.ok() || !k.ok()) return InvalidArgument("segment must be written i/k, e.g. 2/3");
  if (*k < 1 || *i < 1 || *i > *k) {
    return InvalidArgument("segment " + spec + ": need 1 <= i <= k");
  }
  return std::make_pair(static_cast<int>(*i), static_cast<int>(*k));
}

}  // namespace ccmd
