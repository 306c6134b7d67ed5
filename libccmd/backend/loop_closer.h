#pragma once

// Loop closing, the work of the back-end's loop stage, in three steps for every new keyframe
// (the query):
//   1. candidates: the place index's best hits that may be loops (LoopCandidateRule); while
//      the query's agent cools down after a loop (LoopCooldown), none from the query's own map;
//   2. verification and consistency: VerifyLoop on the candidates in score order; the first
//      verified one counts towards LoopConsistency, which accepts a loop once consecutive
//      keyframes of the agent agree on the transform between the two maps;
//   3. correction: inside one map a loop edge, the matched points merged and a pose graph
//      (CloseLoopInMap); between two maps their fusion (FuseMapsByLoop), whose seam is then
//      refined and tied (JoinSeam, loop_seam.h). Both report the keyframes they moved or brought
//      into the primary map, for the dense map.
// Each step is usable on its own (tests, the back-end bench); LoopCloser runs them in order.
// One thread calls a LoopCloser; maps are checked out from the MapManager as they are needed.

#include <functional>
#include <map>
#include <optional>
#include <set>
#include <utility>
#include <vector>

#include "libccmd/backend/loop_options.h"
#include "libccmd/backend/loop_seam.h"
#include "libccmd/backend/loop_verification.h"
#include "libccmd/backend/map_manager.h"
#include "libccmd/backend/map_optimization.h"
#include "libccmd/backend/place_index.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct LoopEvent {
  double server_time = 0;  // seconds since the back-end started
  GlobalKeyframeId query, candidate;
  int inliers = 0;
  // What verification measured: the query's camera in the candidate's camera frame (the loop
  // edge), so that a benchmark can check the transform against ground truth.
  Pose T_candidate_query = Pose::Identity();
  bool fusion = false;          // two maps fused (else a loop inside a map)
  bool already_closed = false;  // inside a map that agreed with it already: nothing corrected
  bool placed_segment = false;  // it placed an agent's restarted segment (ServerMap::Placed)
  bool agent_stopped = false;   // confirmed by neighbours when its agent stopped (AgentStopped)
  MapId map;                    // the map after the event
};

// Step 1, after the place index's query: the candidates LoopCloser verifies, best first. While
// the agent cools down, candidates in the query's own map are dropped (and those whose map is
// unknown); at most `max_candidates` remain.
std::vector<PlaceHit> SelectLoopCandidates(
    std::vector<PlaceHit> hits, bool cooling_down, MapId query_map,
    const std::function<std::optional<MapId>(AgentId)>& map_of_agent, int max_candidates);

// Step 2: the consistency rule. A verified loop of the query with a keyframe of
// `candidate_map` measures T_candidate_map_query_map. It is accepted when it agrees (within
// the tolerances) with the loops verified for the previous loop_consistency - 1 keyframes of
// the same agent, each at most consistency_max_gap ids after the one before, with the same
// candidate map; acceptance starts the count again. One instance per back-end: it remembers
// each agent's last verified loop.
class LoopConsistency {
 public:
  explicit LoopConsistency(const LoopCloserOptions& options) : options_(options) {}
  // A verified loop: its query and candidate keyframes.
  using Pair = std::pair<GlobalKeyframeId, GlobalKeyframeId>;
  // Records a verified loop: the query's pose in the candidate's map (the match) and in its
  // own. True if it completes the rule: the previous loop's map-to-map transform puts this
  // query within consistency_translation and consistency_rotation_deg of the match. `count`
  // receives how many consecutive agreeing loops there are with this one (for the log); on
  // acceptance `earlier` receives the agreeing loops before it (`candidate` is this loop's
  // candidate keyframe).
  bool Confirm(const GlobalKeyframeId& query, MapId candidate_map,
               const Pose& T_candidate_map_query, const Pose& T_query_map_query,
               int* count = nullptr, const GlobalKeyframeId& candidate = {},
               std::vector<Pair>* earlier = nullptr);

  // An agent's latest verified loop that waits for more to agree with it: the loop, its
  // candidate's map, the map-to-map transform it measured and how many agree so far.
  struct Waiting {
    Pair loop;
    MapId candidate_map;
    Pose T_candidate_map_query_map = Pose::Identity();
    int count = 0;
  };
  std::optional<Waiting> WaitingLoop(AgentId agent) const;
  // Whether a keyframe's pose measured in a map agrees with where a waiting loop's transform
  // puts it (the tolerances Confirm uses).
  bool Agrees(const Pose& predicted, const Pose& measured) const;
  void Forget(AgentId agent) { pending_.erase(agent); }

