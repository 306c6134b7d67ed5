#include "libccmd/backend/map_optimization.h"

#include <algorithm>
#include <unordered_map>
#include <unordered_set>

namespace ccmd {

Status MapPoseGraphOptions::Validate() const {
  if (min_covisibility_weight < 1)
    return InvalidArgument("pose graph covisibility weight must be >= 1");
  for (const double s : {odometry_sigma_rotation, odometry_sigma_translation, loop_sigma_rotation,
                         loop_sigma_translation}) {
    if (!(s > 0) || !std::isfinite(s)) return InvalidArgument("pose graph sigmas must be positive");
  }
  if (max_iterations < 1) return InvalidArgument("pose graph iterations must be >= 1");
  return Status::Ok();
}

void MapPoseGraphOptions::Describe(OptionsWriter* out) const {
  out->Add("min_covisibility_weight", min_covisibility_weight);
  out->Add("odometry_sigma_rotation", odometry_sigma_rotation);
  out->Add("odometry_sigma_translation", odometry_sigma_translation);
  out->Add("loop_sigma_rotation", loop_sigma_rotation);
  out->Add("loop_sigma_translation", loop_sigma_translation);
  out->Add("max_iterations", max_iterations);
}

StatusOr<std::vector<ServerKeyframe*>> OptimizeMapPoseGraph(ServerMap* map,
                                                            const MapPoseGraphOptions& options) {
  std::vector<ServerKeyframe*> keyframes;
  std::map<GlobalKeyframeId, int> index;
  std::vector<PoseGraphNode> nodes;
  for (const auto& [id, kf] : map->keyframes()) {
    index[id] = static_cast<int>(keyframes.size());
    keyframes.push_back(kf.get());
    nodes.push_back({kf->T_map_cam, map->origin() && id == *map->origin()});
  }
  if (keyframes.size() < 2) return std::vector<ServerKeyframe*>{};
  std::vector<PoseGraphEdge> edges;
  auto relative = [](const ServerKeyframe* a, const ServerKeyframe* b) {
    return a->T_map_cam.inverse() * b->T_map_cam;
  };
  const double odo_r = 1.0 / options.odometry_sigma_rotation,
               odo_t = 1.0 / options.odometry_sigma_translation;
  // Consecutive keyframes of each agent.
  for (std::size_t i = 1; i < keyframes.size(); ++i) {
    if (keyframes[i]->id.agent != keyframes[i - 1]->id.agent) continue;
    const bool restart = keyframes[i]->restart;
    edges.push_back({static_cast<int>(i - 1), static_cast<int>(i),
                     relative(keyframes[i - 1], keyframes[i]),
                     restart ? 1.0 / kRestartSigmaRotation : odo_r,
                     restart ? 1.0 / kRestartSigmaTranslation : odo_t});
  }
  // Strong covisibility links, once per pair.
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    for (const auto& [other, weight] : keyframes[i]->covisibility) {
      if (weight < options.min_covisibility_weight) continue;
      const auto it = index.find(other);
      if (it == index.end() || it->second <= static_cast<int>(i)) continue;
      edges.push_back({static_cast<int>(i), it->second,
                       relative(keyframes[i], keyframes[it->second]), odo_r, odo_t});
    }
  }
  for (const LoopEdge& loop : map->loop_edges()) {
    const auto a = index.find(loop.a), b = index.find(loop.b);
    if (a == index.end() || b == index.end()) continue;
    edges.push_back({a->second, b->second, loop.T_a_b, 1.0 / options.loop_sigma_rotation,
                     1.0 / options.loop_sigma_translation});
  }
  PoseGraphOptions graph_options;
  graph_options.max_iterations = options.max_iterations;
  CCMD_ASSIGN_OR_RETURN(const PoseGraphSummary summary,
                        OptimizePoseGraph(&nodes, edges, graph_options));
  (void)summary;
  std::vector<ServerKeyframe*> moved;
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    if (TranslationDistance(keyframes[i]->T_map_cam, nodes[i].T_world_node) > 1e-9 ||
        RotationDistance(keyframes[i]->T_map_cam, nodes[i].T_world_node) > 1e-9) {
      keyframes[i]->T_map_cam = Orthonormalized(nodes[i].T_world_node);
      moved.push_back(keyframes[i]);
    }
  }
  return moved;
}

