#include "libccmd/backend/backend.h"

#include <algorithm>
#include <cmath>

#include "libccmd/backend/ingest.h"
#include "libccmd/backend/map_observer.h"
#include "libccmd/codec/rgbd_payload.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

Status BackendOptions::Validate() const {
  if (loop_candidates < 1) return InvalidArgument("loop candidates must be >= 1");
  if (loop_consistency < 1) return InvalidArgument("loop consistency must be >= 1");
  if (verification.min_inliers < 10) return InvalidArgument("loop min inliers must be >= 10");
  if (queue_capacity < 1) return InvalidArgument("queue capacity must be >= 1");
  if (global_ba_iterations < 1) return InvalidArgument("global BA iterations must be >= 1");
  if (dense) CCMD_RETURN_IF_ERROR(dense_options.Validate());
  return Status::Ok();
}

StatusOr<std::unique_ptr<Backend>> Backend::Create(const BackendOptions& options, MapObserver* observer) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  auto backend = std::unique_ptr<Backend>(new Backend(options));
  backend->observer_ = observer;
  if (options.dense) {
    CCMD_ASSIGN_OR_RETURN(backend->dense_, DenseMap::Create(options.dense_options));
  }
  backend->ingest_thread_ = std::thread([b = backend.get()] { b->IngestLoop(); });
  backend->loop_thread_ = std::thread([b = backend.get()] { b->LoopDetectionLoop(); });
  backend->gba_thread_ = std::thread([b = backend.get()] { b->GlobalBaLoop(); });
  backend->dense_thread_ = std::thread([b = backend.get()] { b->DenseLoop(); });
  return backend;
}

Backend::Backend(const BackendOptions& options)
    : options_(options), place_(options.place), start_time_(MonotonicSeconds()),
      ingest_queue_(options.queue_capacity), loop_queue_(options.queue_capacity * 4),
      dense_queue_(options.queue_capacity * 4) {}

Backend::~Backend() { Shutdown(); }

double Backend::Now() const { return MonotonicSeconds() - start_time_; }

void Backend::Shutdown() {
  if (shut_down_) return;
  shut_down_ = true;
  // Stages drain in pipeline order, so nothing queued is lost.
  ingest_queue_.Close();
  if (ingest_thread_.joinable()) ingest_thread_.join();
  loop_queue_.Close();
  if (loop_thread_.joinable()) loop_thread_.join();
  {
    std::lock_guard<std::mutex> lock(gba_mutex_);
    gba_stop_ = true;
  }
  gba_abort_ = true;
  gba_cv_.notify_all();
  if (gba_thread_.joinable()) gba_thread_.join();
  dense_queue_.Close();
  if (dense_thread_.joinable()) dense_thread_.join();
}

Status Backend::RegisterAgent(AgentId agent, const std::string& name, const PinholeCamera& camera) {
  CCMD_RETURN_IF_ERROR(camera.Validate().WithContext("agent " + name));
  std::lock_guard<std::mutex> lock(cameras_mutex_);
  cameras_[agent] = camera;
  names_[agent] = name;
  if (observer_) observer_->OnAgent(agent, name);
  return Status::Ok();
}

Status Backend::SubmitKeyframe(AgentId agent, KeyframeMessage message, double arrived_s) {
  {
    std::lock_guard<std::mutex> lock(work_mutex_);
    ++outstanding_;
  }
  IngestItem item{agent, std::make_unique<KeyframeMessage>(std::move(message)), nullptr, Now(),
                  arrived_s > 0 ? arrived_s : MonotonicSeconds()};
  if (!ingest_queue_.Push(std::move(item))) {
    FinishedWork();
    return Unavailable("the back-end is shutting down");
  }
  return Status::Ok();
}

Status Backend::SubmitPoseUpdate(AgentId agent, PoseUpdateMessage message, double arrived_s) {
  {
    std::lock_guard<std::mutex> lock(work_mutex_);
    ++outstanding_;
  }
  IngestItem item{agent, nullptr, std::make_unique<PoseUpdateMessage>(std::move(message)), Now(),
                  arrived_s > 0 ? arrived_s : MonotonicSeconds()};
  if (!ingest_queue_.Push(std::move(item))) {
    FinishedWork();
    return Unavailable("the back-end is shutting down");
  }
  return Status::Ok();
}

