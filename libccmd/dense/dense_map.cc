#include "libccmd/dense/dense_map.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <utility>

#include "libccmd/dense/label.h"

namespace ccmd {

namespace {

constexpr int kSegmentShift = 6;
static_assert((1 << kSegmentShift) == kSegmentKeyframes);
constexpr std::uint32_t kSlotMask = kSegmentKeyframes - 1;

// Long re-filters (a loop over a whole agent, a fusion) run in chunks of this many keyframes,
// each with its own W successors as context, so the scratch bricks stay small. Ranks within
// a chunk, plus one, must fit the bricks' uint16 values: 32 + W (<= 1000) + 1 does.
constexpr std::size_t kRefilterChunk = 32;

// Bytes a std::map / std::set node costs beyond its value: three pointers and a colour, plus
// the allocator's header.
constexpr std::size_t kTreeNodeOverhead = 48;

Status CheckPose(const Pose& pose) {
  if (!pose.matrix().allFinite()) return InvalidArgument("pose is not finite");
  const Eigen::Matrix3d r = pose.linear();
  const double error = (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (error > 1e-4 || r.determinant() < 0) {
    return InvalidArgument("pose is not rigid (rotation error " + std::to_string(error) + ")");
  }
  return Status::Ok();
}

std::string IdText(const GlobalKeyframeId& id) {
  return "keyframe (agent " + std::to_string(id.agent.value()) + ", keyframe " +
         std::to_string(id.keyframe.value()) + ")";
}

}  // namespace

Status DenseMapOptions::Validate() const {
  if (!std::isfinite(voxel_size_m) || voxel_size_m < 0.001 || voxel_size_m > 10.0) {
    return InvalidArgument("voxel_size_m must be within [0.001, 10] metres");
  }
  if (window_keyframes < 0 || window_keyframes > 1000) {
    return InvalidArgument("window_keyframes must be within [0, 1000]");
  }
  return projection.Validate();
}

std::string DenseMapOptions::ToString() const {
  std::ostringstream s;
  s << "voxel " << voxel_size_m << " m, window " << window_keyframes << " keyframes, depth "
    << projection.min_depth_m << ".." << projection.max_depth_m
    << " m, incidence <= " << projection.max_incidence_deg << " deg";
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
  return &maps_.at(m->second).at(agent);
}

const DenseMap::AgentNode* DenseMap::FindAgent(AgentId agent) const {
  const auto m = agent_map_.find(agent);
  if (m == agent_map_.end()) return nullptr;
  return &maps_.at(m->second).at(agent);
}

DenseMap::AgentNode& DenseMap::AgentOrCreate(AgentId agent) {
  const auto [it, inserted] = agent_map_.emplace(agent, MapId(agent.value()));
  return maps_[it->second][agent];
}

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

// ---- filtering -----------------------------------------------------------------------------

void DenseMap::Transform(Entry* entry) const {
  const Eigen::Matrix3f r = entry->T_world_cam.linear().cast<float>();
  const Eigen::Vector3f t = entry->T_world_cam.translation().cast<float>();
  const auto& cam = entry->cloud.points;
  entry->world.resize(cam.size());
  for (std::size_t i = 0; i < cam.size(); ++i) entry->world[i] = r * cam[i] + t;
}

// The loops below avoid data-dependent branches (whether a point is the first in its voxel is
// as good as random to a branch predictor): kept lists are built by writing every index and
// advancing the end by 0 or 1.
void DenseMap::FilterAppended(const AgentNode& agent, Entry* entry) {
  // The entry's own filter: the first point in each voxel (nothing follows it yet).
  const std::size_t n = entry->world.size();
  grid_.Indices(entry->world, &voxels_);
  occupied_.Clear();
  indices_.resize(n);
  std::size_t kept = 0;
  for (std::size_t i = 0; i < n; ++i) {
    indices_[kept] = static_cast<std::uint32_t>(i);
    kept += occupied_.Insert(voxels_[i]);
  }
  entry->kept.assign(indices_.begin(), indices_.begin() + kept);
  // The entry now occupies these voxels: its W predecessors lose their points there.
  std::uint32_t id = entry->id.keyframe.value();
  for (int w = 0; w < options_.window_keyframes; ++w) {
    Entry* p = Prev(agent, id);
    if (p == nullptr) break;
    id = p->id.keyframe.value();
    if (p->kept.empty()) continue;
    grid_.Indices(p->world, &voxels_);
    std::size_t still = 0;
    for (const std::uint32_t i : p->kept) {
      p->kept[still] = i;
      still += !occupied_.Contains(voxels_[i]);
    }
    p->kept.resize(still);
    // Leaving the window of appends: no further pass will shrink it.
    if (w + 1 == options_.window_keyframes) p->kept.shrink_to_fit();
  }
}

std::size_t DenseMap::RefilterRange(const AgentNode& agent, std::uint32_t first,
                                    std::uint32_t last) {
  std::vector<Entry*> list;
  Entry* e = Find(agent, first);
  if (e == nullptr) e = Next(agent, first);
  while (e != nullptr && e->id.keyframe.value() <= last) {
    list.push_back(e);
    e = Next(agent, e->id.keyframe.value());
  }
  const std::size_t recompute = list.size();
  for (int w = 0; w < options_.window_keyframes && e != nullptr; ++w) {
    list.push_back(e);
    e = Next(agent, e->id.keyframe.value());
  }
  const auto window = static_cast<std::size_t>(options_.window_keyframes);

  for (std::size_t begin = 0; begin < recompute; begin += kRefilterChunk) {
    const std::size_t end = std::min(recompute, begin + kRefilterChunk);
    const std::size_t context_end = std::min(list.size(), end + window);
    // From the last keyframe backwards: when keyframe r is visited, each voxel holds
    // 1 + the rank (within the chunk) of the nearest following keyframe with a point there.
    nearest_.Clear();
    for (std::size_t r = context_end; r-- > begin;) {
      Entry* x = list[r];
      const bool redo = r < end;
      const auto mark = static_cast<std::uint16_t>(r - begin + 1);
      // A voxel marked by a keyframe beyond `limit` is outside the window; one marked `mark`
      // already has a point of x, so this one is not the first.
      const std::size_t limit = r - begin + 1 + window;
      grid_.Indices(x->world, &voxels_);
      const std::size_t n = x->world.size();
      if (redo) {
        indices_.resize(n);
        std::size_t kept = 0;
        for (std::size_t i = 0; i < n; ++i) {
          std::uint16_t& nearest = nearest_.At(voxels_[i]);
          indices_[kept] = static_cast<std::uint32_t>(i);
          kept += (nearest == 0) | (nearest > limit);
          nearest = mark;
        }
        x->kept.assign(indices_.begin(), indices_.begin() + kept);
        x->kept.shrink_to_fit();
      } else {
        for (std::size_t i = 0; i < n; ++i) nearest_.At(voxels_[i]) = mark;
      }
    }
  }
  return recompute;
}

void DenseMap::MarkPending(const Entry& entry) { pending_.insert(entry.id); }

std::size_t DenseMap::MaintainLocked() {
  std::size_t refiltered = 0;
  auto it = pending_.begin();
  while (it != pending_.end()) {
    const AgentId agent = it->agent;
    std::vector<std::uint32_t> ids;
    for (; it != pending_.end() && it->agent == agent; ++it) ids.push_back(it->keyframe.value());
    const AgentNode* node = FindAgent(agent);
    if (node == nullptr) continue;
    // Keyframe k's move changes the filter of [WindowStart(k), k]; overlapping intervals
    // (ids are sorted) are merged into one run.
    bool open = false;
    std::uint32_t run_first = 0, run_last = 0;
    const auto flush = [&] {
      if (!open) return;
      refiltered += RefilterRange(*node, run_first, run_last);
      open = false;
    };
    for (const std::uint32_t k : ids) {
      if (Find(*node, k) == nullptr) continue;  // removed since
      const std::uint32_t start = WindowStart(*node, k);
      if (open && start <= run_last) {
        run_last = k;
        continue;
      }
      flush();
      open = true;
      run_first = start;
      run_last = k;
    }
    flush();
  }
  pending_.clear();
  return refiltered;
}

std::size_t DenseMap::Maintain() {
  std::lock_guard<std::mutex> lock(mutex_);
  return MaintainLocked();
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
  if (Next(node, id) == nullptr) {
    FilterAppended(node, raw);
  } else {
    // Arrived out of order: its predecessors' windows changed shape, recompute them.
    RefilterRange(node, WindowStart(node, id), id);
  }
  return Status::Ok();
}

Status DenseMap::RemoveKeyframe(const GlobalKeyframeId& id) {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentNode* node = FindAgent(id.agent);
  const std::uint32_t k = id.keyframe.value();
  if (node == nullptr || Find(*node, k) == nullptr)
    return NotFound(IdText(id) + " is not in the dense map");
  const std::uint32_t start = WindowStart(*node, k);
  const Entry* prev = Prev(*node, k);
  const std::uint32_t prev_id = prev ? prev->id.keyframe.value() : 0;
  auto segment = node->segments.find(k >> kSegmentShift);
  segment->second.slots[k & kSlotMask].reset();
  if (--segment->second.count == 0) node->segments.erase(segment);
  --node->keyframes;
  pending_.erase(id);
  // Its predecessors compete with one keyframe further now.
  if (prev != nullptr) RefilterRange(*node, start, prev_id);
  return Status::Ok();
}

Status DenseMap::SetAgentMap(AgentId agent, MapId map) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = agent_map_.find(agent);
  if (it == agent_map_.end()) {
    agent_map_.emplace(agent, map);
    maps_[map].emplace(agent, AgentNode{});
    return Status::Ok();
  }
  if (it->second == map) return Status::Ok();
  auto from = maps_.find(it->second);
  auto node = from->second.extract(agent);
  if (from->second.empty()) maps_.erase(from);
  maps_[map].insert(std::move(node));
  it->second = map;
  return Status::Ok();
}

// ---- pose updates --------------------------------------------------------------------------

Status DenseMap::UpdateKeyframePose(const GlobalKeyframeId& id, const Pose& T_world_cam) {
  CCMD_RETURN_IF_ERROR(CheckPose(T_world_cam).WithContext(IdText(id)));
  std::lock_guard<std::mutex> lock(mutex_);
  const AgentNode* node = FindAgent(id.agent);
  Entry* entry = node ? Find(*node, id.keyframe.value()) : nullptr;
  if (entry == nullptr) return NotFound(IdText(id) + " is not in the dense map");
  entry->T_world_cam = T_world_cam;
  Transform(entry);
  MarkPending(*entry);
  return Status::Ok();
}

StatusOr<std::vector<DenseMap::Entry*>> DenseMap::EntriesOf(const std::vector<KeyframePose>& poses) const {
  std::vector<Entry*> entries;
  entries.reserve(poses.size());
  for (const KeyframePose& p : poses) {
    const AgentNode* node = FindAgent(p.id.agent);
    Entry* entry = node ? Find(*node, p.id.keyframe.value()) : nullptr;
    if (entry == nullptr) return NotFound(IdText(p.id) + " is not in the dense map");
    entries.push_back(entry);
  }
  return entries;
}

Status DenseMap::UpdateLoopPoses(const std::vector<KeyframePose>& poses) {
  for (const KeyframePose& p : poses) {
    CCMD_RETURN_IF_ERROR(CheckPose(p.T_world_cam).WithContext(IdText(p.id)));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  CCMD_ASSIGN_OR_RETURN(const std::vector<Entry*> entries, EntriesOf(poses));
  for (std::size_t i = 0; i < poses.size(); ++i) {
    entries[i]->T_world_cam = poses[i].T_world_cam;
    Transform(entries[i]);
    MarkPending(*entries[i]);
  }
  MaintainLocked();
  return Status::Ok();
}

StatusOr<std::size_t> DenseMap::UpdateGlobalPoses(const std::vector<KeyframePose>& poses) {
  for (const KeyframePose& p : poses) {
    CCMD_RETURN_IF_ERROR(CheckPose(p.T_world_cam).WithContext(IdText(p.id)));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  CCMD_ASSIGN_OR_RETURN(const std::vector<Entry*> entries, EntriesOf(poses));
  std::size_t moved = 0;
  for (std::size_t i = 0; i < poses.size(); ++i) {
    const Eigen::Matrix<double, 3, 4> delta =
        (poses[i].T_world_cam.matrix() - entries[i]->T_world_cam.matrix()).topRows<3>();
    if (delta.cwiseAbs().maxCoeff() <= 1e-9) continue;
    entries[i]->T_world_cam = poses[i].T_world_cam;
    Transform(entries[i]);
    MarkPending(*entries[i]);
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
      if (!entry) continue;
      entry->T_world_cam = T_new_old * entry->T_world_cam;
      Transform(entry.get());
      MarkPending(*entry);  // the voxel grid does not move with the points
    }
  }
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
  for (auto& [agent, node] : moved) {
    for (auto& [index, segment] : node.segments) {
      for (auto& entry : segment.slots) {
        if (!entry) continue;
        entry->T_world_cam = T_target_source * entry->T_world_cam;
        Transform(entry.get());
        MarkPending(*entry);
      }
    }
    agent_map_[agent] = target;
    into.emplace(agent, std::move(node));
  }
  return Status::Ok();
}

// ---- reading -------------------------------------------------------------------------------

void DenseMap::AppendPoints(const Entry& entry, DenseFilter filter, PointCloud* cloud) const {
  if (filter == DenseFilter::kNone) {
    cloud->points.insert(cloud->points.end(), entry.world.begin(), entry.world.end());
    cloud->colors.insert(cloud->colors.end(), entry.cloud.colors.begin(), entry.cloud.colors.end());
    cloud->labels.resize(cloud->labels.size() + entry.world.size(), entry.label);
    return;
  }
  for (const std::uint32_t i : entry.kept) {
    cloud->points.push_back(entry.world[i]);
    cloud->colors.push_back(entry.cloud.colors[i]);
  }
  cloud->labels.resize(cloud->labels.size() + entry.kept.size(), entry.label);
}

StatusOr<PointCloud> DenseMap::Extract(const DenseSelection& selection, DenseFilter filter) {
  PointCloud cloud;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    MaintainLocked();
    std::vector<const AgentNode*> agents;
    switch (selection.kind) {
      case DenseSelection::Kind::kGlobal:
        for (const auto& [map, node] : maps_) {
          for (const auto& [agent, agent_node] : node) agents.push_back(&agent_node);
        }
        break;
      case DenseSelection::Kind::kMap: {
        const auto it = maps_.find(selection.map);
        if (it == maps_.end()) {
          return NotFound("map " + std::to_string(selection.map.value()) + " has no dense map");
        }
        for (const auto& [agent, agent_node] : it->second) agents.push_back(&agent_node);
        break;
      }
      case DenseSelection::Kind::kAgent: {
        const AgentNode* node = FindAgent(selection.agent);
        if (node == nullptr) {
          return NotFound("agent " + std::to_string(selection.agent.value()) + " has no dense map");
        }
        agents.push_back(node);
        break;
      }
    }
    std::size_t count = 0;
    for (const AgentNode* node : agents) {
      for (const auto& [index, segment] : node->segments) {
        for (const auto& entry : segment.slots) {
          if (entry)
            count += filter == DenseFilter::kNone ? entry->world.size() : entry->kept.size();
        }
      }
    }
    cloud.points.reserve(count);
    cloud.colors.reserve(count);
    cloud.labels.reserve(count);
    for (const AgentNode* node : agents) {
      for (const auto& [index, segment] : node->segments) {
        for (const auto& entry : segment.slots) {
          if (entry) AppendPoints(*entry, filter, &cloud);
        }
      }
    }
  }
  if (filter == DenseFilter::kGlobal) VoxelFilterLargestLabel(&cloud, options_.voxel_size_m);
  return cloud;
}

Status DenseMap::ExportPly(const std::string& path, const DenseSelection& selection,
                           DenseFilter filter) {
  CCMD_ASSIGN_OR_RETURN(const PointCloud cloud, Extract(selection, filter));
  return WritePly(cloud, path);
}

StatusOr<PointCloud> DenseMap::ExtractKeyframe(const GlobalKeyframeId& id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const AgentNode* node = FindAgent(id.agent);
  const Entry* entry = node ? Find(*node, id.keyframe.value()) : nullptr;
  if (entry == nullptr) return NotFound(IdText(id) + " is not in the dense map");
  PointCloud cloud;
  cloud.points.reserve(entry->world.size());
  cloud.colors.reserve(entry->world.size());
  cloud.labels.reserve(entry->world.size());
  AppendPoints(*entry, DenseFilter::kNone, &cloud);
  return cloud;
}

StatusOr<CameraCloud> DenseMap::KeyframeCloud(const GlobalKeyframeId& id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const AgentNode* node = FindAgent(id.agent);
  const Entry* entry = node ? Find(*node, id.keyframe.value()) : nullptr;
  if (entry == nullptr) return NotFound(IdText(id) + " is not in the dense map");
  return entry->cloud;
}

StatusOr<GlobalKeyframeId> DenseMap::FindLabel(std::uint32_t label) const {
  const GlobalKeyframeId id = DecodeLabel(label);
  std::lock_guard<std::mutex> lock(mutex_);
  const AgentNode* node = FindAgent(id.agent);
  if (node == nullptr || Find(*node, id.keyframe.value()) == nullptr) {
    return NotFound("label " + std::to_string(label) + " names no stored keyframe");
  }
  return id;
}

StatusOr<Pose> DenseMap::KeyframePoseOf(const GlobalKeyframeId& id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const AgentNode* node = FindAgent(id.agent);
  const Entry* entry = node ? Find(*node, id.keyframe.value()) : nullptr;
  if (entry == nullptr) return NotFound(IdText(id) + " is not in the dense map");
  return entry->T_world_cam;
}

std::vector<MapId> DenseMap::Maps() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<MapId> maps;
  for (const auto& [map, node] : maps_) maps.push_back(map);
  return maps;
}

