#include "libccmd/backend/loop_closer.h"

#include <algorithm>
#include <cmath>
#include <set>
#include <unordered_set>

#include "libccmd/geometry/alignment.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/percentile.h"
#include "libccmd/util/timer.h"

namespace ccmd {

Status SeamOptions::Validate() const {
  if (keyframes < 1) return InvalidArgument("seam keyframes must be >= 1");
  for (const double v : {search_radius_px, merge_radius_px, search_depth_m, merge_depth_m,
                         max_correction_m, max_correction_deg}) {
    if (!(v > 0) || !std::isfinite(v))
      return InvalidArgument("seam radii, depth tolerances and corrections must be positive");
  }
  if (max_hamming < 1 || max_hamming > 256)
    return InvalidArgument("seam max Hamming distance must be 1..256");
  if (min_pairs < 3) return InvalidArgument("seam refinement needs at least 3 pairs");
  return Status::Ok();
}

void SeamOptions::Describe(OptionsWriter* out) const {
  out->Add("enabled", enabled);
  out->Add("keyframes", keyframes);
  out->Add("search_radius_px", search_radius_px);
  out->Add("merge_radius_px", merge_radius_px);
  out->Add("search_depth_m", search_depth_m);
  out->Add("merge_depth_m", merge_depth_m);
  out->Add("max_hamming", max_hamming);
  out->Add("min_pairs", min_pairs);
  out->Add("max_correction_m", max_correction_m);
  out->Add("max_correction_deg", max_correction_deg);
}

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
  CCMD_RETURN_IF_ERROR(seam.Validate());
  return pose_graph.Validate();
}

