#include "libccmd/tracking/local_mapper.h"

#include <algorithm>
#include <cmath>
#include <unordered_map>
#include <unordered_set>

#include "libccmd/optim/bundle_adjuster.h"
#include "libccmd/sensors/depth_registration.h"
#include "libccmd/tracking/depth_alignment.h"
#include "libccmd/tracking/local_ba.h"
#include "libccmd/tracking/matching.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

LocalMapper::LocalMapper(const PinholeCamera& camera, const TrackingOptions& options, LocalMap* map,
                         const OrbExtractor* orb, KeyframeSink* sink)
    : camera_(camera),
      options_(options),
      map_(map),
      orb_(orb),
      sink_(sink),
      selector_(options.rgbd_selection),
      budget_(options.mapping_follows_budget ? options.cpu_budget : 0.0, camera.fps) {
  if (!options_.synchronous_mapping) thread_ = std::thread([this] { Run(); });
}

LocalMapper::~LocalMapper() { Finish(); }

bool LocalMapper::Idle() const {
  std::lock_guard<std::mutex> lock(queue_mutex_);
  return queue_.empty() && !busy_;
}

double LocalMapper::DepthFitSigmas() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return stats_.depth_fit_sigmas;
}

bool LocalMapper::CanAccept() const {
  std::lock_guard<std::mutex> lock(queue_mutex_);
  return !stopping_ && queue_.size() < kQueueCapacity;
}

void LocalMapper::Insert(const KeyframePtr& keyframe) {
  keyframe->created_wall_s = WallSeconds();  // the start of its map latency
  {
    std::lock_guard<std::mutex> lock(queue_mutex_);
    queue_.push_back(keyframe);
  }
  abort_ba_ = true;  // newer work: a running local BA stops early
  queue_cv_.notify_one();
}

void LocalMapper::ProcessPending() {
  while (true) {
    KeyframePtr next;
    {
      std::lock_guard<std::mutex> lock(queue_mutex_);
      if (queue_.empty()) return;
      next = queue_.front();
      queue_.pop_front();
      busy_ = true;
    }
    Process(next);
    std::lock_guard<std::mutex> lock(queue_mutex_);
    busy_ = false;
  }
}

void LocalMapper::Run() {
  while (true) {
    KeyframePtr next;
    {
      std::unique_lock<std::mutex> lock(queue_mutex_);
      queue_cv_.wait(lock, [&] { return stopping_ || !queue_.empty(); });
      if (queue_.empty()) return;  // stopping and drained
      next = queue_.front();
      queue_.pop_front();
      busy_ = true;
    }
    Process(next);
    std::lock_guard<std::mutex> lock(queue_mutex_);
    busy_ = false;
  }
}

void LocalMapper::Finish() {
  {
    std::lock_guard<std::mutex> lock(queue_mutex_);
    stopping_ = true;
  }
  queue_cv_.notify_all();
  if (thread_.joinable()) thread_.join();
  ProcessPending();  // synchronous mode, or anything queued after the thread left
}

MappingStats LocalMapper::stats() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return stats_;
}

std::vector<RgbdDecision> LocalMapper::decisions() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return decisions_;
}