void Backend::NotifyPoses(PoseSource source, MapId map, const std::vector<ServerKeyframe*>& moved,
                          double arrived_s) {
  if (!observer_ || moved.empty()) return;
  std::vector<KeyframePose> poses;
  poses.reserve(moved.size());
  for (const ServerKeyframe* kf : moved) poses.push_back({kf->id, kf->T_map_cam});
  observer_->OnPoses(source, map, poses, arrived_s);
}

void Backend::FinishedWork() {
  std::lock_guard<std::mutex> lock(work_mutex_);
  --outstanding_;
  work_cv_.notify_all();
}

void Backend::WaitIdle() {
  std::unique_lock<std::mutex> lock(work_mutex_);
  work_cv_.wait(lock, [&] { return outstanding_ <= 0; });
}

// ---------------------------------------------------------------- ingest

void Backend::IngestLoop() {
  while (auto item = ingest_queue_.Pop()) {
    Ingest(std::move(*item));
    FinishedWork();
  }
}

void Backend::Ingest(IngestItem item) {
  const AgentId agent = item.agent;
  if (const PoseUpdateMessage* pose_update = item.pose_update.get()) {
    std::vector<ServerKeyframe*> moved;
    MapManager::Guard guard = maps_.CheckOutAgent(agent);
    moved = ApplyPoseUpdates(guard.get(), agent, *pose_update);
    NotifyPoses(PoseSource::kAgent, guard->id(), moved, item.arrived);
    QueueDenseUpdates(moved, DenseTask::Kind::kUpdate);
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.pose_updates_received++;
    return;
  }
  if (!item.keyframe) return;
  KeyframeMessage& message = *item.keyframe;
  PinholeCamera camera;
  {
    std::lock_guard<std::mutex> lock(cameras_mutex_);
    const auto it = cameras_.find(agent);
    if (it == cameras_.end()) {
      CCMD_LOG(ERROR) << "keyframe from agent " << agent.value() << " before its camera: dropped";
      return;
    }
    camera = it->second;
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
      const bool primary = maps_.primary() && guard->id() == *maps_.primary();
      if (observer_) observer_->OnKeyframe(id, guard->id(), (*keyframe)->T_map_cam, item.arrived, primary);
      if (rgbd) {
        (*keyframe)->rgbd_bgr = rgbd->bgr;
        (*keyframe)->rgbd_depth_mm = rgbd->depth_mm;
        (*keyframe)->rgbd_downsample = rgbd->downsample;
      }
      if (primary) QueueDenseAdds(guard.get(), {*keyframe});
    }
  }
  const double intake_ms = (Now() - item.submitted) * 1e3;
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.keyframes_received++;
    timings_.intake_ms.push_back(intake_ms);
    timings_.intake_during_gba.push_back(gba_running_);
  }
  if (added) {
    {
      std::lock_guard<std::mutex> lock(work_mutex_);
      ++outstanding_;
    }
    if (!loop_queue_.Push(id)) FinishedWork();
  }
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
    {
      std::lock_guard<std::mutex> lock(cameras_mutex_);
      task.keyframe.camera = cameras_.at(kf->id.agent).Resized(kf->rgbd_depth_mm.cols, kf->rgbd_depth_mm.rows);
    }
    kf->in_dense = true;
    // The store keeps its own copy of the points: the server does not hold the images twice.
    kf->rgbd_bgr.release();
    kf->rgbd_depth_mm.release();
    {
      std::lock_guard<std::mutex> lock(work_mutex_);
      ++outstanding_;
    }
    if (!dense_queue_.Push(std::move(task))) FinishedWork();
  }
}

void Backend::QueueDenseUpdates(const std::vector<ServerKeyframe*>& moved, DenseTask::Kind kind) {
  if (!dense_) return;
  DenseTask task;
  task.kind = kind;
  for (ServerKeyframe* kf : moved) {
    if (kf->in_dense) task.poses.push_back({kf->id, kf->T_map_cam});
  }
  if (task.poses.empty()) return;
  {
    std::lock_guard<std::mutex> lock(work_mutex_);
    ++outstanding_;
  }
  if (!dense_queue_.Push(std::move(task))) FinishedWork();
}

