#include "libccmd/dense/dense_map.h"

#include <algorithm>

#include "libccmd/dense/dense_map_detail.h"
#include "libccmd/dense/label.h"

namespace ccmd {

using dense_detail::IdText;
using dense_detail::kTreeNodeOverhead;

// ---- reading -------------------------------------------------------------------------------

namespace {

// Points AppendPoints gives for an entry with a filter.
template <typename Entry>
std::size_t PointsOf(const Entry& entry, DenseFilter filter) {
  if (entry.compact) return entry.stored.size();
  return filter == DenseFilter::kNone ? entry.world.size() : entry.kept.size();
}

}  // namespace

void DenseMap::AppendPoints(const Entry& entry, DenseFilter filter, PointCloud* cloud) const {
  if (entry.compact) {  // whatever the filter: it keeps only what the map needs
    entry.stored.Transform(entry.T_world_cam, &decoded_);
    cloud->points.insert(cloud->points.end(), decoded_.begin(), decoded_.end());
    cloud->colors.insert(cloud->colors.end(), entry.stored.colors().begin(),
                         entry.stored.colors().end());
    cloud->labels.resize(cloud->labels.size() + decoded_.size(), entry.label);
    return;
  }
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

StatusOr<std::vector<const DenseMap::AgentNode*>> DenseMap::SelectedAgentsLocked(
    const DenseSelection& selection) const {
  std::vector<const AgentNode*> agents;
  switch (selection.kind) {
    case DenseSelection::Kind::kGlobal:
      for (const auto& [map, node] : maps_) {
        for (const auto& [agent, agent_node] : node.agents) agents.push_back(&agent_node);
      }
      break;
    case DenseSelection::Kind::kMap: {
      const auto it = maps_.find(selection.map);
      if (it == maps_.end()) {
        return NotFound("map " + std::to_string(selection.map.value()) + " has no dense map");
      }
      for (const auto& [agent, agent_node] : it->second.agents) agents.push_back(&agent_node);
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
  return agents;
}

std::size_t DenseMap::CountPointsLocked(const std::vector<const AgentNode*>& agents,
                                        DenseFilter filter) const {
  std::size_t count = 0;
  for (const AgentNode* node : agents) {
    for (const auto& [index, segment] : node->segments) {
      for (const auto& entry : segment.slots) {
        if (entry) count += PointsOf(*entry, filter);
      }
    }
  }
  return count;
}

template <typename Visit>
void DenseMap::ForEachPointLocked(const std::vector<const AgentNode*>& agents, DenseFilter filter,
                                  Visit&& visit) const {
  for (const AgentNode* node : agents) {
    for (const auto& [index, segment] : node->segments) {
      for (const auto& slot : segment.slots) {
        if (!slot) continue;
        const Entry& entry = *slot;
        if (entry.compact) {  // whatever the filter, as AppendPoints
          entry.stored.Transform(entry.T_world_cam, &decoded_);
          for (std::size_t i = 0; i < decoded_.size(); ++i) {
            visit(decoded_[i], entry.stored.colors()[i], entry.label);
          }
        } else if (filter == DenseFilter::kNone) {
          for (std::size_t i = 0; i < entry.world.size(); ++i) {
            visit(entry.world[i], entry.cloud.colors[i], entry.label);
          }
        } else {
          for (const std::uint32_t i : entry.kept) {
            visit(entry.world[i], entry.cloud.colors[i], entry.label);
          }
        }
      }
    }
  }
}

StatusOr<PointCloud> DenseMap::Extract(const DenseSelection& selection, DenseFilter filter) {
  PointCloud cloud;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    MaintainLocked();
    CCMD_ASSIGN_OR_RETURN(const std::vector<const AgentNode*> agents,
                          SelectedAgentsLocked(selection));
    const std::size_t count = CountPointsLocked(agents, filter);
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
                           DenseFilter filter, DenseExportMode mode) {
  if (mode == DenseExportMode::kCopy) {
    CCMD_ASSIGN_OR_RETURN(const PointCloud cloud, Extract(selection, filter));
    return WritePly(cloud, path);
  }
  std::lock_guard<std::mutex> lock(mutex_);
  MaintainLocked();
  CCMD_ASSIGN_OR_RETURN(const std::vector<const AgentNode*> agents,
                        SelectedAgentsLocked(selection));
  const PlyVertexWriter::Layout layout{/*normals=*/false, /*colors=*/true, /*labels=*/true};
  if (filter != DenseFilter::kGlobal) {
    CCMD_ASSIGN_OR_RETURN(std::unique_ptr<PlyVertexWriter> writer,
                          PlyVertexWriter::Open(path, CountPointsLocked(agents, filter), layout));
    ForEachPointLocked(agents, filter,
                       [&](const Eigen::Vector3f& p, const auto& color, std::uint32_t label) {
                         writer->Add(p, nullptr, &color, label);
                       });
    return writer->Finish();
  }
  // The voxel filter of Extract (VoxelFilterLargestLabel): in each voxel the first point with
  // the voxel's largest label. First pass: each voxel's largest label.
  VoxelBricks<std::uint32_t> ordinals;  // 1 + the voxel's ordinal; 0: empty
  std::vector<std::uint32_t> largest;   // per ordinal
  ForEachPointLocked(agents, filter,
                     [&](const Eigen::Vector3f& p, const auto&, std::uint32_t label) {
                       std::uint32_t& ordinal = ordinals.At(grid_.Index(p));
                       if (ordinal == 0) {
                         largest.push_back(label);
                         ordinal = static_cast<std::uint32_t>(largest.size());
                       } else if (label > largest[ordinal - 1]) {
                         largest[ordinal - 1] = label;
                       }
                     });
  // Second pass: each voxel's first point with that label.
  CCMD_ASSIGN_OR_RETURN(std::unique_ptr<PlyVertexWriter> writer,
                        PlyVertexWriter::Open(path, largest.size(), layout));
  std::vector<bool> written(largest.size(), false);
  ForEachPointLocked(agents, filter,
                     [&](const Eigen::Vector3f& p, const auto& color, std::uint32_t label) {
                       const std::uint32_t ordinal = ordinals.Get(grid_.Index(p)) - 1;
                       if (label == largest[ordinal] && !written[ordinal]) {
                         written[ordinal] = true;
                         writer->Add(p, nullptr, &color, label);
                       }
                     });
  return writer->Finish();
}

StatusOr<PointCloud> DenseMap::ExtractKeyframe(const GlobalKeyframeId& id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const AgentNode* node = FindAgent(id.agent);
  const Entry* entry = node ? Find(*node, id.keyframe.value()) : nullptr;
  if (entry == nullptr) return NotFound(IdText(id) + " is not in the dense map");
  PointCloud cloud;
  const std::size_t n = PointsOf(*entry, DenseFilter::kNone);
  cloud.points.reserve(n);
  cloud.colors.reserve(n);
  cloud.labels.reserve(n);
  AppendPoints(*entry, DenseFilter::kNone, &cloud);
  return cloud;
}

StatusOr<CameraCloud> DenseMap::KeyframeCloud(const GlobalKeyframeId& id,
                                              DenseFilter filter) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const AgentNode* node = FindAgent(id.agent);
  const Entry* entry = node ? Find(*node, id.keyframe.value()) : nullptr;
  if (entry == nullptr) return NotFound(IdText(id) + " is not in the dense map");
  if (entry->compact) return entry->stored.Decode();
  if (filter == DenseFilter::kNone) return entry->cloud;
  CameraCloud cloud;
  cloud.points.reserve(entry->kept.size());
  cloud.colors.reserve(entry->kept.size());
  for (const std::uint32_t i : entry->kept) {
    cloud.points.push_back(entry->cloud.points[i]);
    cloud.colors.push_back(entry->cloud.colors[i]);
  }
  return cloud;
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
  stats.released_keyframes = released_count_;
  stats.released_points = released_points_;
  stats.absent_updates = absent_updates_;
  std::size_t bytes =
      sizeof(*this) + occupied_.MemoryBytes() + nearest_.MemoryBytes() +
      voxels_.capacity() * sizeof(VoxelIndex) + indices_.capacity() * sizeof(std::uint32_t) +
      decoded_.capacity() * sizeof(Eigen::Vector3f) + released_.size() * sizeof(GlobalKeyframeId);
  bytes += (agent_map_.size() + pending_.size() + maps_.size()) * kTreeNodeOverhead;
  for (const auto& [map, node] : maps_) {
    stats.held_bytes += node.held.MemoryBytes();
    bytes += sizeof(MapNode) + node.held.MemoryBytes();
    for (const auto& [agent, agent_node] : node.agents) {
      bytes += sizeof(AgentNode) + kTreeNodeOverhead;
      stats.segments += agent_node.segments.size();
      for (const auto& [index, segment] : agent_node.segments) {
        bytes += sizeof(Segment) + kTreeNodeOverhead;
        for (const auto& entry : segment.slots) {
          if (!entry) continue;
          ++stats.keyframes;
          stats.points += PointsOf(*entry, DenseFilter::kNone);
          stats.kept_points += PointsOf(*entry, DenseFilter::kWindow);
          stats.compact_keyframes += entry->compact;
          if (entry->compact) stats.compact_points += entry->stored.size();
          bytes += sizeof(Entry) + entry->cloud.points.capacity() * sizeof(Eigen::Vector3f) +
                   entry->cloud.colors.capacity() * sizeof(entry->cloud.colors[0]) +
                   entry->world.capacity() * sizeof(Eigen::Vector3f) +
                   entry->kept.capacity() * sizeof(std::uint32_t) + entry->stored.MemoryBytes();
        }
      }
    }
  }
  stats.memory_bytes = bytes;
  return stats;
}

}  // namespace ccmd
