#pragma once

// The front-end's output in wire form: a KeyframeSnapshot becomes a proto KeyframeMessage
// (keypoints, links, new map points, covisibility, and the RGB-D payload coded by
// libccmd/codec when the keyframe selection chose to send it), pose updates a
// PoseUpdateMessage.

#include <vector>

#include "libccmd/codec/rgbd_payload.h"
#include "libccmd/codec/wire_pose.h"
#include "libccmd/tracking/keyframe_sink.h"
#include "proto/messages.h"

namespace ccmd {

StatusOr<KeyframeMessage> ToKeyframeMessage(const KeyframeSnapshot& snapshot,
                                            const RgbdEncodeOptions& rgbd_options);
PoseUpdateMessage ToPoseUpdateMessage(const std::vector<PoseUpdate>& updates);

}  // namespace ccmd
