#pragma once

// What the back-end tells an observer (the live map view, libccmd/view) as its maps change:
// a keyframe entered a map, keyframes moved (and why), a loop was closed or two maps fused,
// a keyframe's cloud reached the dense store. Nothing is asked back: an observer only watches.
//
// Calls come from the back-end's stage threads after the change is made. Those about one map
// are made while that map is checked out, so they arrive in the order the map changed. An
// observer must return quickly (it runs inside the back-end's stages), must not call the
// back-end, and must outlive it.

#include <string>
#include <vector>

#include "libccmd/dense/dense_map.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/util/ids.h"

namespace ccmd {

struct LoopEvent;

// Why keyframes moved.
enum class PoseSource {
  kAgent,     // the agent's local BA (a pose-update message)
  kLoop,      // the pose graph after a loop inside a map
  kGlobalBa,  // a global bundle adjustment
  kFusion,    // two maps fused: the keyframes of one now in the other's frame
};

inline const char* PoseSourceName(PoseSource source) {
  switch (source) {
    case PoseSource::kAgent:
      return "agent";
    case PoseSource::kLoop:
      return "loop";
    case PoseSource::kGlobalBa:
      return "global_ba";
    case PoseSource::kFusion:
      return "fusion";
  }
  return "unknown";
}

class MapObserver {
 public:
  virtual ~MapObserver() = default;

  // An agent registered (its camera is known).
  virtual void OnAgent(AgentId /*agent*/, const std::string& /*name*/) {}
  // A keyframe was added to `map` at T_map_cam. `arrived_s`: MonotonicSeconds() when its
  // message reached the server. `primary`: `map` is the primary map (the world frame, whose
  // RGB-D keyframes go to the dense store at once; others wait for their map's fusion).
  virtual void OnKeyframe(const GlobalKeyframeId& /*id*/, MapId /*map*/, const Pose& /*T_map_cam*/,
                          double /*arrived_s*/, bool /*primary*/) {}
  // Keyframes of `map` have new poses. `arrived_s`: when the agent's message arrived (kAgent),
  // else when the change was computed.
  virtual void OnPoses(PoseSource /*source*/, MapId /*map*/,
                       const std::vector<KeyframePose>& /*poses*/, double /*arrived_s*/) {}
  // A loop was accepted (before the poses it moves are reported with OnPoses).
  virtual void OnLoop(const LoopEvent& /*event*/) {}
  // The keyframe's points are in the dense store (DenseMap::KeyframeCloud can read them),
  // placed at T_map_cam in `map`. A culled keyframe's cloud can arrive after its culling (its
  // map fused with the primary map later).
  virtual void OnDenseKeyframe(const GlobalKeyframeId& /*id*/, MapId /*map*/,
                               const Pose& /*T_map_cam*/) {}
  // The dense store released these keyframes' clouds: every point they had is held by an
  // earlier keyframe (DenseMap::TakeReleased). Nothing of them is left to draw.
  virtual void OnDenseReleased(const std::vector<GlobalKeyframeId>& /*ids*/) {}
  // A keyframe of `map` was culled as redundant (keyframe_culling.h): it is no longer part of
  // the sparse map; its pose follows a kept keyframe's, and the trajectories keep it, but a
  // view need not draw it as a place the agent went. Its cloud stays until released.
  virtual void OnCulled(MapId /*map*/, const GlobalKeyframeId& /*id*/) {}
  // Keyframes of `map` became unplaced (an agent's restarted segment that nothing measures
  // against the rest of the map yet, or the few keyframes a restart keeps apart:
  // ServerMap::Placed) or, `placed`, were placed by a loop. Unplaced keyframes stay out of the
  // dense map and the trajectories; a view should not draw them as part of the map.
  virtual void OnPlacement(MapId /*map*/, const std::vector<GlobalKeyframeId>& /*keyframes*/,
                           bool /*placed*/) {}
};

}  // namespace ccmd
