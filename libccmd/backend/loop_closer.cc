#include "libccmd/backend/loop_closer.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <unordered_map>
#include <unordered_set>

#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

// ---------------------------------------------------------------- step 1: candidates

std::vector<PlaceHit> SelectLoopCandidates(
    std::vector<PlaceHit> hits, bool cooling_down, MapId query_map,
    const std::function<std::optional<MapId>(AgentId)>& map_of_agent, int max_candidates) {
  if (cooling_down) {
    hits.erase(std::remove_if(hits.begin(), hits.end(),
                              [&](const PlaceHit& c) {
                                const auto map = map_of_agent(c.keyframe.agent);
                                return !map || *map == query_map;
                              }),
               hits.end());
  }
  if (static_cast<int>(hits.size()) > max_candidates) hits.resize(max_candidates);
  return hits;
}

// ---------------------------------------------------------------- step 2: consistency

bool LoopConsistency::Confirm(const GlobalKeyframeId& query, MapId candidate_map,
                              const Pose& T_candidate_map_query, const Pose& T_query_map_query,
                              int* count, const GlobalKeyframeId& candidate,
                              std::vector<Pair>* earlier) {
  Pending& pending = pending_[query.agent];
  // Compared where the query is: where the last loop's map-to-map transform puts this query,
  // against where this loop's match does. (Compared as transforms, their difference at the
  // maps' origin grows with the distance to it: 3 degrees 4 m away is 20 cm there.)
  const Pose predicted = pending.T_candidate_map_query_map * T_query_map_query;
  // Ids compared as unsigned: a query older than the last one (a late query) never confirms.
  const bool consistent = pending.count > 0 && pending.candidate_map == candidate_map &&
                          query.keyframe.value() - pending.last_query.value() <=
                              static_cast<std::uint32_t>(options_.consistency_max_gap) &&
                          Agrees(predicted, T_candidate_map_query);
  pending.count = consistent ? pending.count + 1 : 1;
  if (!consistent) pending.loops.clear();
  pending.candidate_map = candidate_map;
  pending.T_candidate_map_query_map = T_candidate_map_query * T_query_map_query.inverse();
  pending.last_query = query.keyframe;
  if (count) *count = pending.count;
  if (pending.count < options_.loop_consistency) {
    pending.loops.emplace_back(query, candidate);
    return false;
  }
  if (earlier) *earlier = std::move(pending.loops);
  pending.loops.clear();
  pending.count = 0;
  return true;
}

std::optional<LoopConsistency::Waiting> LoopConsistency::WaitingLoop(AgentId agent) const {
  const auto it = pending_.find(agent);
  if (it == pending_.end() || it->second.count == 0 || it->second.loops.empty())
    return std::nullopt;
  const Pending& pending = it->second;
  return Waiting{pending.loops.back(), pending.candidate_map, pending.T_candidate_map_query_map,
                 pending.count};
}

bool LoopConsistency::Agrees(const Pose& predicted, const Pose& measured) const {
  return TranslationDistance(predicted, measured) < options_.consistency_translation &&
         RotationDistance(predicted, measured) < options_.consistency_rotation_deg * M_PI / 180;
}

void LoopCooldown::Start(const GlobalKeyframeId& loop_query) {
  until_[loop_query.agent] = KeyframeId(loop_query.keyframe.value() + keyframes_);
}

bool LoopCooldown::Active(const GlobalKeyframeId& query) const {
  const auto it = until_.find(query.agent);
  return it != until_.end() && query.keyframe <= it->second;
}

void ComparedAgents::Add(AgentId a, AgentId b) {
  if (a != b) pairs_.insert(std::minmax(a, b));
}

bool ComparedAgents::Compared(AgentId a, AgentId b) const {
  return a == b || pairs_.count(std::minmax(a, b)) > 0;
}

// ---------------------------------------------------------------- step 3: correction

std::vector<ServerKeyframe*> CloseLoopInMap(ServerMap* map, const LoopMatch& match,
                                            const MapPoseGraphOptions& options) {
  const ServerKeyframe* candidate = match.candidate;
  map->AddLoopEdge({candidate->id, match.query->id,
                    candidate->T_map_cam.inverse() * match.T_candidate_map_query});
  MergeLoopMatches(map, match);
  auto moved = OptimizeMapPoseGraph(map, options);
  if (!moved.ok()) {
    CCMD_LOG(WARNING) << "pose graph: " << moved.status().ToString();
    return {};
  }
  return std::move(moved).value();
}

bool LoopAlreadyClosed(const LoopMatch& match, const LoopCloserOptions& options) {
  const Pose& T_map_query = match.query->T_map_cam;
  return TranslationDistance(T_map_query, match.T_candidate_map_query) < options.min_correction_m &&
         RotationDistance(T_map_query, match.T_candidate_map_query) <
             options.min_correction_deg * M_PI / 180;
}

