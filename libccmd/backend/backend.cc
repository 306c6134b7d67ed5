#include "libccmd/backend/backend.h"

#include <algorithm>
#include <cmath>

#include "libccmd/backend/ingest.h"
#include "libccmd/codec/rgbd_payload.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

Status BackendOptions::Validate() const {
  CCMD_RETURN_IF_ERROR(loops.Validate());
  if (queue_capacity < 1) return InvalidArgument("queue capacity must be >= 1");
  if (global_ba_iterations < 1) return InvalidArgument("global BA iterations must be >= 1");
  if (dense) CCMD_RETURN_IF_ERROR(dense_options.Validate());
  return Status::Ok();
}

StatusOr<std::unique_ptr<Backend>> Backend::Create(const BackendOptions& options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  auto backend = std::unique_ptr<Backend>(new Backend(options));
  if (options.dense) {
    CCMD_ASSIGN_OR_RETURN(backend->dense_, DenseMap::Create(options.dense_options));
  }
  Backend* b = backend.get();
  b->ingest_stage_.Start([b](IngestItem item) { b->Ingest(std::move(item)); });
  b->loop_stage_.Start([b](GlobalKeyframeId id) { b->DetectLoops(id); });
  b->gba_stage_.Start([b](AgentId agent) { b->RunGlobalBa(agent); });
  b->dense_stage_.Start([b](DenseTask task) { b->UpdateDense(std::move(task)); });
  return backend;
}

Backend::Backend(const BackendOptions& options)
    : options_(options), start_time_(MonotonicSeconds()),
      loop_closer_(options.loops, options.place, &maps_, start_time_),
      ingest_stage_(options.queue_capacity), loop_stage_(options.queue_capacity * 4),
      gba_stage_(1, Stage<AgentId>::Policy::kLatest), dense_stage_(options.queue_capacity * 4) {}

Backend::~Backend() { Shutdown(); }

double Backend::Now() const { return MonotonicSeconds() - start_time_; }

void Backend::Shutdown() {
  if (shut_down_) return;
  shut_down_ = true;
  // Stages drain in pipeline order, so nothing queued is lost; a global BA still waiting or
  // running is abandoned (its map is written out as it stands).
  ingest_stage_.Stop();
  loop_stage_.Stop();
  stopping_ = true;
  gba_abort_ = true;
  gba_stage_.Stop();
  dense_stage_.Stop();
}

Status Backend::RegisterAgent(AgentId agent, const std::string& name, const PinholeCamera& camera) {
  std::string why;
  if (!camera.IsValid(&why)) return InvalidArgument("agent " + name + ": " + why);
  std::lock_guard<std::mutex> lock(cameras_mutex_);
  cameras_[agent] = camera;
  names_[agent] = name;
  return Status::Ok();
}

PinholeCamera Backend::CameraOf(AgentId agent) const {
  std::lock_guard<std::mutex> lock(cameras_mutex_);
  return cameras_.at(agent);
}

Status Backend::SubmitKeyframe(AgentId agent, KeyframeMessage message) {
  IngestItem item{agent, std::make_unique<KeyframeMessage>(std::move(message)), nullptr, Now()};
  if (!ingest_stage_.Push(std::move(item))) return Unavailable("the back-end is shutting down");
  return Status::Ok();
}

Status Backend::SubmitPoseUpdate(AgentId agent, PoseUpdateMessage message) {
  IngestItem item{agent, nullptr, std::make_unique<PoseUpdateMessage>(std::move(message)), Now()};
  if (!ingest_stage_.Push(std::move(item))) return Unavailable("the back-end is shutting down");
  return Status::Ok();
}

void Backend::WaitIdle() {
  // In pipeline order: a stage counts the work an earlier one gives it before that work
  // counts as finished there.
  ingest_stage_.WaitIdle();
  loop_stage_.WaitIdle();
  gba_stage_.WaitIdle();
  dense_stage_.WaitIdle();
}

// ---------------------------------------------------------------- ingest

