#pragma once

// What the server's sparse maps hold in memory, by part, so that the memory per keyframe can
// be reported and bounded (docs/benchmarks/server_load.md). Sizes are what the containers
// have allocated (capacities) plus a fixed estimate per tree or hash node.

#include <cstddef>

#include "libccmd/backend/server_map.h"
#include "libccmd/util/json.h"

namespace ccmd {

struct SparseMemory {
  std::size_t keyframes = 0;         // kept and culled
  std::size_t culled_keyframes = 0;  // of `keyframes`: only their poses are kept (followers)
  std::size_t map_points = 0;
  std::size_t keyframe_bytes = 0;    // the kept keyframe objects and the map's index of them
  std::size_t follower_bytes = 0;    // the culled keyframes (CulledKeyframe, in their leaders)
  std::size_t keypoint_bytes = 0;    // positions, octaves, angles, depths
  std::size_t descriptor_bytes = 0;  // one per keypoint
  std::size_t point_link_bytes = 0;  // keypoint to map point
  std::size_t map_point_bytes = 0;   // points, their descriptors and observations, the index
  std::size_t covisibility_bytes = 0;
  std::size_t depth_link_bytes = 0;
  std::size_t loop_edge_bytes = 0;
  std::size_t rgbd_coded_bytes = 0;  // coded RGB-D waiting for the dense map
  std::size_t place_bytes = 0;       // place recognition (filled in by the back-end)

  std::size_t total() const;
  void Add(const SparseMemory& other);
  // Every part in bytes and per keyframe.
  Json ToJson() const;
};

// One map, read under its lock (the caller holds its guard).
SparseMemory MeasureSparseMemory(const ServerMap& map);

}  // namespace ccmd
