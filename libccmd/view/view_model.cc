#include "libccmd/view/view_model.h"

#include <algorithm>
#include <chrono>
#include <cmath>

#include "libccmd/util/timer.h"

namespace ccmd {

Status ViewModelOptions::Validate() const {
  if (max_events < 16) return InvalidArgument("the view keeps at least 16 events");
  if (max_event_bytes < (1u << 16))
    return InvalidArgument("the view's event log needs at least 64 KiB");
  return Status::Ok();
}

void ViewModelOptions::Describe(OptionsWriter* out) const {
  out->Add("max_events", max_events);
  out->Add("max_event_bytes", max_event_bytes);
}

ViewModel::ViewModel(const ViewModelOptions& options) : options_(options) {}

Json ViewModel::PoseJson(const Pose& T) {
  Json m = Json::MakeArray();
  const Eigen::Matrix<double, 3, 4> rows = T.matrix().topRows<3>();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c) m.Push(rows(r, c));
  }
  return m;
}

double ViewModel::EpochMillis(double monotonic_s) {
  // Whole milliseconds: JSON numbers that are not whole are written with 10 digits, too few
  // for milliseconds since 1970.
  return std::round(1e3 * (WallSeconds() - (MonotonicSeconds() - monotonic_s)));
}

Json ViewModel::KeyframeJson(const ViewKeyframe& kf) {
  Json j;
  j["a"] = static_cast<int>(kf.id.agent.value());
  j["k"] = kf.id.keyframe.value();
  j["m"] = kf.map.value();
  j["T"] = PoseJson(kf.T_map_cam);
  j["cloud"] = kf.has_cloud;
  j["moves"] = kf.pose_updates;
  if (!kf.placed) j["placed"] = false;
  if (kf.culled) j["culled"] = true;
  return j;
}

Json ViewModel::IdJson(const GlobalKeyframeId& id) {
  Json item = Json::MakeArray();
  item.Push(static_cast<int>(id.agent.value()));
  item.Push(id.keyframe.value());
  return item;
}

void ViewModel::DropLoopsOf(const GlobalKeyframeId& id) {
  loops_.erase(std::remove_if(loops_.begin(), loops_.end(),
                              [&](const Loop& l) { return l.query == id || l.candidate == id; }),
               loops_.end());
}

void ViewModel::Append(Json event) {
  std::string text = event.Dump(-1);
  event_bytes_ += text.size();
  events_.emplace_back(++seq_, std::move(text));
  while (events_.size() > 1 &&
         (events_.size() > options_.max_events || event_bytes_ > options_.max_event_bytes)) {
    event_bytes_ -= events_.front().second.size();
    events_.pop_front();
  }
  changed_.notify_all();
}

void ViewModel::OnAgent(AgentId agent, const std::string& name) {
  std::lock_guard<std::mutex> lock(mutex_);
  agents_[agent] = name;
  Json e;
  e["type"] = "agent";
  e["a"] = static_cast<int>(agent.value());
  e["name"] = name;
  Append(std::move(e));
}

void ViewModel::OnKeyframe(const GlobalKeyframeId& id, MapId map, const Pose& T_map_cam,
                           double arrived_s, bool primary) {
  const double t = EpochMillis(arrived_s);
  std::lock_guard<std::mutex> lock(mutex_);
  ViewKeyframe& kf = keyframes_[id];
  kf.id = id;
  kf.map = map;
  kf.T_map_cam = T_map_cam;
  Json e = KeyframeJson(kf);
  e["type"] = "kf";
  e["t"] = t;
  e["primary"] = primary;
  Append(std::move(e));
}

void ViewModel::OnPoses(PoseSource source, MapId map, const std::vector<KeyframePose>& poses,
                        double arrived_s) {
  const double t = EpochMillis(arrived_s);
  std::lock_guard<std::mutex> lock(mutex_);
  Json list = Json::MakeArray();
  for (const KeyframePose& p : poses) {
    const auto it = keyframes_.find(p.id);
    if (it == keyframes_.end()) continue;  // never announced: nothing to move
    it->second.map = map;
    it->second.T_map_cam = p.T_world_cam;
    it->second.pose_updates++;
    Json item = Json::MakeArray();
    item.Push(static_cast<int>(p.id.agent.value()));
    item.Push(p.id.keyframe.value());
    const Json pose = PoseJson(p.T_world_cam);
    for (const Json& v : pose.array()) item.Push(v);
    list.Push(std::move(item));
  }
  if (list.size() == 0) return;
  Json e;
  e["type"] = "poses";
  e["src"] = PoseSourceName(source);
  e["m"] = map.value();
  e["t"] = t;
  e["kfs"] = std::move(list);
  Append(std::move(e));
}