void Backend::Ingest(IngestItem item) {
  const AgentId agent = item.agent;
  if (const PoseUpdateMessage* pose_update = item.pose_update.get()) {
    std::vector<ServerKeyframe*> moved;
    MapManager::Guard guard = maps_.CheckOutAgent(agent);
    moved = ApplyPoseUpdates(guard.get(), agent, *pose_update);
    QueueDenseUpdates(moved, DenseTask::Kind::kUpdate);
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.pose_updates_received++;
    return;
  }
  if (!item.keyframe) return;
  KeyframeMessage& message = *item.keyframe;
  {
    std::lock_guard<std::mutex> lock(cameras_mutex_);
    if (!cameras_.count(agent)) {
      CCMD_LOG(ERROR) << "keyframe from agent " << agent.value() << " before its camera: dropped";
      return;
    }
  }
  // Decoding happens before the map is taken.
  std::optional<DecodedRgbd> rgbd;
  if (message.rgbd) {
    auto decoded = DecodeRgbdPayload(*message.rgbd);
    if (decoded.ok()) {
      rgbd = std::move(decoded).value();
    } else {
      CCMD_LOG(WARNING) << "agent " << agent.value() << " keyframe " << message.id.value()
                        << ": RGB-D payload not decodable (" << decoded.status().ToString() << "), keyframe kept";
    }
  }
  GlobalKeyframeId id{agent, message.id};
  bool added = false;
  {
    MapManager::Guard guard = maps_.CheckOutAgent(agent);
    auto keyframe = AddKeyframeMessage(guard.get(), agent, message, Pose::Identity());
    if (!keyframe.ok()) {
      CCMD_LOG(WARNING) << "agent " << agent.value() << ": " << keyframe.status().ToString();
    } else {
      added = true;
      if (rgbd) {
        (*keyframe)->rgbd_bgr = rgbd->bgr;
        (*keyframe)->rgbd_depth_mm = rgbd->depth_mm;
        (*keyframe)->rgbd_downsample = rgbd->downsample;
      }
      if (maps_.primary() && guard->id() == *maps_.primary()) QueueDenseAdds(guard.get(), {*keyframe});
    }
  }
  const double intake_ms = (Now() - item.submitted) * 1e3;
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.keyframes_received++;
    timings_.intake_ms.push_back(intake_ms);
    timings_.intake_during_gba.push_back(gba_running_);
  }
  if (added) loop_stage_.Push(id);
}

// ---------------------------------------------------------------- dense

void Backend::QueueDenseAdds(ServerMap* map, const std::vector<ServerKeyframe*>& keyframes) {
  if (!dense_) return;
  for (ServerKeyframe* kf : keyframes) {
    if (kf->in_dense || kf->rgbd_downsample == 0 || kf->rgbd_depth_mm.empty()) continue;
    DenseTask task;
    task.kind = DenseTask::Kind::kAdd;
    task.to = map->id();
    task.keyframe.id = kf->id;
    task.keyframe.T_world_cam = kf->T_map_cam;
    task.keyframe.depth_mm = kf->rgbd_depth_mm;
    task.keyframe.bgr = kf->rgbd_bgr;
    task.keyframe.camera = CameraOf(kf->id.agent).Resized(kf->rgbd_depth_mm.cols, kf->rgbd_depth_mm.rows);
    kf->in_dense = true;
    // The store keeps its own copy of the points: the server does not hold the images twice.
    kf->rgbd_bgr.release();
    kf->rgbd_depth_mm.release();
    dense_stage_.Push(std::move(task));
  }
}

void Backend::QueueDenseUpdates(const std::vector<ServerKeyframe*>& moved, DenseTask::Kind kind) {
  if (!dense_) return;
  DenseTask task;
  task.kind = kind;
  for (ServerKeyframe* kf : moved) {
    if (kf->in_dense) task.poses.push_back({kf->id, kf->T_map_cam});
  }
  if (!task.poses.empty()) dense_stage_.Push(std::move(task));
}

void Backend::UpdateDense(DenseTask task) {
  Status status;
  switch (task.kind) {
    case DenseTask::Kind::kAdd:
      status = dense_->SetAgentMap(task.keyframe.id.agent, task.to);
      if (status.ok()) status = dense_->AddKeyframe(task.keyframe);
      if (status.ok()) {
        std::lock_guard<std::mutex> lock(stats_mutex_);
        stats_.dense_keyframes++;
      }
      break;
    case DenseTask::Kind::kUpdate:
      for (const KeyframePose& p : task.poses) {
        const Status s = dense_->UpdateKeyframePose(p.id, p.T_world_cam);
        if (!s.ok()) status = s;
      }
      break;
    case DenseTask::Kind::kLoopUpdate:
      status = dense_->UpdateLoopPoses(task.poses);
      break;
    case DenseTask::Kind::kGlobalUpdate:
      status = dense_->UpdateGlobalPoses(task.poses).status();
      break;
    case DenseTask::Kind::kMergeMaps:
      status = dense_->MergeMaps(task.from, task.to, Pose::Identity());
      break;
  }
  if (!status.ok()) CCMD_LOG(WARNING) << "dense map: " << status.ToString();
  if (dense_stage_.backlog() == 0) dense_->Maintain();  // deferred re-filters when idle
}

