#pragma once

// A rolling shutter's readout read off a recording, with no ground truth: the frames are
// tracked once per candidate readout (TrackingOptions::rolling_shutter_readout, local mapping
// synchronous) and each run's motion is held against the depth images' own
// (MeasureDepthConsistency). A readout set wrong shears the features against the depth, which
// is taken all at once, so the candidate nearest the camera's readout gives the smallest
// disagreement (docs/benchmarks/frontend.md, "Choosing the readout without ground truth").

#include <functional>
#include <optional>
#include <vector>

#include "libccmd/tracking/depth_consistency.h"
#include "libccmd/tracking/options.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct ReadoutTrial {
  double readout = 0;  // seconds
  DepthConsistency consistency;
  int lost_frames = 0;
};

struct ReadoutCheckOptions {
  std::vector<double> candidates = {0, 0.01, 0.02, 0.03, 0.04};  // seconds; 0 is always tried
  // A readout other than 0 is chosen only when its rotation median is at least this fraction
  // below readout 0's: the alignments' own noise moves it by a few per cent from run to run.
  double min_gain = 0.1;
  // Frames paired for the depth consistency: consistency.gap apart, or, when that is 0, as
  // many as the camera takes to turn by this much (the median over the readout-0 run, 2-30
  // frames): too close and the readout's effect is within the alignments' noise, too far and
  // the views no longer overlap enough to align.
  double pair_rotation_deg = 8;
  DepthConsistencyOptions consistency = AutomaticGap();  // depth range and noise: the tracking's

  static DepthConsistencyOptions AutomaticGap() {
    DepthConsistencyOptions o;
    o.gap = 0;
    o.stride = 1;  // every pair: the readouts' medians differ by a few per cent
    return o;
  }
};

// The smallest gap (in frames, 2..30) over which `trajectory` (in time order) turns by
// `rotation_rad` or more in the median; 30 when it never does (or is too short to).
int GapForRotation(const Trajectory& trajectory, double rotation_rad);

// The readout whose run's rotation median is smallest: between the candidates, the vertex of
// the parabola through the smallest and its two neighbours. A readout other than 0 only when
// the smallest is `min_gain` below readout 0's; nullopt when the trials do not show a readout
// either way (or have none at 0). The rotation decides: a readout set wrong turns the
// features' motion against the depth's, and a dense alignment fixes rotation better than
// translation (on a view of a wall and the floor it slides along both), so the translation
// median is the noisier of the two, most of all on small images.
std::optional<double> ChooseReadout(const std::vector<ReadoutTrial>& trials, double min_gain);

struct ReadoutCheck {
  int gap = 0;                       // frames between the two of a pair
  std::vector<ReadoutTrial> trials;  // ascending readout
  std::optional<double> readout;     // ChooseReadout's, seconds
};

// `frames`: consecutive frames of one recording, as the agent reads them (depth registered
// to colour), at least 60 (two of the largest gaps); a candidate must be 0..0.2 s. `progress`
// is called after each trial.
StatusOr<ReadoutCheck> CheckReadout(const std::vector<RgbdFrame>& frames,
                                    const PinholeCamera& camera, TrackingOptions tracking,
                                    const ReadoutCheckOptions& options,
                                    const std::function<void(const ReadoutTrial&)>& progress = {});

}  // namespace ccmd
