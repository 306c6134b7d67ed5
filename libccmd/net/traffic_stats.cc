#include "libccmd/net/traffic_stats.h"

#include <sys/resource.h>

#include <cmath>

#include "libccmd/util/timer.h"
#include "proto/frame.h"

namespace ccmd {

Json KeyframePartsJson(const KeyframeSizeBreakdown& parts) {
  Json j = Json::MakeObject();
  j["pose"] = parts.pose;
  j["keypoints"] = parts.keypoints;
  j["descriptors"] = parts.descriptors;
  j["map_points"] = parts.map_points;
  j["colour"] = parts.colour;
  j["depth"] = parts.depth;
  j["other"] = parts.other;
  return j;
}

namespace {

double ProcessCpuSeconds() {
  rusage u{};
  ::getrusage(RUSAGE_SELF, &u);
  auto seconds = [](const timeval& t) { return static_cast<double>(t.tv_sec) + 1e-6 * t.tv_usec; };
  return seconds(u.ru_utime) + seconds(u.ru_stime);
}

}  // namespace

TrafficStats::TrafficStats(TrafficOptions options, double start_time)
    : options_(options),
      start_(start_time >= 0 ? start_time : MonotonicSeconds()),
      process_cpu_start_(ProcessCpuSeconds()) {}

void TrafficStats::AddAuthentication(double cpu_seconds) {
  if (cpu_seconds <= 0) return;
  std::lock_guard<std::mutex> lock(mutex_);
  auth_cpu_seconds_ += cpu_seconds;
}

void TrafficStats::ForgetAgent(AgentId agent) {
  std::lock_guard<std::mutex> lock(mutex_);
  agents_.erase(agent);
}

AgentTraffic& TrafficStats::Agent(AgentId agent) { return agents_[agent]; }

void TrafficStats::AgentConnected(AgentId agent, const std::string& name, double now) {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentTraffic& a = Agent(agent);
  a.name = name;
  if (!a.connected) {
    a.connected = true;
    a.session_start = now;
    ++a.sessions;
  }
}

void TrafficStats::AgentDisconnected(AgentId agent, double now) {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentTraffic& a = Agent(agent);
  if (a.connected) {
    a.connected_seconds += std::max(0.0, now - a.session_start);
    a.connected = false;
  }
}

void TrafficStats::AddReceivedBytes(AgentId agent, std::size_t bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  Agent(agent).received_bytes += bytes;
}

void TrafficStats::AddSentBytes(AgentId agent, std::size_t bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  Agent(agent).sent_bytes += bytes;
}

void TrafficStats::AddDataMessage(AgentId agent, std::uint8_t type, std::size_t message_bytes,
                                  const KeyframeSizeBreakdown* parts, double now,
                                  std::size_t tag_bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentTraffic& a = Agent(agent);
  const double t = now - start_;
  if (a.first_message < 0) {
    a.first_message = t;
    a.first_message_bytes = message_bytes;
  }
  a.last_message = t;
  a.wire_overhead_bytes += kFrameHeaderSize + 8 + tag_bytes;
  const auto bucket_index = static_cast<std::int64_t>(std::floor(t / options_.bucket_seconds));
  if (!a.buckets.count(bucket_index) && a.buckets.size() >= options_.max_buckets) {
    a.buckets.erase(a.buckets.begin());
  }
  AgentTraffic::Bucket& b = a.buckets[bucket_index];
  b.bytes += message_bytes;
  if (type == static_cast<std::uint8_t>(MessageType::kKeyframe)) {
    ++a.keyframes.count;
    a.keyframes.bytes += message_bytes;
    ++b.keyframes;
    b.keyframe_bytes += message_bytes;
    if (parts) {
      a.keyframe_parts.pose += parts->pose;
      a.keyframe_parts.keypoints += parts->keypoints;
      a.keyframe_parts.descriptors += parts->descriptors;
      a.keyframe_parts.map_points += parts->map_points;
      a.keyframe_parts.colour += parts->colour;
      a.keyframe_parts.depth += parts->depth;
      a.keyframe_parts.other += parts->other;
    }
  } else if (type == static_cast<std::uint8_t>(MessageType::kPoseUpdate)) {
    ++a.pose_updates.count;
    a.pose_updates.bytes += message_bytes;
    ++b.pose_updates;
  }
}

void TrafficStats::AddSessionMessage(AgentId agent, std::size_t frame_bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentTraffic& a = Agent(agent);
  ++a.session_messages.count;
  a.session_messages.bytes += frame_bytes;
}

void TrafficStats::AddDuplicate(AgentId agent, std::size_t frame_bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentTraffic& a = Agent(agent);
  ++a.duplicates.count;
  a.duplicates.bytes += frame_bytes;
}

void TrafficStats::AddDelivered(AgentId agent, std::uint64_t seq, bool replayed) {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentTraffic& a = Agent(agent);
  ++a.delivered;
  if (replayed) ++a.replayed;
  a.last_delivered_seq = seq;
}

void TrafficStats::Count(const std::string& event, std::uint64_t n) {
  std::lock_guard<std::mutex> lock(mutex_);
  counters_[event] += n;
}

std::uint64_t TrafficStats::counter(const std::string& event) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = counters_.find(event);
  return it == counters_.end() ? 0 : it->second;
}

