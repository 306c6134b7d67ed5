#include "libccmd/backend/backend.h"

#include <algorithm>
#include <cmath>
#include <set>

#include "libccmd/backend/ingest.h"
#include "libccmd/backend/map_observer.h"
#include "libccmd/codec/rgbd_payload.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/process_usage.h"
#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

// Appends a timing sample, keeping at least the most recent kMaxSamples (at most twice that).
template <typename T>
void AppendSample(std::vector<T>* samples, T value) {
  constexpr std::size_t kMax = BackendTimings::kMaxSamples;
  if (samples->size() >= 2 * kMax) samples->erase(samples->begin(), samples->begin() + kMax);
  samples->push_back(value);
}

}  // namespace

Status BackendOptions::Validate() const {
  CCMD_RETURN_IF_ERROR(loops.Validate());
  CCMD_RETURN_IF_ERROR(culling.Validate());
  if (queue_capacity < 1) return InvalidArgument("queue capacity must be >= 1");
  if (global_ba_iterations < 1) return InvalidArgument("global BA iterations must be >= 1");
  if (global_ba_max_keyframes < 10)
    return InvalidArgument("global BA window must be >= 10 keyframes");
  if (global_ba_max_observations < 1000)
    return InvalidArgument("global BA window must allow >= 1000 observations");
  if (!(global_ba_duty > 0 && global_ba_duty <= 1))
    return InvalidArgument("global BA duty must be in (0, 1]");
  if (!(idle_global_ba_seconds >= 0 && idle_global_ba_seconds <= 1e6))
    return InvalidArgument("idle global BA seconds must be in [0, 1e6] (0: never)");
  if (!(idle_loop_seconds >= 0 && idle_loop_seconds <= 1e6))
    return InvalidArgument("idle loop seconds must be in [0, 1e6] (0: never)");
  if (dense) CCMD_RETURN_IF_ERROR(dense_options.Validate());
  CCMD_RETURN_IF_ERROR(place.Validate());
  return depth_noise.Validate();
}

void BackendOptions::Describe(OptionsWriter* out) const {
  out->Nested("loops", loops);
  out->Nested("culling", culling);
  out->Add("global_ba", global_ba);
  out->Add("global_ba_iterations", global_ba_iterations);
  out->Add("global_ba_max_keyframes", global_ba_max_keyframes);
  out->Add("global_ba_max_observations", global_ba_max_observations);
  out->Add("global_ba_duty", global_ba_duty);
  out->Add("final_global_ba_max_observations", final_global_ba_max_observations);
  out->Add("idle_global_ba_seconds", idle_global_ba_seconds);
  out->Add("idle_loop_seconds", idle_loop_seconds);
  out->Nested("depth_noise", depth_noise);
  out->Add("dense", dense);
  out->Nested("dense_options", dense_options);
  out->Nested("place", place);
  out->Add("queue_capacity", queue_capacity);
}

StatusOr<std::unique_ptr<Backend>> Backend::Create(const BackendOptions& options,
                                                   MapObserver* observer) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  auto backend = std::unique_ptr<Backend>(new Backend(options));
  backend->observer_ = observer;
  if (options.dense) {
    CCMD_ASSIGN_OR_RETURN(backend->dense_, DenseMap::Create(options.dense_options));
  }
  Backend* b = backend.get();
  b->ingest_stage_.Start([b](IngestItem item) { b->Ingest(std::move(item)); });
  b->loop_stage_.Start([b](LoopTask task) {
    if (task.agent_stopped) {
      b->LoopsOfAStoppedAgent(task.keyframe.agent);
    } else {
      b->DetectLoops(task.keyframe);
    }
  });
  b->gba_stage_.Start([b](GbaRequest request) { b->RunGlobalBa(std::move(request)); });
  b->dense_stage_.Start([b](DenseTask task) { b->UpdateDense(std::move(task)); });
  return backend;
}

Backend::Backend(const BackendOptions& options)
    : options_(options),
      start_time_(MonotonicSeconds()),
      loop_closer_(options.loops, options.place, &maps_, start_time_),
      culler_(options.culling),
      depth_noise_(options.depth_noise),
      ingest_stage_(options.queue_capacity),
      loop_stage_(options.queue_capacity * 4),
      gba_stage_(1, Stage<GbaRequest>::Policy::kLatest),
      dense_stage_(options.queue_capacity * 4) {}