void LoopCloserOptions::Describe(OptionsWriter* out) const {
  out->Nested("verification", verification);
  out->Nested("seam", seam);
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
                              const Pose& T_candidate_map_query, const Pose& T_query_map_query,
                              int* count, const GlobalKeyframeId& candidate,
                              std::vector<Pair>* earlier) {
  Pending& pending = pending_[query.agent];
  // Compared where the query is: where the last loop's map-to-map transform puts this query,
  // against where this loop's match does. (Compared as transforms, their difference at the
  // maps' origin grows with the distance to it: 3 degrees 4 m away is 20 cm there.)
  const Pose predicted = pending.T_candidate_map_query_map * T_query_map_query;
  // Ids compared as unsigned: a query older than the last one (a late query) never confirms.
  const bool consistent =
      pending.count > 0 && pending.candidate_map == candidate_map &&
      query.keyframe.value() - pending.last_query.value() <=
          static_cast<std::uint32_t>(options_.consistency_max_gap) &&
      TranslationDistance(predicted, T_candidate_map_query) < options_.consistency_translation &&
      RotationDistance(predicted, T_candidate_map_query) <
          options_.consistency_rotation_deg * M_PI / 180;
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

std::vector<SeamMatch> SearchSeam(const ServerMap& map,
                                  const std::vector<ServerKeyframe*>& keyframes,
                                  const PinholeCamera& camera,
                                  const std::vector<GlobalMapPointId>& points, double radius_px,
                                  double depth_m, int max_hamming, const DepthNoise& depth_noise) {
  constexpr double kCell = 16;  // pixels per grid cell
  const int columns = static_cast<int>(std::ceil(camera.width / kCell)) + 1,
            rows = static_cast<int>(std::ceil(camera.height / kCell)) + 1;
  std::vector<SeamMatch> result;
  for (ServerKeyframe* kf : keyframes) {
    std::vector<std::vector<int>> grid(static_cast<std::size_t>(columns * rows));
    const auto cell = [&](double u, double v) {
      const int c = std::clamp(static_cast<int>(u / kCell), 0, columns - 1),
                r = std::clamp(static_cast<int>(v / kCell), 0, rows - 1);
      return static_cast<std::size_t>(r * columns + c);
    };
    for (std::size_t i = 0; i < kf->keypoints.size(); ++i)
      grid[cell(kf->keypoints[i].pt.x, kf->keypoints[i].pt.y)].push_back(static_cast<int>(i));
    // Per keypoint: (distance, point).
    std::map<int, std::pair<int, GlobalMapPointId>> best;
    const Pose T_cam_map = kf->T_map_cam.inverse();
    const double max_radius = radius_px * std::pow(1.2, 7);
    for (const GlobalMapPointId& id : points) {
      const ServerMapPoint* p = map.point(id);
      if (!p) continue;
      const bool observed =
          std::any_of(p->observations.begin(), p->observations.end(),
                      [&](const ServerMapPoint::Observation& o) { return o.keyframe == kf; });
      if (observed) continue;
      const Eigen::Vector3d pc = T_cam_map * p->World();
      if (pc.z() < 0.1) continue;
      const Eigen::Vector2d uv = camera.Project(pc);
      if (!camera.InImage(uv)) continue;
      const int c0 = std::max(0, static_cast<int>((uv.x() - max_radius) / kCell)),
                c1 = std::min(columns - 1, static_cast<int>((uv.x() + max_radius) / kCell)),
                r0 = std::max(0, static_cast<int>((uv.y() - max_radius) / kCell)),
                r1 = std::min(rows - 1, static_cast<int>((uv.y() + max_radius) / kCell));
      int best_distance = max_hamming + 1, best_keypoint = -1;
      for (int r = r0; r <= r1; ++r) {
        for (int c = c0; c <= c1; ++c) {
          for (const int i : grid[static_cast<std::size_t>(r * columns + c)]) {
            const ServerKeypoint& kp = kf->keypoints[i];
            const double radius = radius_px * std::pow(1.2, kp.octave);
            if ((Eigen::Vector2d(kp.pt.x, kp.pt.y) - uv).squaredNorm() > radius * radius) continue;
            if (kp.depth > 0 &&
                std::abs(kp.depth - pc.z()) > depth_m + 3 * depth_noise.Sigma(pc.z())) {
              continue;
            }
            const int d = HammingDistance(p->descriptor, kf->descriptor(i));
            if (d < best_distance) {
              best_distance = d;
              best_keypoint = i;
            }
          }
        }
      }
      if (best_keypoint < 0) continue;
      const auto known = best.find(best_keypoint);
      if (known == best.end() || best_distance < known->second.first)
        best[best_keypoint] = {best_distance, p->id};
    }
    for (const auto& [keypoint, entry] : best) result.push_back({kf, keypoint, entry.second});
  }
  return result;
}

namespace {

// A seam pair: a keypoint's back-projection and its matched point, with the back-projection's
// sigmas: along the ray the depth model's, across it the pixel sigma (1.2 to the octave) times
// the depth.
struct SeamPair {
  Eigen::Vector3d query, candidate, ray;
  double along, across;
};

std::vector<SeamPair> SeamPairs(const ServerMap& map, const std::vector<SeamMatch>& matches,
                                const PinholeCamera& camera, const DepthNoise& depth_noise) {
  std::vector<SeamPair> pairs;
  const double focal = std::sqrt(std::abs(camera.fx * camera.fy));
  for (const SeamMatch& m : matches) {
    const ServerMapPoint* candidate = map.point(m.point);
    const ServerKeypoint& kp = m.keyframe->keypoints[m.keypoint];
    if (!candidate || !(kp.depth > 0)) continue;
    const Eigen::Vector3d query =
        m.keyframe->T_map_cam * camera.BackProject(kp.pt.x, kp.pt.y, kp.depth);
    const Eigen::Vector3d ray = (query - m.keyframe->T_map_cam.translation()).normalized();
    pairs.push_back({query, candidate->World(), ray, depth_noise.Sigma(kp.depth),
                     kp.depth * std::pow(1.2, kp.octave) / focal});
  }
  return pairs;
}

// The closed-form rigid fit of the queries onto the candidates, every pair alike; empty if
// the pairs are degenerate.
std::optional<Pose> ClosedFormFit(const std::vector<SeamPair>& pairs) {
  std::vector<Eigen::Vector3d> query, candidate;
  for (const SeamPair& pair : pairs) {
    query.push_back(pair.query);
    candidate.push_back(pair.candidate);
  }
  const auto fit = AlignPoints(query, candidate, /*with_scale=*/false);
  if (!fit.ok()) return std::nullopt;
  return fit->Rigid();
}

// Gauss-Newton on D = exp(delta) * D over the inliers, weighed by `information`. False if the
// step is not finite.
bool RefineSeamFit(const std::vector<SeamPair>& pairs,
                   const std::vector<Eigen::Matrix3d>& information, const std::vector<char>& inlier,
                   Pose* D) {
  for (int iteration = 0; iteration < 5; ++iteration) {
    Eigen::Matrix<double, 6, 6> H = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> g = Eigen::Matrix<double, 6, 1>::Zero();
    for (std::size_t k = 0; k < pairs.size(); ++k) {
      if (!inlier[k]) continue;
      const Eigen::Vector3d p = *D * pairs[k].query;
      const Eigen::Vector3d e = p - pairs[k].candidate;
      Eigen::Matrix<double, 3, 6> J;
      J.leftCols<3>() << 0, p.z(), -p.y(), -p.z(), 0, p.x(), p.y(), -p.x(), 0;  // -[p]x
      J.rightCols<3>() = Eigen::Matrix3d::Identity();
      H += J.transpose() * information[k] * J;
      g += J.transpose() * information[k] * e;
    }
    const Eigen::Matrix<double, 6, 1> delta = H.ldlt().solve(-g);
    if (!delta.allFinite()) return false;
    Pose step = Pose::Identity();
    step.linear() = RotationFromAngleAxis(delta.head<3>());
    step.translation() = delta.tail<3>();
    *D = Orthonormalized(step * *D);
    if (delta.norm() < 1e-9) break;
  }
  return true;
}

}  // namespace

std::optional<Pose> AlignSeam(const ServerMap& map, const std::vector<SeamMatch>& matches,
                              const PinholeCamera& camera, const DepthNoise& depth_noise,
                              int min_pairs, int* inliers) {
  if (inliers) *inliers = 0;
  // The server's depth model need not be the sensor's (the handshake does not carry it): both
  // sigmas of a pair are rescaled in every round by the residuals' robust scales along and
  // across the rays, so a sensor better or worse than the model is weighed as it is.
  const std::vector<SeamPair> pairs = SeamPairs(map, matches, camera, depth_noise);
  if (static_cast<int>(pairs.size()) < min_pairs) return std::nullopt;
  std::vector<char> inlier(pairs.size(), 1);
  std::optional<Pose> start = ClosedFormFit(pairs);
  if (!start) return std::nullopt;
  Pose D = *start;
  std::vector<Eigen::Matrix3d> information(pairs.size());
  for (int round = 0; round < 4; ++round) {
    // The residuals' robust scales along and across the rays (in model sigmas), on the
    // current inliers, rescale the model; a sensor's 2D spread across the ray has a median
    // norm of 1.18 sigmas.
    std::vector<double> along, across;
    for (std::size_t k = 0; k < pairs.size(); ++k) {
      if (!inlier[k]) continue;
      const Eigen::Vector3d e = D * pairs[k].query - pairs[k].candidate;
      const double a = pairs[k].ray.dot(e);
      along.push_back(std::abs(a) / pairs[k].along);
      across.push_back((e - a * pairs[k].ray).norm() / pairs[k].across);
    }
    if (along.empty()) return std::nullopt;
    const double scale_along = std::clamp(1.4826 * Percentile(along, 0.5), 0.02, 50.0),
                 scale_across = std::clamp(Percentile(across, 0.5) / 1.1774, 0.02, 50.0);
    // Residuals in (rescaled) sigmas; beyond 3 robust scales (and at least 3 sigmas):
    // outliers. The first round judges the closed-form start.
    std::vector<double> distance(pairs.size()), kept;
    for (std::size_t k = 0; k < pairs.size(); ++k) {
      const SeamPair& pair = pairs[k];
      const double sa = pair.along * scale_along, sc = pair.across * scale_across;
      const Eigen::Matrix3d along_ray = pair.ray * pair.ray.transpose();
      information[k] =
          (Eigen::Matrix3d::Identity() - along_ray) / (sc * sc) + along_ray / (sa * sa);
      const Eigen::Vector3d e = D * pair.query - pair.candidate;
      distance[k] = std::sqrt(e.dot(information[k] * e));
      if (inlier[k]) kept.push_back(distance[k]);
    }
    const double threshold = 3 * std::max(1.4826 * Percentile(kept, 0.5), 1.0);
    for (std::size_t k = 0; k < pairs.size(); ++k) inlier[k] = distance[k] <= threshold;
    if (!RefineSeamFit(pairs, information, inlier, &D)) return std::nullopt;
  }
  const int count = static_cast<int>(std::count(inlier.begin(), inlier.end(), 1));
  if (inliers) *inliers = count;
  if (count < min_pairs) return std::nullopt;
  return D;
}

namespace {

// The two sides of a loop's seam: the candidate side's keyframes and their map points, and the
// query side's keyframes (the query and its strongest covisible neighbours of its agent).
struct SeamSides {
  std::unordered_set<const ServerKeyframe*> candidate_side;
  std::vector<GlobalMapPointId> points;
  std::vector<ServerKeyframe*> query_keyframes;
};

SeamSides MakeSeamSides(const ServerMap& map, const LoopMatch& match,
                        const std::vector<ServerKeyframe*>& candidate_keyframes,
                        const SeamOptions& seam) {
  SeamSides sides;
  sides.candidate_side.insert(candidate_keyframes.begin(), candidate_keyframes.end());
  std::unordered_set<const ServerMapPoint*> seen;
  for (const ServerKeyframe* kf : candidate_keyframes) {
    for (const ServerMapPoint* p : kf->points) {
      if (p && seen.insert(p).second) sides.points.push_back(p->id);
    }
  }
  ServerKeyframe* query = match.query;
  sides.query_keyframes = {query};
  std::vector<std::pair<GlobalKeyframeId, int>> neighbours(query->covisibility.begin(),
                                                           query->covisibility.end());
  std::sort(neighbours.begin(), neighbours.end(), [](const auto& a, const auto& b) {
    return a.second != b.second ? a.second > b.second : a.first < b.first;
  });
  for (const auto& [id, weight] : neighbours) {
    if (static_cast<int>(sides.query_keyframes.size()) >= seam.keyframes) break;
    ServerKeyframe* kf = map.keyframe(id);
    if (kf && kf->id.agent == query->id.agent && !sides.candidate_side.count(kf))
      sides.query_keyframes.push_back(kf);
  }
  return sides;
}

// The sides of a loop inside one map: the candidate's window without the query's covisible
// keyframes (places the query's side already shares points with).
SeamSides MakeLoopSeamSides(const ServerMap& map, const LoopMatch& match,
                            const LoopCloserOptions& options) {
  std::vector<ServerKeyframe*> window =
      LoopWindowKeyframes(match.query, match.candidate, map, options.verification.window_keyframes);
  window.erase(std::remove_if(window.begin(), window.end(),
                              [&](const ServerKeyframe* kf) {
                                return kf != match.candidate &&
                                       match.query->covisibility.count(kf->id) > 0;
                              }),
               window.end());
  return MakeSeamSides(map, match, window, options.seam);
}

// The seam searched tightly from the current poses: matches merged (or observations added),
// and the query side's keyframes covisible with the candidate side's. Returns how many.
int TieSeam(ServerMap* map, const SeamSides& sides, const PinholeCamera& camera,
            const LoopCloserOptions& options) {
  const SeamOptions& seam = options.seam;
  const std::vector<SeamMatch> ties =
      SearchSeam(*map, sides.query_keyframes, camera, sides.points, seam.merge_radius_px,
                 seam.merge_depth_m, seam.max_hamming, options.verification.depth_noise);
  int merged = 0;
  for (const SeamMatch& m : ties) {
    ServerMapPoint* point = map->point(m.point);
    ServerMapPoint* own = m.keyframe->points[m.keypoint];
    if (!point || own == point) continue;
    if (own) {
      map->MergePoints(own, point);
    } else {
      map->AddObservation(point, m.keyframe, m.keypoint);
    }
    ++merged;
  }
  for (ServerKeyframe* kf : sides.query_keyframes) {
    std::map<ServerKeyframe*, int> shared;
    for (const ServerMapPoint* p : kf->points) {
      if (!p) continue;
      for (const auto& o : p->observations) {
        if (sides.candidate_side.count(o.keyframe)) shared[o.keyframe]++;
      }
    }
    for (const auto& [other, weight] : shared) map->AddCovisibility(kf, other, weight);
  }
  return merged;
}

// The seam searched from the verified poses and the transform fitted to its depth pairs.
std::optional<Pose> FitSeam(const ServerMap& map, const SeamSides& sides,
                            const PinholeCamera& camera, const LoopCloserOptions& options,
                            SeamJoin* join) {
  const SeamOptions& seam = options.seam;
  const DepthNoise& noise = options.verification.depth_noise;
  const std::vector<SeamMatch> found =
      SearchSeam(map, sides.query_keyframes, camera, sides.points, seam.search_radius_px,
                 seam.search_depth_m, seam.max_hamming, noise);
  join->searched = static_cast<int>(found.size());
  return AlignSeam(map, found, camera, noise, seam.min_pairs, &join->pair_inliers);
}

bool SmallCorrection(const Pose& a, const Pose& b, const SeamOptions& seam) {
  return TranslationDistance(a, b) < seam.max_correction_m &&
         RotationDistance(a, b) < seam.max_correction_deg * M_PI / 180;
}

// The verified pose of a loop's query inside one map refined on the seam around the loop, as
// for a fusion (kept when the refinement is not a small one); `sides` receives the seam. The
// map's poses are as they were on return.
LoopMatch RefineLoopOnSeam(ServerMap* map, const LoopMatch& match, const PinholeCamera& camera,
                           const LoopCloserOptions& options, SeamSides* sides) {
  LoopMatch refined = match;
  if (!options.seam.enabled) return refined;
  *sides = MakeLoopSeamSides(*map, match, options);
  // Searched from the verified pose, as a fusion's seam is: the query's side is where the loop
  // puts it while the seam is fitted (from where drift left it, the candidate side's points
  // would be searched as far off as the drift).
  const Pose C = match.T_candidate_map_query * match.query->T_map_cam.inverse();
  std::vector<Pose> before;
  for (ServerKeyframe* kf : sides->query_keyframes) {
    before.push_back(kf->T_map_cam);
    kf->T_map_cam = C * kf->T_map_cam;
  }
  SeamJoin join;
  const std::optional<Pose> D = FitSeam(*map, *sides, camera, options, &join);
  for (std::size_t i = 0; i < before.size(); ++i) sides->query_keyframes[i]->T_map_cam = before[i];
  if (D) {
    const Pose T = Orthonormalized(*D * match.T_candidate_map_query);
    if (SmallCorrection(T, match.T_candidate_map_query, options.seam)) {
      refined.T_candidate_map_query = T;
    }
  }
  CCMD_LOG(INFO) << "loop seam: " << join.searched << " matches, " << join.pair_inliers
                 << " depth pairs agree; verified pose moved by "
                 << 1000 * TranslationDistance(refined.T_candidate_map_query,
                                               match.T_candidate_map_query)
                 << " mm";
  return refined;
}

}  // namespace

Pose RefineLoopPose(ServerMap* map, const LoopMatch& match, const PinholeCamera& camera,
                    const LoopCloserOptions& options) {
  SeamSides sides;
  return RefineLoopOnSeam(map, match, camera, options, &sides).T_candidate_map_query;
}

SeamJoin JoinSeam(ServerMap* fused, const LoopMatch& match, const PinholeCamera& query_camera,
                  const std::vector<ServerKeyframe*>& moved, const LoopCloserOptions& options) {
  SeamJoin join;
  // The candidate side: the keyframes of the candidate's map before the fusion.
  const std::unordered_set<const ServerKeyframe*> moved_set(moved.begin(), moved.end());
  const bool query_moved = moved_set.count(match.query) > 0;
  std::unordered_set<const ServerKeyframe*> candidate_map;
  for (const auto& [id, kf] : fused->keyframes()) {
    if ((moved_set.count(kf.get()) > 0) != query_moved) candidate_map.insert(kf.get());
  }
  std::vector<ServerKeyframe*> window = LoopWindowKeyframes(match.query, match.candidate, *fused,
                                                            options.verification.window_keyframes);
  window.erase(std::remove_if(window.begin(), window.end(),
                              [&](const ServerKeyframe* kf) { return !candidate_map.count(kf); }),
               window.end());
  SeamSides sides = MakeSeamSides(*fused, match, window, options.seam);
  sides.candidate_side = candidate_map;

  // D moves the query side onto the candidate side; the side that entered the fused map's
  // frame takes it (or its inverse).
  const auto apply = [&](const Pose& D) {
    const Pose correction = query_moved ? D : D.inverse();
    for (ServerKeyframe* kf : moved) kf->T_map_cam = Orthonormalized(correction * kf->T_map_cam);
  };
  // A correction's size is how far it moves and turns the query's camera, where the seam is:
  // the map's origin may be metres away, where a fraction of a degree moves it by centimetres.
  const auto small_at_query = [&](const Pose& D) {
    const Pose& T = match.query->T_map_cam;  // as the corrections so far left it
    return SmallCorrection(D * T, T, options.seam);
  };
  if (const std::optional<Pose> D = FitSeam(*fused, sides, query_camera, options, &join)) {
    const Eigen::Vector3d centre = match.query->T_map_cam.translation();
    join.shift_m = (*D * centre - centre).norm();
    if (small_at_query(*D)) {
      apply(*D);
      join.corrected = true;
      join.correction = *D;
    } else {
      // More than one step is trusted with (on a Kinect a verified pose is off by 3-7 cm at
      // times). Searched again from the corrected poses: a fit that found the true seam finds
      // it again there, with at least as many pairs and only a small further step; one that
      // went astray does not, and the verified transform stays.
      std::vector<Pose> before;
      for (const ServerKeyframe* kf : moved) before.push_back(kf->T_map_cam);
      apply(*D);
      SeamJoin again;
      const std::optional<Pose> step = FitSeam(*fused, sides, query_camera, options, &again);
      if (step && small_at_query(*step) && again.pair_inliers >= join.pair_inliers) {
        apply(*step);
        join.corrected = true;
        join.confirmed_by_refit = true;
        // In the fused map's frame before either step: the candidate side moved (by the
        // inverses) when the query side did not.
        join.correction = query_moved ? *step * *D : *D * *step;
        join.pair_inliers = again.pair_inliers;
        join.shift_m = (join.correction * centre - centre).norm();
      } else {
        for (std::size_t i = 0; i < moved.size(); ++i) moved[i]->T_map_cam = before[i];
      }
    }
  }
  // The loop's own matches first (they were verified), then the seam's, searched again from
  // the refined poses.
  MergeLoopMatches(fused, match);
  join.merged = TieSeam(fused, sides, query_camera, options);
  return join;
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

std::vector<ServerKeyframe*> CloseEarlierLoops(ServerMap* fused,
                                               const std::vector<LoopConsistency::Pair>& loops,
                                               const PinholeCamera& camera,
                                               const LoopCloserOptions& options) {
  // The loops that confirmed a fusion may join other places than the one it was made at (an
  // overlap, and a place the other agent came back to later): the fusion's transform and seam
  // come from the last one only, and whatever either agent drifted between the places lies
  // between the maps at the others. Verified again in the fused map, each is closed as a loop
  // inside it: refined on its seam, and where the maps are apart there, the pose graph bends
  // both agents' paths between the places.
  std::vector<ServerKeyframe*> moved;
  for (const auto& [query_id, candidate_id] : loops) {
    ServerKeyframe* query = fused->keyframe(query_id);
    ServerKeyframe* candidate = fused->keyframe(candidate_id);
    // A keyframe of a segment still at a guess is not where it is: nothing to tie it to.
    if (!query || !candidate || !fused->Placed(*query) || !fused->Placed(*candidate)) continue;
    const std::optional<LoopMatch> match =
        VerifyLoop(query, camera, candidate, *fused, options.verification);
    if (!match) continue;
    SeamSides sides;
    const LoopMatch refined = RefineLoopOnSeam(fused, *match, camera, options, &sides);
    const double apart_m = TranslationDistance(query->T_map_cam, refined.T_candidate_map_query);
    const bool closed = LoopAlreadyClosed(refined, options);
    if (closed) {
      MergeLoopMatches(fused, refined);
    } else {
      for (ServerKeyframe* kf : CloseLoopInMap(fused, refined, options.pose_graph))
        moved.push_back(kf);
    }
    if (options.seam.enabled) TieSeam(fused, sides, camera, options);
    CCMD_LOG(INFO) << "fusion also " << (closed ? "tied" : "closed a loop") << " at agent "
                   << query_id.agent.value() << " keyframe " << query_id.keyframe.value()
                   << " ~ agent " << candidate_id.agent.value() << " keyframe "
                   << candidate_id.keyframe.value() << " (" << match->inliers << " inliers, "
                   << 1000 * apart_m << " mm apart)";
  }
  return moved;
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
  std::optional<LoopClosure> closure;
  for (const PlaceHit& candidate : query->candidates) {
    if (TryCandidate(id, camera, options, candidate, query->map, &closure) !=
        Outcome::kNextCandidate)
      break;
  }
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
  if (!match) return Outcome::kNextCandidate;

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
    ServerMap* map = query_guard->get();
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
      closure.moved = CloseLoopInMap(map, refined, options.pose_graph);
    }
    if (options.seam.enabled) TieSeam(map, sides, camera, options);
    // A loop between a placed keyframe and one of a restarted segment places the segment.
    std::vector<ServerKeyframe*> placed = map->LinkSegments(*match.query, *match.candidate);
    if (!placed.empty()) {
      CCMD_LOG(INFO) << "the loop places " << placed.size()
                     << " keyframes of restarted segments in map " << map->id().value();
      event.placed_segment = true;
      closure.placed = WithFollowers(placed);
      if (maps_->primary() == map->id()) closure.joined_primary = std::move(placed);
    }
    closure.map = std::move(*query_guard);
  } else {
    MapFusion fusion =
        FuseMapsByLoop(maps_, query_guard, candidate_guard, match, &options, &camera);
    event.fusion = true;
    const SeamJoin& seam = fusion.seam;
    CCMD_LOG(INFO) << "fusion seam: " << seam.searched << " matches, " << seam.pair_inliers
                   << " depth pairs agree; transform "
                   << (!seam.corrected           ? "kept (no trusted refinement)"
                       : seam.confirmed_by_refit ? "refined (confirmed by a second search)"
                                                 : "refined")
                   << ": query moved " << 1000 * seam.shift_m << " mm, "
                   << RotationDistance(Pose::Identity(), seam.correction) * 180 / M_PI << " deg; "
                   << seam.merged << " points tied";
    // Moved by the fusion, and by the pose graph of an earlier loop: each keyframe once.
    std::unordered_set<ServerKeyframe*> listed(fusion.moved.begin(), fusion.moved.end());
    for (ServerKeyframe* kf : CloseEarlierLoops(fusion.map.get(), earlier, camera, options)) {
      if (listed.insert(kf).second) fusion.moved.push_back(kf);
    }
    if (!fusion.placed.empty() || !fusion.unplaced.empty()) {
      CCMD_LOG(INFO) << "the fusion went through a restarted segment: " << fusion.placed.size()
                     << " keyframes placed, " << fusion.unplaced.size()
                     << " of the moved map wait for a loop";
    }
    event.placed_segment = !fusion.placed.empty();
    closure.placed = WithFollowers(fusion.placed);
    closure.unplaced = WithFollowers(fusion.unplaced);
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