 private:
  struct Pending {
    MapId candidate_map;
    Pose T_candidate_map_query_map = Pose::Identity();
    KeyframeId last_query;
    int count = 0;
    std::vector<Pair> loops;  // the agreeing loops so far
  };
  LoopCloserOptions options_;
  std::map<AgentId, Pending> pending_;
};

// After a loop of an agent, its next loop_cooldown_keyframes keyframes (by id) seek no loop
// in their own map: the place it is in has just been joined. They may still fuse with another
// map (an agent that closes a loop just before its overlap with another agent must still fuse).
class LoopCooldown {
 public:
  explicit LoopCooldown(int keyframes) : keyframes_(keyframes) {}
  void Start(const GlobalKeyframeId& loop_query);
  bool Active(const GlobalKeyframeId& query) const;

 private:
  int keyframes_;
  std::map<AgentId, KeyframeId> until_;
};

// The pairs of agents that a loop inside a map has compared directly. A fusion rests on one
// match, and two agents joined only through a third were never compared: the first loop
// between two agents in one map is the first independent check of where the map holds one
// against the other, and its correction is applied however small (LoopAlreadyClosed is not
// asked). Bounded: at most one such loop per pair of agents.
class ComparedAgents {
 public:
  void Add(AgentId a, AgentId b);             // a loop between them was verified in one map
  bool Compared(AgentId a, AgentId b) const;  // an agent with itself: always

 private:
  std::set<std::pair<AgentId, AgentId>> pairs_;
};

// Step 3 inside one map: the loop edge (the verified relative pose), merged matches, then the
// pose graph. Returns the keyframes the pose graph moved (none if it failed: logged).
std::vector<ServerKeyframe*> CloseLoopInMap(ServerMap* map, const LoopMatch& match,
                                            const MapPoseGraphOptions& options);
// Whether a verified loop inside a map is already closed (see min_correction_m; asked only for
// loops between agents already compared, ComparedAgents).
bool LoopAlreadyClosed(const LoopMatch& match, const LoopCloserOptions& options);

// What a fusion changed, beyond the fused map itself.
struct MapFusion {
  MapManager::Guard map;                        // the fused map, still checked out
  std::vector<ServerKeyframe*> moved;           // keyframes that entered the other map's frame
  std::vector<ServerKeyframe*> joined_primary;  // keyframes that entered the primary map
  std::optional<MapId> primary_before;          // the primary map, if it took part
  // A fusion through an unplaced segment: the segments it placed, and the moved map's
  // keyframes that were placed before and now rest on a guess (ServerMap::UnplaceTogether).
  std::vector<ServerKeyframe*> placed, unplaced;
  SeamJoin seam;
};

// Step 3 between two maps: they are fused into a new map in the primary map's frame if one of
// them is primary, else in the candidate's; with `options`, the seam is refined and tied
// (JoinSeam, through the query's `query_camera`); the loop becomes a loop edge and the matches
// are merged. When either loop keyframe is in an unplaced segment, the loop relates the maps
// only through that segment's guessed pose: the kept map's placed part stays placed, the
// moved map's becomes an unplaced group, and the loop links the segments on its two sides
// (ServerMap::LinkSegments). The guards become empty; the result holds the fused map.
MapFusion FuseMapsByLoop(MapManager* maps, MapManager::Guard* query_map,
                         MapManager::Guard* candidate_map, const LoopMatch& match,
                         const LoopCloserOptions* options = nullptr,
                         const PinholeCamera* query_camera = nullptr);

// A pair of keyframes of one map verified and closed as a loop inside it (CloseLoopAt).
struct PairClosure {
  int inliers = 0;         // 0: not verified (or a keyframe gone or not placed): nothing done
  bool tied_only = false;  // the map agreed with it: its matches merged, nothing moved
  Pose T_candidate_map_query = Pose::Identity();  // the query's verified (refined) pose
  std::vector<ServerKeyframe*> moved;             // what the pose graph moved
};
// Verifies the pair in `map`; where the verified pose agrees with the map (LoopAlreadyClosed)
// merges its matches only; otherwise refines it on its seam and, still apart, adds its loop
// edge and runs the pose graph; then ties its seam.
PairClosure CloseLoopAt(ServerMap* map, const LoopConsistency::Pair& pair,
                        const PinholeCamera& camera, const LoopCloserOptions& options);