Backend::~Backend() { Shutdown(); }

double Backend::Now() const { return MonotonicSeconds() - start_time_; }

void Backend::Shutdown() {
  if (shut_down_) return;
  shut_down_ = true;
  // Stages drain in pipeline order, so nothing queued is lost; a global BA still waiting or
  // running is abandoned (its map is written out as it stands).
  ingest_stage_.Stop();
  loop_stage_.Stop();
  {
    std::lock_guard<std::mutex> lock(gba_turn_mutex_);
    stopping_ = true;
  }
  gba_turn_cv_.notify_all();
  gba_abort_ = true;
  gba_stage_.Stop();
  dense_stage_.Stop();
}

Status Backend::RegisterAgent(AgentId agent, const std::string& name, const PinholeCamera& camera,
                              const std::optional<DepthNoise>& depth_noise,
                              const Pose& T_color_trajectory) {
  CCMD_RETURN_IF_ERROR(camera.Validate().WithContext("agent " + name));
  if (depth_noise) CCMD_RETURN_IF_ERROR(depth_noise->Validate().WithContext("agent " + name));
  std::lock_guard<std::mutex> lock(cameras_mutex_);
  cameras_[agent] = camera;
  if (depth_noise) {
    depth_noise_.agents[agent] = *depth_noise;
  } else {
    depth_noise_.agents.erase(agent);
  }
  names_[agent] = name;
  trajectory_cameras_[agent] = T_color_trajectory;
  if (observer_) observer_->OnAgent(agent, name);
  return Status::Ok();
}

PinholeCamera Backend::CameraOf(AgentId agent) const {
  std::lock_guard<std::mutex> lock(cameras_mutex_);
  return cameras_.at(agent);
}

DepthNoise Backend::DepthNoiseOf(AgentId agent) const {
  std::lock_guard<std::mutex> lock(cameras_mutex_);
  return depth_noise_.Of(agent);
}

Status Backend::SubmitKeyframe(AgentId agent, KeyframeMessage message, double arrived_s) {
  IngestItem item{agent, std::make_unique<KeyframeMessage>(std::move(message)), nullptr,
                  arrived_s > 0 ? arrived_s : MonotonicSeconds()};
  if (!ingest_stage_.Push(std::move(item))) return Unavailable("the back-end is shutting down");
  return Status::Ok();
}

Status Backend::SubmitPoseUpdate(AgentId agent, PoseUpdateMessage message, double arrived_s) {
  IngestItem item{agent, nullptr, std::make_unique<PoseUpdateMessage>(std::move(message)),
                  arrived_s > 0 ? arrived_s : MonotonicSeconds()};
  if (!ingest_stage_.Push(std::move(item))) return Unavailable("the back-end is shutting down");
  return Status::Ok();
}

Status Backend::SubmitSessionEnded(AgentId agent) {
  if (!ingest_stage_.Push(IngestItem{agent, nullptr, nullptr, MonotonicSeconds()}))
    return Unavailable("the back-end is shutting down");
  return Status::Ok();
}

void Backend::NotifyPoses(PoseSource source, MapId map, const std::vector<ServerKeyframe*>& moved,
                          double arrived_s) {
  if (!observer_ || moved.empty()) return;
  std::vector<KeyframePose> poses;
  poses.reserve(moved.size());
  for (const ServerKeyframe* kf : moved) {
    poses.push_back({kf->id, kf->T_map_cam});
    for (const CulledKeyframe& f : kf->followers) poses.push_back({f.id, kf->FollowerPose(f)});
  }
  observer_->OnPoses(source, map, poses, arrived_s);
}

void Backend::WaitIdle() {
  // In pipeline order: a stage counts the work an earlier one gives it before that work
  // counts as finished there.
  ingest_stage_.WaitIdle();
  loop_stage_.WaitIdle();
  gba_stage_.WaitIdle();
  dense_stage_.WaitIdle();
}

