#include "libccmd/backend/map_optimization.h"

#include <unordered_map>

namespace ccmd {

StatusOr<std::vector<ServerKeyframe*>> OptimizeMapPoseGraph(ServerMap* map, const MapPoseGraphOptions& options) {
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
  auto relative = [](const ServerKeyframe* a, const ServerKeyframe* b) { return a->T_map_cam.inverse() * b->T_map_cam; };
  const double odo_r = 1.0 / options.odometry_sigma_rotation, odo_t = 1.0 / options.odometry_sigma_translation;
  // Consecutive keyframes of each agent.
  for (std::size_t i = 1; i < keyframes.size(); ++i) {
    if (keyframes[i]->id.agent != keyframes[i - 1]->id.agent) continue;
    edges.push_back({static_cast<int>(i - 1), static_cast<int>(i), relative(keyframes[i - 1], keyframes[i]), odo_r, odo_t});
  }
  // Strong covisibility links, once per pair.
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    for (const auto& [other, weight] : keyframes[i]->covisibility) {
      if (weight < options.min_covisibility_weight) continue;
      const auto it = index.find(other);
      if (it == index.end() || it->second <= static_cast<int>(i)) continue;
      edges.push_back({static_cast<int>(i), it->second, relative(keyframes[i], keyframes[it->second]), odo_r, odo_t});
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
  CCMD_ASSIGN_OR_RETURN(const PoseGraphSummary summary, OptimizePoseGraph(&nodes, edges, graph_options));
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

GlobalBaProblem BuildGlobalBa(const ServerMap& map, const std::map<AgentId, PinholeCamera>& cameras,
                              const DepthNoise& depth_noise) {
  GlobalBaProblem g;
  std::map<AgentId, int> calibration;
  for (const auto& [agent, camera] : cameras) {
    calibration[agent] = static_cast<int>(g.problem.calibrations.size());
    g.problem.calibrations.push_back({camera.fx, camera.fy, camera.cx, camera.cy});
  }
  std::unordered_map<const ServerKeyframe*, int> camera_index;
  for (const auto& [id, kf] : map.keyframes()) {
    const auto c = calibration.find(id.agent);
    if (c == calibration.end()) continue;  // no camera known for that agent (cannot happen in a session)
    camera_index[kf.get()] = static_cast<int>(g.keyframes.size());
    g.keyframes.push_back(id);
    g.T_map_cam_before[id] = kf->T_map_cam;
    g.problem.cameras.push_back({kf->T_map_cam.inverse(), map.origin() && id == *map.origin(), c->second});
  }
  // The agents' dense depth alignments between keyframes both in this map.
  for (const auto& [id, kf] : map.keyframes()) {
    const auto b = camera_index.find(kf.get());
    if (b == camera_index.end()) continue;
    for (const ServerKeyframe::DepthLink& link : kf->depth_links) {
      const auto a = camera_index.find(map.keyframe(link.other));
      if (a != camera_index.end()) g.problem.relative_poses.push_back({a->second, b->second, link.T_this_other, link.sqrt_information});
    }
  }
  // Points: collected through the keyframes (each once), kept if seen at least twice.
  std::unordered_map<const ServerMapPoint*, int> point_index;
  for (const auto& [id, kf] : map.keyframes()) {
    for (const ServerMapPoint* p : kf->points) {
      if (!p || point_index.count(p) || p->observations.size() < 2) continue;
      point_index[p] = static_cast<int>(g.points.size());
      g.points.push_back(p->id);
      g.problem.points.push_back({p->World()});
      for (const auto& o : p->observations) {
        const auto c = camera_index.find(o.keyframe);
        if (c == camera_index.end()) continue;
        const ServerKeypoint& kp = o.keyframe->keypoints[o.keypoint];
        g.problem.observations.push_back({c->second, point_index[p], Eigen::Vector2d(kp.pt.x, kp.pt.y), kp.depth,
                                          std::pow(1.2, -2.0 * kp.octave),
                                          kp.depth > 0 ? depth_noise.Information(kp.depth) : 0.0});
      }
    }
  }
  return g;
}

std::vector<ServerKeyframe*> ApplyGlobalBa(ServerMap* map, const GlobalBaProblem& g) {
  std::vector<ServerKeyframe*> moved;
  // Corrections of the optimised keyframes (world-frame deltas), by agent in id order.
  std::map<AgentId, std::map<KeyframeId, Pose>> corrections;
  for (std::size_t c = 0; c < g.keyframes.size(); ++c) {
    ServerKeyframe* kf = map->keyframe(g.keyframes[c]);
    if (!kf) continue;
    const Pose before = g.T_map_cam_before.at(g.keyframes[c]);
    const Pose after = g.problem.cameras[c].T_cam_world.inverse();
    // Pose updates from the agent may have arrived during the solve: keep them on top.
    const Pose since = before.inverse() * kf->T_map_cam;
    kf->T_map_cam = Orthonormalized(after * since);
    corrections[kf->id.agent][kf->id.keyframe] = after * before.inverse();
    moved.push_back(kf);
  }
  for (const auto& [id, kf] : map->keyframes()) {
    if (g.T_map_cam_before.count(id)) continue;
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