void LocalMapper::Process(const KeyframePtr& keyframe_ptr) {
  const Stopwatch watch;
  const ThreadCpuStopwatch cpu;
  Keyframe* keyframe = keyframe_ptr.get();
  const std::optional<DepthAsTaken> taken = MoveDepthToColourTime(keyframe);
  {
    const auto lock = map_->Lock();
    if (keyframe->bad()) return;
    for (const MapPointPtr& p : keyframe->points()) {
      if (!p || p->bad()) continue;
      p->UpdateNormalAndDepth(*orb_);
      p->UpdateDescriptor();
      if (p->first_keyframe() == keyframe->id()) recent_points_.push_back(p);
    }
    map_->UpdateConnections(keyframe);
    CullRecentPoints(*keyframe);
    TriangulateWithNeighbours(keyframe);
    FuseWithNeighbours(keyframe);
  }
  AlignWithNeighbours(keyframe, taken ? &*taken : nullptr);
  ScheduleLocalBundleAdjustment(keyframe);

  KeyframeSnapshot snapshot;
  std::vector<PoseUpdate> updates;
  bool emitted = false;
  {
    const auto lock = map_->Lock();
    if (options_.cull_redundant_keyframes) CullRedundantKeyframes(keyframe);
    EvictOldKeyframes(keyframe);
    std::erase_if(depth_edges_, [&](const DepthEdge& e) {
      const KeyframePtr a = map_->keyframe(e.a), b = map_->keyframe(e.b);
      return !a || !b || a->bad() || b->bad();
    });
    emitted = Emit(keyframe, &snapshot, &updates);
  }
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.keyframes++;
    stats_.mapping_ms_total += watch.ElapsedMillis();
    stats_.mapping_cpu_ms_total += cpu.ElapsedMillis();
    stats_.pose_updates += static_cast<int>(updates.size());
    stats_.rgbd_transmitted += snapshot.has_rgbd;
    if (emitted && decisions_.size() < kMaxRecordedDecisions) {
      decisions_.push_back(snapshot.decision);
    } else if (emitted) {
      ++stats_.rgbd_decisions_not_recorded;
    }
  }
  budget_.Spend(cpu.ElapsedMillis());
  if (sink_) {
    if (emitted) sink_->OnKeyframe(std::move(snapshot));
    if (!updates.empty()) sink_->OnPoseUpdates(std::move(updates));
  }
}

void LocalMapper::CullRecentPoints(const Keyframe& keyframe) {
  // A new point survives if trackers find it where it should be seen (found/visible >= 25%)
  // and other keyframes observe it soon (ORB-SLAM's test, with depth observations counting
  // twice).
  int culled = 0;
  std::vector<MapPointPtr> kept;
  for (const MapPointPtr& p : recent_points_) {
    if (p->bad()) continue;
    const std::uint32_t age = keyframe.id().value() - p->first_keyframe().value();
    if (p->FoundRatio() < 0.25f || (age >= 2 && p->WeightedObservations() <= 3)) {
      map_->ErasePoint(p.get());
      ++culled;
    } else if (age < 3) {
      kept.push_back(p);
    }
  }
  recent_points_ = std::move(kept);
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.culled_points += culled;
}