void Backend::FinishGlobalBa() {
  if (!options_.global_ba || options_.final_global_ba_max_observations == 0) return;
  WaitIdle();
  std::set<MapId> done;
  for (const AgentId agent : maps_.Agents()) {
    const std::optional<MapId> map = maps_.MapOfAgent(agent);
    if (!map || !done.insert(*map).second) continue;
    {
      std::lock_guard<std::mutex> lock(gba_counts_mutex_);
      if (gba_requested_[*map] <= gba_whole_map_[*map]) continue;
    }
    // One at a time: a request still waiting in the stage is replaced by a newer one.
    GbaRequest request;
    request.agent = agent;
    request.reason = GbaRequest::Reason::kFinal;
    gba_stage_.Push(std::move(request));
    WaitIdle();
  }
}

void Backend::OptimiseIdleMaps() {
  if (!options_.global_ba || options_.final_global_ba_max_observations == 0 ||
      options_.idle_global_ba_seconds <= 0 || stopping_)
    return;
  // Loops still being looked for would ask for their own run.
  if (loop_stage_.busy() || loop_stage_.backlog() > 0) return;
  const double now = Now();
  std::map<MapId, AgentId> maps;  // each map, by one of its agents
  std::set<MapId> busy;           // an agent of it sent a keyframe lately
  {
    std::lock_guard<std::mutex> lock(gba_counts_mutex_);
    for (const auto& [agent, last] : last_keyframe_at_) {
      const std::optional<MapId> map = maps_.MapOfAgent(agent);
      if (!map) continue;
      if (now - last < options_.idle_global_ba_seconds) busy.insert(*map);
      maps.emplace(*map, agent);
    }
    for (const auto& [map, agent] : maps) {
      const std::uint64_t requested = gba_requested_[map];
      if (busy.count(map) || requested <= gba_whole_map_[map] || requested <= gba_idle_queued_[map])
        continue;
      GbaRequest request;
      request.agent = agent;
      request.reason = GbaRequest::Reason::kIdle;
      if (gba_stage_.PushIfIdle(std::move(request))) gba_idle_queued_[map] = requested;
      return;  // one at a time: the stage is busy now, or was already
    }
  }
}

void Backend::ConfirmIdleAgentsLoops() {
  if (options_.idle_loop_seconds <= 0 || stopping_) return;
  const double now = Now();
  std::vector<AgentId> idle;
  {
    std::lock_guard<std::mutex> lock(gba_counts_mutex_);
    for (const auto& [agent, last] : last_keyframe_at_) {
      if (now - last < options_.idle_loop_seconds) continue;
      const auto checked = idle_loops_checked_.find(agent);
      if (checked != idle_loops_checked_.end() && checked->second == last) continue;
      idle_loops_checked_[agent] = last;
      idle.push_back(agent);
    }
  }
  for (const AgentId agent : idle) {
    LoopTask task;
    task.keyframe.agent = agent;
    task.agent_stopped = true;
    loop_stage_.Push(task);
  }
}

// ---------------------------------------------------------------- ingest

void Backend::Ingest(IngestItem item) {
  if (item.pose_update) {
    IngestPoseUpdate(item.agent, *item.pose_update, item.arrived);
  } else if (item.keyframe) {
    IngestKeyframe(item.agent, std::move(*item.keyframe), item.arrived);
  } else {
    LoopTask task;
    task.keyframe.agent = item.agent;
    task.agent_stopped = true;
    loop_stage_.Push(task);
  }
}

void Backend::IngestPoseUpdate(AgentId agent, const PoseUpdateMessage& update, double arrived) {
  MapManager::Guard guard = maps_.CheckOutAgent(agent);
  const std::vector<ServerKeyframe*> moved = ApplyPoseUpdates(guard.get(), agent, update);
  NotifyPoses(PoseSource::kAgent, guard->id(), moved, arrived);
  QueueDenseUpdates(moved, DenseTask::Kind::kUpdate);
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.pose_updates_received++;
  stats_.pose_updates_of_culled += update.entries.size() - moved.size();
}

