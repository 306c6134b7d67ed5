#include "libccmd/tracking/local_ba.h"

#include <unordered_map>

namespace ccmd {

LocalBaProblem BuildLocalBa(Keyframe* keyframe, int window, const LocalMap& map,
                            const OrbExtractor& orb) {
  LocalBaProblem local;
  BaProblem& problem = local.problem;
  std::vector<Keyframe*> free = {keyframe};
  for (Keyframe* n : keyframe->BestCovisible(window)) free.push_back(n);
  std::unordered_map<const Keyframe*, int> camera_index;
  for (Keyframe* kf : free) {
    camera_index[kf] = static_cast<int>(local.cameras.size());
    local.cameras.push_back(map.keyframe(kf->id()));
    problem.cameras.push_back({kf->T_cam_world(), false});
  }
  std::unordered_map<const MapPoint*, int> point_index;
  for (Keyframe* kf : free) {
    for (const MapPointPtr& p : kf->points()) {
      if (!p || p->bad() || point_index.count(p.get())) continue;
      point_index[p.get()] = static_cast<int>(local.points.size());
      local.points.push_back(p);
      problem.points.push_back({p->position()});
    }
  }
  // Every keyframe that sees a local point constrains it; those outside the window are fixed.
  for (std::size_t j = 0; j < local.points.size(); ++j) {
    for (const auto& o : local.points[j]->observations()) {
      Keyframe* kf = o.keyframe;
      if (kf->bad()) continue;
      auto it = camera_index.find(kf);
      if (it == camera_index.end()) {
        it = camera_index.emplace(kf, static_cast<int>(local.cameras.size())).first;
        local.cameras.push_back(map.keyframe(kf->id()));
        problem.cameras.push_back({kf->T_cam_world(), true});
      }
      const cv::KeyPoint& kp = kf->features().keypoints[o.keypoint];
      const double z = kf->features().depth[o.keypoint];
      problem.observations.push_back(
          {it->second, static_cast<int>(j), Eigen::Vector2d(kp.pt.x, kp.pt.y), z,
           orb.inv_sigma2()[kp.octave], kf->features().DepthInformation(o.keypoint)});
    }
  }
  // Gauge: the map's first keyframe never moves; without any fixed keyframe, the oldest one in
  // the window is held.
  bool any_fixed = false;
  int oldest = 0;
  for (std::size_t c = 0; c < local.cameras.size(); ++c) {
    if (local.cameras[c]->id().value() == 0) problem.cameras[c].fixed = true;
    any_fixed |= problem.cameras[c].fixed;
    if (local.cameras[c]->id() < local.cameras[oldest]->id()) oldest = static_cast<int>(c);
  }
  if (!any_fixed) problem.cameras[oldest].fixed = true;
  return local;
}

void ApplyLocalBa(const LocalBaProblem& local, const BaSummary& summary, LocalMap* map,
                  const OrbExtractor& orb) {
  const BaProblem& problem = local.problem;
  for (std::size_t i = 0; i < problem.observations.size(); ++i) {
    if (!summary.outlier[i]) continue;
    const BaObservation& o = problem.observations[i];
    Keyframe* kf = local.cameras[o.camera].get();
    MapPoint* p = local.points[o.point].get();
    if (!kf->bad() && !p->bad() && p->KeypointIn(kf) >= 0) map->EraseObservation(p, kf);
  }
  for (std::size_t c = 0; c < local.cameras.size(); ++c) {
    if (!problem.cameras[c].fixed && !local.cameras[c]->bad()) {
      local.cameras[c]->set_T_world_cam(problem.cameras[c].T_cam_world.inverse());
    }
  }
  for (std::size_t j = 0; j < local.points.size(); ++j) {
    if (local.points[j]->bad()) continue;
    local.points[j]->set_position(problem.points[j].position);
    local.points[j]->UpdateNormalAndDepth(orb);
  }
}

}  // namespace ccmd
