#include "libccmd/tracking/keyframe_message.h"

#include <cstring>

namespace ccmd {

StatusOr<KeyframeMessage> ToKeyframeMessage(const KeyframeSnapshot& s,
                                            const RgbdEncodeOptions& rgbd_options) {
  KeyframeMessage m;
  m.id = s.id;
  m.timestamp = s.timestamp;
  m.T_world_cam = PoseToWire(s.T_world_cam);
  m.parent = s.parent;
  m.restart = s.restart;
  m.reset = s.reset;
  m.keypoints.resize(s.keypoints.size());
  for (std::size_t i = 0; i < s.keypoints.size(); ++i) {
    WireKeypoint& k = m.keypoints[i];
    k.u = s.keypoints[i].pt.x;
    k.v = s.keypoints[i].pt.y;
    k.octave = static_cast<std::uint8_t>(s.keypoints[i].octave);
    k.angle_deg = s.keypoints[i].angle;
    k.depth_m = s.depth[i];
    k.map_point = s.point_ids[i];
    // Only unlinked keypoints carry their descriptor; a linked one's is its map point's.
    if (!k.map_point)
      std::memcpy(k.descriptor.data(), s.descriptors.ptr<std::uint8_t>(static_cast<int>(i)), 32);
  }
  for (const auto& p : s.new_points) {
    NewMapPoint n;
    n.id = p.id;
    n.p_cam = {static_cast<float>(p.position_cam.x()), static_cast<float>(p.position_cam.y()),
               static_cast<float>(p.position_cam.z())};
    n.descriptor = p.descriptor;
    m.new_map_points.push_back(n);
  }
  for (const KeyframeSnapshot::DepthLink& l : s.depth_links) {
    DepthLink link;
    link.keyframe = l.other;
    link.T_this_other = PoseToWire(l.T_this_other);
    int k = 0;
    for (int r = 0; r < 6; ++r) {
      for (int c = r; c < 6; ++c) link.information[k++] = static_cast<float>(l.information(r, c));
    }
    m.depth_links.push_back(link);
  }
  for (const auto& [id, weight] : s.covisibility) {
    m.covisibility.push_back({id, static_cast<std::uint32_t>(weight)});
  }
  if (s.has_rgbd) {
    RgbdFrame frame;
    frame.bgr = s.bgr;
    frame.depth_mm = s.depth_mm;
    frame.timestamp = s.timestamp;
    CCMD_ASSIGN_OR_RETURN(m.rgbd, EncodeRgbdPayload(frame, rgbd_options));
  }
  return m;
}

PoseUpdateMessage ToPoseUpdateMessage(const std::vector<PoseUpdate>& updates) {
  PoseUpdateMessage m;
  for (const PoseUpdate& u : updates) m.entries.push_back({u.id, PoseToWire(u.T_world_cam)});
  return m;
}

}  // namespace ccmd
