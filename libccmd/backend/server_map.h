#pragma once

// The server's copy of the agents' maps. Keyframes and map points arrive in keyframe messages;
// a server map holds the keyframes of one or more agents (several after map fusion) in one
// frame. Map points are anchored to a keyframe (their position is kept in that keyframe's
// camera frame), so any change to a keyframe's pose — a pose update from the agent, a pose
// graph or a fusion transform — carries its points along; global BA writes positions back in
// the anchor's frame.

#include <array>
#include <map>
#include <memory>
#include <optional>
#include <unordered_map>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/features/descriptor.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/util/ids.h"
#include "proto/messages.h"

namespace ccmd {

class ServerKeyframe;

class ServerMapPoint {
 public:
  ServerMapPoint(GlobalMapPointId id, ServerKeyframe* anchor, const Eigen::Vector3d& p_anchor,
                 const Descriptor& descriptor)
      : id(id), anchor(anchor), p_anchor(p_anchor), descriptor(descriptor) {}

  Eigen::Vector3d World() const;
  void SetWorld(const Eigen::Vector3d& p_world);

  GlobalMapPointId id;
  ServerKeyframe* anchor;
  Eigen::Vector3d p_anchor;  // in the anchor keyframe's camera frame
  Descriptor descriptor;
  struct Observation {
    ServerKeyframe* keyframe;
    int keypoint;
  };
  std::vector<Observation> observations;
};

// What the server uses of a keypoint (its orientation is not used: matching is by descriptor).
struct ServerKeypoint {
  cv::Point2f pt;
  std::uint8_t octave = 0;
  float depth = 0;  // metres, 0 = none
};

// What the server keeps of a keyframe the culling removed (ServerMap::Cull): what the
// trajectories and the dense map still need of it, held by the kept keyframe whose pose it
// follows (its leader): T_map_cam = leader.T_map_cam * T_leader_this. About 64 bytes where
// the keyframe object, its sparse data gone, took 0.7 kB: a camera circling a mapped room
// for hours adds no more than its trajectory.
struct CulledKeyframe {
  GlobalKeyframeId id;
  double timestamp = 0;
  // T_leader_this in single precision: the two are within a metre of each other, so the
  // rounding is under a micrometre and a microradian.
  std::array<float, 4> q_leader_this{0, 0, 0, 1};  // x y z w
  std::array<float, 3> t_leader_this{0, 0, 0};
  bool in_dense = false;  // its cloud went to the dense map (which may release it since)
  // Coded RGB-D waiting for its map to join the primary map (as ServerKeyframe::rgbd).
  std::shared_ptr<const RgbdPayload> rgbd;

  Pose T_leader_this() const;
  void SetT_leader_this(const Pose& T);
};

class ServerKeyframe {
 public:
  GlobalKeyframeId id;
  double timestamp = 0;
  Pose T_map_cam = Pose::Identity();    // in the server map it belongs to
  Pose T_agent_cam = Pose::Identity();  // as its agent last reported it (agent's own frame)
  std::optional<KeyframeId> parent;     // spanning tree, same agent
  // The agent lost tracking and started a new segment of its map with this keyframe
  // (KeyframeMessage::restart); `segment` is the first keyframe of this one's segment. Nothing
  // but a loop measures where a segment lies against the agent's earlier ones.
  bool restart = false;
  KeyframeId segment{0};
  std::vector<ServerKeypoint> keypoints;
  std::vector<ServerMapPoint*> points;  // per keypoint, may be null
  // A keypoint's descriptor is its map point's (as the agent sends it); only keypoints without
  // a map point keep one of their own, sorted by keypoint (most keypoints are linked: this
  // saves about 15 kB a keyframe).
  std::vector<std::pair<std::uint32_t, Descriptor>> own_descriptors;

  // The descriptor of keypoint i.
  const Descriptor& descriptor(std::size_t i) const;
  // Every keypoint's, in keypoint order.
  std::vector<Descriptor> Descriptors() const;
  // Appends a keypoint without a map point (tests and tools build keyframes with it).
  void AppendKeypoint(const ServerKeypoint& keypoint, const Descriptor& descriptor);
  // Keeps `descriptor` for keypoint i, which is losing its map point.
  void KeepOwnDescriptor(std::size_t i, const Descriptor& descriptor);
  std::map<GlobalKeyframeId, int> covisibility;  // weights, symmetric
  // Dense depth alignments its agent measured with earlier keyframes of its own (the global BA
  // weighs them as the agent's local BA does).
  struct DepthLink {
    GlobalKeyframeId other;
    Pose T_this_other;
    Eigen::Matrix<double, 6, 6> sqrt_information;
  };
  std::vector<DepthLink> depth_links;
  // The coded RGB-D as it arrived (colour JPEG and depth bitstream, a few kilobytes), until the
  // keyframe enters the dense map, whose stage decodes it; never kept without a dense map.
  std::shared_ptr<const RgbdPayload> rgbd;
  bool in_dense = false;

