#include "libccmd/backend/map_memory.h"

namespace ccmd {
namespace {

// A std::map node beyond its value: three pointers, a colour, the allocator's header.
constexpr std::size_t kTreeNode = 48;
// An unordered_map node beyond its value (next pointer, cached hash, header) and its bucket.
constexpr std::size_t kHashNode = 32;

template <typename T>
std::size_t Capacity(const std::vector<T>& v) {
  return v.capacity() * sizeof(T);
}

}  // namespace

std::size_t SparseMemory::total() const {
  return keyframe_bytes + follower_bytes + keypoint_bytes + descriptor_bytes + point_link_bytes +
         map_point_bytes + covisibility_bytes + depth_link_bytes + loop_edge_bytes +
         rgbd_coded_bytes + place_bytes;
}

void SparseMemory::Add(const SparseMemory& o) {
  keyframes += o.keyframes;
  culled_keyframes += o.culled_keyframes;
  follower_bytes += o.follower_bytes;
  map_points += o.map_points;
  keyframe_bytes += o.keyframe_bytes;
  keypoint_bytes += o.keypoint_bytes;
  descriptor_bytes += o.descriptor_bytes;
  point_link_bytes += o.point_link_bytes;
  map_point_bytes += o.map_point_bytes;
  covisibility_bytes += o.covisibility_bytes;
  depth_link_bytes += o.depth_link_bytes;
  loop_edge_bytes += o.loop_edge_bytes;
  rgbd_coded_bytes += o.rgbd_coded_bytes;
  place_bytes += o.place_bytes;
}

Json SparseMemory::ToJson() const {
  Json j;
  j["keyframes"] = keyframes;
  j["culled_keyframes"] = culled_keyframes;
  j["map_points"] = map_points;
  const std::pair<const char*, std::size_t> parts[] = {
      {"keyframe", keyframe_bytes},         {"followers", follower_bytes},
      {"keypoints", keypoint_bytes},        {"descriptors", descriptor_bytes},
      {"point_links", point_link_bytes},    {"map_points", map_point_bytes},
      {"covisibility", covisibility_bytes}, {"depth_links", depth_link_bytes},
      {"loop_edges", loop_edge_bytes},      {"rgbd_coded", rgbd_coded_bytes},
      {"place_recognition", place_bytes},   {"total", total()}};
  Json bytes, per_keyframe;
  for (const auto& [name, value] : parts) {
    bytes[name] = value;
    per_keyframe[name] = keyframes ? static_cast<double>(value) / keyframes : 0.0;
  }
  j["bytes"] = bytes;
  j["bytes_per_keyframe"] = per_keyframe;
  return j;
}

SparseMemory MeasureSparseMemory(const ServerMap& map) {
  SparseMemory m;
  for (const auto& [id, kf] : map.keyframes()) {
    m.keyframes += 1 + kf->followers.size();
    m.culled_keyframes += kf->followers.size();
    m.follower_bytes += Capacity(kf->followers);
    for (const CulledKeyframe& f : kf->followers) {
      if (f.rgbd) {
        m.rgbd_coded_bytes +=
            sizeof(RgbdPayload) + f.rgbd->colour_jpeg.capacity() + f.rgbd->depth.capacity();
      }
    }
    m.keyframe_bytes += sizeof(ServerKeyframe) + kTreeNode + sizeof(id) + sizeof(kf);
    m.keypoint_bytes += Capacity(kf->keypoints);
    m.descriptor_bytes += Capacity(kf->own_descriptors);
    m.point_link_bytes += Capacity(kf->points);
    m.covisibility_bytes +=
        kf->covisibility.size() * (kTreeNode + sizeof(GlobalKeyframeId) + sizeof(int));
    m.depth_link_bytes += Capacity(kf->depth_links);
    if (kf->rgbd) {
      m.rgbd_coded_bytes +=
          sizeof(RgbdPayload) + kf->rgbd->colour_jpeg.capacity() + kf->rgbd->depth.capacity();
    }
  }
  m.map_points = map.num_points();
  m.map_point_bytes = map.PointBytes(kHashNode);
  m.loop_edge_bytes = Capacity(map.loop_edges());
  return m;
}

}  // namespace ccmd
