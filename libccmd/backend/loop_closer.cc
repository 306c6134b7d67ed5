#include "libccmd/backend/loop_closer.h"

#include <algorithm>
#include <cmath>

#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

Status LoopCloserOptions::Validate() const {
  if (loop_candidates < 1) return InvalidArgument("loop candidates must be >= 1");
  if (loop_consistency < 1) return InvalidArgument("loop consistency must be >= 1");
  if (verification.min_inliers < 10) return InvalidArgument("loop min inliers must be >= 10");
  if (consistency_max_gap < 1) return InvalidArgument("loop consistency gap must be >= 1");
  if (!(consistency_translation > 0) || !(consistency_rotation_deg > 0)) {
    return InvalidArgument("loop consistency tolerances must be positive");
  }
  if (exclude_recent_keyframes < 0 || loop_cooldown_keyframes < 0) {
    return InvalidArgument("loop exclusion and cool-down must be >= 0 keyframes");
  }
  if (!(min_correction_m >= 0) || !(min_correction_deg >= 0)) {
    return InvalidArgument("the smallest loop correction must be >= 0");
  }
  CCMD_RETURN_IF_ERROR(verification.Validate());
  return pose_graph.Validate();
}

void LoopCloserOptions::Describe(OptionsWriter* out) const {
  out->Nested("verification", verification);
  out->Add("loop_candidates", loop_candidates);
  out->Add("loop_consistency", loop_consistency);
  out->Add("consistency_translation", consistency_translation);
  out->Add("consistency_rotation_deg", consistency_rotation_deg);
  out->Add("consistency_max_gap", consistency_max_gap);
  out->Add("exclude_recent_keyframes", exclude_recent_keyframes);
  out->Add("loop_cooldown_keyframes", loop_cooldown_keyframes);
  out->Add("min_correction_m", min_correction_m);
  out->Add("min_correction_deg", min_correction_deg);
  out->Nested("pose_graph", pose_graph);
}

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
                              const Pose& T_candidate_map_query_map, int* count) {
  Pending& pending = pending_[query.agent];
  // Ids compared as unsigned: a query older than the last one (a late query) never confirms.
  const bool consistent =
      pending.count > 0 && pending.candidate_map == candidate_map &&
      query.keyframe.value() - pending.last_query.value() <=
          static_cast<std::uint32_t>(options_.consistency_max_gap) &&
      TranslationDistance(pending.T_candidate_map_query_map, T_candidate_map_query_map) <
          options_.consistency_translation &&
      RotationDistance(pending.T_candidate_map_query_map, T_candidate_map_query_map) <
          options_.consistency_rotation_deg * M_PI / 180;
  pending.count = consistent ? pending.count + 1 : 1;
  pending.candidate_map = candidate_map;
  pending.T_candidate_map_query_map = T_candidate_map_query_map;
  pending.last_query = query.keyframe;
  if (count) *count = pending.count;
  if (pending.count < options_.loop_consistency) return false;
  pending.count = 0;
  return true;
}

void LoopCooldown::Start(const GlobalKeyframeId& loop_query) {
  until_[loop_query.agent] = KeyframeId(loop_query.keyframe.value() + keyframes_);
}

bool LoopCooldown::Active(const GlobalKeyframeId& query) const {
  const auto it = until_.find(query.agent);
  return it != until_.end() && query.keyframe <= it->second;
}

// ---------------------------------------------------------------- step 3: correction