MapFusion FuseMapsByLoop(MapManager* maps, MapManager::Guard* query_map,
                         MapManager::Guard* candidate_map, const LoopMatch& match,
                         const LoopCloserOptions* options, const PinholeCamera* query_camera) {
  const Pose T_cmap_qmap = match.T_candidate_map_query * match.query->T_map_cam.inverse();
  const auto primary = maps->primary();
  const MapId old_query = (*query_map)->id(), old_candidate = (*candidate_map)->id();
  const bool keep_query = primary && old_query == *primary;
  MapFusion fusion;
  // The map that is not kept enters the other's frame (the primary map's, if it is one).
  for (const auto& [kid, kf] : (keep_query ? *candidate_map : *query_map)->keyframes()) {
    fusion.moved.push_back(kf.get());
  }
  if (primary && (old_query == *primary || old_candidate == *primary)) {
    fusion.primary_before = *primary;
    fusion.joined_primary = fusion.moved;
  }
  fusion.map = keep_query ? maps->Fuse(query_map, candidate_map, T_cmap_qmap.inverse())
                          : maps->Fuse(candidate_map, query_map, T_cmap_qmap);
  ServerMap* fused = fusion.map.get();
  if (options && query_camera && options->seam.enabled) {
    fusion.seam = JoinSeam(fused, match, *query_camera, fusion.moved, *options);
  } else {
    MergeLoopMatches(fused, match);
  }
  // Both keyframes are in one frame now: the loop edge is their current relative pose.
  fused->AddLoopEdge({match.candidate->id, match.query->id,
                      match.candidate->T_map_cam.inverse() * match.query->T_map_cam});
  // Through a segment placed by its agent's guess only, the moved map's placed part now lies
  // where that guess put it: it waits for a loop, as the segment did. (The moved map is never
  // the primary one, so none of its keyframes is in the dense map.)
  if (!fused->Placed(*match.query) || !fused->Placed(*match.candidate)) {
    fusion.unplaced = fused->UnplaceTogether(fusion.moved);
    fusion.placed = fused->LinkSegments(*match.query, *match.candidate);
  }
  return fusion;
}

PairClosure CloseLoopAt(ServerMap* map, const LoopConsistency::Pair& pair,
                        const PinholeCamera& camera, const LoopCloserOptions& options) {
  PairClosure result;
  const auto& [query_id, candidate_id] = pair;
  ServerKeyframe* query = map->keyframe(query_id);
  ServerKeyframe* candidate = map->keyframe(candidate_id);
  // A keyframe of a segment still at a guess is not where it is: nothing to tie it to.
  if (!query || !candidate || !map->Placed(*query) || !map->Placed(*candidate)) return result;
  const std::optional<LoopMatch> match =
      VerifyLoop(query, camera, candidate, *map, options.verification);
  if (!match) {
    CCMD_LOG(INFO) << "no loop verified at agent " << query_id.agent.value() << " keyframe "
                   << query_id.keyframe.value() << " ~ agent " << candidate_id.agent.value()
                   << " keyframe " << candidate_id.keyframe.value();
    return result;
  }
  result.inliers = match->inliers;
  // Where the verification already agrees with the map (typically next to a fusion's own
  // place, which its seam has just tied), the two say the same and the loop only ties. A seam
  // searched there finds what the tie left out: in the split replays, a few dozen pairs at
  // the far edge of the candidate's window that moved the verified pose by 2-15 mm, which the
  // pose graph then bent both paths by.
  SeamSides sides;  // searched only for a loop that does not agree
  const bool agreed = LoopAlreadyClosed(*match, options);
  const LoopMatch refined =
      agreed ? *match : RefineLoopOnSeam(map, *match, camera, options, &sides);
  result.T_candidate_map_query = refined.T_candidate_map_query;
  const double apart_m = TranslationDistance(query->T_map_cam, refined.T_candidate_map_query);
  result.tied_only = agreed || LoopAlreadyClosed(refined, options);
  if (result.tied_only) {
    MergeLoopMatches(map, refined);
  } else {
    result.moved = CloseLoopInMap(map, refined, options.pose_graph);
  }
  if (options.seam.enabled && !agreed) TieSeam(map, sides, camera, options);
  CCMD_LOG(INFO) << (result.tied_only ? "tied" : "closed a loop") << " at agent "
                 << query_id.agent.value() << " keyframe " << query_id.keyframe.value()
                 << " ~ agent " << candidate_id.agent.value() << " keyframe "
                 << candidate_id.keyframe.value() << " (" << match->inliers << " inliers, "
                 << 1000 * apart_m << " mm apart)";
  return result;
}