// After a fusion: the earlier loops of the consistency group that confirmed it (pairs of
// query and candidate keyframes, LoopConsistency::Confirm), each verified again in the fused
// map and closed there as a loop inside one map: where the verified pose agrees with the map
// (LoopAlreadyClosed) its matches merged only; otherwise refined on its seam and, where the
// maps are still apart at its place, a loop edge and the pose graph; then its seam tied. Pairs with
// a keyframe gone or not placed are skipped. Returns the keyframes the pose graphs moved (a
// keyframe may appear more than once).
std::vector<ServerKeyframe*> CloseEarlierLoops(ServerMap* fused,
                                               const std::vector<LoopConsistency::Pair>& loops,
                                               const PinholeCamera& camera,
                                               const LoopCloserOptions& options);

// After a fusion (see FusionOverlapOptions): pairs of a placed keyframe of the fusion query's
// agent (not the query) and the nearest placed keyframe of the other map within the distance
// and angle that shares fewer than tied_points map points with it; one pair per place (the
// closest; queries spacing_m apart), at most max_pairs, the places furthest along the agents'
// paths from the fusion's loop first (keyframes of its query's and candidate's agents apart in
// id; another agent's counts as furthest). `moved`: the keyframes that
// entered the other map's frame (MapFusion::moved as FuseMapsByLoop returns it).
std::vector<LoopConsistency::Pair> UncomparedOverlaps(const ServerMap& fused,
                                                      const LoopMatch& fusion,
                                                      const std::vector<ServerKeyframe*>& moved,
                                                      const FusionOverlapOptions& options);

// Before a fusion: the places where the query agent's keyframes and the candidate map's
// overlap, by the confirming loop's transform (the pairs UncomparedOverlaps would give after
// it), verified; the one with the most inliers if it has more than `match` (else none).
std::optional<LoopMatch> StrongerFusionLoop(const ServerMap& query_map,
                                            const ServerMap& candidate_map, const LoopMatch& match,
                                            const PinholeCamera& camera,
                                            const LoopCloserOptions& options);

// While an agent cools down after a fusion: the nearest placed keyframe of another agent in
// `keyframe`'s map within the overlap distance and angle that shares fewer than tied_points
// map points with it (none if overlap.max_pairs is 0). The agent may reach the place where it
// overlaps the other map only after the fusion, and cooling down it queries no loop there.
std::optional<LoopConsistency::Pair> UncomparedNeighbour(const ServerMap& map,
                                                         const ServerKeyframe& keyframe,
                                                         const FusionOverlapOptions& options);

// A loop the LoopCloser accepted and corrected.
struct LoopClosure {
  LoopEvent event;
  MapManager::Guard map;  // the map after the correction, still checked out
  // Keyframes the pose graph moved, or a fusion brought into the other map's frame.
  std::vector<ServerKeyframe*> moved;
  std::vector<ServerKeyframe*> joined_primary;  // keyframes a fusion brought into the primary map
  std::vector<GlobalKeyframeId> placed;         // keyframes of restarted segments it placed
  std::vector<GlobalKeyframeId> unplaced;       // keyframes a fusion left at a guess
  std::optional<MapId> primary_before;          // the primary map, when a fusion absorbed it
};

class LoopCloser {
 public:
  // `start_time`: MonotonicSeconds() at which the back-end started (the events' clock).
  LoopCloser(const LoopCloserOptions& options, const PlaceIndexOptions& place, MapManager* maps,
             double start_time);

  // Runs the three steps for a keyframe of an agent with `camera` and a depth sensor of
  // `depth_noise` (it weighs the keyframe's depths in verification and seam refinement).
  // `stored`: the keyframe is already in the place index (a late query), so it is only
  // queried. Returns the loop it closed, if any, with its map still checked out.
  std::optional<LoopClosure> Process(const GlobalKeyframeId& id, const PinholeCamera& camera,
                                     const DepthNoise& depth_noise, bool stored);

