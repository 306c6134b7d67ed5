#include "libccmd/dense/dense_map.h"

#include <algorithm>

#include "libccmd/dense/dense_map_detail.h"

namespace ccmd {

using dense_detail::kRefilterChunk;

// ---- filtering -----------------------------------------------------------------------------

const std::vector<Eigen::Vector3f>& DenseMap::WorldPoints(
    const Entry& entry, std::vector<Eigen::Vector3f>* scratch) const {
  if (!entry.compact) return entry.world;
  entry.stored.Transform(entry.T_world_cam, scratch);
  return *scratch;
}

void DenseMap::SetPose(Entry* entry, const Pose& T_world_cam) {
  entry->T_world_cam = T_world_cam;
  if (!entry->compact) Transform(entry);
  MarkPending(*entry);
}

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

void DenseMap::CompactSettled(AgentId agent_id, std::uint32_t first, std::uint32_t last) {
  if (!options_.compact_keyframes) return;
  const AgentNode* agent = FindAgent(agent_id);
  if (agent == nullptr) return;
  Entry* e = Find(*agent, first);
  if (e == nullptr) e = Next(*agent, first);
  std::vector<GlobalKeyframeId> release;
  for (; e != nullptr && e->id.keyframe.value() <= last; e = Next(*agent, e->id.keyframe.value())) {
    if (e->compact) continue;
    int successors = 0;
    for (const Entry* s = e; successors < options_.window_keyframes; ++successors) {
      s = Next(*agent, s->id.keyframe.value());
      if (s == nullptr) break;
    }
    if (successors < options_.window_keyframes) continue;  // still in the window
    // Its filter must be current before it becomes final.
    if (!pending_.empty()) MaintainLocked();
    MapNode& map = MapNodeOf(agent_id);
    if (map.rebuild_held) RebuildHeld(&map);
    if (Compact(&map, e)) release.push_back(e->id);
  }
  Release(release);
}

bool DenseMap::Compact(MapNode* map, Entry* entry) {
  grid_.Indices(entry->world, &voxels_);
  indices_.clear();
  for (const std::uint32_t i : entry->kept) {
    // Insert returns 0 where an earlier compacted keyframe holds the voxel.
    if (map->held.Insert(voxels_[i])) indices_.push_back(i);
  }
  entry->stored = CompactCloud::Encode(entry->cloud, indices_);
  entry->compact = true;
  entry->T_held = entry->T_world_cam;
  entry->cloud = CameraCloud();
  std::vector<Eigen::Vector3f>().swap(entry->world);
  std::vector<std::uint32_t>().swap(entry->kept);
  return TooFewToKeep(*entry);
}

bool DenseMap::TooFewToKeep(const Entry& entry) const {
  return entry.compact &&
         entry.stored.size() < std::max<std::size_t>(1, options_.release_below_points);
}

void DenseMap::MoveHeld(MapNode* map, Entry* entry) {
  entry->stored.Transform(entry->T_held, &decoded_);
  grid_.Indices(decoded_, &voxels_);
  for (const VoxelIndex& v : voxels_) map->held.Erase(v);
  entry->stored.Transform(entry->T_world_cam, &decoded_);
  grid_.Indices(decoded_, &voxels_);
  for (const VoxelIndex& v : voxels_) map->held.Insert(v);
  entry->T_held = entry->T_world_cam;
}

void DenseMap::RebuildHeld(MapNode* map) {
  map->held.Clear();
  std::vector<GlobalKeyframeId> release;
  for (auto& [agent, node] : map->agents) {
    for (auto& [index, segment] : node.segments) {
      for (auto& entry : segment.slots) {
        if (!entry || !entry->compact) continue;
        entry->stored.Transform(entry->T_world_cam, &decoded_);
        grid_.Indices(decoded_, &voxels_);
        indices_.clear();
        for (std::size_t i = 0; i < voxels_.size(); ++i) {
          if (map->held.Insert(voxels_[i])) indices_.push_back(static_cast<std::uint32_t>(i));
        }
        if (indices_.size() < voxels_.size()) entry->stored.Keep(indices_);
        entry->T_held = entry->T_world_cam;
        if (TooFewToKeep(*entry)) release.push_back(entry->id);
      }
    }
  }
  map->rebuild_held = false;
  Release(release);
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
  std::size_t recomputed = 0;
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
      const bool redo = r < end && !x->compact;  // a compacted keyframe's filter is final
      const auto mark = static_cast<std::uint16_t>(r - begin + 1);
      // A voxel marked by a keyframe beyond `limit` is outside the window; one marked `mark`
      // already has a point of x, so this one is not the first.
      const std::size_t limit = r - begin + 1 + window;
      grid_.Indices(WorldPoints(*x, &decoded_), &voxels_);
      const std::size_t n = voxels_.size();
      if (redo) {
        ++recomputed;
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
  return recomputed;
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
      Entry* entry = Find(*node, k);
      if (entry == nullptr) continue;  // removed since
      if (entry->compact) {
        MapNode& map = MapNodeOf(agent);
        if (!map.rebuild_held) MoveHeld(&map, entry);
        continue;
      }
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
  const std::size_t refiltered = MaintainLocked();
  for (auto& [id, map] : maps_) {
    if (map.rebuild_held) RebuildHeld(&map);
  }
  return refiltered;
}

}  // namespace ccmd