std::vector<ServerKeyframe*> CloseEarlierLoops(ServerMap* fused,
                                               const std::vector<LoopConsistency::Pair>& loops,
                                               const PinholeCamera& camera,
                                               const LoopCloserOptions& options) {
  // The loops that confirmed a fusion may join other places than the one it was made at (an
  // overlap, and a place the other agent came back to later): the fusion's transform and seam
  // come from one only, and whatever either agent drifted between the places lies between
  // the maps at the others. Verified again in the fused map, each is closed as a loop inside
  // it: where the verification puts the query apart from the map, refined on its seam and,
  // still apart, the pose graph bends both agents' paths between the places.
  std::vector<ServerKeyframe*> moved;
  for (const LoopConsistency::Pair& pair : loops) {
    for (ServerKeyframe* kf : CloseLoopAt(fused, pair, camera, options).moved) moved.push_back(kf);
  }
  return moved;
}

namespace {

// The core of UncomparedOverlaps, StrongerFusionLoop and UncomparedNeighbour: `queries`
// (placed keyframes of one agent) paired with `others` (placed keyframes of other agents or
// another map), the queries put in the others' frame by T_other_query. `fusion`: the loop the
// places are ordered from (none: closest first).
std::vector<LoopConsistency::Pair> NearbyPairs(const std::vector<const ServerKeyframe*>& queries,
                                               const std::vector<const ServerKeyframe*>& others,
                                               const Pose& T_other_query, const LoopMatch* fusion,
                                               const FusionOverlapOptions& options) {
  if (options.max_pairs <= 0) return {};
  // How many keyframes apart along its agent's path a keyframe is from the fusion's on its
  // side (another agent's: as far as can be).
  const auto along = [](const ServerKeyframe* kf, const ServerKeyframe* fused_at) {
    if (kf->id.agent != fused_at->id.agent) return std::int64_t{1} << 32;
    return std::abs(std::int64_t{kf->id.keyframe.value()} - fused_at->id.keyframe.value());
  };
  const double min_cos = std::cos(options.max_angle_deg * M_PI / 180);
  struct Near {
    double distance;
    std::int64_t apart;  // along both paths from the fusion's loop
    Eigen::Vector3d place;
    const ServerKeyframe* query;
    const ServerKeyframe* other;
  };
  std::vector<Near> near;
  for (const ServerKeyframe* q : queries) {
    const Pose T_other_q = T_other_query * q->T_map_cam;
    const Eigen::Vector3d axis = T_other_q.linear().col(2);
    std::vector<std::pair<double, const ServerKeyframe*>> close;
    for (const ServerKeyframe* o : others) {
      const double d = (o->camera_center() - T_other_q.translation()).norm();
      if (d < options.max_distance_m && axis.dot(o->T_map_cam.linear().col(2)) >= min_cos)
        close.emplace_back(d, o);
    }
    if (close.empty()) continue;
    // A keyframe the seam or a merged loop already tied to q shares its points.
    std::unordered_map<const ServerKeyframe*, int> shared;
    for (const ServerMapPoint* p : q->points) {
      if (!p) continue;
      for (const ServerMapPoint::Observation& o : p->observations) ++shared[o.keyframe];
    }
    std::sort(close.begin(), close.end());
    for (const auto& [d, o] : close) {
      const auto it = shared.find(o);
      if (it == shared.end() || it->second < options.tied_points) {
        near.push_back({d, fusion ? along(q, fusion->query) + along(o, fusion->candidate) : 0,
                        T_other_q.translation(), q, o});
        break;
      }
    }
  }
  // One pair per place: the closest (the views most alike, most likely to verify).
  std::sort(near.begin(), near.end(),
            [](const Near& a, const Near& b) { return a.distance < b.distance; });
  std::vector<Near> places;
  for (const Near& n : near) {
    if (std::none_of(places.begin(), places.end(),
                     [&](const Near& p) { return (p.place - n.place).norm() < options.spacing_m; }))
      places.push_back(n);
  }
  // The places furthest from the fusion's along the paths first: what the agents drifted
  // between there and the fusion is largest.
  std::stable_sort(places.begin(), places.end(),
                   [](const Near& a, const Near& b) { return a.apart > b.apart; });
  if (static_cast<int>(places.size()) > options.max_pairs) places.resize(options.max_pairs);
  std::vector<LoopConsistency::Pair> pairs;
  for (const Near& n : places) pairs.emplace_back(n.query->id, n.other->id);
  return pairs;
}

}  // namespace

std::vector<LoopConsistency::Pair> UncomparedOverlaps(const ServerMap& fused,
                                                      const LoopMatch& fusion,
                                                      const std::vector<ServerKeyframe*>& moved,
                                                      const FusionOverlapOptions& options) {
  const ServerKeyframe* query = fusion.query;
  const std::unordered_set<const ServerKeyframe*> moved_set(moved.begin(), moved.end());
  const bool query_moved = moved_set.count(query) > 0;
  std::vector<const ServerKeyframe*> queries, others;
  for (const auto& [id, kf] : fused.keyframes()) {
    if (!fused.Placed(*kf)) continue;
    if ((moved_set.count(kf.get()) > 0) != query_moved) {
      others.push_back(kf.get());
    } else if (id.agent == query->id.agent && kf.get() != query) {
      queries.push_back(kf.get());
    }
  }
  return NearbyPairs(queries, others, Pose::Identity(), &fusion, options);
}