void Backend::IngestKeyframe(AgentId agent, KeyframeMessage message, double arrived) {
  {
    std::lock_guard<std::mutex> lock(cameras_mutex_);
    if (!cameras_.count(agent)) {
      CCMD_LOG(ERROR) << "keyframe from agent " << agent.value() << " before its camera: dropped";
      return;
    }
  }
  const GlobalKeyframeId id{agent, message.id};
  {
    std::lock_guard<std::mutex> lock(gba_counts_mutex_);
    last_keyframe_at_[agent] = Now();
  }
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    RecordArrival({id, KeyframeArrival::Stage::kReceived, WallSeconds(), false});
  }
  bool added = false;
  {
    MapManager::Guard guard = maps_.CheckOutAgent(agent);
    auto keyframe = AddKeyframeMessage(guard.get(), agent, message, Pose::Identity());
    if (!keyframe.ok()) {
      CCMD_LOG(WARNING) << "agent " << agent.value() << ": " << keyframe.status().ToString();
    } else {
      added = true;
      // The coded images stay coded until the dense stage uses them; without a dense map
      // they are not kept at all.
      if (dense_ && message.rgbd)
        (*keyframe)->rgbd = std::make_shared<const RgbdPayload>(std::move(*message.rgbd));
      const bool primary = maps_.primary() && guard->id() == *maps_.primary();
      if (observer_)
        observer_->OnKeyframe(id, guard->id(), (*keyframe)->T_map_cam, arrived, primary);
      if (primary) QueueDenseAdds(guard.get(), {*keyframe}, arrived - start_time_);
      // A restart in an almost empty map leaves the few keyframes before it unplaced.
      std::vector<GlobalKeyframeId> unplaced;
      if (!guard->Placed(**keyframe)) unplaced.push_back(id);
      if (message.restart) RemoveUnplacedFromDense(guard.get(), id, &unplaced);
      if (observer_ && !unplaced.empty()) observer_->OnPlacement(guard->id(), unplaced, false);
      // Past the young map's size no restart keeps keyframes apart: what QueueDenseAdds kept
      // of the first keyframes' coded images goes (those kept apart keep theirs for a loop).
      if (guard->keyframes().size() == kYoungSegmentKeyframes) {
        for (const auto& [kid, kf] : guard->keyframes()) {
          if (kf->in_dense) kf->rgbd.reset();
          for (CulledKeyframe& f : kf->followers) {
            if (f.in_dense) f.rgbd.reset();
          }
        }
      }
    }
  }
  const double now = Now();
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.keyframes_received++;
    stats_.segments_restarted += added && message.restart;
    AppendSample(&timings_.intake_ms, (now - (arrived - start_time_)) * 1e3);
    AppendSample(&timings_.intake_at_s, now);
    AppendSample(&timings_.intake_during_gba, static_cast<char>(gba_running_.load()));
  }
  if (added) loop_stage_.Push(LoopTask{id});
}

void Backend::RemoveUnplacedFromDense(ServerMap* map, const GlobalKeyframeId& restart,
                                      std::vector<GlobalKeyframeId>* unplaced) {
  const auto remove_from_dense = [&](const GlobalKeyframeId& k, bool* in_dense) {
    if (!dense_ || !*in_dense) return;
    *in_dense = false;
    DenseTask task;
    task.kind = DenseTask::Kind::kRemove;
    task.keyframe = k;
    dense_stage_.Push(std::move(task));
  };
  for (const auto& [kid, kf] : map->keyframes()) {
    if (map->Placed(*kf) || kid == restart) continue;
    unplaced->push_back(kid);
    remove_from_dense(kid, &kf->in_dense);
    for (CulledKeyframe& f : kf->followers) {
      unplaced->push_back(f.id);
      remove_from_dense(f.id, &f.in_dense);
    }
  }
}

// ---------------------------------------------------------------- dense

void Backend::QueueDenseAdds(ServerMap* map, const std::vector<ServerKeyframe*>& keyframes,
                             double received) {
  if (!dense_) return;
  // The dense map keeps its own copy of the points, so the coded images go with the task;
  // in a map too young for a restart to place its new segment against them, a restart keeps
  // these keyframes apart (they leave the dense map), and a loop may place them again later:
  // their coded images stay until the map has grown past that (AddKeyframe).
  const bool keep_coded = map->keyframes().size() < kYoungSegmentKeyframes;
  const auto add = [&](const GlobalKeyframeId& id, const Pose& T_map_cam,
                       std::shared_ptr<const RgbdPayload>* rgbd, bool* in_dense) {
    if (*in_dense || !*rgbd) return;
    DenseTask task;
    task.kind = DenseTask::Kind::kAdd;
    task.to = map->id();
    task.keyframe = id;
    task.T_world_cam = T_map_cam;
    task.rgbd = keep_coded ? *rgbd : std::move(*rgbd);
    task.camera = CameraOf(id.agent);
    task.received = received;
    *in_dense = true;
    dense_stage_.Push(std::move(task));
  };
  for (ServerKeyframe* kf : keyframes) {
    if (!map->Placed(*kf)) continue;
    add(kf->id, kf->T_map_cam, &kf->rgbd, &kf->in_dense);
    for (CulledKeyframe& f : kf->followers) add(f.id, kf->FollowerPose(f), &f.rgbd, &f.in_dense);
  }
}

