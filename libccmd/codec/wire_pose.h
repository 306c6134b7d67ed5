#pragma once

// Poses on the wire (proto's WirePose: quaternion x y z w and translation) and in memory.
// One pair of conversions for the agent, which writes them, and the server, which reads them.

#include "libccmd/geometry/pose.h"
#include "proto/messages.h"

namespace ccmd {

WirePose PoseToWire(const Pose& T);
Pose PoseFromWire(const WirePose& pose);

}  // namespace ccmd