void ViewModel::OnLoop(const LoopEvent& event) {
  std::lock_guard<std::mutex> lock(mutex_);
  Json from = Json::MakeArray();
  if (event.fusion) {
    // Both maps become event.map; the poses that change follow in OnPoses.
    std::vector<MapId> old;
    for (const GlobalKeyframeId& id : {event.query, event.candidate}) {
      const auto it = keyframes_.find(id);
      if (it != keyframes_.end() && it->second.map != event.map) old.push_back(it->second.map);
    }
    for (auto& [id, kf] : keyframes_) {
      for (MapId m : old) {
        if (kf.map == m) kf.map = event.map;
      }
    }
    for (MapId m : old) from.Push(m.value());
  }
  loops_.push_back({event.query, event.candidate, event.fusion, event.map});
  Json e;
  e["type"] = "loop";
  e["qa"] = static_cast<int>(event.query.agent.value());
  e["qk"] = event.query.keyframe.value();
  e["ca"] = static_cast<int>(event.candidate.agent.value());
  e["ck"] = event.candidate.keyframe.value();
  e["fusion"] = event.fusion;
  e["m"] = event.map.value();
  e["from"] = std::move(from);
  e["inliers"] = event.inliers;
  Append(std::move(e));
}

void ViewModel::OnPlacement(MapId map, const std::vector<GlobalKeyframeId>& keyframes,
                            bool placed) {
  std::lock_guard<std::mutex> lock(mutex_);
  Json list = Json::MakeArray();
  for (const GlobalKeyframeId& id : keyframes) {
    const auto it = keyframes_.find(id);
    if (it == keyframes_.end()) continue;  // never announced
    it->second.placed = placed;
    // Unplaced keyframes are out of the dense map (the few a restart keeps apart leave it).
    if (!placed) it->second.has_cloud = false;
    list.Push(IdJson(id));
  }
  if (list.size() == 0) return;
  Json e;
  e["type"] = "placed";
  e["m"] = map.value();
  e["placed"] = placed;
  e["kfs"] = std::move(list);
  Append(std::move(e));
}

void ViewModel::OnDenseKeyframe(const GlobalKeyframeId& id, MapId map, const Pose& T_map_cam) {
  const double t = EpochMillis(MonotonicSeconds());
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = keyframes_.find(id);
  if (it == keyframes_.end()) {
    // A keyframe culled (and forgotten here) before its map fused with the world map, whose
    // cloud came with the fusion: back, for its cloud only.
    ViewKeyframe kf;
    kf.id = id;
    kf.map = map;
    kf.T_map_cam = T_map_cam;
    kf.culled = true;
    it = keyframes_.emplace(id, kf).first;
    Json e = KeyframeJson(kf);
    e["type"] = "kf";
    e["t"] = t;
    e["primary"] = true;
    Append(std::move(e));
  }
  it->second.has_cloud = true;
  Json e;
  e["type"] = "cloud";
  e["a"] = static_cast<int>(id.agent.value());
  e["k"] = id.keyframe.value();
  e["t"] = t;
  Append(std::move(e));
}

void ViewModel::OnDenseReleased(const std::vector<GlobalKeyframeId>& ids) {
  std::lock_guard<std::mutex> lock(mutex_);
  Json list = Json::MakeArray();
  for (const GlobalKeyframeId& id : ids) {
    const auto it = keyframes_.find(id);
    if (it == keyframes_.end()) continue;
    it->second.has_cloud = false;
    if (it->second.culled) keyframes_.erase(it);
    list.Push(IdJson(id));
  }
  if (list.size() == 0) return;
  Json e;
  e["type"] = "released";
  e["kfs"] = std::move(list);
  Append(std::move(e));
}

