#pragma once

// The camera an agent announces in its handshake (SessionCamera, the wire's form) and the
// library's PinholeCamera: the agent converts its camera to announce it, the server converts
// the announcement back to verify loops and back-project depth.

#include "libccmd/geometry/camera.h"
#include "libccmd/net/session_messages.h"

namespace ccmd {

SessionCamera SessionFromCamera(const PinholeCamera& camera);
PinholeCamera CameraFromSession(const SessionCamera& camera);

}  // namespace ccmd