void Backend::QueueDenseUpdates(const std::vector<ServerKeyframe*>& moved, DenseTask::Kind kind) {
  if (!dense_) return;
  DenseTask task;
  task.kind = kind;
  for (const ServerKeyframe* kf : moved) {
    if (kf->in_dense) task.poses.push_back({kf->id, kf->T_map_cam});
    for (const CulledKeyframe& f : kf->followers) {
      if (f.in_dense) task.poses.push_back({f.id, kf->FollowerPose(f)});
    }
  }
  if (!task.poses.empty()) dense_stage_.Push(std::move(task));
}

void Backend::UpdateDense(DenseTask task) {
  Status status;
  switch (task.kind) {
    case DenseTask::Kind::kAdd:
      status = AddToDense(task);
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
    case DenseTask::Kind::kRemove:
      status = dense_->RemoveKeyframe(task.keyframe);
      // Released already: it held no point.
      if (status.code() == StatusCode::kNotFound) status = Status::Ok();
      break;
  }
  if (!status.ok()) CCMD_LOG(WARNING) << "dense map: " << status.ToString();
  if (observer_) {
    const std::vector<GlobalKeyframeId> released = dense_->TakeReleased();
    if (!released.empty()) observer_->OnDenseReleased(released);
  }
  if (dense_stage_.backlog() == 0) {
    dense_->Maintain();  // deferred re-filters when idle
    // Keyframes that left the window freed their full clouds: give the pages back now and then.
    if (Now() - dense_trimmed_ > 10) {
      dense_trimmed_ = Now();
      ReleaseFreeMemory();
    }
  }
}

Status Backend::AddToDense(const DenseTask& task) {
  auto decoded = DecodeRgbdPayload(*task.rgbd);
  if (!decoded.ok()) {
    return decoded.status().WithContext("agent " + std::to_string(task.keyframe.agent.value()) +
                                        " keyframe " +
                                        std::to_string(task.keyframe.keyframe.value()) +
                                        ": RGB-D payload not decodable, keyframe kept without it");
  }
  DenseKeyframe keyframe;
  keyframe.id = task.keyframe;
  keyframe.T_world_cam = task.T_world_cam;
  keyframe.depth_mm = decoded->depth_mm;
  keyframe.bgr = decoded->bgr;
  keyframe.camera = task.camera.Resized(decoded->depth_mm.cols, decoded->depth_mm.rows);
  CCMD_RETURN_IF_ERROR(dense_->SetAgentMap(task.keyframe.agent, task.to));
  CCMD_RETURN_IF_ERROR(dense_->AddKeyframe(keyframe));
  if (observer_) observer_->OnDenseKeyframe(keyframe.id, task.to, keyframe.T_world_cam);
  const double now = Now();
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.dense_keyframes++;
  // Without a receipt time the keyframe came into the primary map with its map's fusion.
  RecordArrival({keyframe.id, KeyframeArrival::Stage::kDense, WallSeconds(), task.received < 0});
  if (task.received >= 0) {
    AppendSample(&timings_.dense_ms, (now - task.received) * 1e3);
    AppendSample(&timings_.dense_at_s, now);
  }
  return Status::Ok();
}

Status Backend::ExportDenseMap(const std::string& path) {
  if (!dense_) return Unsupported("the dense map is disabled");
  const auto primary = maps_.primary();
  if (!primary) return NotFound("no map yet");
  const auto transient = LockLargeTransient();
  // At shutdown (WriteResults): no agent waits for the dense map, so the export may hold its
  // lock while it writes and take less memory.
  return dense_->ExportPly(path, DenseSelection::Map(*primary), DenseFilter::kGlobal,
                           DenseExportMode::kStreamed);
}

