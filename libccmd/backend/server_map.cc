#include "libccmd/backend/server_map.h"

#include <algorithm>
#include <set>

#include "libccmd/util/logging.h"

namespace ccmd {

namespace {

const Descriptor kNoDescriptor{};

}  // namespace

const Descriptor& ServerKeyframe::descriptor(std::size_t i) const {
  if (points[i]) return points[i]->descriptor;
  const auto it =
      std::lower_bound(own_descriptors.begin(), own_descriptors.end(), i,
                       [](const auto& entry, std::size_t k) { return entry.first < k; });
  return it != own_descriptors.end() && it->first == i ? it->second : kNoDescriptor;
}

std::vector<Descriptor> ServerKeyframe::Descriptors() const {
  std::vector<Descriptor> all(keypoints.size());
  for (std::size_t i = 0; i < all.size(); ++i) all[i] = descriptor(i);
  return all;
}

void ServerKeyframe::AppendKeypoint(const ServerKeypoint& keypoint, const Descriptor& d) {
  own_descriptors.emplace_back(static_cast<std::uint32_t>(keypoints.size()), d);
  keypoints.push_back(keypoint);
  points.push_back(nullptr);
}

void ServerKeyframe::KeepOwnDescriptor(std::size_t i, const Descriptor& d) {
  const auto it =
      std::lower_bound(own_descriptors.begin(), own_descriptors.end(), i,
                       [](const auto& entry, std::size_t k) { return entry.first < k; });
  if (it != own_descriptors.end() && it->first == i) {
    it->second = d;
  } else {
    own_descriptors.insert(it, {static_cast<std::uint32_t>(i), d});
  }
}

Pose CulledKeyframe::T_leader_this() const {
  Pose T = Pose::Identity();
  T.linear() =
      Eigen::Quaterniond(q_leader_this[3], q_leader_this[0], q_leader_this[1], q_leader_this[2])
          .normalized()
          .toRotationMatrix();
  T.translation() = Eigen::Vector3d(t_leader_this[0], t_leader_this[1], t_leader_this[2]);
  return T;
}

void CulledKeyframe::SetT_leader_this(const Pose& T) {
  const Eigen::Quaterniond q(T.linear());
  q_leader_this = {static_cast<float>(q.x()), static_cast<float>(q.y()), static_cast<float>(q.z()),
                   static_cast<float>(q.w())};
  t_leader_this = {static_cast<float>(T.translation().x()), static_cast<float>(T.translation().y()),
                   static_cast<float>(T.translation().z())};
}

Eigen::Vector3d ServerMapPoint::World() const { return anchor->T_map_cam * p_anchor; }

void ServerMapPoint::SetWorld(const Eigen::Vector3d& p_world) {
  p_anchor = anchor->T_map_cam.inverse() * p_world;
}

ServerKeyframe* ServerMap::keyframe(const GlobalKeyframeId& id) const {
  const auto it = keyframes_.find(id);
  return it == keyframes_.end() ? nullptr : it->second.get();
}

ServerMapPoint* ServerMap::point(const GlobalMapPointId& id) const {
  GlobalMapPointId current = id;
  for (int hops = 0; hops < 64; ++hops) {
    const auto it = points_.find(current);
    if (it != points_.end()) return it->second.get();
    const auto alias = merged_into_.find(current);
    if (alias == merged_into_.end()) return nullptr;
    current = alias->second.into;
  }
  return nullptr;
}

std::size_t ServerMap::PointBytes(std::size_t hash_node) const {
  std::size_t bytes =
      (points_.size() + merged_into_.size()) * hash_node +
      points_.size() * (sizeof(GlobalMapPointId) + sizeof(std::unique_ptr<ServerMapPoint>)) +
      merged_into_.size() * (sizeof(GlobalMapPointId) + sizeof(MergeAlias));
  for (const auto& [id, p] : points_) {
    bytes +=
        sizeof(ServerMapPoint) + p->observations.capacity() * sizeof(ServerMapPoint::Observation);
  }
  return bytes;
}

ServerKeyframe* ServerMap::AddKeyframe(std::unique_ptr<ServerKeyframe> keyframe) {
  ServerKeyframe* raw = keyframe.get();
  if (!origin_) origin_ = raw->id;
  if (std::find(agents_.begin(), agents_.end(), raw->id.agent) == agents_.end())
    agents_.push_back(raw->id.agent);
  KeyframeId& newest = newest_[raw->id.agent];
  newest = std::max(newest, raw->id.keyframe);
  keyframes_[raw->id] = std::move(keyframe);
  return raw;
}

ServerMapPoint* ServerMap::AddPoint(std::unique_ptr<ServerMapPoint> point) {
  ServerMapPoint* raw = point.get();
  points_[raw->id] = std::move(point);
  return raw;
}

void ServerMap::AddObservation(ServerMapPoint* point, ServerKeyframe* keyframe, int keypoint) {
  CCMD_CHECK(keypoint >= 0 && keypoint < static_cast<int>(keyframe->points.size()));
  for (const auto& o : point->observations) {
    if (o.keyframe == keyframe) return;  // one observation per keyframe
  }
  keyframe->points[keypoint] = point;
  point->observations.push_back({keyframe, keypoint});
}

void ServerMap::MergePoints(ServerMapPoint* from, ServerMapPoint* into) {
  if (from == into) return;
  for (const auto& o : from->observations) {
    const bool seen = std::any_of(into->observations.begin(), into->observations.end(),
                                  [&](const auto& x) { return x.keyframe == o.keyframe; });
    if (seen) {
      o.keyframe->KeepOwnDescriptor(o.keypoint, from->descriptor);
      o.keyframe->points[o.keypoint] = nullptr;
    } else {
      o.keyframe->points[o.keypoint] = into;
      into->observations.push_back(o);
    }
  }
  const GlobalMapPointId id = from->id;
  merged_into_[id] = {into->id, NewestKeyframe(id.agent)};
  points_.erase(id);
  if (merged_into_.size() > prune_aliases_at_) PruneMergeAliases();
}

KeyframeId ServerMap::NewestKeyframe(AgentId agent) const {
  return NewestKeyframeOf(agent).value_or(KeyframeId(0));
}

std::optional<KeyframeId> ServerMap::NewestKeyframeOf(AgentId agent) const {
  const auto it = newest_.find(agent);
  if (it == newest_.end()) return std::nullopt;
  return it->second;
}

std::vector<LoopEdge>::iterator ServerMap::FindLoopEdge(const GlobalKeyframeId& a,
                                                        const GlobalKeyframeId& b) {
  return std::find_if(loop_edges_.begin(), loop_edges_.end(), [&](const LoopEdge& e) {
    return (e.a == a && e.b == b) || (e.a == b && e.b == a);
  });
}

void ServerMap::AddLoopEdge(const LoopEdge& edge) {
  const auto known = FindLoopEdge(edge.a, edge.b);
  if (known == loop_edges_.end()) {
    loop_edges_.push_back(edge);
  } else {
    *known = known->a == edge.a ? edge : LoopEdge{edge.b, edge.a, edge.T_a_b.inverse()};
  }
}

std::size_t ServerMap::Cull(ServerKeyframe* kf, ServerKeyframe* follow) {
  CCMD_CHECK(kf != follow && keyframe(kf->id) == kf && keyframe(follow->id) == follow &&
             kf->followers.empty());
  std::size_t removed = 0;
  for (ServerMapPoint* p : kf->points) {
    if (!p) continue;
    auto& observations = p->observations;
    observations.erase(std::remove_if(observations.begin(), observations.end(),
                                      [&](const auto& o) { return o.keyframe == kf; }),
                       observations.end());
    if (observations.empty()) {
      points_.erase(p->id);
      ++removed;
    } else if (p->anchor == kf) {
      const Eigen::Vector3d p_map = p->World();
      p->anchor = observations.front().keyframe;
      p->SetWorld(p_map);
    }
  }
  for (const auto& [other, weight] : kf->covisibility) {
    if (ServerKeyframe* o = keyframe(other)) o->covisibility.erase(kf->id);
  }
  const Pose T_follow_kf = follow->T_map_cam.inverse() * kf->T_map_cam;
  std::vector<LoopEdge> moved;
  for (auto it = loop_edges_.begin(); it != loop_edges_.end();) {
    if (it->a != kf->id && it->b != kf->id) {
      ++it;
      continue;
    }
    LoopEdge edge = *it;
    it = loop_edges_.erase(it);
    if (edge.a == kf->id) {
      edge.a = follow->id;
      edge.T_a_b = T_follow_kf * edge.T_a_b;
    }
    if (edge.b == kf->id) {
      edge.b = follow->id;
      edge.T_a_b = edge.T_a_b * T_follow_kf.inverse();
    }
    if (edge.a != edge.b) moved.push_back(edge);
  }
  // One edge per pair: the pair's own measurement stays, the composed one is dropped.
  for (const LoopEdge& edge : moved) {
    if (FindLoopEdge(edge.a, edge.b) == loop_edges_.end()) loop_edges_.push_back(edge);
  }
  CulledKeyframe record;
  record.id = kf->id;
  record.timestamp = kf->timestamp;
  record.SetT_leader_this(T_follow_kf);
  record.in_dense = kf->in_dense;
  // Coded RGB-D still waiting for its map to join the primary map goes when the leader has
  // its own: the leader's view covers this one, and a map that never fuses must not hold
  // every culled keyframe's images.
  if (kf->rgbd && !(follow->rgbd || follow->in_dense)) record.rgbd = std::move(kf->rgbd);
  follow->followers.push_back(std::move(record));
  keyframes_.erase(kf->id);
  ++culled_;
  return removed;
}

const ServerKeyframe* ServerMap::LeaderOf(const GlobalKeyframeId& id) const {
  for (const auto& [kid, kf] : keyframes_) {
    for (const CulledKeyframe& f : kf->followers) {
      if (f.id == id) return kf.get();
    }
  }
  return nullptr;
}

std::size_t ServerMap::CountPlacedKeyframes(AgentId agent) const {
  std::size_t count = 0;
  for (const auto& [id, kf] : keyframes_) {
    if (!Placed(*kf)) continue;
    count += id.agent == agent;
    for (const CulledKeyframe& f : kf->followers) count += f.id.agent == agent;
  }
  return count;
}

std::vector<ServerMap::KeyframeSample> ServerMap::AllKeyframes(std::optional<AgentId> agent) const {
  std::vector<KeyframeSample> samples;
  for (const auto& [id, kf] : keyframes_) {
    const bool placed = Placed(*kf);
    if (!agent || id.agent == *agent) samples.push_back({id, kf->timestamp, kf->T_map_cam, placed});
    for (const CulledKeyframe& f : kf->followers) {
      if (!agent || f.id.agent == *agent)
        samples.push_back({f.id, f.timestamp, kf->FollowerPose(f), placed});
    }
  }
  std::sort(samples.begin(), samples.end(),
            [](const KeyframeSample& a, const KeyframeSample& b) { return a.id < b.id; });
  return samples;
}

void ServerMap::PruneMergeAliases() {
  for (auto it = merged_into_.begin(); it != merged_into_.end();) {
    const std::uint32_t age =
        NewestKeyframe(it->first.agent).value() - it->second.agent_newest.value();
    it = age <= kMergeAliasKeyframes && point(it->first) ? std::next(it) : merged_into_.erase(it);
  }
  prune_aliases_at_ = 2 * merged_into_.size() + 1024;
}

void ServerMap::AddCovisibility(ServerKeyframe* a, ServerKeyframe* b, int weight) {
  if (a == b) return;
  a->covisibility[b->id] = std::max(a->covisibility[b->id], weight);
  b->covisibility[a->id] = std::max(b->covisibility[a->id], weight);
}

void ServerMap::Absorb(ServerMap* other, const Pose& T_this_other) {
  if (!origin_) origin_ = other->origin_;  // the first map absorbed gives the gauge
  for (auto& [id, kf] : other->keyframes_) {
    kf->T_map_cam = T_this_other * kf->T_map_cam;
    keyframes_[id] = std::move(kf);
  }
  for (auto& [id, p] : other->points_) points_[id] = std::move(p);
  for (const auto& [from, to] : other->merged_into_) merged_into_[from] = to;
  culled_ += other->culled_;
  for (const auto& [agent, newest] : other->newest_) {
    KeyframeId& mine = newest_[agent];
    mine = std::max(mine, newest);
  }
  other->newest_.clear();
  other->culled_ = 0;
  for (const LoopEdge& edge : other->loop_edges_) AddLoopEdge(edge);
  unplaced_.merge(other->unplaced_);
  other->unplaced_.clear();
  for (AgentId a : other->agents_) {
    if (std::find(agents_.begin(), agents_.end(), a) == agents_.end()) agents_.push_back(a);
  }
  other->keyframes_.clear();
  other->points_.clear();
  other->merged_into_.clear();
  other->loop_edges_.clear();
  other->agents_.clear();
}

std::vector<ServerKeyframe*> ServerMap::LinkSegments(const ServerKeyframe& a,
                                                     const ServerKeyframe& b) {
  std::vector<ServerKeyframe*> placed;
  const auto ia = unplaced_.find({a.id.agent, a.segment}),
             ib = unplaced_.find({b.id.agent, b.segment});
  if (ia == unplaced_.end() && ib == unplaced_.end()) return placed;
  if (ia != unplaced_.end() && ib != unplaced_.end()) {
    const GlobalKeyframeId from = ib->second, to = ia->second;
    for (auto& [segment, group] : unplaced_) {
      if (group == from) group = to;
    }
    return placed;
  }
  const GlobalKeyframeId group = (ia != unplaced_.end() ? ia : ib)->second;
  std::set<GlobalKeyframeId> segments;
  for (auto it = unplaced_.begin(); it != unplaced_.end();) {
    if (it->second == group) {
      segments.insert(it->first);
      it = unplaced_.erase(it);
    } else {
      ++it;
    }
  }
  for (const auto& [id, kf] : keyframes_) {
    if (segments.count({id.agent, kf->segment})) placed.push_back(kf.get());
  }
  return placed;
}

std::vector<ServerKeyframe*> ServerMap::UnplaceTogether(
    const std::vector<ServerKeyframe*>& keyframes) {
  std::vector<ServerKeyframe*> placed;
  std::set<GlobalKeyframeId> segments;
  for (ServerKeyframe* kf : keyframes) {
    if (!Placed(*kf)) continue;
    placed.push_back(kf);
    segments.insert({kf->id.agent, kf->segment});
  }
  // The label is one of the group's own segments: no other group can have it.
  for (const GlobalKeyframeId& segment : segments) AddUnplacedSegment(segment, *segments.begin());
  return placed;
}

std::vector<ServerKeyframe*> ServerMap::AgentKeyframes(AgentId agent) const {
  std::vector<ServerKeyframe*> result;
  for (const auto& [id, kf] : keyframes_) {
    if (id.agent == agent) result.push_back(kf.get());
  }
  return result;
}

}  // namespace ccmd
