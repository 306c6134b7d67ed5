#pragma once

// Traffic accounting on the server, per agent: bytes and counts per message kind, bytes per
// keyframe part (pose, keypoints, descriptors, map points, colour, depth, other; from
// proto's KeyframeSizeBreakdown of what arrived), and the same over time in fixed buckets
// (1 s by default). Exported as JSON for the evaluation: average traffic per second,
// average keyframe size, keyframe rate, breakdown per kind. Thread-safe.
//
// Definitions (JSON field names):
//   messages.<kind>.bytes     message bytes (the proto payload, without the 20-byte frame
//                             header and 8-byte sequence number, which are in
//                             wire_overhead_bytes)
//   received_bytes            every byte read from the agent's connections, handshakes,
//                             heartbeats and duplicates included
//   connected_seconds         time the agent had a session (sum over its sessions)
//   average_traffic_bytes_per_s = (keyframe + pose update message bytes) / connected_seconds
//   average_keyframe_bytes    keyframe message bytes / keyframes
//   keyframe_rate_hz          keyframes / connected_seconds

#include <cstdint>
#include <map>
#include <mutex>
#include <string>

#include "libccmd/util/ids.h"
#include "libccmd/util/json.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"
#include "proto/messages.h"

namespace ccmd {

// Bytes per keyframe part as JSON ("pose", "keypoints", "descriptors", "map_points", "colour",
// "depth", "other"): the agent's link statistics and the server's traffic report share it.
Json KeyframePartsJson(const KeyframeSizeBreakdown& parts);

struct TrafficOptions {
  double bucket_seconds = 1.0;
  // Per agent; beyond this the oldest buckets are dropped (the totals keep everything), so
  // the JSON stays small on long runs: one hour of 1 s buckets.
  std::size_t max_buckets = 3600;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct KindCounter {
  std::uint64_t count = 0;
  std::uint64_t bytes = 0;
};

struct AgentTraffic {
  std::string name;
  bool connected = false;
  std::uint64_t sessions = 0;
  double connected_seconds = 0;  // closed sessions only; ToJson adds the open one
  double session_start = 0;
  std::uint64_t received_bytes = 0;
  std::uint64_t sent_bytes = 0;
  KindCounter keyframes, pose_updates, session_messages, duplicates;
  std::uint64_t wire_overhead_bytes = 0;
  KeyframeSizeBreakdown keyframe_parts;
  double first_message = -1, last_message = -1;  // seconds since the server started
  std::uint64_t first_message_bytes =
      0;  // sent before first_message: not part of a rate over the span
  std::uint64_t delivered = 0, replayed = 0, last_delivered_seq = 0;
  struct Bucket {
    std::uint64_t bytes = 0;
    std::uint64_t keyframes = 0;
    std::uint64_t keyframe_bytes = 0;
    std::uint64_t pose_updates = 0;
  };
  std::map<std::int64_t, Bucket> buckets;
};

class TrafficStats {
 public:
  explicit TrafficStats(TrafficOptions options = {}, double start_time = -1);

  void AgentConnected(AgentId agent, const std::string& name, double now);
  void AgentDisconnected(AgentId agent, double now);
  void AddReceivedBytes(AgentId agent, std::size_t bytes);
  void AddSentBytes(AgentId agent, std::size_t bytes);
  // A data message accepted for journaling; parts only for keyframes.
  // `tag_bytes`: the frame's authentication tag (16 with a key), counted as overhead.
  void AddDataMessage(AgentId agent, std::uint8_t type, std::size_t message_bytes,
                      const KeyframeSizeBreakdown* parts, double now, std::size_t tag_bytes = 0);
  void AddSessionMessage(AgentId agent, std::size_t frame_bytes);
  void AddDuplicate(AgentId agent, std::size_t frame_bytes);
  void AddDelivered(AgentId agent, std::uint64_t seq, bool replayed);
  // Server-wide event counters ("connections_accepted", "refused_auth_failed", ...).
  void Count(const std::string& event, std::uint64_t n = 1);
  // CPU time spent making and checking frame tags; the JSON gives its share of the
  // process's CPU time since these statistics started ("authentication").
  void AddAuthentication(double cpu_seconds);
  // Drops an agent that was registered provisionally and left without sending anything.
  void ForgetAgent(AgentId agent);

  std::uint64_t counter(const std::string& event) const;
  AgentTraffic agent(AgentId agent) const;  // a copy; empty if unknown
  Json ToJson(double now) const;

 private:
  AgentTraffic& Agent(AgentId agent);  // mutex held

  TrafficOptions options_;
  double start_;
  mutable std::mutex mutex_;
  std::map<AgentId, AgentTraffic> agents_;
  std::map<std::string, std::uint64_t> counters_;
  double auth_cpu_seconds_ = 0;
  double process_cpu_start_ = 0;
};

}  // namespace ccmd
