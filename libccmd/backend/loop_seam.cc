#include "libccmd/backend/loop_seam.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <unordered_set>

#include "libccmd/geometry/alignment.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/percentile.h"

namespace ccmd {

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

}  // namespace

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

}  // namespace ccmd
