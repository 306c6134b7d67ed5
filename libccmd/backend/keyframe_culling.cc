#include "libccmd/backend/keyframe_culling.h"

#include <algorithm>
#include <cmath>

#include "libccmd/util/percentile.h"

namespace ccmd {

Status KeyframeCullingOptions::Validate() const {
  if (keep_recent < 1) return InvalidArgument("culling: keep_recent must be >= 1");
  if (!(min_coverage > 0 && min_coverage <= 1))
    return InvalidArgument("culling: min_coverage must be in (0, 1]");
  if (!(max_scale >= 1) || !std::isfinite(max_scale))
    return InvalidArgument("culling: max_scale must be >= 1");
  if (!(max_view_angle_deg > 0 && max_view_angle_deg < 90))
    return InvalidArgument("culling: max_view_angle_deg must be in (0, 90)");
  if (max_covering < 1) return InvalidArgument("culling: max_covering must be >= 1");
  if (min_depth_keypoints < 1) return InvalidArgument("culling: min_depth_keypoints must be >= 1");
  return Status::Ok();
}

void KeyframeCullingOptions::Describe(OptionsWriter* out) const {
  out->Add("enabled", enabled);
  out->Add("keep_recent", keep_recent);
  out->Add("min_coverage", min_coverage);
  out->Add("max_scale", max_scale);
  out->Add("max_view_angle_deg", max_view_angle_deg);
  out->Add("max_covering", max_covering);
  out->Add("min_depth_keypoints", min_depth_keypoints);
}

namespace {

double MedianDepth(const ServerKeyframe& kf) {
  std::vector<double> depths;
  depths.reserve(kf.keypoints.size());
  for (const ServerKeypoint& kp : kf.keypoints) {
    if (kp.depth > 0) depths.push_back(kp.depth);
  }
  return Percentile(std::move(depths), 0.5);
}

}  // namespace

std::vector<ServerKeyframe*> CoveringCandidates(const ServerMap& map, const ServerKeyframe& kf,
                                                const KeyframeCullingOptions& options,
                                                const std::vector<GlobalKeyframeId>* kept) {
  const double radius = MedianDepth(kf) / 3;
  const Eigen::Vector3d axis = kf.T_map_cam.linear().col(2);
  const double min_cos = std::cos(options.max_view_angle_deg * M_PI / 180);
  std::vector<std::pair<double, ServerKeyframe*>> near;
  // Only keyframes whose poses rest on the same measurements: a restarted segment that no loop
  // has placed yet may lie anywhere against the rest of the map.
  const std::optional<GlobalKeyframeId> group = map.UnplacedGroup(kf);
  const auto consider = [&](ServerKeyframe* other) {
    if (!other || other == &kf || !other->cull_checked) return;
    if (map.UnplacedGroup(*other) != group) return;
    const double distance = (other->camera_center() - kf.camera_center()).norm();
    if (distance > radius || other->T_map_cam.linear().col(2).dot(axis) < min_cos) return;
    near.emplace_back(distance, other);
  };
  if (kept) {
    for (const GlobalKeyframeId& id : *kept) consider(map.keyframe(id));
  } else {
    for (const auto& [id, other] : map.keyframes()) consider(other.get());
  }
  const std::size_t n = std::min<std::size_t>(near.size(), options.max_covering);
  std::partial_sort(near.begin(), near.begin() + static_cast<std::ptrdiff_t>(n), near.end(),
                    [](const auto& a, const auto& b) {
                      return a.first != b.first ? a.first < b.first : a.second->id < b.second->id;
                    });
  std::vector<ServerKeyframe*> result;
  for (std::size_t i = 0; i < n; ++i) result.push_back(near[i].second);
  return result;
}

Coverage MeasureCoverage(const ServerKeyframe& kf, const std::vector<ServerKeyframe*>& others,
                         const std::function<const PinholeCamera*(AgentId)>& camera_of,
                         const KeyframeCullingOptions& options) {
  Coverage coverage;
  const PinholeCamera* camera = camera_of(kf.id.agent);
  if (!camera || others.empty()) return coverage;
  struct Other {
    ServerKeyframe* kf;
    const PinholeCamera* camera;
    Pose T_other_kf;
    Eigen::Vector3d centre_in_kf;
    int seen = 0;
  };
  std::vector<Other> candidates;
  for (ServerKeyframe* o : others) {
    const PinholeCamera* c = camera_of(o->id.agent);
    if (!c) continue;
    const Pose T_other_kf = o->T_map_cam.inverse() * kf.T_map_cam;
    candidates.push_back({o, c, T_other_kf, T_other_kf.inverse().translation()});
  }
  const double min_cos = std::cos(options.max_view_angle_deg * M_PI / 180);
  int with_depth = 0, covered = 0;
  for (const ServerKeypoint& kp : kf.keypoints) {
    if (kp.depth <= 0) continue;
    ++with_depth;
    const Eigen::Vector3d p = camera->BackProject(kp.pt.x, kp.pt.y, kp.depth);
    const double distance = p.norm();
    bool seen = false;
    for (Other& o : candidates) {
      const Eigen::Vector3d q = o.T_other_kf * p;
      if (q.z() <= 0) continue;
      const double other_distance = q.norm();
      const double scale = other_distance / distance;
      if (scale > options.max_scale || scale * options.max_scale < 1) continue;
      // The angle between the two rays to the point.
      const Eigen::Vector3d ray_other = p - o.centre_in_kf;
      if (ray_other.dot(p) < min_cos * distance * other_distance) continue;
      if (!o.camera->InImage(o.camera->ProjectToImage(q))) continue;
      ++o.seen;
      seen = true;
    }
    covered += seen;
  }
  if (with_depth < options.min_depth_keypoints) return coverage;
  coverage.fraction = static_cast<double>(covered) / with_depth;
  const auto best =
      std::max_element(candidates.begin(), candidates.end(),
                       [](const Other& a, const Other& b) { return a.seen < b.seen; });
  if (best != candidates.end() && best->seen > 0) coverage.best = best->kf;
  return coverage;
}

std::optional<GlobalKeyframeId> KeyframeCuller::Arrived(const GlobalKeyframeId& id) {
  if (!options_.enabled) return std::nullopt;
  std::deque<GlobalKeyframeId>& recent = recent_[id.agent];
  recent.push_back(id);
  if (static_cast<int>(recent.size()) <= options_.keep_recent) return std::nullopt;
  const GlobalKeyframeId old = recent.front();
  recent.pop_front();
  return old;
}

bool KeyframeCuller::Check(ServerMap* map, const GlobalKeyframeId& id,
                           const std::function<const PinholeCamera*(AgentId)>& camera_of,
                           const std::function<bool(const GlobalKeyframeId&)>& may_cull) {
  ServerKeyframe* kf = map->keyframe(id);
  if (!kf || kf->cull_checked) return false;
  kf->cull_checked = true;
  ++stats_.checked;
  // The map's origin holds its gauge; a restarted segment's first keyframe carries the loose
  // link to the segment before it (map_optimization.h).
  if ((map->origin() && *map->origin() == id) || kf->restart) {
    kept_.push_back(id);
    return false;
  }
  const Coverage coverage =
      MeasureCoverage(*kf, CoveringCandidates(*map, *kf, options_, &kept_), camera_of, options_);
  if (coverage.fraction < options_.min_coverage || !coverage.best || !may_cull(id)) {
    kept_.push_back(id);
    return false;
  }
  stats_.points_removed += map->Cull(kf, coverage.best);
  ++stats_.culled;
  return true;
}

}  // namespace ccmd