std::optional<LoopMatch> StrongerFusionLoop(const ServerMap& query_map,
                                            const ServerMap& candidate_map, const LoopMatch& match,
                                            const PinholeCamera& camera,
                                            const LoopCloserOptions& options) {
  std::vector<const ServerKeyframe*> queries, others;
  for (const auto& [id, kf] : query_map.keyframes()) {
    if (id.agent == match.query->id.agent && kf.get() != match.query && query_map.Placed(*kf))
      queries.push_back(kf.get());
  }
  for (const auto& [id, kf] : candidate_map.keyframes()) {
    if (candidate_map.Placed(*kf)) others.push_back(kf.get());
  }
  const Pose T_cmap_qmap = match.T_candidate_map_query * match.query->T_map_cam.inverse();
  std::optional<LoopMatch> best;
  int most = match.inliers;
  for (const auto& [q, o] : NearbyPairs(queries, others, T_cmap_qmap, &match, options.overlap)) {
    std::optional<LoopMatch> verified =
        VerifyLoop(query_map.keyframe(q), camera, candidate_map.keyframe(o), candidate_map,
                   options.verification);
    if (verified && verified->inliers > most) {
      most = verified->inliers;
      best = std::move(verified);
    }
  }
  return best;
}

std::optional<LoopConsistency::Pair> UncomparedNeighbour(const ServerMap& map,
                                                         const ServerKeyframe& keyframe,
                                                         const FusionOverlapOptions& options) {
  if (!map.Placed(keyframe)) return std::nullopt;
  std::vector<const ServerKeyframe*> others;
  for (const auto& [id, kf] : map.keyframes()) {
    if (id.agent != keyframe.id.agent && map.Placed(*kf)) others.push_back(kf.get());
  }
  FusionOverlapOptions one = options;
  one.max_pairs = std::min(options.max_pairs, 1);
  const std::vector<LoopConsistency::Pair> pairs =
      NearbyPairs({&keyframe}, others, Pose::Identity(), nullptr, one);
  if (pairs.empty()) return std::nullopt;
  return pairs.front();
}

namespace {

// The ids of `keyframes` and of the culled keyframes each leads.
std::vector<GlobalKeyframeId> WithFollowers(const std::vector<ServerKeyframe*>& keyframes) {
  std::vector<GlobalKeyframeId> ids;
  for (const ServerKeyframe* kf : keyframes) {
    ids.push_back(kf->id);
    for (const CulledKeyframe& f : kf->followers) ids.push_back(f.id);
  }
  return ids;
}

}  // namespace

// ---------------------------------------------------------------- the three steps in order

LoopCloser::LoopCloser(const LoopCloserOptions& options, const PlaceIndexOptions& place,
                       MapManager* maps, double start_time)
    : options_(options),
      place_(place),
      maps_(maps),
      start_time_(start_time),
      consistency_(options),
      cooldown_(options.loop_cooldown_keyframes) {}

std::optional<GlobalKeyframeId> LoopCloser::NextLateQuery() {
  if (late_queries_.empty()) return std::nullopt;
  const GlobalKeyframeId id = late_queries_.front();
  late_queries_.erase(late_queries_.begin());
  return id;
}

bool LoopCloser::Forget(const GlobalKeyframeId& id) {
  if (std::find(late_queries_.begin(), late_queries_.end(), id) != late_queries_.end())
    return false;
  place_.Remove(id);
  return true;
}

std::optional<LoopCloser::Query> LoopCloser::FindCandidates(const GlobalKeyframeId& id,
                                                            bool stored) {
  std::vector<Descriptor> descriptors;
  LoopCandidateRule rule;
  Query query;
  {
    MapManager::Guard guard = maps_->CheckOutAgent(id.agent);
    const ServerKeyframe* keyframe = guard->keyframe(id);
    if (!keyframe) return std::nullopt;
    query.map = guard->id();
    descriptors = keyframe->Descriptors();
    rule = MakeLoopCandidateRule(place_, id, *keyframe, options_.exclude_recent_keyframes);
  }
  const auto map_of = [this](AgentId agent) { return maps_->MapOfAgent(agent); };
  std::vector<PlaceHit> hits =
      QueryLoopCandidates(place_, descriptors, rule, options_.loop_candidates * 3);
  // A map that many agents share holds a place many times over (each agent's recent keyframes
  // stay), and its copies can fill every slot. While the agent cools down after a loop its own
  // map's candidates are dropped, and if they filled the list nothing would be left: then the
  // best hits in the other maps are asked for on their own, so that a fusion is still found.
  // With 16 agents replaying three streams, the three streams' maps never fused without this.
  const bool other_found = std::any_of(hits.begin(), hits.end(), [&](const PlaceHit& h) {
    const auto map = map_of(h.keyframe.agent);
    return map && *map != query.map;
  });
  const bool cooling_down = cooldown_.Active(id);
  const bool cut_off = static_cast<int>(hits.size()) >= options_.loop_candidates * 3;
  if (cooling_down && cut_off && !other_found && maps_->Maps().size() > 1) {
    LoopCandidateRule others = rule;
    for (const AgentId agent : maps_->Agents()) {
      if (map_of(agent) == query.map) others.excluded_agents.insert(agent);
    }
    const std::vector<PlaceHit> more =
        QueryLoopCandidates(place_, descriptors, others, options_.loop_candidates);
    hits.insert(hits.end(), more.begin(), more.end());
  }
  query.candidates = SelectLoopCandidates(std::move(hits), cooling_down, query.map, map_of,
                                          options_.loop_candidates);
  if (!stored) {
    const std::vector<GlobalKeyframeId> late = place_.Add(id, descriptors);
    late_queries_.insert(late_queries_.end(), late.begin(), late.end());
  }
  return query;
}

