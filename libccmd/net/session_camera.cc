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

Pose TrajectoryCameraFromSession(const SessionCamera& s) {
  const Eigen::Quaterniond q(s.trajectory_q[3], s.trajectory_q[0], s.trajectory_q[1],
                             s.trajectory_q[2]);
  Pose T = Pose::Identity();
  T.linear() = q.normalized().toRotationMatrix();
  T.translation() = Eigen::Vector3d(s.trajectory_t[0], s.trajectory_t[1], s.trajectory_t[2]);
  return T;
}

void SetSessionTrajectoryCamera(const Pose& T, SessionCamera* s) {
  Eigen::Quaterniond q(T.linear());
  q.normalize();
  if (q.w() < 0) q.coeffs() = -q.coeffs();  // one sign, so that identity reads as identity
  s->trajectory_q = {q.x(), q.y(), q.z(), q.w()};
  s->trajectory_t = {T.translation().x(), T.translation().y(), T.translation().z()};
  if (T.linear().isIdentity(1e-12)) s->trajectory_q = {0, 0, 0, 1};
}

}  // namespace ccmd