Status Backend::ExportDenseMap(const std::string& path) {
  if (!dense_) return Unsupported("the dense map is disabled");
  const auto primary = maps_.primary();
  if (!primary) return NotFound("no map yet");
  return dense_->ExportPly(path, DenseSelection::Map(*primary));
}

// ---------------------------------------------------------------- loops

void Backend::DetectLoops(const GlobalKeyframeId& id) {
  if (auto closure = loop_closer_.Process(id, CameraOf(id.agent), /*stored=*/false)) AfterLoop(std::move(*closure));
  // Keyframes that arrived before the first vocabulary was trained are queried now, oldest
  // first, between new arrivals.
  while (loop_stage_.backlog() == 0) {
    const auto late = loop_closer_.NextLateQuery();
    if (!late) break;
    if (auto closure = loop_closer_.Process(*late, CameraOf(late->agent), /*stored=*/true)) {
      AfterLoop(std::move(*closure));
    }
  }
}

void Backend::AfterLoop(LoopClosure closure) {
  if (dense_ && closure.primary_before) {
    DenseTask merge;
    merge.kind = DenseTask::Kind::kMergeMaps;
    merge.from = *closure.primary_before;
    merge.to = closure.event.map;
    dense_stage_.Push(std::move(merge));
  }
  QueueDenseUpdates(closure.moved, DenseTask::Kind::kLoopUpdate);
  // The other map's keyframes now feed the dense map.
  QueueDenseAdds(closure.map.get(), closure.joined_primary);
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    loop_events_.push_back(closure.event);
    if (closure.event.fusion) {
      stats_.fusions++;
    } else {
      stats_.loops++;
    }
  }
  closure.map = MapManager::Guard();
  RequestGlobalBa(closure.event.query.agent);
}

// ---------------------------------------------------------------- global BA

void Backend::RequestGlobalBa(AgentId agent) {
  if (!options_.global_ba) return;
  gba_abort_ = true;  // a running global BA is outdated by the new loop
  gba_stage_.Push(agent);
}

void Backend::RunGlobalBa(AgentId agent) {
  if (stopping_) return;
  gba_abort_ = false;
  if (stopping_) return;  // Shutdown sets stopping_ before gba_abort_: no abort is lost
  const std::map<AgentId, PinholeCamera> cameras = [&] {
    std::lock_guard<std::mutex> lock(cameras_mutex_);
    return cameras_;
  }();
  const Stopwatch watch;
  gba_running_ = true;
  GlobalBaProblem problem;
  MapId map_id;
  {
    MapManager::Guard guard = maps_.CheckOutAgent(agent);
    map_id = guard->id();
    problem = BuildGlobalBa(*guard, cameras, options_.depth_noise);
  }
  BaOptions ba;
  ba.solver = BaLinearSolver::kSparseSchur;
  ba.first_iterations = options_.global_ba_iterations;
  ba.second_iterations = options_.global_ba_iterations;
  ba.abort = &gba_abort_;
  const BaSummary summary = BundleAdjust(&problem.problem, ba);
  bool applied = false;
  if (!summary.aborted) {
    MapManager::Guard guard = maps_.CheckOut(map_id);
    if (guard) {  // not fused meanwhile
      QueueDenseUpdates(ApplyGlobalBa(guard.get(), problem), DenseTask::Kind::kGlobalUpdate);
      applied = true;
    }
  }
  gba_running_ = false;
  const double seconds = watch.ElapsedSeconds();
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.global_ba_runs++;
    stats_.global_ba_aborted += !applied;
    stats_.global_ba_seconds += seconds;
    timings_.global_ba_seconds.push_back(seconds);
    timings_.global_ba_applied.push_back(applied);
  }
  CCMD_LOG(INFO) << "global BA on map " << map_id.value() << ": " << problem.keyframes.size() << " keyframes, "
                 << problem.points.size() << " points, " << summary.iterations << " iterations, " << seconds << " s"
                 << (applied ? "" : " (abandoned: newer work)");
}

