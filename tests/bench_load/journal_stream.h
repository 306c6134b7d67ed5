#pragma once

// The keyframe streams ccmd_load replays: a run's journals (one per agent, as ccmd_server
// wrote them), read back into messages. A stream can be replayed for as long as wanted: each
// further pass (lap) renumbers keyframes and map points past the previous lap's, as an agent
// that keeps circling the place would number them, and every pose is moved by the agent's own
// rigid offset, so that the server must find how the agents' maps relate.

#include <memory>
#include <string>
#include <vector>

#include "libccmd/geometry/pose.h"
#include "libccmd/net/session_messages.h"
#include "libccmd/util/status.h"
#include "proto/messages.h"

namespace ccmd::load {

struct StreamMessage {
  // Exactly one is set.
  std::shared_ptr<const KeyframeMessage> keyframe;
  std::shared_ptr<const PoseUpdateMessage> pose_update;
};

struct JournalStream {
  std::string name;  // the recorded agent's
  SessionCamera camera;
  std::vector<StreamMessage> messages;  // in journal order
  std::size_t keyframes = 0;
  std::uint32_t keyframe_ids = 0;   // one past the largest keyframe id
  std::uint32_t map_point_ids = 0;  // one past the largest map point id
  std::size_t keyframe_bytes = 0;   // serialized, all keyframes of one lap
};

// Every agent_*.journal in `folder`, in file name order. Errors: no journal, a journal that
// does not read, or a stream without keyframes.
StatusOr<std::vector<JournalStream>> ReadJournalStreams(const std::string& folder);

// Message `index` of lap `lap` of the stream, for an agent whose poses are moved by
// T_offset_recorded (maps the recorded world frame into the agent's own).
KeyframeMessage LapKeyframe(const JournalStream& stream, const KeyframeMessage& recorded,
                            std::uint32_t lap, const Pose& T_offset_recorded);
PoseUpdateMessage LapPoseUpdate(const JournalStream& stream, const PoseUpdateMessage& recorded,
                                std::uint32_t lap, const Pose& T_offset_recorded);

// The rigid offset of agent `index` (0-based): a turn about the vertical and a shift, different
// for every agent; agent 0 keeps the recorded frame.
Pose AgentOffset(int index);

}  // namespace ccmd::load