void LocalMapper::TriangulateWithNeighbours(Keyframe* keyframe) {
  if (options_.triangulation_neighbours <= 0) return;
  const FrameFeatures& f1 = keyframe->features();
  const Eigen::Vector3d c1 = keyframe->camera_center();
  const Eigen::Matrix3d R1 = keyframe->T_world_cam().linear();
  const double baseline_rgbd = camera_.bf / camera_.fx;  // the depth sensor's virtual baseline
  const std::vector<float>& scale = orb_->scale();
  const float scale_ratio_margin = 1.5f * orb_->options().scale_factor;
  // Parallax of a depth measurement: the angle the virtual stereo baseline spans at that depth.
  const auto depth_parallax_cos = [&](float z) {
    return z > 0 ? std::cos(2.0 * std::atan2(baseline_rgbd / 2, z)) : 2.0;
  };
  // Whether the point is seen where keypoint i of kf is, within the 95 % gate.
  const auto consistent = [&](const Keyframe& kf, int i, const Eigen::Vector3d& p_world) {
    const Eigen::Vector3d pc = kf.T_cam_world() * p_world;
    if (pc.z() < options_.min_depth || pc.z() > options_.max_depth) return false;
    const Eigen::Vector2d uv = camera_.Project(pc);
    return WithinReprojectionGate(kf.features(), i, uv, uv.x() - camera_.bf / pc.z(), *orb_);
  };
  int created = 0;
  for (Keyframe* neighbour : keyframe->BestCovisible(options_.triangulation_neighbours)) {
    const Eigen::Vector3d c2 = neighbour->camera_center();
    if ((c2 - c1).norm() < baseline_rgbd) continue;  // too close to add to what depth gives
    const FrameFeatures& f2 = neighbour->features();
    const Eigen::Matrix3d R2 = neighbour->T_world_cam().linear();
    for (const auto& [i, j] : SearchForTriangulation(*keyframe, *neighbour, *orb_, camera_)) {
      if (keyframe->point(i) || neighbour->point(j)) continue;
      const cv::Point2f &u1 = f1.keypoints[i].pt, &u2 = f2.keypoints[j].pt;
      const Eigen::Vector3d ray1 = R1 * camera_.BackProject(u1.x, u1.y, 1.0).normalized();
      const Eigen::Vector3d ray2 = R2 * camera_.BackProject(u2.x, u2.y, 1.0).normalized();
      const double rays_cos = ray1.dot(ray2);
      const double depth1_cos = depth_parallax_cos(f1.depth[i]);
      const double depth2_cos = depth_parallax_cos(f2.depth[j]);
      // The rays' intersection where they part more than a depth measurement would, else the
      // better measured depth; without either, too little parallax to place the point.
      Eigen::Vector3d p;
      if (rays_cos > 0 && rays_cos < std::min({depth1_cos, depth2_cos, 0.9998})) {
        // Midpoint of the closest approach of the two rays.
        const Eigen::Vector3d w = c1 - c2;
        const double b = ray1.dot(ray2), d = ray1.dot(w), e = ray2.dot(w);
        const double denom = 1 - b * b;
        const double s = (b * e - d) / denom, t = (e - b * d) / denom;
        if (s <= 0 || t <= 0) continue;
        p = 0.5 * ((c1 + s * ray1) + (c2 + t * ray2));
        // From the rays alone only where they place the point at least as precisely as the
        // sensor's depth would: a parallax wider than its baseline spans at that distance.
        if (f1.depth[i] <= 0 && f2.depth[j] <= 0 &&
            rays_cos >= depth_parallax_cos(static_cast<float>((p - c1).norm()))) {
          continue;
        }
      } else if (f1.depth[i] > 0 && depth1_cos <= depth2_cos) {
        p = keyframe->T_world_cam() * camera_.BackProject(u1.x, u1.y, f1.depth[i]);
      } else if (f2.depth[j] > 0) {
        p = neighbour->T_world_cam() * camera_.BackProject(u2.x, u2.y, f2.depth[j]);
      } else {
        continue;
      }
      if (!consistent(*keyframe, i, p) || !consistent(*neighbour, j, p)) continue;
      // Scale consistency: the distance ratio must agree with the octaves' scale ratio.
      const float distance_ratio =
          static_cast<float>((p - c2).norm() / std::max((p - c1).norm(), 1e-9));
      const float octave_ratio = scale[f1.keypoints[i].octave] / scale[f2.keypoints[j].octave];
      if (distance_ratio * scale_ratio_margin < octave_ratio ||
          distance_ratio > octave_ratio * scale_ratio_margin) {
        continue;
      }
      auto point = std::make_shared<MapPoint>(map_->NextMapPointId(), p);
      map_->AddMapPoint(point);
      map_->AddObservation(point, keyframe, i);
      map_->AddObservation(point, neighbour, j);
      point->UpdateDescriptor();
      point->UpdateNormalAndDepth(*orb_);
      recent_points_.push_back(point);
      ++created;
    }
  }
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.triangulated_points += created;
}

