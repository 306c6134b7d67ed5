#pragma once

// ORB extraction speed for ccmd_frontend_bench: our extractor against OpenCV's own ORB
// (detection and descriptors, the same number of features, levels and scale) on the same
// frames in the same run, so that the ratio holds on a machine shared with other work.

#include <vector>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/util/json.h"

namespace ccmd::bench {

struct ExtractionSpeed {
  int frames = 0;
  double ours_ms = 0, ours_cpu_ms = 0;        // per frame
  double opencv_ms = 0, opencv_cpu_ms = 0;    // per frame
  double ours_keypoints = 0, opencv_keypoints = 0;  // per frame
};

// Converts the frames to grey first (not timed), then times both extractors in alternating
// passes and keeps each one's fastest pass (`passes` >= 1). `reference` false: ours only.
ExtractionSpeed MeasureExtraction(const std::vector<RgbdFrame>& frames, const OrbOptions& options,
                                  int passes, bool reference);

Json ToJson(const ExtractionSpeed& speed);
void Print(const ExtractionSpeed& speed);

}  // namespace ccmd::bench
