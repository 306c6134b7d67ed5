#include "libccmd/system/link_sink.h"

#include <unistd.h>

#include <cctype>
#include <cmath>

#include "libccmd/net/traffic_stats.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

RgbdRequest LinkSink::NextRgbdRequest() {
  if (!budget_) return {};
  std::lock_guard<std::mutex> lock(mutex_);
  const RgbdLevel& level = budget_->Plan(ObserveLocked());
  planned_ = level.encode;
  return level.request;
}

double LinkSink::KeyframeRatioScale() {
  if (!budget_) return 1.0;
  std::lock_guard<std::mutex> lock(mutex_);
  const double now = MonotonicSeconds();
  if (now - last_refresh_s_ >= 0.1) {
    last_refresh_s_ = now;
    budget_->Refresh(ObserveLocked());
  }
  return budget_->KeyframeRatioScale();
}

LinkObservation LinkSink::ObserveLocked() {
  // Messages are acknowledged in order: the link's count says which of ours are stored.
  const std::uint64_t acked = link_->stats().acked;
  while (!unacked_.empty() && unacked_.front().first <= acked) {
    unacked_bytes_ -= unacked_.front().second;
    unacked_.pop_front();
  }
  LinkObservation o;
  o.now_s = MonotonicSeconds();
  o.handed_bytes = handed_bytes_;
  o.unacked_bytes = unacked_bytes_;
  return o;
}

void LinkSink::Handed(std::uint64_t link_number, std::size_t bytes) {
  handed_bytes_ += bytes;
  unacked_bytes_ += bytes;
  unacked_.emplace_back(link_number, bytes);
}

void LinkSink::OnKeyframe(KeyframeSnapshot keyframe) {
  const Stopwatch watch;
  RgbdEncodeOptions rgbd = rgbd_;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (planned_) rgbd = *planned_;
    planned_.reset();
  }
  auto message = ToKeyframeMessage(keyframe, rgbd);
  if (!message.ok()) {
    CCMD_LOG(ERROR) << "keyframe " << keyframe.id
                    << " not encodable: " << message.status().ToString();
    std::lock_guard<std::mutex> lock(mutex_);
    ++stats_.failed;
    return;
  }
  KeyframeSizeBreakdown parts;
  auto bytes = SerializeKeyframe(*message, &parts);
  if (!bytes.ok()) {
    CCMD_LOG(ERROR) << "keyframe " << keyframe.id
                    << " not serializable: " << bytes.status().ToString();
    std::lock_guard<std::mutex> lock(mutex_);
    ++stats_.failed;
    return;
  }
  const std::size_t size = bytes->size();
  const double encode_ms = watch.ElapsedMillis();
  const auto sent = link_->Send(MessageType::kKeyframe, std::move(bytes).value());
  std::lock_guard<std::mutex> lock(mutex_);
  if (!sent.ok()) {
    CCMD_LOG(ERROR) << "keyframe " << keyframe.id
                    << " refused by the link: " << sent.status().ToString();
    ++stats_.failed;
    return;
  }
  Handed(*sent, size);
  if (sent_.size() < kMaxLogged) {
    sent_.push_back(
        {keyframe.id, keyframe.created_wall_s, WallSeconds(), size, parts.colour + parts.depth});
  } else {
    ++not_logged_;  // memory must not grow with the run's length
  }
  if (budget_)
    budget_->Record(keyframe.id, size, parts.colour + parts.depth, message->rgbd.has_value());
  ++stats_.keyframes;
  stats_.rgbd_keyframes += message->rgbd.has_value();
  stats_.keypoints_sent += message->keypoints.size();
  stats_.keypoints_extracted += keyframe.keypoints_extracted;
  stats_.new_points += message->new_map_points.size();
  stats_.full_rgbd_pixels +=
      static_cast<std::uint64_t>(keyframe.image_width) * keyframe.image_height;
  stats_.keyframe_bytes += size;
  stats_.encode_ms_total += encode_ms;
  stats_.parts.pose += parts.pose;
  stats_.parts.keypoints += parts.keypoints;
  stats_.parts.descriptors += parts.descriptors;
  stats_.parts.map_points += parts.map_points;
  stats_.parts.colour += parts.colour;
  stats_.parts.depth += parts.depth;
  stats_.parts.other += parts.other;
}

void LinkSink::OnPoseUpdates(std::vector<PoseUpdate> updates) {
  auto bytes = SerializePoseUpdate(ToPoseUpdateMessage(updates));
  if (!bytes.ok()) {
    CCMD_LOG(ERROR) << "pose update not serializable: " << bytes.status().ToString();
    return;
  }
  const std::size_t size = bytes->size();
  const auto sent = link_->Send(MessageType::kPoseUpdate, std::move(bytes).value());
  std::lock_guard<std::mutex> lock(mutex_);
  if (!sent.ok()) {
    CCMD_LOG(ERROR) << "pose update refused by the link: " << sent.status().ToString();
    ++stats_.failed;
    return;
  }
  Handed(*sent, size);
  ++stats_.pose_updates;
  stats_.pose_update_bytes += size;
}

LinkSinkStats LinkSink::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return stats_;
}

Json LinkSink::StatsJson(bool detailed) const {
  const LinkSinkStats s = stats();
  Json j;
  j["keyframes_sent"] = s.keyframes;
  j["rgbd_keyframes_sent"] = s.rgbd_keyframes;
  j["pose_updates_sent"] = s.pose_updates;
  j["keyframe_bytes"] = s.keyframe_bytes;
  j["pose_update_bytes"] = s.pose_update_bytes;
  j["keyframe_bytes_mean"] =
      s.keyframes ? static_cast<double>(s.keyframe_bytes) / s.keyframes : 0.0;
  j["encode_ms_mean"] = s.keyframes ? s.encode_ms_total / s.keyframes : 0.0;
  j["failed"] = s.failed;
  j["keyframe_parts_bytes"] = KeyframePartsJson(s.parts);
  j["keypoints_sent"] = s.keypoints_sent;
  j["keypoints_extracted"] = s.keypoints_extracted;
  j["new_points"] = s.new_points;
  j["full_rgbd_pixels"] = s.full_rgbd_pixels;
  if (!detailed) return j;
  std::lock_guard<std::mutex> lock(mutex_);
  Json log = Json::MakeArray();
  for (const SentKeyframe& k : sent_) {
    // Whole milliseconds since the Unix epoch: JSON numbers keep them exactly.
    log.Push(Json(Json::Array{k.id.value(), std::llround(k.created_wall_s * 1e3),
                              std::llround(k.handed_wall_s * 1e3), k.bytes, k.rgbd_bytes}));
  }
  j["keyframe_log"] = log;
  j["keyframe_log_not_logged"] = not_logged_;
  if (budget_) j["budget"] = budget_->ToJson();
  return j;
}

std::string DefaultAgentName() {
  char host[256] = {0};
  if (gethostname(host, sizeof(host) - 1) != 0) host[0] = 0;
  std::string name;
  for (const char* c = host; *c; ++c) {
    if (std::isalnum(static_cast<unsigned char>(*c)) || *c == '-' || *c == '_' || *c == '.')
      name.push_back(*c);
  }
  if (name.empty()) name = "agent";
  return name + "-" + std::to_string(getpid());
}

}  // namespace ccmd
