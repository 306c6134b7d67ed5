#pragma once

// Optimisation of a whole server map: the pose graph after a loop closure and global bundle
// adjustment. Both report which keyframes moved, for the dense map.

#include <atomic>
#include <cstdint>
#include <map>
#include <set>
#include <vector>

#include "libccmd/backend/server_map.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/optim/bundle_adjuster.h"
#include "libccmd/optim/pose_graph.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct MapPoseGraphOptions {
  int min_covisibility_weight = 50;          // covisibility edges kept in the graph
  double odometry_sigma_rotation = 0.01;     // radians
  double odometry_sigma_translation = 0.01;  // metres
  double loop_sigma_rotation = 0.005;
  double loop_sigma_translation = 0.005;
  int max_iterations = 50;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

// How loosely a restarted segment's first keyframe (ServerKeyframe::restart) is tied to its
// agent's keyframe before it, in the pose graph and the global BA: its pose there is the
// agent's last tracked one, not a measurement, so a loop that joins the two segments moves the
// gap instead of bending them, and before any loop the tie only holds the segment in place.
inline constexpr double kRestartSigmaRotation = 1.0;     // radians
inline constexpr double kRestartSigmaTranslation = 1.0;  // metres

// Nodes: the map's keyframes (culled ones follow theirs: ServerKeyframe::followers); edges:
// consecutive keyframes of each agent (loose across a restart, kRestartSigma*) and
// covisibility links (measured as the current relative poses), and the map's loop edges (their
// measurements). The map's origin keyframe is fixed. Keyframes are moved in place; returns
// those that moved.
StatusOr<std::vector<ServerKeyframe*>> OptimizeMapPoseGraph(
    ServerMap* map, const MapPoseGraphOptions& options = {});

// The depth noise of each agent's sensor, as its handshake announced it; `fallback` (a
// structured-light sensor's by default) for agents that announced none.
struct AgentDepthNoise {
  AgentDepthNoise(const DepthNoise& fallback_noise = {})  // NOLINT: every agent alike
      : fallback(fallback_noise) {}
  DepthNoise fallback;
  std::map<AgentId, DepthNoise> agents;
  const DepthNoise& Of(AgentId agent) const {
    const auto it = agents.find(agent);
    return it == agents.end() ? fallback : it->second;
  }
};

// Global BA in three steps so that the solve runs without holding the map:
struct GlobalBaProblem {
  BaProblem problem;
  std::vector<GlobalKeyframeId> keyframes;  // per camera
  std::vector<GlobalMapPointId> points;     // per point
  std::map<GlobalKeyframeId, Pose> T_map_cam_before;
  std::map<AgentId, KeyframeId> last_keyframe;  // each agent's newest keyframe when built
};
// Every keyframe and every point with at least two observations; the origin is fixed. With a
// `window`, only its keyframes are optimised: the points they observe (at least twice in the
// map) with every observation, keyframes outside the window that observe them held fixed (and
// the first of the window if none does, to fix the gauge).
GlobalBaProblem BuildGlobalBa(const ServerMap& map, const std::map<AgentId, PinholeCamera>& cameras,
                              const AgentDepthNoise& depth_noise,
                              const std::set<GlobalKeyframeId>* window = nullptr);
// The keyframes closest to `seeds` in the covisibility graph (breadth first, strongest links
// first), at most `max_keyframes` and no more than make `max_observations` observations of
// points seen twice: the window of a global BA around a loop in a large map. A place seen on
// many passes has points with many observations; the second bound keeps the problem (its
// time and memory) the same size there.
std::set<GlobalKeyframeId> SelectGlobalBaWindow(const ServerMap& map,
                                                const std::vector<GlobalKeyframeId>& seeds,
                                                int max_keyframes,
                                                std::size_t max_observations = SIZE_MAX);
// The observations a global BA of the whole map would hold (of points seen at least twice).
std::size_t CountGlobalBaObservations(const ServerMap& map);
// Writes the result back: optimised keyframes get their new poses; keyframes added since the
// problem was built move with the correction of the nearest optimised keyframe of their agent
// (keyframes left out of a window stay); optimised points get their new positions. Returns
// the keyframes that moved (their culled followers move with them).
std::vector<ServerKeyframe*> ApplyGlobalBa(ServerMap* map, const GlobalBaProblem& result);

}  // namespace ccmd
