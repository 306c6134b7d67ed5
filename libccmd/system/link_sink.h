#pragma once

// The agent's end of the pipeline: the front-end's keyframes and pose updates, coded for the
// wire (keyframe_message.h) and handed to the transport link, which stores them until the
// server acknowledges them.

#include <deque>
#include <memory>
#include <mutex>
#include <optional>

#include "libccmd/net/agent_link.h"
#include "libccmd/system/bandwidth_budget.h"
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
  std::uint64_t failed = 0;            // messages the link refused (it logs why)
  double encode_ms_total = 0;
};

// One keyframe as handed to the link: when it was made and handed over (wall clock, Unix
// seconds), its size. Matched with the server's arrival times for the map latency.
struct SentKeyframe {
  KeyframeId id;
  double created_wall_s = 0, handed_wall_s = 0;
  std::uint64_t bytes = 0, rgbd_bytes = 0;
};

class LinkSink : public KeyframeSink {
 public:
  // With a budget, each keyframe's RGB-D selection and coding follow its plan.
  LinkSink(AgentLink* link, const RgbdEncodeOptions& rgbd,
           std::unique_ptr<BandwidthBudget> budget = nullptr)
      : link_(link), rgbd_(rgbd), budget_(std::move(budget)) {}
  void OnKeyframe(KeyframeSnapshot keyframe) override;
  void OnPoseUpdates(std::vector<PoseUpdate> updates) override;
  RgbdRequest NextRgbdRequest() override;
  // The budget's keyframe density, refreshed from the link at most every 0.1 s.
  double KeyframeRatioScale() override;
  LinkSinkStats stats() const;
  // Counters, the keyframe log ("keyframe_log": [id, created, handed, bytes, RGB-D bytes]
  // per keyframe, times in milliseconds since the Unix epoch) and the budget's decisions.
  // `detailed` = false leaves the per-keyframe lists out (progress files).
  Json StatsJson(bool detailed = true) const;

 private:
  // Message bytes handed over and not yet acknowledged (mutex held).
  LinkObservation ObserveLocked();
  void Handed(std::uint64_t link_number, std::size_t bytes);  // mutex held

  AgentLink* link_;
  RgbdEncodeOptions rgbd_;
  mutable std::mutex mutex_;
  LinkSinkStats stats_;
  std::unique_ptr<BandwidthBudget> budget_;
  std::optional<RgbdEncodeOptions> planned_;  // the budget's coding for the next keyframe
  double last_refresh_s_ = -1;                // of the budget, between keyframes
  std::vector<SentKeyframe> sent_;            // the first kMaxLogged keyframes
  std::uint64_t not_logged_ = 0;
  static constexpr std::size_t kMaxLogged = 100000;
  std::uint64_t handed_bytes_ = 0;
  std::deque<std::pair<std::uint64_t, std::size_t>> unacked_;  // link number, bytes
  std::uint64_t unacked_bytes_ = 0;
};

// host name and process id: a name that differs between agents started on one machine.
std::string DefaultAgentName();

}  // namespace ccmd