void LocalMapper::FuseWithNeighbours(Keyframe* keyframe) {
  std::vector<Keyframe*> targets;
  std::unordered_set<Keyframe*> seen = {keyframe};
  for (Keyframe* n : keyframe->BestCovisible(10)) {
    if (seen.insert(n).second) targets.push_back(n);
    for (Keyframe* n2 : n->BestCovisible(5)) {
      if (seen.insert(n2).second) targets.push_back(n2);
    }
  }
  int fused = 0;
  std::vector<MapPointPtr> own;
  for (const MapPointPtr& p : keyframe->points()) {
    if (p && !p->bad()) own.push_back(p);
  }
  for (Keyframe* target : targets) fused += FusePoints(map_, target, own, *orb_, camera_);
  std::vector<MapPointPtr> theirs;
  std::unordered_set<const MapPoint*> unique;
  for (Keyframe* target : targets) {
    for (const MapPointPtr& p : target->points()) {
      if (p && !p->bad() && unique.insert(p.get()).second) theirs.push_back(p);
    }
  }
  fused += FusePoints(map_, keyframe, theirs, *orb_, camera_);
  for (const MapPointPtr& p : keyframe->points()) {
    if (!p || p->bad()) continue;
    p->UpdateDescriptor();
    p->UpdateNormalAndDepth(*orb_);
  }
  map_->UpdateConnections(keyframe);
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.fused_points += fused;
}

std::optional<LocalMapper::DepthAsTaken> LocalMapper::MoveDepthToColourTime(Keyframe* keyframe) {
  DepthAsTaken taken;
  {
    const auto lock = map_->Lock();
    if (!keyframe->T_colour_depth || keyframe->depth_mm.empty()) return std::nullopt;
    taken = {keyframe->depth_mm, *keyframe->T_colour_depth};
  }
  cv::Mat moved = DepthFromNearbyPose(taken.depth_mm, camera_, taken.T_colour_depth.inverse());
  const auto lock = map_->Lock();
  keyframe->depth_mm = std::move(moved);
  keyframe->T_colour_depth.reset();
  return taken;
}

void LocalMapper::AlignWithNeighbours(Keyframe* keyframe, const DepthAsTaken* taken) {
  if (options_.depth_alignment_weight <= 0 || options_.depth_alignment_neighbours == 0) return;
  const Stopwatch watch;
  cv::Mat depth;
  {
    const auto lock = map_->Lock();
    if (keyframe->bad()) return;
    depth = keyframe->depth_mm;
  }
  // Quarter resolution: 160x120 cells for VGA, a few milliseconds per alignment.
  auto model = std::make_shared<const DepthModel>(
      taken ? DepthModel::FromDepth(taken->depth_mm, camera_, 4, options_.min_depth,
                                    options_.max_depth)
                  .Moved(taken->T_colour_depth)
            : DepthModel::FromDepth(depth, camera_, 4, options_.min_depth, options_.max_depth));
  struct Job {
    KeyframeId id;
    Pose T_kf_neighbour;
    std::shared_ptr<const DepthModel> model;
  };
  if (model->empty()) return;
  std::vector<Job> jobs;
  {
    const auto lock = map_->Lock();
    if (keyframe->bad()) return;
    keyframe->depth_model = model;
    for (Keyframe* n : keyframe->BestCovisible(options_.depth_alignment_neighbours)) {
      if (n->bad() || !n->depth_model) continue;
      jobs.push_back({n->id(), keyframe->T_cam_world() * n->T_world_cam(), n->depth_model});
    }
  }
  int accepted = 0, failed = 0;
  std::vector<double> fits;
  for (const Job& job : jobs) {
    const auto aligned = AlignDepth(*job.model, *model, job.T_kf_neighbour, options_.depth_noise);
    if (!aligned || !StaysNearStart(*aligned, job.T_kf_neighbour)) {
      ++failed;
      continue;
    }
    // Directions the geometry does not constrain have eigenvalues near zero and add nothing.
    depth_edges_.push_back(
        {job.id, keyframe->id(), aligned->T_target_source,
         SqrtInformation(options_.depth_alignment_weight * aligned->information)});
    fits.push_back(aligned->rms / options_.depth_noise.Sigma(aligned->mean_range));
    ++accepted;
  }
  std::lock_guard<std::mutex> lock(stats_mutex_);
  for (const double fit : fits) {
    fit_sigmas_.push_back(fit);
    if (fit_sigmas_.size() > kFitWindow) fit_sigmas_.pop_front();
  }
  // Mean plus three standard deviations rather than the largest: known after a few alignments
  // (ICL-NUIM: 2.3-2.9 over its first hundred, where the largest stays at 2.06 for 35 and then
  // reaches 2.53), and one loose alignment moves it less (a 5 sigma one among 64: +1.1, the
  // largest +3.6).
  if (!fit_sigmas_.empty()) {
    double sum = 0, sum_sq = 0;
    for (const double f : fit_sigmas_) {
      sum += f;
      sum_sq += f * f;
    }
    const double n = static_cast<double>(fit_sigmas_.size());
    const double mean = sum / n;
    stats_.depth_fit_sigmas = mean + 3.0 * std::sqrt(std::max(0.0, sum_sq / n - mean * mean));
  }
  stats_.depth_alignments += accepted;
  stats_.depth_alignments_failed += failed;
  stats_.depth_alignment_ms_total += watch.ElapsedMillis();
}