std::optional<LoopClosure> LoopCloser::Process(const GlobalKeyframeId& id,
                                               const PinholeCamera& camera,
                                               const DepthNoise& depth_noise, bool stored) {
  const std::optional<Query> query = FindCandidates(id, stored);
  if (!query) return std::nullopt;
  LoopCloserOptions options = options_;
  options.verification.depth_noise = depth_noise;
  if (MinLogLevel() <= LogLevel::DEBUG) {
    std::ostringstream listed;
    for (const PlaceHit& c : query->candidates)
      listed << " " << c.keyframe.agent.value() << ":" << c.keyframe.keyframe.value() << " ("
             << c.score << ")";
    CCMD_LOG(DEBUG) << "loop query: agent " << id.agent.value() << " keyframe "
                    << id.keyframe.value() << (cooldown_.Active(id) ? " (cooling down)" : "")
                    << ", candidates:" << listed.str();
  }
  std::optional<LoopClosure> closure;
  for (const PlaceHit& candidate : query->candidates) {
    if (TryCandidate(id, camera, options, candidate, query->map, &closure) !=
        Outcome::kNextCandidate)
      break;
  }
  if (!closure && cooldown_.Active(id) && cooling_after_fusion_.count(id.agent))
    closure = CloseUncomparedNeighbour(id, camera, options);
  return closure;
}

std::optional<LoopClosure> LoopCloser::CloseUncomparedNeighbour(const GlobalKeyframeId& id,
                                                                const PinholeCamera& camera,
                                                                const LoopCloserOptions& options) {
  MapManager::Guard guard = maps_->CheckOutAgent(id.agent);
  const ServerKeyframe* keyframe = guard ? guard->keyframe(id) : nullptr;
  if (!keyframe) return std::nullopt;
  const std::optional<LoopConsistency::Pair> pair =
      UncomparedNeighbour(*guard, *keyframe, options.overlap);
  if (!pair) return std::nullopt;
  PairClosure closed = CloseLoopAt(guard.get(), *pair, camera, options);
  if (closed.inliers == 0) return std::nullopt;
  compared_.Add(id.agent, pair->second.agent);
  LoopClosure closure;
  LoopEvent& event = closure.event;
  event.server_time = MonotonicSeconds() - start_time_;
  event.query = id;
  event.candidate = pair->second;
  event.inliers = closed.inliers;
  event.T_candidate_query =
      guard->keyframe(pair->second)->T_map_cam.inverse() * closed.T_candidate_map_query;
  event.already_closed = closed.tied_only;
  event.map = guard->id();
  closure.moved = std::move(closed.moved);
  closure.map = std::move(guard);
  CCMD_LOG(INFO) << "cooling down after a fusion, agent " << id.agent.value() << " keyframe "
                 << id.keyframe.value() << " met agent " << pair->second.agent.value()
                 << " keyframe " << pair->second.keyframe.value() << " where no loop had";
  return closure;
}