namespace {

// Fills a GlobalBaProblem: cameras (keyframes) and points, each added once.
class GlobalBaBuilder {
 public:
  GlobalBaBuilder(const ServerMap& map, const std::map<AgentId, PinholeCamera>& cameras,
                  const AgentDepthNoise& depth_noise, GlobalBaProblem* g)
      : map_(map), depth_noise_(depth_noise), g_(g) {
    for (const auto& [agent, camera] : cameras) {
      calibration_[agent] = static_cast<int>(g_->problem.calibrations.size());
      g_->problem.calibrations.push_back({camera.fx, camera.fy, camera.cx, camera.cy});
    }
    for (const auto& [id, kf] : map.keyframes()) {
      KeyframeId& last = g_->last_keyframe[id.agent];
      last = std::max(last, id.keyframe);
    }
  }

  // The keyframe's camera index, added (fixed or not) the first time; -1 without a camera.
  int Camera(const ServerKeyframe* kf, bool fixed) {
    const auto known = camera_index_.find(kf);
    if (known != camera_index_.end()) return known->second;
    const auto c = calibration_.find(kf->id.agent);
    if (c == calibration_.end())
      return -1;  // no camera known for that agent (cannot happen in a session)
    const int index = static_cast<int>(g_->keyframes.size());
    camera_index_[kf] = index;
    g_->keyframes.push_back(kf->id);
    g_->T_map_cam_before[kf->id] = kf->T_map_cam;
    const bool origin = map_.origin() && kf->id == *map_.origin();
    g_->problem.cameras.push_back({kf->T_map_cam.inverse(), fixed || origin, c->second});
    return index;
  }

  // A point seen at least twice, with its observations by the problem's cameras and by the
  // keyframes in `fixed` (they join as fixed cameras).
  void Point(const ServerMapPoint* p, const std::set<const ServerKeyframe*>* fixed = nullptr) {
    if (!p || point_index_.count(p) || p->observations.size() < 2) return;
    const int index = static_cast<int>(g_->points.size());
    point_index_[p] = index;
    g_->points.push_back(p->id);
    g_->problem.points.push_back({p->World()});
    for (const auto& o : p->observations) {
      const int c = fixed && fixed->count(o.keyframe) ? Camera(o.keyframe, /*fixed=*/true)
                                                      : Known(o.keyframe);
      if (c < 0) continue;
      const ServerKeypoint& kp = o.keyframe->keypoints[o.keypoint];
      const DepthNoise& noise = depth_noise_.Of(o.keyframe->id.agent);
      g_->problem.observations.push_back({c, index, Eigen::Vector2d(kp.pt.x, kp.pt.y), kp.depth,
                                          std::pow(1.2, -2.0 * kp.octave),
                                          kp.depth > 0 ? noise.Information(kp.depth) : 0.0});
    }
  }

  // The agents' dense depth alignments between keyframes both in the problem.
  void DepthLinks() {
    for (std::size_t b = 0; b < g_->keyframes.size(); ++b) {
      for (const ServerKeyframe::DepthLink& link : map_.keyframe(g_->keyframes[b])->depth_links) {
        const int a = Known(map_.keyframe(link.other));
        if (a >= 0) {
          g_->problem.relative_poses.push_back(
              {a, static_cast<int>(b), link.T_this_other, link.sqrt_information});
        }
      }
    }
  }

  // Each restarted segment's first keyframe, loosely tied at its current place to its
  // agent's kept keyframe before it: without the tie nothing holds the segment's gauge.
  void RestartLinks() {
    Eigen::Matrix<double, 6, 6> sqrt_information = Eigen::Matrix<double, 6, 6>::Zero();
    sqrt_information.diagonal() << Eigen::Vector3d::Constant(1.0 / kRestartSigmaRotation),
        Eigen::Vector3d::Constant(1.0 / kRestartSigmaTranslation);
    const ServerKeyframe* previous = nullptr;
    for (const auto& [id, kf] : map_.keyframes()) {
      if (kf->restart && previous && previous->id.agent == id.agent) {
        const int a = Known(previous), b = Known(kf.get());
        if (a >= 0 && b >= 0) {
          g_->problem.relative_poses.push_back(
              {a, b, kf->T_map_cam.inverse() * previous->T_map_cam, sqrt_information});
        }
      }
      previous = kf.get();
    }
  }

