#pragma once

// How far a trajectory's motion is from what the depth images alone say, with no ground truth:
// for frames `gap` apart, the first frame's depth is aligned to the second's (AlignDepth),
// starting from the relative pose the trajectory gives, and the correction the alignment makes
// is that pair's disagreement. A depth camera takes its whole image at once, so where the
// colour images distort the features' motion (a rolling shutter's readout set wrong, a
// registration offset) the tracked motion and the depth's part ways, even where the features'
// own residuals do not show it (they are measured against map points made from the same
// distorted images). The alignments have their own noise, so only differences between runs on
// the same frames mean something: the setting that makes the smaller median fits the camera.

#include <optional>
#include <vector>

#include "libccmd/geometry/camera.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/tracking/options.h"

namespace ccmd {

struct DepthConsistencyOptions {
  int gap = 10;                              // frames between the two of a pair
  int stride = 3;                            // a pair starts at every stride-th frame
  int cell = 4;                              // pixels per depth-model cell
  double min_depth = 0.1, max_depth = 10.0;  // metres
  DepthNoise noise;

  // The depth range and noise the front-end tracked with.
  void UseSensorOf(const TrackingOptions& tracking) {
    min_depth = tracking.min_depth;
    max_depth = tracking.max_depth;
    noise = tracking.depth_noise;
  }
};

struct DepthConsistency {
  int pairs = 0;   // aligned
  int failed = 0;  // without a trajectory pose for both frames, or not aligned
  // Median (and mean) over the pairs of the correction's translation and rotation angle.
  double translation_median_m = 0, translation_mean_m = 0;
  double rotation_median_rad = 0, rotation_mean_rad = 0;
};

// `frames`: depth in `camera`'s image (registered to it) as the front-end read them, in the
// order they were tracked; `trajectory`: poses of that camera, matched to the frames by
// timestamp (within 1 ms). nullopt when no pair could be aligned.
std::optional<DepthConsistency> MeasureDepthConsistency(const std::vector<RgbdFrame>& frames,
                                                        const Trajectory& trajectory,
                                                        const PinholeCamera& camera,
                                                        const DepthConsistencyOptions& options);

}  // namespace ccmd