bool LoopCloser::NeighboursConfirm(const LoopConsistency::Waiting& waiting, ServerKeyframe* query,
                                   const ServerMap& query_map, ServerKeyframe* candidate,
                                   const ServerMap& candidate_map,
                                   const std::function<PinholeCamera(AgentId)>& camera_of,
                                   const std::function<DepthNoise(AgentId)>& depth_noise_of) {
  // Each side's neighbours that see none of the other side's keyframe already (those would
  // only repeat what the map holds), strongest first, verified against that keyframe: where
  // they find themselves in its map must be where the loop's transform puts them.
  const auto neighbours = [&](const ServerKeyframe& of, const ServerMap& map,
                              const ServerKeyframe& other) {
    std::vector<std::pair<int, ServerKeyframe*>> found;
    for (const auto& [id, weight] : of.covisibility) {
      ServerKeyframe* n = map.keyframe(id);
      if (!n || n == &other || !map.Placed(*n) || other.covisibility.count(id)) continue;
      found.emplace_back(weight, n);
    }
    std::sort(found.begin(), found.end(),
              [](const auto& a, const auto& b) { return a.first > b.first; });
    if (static_cast<int>(found.size()) > options_.neighbour_checks)
      found.resize(options_.neighbour_checks);
    return found;
  };
  struct Check {
    ServerKeyframe* neighbour;
    ServerKeyframe* against;
    const ServerMap* in;
    Pose T_in_neighbours_map;  // the neighbour's map into `in`, by the waiting loop
  };
  std::vector<Check> checks;
  for (const auto& [weight, n] : neighbours(*candidate, candidate_map, *query))
    checks.push_back({n, query, &query_map, waiting.T_candidate_map_query_map.inverse()});
  for (const auto& [weight, n] : neighbours(*query, query_map, *candidate))
    checks.push_back({n, candidate, &candidate_map, waiting.T_candidate_map_query_map});
  int agreeing = waiting.count;
  for (const Check& check : checks) {
    const ServerKeyframe* n = check.neighbour;
    LoopVerificationOptions verification = options_.verification;
    verification.depth_noise = depth_noise_of(n->id.agent);
    const auto verified =
        VerifyLoop(check.neighbour, camera_of(n->id.agent), check.against, *check.in, verification);
    const bool agrees = verified && consistency_.Agrees(check.T_in_neighbours_map * n->T_map_cam,
                                                        verified->T_candidate_map_query);
    CCMD_LOG(INFO) << "agent " << query->id.agent.value()
                   << " stopped with a loop waiting (keyframe " << query->id.keyframe.value()
                   << " ~ agent " << candidate->id.agent.value() << " keyframe "
                   << candidate->id.keyframe.value() << "): agent " << n->id.agent.value()
                   << " keyframe " << n->id.keyframe.value() << " verified against agent "
                   << check.against->id.agent.value() << " keyframe "
                   << check.against->id.keyframe.value() << ": "
                   << (!verified ? "no loop"
                       : agrees  ? "agrees (" + std::to_string(verified->inliers) + " inliers)"
                                 : "disagrees");
    // A neighbour that finds itself elsewhere speaks against the loop, as a next keyframe
    // that disagreed would.
    if (verified && !agrees) return false;
    if (agrees && ++agreeing >= options_.loop_consistency) break;
  }
  return agreeing >= options_.loop_consistency;
}

std::optional<LoopClosure> LoopCloser::AgentStopped(
    AgentId agent, const std::function<PinholeCamera(AgentId)>& camera_of,
    const std::function<DepthNoise(AgentId)>& depth_noise_of) {
  const std::optional<LoopConsistency::Waiting> waiting = consistency_.WaitingLoop(agent);
  if (!waiting || options_.neighbour_checks == 0) return std::nullopt;
  const auto& [query_id, candidate_id] = waiting->loop;
  const auto query_map = maps_->MapOfAgent(agent);
  const auto candidate_map = maps_->MapOfAgent(candidate_id.agent);
  // The candidate's map fused with another since: the transform no longer says where it is.
  if (!query_map || !candidate_map || *candidate_map != waiting->candidate_map) return std::nullopt;
  const bool same_map = *candidate_map == *query_map;
  MapManager::Guard query_guard, candidate_guard;
  if (same_map) {
    query_guard = maps_->CheckOut(*query_map);
  } else {
    std::tie(query_guard, candidate_guard) = maps_->CheckOutPair(*query_map, *candidate_map);
  }
  if (!query_guard || (!same_map && !candidate_guard)) return std::nullopt;
  const ServerMap& cmap = same_map ? *query_guard : *candidate_guard;
  ServerKeyframe* query = query_guard->keyframe(query_id);
  ServerKeyframe* candidate = cmap.keyframe(candidate_id);
  if (!query || !candidate || !query_guard->Placed(*query) || !cmap.Placed(*candidate))
    return std::nullopt;

  if (!NeighboursConfirm(*waiting, query, *query_guard, candidate, cmap, camera_of, depth_noise_of))
    return std::nullopt;

  LoopCloserOptions options = options_;
  options.verification.depth_noise = depth_noise_of(agent);
  const PinholeCamera camera = camera_of(agent);
  const auto match = VerifyLoop(query, camera, candidate, cmap, options.verification);
  if (!match) return std::nullopt;
  consistency_.Forget(agent);
  LoopClosure closure =
      Correct(&query_guard, same_map ? nullptr : &candidate_guard, *match, camera, options, {});
  closure.event.agent_stopped = true;
  return closure;
}