std::vector<AgentId> DenseMap::Agents() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<AgentId> agents;
  for (const auto& [agent, map] : agent_map_) agents.push_back(agent);
  return agents;
}

StatusOr<MapId> DenseMap::MapOf(AgentId agent) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = agent_map_.find(agent);
  if (it == agent_map_.end())
    return NotFound("agent " + std::to_string(agent.value()) + " has no dense map");
  return it->second;
}

std::vector<KeyframeId> DenseMap::Keyframes(AgentId agent) const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<KeyframeId> ids;
  const AgentNode* node = FindAgent(agent);
  if (node == nullptr) return ids;
  for (const auto& [index, segment] : node->segments) {
    for (const auto& entry : segment.slots) {
      if (entry) ids.push_back(entry->id.keyframe);
    }
  }
  return ids;
}

DenseMapStats DenseMap::Stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  DenseMapStats stats;
  stats.maps = maps_.size();
  stats.agents = agent_map_.size();
  stats.pending_keyframes = pending_.size();
  std::size_t bytes = sizeof(*this) + occupied_.MemoryBytes() + nearest_.MemoryBytes() +
                      voxels_.capacity() * sizeof(VoxelIndex) +
                      indices_.capacity() * sizeof(std::uint32_t);
  bytes += (agent_map_.size() + pending_.size() + maps_.size()) * kTreeNodeOverhead;
  for (const auto& [map, node] : maps_) {
    for (const auto& [agent, agent_node] : node) {
      bytes += sizeof(AgentNode) + kTreeNodeOverhead;
      stats.segments += agent_node.segments.size();
      for (const auto& [index, segment] : agent_node.segments) {
        bytes += sizeof(Segment) + kTreeNodeOverhead;
        for (const auto& entry : segment.slots) {
          if (!entry) continue;
          ++stats.keyframes;
          stats.points += entry->world.size();
          stats.kept_points += entry->kept.size();
          bytes += sizeof(Entry) + entry->cloud.points.capacity() * sizeof(Eigen::Vector3f) +
                   entry->cloud.colors.capacity() * sizeof(entry->cloud.colors[0]) +
                   entry->world.capacity() * sizeof(Eigen::Vector3f) +
                   entry->kept.capacity() * sizeof(std::uint32_t);
        }
      }
    }
  }
  stats.memory_bytes = bytes;
  return stats;
}

}  // namespace ccmd