// ---------------------------------------------------------------- loops

void Backend::DetectLoops(const GlobalKeyframeId& id) {
  if (auto closure =
          loop_closer_.Process(id, CameraOf(id.agent), DepthNoiseOf(id.agent), /*stored=*/false))
    AfterLoop(std::move(*closure));
  if (const auto old = culler_.Arrived(id)) CullIfRedundant(*old);
  // Measuring the index visits every word's list: now and then is enough.
  if (id.keyframe.value() % 32 == 0) place_bytes_ = loop_closer_.place().MemoryBytes();
  // Keyframes that arrived before the first vocabulary was trained are queried now, oldest
  // first, between new arrivals.
  while (loop_stage_.backlog() == 0) {
    const auto late = loop_closer_.NextLateQuery();
    if (!late) break;
    if (auto closure = loop_closer_.Process(*late, CameraOf(late->agent), DepthNoiseOf(late->agent),
                                            /*stored=*/true)) {
      AfterLoop(std::move(*closure));
    }
  }
}

void Backend::LoopsOfAStoppedAgent(AgentId agent) {
  if (auto closure = loop_closer_.AgentStopped(
          agent, [this](AgentId a) { return CameraOf(a); },
          [this](AgentId a) { return DepthNoiseOf(a); }))
    AfterLoop(std::move(*closure));
}

void Backend::CullIfRedundant(const GlobalKeyframeId& id) {
  const std::map<AgentId, PinholeCamera> cameras = [&] {
    std::lock_guard<std::mutex> lock(cameras_mutex_);
    return cameras_;
  }();
  const auto camera_of = [&](AgentId agent) -> const PinholeCamera* {
    const auto it = cameras.find(agent);
    return it == cameras.end() ? nullptr : &it->second;
  };
  {
    MapManager::Guard guard = maps_.CheckOutAgent(id.agent);
    const bool culled = culler_.Check(guard.get(), id, camera_of, [&](const GlobalKeyframeId& k) {
      return loop_closer_.Forget(k);
    });
    if (culled && observer_) observer_->OnCulled(guard->id(), id);
  }
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.culling_checked = culler_.stats().checked;
  stats_.keyframes_culled = culler_.stats().culled;
  stats_.culled_points = culler_.stats().points_removed;
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
  if (observer_) observer_->OnLoop(closure.event);
  if (observer_ && !closure.placed.empty())
    observer_->OnPlacement(closure.event.map, closure.placed, true);
  if (observer_ && !closure.unplaced.empty())
    observer_->OnPlacement(closure.event.map, closure.unplaced, false);
  NotifyPoses(closure.event.fusion ? PoseSource::kFusion : PoseSource::kLoop, closure.event.map,
              closure.moved, MonotonicSeconds());
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    AppendSample(&loop_events_, closure.event);
    if (closure.event.fusion) {
      stats_.fusions++;
    } else if (closure.event.already_closed) {
      stats_.loops_already_closed++;
    } else {
      stats_.loops++;
    }
    stats_.segments_placed += closure.event.placed_segment;
    stats_.loops_at_agent_stop += closure.event.agent_stopped;
  }
  closure.map = MapManager::Guard();
  // A loop the map already agreed with corrected nothing: there is nothing to optimise.
  if (!closure.event.already_closed) {
    RequestGlobalBa({closure.event.query.agent,
                     {closure.event.query, closure.event.candidate},
                     closure.event.fusion});
  }
}

// ---------------------------------------------------------------- global BA

void Backend::RequestGlobalBa(GbaRequest request) {
  if (!options_.global_ba) return;
  // A running global BA of the whole map the loop is in is outdated by it; a windowed one
  // stays valid, and so does a run of another map, unless a fusion takes its map away.
  bool abort = request.fusion;
  if (const std::optional<MapId> map = maps_.MapOfAgent(request.agent)) {
    std::lock_guard<std::mutex> lock(gba_counts_mutex_);
    ++gba_requested_[*map];
    abort = abort || (!gba_windowed_ && gba_running_map_ == map);
  }
  if (abort) gba_abort_ = true;
  gba_stage_.Push(std::move(request));
}