// ---------------------------------------------------------------- results

bool Backend::AgentInPrimaryMap(AgentId agent) const {
  const auto map = maps_.MapOfAgent(agent);
  const auto primary = maps_.primary();
  return map && primary && *map == *primary;
}

Trajectory Backend::AgentTrajectory(AgentId agent) {
  Trajectory trajectory;
  MapManager::Guard guard = maps_.CheckOutAgent(agent);
  for (ServerKeyframe* kf : guard->AgentKeyframes(agent)) trajectory.push_back({kf->timestamp, kf->T_map_cam});
  std::sort(trajectory.begin(), trajectory.end(),
            [](const StampedPose& a, const StampedPose& b) { return a.timestamp < b.timestamp; });
  return trajectory;
}

Trajectory Backend::FusedTrajectory() {
  Trajectory trajectory;
  const auto primary = maps_.primary();
  if (!primary) return trajectory;
  MapManager::Guard guard = maps_.CheckOut(*primary);
  if (!guard) return trajectory;
  for (const auto& [id, kf] : guard->keyframes()) trajectory.push_back({kf->timestamp, kf->T_map_cam});
  std::stable_sort(trajectory.begin(), trajectory.end(),
                   [](const StampedPose& a, const StampedPose& b) { return a.timestamp < b.timestamp; });
  return trajectory;
}

namespace {

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(q * (v.size() - 1) + 0.5));
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

}  // namespace

BackendStats Backend::stats() {
  BackendStats s;
  std::vector<double> intake, during;
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    s = stats_;
    intake = timings_.intake_ms;
    for (std::size_t i = 0; i < intake.size(); ++i) {
      if (timings_.intake_during_gba[i]) during.push_back(intake[i]);
    }
  }
  s.intake_ms_median = Percentile(intake, 0.5);
  s.intake_ms_p99 = Percentile(intake, 0.99);
  s.intake_ms_max = intake.empty() ? 0 : *std::max_element(intake.begin(), intake.end());
  s.intake_during_gba_count = during.size();
  s.intake_during_gba_ms_median = Percentile(during, 0.5);
  s.intake_during_gba_ms_max = during.empty() ? 0 : *std::max_element(during.begin(), during.end());
  s.agents = maps_.Agents().size();
  s.maps = maps_.Maps().size();
  for (MapId id : maps_.Maps()) {
    MapManager::Guard guard = maps_.CheckOut(id);
    if (!guard) continue;
    s.keyframes += guard->keyframes().size();
    s.map_points += guard->num_points();
  }
  return s;
}

std::vector<LoopEvent> Backend::loop_events() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return loop_events_;
}

BackendTimings Backend::timings() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return timings_;
}

Json Backend::StatsJson() {
  const BackendStats s = stats();
  Json j;
  j["agents"] = s.agents;
  j["maps"] = s.maps;
  j["keyframes"] = s.keyframes;
  j["map_points"] = s.map_points;
  j["keyframes_received"] = s.keyframes_received;
  j["pose_updates_received"] = s.pose_updates_received;
  j["loops"] = s.loops;
  j["fusions"] = s.fusions;
  j["global_ba_runs"] = s.global_ba_runs;
  j["global_ba_abandoned"] = s.global_ba_aborted;
  j["global_ba_seconds"] = s.global_ba_seconds;
  j["dense_keyframes"] = s.dense_keyframes;
  j["intake_ms_median"] = s.intake_ms_median;
  j["intake_ms_p99"] = s.intake_ms_p99;
  j["intake_ms_max"] = s.intake_ms_max;
  j["intake_during_gba_count"] = s.intake_during_gba_count;
  j["intake_during_gba_ms_median"] = s.intake_during_gba_ms_median;
  j["intake_during_gba_ms_max"] = s.intake_during_gba_ms_max;
  Json events = Json::MakeArray();
  for (const LoopEvent& e : loop_events()) {
    Json x;
    x["time_s"] = e.server_time;
    x["query_agent"] = e.query.agent.value();
    x["query_keyframe"] = e.query.keyframe.value();
    x["candidate_agent"] = e.candidate.agent.value();
    x["candidate_keyframe"] = e.candidate.keyframe.value();
    x["inliers"] = e.inliers;
    x["fusion"] = e.fusion;
    x["map"] = e.map.value();
    events.Push(x);
  }
  j["loop_events"] = events;
  return j;
}

}  // namespace ccmd
