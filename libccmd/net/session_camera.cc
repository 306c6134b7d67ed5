#include "libccmd/net/session_camera.h"

namespace ccmd {

SessionCamera SessionFromCamera(const PinholeCamera& c) {
  SessionCamera s;
  s.fx = c.fx;
  s.fy = c.fy;
  s.cx = c.cx;
  s.cy = c.cy;
  s.width = static_cast<std::uint32_t>(c.width);
  s.height = static_cast<std::uint32_t>(c.height);
  s.depth_scale = c.depth_map_factor;
  s.distortion = c.distortion;
  return s;
}

PinholeCamera CameraFromSession(const SessionCamera& s) {
  PinholeCamera c;
  c.fx = s.fx;
  c.fy = s.fy;
  c.cx = s.cx;
  c.cy = s.cy;
  c.width = static_cast<int>(s.width);
  c.height = static_cast<int>(s.height);
  if (s.depth_scale > 0) c.depth_map_factor = s.depth_scale;
  c.distortion = s.distortion;
  return c;
}

}  // namespace ccmd
