#pragma once

// The local bundle adjustment of the agent's mapper, apart from its scheduling: the problem
// around a new keyframe (it and its best covisible keyframes free, the points they see, every
// other keyframe seeing those points held fixed) and the write-back of the result.

#include <vector>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/optim/bundle_adjuster.h"
#include "libccmd/tracking/map.h"

namespace ccmd {

struct LocalBaProblem {
  BaProblem problem;
  std::vector<KeyframePtr> cameras;  // per problem camera
  std::vector<MapPointPtr> points;   // per problem point
};

// Call with the map locked. `window`: covisible keyframes optimised with the keyframe. The
// map's first keyframe is always fixed; without any fixed keyframe the oldest is held.
LocalBaProblem BuildLocalBa(Keyframe* keyframe, int window, const LocalMap& map,
                            const OrbExtractor& orb);

// Call with the map locked: poses and points back into the map, outlier observations removed
// from it (ORB-SLAM).
void ApplyLocalBa(const LocalBaProblem& local, const BaSummary& summary, LocalMap* map,
                  const OrbExtractor& orb);

}  // namespace ccmd