void Backend::DenseLoop() {
  while (auto task = dense_queue_.Pop()) {
    Status status;
    switch (task->kind) {
      case DenseTask::Kind::kAdd:
        status = dense_->SetAgentMap(task->keyframe.id.agent, task->to);
        if (status.ok()) status = dense_->AddKeyframe(task->keyframe);
        if (status.ok()) {
          if (observer_) observer_->OnDenseKeyframe(task->keyframe.id);
          std::lock_guard<std::mutex> lock(stats_mutex_);
          stats_.dense_keyframes++;
        }
        break;
      case DenseTask::Kind::kUpdate:
        for (const KeyframePose& p : task->poses) {
          const Status s = dense_->UpdateKeyframePose(p.id, p.T_world_cam);
          if (!s.ok()) status = s;
        }
        break;
      case DenseTask::Kind::kLoopUpdate:
        status = dense_->UpdateLoopPoses(task->poses);
        break;
      case DenseTask::Kind::kGlobalUpdate:
        status = dense_->UpdateGlobalPoses(task->poses).status();
        break;
      case DenseTask::Kind::kMergeMaps:
        status = dense_->MergeMaps(task->from, task->to, Pose::Identity());
        break;
    }
    if (!status.ok()) CCMD_LOG(WARNING) << "dense map: " << status.ToString();
    if (dense_queue_.size() == 0) dense_->Maintain();  // deferred re-filters when idle
    FinishedWork();
  }
}

Status Backend::ExportDenseMap(const std::string& path) {
  if (!dense_) return Unsupported("the dense map is disabled");
  const auto primary = maps_.primary();
  if (!primary) return NotFound("no map yet");
  return dense_->ExportPly(path, DenseSelection::Map(*primary));
}

// ---------------------------------------------------------------- loops

void Backend::LoopDetectionLoop() {
  while (auto id = loop_queue_.Pop()) {
    DetectLoop(*id, /*stored=*/false);
    // Keyframes that arrived before the first vocabulary was trained are queried now, oldest
    // first, between new arrivals.
    while (!late_queries_.empty() && loop_queue_.size() == 0) {
      const GlobalKeyframeId late = late_queries_.front();
      late_queries_.erase(late_queries_.begin());
      DetectLoop(late, /*stored=*/true);
    }
    FinishedWork();
  }
}

namespace {

std::vector<Descriptor> DescriptorsOf(const ServerKeyframe& kf) { return kf.descriptors; }

}  // namespace