void LocalMapper::ScheduleLocalBundleAdjustment(Keyframe* keyframe) {
  abort_ba_ = false;
  bool more_waiting;
  {
    std::lock_guard<std::mutex> lock(queue_mutex_);
    more_waiting = !queue_.empty();
  }
  const LocalBaLevel level = budget_.Level();
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    // ORB-SLAM skips the local BA when the tracker is already waiting with a newer keyframe.
    stats_.local_ba_skipped_waiting += more_waiting;
    stats_.local_ba_skipped_budget += !more_waiting && level == LocalBaLevel::kSkipped;
    stats_.budget_balance_ms = budget_.balance_ms();
    stats_.budget_lowest_ms = budget_.lowest_balance_ms();
  }
  if (more_waiting || level == LocalBaLevel::kSkipped) return;
  LocalBundleAdjustment(keyframe, level == LocalBaLevel::kReduced);
}

void LocalMapper::LocalBundleAdjustment(Keyframe* keyframe, bool reduced) {
  const Stopwatch watch;
  const ThreadCpuStopwatch cpu;
  BaOptions ba_options;
  ba_options.abort = &abort_ba_;
  ba_options.first_iterations = options_.local_ba_robust_iterations;
  ba_options.second_iterations = options_.local_ba_iterations;
  ba_options.function_tolerance = options_.local_ba_function_tolerance;
  int window = options_.local_ba_window;
  if (reduced) {
    // Over the CPU budget: half the window and half the iterations.
    window = std::max(1, window / 2);
    ba_options.first_iterations = (ba_options.first_iterations + 1) / 2;
    ba_options.second_iterations = (ba_options.second_iterations + 1) / 2;
  }
  LocalBaProblem local;
  {
    const auto lock = map_->Lock();
    if (keyframe->bad()) return;
    local = BuildLocalBa(keyframe, window, *map_, *orb_);
  }
  BaProblem& problem = local.problem;
  if (problem.observations.empty()) return;
  if (!depth_edges_.empty()) {
    std::unordered_map<KeyframeId, int> index;
    for (std::size_t c = 0; c < local.cameras.size(); ++c)
      index[local.cameras[c]->id()] = static_cast<int>(c);
    for (const DepthEdge& e : depth_edges_) {
      const auto a = index.find(e.a), b = index.find(e.b);
      if (a != index.end() && b != index.end()) {
        problem.relative_poses.push_back({a->second, b->second, e.T_b_a, e.sqrt_information});
      }
    }
  }
  problem.calibrations = {Intrinsics{camera_.fx, camera_.fy, camera_.cx, camera_.cy}};
  const BaSummary summary = BundleAdjust(&problem, ba_options);
  {
    const auto lock = map_->Lock();
    ApplyLocalBa(local, summary, map_, *orb_);
  }
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.local_ba_runs++;
  stats_.local_ba_aborted += summary.aborted;
  stats_.local_ba_reduced += reduced;
  stats_.local_ba_iterations += summary.iterations;
  stats_.local_ba_ms_total += watch.ElapsedMillis();
  stats_.local_ba_cpu_ms_total += cpu.ElapsedMillis();
}