LoopCloser::Outcome LoopCloser::TryCandidate(const GlobalKeyframeId& id,
                                             const PinholeCamera& camera,
                                             const LoopCloserOptions& options,
                                             const PlaceHit& candidate, MapId query_map,
                                             std::optional<LoopClosure>* closure) {
  const auto candidate_map = maps_->MapOfAgent(candidate.keyframe.agent);
  if (!candidate_map) return Outcome::kNextCandidate;
  const bool same_map = *candidate_map == query_map;
  MapManager::Guard query_guard, candidate_guard;
  if (same_map) {
    query_guard = maps_->CheckOut(query_map);
  } else {
    std::tie(query_guard, candidate_guard) = maps_->CheckOutPair(query_map, *candidate_map);
  }
  if (!query_guard || (!same_map && !candidate_guard))
    return Outcome::kDone;  // fused meanwhile: next keyframe
  const ServerMap& cmap = same_map ? *query_guard : *candidate_guard;
  ServerKeyframe* query = query_guard->keyframe(id);
  ServerKeyframe* cand = cmap.keyframe(candidate.keyframe);
  if (!query || !cand) return Outcome::kNextCandidate;
  auto match = VerifyLoop(query, camera, cand, cmap, options.verification);
  if (!match) {
    CCMD_LOG(DEBUG) << "loop candidate not verified: agent " << id.agent.value() << " keyframe "
                    << id.keyframe.value() << " ~ agent " << cand->id.agent.value() << " keyframe "
                    << cand->id.keyframe.value();
    return Outcome::kNextCandidate;
  }

  int count = 0;
  std::vector<LoopConsistency::Pair> earlier;
  const bool accepted = consistency_.Confirm(id, cmap.id(), match->T_candidate_map_query,
                                             query->T_map_cam, &count, cand->id, &earlier);
  CCMD_LOG(INFO) << "loop candidate: agent " << id.agent.value() << " keyframe "
                 << id.keyframe.value() << " ~ agent " << cand->id.agent.value() << " keyframe "
                 << cand->id.keyframe.value() << " (" << match->inliers << " inliers, " << count
                 << "/" << options_.loop_consistency << " consistent)";
  if (!accepted) return Outcome::kDone;
  *closure = Correct(&query_guard, same_map ? nullptr : &candidate_guard, *match, camera, options,
                     earlier);
  return Outcome::kClosed;
}

namespace {

void LogSeam(const SeamJoin& seam) {
  CCMD_LOG(INFO) << "fusion seam: " << seam.searched << " matches, " << seam.pair_inliers
                 << " depth pairs agree; transform "
                 << (!seam.corrected           ? "kept (no trusted refinement)"
                     : seam.confirmed_by_refit ? "refined (confirmed by a second search)"
                                               : "refined")
                 << ": query moved " << 1000 * seam.shift_m << " mm, "
                 << RotationDistance(Pose::Identity(), seam.correction) * 180 / M_PI << " deg; "
                 << seam.merged << " points tied";
}

// After a fusion made at `fused_at`: `loops` (the confirming group's others) and then the
// places the maps now overlap that no loop has related yet (asked after the loops, which tie
// theirs) closed in the fused map; what their pose graphs moved joins fusion->moved, each
// keyframe once.
void CloseLoopsInTheFusedMap(MapFusion* fusion, const std::vector<LoopConsistency::Pair>& loops,
                             const LoopMatch& fused_at, const PinholeCamera& camera,
                             const LoopCloserOptions& options) {
  const std::vector<ServerKeyframe*> entered = fusion->moved;  // the moved map's keyframes
  std::unordered_set<ServerKeyframe*> listed(fusion->moved.begin(), fusion->moved.end());
  const auto close = [&](const std::vector<LoopConsistency::Pair>& pairs) {
    for (ServerKeyframe* kf : CloseEarlierLoops(fusion->map.get(), pairs, camera, options)) {
      if (listed.insert(kf).second) fusion->moved.push_back(kf);
    }
  };
  close(loops);
  const std::vector<LoopConsistency::Pair> overlaps =
      UncomparedOverlaps(*fusion->map, fused_at, entered, options.overlap);
  if (!overlaps.empty()) {
    std::ostringstream named;
    for (const auto& [q, o] : overlaps)
      named << " " << q.agent.value() << ":" << q.keyframe.value() << "~" << o.agent.value() << ":"
            << o.keyframe.value();
    CCMD_LOG(INFO) << "fusion: " << overlaps.size()
                   << " more places where the maps overlap and no loop related them:"
                   << named.str();
  }
  close(overlaps);
}

}  // namespace

void LoopCloser::CloseInMap(MapManager::Guard* guard, const LoopMatch& match,
                            const PinholeCamera& camera, const LoopCloserOptions& options,
                            LoopClosure* closure) {
  LoopEvent& event = closure->event;
  ServerMap* map = guard->get();
  SeamSides sides;
  const LoopMatch refined = RefineLoopOnSeam(map, match, camera, options, &sides);
  event.T_candidate_query = match.candidate->T_map_cam.inverse() * refined.T_candidate_map_query;
  const AgentId a = match.query->id.agent, b = match.candidate->id.agent;
  const bool compared = compared_.Compared(a, b);
  compared_.Add(a, b);
  if (compared && LoopAlreadyClosed(refined, options)) {
    event.already_closed = true;
    map->AddLoopEdge({match.candidate->id, match.query->id, event.T_candidate_query});
    MergeLoopMatches(map, refined);
  } else {
    closure->moved = CloseLoopInMap(map, refined, options.pose_graph);
  }
  if (options.seam.enabled) TieSeam(map, sides, camera, options);
  // A loop between a placed keyframe and one of a restarted segment places the segment.
  std::vector<ServerKeyframe*> placed = map->LinkSegments(*match.query, *match.candidate);
  if (!placed.empty()) {
    CCMD_LOG(INFO) << "the loop places " << placed.size()
                   << " keyframes of restarted segments in map " << map->id().value();
    event.placed_segment = true;
    closure->placed = WithFollowers(placed);
    if (maps_->primary() == map->id()) closure->joined_primary = std::move(placed);
  }
  closure->map = std::move(*guard);
}