void Backend::DetectLoop(const GlobalKeyframeId& id, bool stored) {
  const AgentId agent = id.agent;
  PinholeCamera camera;
  {
    std::lock_guard<std::mutex> lock(cameras_mutex_);
    camera = cameras_.at(agent);
  }
  // Candidates, from the query's map under its lock.
  std::vector<Descriptor> descriptors;
  std::vector<PlaceHit> candidates;
  MapId query_map;
  bool in_cooldown = false;
  {
    MapManager::Guard guard = maps_.CheckOutAgent(agent);
    ServerKeyframe* query = guard->keyframe(id);
    if (!query) return;
    query_map = guard->id();
    descriptors = DescriptorsOf(*query);
    const auto cooldown = loop_cooldown_until_.find(agent);
    in_cooldown = cooldown != loop_cooldown_until_.end() && id.keyframe <= cooldown->second;
    const LoopCandidateRule rule = MakeLoopCandidateRule(place_, id, *query, options_.exclude_recent_keyframes);
    candidates = QueryLoopCandidates(place_, descriptors, rule, options_.loop_candidates * 3);
  }
  // The cool-down after a loop holds back further loops inside the map only: a keyframe that
  // sees another agent's map can still fuse the two (an agent that closes a loop just before
  // its segment's overlap with the next one would otherwise never fuse).
  if (in_cooldown) {
    candidates.erase(std::remove_if(candidates.begin(), candidates.end(),
                                    [&](const PlaceHit& c) {
                                      const auto map = maps_.MapOfAgent(c.keyframe.agent);
                                      return !map || *map == query_map;
                                    }),
                     candidates.end());
  }
  if (static_cast<int>(candidates.size()) > options_.loop_candidates) candidates.resize(options_.loop_candidates);
  if (!stored) {
    std::vector<GlobalKeyframeId> late = place_.Add(id, descriptors);
    late_queries_.insert(late_queries_.end(), late.begin(), late.end());
  }
  if (candidates.empty()) return;

  for (const PlaceHit& candidate : candidates) {
    const auto candidate_map_id = maps_.MapOfAgent(candidate.keyframe.agent);
    if (!candidate_map_id) continue;
    const bool same_map = *candidate_map_id == query_map;
    MapManager::Guard query_guard, candidate_guard;
    if (same_map) {
      query_guard = maps_.CheckOut(query_map);
    } else {
      std::tie(query_guard, candidate_guard) = maps_.CheckOutPair(query_map, *candidate_map_id);
    }
    if (!query_guard || (!same_map && !candidate_guard)) return;  // fused meanwhile: next keyframe
    ServerMap* qmap = query_guard.get();
    ServerMap* cmap = same_map ? qmap : candidate_guard.get();
    ServerKeyframe* query = qmap->keyframe(id);
    ServerKeyframe* cand = cmap->keyframe(candidate.keyframe);
    if (!query || !cand) continue;
    auto match = VerifyLoop(query, camera, cand, *cmap, options_.verification);
    if (!match) continue;

    // Consistency: consecutive keyframes of the agent must agree on the same map-to-map
    // transform before the loop is accepted.
    const Pose T_cmap_qmap = match->T_candidate_map_query * query->T_map_cam.inverse();
    PendingLoop& pending = pending_loops_[agent];
    const bool consistent = pending.count > 0 && pending.candidate_map == cmap->id() &&
                            id.keyframe.value() - pending.last_query.value() <= 3 &&
                            TranslationDistance(pending.T_candidate_map_query_map, T_cmap_qmap) <
                                options_.consistency_translation &&
                            RotationDistance(pending.T_candidate_map_query_map, T_cmap_qmap) <
                                options_.consistency_rotation_deg * M_PI / 180;
    pending.count = consistent ? pending.count + 1 : 1;
    pending.candidate_map = cmap->id();
    pending.T_candidate_map_query_map = T_cmap_qmap;
    pending.last_query = id.keyframe;
    CCMD_LOG(INFO) << "loop candidate: agent " << agent.value() << " keyframe " << id.keyframe.value()
                   << " ~ agent " << cand->id.agent.value() << " keyframe " << cand->id.keyframe.value()
                   << " (" << match->inliers << " inliers, " << pending.count << "/" << options_.loop_consistency
                   << " consistent)";
    if (pending.count < options_.loop_consistency) return;
    pending.count = 0;

    LoopEvent event;
    event.server_time = Now();
    event.query = id;
    event.candidate = cand->id;
    event.inliers = match->inliers;
    event.T_candidate_query = cand->T_map_cam.inverse() * match->T_candidate_map_query;
    ServerMap* result_map = cmap;
    MapManager::Guard fused_guard;
    std::vector<ServerKeyframe*> entering_primary;
    std::vector<ServerKeyframe*> moved;  // by the fusion or the pose graph
    const auto primary = maps_.primary();
    if (same_map) {
      // Loop inside one map: a loop edge and a pose graph spread the correction.
      const LoopEdge edge{cand->id, id, cand->T_map_cam.inverse() * match->T_candidate_map_query};
      qmap->AddLoopEdge(edge);
    } else {
      // Two maps: fused in the frame of the primary map if one is primary, else the candidate's.
      const bool keep_query = primary && qmap->id() == *primary;
      const MapId old_query = qmap->id(), old_candidate = cmap->id();
      const bool primary_involved = primary && (old_query == *primary || old_candidate == *primary);
      std::vector<ServerKeyframe*> newcomers;
      for (const auto& [kid, kf] : (keep_query ? cmap : qmap)->keyframes()) newcomers.push_back(kf.get());
      fused_guard = keep_query ? maps_.Fuse(&query_guard, &candidate_guard, T_cmap_qmap.inverse())
                               : maps_.Fuse(&candidate_guard, &query_guard, T_cmap_qmap);
      result_map = fused_guard.get();
      result_map->AddLoopEdge({cand->id, id, cand->T_map_cam.inverse() * query->T_map_cam});
      event.fusion = true;
      moved = newcomers;
      if (primary_involved && dense_) {
        DenseTask merge;
        merge.kind = DenseTask::Kind::kMergeMaps;
        merge.from = *primary;
        merge.to = result_map->id();
        {
          std::lock_guard<std::mutex> lock(work_mutex_);
          ++outstanding_;
        }
        if (!dense_queue_.Push(std::move(merge))) FinishedWork();
        entering_primary = newcomers;  // the other map's keyframes now feed the dense map
      }
    }
    // Matched points become one; the two keyframes become covisible.
    for (const auto& [keypoint, point] : match->matches) {
      ServerMapPoint* own = query->points[keypoint];
      if (own == point) continue;
      if (own) {
        result_map->MergePoints(own, point);
      } else {
        result_map->AddObservation(point, query, keypoint);
      }
    }
    result_map->AddCovisibility(query, cand, match->inliers);
    if (same_map) {
      auto optimized = OptimizeMapPoseGraph(result_map, options_.pose_graph);
      if (optimized.ok()) {
        moved = *optimized;
        QueueDenseUpdates(moved, DenseTask::Kind::kLoopUpdate);
      } else {
        CCMD_LOG(WARNING) << "pose graph: " << optimized.status().ToString();
      }
    }
    if (!entering_primary.empty()) QueueDenseAdds(result_map, entering_primary);
    event.map = result_map->id();
    if (observer_) observer_->OnLoop(event);
    NotifyPoses(event.fusion ? PoseSource::kFusion : PoseSource::kLoop, event.map, moved, MonotonicSeconds());
    loop_cooldown_until_[agent] = KeyframeId(id.keyframe.value() + options_.loop_cooldown_keyframes);
    {
      std::lock_guard<std::mutex> lock(stats_mutex_);
      loop_events_.push_back(event);
      if (event.fusion) {
        stats_.fusions++;
      } else {
        stats_.loops++;
      }
    }
    CCMD_LOG(INFO) << (event.fusion ? "maps fused" : "loop closed") << ": agent " << agent.value()
                   << " keyframe " << id.keyframe.value() << " with agent " << cand->id.agent.value()
                   << " keyframe " << cand->id.keyframe.value() << ", " << match->inliers << " inliers, map "
                   << event.map.value();
    query_guard = MapManager::Guard();
    candidate_guard = MapManager::Guard();
    fused_guard = MapManager::Guard();
    RequestGlobalBa(agent);
    return;
  }
}