  // Keyframe culling (keyframe_culling.h). The keyframes culled because this one sees what
  // they saw; their poses follow this one's (CulledKeyframe). A keyframe the culling has
  // kept stays.
  std::vector<CulledKeyframe> followers;
  bool cull_checked = false;  // the culling has looked at it
  // A follower's pose in the map.
  Pose FollowerPose(const CulledKeyframe& f) const { return T_map_cam * f.T_leader_this(); }

  Eigen::Vector3d camera_center() const { return T_map_cam.translation(); }
};

struct LoopEdge {
  GlobalKeyframeId a, b;
  Pose T_a_b;  // measured
};

class ServerMap {
 public:
  explicit ServerMap(MapId id) : id_(id) {}
  MapId id() const { return id_; }

  ServerKeyframe* keyframe(const GlobalKeyframeId& id) const;
  ServerMapPoint* point(const GlobalMapPointId& id) const;  // follows merges
  const std::map<GlobalKeyframeId, std::unique_ptr<ServerKeyframe>>& keyframes() const {
    return keyframes_;
  }
  std::size_t num_points() const { return points_.size(); }
  // Ids of merged points that still resolve to a point (`point` follows them). An agent names
  // a point again only while it is in its local map, so an alias lives for
  // kMergeAliasKeyframes keyframes of its agent (and never after its point is gone): swept
  // each time the aliases have doubled since the last sweep.
  static constexpr std::uint32_t kMergeAliasKeyframes = 100;
  std::size_t num_merge_aliases() const { return merged_into_.size(); }
  // Bytes of the map points (objects, observations) and of the point index and merge aliases,
  // counting `hash_node` per hash table entry.
  std::size_t PointBytes(std::size_t hash_node) const;
  const std::vector<LoopEdge>& loop_edges() const { return loop_edges_; }
  const std::vector<AgentId>& agents() const { return agents_; }
  // The keyframe whose pose is held fixed in optimisation (the founding agent's first).
  std::optional<GlobalKeyframeId> origin() const { return origin_; }

  ServerKeyframe* AddKeyframe(std::unique_ptr<ServerKeyframe> keyframe);
  // The agent's newest keyframe id in this map, kept or culled (none: no keyframe yet).
  std::optional<KeyframeId> NewestKeyframeOf(AgentId agent) const;
  ServerMapPoint* AddPoint(std::unique_ptr<ServerMapPoint> point);
  void AddObservation(ServerMapPoint* point, ServerKeyframe* keyframe, int keypoint);
  // Fuses `from` into `into` (observations move over; ids of `from` resolve to `into`).
  void MergePoints(ServerMapPoint* from, ServerMapPoint* into);
  // A loop edge between two keyframes replaces the one they had (the newer measurement): an
  // agent passing a place again closes the same loop again, and the edges must not grow
  // with the passes.
  void AddLoopEdge(const LoopEdge& edge);
  void AddCovisibility(ServerKeyframe* a, ServerKeyframe* b, int weight);

  // Culls `kf`: its observations leave their points (a point anchored to it moves its anchor
  // to another observer; a point nobody else sees is removed), its covisibility links go, its
  // loop edges move to `follow` (composed with their relative pose), its coded RGB-D not yet in
  // the dense map goes if `follow` has RGB-D, and it leaves the map's keyframes: what remains
  // of it is a CulledKeyframe among `follow`'s followers, whose pose follows `follow`, a kept
  // keyframe of this map. `kf` is destroyed. Returns the number of points removed.
  std::size_t Cull(ServerKeyframe* kf, ServerKeyframe* follow);
  std::size_t num_culled() const { return culled_; }
  // The kept keyframe a culled keyframe follows (null if `id` is not a culled keyframe of
  // this map). Looks through every kept keyframe: for tests and tools.
  const ServerKeyframe* LeaderOf(const GlobalKeyframeId& id) const;