 private:
  int Known(const ServerKeyframe* kf) const {
    const auto it = camera_index_.find(kf);
    return it == camera_index_.end() ? -1 : it->second;
  }

  const ServerMap& map_;
  const AgentDepthNoise& depth_noise_;
  GlobalBaProblem* g_;
  std::map<AgentId, int> calibration_;
  std::unordered_map<const ServerKeyframe*, int> camera_index_;
  std::unordered_map<const ServerMapPoint*, int> point_index_;
};

}  // namespace

namespace {

// The keyframes outside a window that see its points most often, at most half as many as the
// window holds: they hold the window in place (the gauge) without the problem growing with
// every pass over the place.
std::set<const ServerKeyframe*> FixedNeighbours(const ServerMap& map,
                                                const std::set<GlobalKeyframeId>& window) {
  std::map<const ServerKeyframe*, int> seen;
  std::unordered_set<const ServerMapPoint*> visited;
  for (const GlobalKeyframeId& id : window) {
    const ServerKeyframe* kf = map.keyframe(id);
    if (!kf) continue;
    for (const ServerMapPoint* p : kf->points) {
      if (!p || p->observations.size() < 2 || !visited.insert(p).second) continue;
      for (const auto& o : p->observations) {
        if (!window.count(o.keyframe->id)) seen[o.keyframe]++;
      }
    }
  }
  std::vector<std::pair<int, const ServerKeyframe*>> ranked;
  for (const auto& [kf, count] : seen) ranked.emplace_back(count, kf);
  std::sort(ranked.begin(), ranked.end(), [](const auto& a, const auto& b) {
    return a.first != b.first ? a.first > b.first : a.second->id < b.second->id;
  });
  std::set<const ServerKeyframe*> fixed;
  const std::size_t budget = std::max<std::size_t>(10, window.size() / 2);
  for (std::size_t i = 0; i < ranked.size() && i < budget; ++i) fixed.insert(ranked[i].second);
  return fixed;
}

}  // namespace

GlobalBaProblem BuildGlobalBa(const ServerMap& map, const std::map<AgentId, PinholeCamera>& cameras,
                              const AgentDepthNoise& depth_noise,
                              const std::set<GlobalKeyframeId>* window) {
  GlobalBaProblem g;
  GlobalBaBuilder builder(map, cameras, depth_noise, &g);
  for (const auto& [id, kf] : map.keyframes()) {
    if (!window || window->count(id)) builder.Camera(kf.get(), /*fixed=*/false);
  }
  std::set<const ServerKeyframe*> fixed;
  if (window) fixed = FixedNeighbours(map, *window);
  // Points: collected through the keyframes (each once), kept if seen at least twice.
  for (const auto& [id, kf] : map.keyframes()) {
    if (window && !window->count(id)) continue;
    for (const ServerMapPoint* p : kf->points) builder.Point(p, window ? &fixed : nullptr);
  }
  builder.DepthLinks();
  builder.RestartLinks();
  const bool gauge = std::any_of(g.problem.cameras.begin(), g.problem.cameras.end(),
                                 [](const auto& c) { return c.fixed; });
  if (!gauge && !g.problem.cameras.empty()) g.problem.cameras[0].fixed = true;
  return g;
}

namespace {

// A keyframe's observations in a global BA: of its points seen at least twice.
std::size_t GlobalBaObservationsOf(const ServerKeyframe& kf) {
  std::size_t observations = 0;
  for (const ServerMapPoint* p : kf.points) observations += p && p->observations.size() >= 2;
  return observations;
}

}  // namespace

