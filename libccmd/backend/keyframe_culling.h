#pragma once

// Keyframe culling on the server: memory that follows the mapped space, not the time spent in
// it. An agent's front-end forgets what is outside its local map, so every pass over a place
// it has mapped brings new keyframes, and new map points for the same surfaces; without
// culling the server's sparse maps grow with time (about 90 kB per keyframe).
//
// When a keyframe of an agent leaves the agent's recent window (`keep_recent` keyframes: the
// agent may still refine its pose and link its points), the culling looks at it once. It is
// redundant when kept keyframes of its map that were looked at before see what it sees: at
// least `min_coverage` of its keypoints with depth, back-projected into the map, fall in the
// image of one of the nearest such keyframes at a similar distance (within `max_scale`, so
// that they see it at about the same resolution, ORB-SLAM's scale condition) and from a
// similar direction (`max_view_angle_deg`). A redundant keyframe is culled
// (ServerMap::Cull): it keeps its pose, following the keyframe that covers most of it, so the
// trajectories and the dense map keep it, and gives up its keypoints, observations, links and
// place-recognition entry; points only it observed go with it. A kept keyframe stays kept, so
// the first views of a place remain its sparse map, and a place seen again adds keyframes
// only where they see something the map did not.

#include <cstddef>
#include <deque>
#include <functional>
#include <map>

#include "libccmd/backend/server_map.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct KeyframeCullingOptions {
  bool enabled = true;
  // An agent's newest keyframes are never culled: as many as its local map holds
  // (Tracking.maxKeyframes, 60), whose points its tracking may still link.
  int keep_recent = 60;
  double min_coverage = 0.9;
  double max_scale = 1.25;  // distance ratio, either way
  double max_view_angle_deg = 30;
  int max_covering = 4;          // nearest kept keyframes tried
  int min_depth_keypoints = 50;  // fewer: never culled (nothing to judge it by)

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// The share of `kf`'s keypoints with depth that `others` see (each counted once), and which
// one of them sees most (null if none sees any). Cameras by agent.
struct Coverage {
  double fraction = 0;
  ServerKeyframe* best = nullptr;
};
Coverage MeasureCoverage(const ServerKeyframe& kf, const std::vector<ServerKeyframe*>& others,
                         const std::function<const PinholeCamera*(AgentId)>& camera_of,
                         const KeyframeCullingOptions& options);

// The kept, already looked-at keyframes of `map` nearest to `kf` (at most max_covering), whose
// centres lie within a third of its median keypoint depth and whose viewing directions are
// within max_view_angle_deg of its own. With `kept`, only those keyframes are looked at (the
// culler's list: a map of many revisits holds far more culled keyframes than kept ones);
// without, every keyframe of the map.
std::vector<ServerKeyframe*> CoveringCandidates(
    const ServerMap& map, const ServerKeyframe& kf, const KeyframeCullingOptions& options,
    const std::vector<GlobalKeyframeId>* kept = nullptr);

struct CullingStats {
  std::size_t checked = 0, culled = 0, points_removed = 0;
};

// Runs the culling as keyframes arrive (one thread: the back-end's loop stage).
class KeyframeCuller {
 public:
  explicit KeyframeCuller(const KeyframeCullingOptions& options) : options_(options) {}

  // Records that `id` arrived. Returns the keyframe of its agent that has just left the recent
  // window, which the caller then checks with Check, if there is one.
  std::optional<GlobalKeyframeId> Arrived(const GlobalKeyframeId& id);

  // Looks at `id` in `map` (once) and culls it if it is redundant. `may_cull` is asked last
  // (the place index must be able to forget it). Returns whether it was culled.
  bool Check(ServerMap* map, const GlobalKeyframeId& id,
             const std::function<const PinholeCamera*(AgentId)>& camera_of,
             const std::function<bool(const GlobalKeyframeId&)>& may_cull);

  const CullingStats& stats() const { return stats_; }

 private:
  KeyframeCullingOptions options_;
  std::map<AgentId, std::deque<GlobalKeyframeId>> recent_;
  // Keyframes looked at and kept, in every map: as many as the mapped space needs.
  std::vector<GlobalKeyframeId> kept_;
  CullingStats stats_;
};

}  // namespace ccmd