void LocalMapper::CullRedundantKeyframes(Keyframe* keyframe) {
  // A neighbour is redundant when 90% of its close points are seen by at least three other
  // keyframes at the same or a finer scale (ORB-SLAM). The first keyframe stays, and so does
  // the first of each restarted segment (the server weakens the link before it).
  int culled = 0;
  const std::vector<std::pair<Keyframe*, int>> neighbours = keyframe->connections();
  for (const auto& [kf, weight] : neighbours) {
    if (kf->bad() || kf->id().value() == 0 || kf->restart || kf == keyframe) continue;
    int total = 0, redundant = 0;
    for (int i = 0; i < kf->features().size(); ++i) {
      const MapPointPtr& p = kf->points()[i];
      if (!p || p->bad()) continue;
      const float z = kf->features().depth[i];
      if (z <= 0 || z > camera_.far_depth_m) continue;
      ++total;
      if (p->WeightedObservations() <= 3) continue;
      const int octave = kf->features().keypoints[i].octave;
      int others = 0;
      for (const auto& o : p->observations()) {
        if (o.keyframe == kf) continue;
        if (o.keyframe->features().keypoints[o.keypoint].octave <= octave + 1 && ++others >= 3)
          break;
      }
      if (others >= 3) ++redundant;
    }
    if (total > 0 && redundant > 0.9 * total) {
      map_->EraseKeyframe(kf, /*relative=*/true);
      ++culled;
    }
  }
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.culled_keyframes += culled;
}

void LocalMapper::EvictOldKeyframes(Keyframe* keyframe) {
  const auto& keyframes = map_->keyframes();
  if (static_cast<int>(keyframes.size()) <= options_.max_keyframes) return;
  std::unordered_set<const Keyframe*> protect = {keyframe};
  for (Keyframe* n : keyframe->BestCovisible(options_.local_ba_window)) protect.insert(n);
  std::vector<Keyframe*> order;
  for (const auto& [id, kf] : keyframes) order.push_back(kf.get());  // oldest first
  int evicted = 0;
  for (Keyframe* kf : order) {
    if (static_cast<int>(keyframes.size()) <= options_.max_keyframes) break;
    if (protect.count(kf) || !kf->emitted) continue;
    map_->EraseKeyframe(kf, /*relative=*/false);
    ++evicted;
  }
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.evicted_keyframes += evicted;
}