std::set<GlobalKeyframeId> SelectGlobalBaWindow(const ServerMap& map,
                                                const std::vector<GlobalKeyframeId>& seeds,
                                                int max_keyframes, std::size_t max_observations) {
  std::set<GlobalKeyframeId> window;
  std::size_t observations = 0;
  // Adds a keyframe if both bounds allow it.
  const auto admit = [&](const ServerKeyframe* kf) {
    const std::size_t own = GlobalBaObservationsOf(*kf);
    if (static_cast<int>(window.size()) >= max_keyframes ||
        (!window.empty() && observations + own > max_observations)) {
      return false;
    }
    observations += own;
    return window.insert(kf->id).second;
  };
  std::vector<const ServerKeyframe*> frontier;
  for (const GlobalKeyframeId& id : seeds) {
    const ServerKeyframe* kf = map.keyframe(id);
    if (kf && !window.count(id) && admit(kf)) frontier.push_back(kf);
  }
  bool full = false;
  while (!frontier.empty() && !full) {
    std::vector<std::pair<int, const ServerKeyframe*>> next;  // (link weight, keyframe)
    for (const ServerKeyframe* kf : frontier) {
      for (const auto& [other, weight] : kf->covisibility) {
        const ServerKeyframe* o = map.keyframe(other);
        if (o && !window.count(other)) next.emplace_back(weight, o);
      }
    }
    std::sort(next.begin(), next.end(), [](const auto& a, const auto& b) {
      return a.first != b.first ? a.first > b.first : a.second->id < b.second->id;
    });
    frontier.clear();
    for (const auto& [weight, kf] : next) {
      if (window.count(kf->id)) continue;
      if (!admit(kf)) {
        full = true;
        break;
      }
      frontier.push_back(kf);
    }
  }
  return window;
}

std::size_t CountGlobalBaObservations(const ServerMap& map) {
  std::size_t observations = 0;
  for (const auto& [id, kf] : map.keyframes()) observations += GlobalBaObservationsOf(*kf);
  return observations;
}

std::vector<ServerKeyframe*> ApplyGlobalBa(ServerMap* map, const GlobalBaProblem& g) {
  std::vector<ServerKeyframe*> moved;
  // Corrections of the optimised keyframes (world-frame deltas), by agent in id order.
  std::map<AgentId, std::map<KeyframeId, Pose>> corrections;
  for (std::size_t c = 0; c < g.keyframes.size(); ++c) {
    ServerKeyframe* kf = map->keyframe(g.keyframes[c]);
    if (!kf) continue;  // culled during the solve: it follows its leader
    const Pose before = g.T_map_cam_before.at(g.keyframes[c]);
    const Pose after = g.problem.cameras[c].T_cam_world.inverse();
    corrections[kf->id.agent][kf->id.keyframe] = after * before.inverse();
    if (g.problem.cameras[c].fixed) continue;
    // Pose updates from the agent may have arrived during the solve: keep them on top.
    const Pose since = before.inverse() * kf->T_map_cam;
    kf->T_map_cam = Orthonormalized(after * since);
    moved.push_back(kf);
  }
  for (const auto& [id, kf] : map->keyframes()) {
    // Only keyframes that arrived after the problem was built (others were left out on purpose).
    const auto last = g.last_keyframe.find(id.agent);
    if (g.T_map_cam_before.count(id) ||
        (last != g.last_keyframe.end() && id.keyframe <= last->second))
      continue;
    const auto agent = corrections.find(id.agent);
    if (agent == corrections.end() || agent->second.empty()) continue;
    // Nearest optimised keyframe of the same agent at or before this one (else the first).
    auto it = agent->second.upper_bound(id.keyframe);
    if (it != agent->second.begin()) --it;
    kf->T_map_cam = Orthonormalized(it->second * kf->T_map_cam);
    moved.push_back(kf.get());
  }
  // Points last: their anchors have their final poses now.
  for (std::size_t j = 0; j < g.points.size(); ++j) {
    if (ServerMapPoint* p = map->point(g.points[j])) p->SetWorld(g.problem.points[j].position);
  }
  return moved;
}

}  // namespace ccmd
