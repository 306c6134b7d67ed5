#pragma once

// Tracking options from the run config (ORB-SLAM key names where ORB-SLAM has them).

#include "libccmd/io/config.h"
#include "libccmd/tracking/options.h"

namespace ccmd {

// Reads ORBextractor.nFeatures / scaleFactor / nLevels / iniThFAST / minThFAST and the ccmd
// keys Tracking.*, DepthNoise.* and RgbdSelection.* (docs/frontend.md lists them); absent keys
// keep `defaults`.
StatusOr<TrackingOptions> ReadTrackingOptions(const ConfigFile& config,
                                              TrackingOptions defaults = {});

}  // namespace ccmd
