#include "libccmd/backend/loop_verification.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/core.hpp>
#include <unordered_set>

#include "libccmd/geometry/pnp.h"
#include "libccmd/optim/pose_optimizer.h"

namespace ccmd {

Status LoopVerificationOptions::Validate() const {
  if (window_keyframes < 0) return InvalidArgument("loop verification window must be >= 0");
  if (max_hamming < 1 || max_hamming > 256)
    return InvalidArgument("loop max Hamming distance must be 1..256");
  if (!(ratio > 0 && ratio <= 1)) return InvalidArgument("loop match ratio must be in (0, 1]");
  if (min_matches < 4 || min_ransac_inliers < 4 || min_inliers < 10) {
    return InvalidArgument(
        "loop verification needs at least 4 matches and inliers, 10 after refinement");
  }
  if (!(ransac_reprojection_px > 0))
    return InvalidArgument("loop RANSAC threshold must be positive");
  return depth_noise.Validate();
}

void LoopVerificationOptions::Describe(OptionsWriter* out) const {
  out->Add("window_keyframes", window_keyframes);
  out->Add("max_hamming", max_hamming);
  out->Add("ratio", ratio);
  out->Add("min_matches", min_matches);
  out->Add("min_ransac_inliers", min_ransac_inliers);
  out->Add("min_inliers", min_inliers);
  out->Add("ransac_reprojection_px", ransac_reprojection_px);
  out->Nested("depth_noise", depth_noise);
}

bool LoopCandidateRule::Allowed(const GlobalKeyframeId& c) const {
  if (c == query || connected.count(c) || excluded_agents.count(c.agent)) return false;
  return c.agent != query.agent || c.keyframe < segment ||
         std::abs(static_cast<long>(c.keyframe.value()) -
                  static_cast<long>(query.keyframe.value())) > exclude_recent;
}

LoopCandidateRule MakeLoopCandidateRule(const PlaceIndex& place, const GlobalKeyframeId& id,
                                        const ServerKeyframe& query, int exclude_recent) {
  LoopCandidateRule rule;
  rule.query = id;
  rule.connected = query.covisibility;
  rule.exclude_recent = exclude_recent;
  rule.segment = query.segment;
  double min_score = 1e9;
  for (const auto& [other, weight] : query.covisibility) {
    if (weight >= 30) min_score = std::min(min_score, place.Score(id, other));
  }
  rule.min_score = min_score == 1e9 ? 0 : min_score;
  return rule;
}

std::vector<PlaceHit> QueryLoopCandidates(const PlaceIndex& place,
                                          const std::vector<Descriptor>& descriptors,
                                          const LoopCandidateRule& rule, int max_results) {
  std::vector<PlaceHit> hits = place.Query(
      descriptors, max_results, [&rule](const GlobalKeyframeId& c) { return rule.Allowed(c); });
  hits.erase(std::remove_if(hits.begin(), hits.end(),
                            [&](const PlaceHit& h) { return h.score < rule.min_score; }),
             hits.end());
  return hits;
}

std::vector<ServerKeyframe*> LoopWindowKeyframes(const ServerKeyframe* query,
                                                 ServerKeyframe* candidate,
                                                 const ServerMap& candidate_map,
                                                 int window_keyframes) {
  std::vector<ServerKeyframe*> window = {candidate};
  std::vector<std::pair<GlobalKeyframeId, int>> neighbours(candidate->covisibility.begin(),
                                                           candidate->covisibility.end());
  std::sort(neighbours.begin(), neighbours.end(), [](const auto& a, const auto& b) {
    return a.second != b.second ? a.second > b.second : a.first < b.first;
  });
  for (const auto& [id, weight] : neighbours) {
    if (static_cast<int>(window.size()) > window_keyframes) break;
    if (ServerKeyframe* kf = candidate_map.keyframe(id); kf && kf != query) window.push_back(kf);
  }
  return window;
}

std::vector<ServerMapPoint*> LoopWindowPoints(const ServerKeyframe* query,
                                              ServerKeyframe* candidate,
                                              const ServerMap& candidate_map,
                                              int window_keyframes) {
  const std::vector<ServerKeyframe*> window =
      LoopWindowKeyframes(query, candidate, candidate_map, window_keyframes);
  std::vector<ServerMapPoint*> points;
  std::unordered_set<const ServerMapPoint*> seen;
  for (ServerKeyframe* kf : window) {
    for (ServerMapPoint* p : kf->points) {
      if (p && seen.insert(p).second) points.push_back(p);
    }
  }
  return points;
}

namespace {

// The loosest depth weighting a loop's first refinement uses: 1 mm + 2 mm per m^2, about 40 %
// above a Kinect v1's noise at 2-3 m, for the millimetres of error a map's points carry on top
// of the query's sensor.
const DepthNoise kTolerantDepthNoise{0.001, 0.002};

// Each query keypoint to its best map point (ratio test), one keypoint per point: the index
// into `points` per keypoint, -1 for none.
CCMD_POPCNT_CLONES std::vector<int> MatchKeypoints(const ServerKeyframe& query,
                                                   const std::vector<ServerMapPoint*>& points,
                                                   const LoopVerificationOptions& options) {
  const std::vector<Descriptor> descriptors = query.Descriptors();
  std::vector<int> point_of(query.keypoints.size(), -1);
  std::vector<int> best_distance_of_point(points.size(), std::numeric_limits<int>::max());
  std::vector<int> keypoint_of_point(points.size(), -1);
  for (std::size_t i = 0; i < query.keypoints.size(); ++i) {
    int best = std::numeric_limits<int>::max(), second = best, best_j = -1;
    for (std::size_t j = 0; j < points.size(); ++j) {
      const int d = HammingDistance(descriptors[i], points[j]->descriptor);
      if (d < best) {
        second = best;
        best = d;
        best_j = static_cast<int>(j);
      } else if (d < second) {
        second = d;
      }
    }
    if (best_j < 0 || best > options.max_hamming || best > options.ratio * second) continue;
    if (best >= best_distance_of_point[best_j]) continue;
    if (keypoint_of_point[best_j] >= 0) point_of[keypoint_of_point[best_j]] = -1;
    best_distance_of_point[best_j] = best;
    keypoint_of_point[best_j] = static_cast<int>(i);
    point_of[i] = best_j;
  }
  return point_of;
}

// The RANSAC's settings for a loop: more draws and a higher confidence than tracking's, and
// the options' threshold and count.
PnpRansacOptions LoopPnp(const LoopVerificationOptions& options) {
  PnpRansacOptions pnp;
  pnp.iterations = 300;
  pnp.reprojection_px = static_cast<float>(options.ransac_reprojection_px);
  pnp.confidence = 0.999;
  pnp.min_inliers = options.min_ransac_inliers;
  return pnp;
}

}  // namespace

std::optional<LoopMatch> VerifyLoop(ServerKeyframe* query, const PinholeCamera& camera,
                                    ServerKeyframe* candidate, const ServerMap& candidate_map,
                                    const LoopVerificationOptions& options) {
  const std::vector<ServerMapPoint*> points =
      LoopWindowPoints(query, candidate, candidate_map, options.window_keyframes);
  if (static_cast<int>(points.size()) < options.min_matches) return std::nullopt;
  const std::vector<int> point_of = MatchKeypoints(*query, points, options);
  std::vector<cv::Point3f> object;
  std::vector<cv::Point2f> image;
  std::vector<int> keypoint_index;
  for (std::size_t i = 0; i < point_of.size(); ++i) {
    if (point_of[i] < 0) continue;
    const Eigen::Vector3d p = points[point_of[i]]->World();
    object.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()),
                        static_cast<float>(p.z()));
    image.push_back(query->keypoints[i].pt);
    keypoint_index.push_back(static_cast<int>(i));
  }
  if (static_cast<int>(object.size()) < options.min_matches) return std::nullopt;
  // The query camera's pose in the candidate's map, if enough matches agree.
  cv::setRNGSeed(0x100b);  // deterministic RANSAC
  const std::optional<Pose> T_cam_map = SolvePnpRansac(object, image, camera, LoopPnp(options));
  if (!T_cam_map) return std::nullopt;

  // Refine with every match (outliers are re-classified) and the measured depths, twice. First
  // with depth weighed no stricter than kTolerantDepthNoise: the other map's points carry
  // their own errors of millimetres, which a precise sensor's model (rendered depth: 0.5 mm)
  // would count against nearly every true match, so this pass decides whether the loop
  // holds. Then from that pose with the agent's own model: at least as many matches as RANSAC
  // needed must agree to the sensor's precision; its pose is the loop's, and only its inliers
  // are merged later (a merged point the global BA weighs with that precision must be one
  // point).
  std::vector<PoseObservation> observations;
  for (std::size_t k = 0; k < object.size(); ++k) {
    const ServerKeypoint& kp = query->keypoints[keypoint_index[k]];
    const double inv_sigma2 = std::pow(1.2, -2.0 * kp.octave);
    observations.push_back({points[point_of[keypoint_index[k]]]->World(),
                            Eigen::Vector2d(kp.pt.x, kp.pt.y), kp.depth, inv_sigma2, 0.0});
  }
  const Intrinsics intrinsics{camera.fx, camera.fy, camera.cx, camera.cy};
  const auto weigh = [&](bool tolerant) {
    for (PoseObservation& o : observations) {
      if (o.depth <= 0) continue;
      o.depth_information = options.depth_noise.Information(o.depth);
      if (tolerant) {
        o.depth_information =
            std::min(o.depth_information, kTolerantDepthNoise.Information(o.depth));
      }
    }
  };
  weigh(/*tolerant=*/true);
  const PoseOptimizationResult held = OptimizePose(*T_cam_map, observations, intrinsics);
  if (held.inliers < options.min_inliers) return std::nullopt;
  weigh(/*tolerant=*/false);
  const PoseOptimizationResult precise = OptimizePose(held.T_cam_world, observations, intrinsics);
  if (precise.inliers < options.min_ransac_inliers) return std::nullopt;

  LoopMatch match;
  match.query = query;
  match.candidate = candidate;
  match.T_candidate_map_query = precise.T_cam_world.inverse();
  match.inliers = held.inliers;
  for (std::size_t k = 0; k < observations.size(); ++k) {
    if (precise.inlier[k])
      match.matches.emplace_back(keypoint_index[k], points[point_of[keypoint_index[k]]]);
  }
  return match;
}

}  // namespace ccmd