void Backend::WaitForGbaTurn() {
  std::unique_lock<std::mutex> lock(gba_turn_mutex_);
  const double wait_s = gba_next_start_ - Now();
  if (wait_s <= 0) return;
  gba_turn_cv_.wait_for(lock, std::chrono::duration<double>(wait_s),
                        [&] { return stopping_.load(); });
}

bool Backend::WholeMapBaFits(const ServerMap& map, GbaRequest::Reason reason) {
  const bool final = reason == GbaRequest::Reason::kFinal;
  const std::size_t observations = CountGlobalBaObservations(map);
  if (observations > options_.final_global_ba_max_observations) {
    CCMD_LOG(INFO) << "map " << map.id().value()
                   << (final ? " is written as its last global BA left it: "
                             : " keeps its last global BA's result while idle: ")
                   << observations << " observations, more than a whole-map run takes ("
                   << options_.final_global_ba_max_observations << ")";
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.global_ba_final_skipped += final;
    return false;
  }
  CCMD_LOG(INFO) << (final ? "final" : "idle") << " global BA of map " << map.id().value() << ": "
                 << map.keyframes().size() << " keyframes, " << observations << " observations";
  return true;
}

std::optional<GlobalBaProblem> Backend::BuildGlobalBaProblem(const GbaRequest& request,
                                                             bool windowed, MapId* map_id,
                                                             std::uint64_t* loops_in_problem) {
  std::map<AgentId, PinholeCamera> cameras;
  AgentDepthNoise depth_noise;
  {
    std::lock_guard<std::mutex> lock(cameras_mutex_);
    cameras = cameras_;
    depth_noise = depth_noise_;
  }
  MapManager::Guard guard = maps_.CheckOutAgent(request.agent);
  *map_id = guard->id();
  if (request.reason != GbaRequest::Reason::kLoop && !WholeMapBaFits(*guard, request.reason))
    return std::nullopt;
  {
    // A loop is in the map before it asks for a global BA, and not while it is checked out:
    // a request counted after this abandons the run (RequestGlobalBa).
    std::lock_guard<std::mutex> lock(gba_counts_mutex_);
    *loops_in_problem = gba_requested_[*map_id];
    gba_running_map_ = *map_id;
  }
  if (!windowed) return BuildGlobalBa(*guard, cameras, depth_noise);
  const std::set<GlobalKeyframeId> window =
      SelectGlobalBaWindow(*guard, request.around, options_.global_ba_max_keyframes,
                           options_.global_ba_max_observations);
  return BuildGlobalBa(*guard, cameras, depth_noise, &window);
}

void Backend::RunGlobalBa(GbaRequest request) {
  if (stopping_) return;
  gba_abort_ = false;
  if (stopping_) return;  // Shutdown sets stopping_ before gba_abort_: no abort is lost
  const bool windowed = [&] {
    MapManager::Guard guard = maps_.CheckOutAgent(request.agent);
    return request.reason == GbaRequest::Reason::kLoop &&
           static_cast<int>(guard->keyframes().size()) > options_.global_ba_max_keyframes;
  }();
  if (windowed) WaitForGbaTurn();
  if (stopping_) return;
  gba_windowed_ = windowed;
  const Stopwatch watch;
  gba_running_ = true;
  MapId map_id;
  std::uint64_t loops_in_problem = 0;  // the map's requests whose loops the problem holds
  std::optional<GlobalBaProblem> built =
      BuildGlobalBaProblem(request, windowed, &map_id, &loops_in_problem);
  if (!built) {
    gba_running_ = false;
    return;
  }
  GlobalBaProblem& problem = *built;
  BaOptions ba;
  ba.solver = BaLinearSolver::kSparseSchur;
  ba.first_iterations = options_.global_ba_iterations;
  ba.second_iterations = options_.global_ba_iterations;
  ba.abort = &gba_abort_;
  const BaSummary summary = [&] {
    const auto transient = LockLargeTransient();
    return BundleAdjust(&problem.problem, ba);
  }();
  bool applied = false;
  if (!summary.aborted) {
    MapManager::Guard guard = maps_.CheckOut(map_id);
    if (guard) {  // not fused meanwhile
      const std::vector<ServerKeyframe*> moved = ApplyGlobalBa(guard.get(), problem);
      NotifyPoses(PoseSource::kGlobalBa, map_id, moved, MonotonicSeconds());
      QueueDenseUpdates(moved, DenseTask::Kind::kGlobalUpdate);
      applied = true;
    }
  }
  {
    std::lock_guard<std::mutex> lock(gba_counts_mutex_);
    if (applied && !windowed) {
      std::uint64_t& whole = gba_whole_map_[map_id];
      whole = std::max(whole, loops_in_problem);
    }
    gba_running_map_.reset();
  }
  gba_running_ = false;
  gba_windowed_ = false;
  const double seconds = watch.ElapsedSeconds();
  // A windowed run is followed by a pause that keeps it to its share of the time.
  if (windowed) gba_next_start_ = Now() + seconds * (1 / options_.global_ba_duty - 1);
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.global_ba_runs++;
    stats_.global_ba_windowed += windowed;
    stats_.global_ba_final += request.reason == GbaRequest::Reason::kFinal && applied;
    stats_.global_ba_idle += request.reason == GbaRequest::Reason::kIdle && applied;
    stats_.global_ba_aborted += !applied;
    stats_.global_ba_seconds += seconds;
    AppendSample(&timings_.global_ba_seconds, seconds);
    AppendSample(&timings_.global_ba_applied, static_cast<char>(applied));
  }
  ReleaseFreeMemory();  // the solver's workspace
  CCMD_LOG(INFO) << "global BA on map " << map_id.value()
                 << (windowed                                       ? " (window)"
                     : request.reason == GbaRequest::Reason::kFinal ? " (final)"
                     : request.reason == GbaRequest::Reason::kIdle  ? " (idle)"
                                                                    : "")
                 << ": " << problem.keyframes.size() << " keyframes, " << problem.points.size()
                 << " points, " << problem.problem.observations.size() << " observations, "
                 << summary.iterations << " iterations, " << seconds << " s"
                 << (applied ? "" : " (abandoned: newer work)");
}

