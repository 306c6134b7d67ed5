#include "libccmd/backend/ingest.h"

#include "libccmd/codec/wire_pose.h"
#include "libccmd/optim/bundle_adjuster.h"
#include "libccmd/util/logging.h"

namespace ccmd {

namespace {

// The keyframe placed in the map's frame: relative to a keyframe of the same agent the server
// already has, else by T_map_agent; a restarted segment is kept apart until a loop places it.
std::unique_ptr<ServerKeyframe> MakeKeyframe(ServerMap* map, AgentId agent,
                                             const KeyframeMessage& m, const Pose& T_map_agent) {
  const GlobalKeyframeId id{agent, m.id};
  auto kf = std::make_unique<ServerKeyframe>();
  kf->id = id;
  kf->timestamp = m.timestamp;
  kf->T_agent_cam = PoseFromWire(m.T_world_cam);
  kf->parent = m.parent;

  // Placement: relative to a keyframe of the same agent the server already has.
  ServerKeyframe* reference = m.parent ? map->keyframe({agent, *m.parent}) : nullptr;
  if (!reference) {
    const auto own = map->AgentKeyframes(agent);
    if (!own.empty()) reference = own.back();
  }
  kf->restart = m.restart;
  kf->segment = m.restart || !reference ? m.id : reference->segment;
  // Only a loop can place a restarted segment against the agent's earlier keyframes. A reset
  // (KeyframeMessage::reset) is posed as well as tracking would: it is placed as the segment
  // before it is. In a map of fewer keyframes than a young segment, those few are what is
  // kept apart instead: the new segment is the map from now on.
  if (m.restart && reference) {
    if (m.reset) {
      if (const auto group = map->UnplacedGroup(*reference)) map->AddUnplacedSegment(id, *group);
    } else if (map->keyframes().size() >= kYoungSegmentKeyframes) {
      map->AddUnplacedSegment(id);
    } else {
      std::optional<GlobalKeyframeId> group;
      for (const auto& [kid, k] : map->keyframes()) {
        const GlobalKeyframeId segment{kid.agent, k->segment};
        if (!group) group = segment;
        map->AddUnplacedSegment(segment, *group);
      }
    }
  }
  kf->T_map_cam = reference
                      ? reference->T_map_cam * (reference->T_agent_cam.inverse() * kf->T_agent_cam)
                      : T_map_agent * kf->T_agent_cam;

  const std::size_t n = m.keypoints.size();
  kf->keypoints.resize(n);
  kf->points.assign(n, nullptr);
  for (std::size_t i = 0; i < n; ++i) {
    const WireKeypoint& w = m.keypoints[i];
    kf->keypoints[i] = {cv::Point2f(w.u, w.v), w.octave, w.depth_m > 0 ? w.depth_m : 0.0f};
  }
  return kf;
}

// Its new map points anchored in it, its keypoints' links to points the server has, and the
// own descriptors of the keypoints left without a point.
void AttachMapPoints(ServerMap* map, AgentId agent, const KeyframeMessage& m,
                     ServerKeyframe* keyframe) {
  const std::size_t n = m.keypoints.size();
  // New points are anchored here; the keypoint observing each is found by its link.
  std::unordered_map<std::uint32_t, int> keypoint_of;
  for (std::size_t i = 0; i < n; ++i) {
    if (m.keypoints[i].map_point)
      keypoint_of[m.keypoints[i].map_point->value()] = static_cast<int>(i);
  }
  for (const NewMapPoint& p : m.new_map_points) {
    const GlobalMapPointId pid{agent, p.id};
    if (map->point(pid)) continue;  // resent after a reconnect: already known
    ServerMapPoint* point = map->AddPoint(std::make_unique<ServerMapPoint>(
        pid, keyframe, Eigen::Vector3d(p.p_cam[0], p.p_cam[1], p.p_cam[2]), p.descriptor));
    const auto it = keypoint_of.find(p.id.value());
    if (it != keypoint_of.end()) map->AddObservation(point, keyframe, it->second);
  }
  int unknown_links = 0;
  for (std::size_t i = 0; i < n; ++i) {
    if (!m.keypoints[i].map_point || keyframe->points[i]) continue;
    ServerMapPoint* point = map->point({agent, *m.keypoints[i].map_point});
    if (!point) {
      ++unknown_links;
      continue;
    }
    map->AddObservation(point, keyframe, static_cast<int>(i));  // its descriptor is the point's
  }
  // Keypoints without a map point (none, or one the server never received) keep their own.
  for (std::size_t i = 0; i < n; ++i) {
    if (!keyframe->points[i])
      keyframe->own_descriptors.emplace_back(static_cast<std::uint32_t>(i),
                                             m.keypoints[i].descriptor);
  }
  keyframe->own_descriptors.shrink_to_fit();
  if (unknown_links > 0) {
    CCMD_LOG(WARNING) << "keyframe " << m.id.value() << " of agent " << agent.value() << " links "
                      << unknown_links << " map points the server never received";
  }
}

// Its covisibility with, and depth alignments to, the agent's earlier keyframes.
void AttachLinks(ServerMap* map, AgentId agent, const KeyframeMessage& m,
                 ServerKeyframe* keyframe) {
  for (const CovisibilityLink& link : m.covisibility) {
    if (ServerKeyframe* other = map->keyframe({agent, link.keyframe})) {
      map->AddCovisibility(keyframe, other, static_cast<int>(link.weight));
    }
  }
  for (const DepthLink& link : m.depth_links) {
    Eigen::Matrix<double, 6, 6> information;
    int k = 0;
    for (int r = 0; r < 6; ++r) {
      for (int c = r; c < 6; ++c) information(r, c) = information(c, r) = link.information[k++];
    }
    keyframe->depth_links.push_back(
        {{agent, link.keyframe}, PoseFromWire(link.T_this_other), SqrtInformation(information)});
  }
}

}  // namespace

StatusOr<ServerKeyframe*> AddKeyframeMessage(ServerMap* map, AgentId agent,
                                             const KeyframeMessage& m, const Pose& T_map_agent) {
  // An agent's keyframe ids only grow: an id not newer than its newest was received before
  // (and may have been culled since, leaving only its pose).
  const std::optional<KeyframeId> newest = map->NewestKeyframeOf(agent);
  if (newest && m.id <= *newest) {
    return InvalidArgument("keyframe " + std::to_string(m.id.value()) +
                           " already known (the agent's newest is " +
                           std::to_string(newest->value()) + ")");
  }
  ServerKeyframe* keyframe = map->AddKeyframe(MakeKeyframe(map, agent, m, T_map_agent));
  AttachMapPoints(map, agent, m, keyframe);
  AttachLinks(map, agent, m, keyframe);
  return keyframe;
}

std::vector<ServerKeyframe*> ApplyPoseUpdates(ServerMap* map, AgentId agent,
                                              const PoseUpdateMessage& m) {
  std::vector<ServerKeyframe*> moved;
  for (const PoseUpdateEntry& e : m.entries) {
    ServerKeyframe* kf = map->keyframe({agent, e.keyframe});
    if (!kf) continue;
    const Pose T_agent_new = PoseFromWire(e.T_world_cam);
    const Pose change = kf->T_agent_cam.inverse() * T_agent_new;
    kf->T_map_cam = kf->T_map_cam * change;
    kf->T_agent_cam = T_agent_new;
    moved.push_back(kf);
  }
  return moved;
}

}  // namespace ccmd
