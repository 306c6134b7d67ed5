#include "libccmd/system/server_runtime.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "libccmd/net/session_camera.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/process_usage.h"
#include "libccmd/util/timer.h"

namespace ccmd {

Status ServerRuntimeOptions::Validate() const {
  CCMD_RETURN_IF_ERROR(net.Validate());
  CCMD_RETURN_IF_ERROR(backend.Validate());
  if (output_dir.empty()) return InvalidArgument("the server needs an output folder");
  if (!(stats_period_s > 0)) return InvalidArgument("the statistics period must be positive");
  if (view) CCMD_RETURN_IF_ERROR(view->Validate());
  return Status::Ok();
}

void ServerRuntimeOptions::Describe(OptionsWriter* out) const {
  out->Nested("net", net);
  out->Nested("backend", backend);
  out->Add("output_dir", output_dir);
  out->Add("stats_period_s", stats_period_s);
  out->Add("snapshot_period_s", snapshot_period_s);
  if (view) out->Nested("view", *view);
}

StatusOr<std::unique_ptr<ServerRuntime>> ServerRuntime::Create(
    const ServerRuntimeOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  CCMD_RETURN_IF_ERROR(MakeDirectories(options.output_dir));
  return std::unique_ptr<ServerRuntime>(new ServerRuntime(options));
}

ServerRuntime::~ServerRuntime() { Stop().IgnoreError(); }

Status ServerRuntime::Start() {
  if (options_.view) view_model_ = std::make_unique<ViewModel>();
  CCMD_ASSIGN_OR_RETURN(backend_, Backend::Create(options_.backend, view_model_.get()));
  if (backend_->dense()) {
    SnapshotOptions snapshot;
    snapshot.folder = JoinPath(options_.output_dir, "snapshots");
    snapshot.period_s = options_.snapshot_period_s;
    snapshots_ = std::make_unique<DenseSnapshotWriter>(backend_->dense(), snapshot);
  }
  CCMD_RETURN_IF_ERROR(StartView());
  server_ = std::make_unique<Server>(options_.net, this);
  return server_->Start();
}

void ServerRuntime::OnAgentKnown(const AgentDescription& agent, bool from_journal) {
  {
    std::lock_guard<std::mutex> lock(names_mutex_);
    names_[agent.id] = agent.name;
  }
  std::optional<DepthNoise> depth_noise;
  if (agent.camera.HasDepthNoise()) {
    depth_noise.emplace();
    depth_noise->sigma_0 = agent.camera.depth_sigma0;
    depth_noise->sigma_2 = agent.camera.depth_sigma2;
  }
  const Status s = backend_->RegisterAgent(agent.id, agent.name, CameraFromSession(agent.camera),
                                           depth_noise, TrajectoryCameraFromSession(agent.camera));
  if (!s.ok()) CCMD_LOG(ERROR) << "agent " << agent.name << ": " << s.ToString();
  CCMD_LOG(INFO) << "agent " << agent.id << " '" << agent.name << "' "
                 << (from_journal ? "restored" : "joined") << " (" << DescribeCamera(agent.camera)
                 << ")";
}

void ServerRuntime::OnAgentDisconnected(AgentId agent, const std::string& reason) {
  CCMD_LOG(INFO) << "agent " << agent << " left: " << reason;
  backend_->SubmitSessionEnded(agent).IgnoreError();
}

void ServerRuntime::OnMessage(DeliveredMessage m) {
  // The payload passed the frame CRC and was journaled; a message that still does not parse
  // is logged and skipped (it stays in the journal for inspection).
  if (m.type == static_cast<std::uint8_t>(MessageType::kKeyframe)) {
    auto keyframe = ParseKeyframe(m.payload);
    if (keyframe.ok()) {
      backend_
          ->SubmitKeyframe(m.agent, std::move(keyframe).value(), m.replayed ? 0.0 : m.received_time)
          .IgnoreError();
      return;
    }
    CCMD_LOG(WARNING) << "agent " << m.agent << " message " << m.seq << ": "
                      << keyframe.status().ToString();
  } else if (m.type == static_cast<std::uint8_t>(MessageType::kPoseUpdate)) {
    auto update = ParsePoseUpdate(m.payload);
    if (update.ok()) {
      backend_->SubmitPoseUpdate(m.agent, std::move(update).value(), m.received_time).IgnoreError();
      return;
    }
    CCMD_LOG(WARNING) << "agent " << m.agent << " message " << m.seq << ": "
                      << update.status().ToString();
  } else {
    CCMD_LOG(WARNING) << "agent " << m.agent << " message " << m.seq << ": unknown type "
                      << int{m.type};
  }
  ++malformed_messages_;
}

void ServerRuntime::OnReplayFinished(std::uint64_t messages) {
  CCMD_LOG(INFO) << "journal replay: " << messages << " messages handed to the back-end";
}

Json ServerRuntime::StatsJson() {
  Json j;
  if (server_) j["transport"] = server_->StatsJson();
  if (backend_) j["backend"] = backend_->StatsJson();
  std::map<AgentId, std::string> names;
  {
    std::lock_guard<std::mutex> lock(names_mutex_);
    names = names_;
  }
  // Counting an agent's placed keyframes checks its map out, which waits for the loop stage:
  // not under the names' lock, which sessions take when agents join.
  Json agents, agent_maps, agent_placed;
  for (const auto& [id, name] : names) {
    agents[name] = Json(static_cast<int>(id.value()));
    // Which map each agent's keyframes are in, and how many of them are placed: the
    // evaluation names the primary map's agents.
    const auto map = backend_ ? backend_->MapOf(id) : std::nullopt;
    if (map) {
      agent_maps[name] = Json(static_cast<int>(map->value()));
      agent_placed[name] = Json(static_cast<int>(backend_->AgentKeyframeCount(id)));
    }
  }
  j["agent_ids"] = agents;
  j["agent_maps"] = agent_maps;
  j["agent_placed_keyframes"] = agent_placed;
  if (backend_ && backend_->PrimaryMap())
    j["primary_map"] = static_cast<int>(backend_->PrimaryMap()->value());
  j["malformed_messages"] = malformed_messages_.load();
  const ProcessUsage usage = CurrentProcessUsage();
  Json process;
  process["rss_mb"] = usage.rss_mb;
  process["peak_rss_mb"] = usage.peak_rss_mb;
  process["cpu_seconds"] = usage.cpu_seconds;
  process["time_s"] = MonotonicSeconds();
  j["process"] = process;
  if (!memory_.is_null()) j["memory"] = memory_;
  return j;
}

void ServerRuntime::Tick() {
  const double now = MonotonicSeconds();
  if (backend_ && now - last_memory_ >= options_.memory_period_s) {
    last_memory_ = now;
    memory_ = backend_->MemoryJson();
  }
  if (now - last_stats_ >= options_.stats_period_s) {
    last_stats_ = now;
    const Status s = WriteJsonFile(StatsJson(), JoinPath(options_.output_dir, "server_stats.json"));
    if (!s.ok()) CCMD_LOG(WARNING) << s.ToString();
  }
  if (backend_) {
    backend_->ConfirmIdleAgentsLoops();
    backend_->OptimiseIdleMaps();
  }
  if (snapshots_ && options_.snapshot_period_s > 0 && snapshots_->Due(now)) {
    // Not while a global BA solves (their transient memory would add up): next tick.
    if (const auto transient = backend_->LockLargeTransient(/*wait=*/false)) {
      auto wrote = snapshots_->Tick(now);
      if (!wrote.ok()) CCMD_LOG(WARNING) << "snapshot: " << wrote.status().ToString();
    }
  }
}

Status ServerRuntime::WriteResults() {
  Status first;
  auto keep = [&](const Status& s) {
    if (!s.ok()) {
      CCMD_LOG(ERROR) << s.ToString();
      if (first.ok()) first = s;
    }
  };
  std::map<AgentId, std::string> names;
  {
    std::lock_guard<std::mutex> lock(names_mutex_);
    names = names_;
  }
  keep(WriteTumTrajectory(backend_->FusedTrajectory(),
                          JoinPath(options_.output_dir, "trajectory_fused.txt"),
                          "keyframes of the primary map (world frame)"));
  for (const auto& [id, name] : names) {
    keep(WriteTumTrajectory(
        backend_->AgentTrajectory(id), JoinPath(options_.output_dir, "trajectory_" + name + ".txt"),
        backend_->AgentInPrimaryMap(id) ? "keyframes, world frame (primary map)"
                                        : "keyframes, NOT fused: the agent's own map frame"));
  }
  if (backend_->dense() && backend_->PrimaryMap()) {
    const auto dense_maps = backend_->dense()->Maps();
    if (std::find(dense_maps.begin(), dense_maps.end(), *backend_->PrimaryMap()) !=
        dense_maps.end()) {
      keep(backend_->ExportDenseMap(JoinPath(options_.output_dir, "map.ply")));
    } else {
      CCMD_LOG(INFO) << "no RGB-D keyframe reached the primary map: no map.ply";
    }
  }
  keep(WriteKeyframeArrivals(names));
  memory_ = backend_->MemoryJson();
  keep(WriteJsonFile(StatsJson(), JoinPath(options_.output_dir, "server_stats.json")));
  return first;
}

Status ServerRuntime::WriteKeyframeArrivals(const std::map<AgentId, std::string>& names) {
  std::string csv =
      "# agent,keyframe,stage,wall_ms (stage: received by the back-end, dense = points in the "
      "dense map, "
      "dense_fused = came in with a map fusion)\n";
  char line[160];
  for (const KeyframeArrival& a : backend_->keyframe_arrivals()) {
    const auto name = names.find(a.id.agent);
    const char* stage = a.stage == KeyframeArrival::Stage::kReceived ? "received"
                        : a.after_fusion                             ? "dense_fused"
                                                                     : "dense";
    std::snprintf(
        line, sizeof(line), "%s,%u,%s,%.3f\n",
        name != names.end() ? name->second.c_str() : std::to_string(a.id.agent.value()).c_str(),
        a.id.keyframe.value(), stage, a.wall_s * 1e3);
    csv += line;
  }
  return WriteFileAtomic(JoinPath(options_.output_dir, "keyframe_arrivals.csv"), csv);
}

Status ServerRuntime::Stop() {
  if (stopped_) return Status::Ok();
  stopped_ = true;
  if (server_) server_->Stop();  // everything received is delivered to the back-end
  if (!backend_) {
    if (view_) view_->Stop();
    return Status::Ok();
  }
  backend_->WaitIdle();
  backend_->FinishGlobalBa();  // the maps as a global BA of each whole map leaves them
  const Status results = WriteResults();
  if (view_) view_->Stop();  // browsers see the final map, then "server gone"
  backend_->Shutdown();
  return results;
}

// ---------------------------------------------------------------- live map view

Status ServerRuntime::StartView() {
  if (!options_.view) return Status::Ok();
  auto view = ViewServer::Start(*options_.view, view_model_.get(), backend_->dense(),
                                [this] { return CollectViewStats(); });
  if (!view.ok()) return view.status();
  view_ = std::move(view).value();
  return Status::Ok();
}

namespace {

// One agent's traffic from the transport's statistics (TrafficStats::ToJson).
void FillTraffic(const Json& agent, double uptime_s, double bucket_s, ViewAgentStats* stats) {
  auto num = [](const Json* j, const char* key) {
    return j && j->Get(key) ? j->Get(key)->number() : 0.0;
  };
  const Json* messages = agent.Get("messages");
  stats->bytes =
      static_cast<std::uint64_t>(num(messages ? messages->Get("keyframe") : nullptr, "bytes") +
                                 num(messages ? messages->Get("pose_update") : nullptr, "bytes"));
  stats->rate_kBps = num(&agent, "average_traffic_bytes_per_s") / 1e3;
  stats->connected = agent.Get("connected") && agent.Get("connected")->boolean();
  stats->bucket_s = bucket_s;
  // The last two minutes, one value per bucket (buckets without traffic are absent).
  constexpr int kShown = 120;
  const long last = static_cast<long>(uptime_s / bucket_s);
  stats->traffic_kBps.assign(kShown, 0.0);
  if (const Json* buckets = agent.Get("per_bucket")) {
    for (const Json& b : buckets->array()) {
      const long index = std::lround(num(&b, "t") / bucket_s) - (last - kShown + 1);
      if (index >= 0 && index < kShown)
        stats->traffic_kBps[index] = num(&b, "bytes") / 1e3 / bucket_s;
    }
  }
}

}  // namespace

ViewStats ServerRuntime::CollectViewStats() {
  ViewStats view;
  const BackendStats backend = backend_->stats();
  view.keyframes = backend.keyframes;
  if (DenseMap* dense = backend_->dense()) view.points = dense->Stats().kept_points;
  const auto primary = backend_->PrimaryMap();
  std::map<MapId, ViewMapStats> maps;
  for (MapId id : backend_->Maps()) maps[id] = {id, 0, primary && *primary == id, {}};
  const Json transport = server_ ? server_->StatsJson() : Json();
  std::map<std::string, const Json*> traffic;
  if (const Json* agents = transport.Get("agents")) {
    for (const Json& a : agents->array())
      traffic[a.Get("name") ? a.Get("name")->string() : ""] = &a;
  }
  std::map<AgentId, std::string> names;
  {
    std::lock_guard<std::mutex> lock(names_mutex_);
    names = names_;
  }
  const std::vector<AgentId> mapped = backend_->Agents();
  for (const auto& [id, name] : names) {
    ViewAgentStats a;
    a.id = id;
    a.name = name;
    // Only agents the back-end has a map for: asking about another would create its map.
    if (std::find(mapped.begin(), mapped.end(), id) != mapped.end()) {
      a.keyframes = backend_->AgentKeyframeCount(id);
      a.map = backend_->MapOf(id);
      if (a.map && maps.count(*a.map)) {
        maps[*a.map].keyframes += a.keyframes;
        maps[*a.map].agents.push_back(id);
      }
    }
    if (const auto it = traffic.find(name); it != traffic.end()) {
      FillTraffic(*it->second, transport.Get("uptime_s") ? transport.Get("uptime_s")->number() : 0,
                  transport.Get("bucket_seconds") ? transport.Get("bucket_seconds")->number() : 1.0,
                  &a);
    }
    view.agents.push_back(std::move(a));
  }
  for (auto& [id, m] : maps) view.maps.push_back(std::move(m));
  return view;
}

}  // namespace ccmd
