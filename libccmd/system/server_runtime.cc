#include "libccmd/system/server_runtime.h"

#include <algorithm>

#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/process_usage.h"
#include "libccmd/util/timer.h"

namespace ccmd {

PinholeCamera CameraFromSession(const SessionCamera& s) {
  PinholeCamera c;
  c.fx = s.fx;
  c.fy = s.fy;
  c.cx = s.cx;
  c.cy = s.cy;
  c.width = static_cast<int>(s.width);
  c.height = static_cast<int>(s.height);
  if (s.depth_scale > 0) c.depth_map_factor = s.depth_scale;
  return c;
}

SessionCamera SessionFromCamera(const PinholeCamera& c) {
  SessionCamera s;
  s.fx = c.fx;
  s.fy = c.fy;
  s.cx = c.cx;
  s.cy = c.cy;
  s.width = static_cast<std::uint32_t>(c.width);
  s.height = static_cast<std::uint32_t>(c.height);
  s.depth_scale = c.depth_map_factor;
  return s;
}

StatusOr<std::unique_ptr<ServerRuntime>> ServerRuntime::Create(const ServerRuntimeOptions& options) {
  if (options.output_dir.empty()) return InvalidArgument("the server needs an output folder");
  CCMD_RETURN_IF_ERROR(options.net.Validate());
  CCMD_RETURN_IF_ERROR(options.backend.Validate());
  CCMD_RETURN_IF_ERROR(MakeDirectories(options.output_dir));
  return std::unique_ptr<ServerRuntime>(new ServerRuntime(options));
}

ServerRuntime::~ServerRuntime() { Stop().IgnoreError(); }

Status ServerRuntime::Start() {
  CCMD_ASSIGN_OR_RETURN(backend_, Backend::Create(options_.backend));
  if (backend_->dense()) {
    SnapshotOptions snapshot;
    snapshot.folder = JoinPath(options_.output_dir, "snapshots");
    snapshot.period_s = options_.snapshot_period_s;
    snapshots_ = std::make_unique<DenseSnapshotWriter>(backend_->dense(), snapshot);
  }
  server_ = std::make_unique<Server>(options_.net, this);
  return server_->Start();
}

void ServerRuntime::OnAgentKnown(const AgentDescription& agent, bool from_journal) {
  {
    std::lock_guard<std::mutex> lock(names_mutex_);
    names_[agent.id] = agent.name;
  }
  const Status s = backend_->RegisterAgent(agent.id, agent.name, CameraFromSession(agent.camera));
  if (!s.ok()) CCMD_LOG(ERROR) << "agent " << agent.name << ": " << s.ToString();
  CCMD_LOG(INFO) << "agent " << agent.id << " '" << agent.name << "' " << (from_journal ? "restored" : "joined")
                 << " (" << DescribeCamera(agent.camera) << ")";
}

void ServerRuntime::OnAgentDisconnected(AgentId agent, const std::string& reason) {
  CCMD_LOG(INFO) << "agent " << agent << " left: " << reason;
}

void ServerRuntime::OnMessage(DeliveredMessage m) {
  // The payload passed the frame CRC and was journaled; a message that still does not parse
  // is logged and skipped (it stays in the journal for inspection).
  if (m.type == static_cast<std::uint8_t>(MessageType::kKeyframe)) {
    auto keyframe = ParseKeyframe(m.payload);
    if (keyframe.ok()) {
      backend_->SubmitKeyframe(m.agent, std::move(keyframe).value(), m.replayed ? 0.0 : m.received_time)
          .IgnoreError();
      return;
    }
    CCMD_LOG(WARNING) << "agent " << m.agent << " message " << m.seq << ": " << keyframe.status().ToString();
  } else if (m.type == static_cast<std::uint8_t>(MessageType::kPoseUpdate)) {
    auto update = ParsePoseUpdate(m.payload);
    if (update.ok()) {
      backend_->SubmitPoseUpdate(m.agent, std::move(update).value()).IgnoreError();
      return;
    }
    CCMD_LOG(WARNING) << "agent " << m.agent << " message " << m.seq << ": " << update.status().ToString();
  } else {
    CCMD_LOG(WARNING) << "agent " << m.agent << " message " << m.seq << ": unknown type " << int{m.type};
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
  Json agents;
  {
    std::lock_guard<std::mutex> lock(names_mutex_);
    for (const auto& [id, name] : names_) {
      agents[name] = Json(static_cast<int>(id.value()));
    }
  }
  j["agent_ids"] = agents;
  if (backend_ && backend_->PrimaryMap()) j["primary_map"] = static_cast<int>(backend_->PrimaryMap()->value());
  j["malformed_messages"] = malformed_messages_;
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
  if (snapshots_ && options_.snapshot_period_s > 0) {
    auto wrote = snapshots_->Tick(now);
    if (!wrote.ok()) CCMD_LOG(WARNING) << "snapshot: " << wrote.status().ToString();
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
  keep(WriteTumTrajectory(backend_->FusedTrajectory(), JoinPath(options_.output_dir, "trajectory_fused.txt"),
                          "keyframes of the primary map (world frame)"));
  for (const auto& [id, name] : names) {
    keep(WriteTumTrajectory(backend_->AgentTrajectory(id), JoinPath(options_.output_dir, "trajectory_" + name + ".txt"),
                            backend_->AgentInPrimaryMap(id) ? "keyframes, world frame (primary map)"
                                                            : "keyframes, NOT fused: the agent's own map frame"));
  }
  if (backend_->dense() && backend_->PrimaryMap()) {
    const auto dense_maps = backend_->dense()->Maps();
    if (std::find(dense_maps.begin(), dense_maps.end(), *backend_->PrimaryMap()) != dense_maps.end()) {
      keep(backend_->ExportDenseMap(JoinPath(options_.output_dir, "map.ply")));
    } else {
      CCMD_LOG(INFO) << "no RGB-D keyframe reached the primary map: no map.ply";
    }
  }
  memory_ = backend_->MemoryJson();
  keep(WriteJsonFile(StatsJson(), JoinPath(options_.output_dir, "server_stats.json")));
  return first;
}

Status ServerRuntime::Stop() {
  if (stopped_) return Status::Ok();
  stopped_ = true;
  if (server_) server_->Stop();  // everything received is delivered to the back-end
  if (!backend_) return Status::Ok();
  backend_->WaitIdle();
  const Status results = WriteResults();
  backend_->Shutdown();
  return results;
}

}  // namespace ccmd
