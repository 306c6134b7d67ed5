#pragma once

// Geometric verification of a place-recognition candidate: the query keyframe's keypoints are
// matched against the map points around the candidate (the candidate and its strongest
// covisible keyframes), a 3D-2D RANSAC (PnP) finds the query's pose in the candidate's map,
// and a robust pose refinement with the query's measured depth keeps the matches that agree.

#include <set>
#include <vector>

#include "libccmd/backend/place_index.h"
#include "libccmd/backend/server_map.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

// Which indexed keyframes may be loop candidates of a query (ORB-SLAM's rules): not the query,
// not one it is covisible with, not one of its own agent's `exclude_recent` nearest keyframes
// (the same pass), and, for a hit of the place index, a score at least as high as the weakest
// between the query and its well-connected neighbours (covisibility >= 30).
struct LoopCandidateRule {
  GlobalKeyframeId query;
  std::map<GlobalKeyframeId, int> connected;
  int exclude_recent = 0;
  // The query's segment (ServerKeyframe::segment): its agent's keyframes before it are
  // candidates however recent, since only a loop can join the segments.
  KeyframeId segment{0};
  double min_score = 0;
  std::set<AgentId> excluded_agents;  // none of their keyframes is a candidate
  bool Allowed(const GlobalKeyframeId& candidate) const;
};
LoopCandidateRule MakeLoopCandidateRule(const PlaceIndex& place, const GlobalKeyframeId& id,
                                        const ServerKeyframe& query, int exclude_recent);
// The place index's best hits that pass the rule, best first, at most `max_results`.
std::vector<PlaceHit> QueryLoopCandidates(const PlaceIndex& place,
                                          const std::vector<Descriptor>& descriptors,
                                          const LoopCandidateRule& rule, int max_results);

struct LoopVerificationOptions {
  int window_keyframes = 10;  // candidate + this many covisible neighbours
  int max_hamming = 50;       // descriptor distance accepted
  float ratio = 0.8f;         // best / second best
  int min_matches = 30;       // before RANSAC
  int min_ransac_inliers = 25;
  int min_inliers = 40;  // after refinement: the loop's acceptance threshold
  double ransac_reprojection_px = 4.0;
  DepthNoise depth_noise;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct LoopMatch {
  ServerKeyframe* query = nullptr;
  ServerKeyframe* candidate = nullptr;
  Pose T_candidate_map_query = Pose::Identity();  // the query's pose in the candidate's map
  int inliers = 0;
  // (query keypoint, candidate-side map point) pairs that agree with the pose.
  std::vector<std::pair<int, ServerMapPoint*>> matches;
};

// The candidate and its strongest covisible neighbours (at most `window_keyframes` besides it,
// never the query), and their map points, each once: what a query is matched against.
std::vector<ServerKeyframe*> LoopWindowKeyframes(const ServerKeyframe* query,
                                                 ServerKeyframe* candidate,
                                                 const ServerMap& candidate_map,
                                                 int window_keyframes);
std::vector<ServerMapPoint*> LoopWindowPoints(const ServerKeyframe* query,
                                              ServerKeyframe* candidate,
                                              const ServerMap& candidate_map, int window_keyframes);

// `query_camera`: intrinsics of the query keyframe's agent. Both keyframes may be in the same
// map or in different ones (`candidate_map` is the candidate's).
std::optional<LoopMatch> VerifyLoop(ServerKeyframe* query, const PinholeCamera& query_camera,
                                    ServerKeyframe* candidate, const ServerMap& candidate_map,
                                    const LoopVerificationOptions& options = {});

}  // namespace ccmd
