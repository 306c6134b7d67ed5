#pragma once

// The agent's end of the pipeline: the front-end's keyframes and pose updates, coded for the
// wire (keyframe_message.h) and handed to the transport link, which stores them until the
// server acknowledges them.

#include <mutex>

#include "libccmd/net/agent_link.h"
#include "libccmd/tracking/keyframe_message.h"
#include "libccmd/tracking/keyframe_sink.h"
#include "libccmd/util/json.h"

namespace ccmd {

struct LinkSinkStats {
  std::uint64_t keyframes = 0, pose_updates = 0, rgbd_keyframes = 0;
  std::uint64_t keyframe_bytes = 0, pose_update_bytes = 0;
  KeyframeSizeBreakdown parts;
  // Counts behind the parts, for the size an uncompressed format would need.
  std::uint64_t keypoints_sent = 0, keypoints_extracted = 0, new_points = 0;
  std::uint64_t full_rgbd_pixels = 0;  // width x height of every keyframe
  std::uint64_t failed = 0;  // messages the link refused (it logs why)
  double encode_ms_total = 0;
};

class LinkSink : public KeyframeSink {
 public:
  LinkSink(AgentLink* link, const RgbdEncodeOptions& rgbd) : link_(link), rgbd_(rgbd) {}
  void OnKeyframe(KeyframeSnapshot keyframe) override;
  void OnPoseUpdates(std::vector<PoseUpdate> updates) override;
  LinkSinkStats stats() const;
  Json StatsJson() const;

 private:
  AgentLink* link_;
  RgbdEncodeOptions rgbd_;
  mutable std::mutex mutex_;
  LinkSinkStats stats_;
};

// host name and process id: a name that differs between agents started on one machine.
std::string DefaultAgentName();

}  // namespace ccmd
