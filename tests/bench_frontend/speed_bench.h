#pragma once

// Speed figures of ccmd_frontend_bench, apart from its main() (which others extend with
// sequences and ablations): ORB extraction against OpenCV's own ORB (detection and
// descriptors, the same number of features, levels and scale) on the same frames in the
// same run, so that the ratio holds on a machine shared with other work; the front-end's
// per-stage wall and CPU times and its mapping counters.

#include <vector>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/tracking/frontend.h"
#include "libccmd/util/json.h"

namespace ccmd::bench {

struct ExtractionSpeed {
  int frames = 0, passes = 0;
  double ours_ms = 0, ours_cpu_ms = 0;              // per frame
  double opencv_ms = 0, opencv_cpu_ms = 0;          // per frame
  double ours_keypoints = 0, opencv_keypoints = 0;  // per frame
};

// Converts the frames to grey first (not timed), then times both extractors in alternating
// passes and keeps each one's fastest pass (`passes` >= 1). `reference` false: ours only.
ExtractionSpeed MeasureExtraction(const std::vector<RgbdFrame>& frames, const OrbOptions& options,
                                  int passes, bool reference);

Json ToJson(const ExtractionSpeed& speed);
void Print(const ExtractionSpeed& speed);

// Adds the per-stage means (wall and CPU milliseconds) and the mapping counters to `result`
// and prints them.
void ReportStages(const FrontendStats& stats, Json* result);

}  // namespace ccmd::bench