bool LocalMapper::Emit(Keyframe* keyframe, KeyframeSnapshot* s, std::vector<PoseUpdate>* updates) {
  if (keyframe->bad())
    return false;  // culled before it was ever sent: the server never hears of it
  std::vector<std::pair<KeyframeId, int>> transmitted;
  for (const auto& [kf, weight] : keyframe->connections()) {
    if (kf->emitted && kf->rgbd_sent) transmitted.emplace_back(kf->id(), weight);
  }
  const RgbdRequest request = sink_ ? sink_->NextRgbdRequest() : RgbdRequest{};
  s->decision = selector_.Decide(keyframe->id(), keyframe->TrackedPoints(1), transmitted, request);
  s->created_wall_s = keyframe->created_wall_s;
  s->id = keyframe->id();
  s->timestamp = keyframe->timestamp();
  s->frame_index = keyframe->frame_index();
  s->T_world_cam = keyframe->T_world_cam();
  if (Keyframe* parent = keyframe->parent(); parent && parent->emitted) s->parent = parent->id();
  s->restart = keyframe->restart;
  s->reset = keyframe->reset;
  const FrameFeatures& f = keyframe->features();
  // New map points go to the server at most `max_new_points_per_keyframe` per keyframe:
  // those already seen by several keyframes first (they have survived culling and carry the
  // most constraints), then the finer octaves. The rest stay on the agent and may be sent with
  // a later keyframe that observes them.
  std::vector<int> unsent;
  for (int i = 0; i < f.size(); ++i) {
    const MapPointPtr& p = keyframe->points()[i];
    if (p && !p->bad() && !p->sent()) unsent.push_back(i);
  }
  std::stable_sort(unsent.begin(), unsent.end(), [&](int a, int b) {
    const int wa = keyframe->points()[a]->WeightedObservations(),
              wb = keyframe->points()[b]->WeightedObservations();
    if (wa != wb) return wa > wb;
    return f.keypoints[a].octave < f.keypoints[b].octave;
  });
  const int budget = options_.max_new_points_per_keyframe;
  if (budget > 0 && static_cast<int>(unsent.size()) > budget) unsent.resize(budget);
  std::vector<bool> send_new(f.size(), false);
  for (int i : unsent) send_new[i] = true;

  // Keypoints: those linked to a point the server has (or gets now), and, if configured,
  // unlinked ones with their descriptors.
  const Pose& T_cam_world = keyframe->T_cam_world();
  std::vector<int> rows;
  for (int i = 0; i < f.size(); ++i) {
    const MapPointPtr& p = keyframe->points()[i];
    const bool linked = p && !p->bad() && (p->sent() || send_new[i]);
    if (!linked && !options_.send_unlinked_keypoints) continue;
    const int row = static_cast<int>(s->keypoints.size());
    rows.push_back(i);
    s->keypoints.push_back(f.keypoints[i]);
    s->depth.push_back(f.depth[i]);
    s->point_ids.push_back(linked ? std::optional<MapPointId>(p->id()) : std::nullopt);
    if (linked && send_new[i]) {
      s->new_points.push_back({p->id(), T_cam_world * p->position(), p->descriptor(), row});
      p->set_sent();
    }
  }
  s->descriptors = cv::Mat(static_cast<int>(rows.size()), 32, CV_8U);
  for (std::size_t r = 0; r < rows.size(); ++r)
    f.descriptors.row(rows[r]).copyTo(s->descriptors.row(static_cast<int>(r)));
  for (const auto& [kf, weight] : keyframe->connections()) {
    if (kf->emitted) s->covisibility.emplace_back(kf->id(), weight);
  }
  for (const DepthEdge& e : depth_edges_) {
    if (e.b != keyframe->id()) continue;
    const KeyframePtr other = map_->keyframe(e.a);
    if (other && other->emitted) {
      s->depth_links.push_back({e.a, e.T_b_a, e.sqrt_information.transpose() * e.sqrt_information});
    }
  }
  s->keypoints_extracted = f.size();
  s->image_width = camera_.width;
  s->image_height = camera_.height;
  s->has_rgbd = s->decision.transmit;
  if (s->has_rgbd) {
    s->bgr = keyframe->bgr;
    s->depth_mm = keyframe->depth_mm;
  }
  // The dense map lives on the server: the agent keeps no images once they are handed over.
  keyframe->bgr.release();
  keyframe->depth_mm.release();
  keyframe->emitted = true;
  keyframe->rgbd_sent = s->has_rgbd;
  keyframe->emitted_T_world_cam = keyframe->T_world_cam();

  for (const auto& [id, kf] : map_->keyframes()) {
    if (!kf->emitted || kf.get() == keyframe) continue;
    const Pose& before = kf->emitted_T_world_cam;
    const Pose& now = kf->T_world_cam();
    if (TranslationDistance(before, now) > options_.pose_update_min_translation ||
        RotationDistance(before, now) > options_.pose_update_min_rotation) {
      updates->push_back({kf->id(), now});
      kf->emitted_T_world_cam = now;
    }
  }
  return true;
}

}  // namespace ccmd