  // Every keyframe of the map, kept and culled (of one agent, with `agent`), with its pose in
  // the map and whether it is placed (a culled keyframe is placed as its leader is), in id
  // order: what the trajectories are written from.
  struct KeyframeSample {
    GlobalKeyframeId id;
    double timestamp = 0;
    Pose T_map_cam = Pose::Identity();
    bool placed = true;
  };
  std::vector<KeyframeSample> AllKeyframes(std::optional<AgentId> agent = std::nullopt) const;
  // How many of those are placed (AllKeyframes(agent) with `placed`), without their poses.
  std::size_t CountPlacedKeyframes(AgentId agent) const;

  // Moves every keyframe and point of `other` into this map, `other`'s poses premultiplied by
  // T_this_other. `other` is left empty.
  void Absorb(ServerMap* other, const Pose& T_this_other);

  // Keyframes of one agent in id order.
  std::vector<ServerKeyframe*> AgentKeyframes(AgentId agent) const;

  // Restarted segments (ServerKeyframe::restart) that no loop has placed against the rest of
  // the map yet. Their poses rest on the agent's guess, so they stay out of the world-frame
  // outputs (dense map, trajectories) and out of fusions until a loop inside the map joins
  // them, directly or through other such segments, to a placed keyframe.
  bool Placed(const ServerKeyframe& kf) const { return !UnplacedGroup(kf); }
  // The group of unplaced segments `kf` belongs to (none when it is placed): keyframes of
  // different groups, or of a group and the placed part, lie anywhere against each other.
  std::optional<GlobalKeyframeId> UnplacedGroup(const ServerKeyframe& kf) const {
    if (unplaced_.empty()) return std::nullopt;
    const auto it = unplaced_.find({kf.id.agent, kf.segment});
    return it == unplaced_.end() ? std::nullopt : std::optional<GlobalKeyframeId>(it->second);
  }
  // A new unplaced segment starting at `first`, in a group of its own or in `group`.
  void AddUnplacedSegment(const GlobalKeyframeId& first,
                          std::optional<GlobalKeyframeId> group = std::nullopt) {
    unplaced_[first] = group.value_or(first);
  }
  // Records that a loop links the segments of `a` and `b`: two unplaced ones become one
  // group; a placed and an unplaced one place the whole group, whose keyframes are returned.
  std::vector<ServerKeyframe*> LinkSegments(const ServerKeyframe& a, const ServerKeyframe& b);
  // Makes the segments of the placed keyframes among `keyframes` one unplaced group (a fusion
  // through an unplaced segment leaves the other map's placed part where its agent's guess put
  // it). Returns the keyframes that were placed.
  std::vector<ServerKeyframe*> UnplaceTogether(const std::vector<ServerKeyframe*>& keyframes);
  std::size_t num_unplaced_segments() const { return unplaced_.size(); }

 private:
  // Forgets merge aliases whose point is gone (removed with a culled keyframe) or that are
  // older than kMergeAliasKeyframes keyframes of their agent.
  void PruneMergeAliases();
  KeyframeId NewestKeyframe(AgentId agent) const;
  // The edge between a and b, either way round (end() if none).
  std::vector<LoopEdge>::iterator FindLoopEdge(const GlobalKeyframeId& a,
                                               const GlobalKeyframeId& b);

  struct MergeAlias {
    GlobalMapPointId into;
    KeyframeId agent_newest;  // the merged point's agent's newest keyframe at the merge
  };

  MapId id_;
  std::map<GlobalKeyframeId, std::unique_ptr<ServerKeyframe>> keyframes_;
  std::unordered_map<GlobalMapPointId, std::unique_ptr<ServerMapPoint>> points_;
  std::unordered_map<GlobalMapPointId, MergeAlias> merged_into_;
  std::map<AgentId, KeyframeId> newest_;  // each agent's newest keyframe in this map
  std::vector<LoopEdge> loop_edges_;
  std::vector<AgentId> agents_;
  std::optional<GlobalKeyframeId> origin_;
  // Unplaced segments by their first keyframe, each with its group's label (segments a loop
  // linked share one).
  std::map<GlobalKeyframeId, GlobalKeyframeId> unplaced_;
  std::size_t culled_ = 0;
  std::size_t prune_aliases_at_ = 1024;  // merge aliases that start the next sweep
};

}  // namespace ccmd
