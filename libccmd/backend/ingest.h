#pragma once

// Turning agent messages into server-map content.

#include <vector>

#include "libccmd/backend/server_map.h"
#include "libccmd/geometry/camera.h"
#include "proto/messages.h"

namespace ccmd {

// Adds a keyframe message of `agent` to `map`. Its server pose follows the agent's relative
// motion from the keyframe it is placed against (its parent, else the agent's latest keyframe
// in the map), so corrections the server applied to earlier keyframes carry over; the agent's
// first keyframe in a map is placed by `T_map_agent`. Known map points are linked, new ones
// anchored to this keyframe, covisibility recorded. RGB-D data is not decoded here.
// Returns the new keyframe, or an error for an inconsistent message (duplicate id, ...).
StatusOr<ServerKeyframe*> AddKeyframeMessage(ServerMap* map, AgentId agent,
                                             const KeyframeMessage& message,
                                             const Pose& T_map_agent);

// Applies an agent's local-BA pose updates: each keyframe moves by the change the agent made
// (T_agent_old^-1 T_agent_new, on the right), which keeps server-side corrections. Returns the
// keyframes that moved (unknown ids are skipped).
std::vector<ServerKeyframe*> ApplyPoseUpdates(ServerMap* map, AgentId agent,
                                              const PoseUpdateMessage& message);

}  // namespace ccmd