AgentTraffic TrafficStats::agent(AgentId agent) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = agents_.find(agent);
  return it == agents_.end() ? AgentTraffic{} : it->second;
}

namespace {

Json Counter(const KindCounter& c) {
  Json j = Json::MakeObject();
  j["count"] = c.count;
  j["bytes"] = c.bytes;
  return j;
}

Json Ratio(double num, double den) { return den > 0 ? Json(num / den) : Json(nullptr); }

}  // namespace

Json TrafficStats::ToJson(double now) const {
  std::lock_guard<std::mutex> lock(mutex_);
  Json root = Json::MakeObject();
  root["uptime_s"] = now - start_;
  root["bucket_seconds"] = options_.bucket_seconds;
  Json counters = Json::MakeObject();
  for (const auto& [name, n] : counters_) counters[name] = n;
  root["counters"] = counters;
  Json auth = Json::MakeObject();
  const double process_cpu = ProcessCpuSeconds() - process_cpu_start_;
  auth["cpu_seconds"] = auth_cpu_seconds_;
  auth["process_cpu_seconds"] = process_cpu;
  auth["cpu_share"] = Ratio(auth_cpu_seconds_, process_cpu);
  root["authentication"] = auth;
  Json agents = Json::MakeArray();
  for (const auto& [id, a] : agents_) {
    Json j = Json::MakeObject();
    j["id"] = static_cast<unsigned>(id.value());
    j["name"] = a.name;
    j["connected"] = a.connected;
    j["sessions"] = a.sessions;
    const double connected =
        a.connected_seconds + (a.connected ? std::max(0.0, now - a.session_start) : 0.0);
    j["connected_seconds"] = connected;
    j["received_bytes"] = a.received_bytes;
    j["sent_bytes"] = a.sent_bytes;
    Json messages = Json::MakeObject();
    messages["keyframe"] = Counter(a.keyframes);
    messages["pose_update"] = Counter(a.pose_updates);
    messages["session"] = Counter(a.session_messages);
    j["messages"] = messages;
    j["wire_overhead_bytes"] = a.wire_overhead_bytes;
    j["duplicates"] = Counter(a.duplicates);
    j["keyframe_parts_bytes"] = KeyframePartsJson(a.keyframe_parts);
    const double data_bytes = static_cast<double>(a.keyframes.bytes + a.pose_updates.bytes);
    j["average_traffic_bytes_per_s"] = Ratio(data_bytes, connected);
    j["average_keyframe_bytes"] =
        Ratio(static_cast<double>(a.keyframes.bytes), static_cast<double>(a.keyframes.count));
    j["keyframe_rate_hz"] = Ratio(static_cast<double>(a.keyframes.count), connected);
    j["first_message_s"] = a.first_message >= 0 ? Json(a.first_message) : Json(nullptr);
    j["last_message_s"] = a.last_message >= 0 ? Json(a.last_message) : Json(nullptr);
    j["first_message_bytes"] = a.first_message_bytes;
    Json delivered = Json::MakeObject();
    delivered["count"] = a.delivered;
    delivered["replayed"] = a.replayed;
    delivered["last_seq"] = a.last_delivered_seq;
    j["delivered"] = delivered;
    Json buckets = Json::MakeArray();
    for (const auto& [index, b] : a.buckets) {
      Json e = Json::MakeObject();
      e["t"] = static_cast<double>(index) * options_.bucket_seconds;
      e["bytes"] = b.bytes;
      e["keyframes"] = b.keyframes;
      e["keyframe_bytes"] = b.keyframe_bytes;
      e["pose_updates"] = b.pose_updates;
      buckets.Push(e);
    }
    j["per_bucket"] = buckets;
    agents.Push(j);
  }
  root["agents"] = agents;
  return root;
}

Status TrafficOptions::Validate() const {
  if (!(bucket_seconds > 0) || !std::isfinite(bucket_seconds)) {
    return InvalidArgument("bucket_seconds must be positive");
  }
  if (max_buckets == 0) return InvalidArgument("max_buckets must be positive");
  return Status::Ok();
}

void TrafficOptions::Describe(OptionsWriter* out) const {
  out->Add("bucket_seconds", bucket_seconds);
  out->Add("max_buckets", max_buckets);
}

}  // namespace ccmd