void ViewModel::OnCulled(MapId map, const GlobalKeyframeId& id) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = keyframes_.find(id);
  if (it == keyframes_.end()) return;
  // Off its agent's path, with its loops; kept while it has a cloud to draw.
  DropLoopsOf(id);
  if (it->second.has_cloud) {
    it->second.culled = true;
  } else {
    keyframes_.erase(it);
  }
  Json list = Json::MakeArray();
  list.Push(IdJson(id));
  Json e;
  e["type"] = "culled";
  e["m"] = map.value();
  e["kfs"] = std::move(list);
  Append(std::move(e));
}

void ViewModel::PublishStats(const Json& stats) {
  std::string text = stats.Dump(-1);
  std::lock_guard<std::mutex> lock(mutex_);
  if (text == stats_) return;
  stats_ = std::move(text);
  ++stats_version_;
  changed_.notify_all();
}

Json ViewModel::StateJson() const {
  std::lock_guard<std::mutex> lock(mutex_);
  Json state;
  state["seq"] = seq_;
  state["server_time"] = std::round(WallSeconds() * 1e3);
  Json agents = Json::MakeArray();
  for (const auto& [id, name] : agents_) {
    Json a;
    a["a"] = static_cast<int>(id.value());
    a["name"] = name;
    agents.Push(std::move(a));
  }
  state["agents"] = std::move(agents);
  Json keyframes = Json::MakeArray();
  for (const auto& [id, kf] : keyframes_) keyframes.Push(KeyframeJson(kf));
  state["keyframes"] = std::move(keyframes);
  Json loops = Json::MakeArray();
  for (const Loop& l : loops_) {
    Json j;
    j["qa"] = static_cast<int>(l.query.agent.value());
    j["qk"] = l.query.keyframe.value();
    j["ca"] = static_cast<int>(l.candidate.agent.value());
    j["ck"] = l.candidate.keyframe.value();
    j["fusion"] = l.fusion;
    j["m"] = l.map.value();
    loops.Push(std::move(j));
  }
  state["loops"] = std::move(loops);
  auto stats = Json::Parse(stats_);
  state["stats"] = stats.ok() ? std::move(stats).value() : Json::MakeObject();
  state["stats_version"] = stats_version_;
  return state;
}

EventBatch ViewModel::WaitEvents(std::uint64_t after, std::uint64_t stats_version,
                                 double timeout_s) const {
  EventBatch batch;
  std::unique_lock<std::mutex> lock(mutex_);
  if (after > seq_) {  // a number from another server run
    batch.kind = EventBatch::Kind::kReset;
    return batch;
  }
  const auto ready = [&] { return closed_ || seq_ > after || stats_version_ != stats_version; };
  if (!changed_.wait_for(lock, std::chrono::duration<double>(timeout_s), ready))
    return batch;  // kTimeout
  if (closed_) {
    batch.kind = EventBatch::Kind::kClosed;
    return batch;
  }
  batch.kind = EventBatch::Kind::kEvents;
  if (seq_ > after) {
    const std::uint64_t first = events_.empty() ? seq_ + 1 : events_.front().first;
    if (after + 1 < first) {
      batch.kind = EventBatch::Kind::kReset;
      return batch;
    }
    // A bounded batch: a stream far behind catches up over several writes.
    constexpr std::size_t kMaxBatch = 512;
    for (auto it = events_.begin() + static_cast<std::ptrdiff_t>(after + 1 - first);
         it != events_.end() && batch.events.size() < kMaxBatch; ++it) {
      batch.events.push_back(*it);
    }
  }
  if (stats_version_ != stats_version) batch.stats = stats_;
  batch.stats_version = stats_version_;
  return batch;
}

void ViewModel::Close() {
  std::lock_guard<std::mutex> lock(mutex_);
  closed_ = true;
  changed_.notify_all();
}

std::vector<ViewKeyframe> ViewModel::Keyframes() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<ViewKeyframe> out;
  out.reserve(keyframes_.size());
  for (const auto& [id, kf] : keyframes_) out.push_back(kf);
  return out;
}

std::map<AgentId, std::string> ViewModel::AgentNames() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return agents_;
}

std::uint64_t ViewModel::last_seq() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return seq_;
}

}  // namespace ccmd