// ---------------------------------------------------------------- global BA

void Backend::RequestGlobalBa(AgentId agent) {
  if (!options_.global_ba) return;
  std::lock_guard<std::mutex> lock(gba_mutex_);
  if (!gba_request_) {
    std::lock_guard<std::mutex> work(work_mutex_);
    ++outstanding_;
  }
  gba_request_ = agent;
  gba_abort_ = true;  // a running GBA is outdated by the new loop
  gba_cv_.notify_all();
}

void Backend::GlobalBaLoop() {
  while (true) {
    AgentId agent;
    {
      std::unique_lock<std::mutex> lock(gba_mutex_);
      gba_cv_.wait(lock, [&] { return gba_stop_ || gba_request_.has_value(); });
      if (!gba_request_) return;  // stopping with nothing requested
      agent = *gba_request_;
      gba_request_.reset();
      gba_abort_ = false;
      if (gba_stop_) {
        FinishedWork();
        return;
      }
    }
    std::map<AgentId, PinholeCamera> cameras;
    {
      std::lock_guard<std::mutex> lock(cameras_mutex_);
      cameras = cameras_;
    }
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
        const std::vector<ServerKeyframe*> moved = ApplyGlobalBa(guard.get(), problem);
        NotifyPoses(PoseSource::kGlobalBa, map_id, moved, MonotonicSeconds());
        QueueDenseUpdates(moved, DenseTask::Kind::kGlobalUpdate);
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
                   << problem.points.size() << " points, " << summary.iterations << " iterations, "
                   << seconds << " s" << (applied ? "" : " (abandoned: newer work)");
    FinishedWork();
  }
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
