#include "libccmd/dense/dense_map.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <utility>

#include "libccmd/dense/dense_map_detail.h"
#include "libccmd/dense/label.h"

namespace ccmd {

namespace {

using dense_detail::IdText;
using dense_detail::kSegmentShift;
using dense_detail::kSlotMask;

Status CheckPose(const Pose& pose) {
  if (!pose.matrix().allFinite()) return InvalidArgument("pose is not finite");
  const Eigen::Matrix3d r = pose.linear();
  const double error = (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (error > 1e-4 || r.determinant() < 0) {
    return InvalidArgument("pose is not rigid (rotation error " + std::to_string(error) + ")");
  }
  return Status::Ok();
}

}  // namespace

Status DenseMapOptions::Validate() const {
  if (!std::isfinite(voxel_size_m) || voxel_size_m < 0.001 || voxel_size_m > 10.0) {
    return InvalidArgument("voxel_size_m must be within [0.001, 10] metres");
  }
  if (window_keyframes < 0 || window_keyframes > 1000) {
    return InvalidArgument("window_keyframes must be within [0, 1000]");
  }
  if (release_below_points < 0) return InvalidArgument("release_below_points must be >= 0");
  return projection.Validate();
}

void DenseMapOptions::Describe(OptionsWriter* out) const {
  out->Add("voxel_size_m", voxel_size_m);
  out->Add("window_keyframes", window_keyframes);
  out->Add("compact_keyframes", compact_keyframes);
  out->Add("release_below_points", release_below_points);
  out->Nested("projection", projection);
}

std::string DenseMapOptions::ToString() const {
  std::ostringstream s;
  s << "voxel " << voxel_size_m << " m, window " << window_keyframes << " keyframes, depth "
    << projection.min_depth_m << ".." << projection.max_depth_m
    << " m, incidence <= " << projection.max_incidence_deg << " deg, "
    << (compact_keyframes ? "compact" : "full") << " keyframes out of the window";
  return s.str();
}

StatusOr<std::unique_ptr<DenseMap>> DenseMap::Create(const DenseMapOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  return std::unique_ptr<DenseMap>(new DenseMap(options));
}

DenseMap::DenseMap(const DenseMapOptions& options)
    : options_(options), grid_(options.voxel_size_m) {}

DenseMap::~DenseMap() = default;

// ---- tree navigation ----------------------------------------------------------------------

DenseMap::AgentNode* DenseMap::FindAgent(AgentId agent) {
  const auto m = agent_map_.find(agent);
  if (m == agent_map_.end()) return nullptr;
  return &maps_.at(m->second).agents.at(agent);
}

const DenseMap::AgentNode* DenseMap::FindAgent(AgentId agent) const {
  const auto m = agent_map_.find(agent);
  if (m == agent_map_.end()) return nullptr;
  return &maps_.at(m->second).agents.at(agent);
}

DenseMap::AgentNode& DenseMap::AgentOrCreate(AgentId agent) {
  const auto [it, inserted] = agent_map_.emplace(agent, MapId(agent.value()));
  return maps_[it->second].agents[agent];
}

DenseMap::MapNode& DenseMap::MapNodeOf(AgentId agent) { return maps_.at(agent_map_.at(agent)); }

DenseMap::Entry* DenseMap::Find(const AgentNode& agent, std::uint32_t id) {
  const auto it = agent.segments.find(id >> kSegmentShift);
  if (it == agent.segments.end()) return nullptr;
  return it->second.slots[id & kSlotMask].get();
}

DenseMap::Entry* DenseMap::Next(const AgentNode& agent, std::uint32_t id) {
  const std::uint32_t segment = id >> kSegmentShift;
  for (auto it = agent.segments.lower_bound(segment); it != agent.segments.end(); ++it) {
    const std::uint32_t first = it->first == segment ? (id & kSlotMask) + 1 : 0;
    for (std::uint32_t s = first; s < kSegmentKeyframes; ++s) {
      if (it->second.slots[s]) return it->second.slots[s].get();
    }
  }
  return nullptr;
}

DenseMap::Entry* DenseMap::Prev(const AgentNode& agent, std::uint32_t id) {
  const std::uint32_t segment = id >> kSegmentShift;
  for (auto it = agent.segments.upper_bound(segment); it != agent.segments.begin();) {
    --it;
    int s = it->first == segment ? static_cast<int>(id & kSlotMask) - 1 : kSegmentKeyframes - 1;
    for (; s >= 0; --s) {
      if (it->second.slots[s]) return it->second.slots[s].get();
    }
  }
  return nullptr;
}

std::uint32_t DenseMap::WindowStart(const AgentNode& agent, std::uint32_t id) const {
  for (int w = 0; w < options_.window_keyframes; ++w) {
    const Entry* p = Prev(agent, id);
    if (p == nullptr) break;
    id = p->id.keyframe.value();
  }
  return id;
}

// ---- insertion and removal -----------------------------------------------------------------

Status DenseMap::AddKeyframe(const DenseKeyframe& keyframe) {
  CCMD_ASSIGN_OR_RETURN(
      CameraCloud cloud,
      BackProjectKeyframe(keyframe.depth_mm, keyframe.bgr, keyframe.camera, options_.projection));
  return AddKeyframeCloud(keyframe.id, keyframe.T_world_cam, std::move(cloud));
}

Status DenseMap::AddKeyframeCloud(const GlobalKeyframeId& id, const Pose& T_world_cam,
                                  CameraCloud cloud) {
  CCMD_ASSIGN_OR_RETURN(const std::uint32_t label, EncodeLabel(id));
  CCMD_RETURN_IF_ERROR(CheckPose(T_world_cam).WithContext(IdText(id)));
  if (cloud.colors.size() != cloud.points.size()) {
    return InvalidArgument("camera cloud has " + std::to_string(cloud.points.size()) +
                           " points but " + std::to_string(cloud.colors.size()) + " colours");
  }
  if (cloud.points.size() > static_cast<std::size_t>(INT32_MAX)) {
    return OutOfRange("keyframe cloud too large");
  }
  auto entry = std::make_unique<Entry>();
  entry->id = id;
  entry->label = label;
  entry->T_world_cam = T_world_cam;
  entry->cloud = std::move(cloud);
  Transform(entry.get());  // outside the lock: depends on nothing shared

  std::lock_guard<std::mutex> lock(mutex_);
  return InsertLocked(std::move(entry));
}

Status DenseMap::InsertLocked(std::unique_ptr<Entry> entry) {
  const std::uint32_t id = entry->id.keyframe.value();
  AgentNode& node = AgentOrCreate(entry->id.agent);
  if (Find(node, id) != nullptr) {
    return InvalidArgument(IdText(entry->id) + " is already in the dense map");
  }
  Segment& segment = node.segments[id >> kSegmentShift];
  Entry* raw = entry.get();
  segment.slots[id & kSlotMask] = std::move(entry);
  ++segment.count;
  ++node.keyframes;
  const std::uint32_t window_start = WindowStart(node, id);
  if (Next(node, id) == nullptr) {
    FilterAppended(node, raw);
  } else {
    // Arrived out of order: its predecessors' windows changed shape, recompute them.
    RefilterRange(node, window_start, id);
  }
  // The keyframe W before it has left the window now (or, out of order, it itself).
  CompactSettled(raw->id.agent, window_start, id);
  return Status::Ok();
}

Status DenseMap::RemoveKeyframe(const GlobalKeyframeId& id) {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentNode* node = FindAgent(id.agent);
  const std::uint32_t k = id.keyframe.value();
  if (node == nullptr || Find(*node, k) == nullptr)
    return NotFound(IdText(id) + " is not in the dense map");
  FreeHeld(*Find(*node, k));
  RemoveLocked(node, k);
  return Status::Ok();
}

void DenseMap::FreeHeld(const Entry& entry) {
  MapNode& map = MapNodeOf(entry.id.agent);
  if (!entry.compact || map.rebuild_held) return;  // a rebuild marks the others anew
  entry.stored.Transform(entry.T_held, &decoded_);
  grid_.Indices(decoded_, &voxels_);
  for (const VoxelIndex& v : voxels_) map.held.Erase(v);
}

void DenseMap::RemoveLocked(AgentNode* node, std::uint32_t k) {
  const std::uint32_t start = WindowStart(*node, k);
  const Entry* prev = Prev(*node, k);
  const std::uint32_t prev_id = prev ? prev->id.keyframe.value() : 0;
  // A compacted predecessor's filter is final: only window keyframes need the re-filter.
  const bool refilter = prev != nullptr && !prev->compact;
  auto segment = node->segments.find(k >> kSegmentShift);
  pending_.erase(segment->second.slots[k & kSlotMask]->id);
  segment->second.slots[k & kSlotMask].reset();
  if (--segment->second.count == 0) node->segments.erase(segment);
  --node->keyframes;
  // Its predecessors compete with one keyframe further now.
  if (refilter) RefilterRange(*node, start, prev_id);
}

void DenseMap::Release(const std::vector<GlobalKeyframeId>& ids) {
  for (const GlobalKeyframeId& id : ids) {
    AgentNode* node = FindAgent(id.agent);
    Entry* entry = node ? Find(*node, id.keyframe.value()) : nullptr;
    if (entry == nullptr) continue;
    FreeHeld(*entry);
    released_points_ += entry->stored.size();
    RemoveLocked(node, id.keyframe.value());
    ++released_count_;
    if (released_.size() >= kMaxReleasedQueued) released_.pop_front();
    released_.push_back(id);
  }
}

std::vector<GlobalKeyframeId> DenseMap::TakeReleased() {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<GlobalKeyframeId> taken(released_.begin(), released_.end());
  released_.clear();
  return taken;
}

Status DenseMap::SetAgentMap(AgentId agent, MapId map) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = agent_map_.find(agent);
  if (it == agent_map_.end()) {
    agent_map_.emplace(agent, map);
    maps_[map].agents.emplace(agent, AgentNode{});
    return Status::Ok();
  }
  if (it->second == map) return Status::Ok();
  auto from = maps_.find(it->second);
  auto node = from->second.agents.extract(agent);
  // The agent's compacted keyframes hold voxels in the map it leaves and none in the other.
  from->second.rebuild_held = true;
  if (from->second.agents.empty()) maps_.erase(from);
  MapNode& to = maps_[map];
  to.agents.insert(std::move(node));
  to.rebuild_held = true;
  it->second = map;
  return Status::Ok();
}

// ---- pose updates --------------------------------------------------------------------------

Status DenseMap::UpdateKeyframePose(const GlobalKeyframeId& id, const Pose& T_world_cam) {
  CCMD_RETURN_IF_ERROR(CheckPose(T_world_cam).WithContext(IdText(id)));
  std::lock_guard<std::mutex> lock(mutex_);
  if (Entry* entry = UpdatedEntry(id)) SetPose(entry, T_world_cam);
  return Status::Ok();
}

DenseMap::Entry* DenseMap::UpdatedEntry(const GlobalKeyframeId& id) {
  const AgentNode* node = FindAgent(id.agent);
  Entry* entry = node ? Find(*node, id.keyframe.value()) : nullptr;
  absent_updates_ += entry == nullptr;
  return entry;
}

std::vector<DenseMap::Entry*> DenseMap::EntriesOf(const std::vector<KeyframePose>& poses) {
  std::vector<Entry*> entries;
  entries.reserve(poses.size());
  for (const KeyframePose& p : poses) entries.push_back(UpdatedEntry(p.id));
  return entries;
}

Status DenseMap::UpdateLoopPoses(const std::vector<KeyframePose>& poses) {
  for (const KeyframePose& p : poses) {
    CCMD_RETURN_IF_ERROR(CheckPose(p.T_world_cam).WithContext(IdText(p.id)));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  const std::vector<Entry*> entries = EntriesOf(poses);
  for (std::size_t i = 0; i < poses.size(); ++i) {
    if (!entries[i]) continue;
    SetPose(entries[i], poses[i].T_world_cam);
    // Compacted keyframes moved relative to each other: what they hold is redone.
    if (entries[i]->compact) MapNodeOf(poses[i].id.agent).rebuild_held = true;
  }
  MaintainLocked();
  return Status::Ok();
}

StatusOr<std::size_t> DenseMap::UpdateGlobalPoses(const std::vector<KeyframePose>& poses) {
  for (const KeyframePose& p : poses) {
    CCMD_RETURN_IF_ERROR(CheckPose(p.T_world_cam).WithContext(IdText(p.id)));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  const std::vector<Entry*> entries = EntriesOf(poses);
  std::size_t moved = 0;
  for (std::size_t i = 0; i < poses.size(); ++i) {
    if (!entries[i]) continue;
    const Eigen::Matrix<double, 3, 4> delta =
        (poses[i].T_world_cam.matrix() - entries[i]->T_world_cam.matrix()).topRows<3>();
    if (delta.cwiseAbs().maxCoeff() <= 1e-9) continue;
    SetPose(entries[i], poses[i].T_world_cam);
    if (entries[i]->compact) MapNodeOf(poses[i].id.agent).rebuild_held = true;
    ++moved;
  }
  MaintainLocked();
  return moved;
}

Status DenseMap::TransformAgent(AgentId agent, const Pose& T_new_old) {
  CCMD_RETURN_IF_ERROR(CheckPose(T_new_old).WithContext("agent transform"));
  std::lock_guard<std::mutex> lock(mutex_);
  AgentNode* node = FindAgent(agent);
  if (node == nullptr)
    return NotFound("agent " + std::to_string(agent.value()) + " has no dense map");
  for (auto& [index, segment] : node->segments) {
    for (auto& entry : segment.slots) {
      if (entry)
        SetPose(entry.get(),
                T_new_old * entry->T_world_cam);  // the voxel grid does not move with the points
    }
  }
  MapNodeOf(agent).rebuild_held = true;
  return Status::Ok();
}

Status DenseMap::MergeMaps(MapId source, MapId target, const Pose& T_target_source) {
  if (source == target) return InvalidArgument("cannot merge a map into itself");
  CCMD_RETURN_IF_ERROR(CheckPose(T_target_source).WithContext("map fusion transform"));
  std::lock_guard<std::mutex> lock(mutex_);
  auto from = maps_.find(source);
  if (from == maps_.end())
    return NotFound("map " + std::to_string(source.value()) + " has no dense map");
  MapNode moved = std::move(from->second);
  maps_.erase(from);
  MapNode& into = maps_[target];
  for (auto& [agent, node] : moved.agents) {
    for (auto& [index, segment] : node.segments) {
      for (auto& entry : segment.slots) {
        if (entry) SetPose(entry.get(), T_target_source * entry->T_world_cam);
      }
    }
    agent_map_[agent] = target;
    into.agents.emplace(agent, std::move(node));
  }
  into.rebuild_held = true;  // the source's compacted keyframes hold nothing in the target yet
  return Status::Ok();
}

}  // namespace ccmd