void LoopCloser::Fuse(MapManager::Guard* query_guard, MapManager::Guard* candidate_guard,
                      const LoopMatch& match, const PinholeCamera& camera,
                      const LoopCloserOptions& options,
                      const std::vector<LoopConsistency::Pair>& earlier, LoopClosure* closure) {
  LoopEvent& event = closure->event;
  // Fused where the maps' views agree best: the confirming loop may join a place one agent
  // came back to, with few matches, while the query agent's keyframes overlap the other map
  // elsewhere with many. The confirming loop is then closed like an earlier one.
  std::vector<LoopConsistency::Pair> loops = earlier;
  std::optional<LoopMatch> stronger =
      StrongerFusionLoop(**query_guard, **candidate_guard, match, camera, options);
  if (stronger) {
    CCMD_LOG(INFO) << "fusion made at agent " << stronger->query->id.agent.value() << " keyframe "
                   << stronger->query->id.keyframe.value() << " ~ agent "
                   << stronger->candidate->id.agent.value() << " keyframe "
                   << stronger->candidate->id.keyframe.value() << " (" << stronger->inliers
                   << " inliers), where the maps overlap, rather than at the confirming loop ("
                   << match.inliers << ")";
    loops.emplace_back(match.query->id, match.candidate->id);
    event.query = stronger->query->id;
    event.candidate = stronger->candidate->id;
    event.inliers = stronger->inliers;
    event.T_candidate_query =
        stronger->candidate->T_map_cam.inverse() * stronger->T_candidate_map_query;
  }
  const LoopMatch& fused_at = stronger ? *stronger : match;
  MapFusion fusion =
      FuseMapsByLoop(maps_, query_guard, candidate_guard, fused_at, &options, &camera);
  event.fusion = true;
  LogSeam(fusion.seam);
  CloseLoopsInTheFusedMap(&fusion, loops, fused_at, camera, options);
  if (!fusion.placed.empty() || !fusion.unplaced.empty()) {
    CCMD_LOG(INFO) << "the fusion went through a restarted segment: " << fusion.placed.size()
                   << " keyframes placed, " << fusion.unplaced.size()
                   << " of the moved map wait for a loop";
  }
  event.placed_segment = !fusion.placed.empty();
  closure->placed = WithFollowers(fusion.placed);
  closure->unplaced = WithFollowers(fusion.unplaced);
  closure->map = std::move(fusion.map);
  closure->moved = std::move(fusion.moved);
  closure->joined_primary = std::move(fusion.joined_primary);
  closure->primary_before = fusion.primary_before;
}

LoopClosure LoopCloser::Correct(MapManager::Guard* query_guard, MapManager::Guard* candidate_guard,
                                const LoopMatch& match, const PinholeCamera& camera,
                                const LoopCloserOptions& options,
                                const std::vector<LoopConsistency::Pair>& earlier) {
  LoopClosure closure;
  LoopEvent& event = closure.event;
  event.server_time = MonotonicSeconds() - start_time_;
  event.query = match.query->id;
  event.candidate = match.candidate->id;
  event.inliers = match.inliers;
  event.T_candidate_query = match.candidate->T_map_cam.inverse() * match.T_candidate_map_query;
  if (!candidate_guard) {
    CloseInMap(query_guard, match, camera, options, &closure);
  } else {
    Fuse(query_guard, candidate_guard, match, camera, options, earlier, &closure);
  }
  event.map = closure.map->id();
  cooldown_.Start(match.query->id);  // the confirming query, wherever the fusion was made
  if (event.fusion) {
    cooling_after_fusion_.insert(match.query->id.agent);
  } else {
    cooling_after_fusion_.erase(match.query->id.agent);
  }
  CCMD_LOG(INFO) << (event.fusion           ? "maps fused"
                     : event.already_closed ? "loop already closed"
                                            : "loop closed")
                 << ": agent " << event.query.agent.value() << " keyframe "
                 << event.query.keyframe.value() << " with agent " << event.candidate.agent.value()
                 << " keyframe " << event.candidate.keyframe.value() << ", " << event.inliers
                 << " inliers, map " << event.map.value();
  return closure;
}

}  // namespace ccmd