// ---------------------------------------------------------------- results

bool Backend::AgentInPrimaryMap(AgentId agent) const {
  const auto map = maps_.MapOfAgent(agent);
  const auto primary = maps_.primary();
  return map && primary && *map == *primary;
}

Pose Backend::TrajectoryCameraOf(AgentId agent) const {
  std::lock_guard<std::mutex> lock(cameras_mutex_);
  const auto it = trajectory_cameras_.find(agent);
  return it == trajectory_cameras_.end() ? Pose::Identity() : it->second;
}

Trajectory Backend::AgentTrajectory(AgentId agent) {
  Trajectory trajectory;
  const Pose T_color_trajectory = TrajectoryCameraOf(agent);
  MapManager::Guard guard = maps_.CheckOutAgent(agent);
  for (const ServerMap::KeyframeSample& kf : guard->AllKeyframes(agent)) {
    if (kf.placed) trajectory.push_back({kf.timestamp, kf.T_map_cam * T_color_trajectory});
  }
  std::sort(trajectory.begin(), trajectory.end(),
            [](const StampedPose& a, const StampedPose& b) { return a.timestamp < b.timestamp; });
  return trajectory;
}

std::size_t Backend::AgentKeyframeCount(AgentId agent) {
  MapManager::Guard guard = maps_.CheckOutAgent(agent);
  return guard->CountPlacedKeyframes(agent);
}

Trajectory Backend::FusedTrajectory() {
  Trajectory trajectory;
  const auto primary = maps_.primary();
  if (!primary) return trajectory;
  MapManager::Guard guard = maps_.CheckOut(*primary);
  if (!guard) return trajectory;
  std::map<AgentId, Pose> trajectory_cameras;
  {
    std::lock_guard<std::mutex> lock(cameras_mutex_);
    trajectory_cameras = trajectory_cameras_;
  }
  for (const ServerMap::KeyframeSample& kf : guard->AllKeyframes()) {
    if (!kf.placed) continue;
    const auto camera = trajectory_cameras.find(kf.id.agent);
    trajectory.push_back({kf.timestamp, camera == trajectory_cameras.end()
                                            ? kf.T_map_cam
                                            : kf.T_map_cam * camera->second});
  }
  // Ties in time stay in id order.
  std::stable_sort(
      trajectory.begin(), trajectory.end(),
      [](const StampedPose& a, const StampedPose& b) { return a.timestamp < b.timestamp; });
  return trajectory;
}

}  // namespace ccmd
