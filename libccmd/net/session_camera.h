#pragma once

// The camera an agent announces in its handshake (SessionCamera, the wire's form) and the
// library's PinholeCamera: the agent converts its camera to announce it, the server converts
// the announcement back to verify loops and back-project depth.

#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/net/session_messages.h"

namespace ccmd {

SessionCamera SessionFromCamera(const PinholeCamera& camera);
PinholeCamera CameraFromSession(const SessionCamera& camera);

// The trajectory camera (SessionCamera::trajectory_t, trajectory_q) as the pose that maps its
// points into the colour camera's frame, and back.
Pose TrajectoryCameraFromSession(const SessionCamera& camera);
void SetSessionTrajectoryCamera(const Pose& T_color_trajectory, SessionCamera* camera);

}  // namespace ccmd
