#include "libccmd/codec/wire_pose.h"

namespace ccmd {

WirePose PoseToWire(const Pose& T) {
  const Eigen::Quaterniond q = QuaternionOf(T);
  WirePose w;
  w.q_xyzw = {q.x(), q.y(), q.z(), q.w()};
  w.t = {T.translation().x(), T.translation().y(), T.translation().z()};
  return w;
}

Pose PoseFromWire(const WirePose& w) {
  return PoseFromTranslationQuaternion(
      Eigen::Vector3d(w.t[0], w.t[1], w.t[2]),
      Eigen::Quaterniond(w.q_xyzw[3], w.q_xyzw[0], w.q_xyzw[1], w.q_xyzw[2]));
}

}  // namespace ccmd