  // An agent stopped sending keyframes (its session ended, or it has been idle for a while):
  // its verified loop still waiting for its next keyframes to agree (LoopConsistency) gets no
  // more of them; with only the overlap at a segment's end to join two maps, the last keyframe
  // before it is often the only one to see the other map. The rest of the agreement is sought
  // from both sides' neighbours: the candidate's covisible neighbours not covisible with the
  // query, then the query's not covisible with the candidate (strongest first, at most
  // neighbour_checks on each side), each verified as a query against the other side's
  // keyframe, must find themselves where the loop's map-to-map transform puts them. Each that
  // does counts as a next keyframe would; one that verifies elsewhere rejects the loop.
  // Returns the loop it then closed (corrected as Process would), if any. `camera_of` and
  // `depth_noise_of` give each agent's camera and depth sensor.
  std::optional<LoopClosure> AgentStopped(AgentId agent,
                                          const std::function<PinholeCamera(AgentId)>& camera_of,
                                          const std::function<DepthNoise(AgentId)>& depth_noise_of);

  // Keyframes stored before an online vocabulary existed, to be queried now, oldest first.
  std::optional<GlobalKeyframeId> NextLateQuery();
  // Forgets a keyframe that is being culled: false (and nothing forgotten) while it still waits
  // for its late query.
  bool Forget(const GlobalKeyframeId& id);

  const PlaceIndex& place() const { return place_; }

 private:
  struct Query {
    MapId map;
    std::vector<PlaceHit> candidates;
  };
  std::optional<Query> FindCandidates(const GlobalKeyframeId& id, bool stored);
  enum class Outcome { kNextCandidate, kDone, kClosed };
  // Verifies one candidate; on acceptance corrects and fills `closure`.
  // `options`: the closer's, with the query agent's depth noise.
  Outcome TryCandidate(const GlobalKeyframeId& id, const PinholeCamera& camera,
                       const LoopCloserOptions& options, const PlaceHit& candidate, MapId query_map,
                       std::optional<LoopClosure>* closure);
  // A keyframe of an agent cooling down after a fusion, against the other agents' nearest
  // (UncomparedNeighbour): verified and closed like an earlier loop of a fusion.
  std::optional<LoopClosure> CloseUncomparedNeighbour(const GlobalKeyframeId& id,
                                                      const PinholeCamera& camera,
                                                      const LoopCloserOptions& options);
  // AgentStopped's agreement: each side's neighbours (at most neighbour_checks, strongest
  // first) verified against the other side's keyframe must find themselves where the waiting
  // loop's transform puts them, until loop_consistency agree; one that verifies elsewhere
  // rejects the loop.
  bool NeighboursConfirm(const LoopConsistency::Waiting& waiting, ServerKeyframe* query,
                         const ServerMap& query_map, ServerKeyframe* candidate,
                         const ServerMap& candidate_map,
                         const std::function<PinholeCamera(AgentId)>& camera_of,
                         const std::function<DepthNoise(AgentId)>& depth_noise_of);
  // Correct's two cases: a loop inside the query's map, and a fusion of the two maps.
  void CloseInMap(MapManager::Guard* guard, const LoopMatch& match, const PinholeCamera& camera,
                  const LoopCloserOptions& options, LoopClosure* closure);
  void Fuse(MapManager::Guard* query_guard, MapManager::Guard* candidate_guard,
            const LoopMatch& match, const PinholeCamera& camera, const LoopCloserOptions& options,
            const std::vector<LoopConsistency::Pair>& earlier, LoopClosure* closure);
  // `earlier`: the loops of the consistency group before `match` (a fusion ties them too).
  LoopClosure Correct(MapManager::Guard* query_guard, MapManager::Guard* candidate_guard,
                      const LoopMatch& match, const PinholeCamera& camera,
                      const LoopCloserOptions& options,
                      const std::vector<LoopConsistency::Pair>& earlier);

  const LoopCloserOptions options_;
  PlaceIndex place_;
  MapManager* maps_;
  const double start_time_;
  LoopConsistency consistency_;
  LoopCooldown cooldown_;
  std::set<AgentId> cooling_after_fusion_;  // agents whose cool-down a fusion started
  ComparedAgents compared_;
  std::vector<GlobalKeyframeId> late_queries_;
};

}  // namespace ccmd