void MergeLoopMatches(ServerMap* map, const LoopMatch& match) {
  for (const auto& [keypoint, point] : match.matches) {
    ServerMapPoint* own = match.query->points[keypoint];
    if (own == point) continue;
    if (own) {
      map->MergePoints(own, point);
    } else {
      map->AddObservation(point, match.query, keypoint);
    }
  }
  map->AddCovisibility(match.query, match.candidate, match.inliers);
}

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
                         MapManager::Guard* candidate_map, const LoopMatch& match) {
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
  // Both keyframes are in one frame now: the loop edge is their current relative pose.
  fused->AddLoopEdge({match.candidate->id, match.query->id,
                      match.candidate->T_map_cam.inverse() * match.query->T_map_cam});
  MergeLoopMatches(fused, match);
  return fusion;
}

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
  std::vector<PlaceHit> hits;
  Query query;
  {
    MapManager::Guard guard = maps_->CheckOutAgent(id.agent);
    const ServerKeyframe* keyframe = guard->keyframe(id);
    if (!keyframe) return std::nullopt;
    query.map = guard->id();
    descriptors = keyframe->Descriptors();
    const LoopCandidateRule rule =
        MakeLoopCandidateRule(place_, id, *keyframe, options_.exclude_recent_keyframes);
    hits = QueryLoopCandidates(place_, descriptors, rule, options_.loop_candidates * 3);
  }
  query.candidates = SelectLoopCandidates(
      std::move(hits), cooldown_.Active(id), query.map,
      [this](AgentId agent) { return maps_->MapOfAgent(agent); }, options_.loop_candidates);
  if (!stored) {
    const std::vector<GlobalKeyframeId> late = place_.Add(id, descriptors);
    late_queries_.insert(late_queries_.end(), late.begin(), late.end());
  }
  return query;
}

std::optional<LoopClosure> LoopCloser::Process(const GlobalKeyframeId& id,
                                               const PinholeCamera& camera, bool stored) {
  const std::optional<Query> query = FindCandidates(id, stored);
  if (!query) return std::nullopt;
  std::optional<LoopClosure> closure;
  for (const PlaceHit& candidate : query->candidates) {
    if (TryCandidate(id, camera, candidate, query->map, &closure) != Outcome::kNextCandidate) break;
  }
  return closure;
}

LoopCloser::Outcome LoopCloser::TryCandidate(const GlobalKeyframeId& id,
                                             const PinholeCamera& camera, const PlaceHit& candidate,
                                             MapId query_map, std::optional<LoopClosure>* closure) {
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
  auto match = VerifyLoop(query, camera, cand, cmap, options_.verification);
  if (!match) return Outcome::kNextCandidate;

  int count = 0;
  const bool accepted = consistency_.Confirm(
      id, cmap.id(), match->T_candidate_map_query * query->T_map_cam.inverse(), &count);
  CCMD_LOG(INFO) << "loop candidate: agent " << id.agent.value() << " keyframe "
                 << id.keyframe.value() << " ~ agent " << cand->id.agent.value() << " keyframe "
                 << cand->id.keyframe.value() << " (" << match->inliers << " inliers, " << count
                 << "/" << options_.loop_consistency << " consistent)";
  if (!accepted) return Outcome::kDone;
  *closure = Correct(&query_guard, same_map ? nullptr : &candidate_guard, *match);
  return Outcome::kClosed;
}

LoopClosure LoopCloser::Correct(MapManager::Guard* query_guard, MapManager::Guard* candidate_guard,
                                const LoopMatch& match) {
  LoopClosure closure;
  LoopEvent& event = closure.event;
  event.server_time = MonotonicSeconds() - start_time_;
  event.query = match.query->id;
  event.candidate = match.candidate->id;
  event.inliers = match.inliers;
  event.T_candidate_query = match.candidate->T_map_cam.inverse() * match.T_candidate_map_query;
  if (!candidate_guard && LoopAlreadyClosed(match, options_)) {
    event.already_closed = true;
    (*query_guard)->AddLoopEdge({match.candidate->id, match.query->id, event.T_candidate_query});
    MergeLoopMatches(query_guard->get(), match);
    closure.map = std::move(*query_guard);
  } else if (!candidate_guard) {
    closure.moved = CloseLoopInMap(query_guard->get(), match, options_.pose_graph);
    closure.map = std::move(*query_guard);
  } else {
    MapFusion fusion = FuseMapsByLoop(maps_, query_guard, candidate_guard, match);
    event.fusion = true;
    closure.map = std::move(fusion.map);
    closure.moved = std::move(fusion.moved);
    closure.joined_primary = std::move(fusion.joined_primary);
    closure.primary_before = fusion.primary_before;
  }
  event.map = closure.map->id();
  cooldown_.Start(event.query);
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
