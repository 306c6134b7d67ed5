#include "libccmd/tracking/tracker.h"

#include <algorithm>
#include <cmath>
#include <unordered_map>
#include <unordered_set>

#include "libccmd/geometry/pnp.h"
#include "libccmd/optim/bundle_adjuster.h"
#include "libccmd/tracking/depth_alignment.h"
#include "libccmd/tracking/matching.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"

namespace ccmd {

const char* TrackingStateName(TrackingState state) {
  switch (state) {
    case TrackingState::kNotInitialized:
      return "not initialized";
    case TrackingState::kOk:
      return "ok";
    case TrackingState::kLost:
      return "lost";
  }
  return "?";
}

Tracker::FrameRecord::FrameRecord(double timestamp, KeyframeId reference, const Pose& T_ref_cam)
    : timestamp(timestamp),
      reference(reference),
      q_ref_cam(Eigen::Quaterniond(T_ref_cam.linear()).cast<float>()),
      t_ref_cam(T_ref_cam.translation().cast<float>()) {}

Pose Tracker::FrameRecord::T_ref_cam() const {
  Pose T = Pose::Identity();
  T.linear() = q_ref_cam.cast<double>().normalized().toRotationMatrix();
  T.translation() = t_ref_cam.cast<double>();
  return T;
}

Tracker::Tracker(const PinholeCamera& camera, const TrackingOptions& options, LocalMap* map,
                 const OrbExtractor* orb, MappingQueue* mapping)
    : camera_(camera), options_(options), map_(map), orb_(orb), mapping_(mapping) {
  if (options_.max_frames_between_keyframes <= 0) {
    options_.max_frames_between_keyframes = static_cast<int>(std::lround(camera_.fps));
  }
}

TrackResult Tracker::Track(const RgbdFrame& input) {
  TrackResult result;
  Stopwatch watch;
  ThreadCpuStopwatch cpu;
  std::optional<RollingShutter> shutter;
  if (options_.rolling_shutter_readout > 0 && state_ == TrackingState::kOk && velocity_ &&
      velocity_interval_ > 0) {
    shutter = RollingShutter{options_.rolling_shutter_readout, *velocity_, velocity_interval_};
  }
  current_ =
      MakeFrame(input, *orb_, camera_, options_,
                input.depth_mm.empty() ? std::nullopt : DepthCameraPose(input.depth_time_offset),
                shutter ? &*shutter : nullptr);
  current_->motion_pending = (options_.rolling_shutter_readout > 0 && !shutter) ||
                             (CompensatesLag(*current_) && !current_->T_colour_depth);
  if (current_->motion_pending && current_->keypoints_as_read.empty())
    current_->keypoints_as_read = current_->features.keypoints;
  result.extract_ms = watch.ElapsedMillis();
  result.extract_cpu_ms = cpu.ElapsedMillis();
  watch.Restart();
  cpu.Restart();

  const auto lock = map_->Lock();
  bool ok = false;
  if (state_ == TrackingState::kNotInitialized) {
    ok = Initialize(current_.get(), Pose::Identity(), /*restart=*/false);
    if (ok) state_ = TrackingState::kOk;
  } else {
    if (state_ == TrackingState::kOk) {
      if (velocity_ && last_ && last_->has_pose &&
          current_->index > last_relocalisation_frame_ + 2) {
        ok = TrackWithMotionModel();
      }
      if (!ok) ok = TrackReferenceKeyframe();
    } else {
      ok = Relocalize();
    }
    current_->reference = reference_;
    if (ok) ok = TrackLocalMap(/*depth_may_confirm=*/!bridged_since_);
    bool by_depth = false;
    if (!ok && state_ == TrackingState::kOk) ok = by_depth = BridgeWithDepth();
    if (ok) {
      state_ = TrackingState::kOk;
      last_T_world_cam_ = current_->T_cam_world.inverse();
      last_tracked_timestamp_ = current_->timestamp;
      if (last_ && last_->has_pose) {
        velocity_ = current_->T_cam_world * last_->T_cam_world.inverse();
        velocity_interval_ = current_->timestamp - last_->timestamp;
      }
      result.depth_only = by_depth && matches_inliers_ == 0;
      const bool restarted = result.depth_only && RestartAtBridgedFrame();
      if (restarted) result.depth_only = false;
      if (!result.depth_only) EndBridge();
      if (!result.depth_only && !restarted && NeedNewKeyframe()) {
        const KeyframePtr tracked_against = reference_;
        CreateKeyframe();
        result.new_keyframe = true;
        if (options_.record_trajectory && tracked_against) {
          const Pose T_ref_cam = tracked_against->T_cam_world() * *last_T_world_cam_;
          keyframe_records_.push_back(
              {reference_->id(), tracked_since_keyframe_, records_.size(),
               FrameRecord(current_->timestamp, tracked_against->id(), T_ref_cam)});
        }
        tracked_since_keyframe_ = true;
      }
      // Outliers do not carry over to the next frame's motion-model search.
      for (int i = 0; i < current_->size(); ++i) {
        if (current_->outlier[i]) current_->points[i] = nullptr;
      }
    } else {
      if (state_ == TrackingState::kOk) {
        CCMD_LOG(WARNING) << "tracking lost at frame " << current_->index
                          << " (t=" << current_->timestamp << "); relocalising";
        lost_since_ = current_->timestamp;
      }
      state_ = TrackingState::kLost;
      EndBridge();
      tracked_since_keyframe_ = false;
      velocity_.reset();
      current_->has_pose = false;
      if (RestartDue() && Initialize(current_.get(), *last_T_world_cam_, /*restart=*/true)) {
        CCMD_LOG(WARNING) << "no relocalisation since t=" << lost_since_
                          << ": a new map segment starts at frame " << current_->index
                          << " from the last tracked pose";
        state_ = TrackingState::kOk;
        ++restarts_;
      }
    }
  }
  ++frames_since_relocalisation_;
  result.state = state_;
  if (state_ == TrackingState::kOk && current_->has_pose && reference_) {
    const Pose T_world_cam = current_->T_cam_world.inverse();
    result.T_world_cam = T_world_cam;
    if (options_.record_trajectory) {
      records_.emplace_back(current_->timestamp, reference_->id(),
                            reference_->T_cam_world() * T_world_cam);
    }
  }
  // The first keyframe waited for this frame's motion (MoveFirstKeyframeWithOwnMotion), which
  // has it now or never will.
  if (pending_keyframe_ && pending_keyframe_->frame_index() != current_->index)
    InsertPendingKeyframe();
  result.tracked_points = current_->TrackedPoints();
  result.track_ms = watch.ElapsedMillis();
  result.track_cpu_ms = cpu.ElapsedMillis();
  last_ = std::move(current_);
  return result;
}

void Tracker::Finish() {
  const auto lock = map_->Lock();
  InsertPendingKeyframe();
}

void Tracker::InsertPendingKeyframe() {
  if (pending_keyframe_) mapping_->Insert(pending_keyframe_);
  pending_keyframe_.reset();
}

bool Tracker::CompensatesLag(const TrackingFrame& frame) const {
  return options_.compensate_depth_lag && !frame.depth_mm.empty() && frame.depth_time_offset != 0 &&
         std::isfinite(frame.depth_time_offset);
}

std::optional<Pose> Tracker::DepthCameraPose(double offset) const {
  if (!options_.compensate_depth_lag || offset == 0 || !std::isfinite(offset) ||
      state_ != TrackingState::kOk || !velocity_ || !(velocity_interval_ > 0)) {
    return std::nullopt;
  }
  // The camera's motion from the colour image's time to the depth image's.
  return MotionOver(*velocity_, velocity_interval_, offset);
}

void Tracker::AddMapPoint(TrackingFrame* frame, Keyframe* keyframe, const Pose& T_world_cam,
                          int i) {
  const cv::Point2f& pt = frame->features.keypoints[i].pt;
  auto point = std::make_shared<MapPoint>(
      map_->NextMapPointId(),
      T_world_cam * camera_.BackProject(pt.x, pt.y, frame->features.depth[i]));
  map_->AddMapPoint(point);
  map_->AddObservation(point, keyframe, i);
  point->UpdateDescriptor();
  point->UpdateNormalAndDepth(*orb_);
  frame->points[i] = point;
  frame->outlier[i] = false;
}

bool Tracker::YoungSegment() const {
  return map_->keyframes_created() - segment_start_.value() < kYoungSegmentKeyframes;
}

bool Tracker::RestartDue() const {
  if (!last_T_world_cam_) return false;
  return YoungSegment() || current_->timestamp - lost_since_ >= options_.relocalisation_seconds;
}

bool Tracker::Initialize(TrackingFrame* frame, const Pose& T_world_cam, bool restart,
                         bool tracked) {
  int with_depth = 0;
  for (float d : frame->features.depth) with_depth += d > 0;
  if (frame->size() < 300 || with_depth < 100) return false;
  InsertPendingKeyframe();
  // A failed search may have left matches with the old map's points.
  frame->ClearMatches();
  frame->SetPose(T_world_cam.inverse());
  // Started again at the frame after the last tracked one, or at a frame tracked itself, the
  // pose is as good as tracking's (asked before the new keyframe counts in the segment it leaves).
  const bool reset =
      restart && (tracked || (YoungSegment() &&
                              frame->timestamp - last_tracked_timestamp_ <= 1.5 / camera_.fps));
  auto keyframe =
      std::make_shared<Keyframe>(map_->NextKeyframeId(), frame->timestamp, frame->index,
                                 frame->features, T_world_cam, camera_.width, camera_.height);
  keyframe->restart = restart;
  keyframe->reset = reset;
  keyframe->bgr = frame->bgr;
  frame->HandDepthTo(keyframe.get());
  segment_start_ = keyframe->id();
  last_T_world_cam_ = T_world_cam;
  last_tracked_timestamp_ = frame->timestamp;
  map_->AddKeyframe(keyframe);
  for (int i = 0; i < frame->size(); ++i) {
    if (frame->features.depth[i] > 0) AddMapPoint(frame, keyframe.get(), T_world_cam, i);
  }
  CCMD_LOG(INFO) << (restart ? "map segment" : "map") << " initialised with "
                 << keyframe->TrackedPoints(1) << " points at frame " << frame->index;
  reference_ = keyframe;
  last_keyframe_ = keyframe;
  last_keyframe_frame_ = frame->index;
  frame->reference = keyframe;
  if (options_.record_trajectory) {
    // Placed, not tracked: nothing links it to the keyframe before.
    keyframe_records_.push_back({keyframe->id(), false, records_.size(),
                                 FrameRecord(frame->timestamp, keyframe->id(), Pose::Identity())});
  }
  tracked_since_keyframe_ = true;
  if (frame->motion_pending) {
    pending_keyframe_ = keyframe;
  } else {
    mapping_->Insert(keyframe);
  }
  return true;
}

int Tracker::OptimizeCurrentPose(const PosePrior* prior) {
  std::vector<PoseObservation> observations;
  std::vector<int> keypoint_of;
  for (int i = 0; i < current_->size(); ++i) {
    const MapPointPtr& p = current_->points[i];
    if (!p || p->bad()) continue;
    const cv::KeyPoint& kp = current_->features.keypoints[i];
    const double z = current_->features.depth[i];
    observations.push_back({p->position(), Eigen::Vector2d(kp.pt.x, kp.pt.y), z,
                            orb_->inv_sigma2()[kp.octave], current_->features.DepthInformation(i)});
    keypoint_of.push_back(i);
  }
  const Intrinsics k{camera_.fx, camera_.fy, camera_.cx, camera_.cy};
  const PoseOptimizationResult r = OptimizePose(current_->T_cam_world, observations, k, {}, prior);
  current_->SetPose(r.T_cam_world);
  for (std::size_t j = 0; j < keypoint_of.size(); ++j)
    current_->outlier[keypoint_of[j]] = !r.inlier[j];
  return r.inliers;
}

namespace {

// Drops outlier matches; returns matches with points that are in the map (observed).
int DiscardOutliers(TrackingFrame* frame) {
  int in_map = 0;
  for (int i = 0; i < frame->size(); ++i) {
    if (!frame->points[i]) continue;
    if (frame->outlier[i]) {
      frame->points[i] = nullptr;
      frame->outlier[i] = false;
    } else if (frame->points[i]->num_observations() > 0) {
      ++in_map;
    }
  }
  return in_map;
}

}  // namespace

Pose Tracker::PredictedMotion() const {
  // Constant velocity in time: a frame that comes after dropped ones has moved further.
  const double interval = current_->timestamp - last_->timestamp;
  if (!(velocity_interval_ > 0) || !(interval > 0)) return *velocity_;
  return MotionOver(*velocity_, velocity_interval_, interval).inverse();
}

bool Tracker::TrackWithMotionModel() {
  current_->SetPose(PredictedMotion() * last_->T_cam_world);
  std::fill(current_->points.begin(), current_->points.end(), nullptr);
  constexpr float kRadius = 15.0f;
  int matches = SearchFromLastFrame(current_.get(), *last_, kRadius, *orb_, camera_);
  if (matches < 20) {
    ++motion_model_misses_;
    std::fill(current_->points.begin(), current_->points.end(), nullptr);
    matches = SearchFromLastFrame(current_.get(), *last_, 2 * kRadius, *orb_, camera_);
  }
  if (matches < 20) return false;
  const int inliers = OptimizeCurrentPose();
  const int in_map = DiscardOutliers(current_.get());
  CCMD_LOG(DEBUG) << "frame " << current_->index << " motion model: " << matches << " matches, "
                  << inliers << " inliers, " << in_map << " in map";
  return in_map >= 10;
}

bool Tracker::TrackReferenceKeyframe() {
  if (!reference_ || reference_->bad()) return false;
  std::fill(current_->points.begin(), current_->points.end(), nullptr);
  const int matches = SearchByDescriptor(current_.get(), *reference_);
  if (matches < 15) return false;
  current_->SetPose(last_ && last_->has_pose ? last_->T_cam_world : reference_->T_cam_world());
  const int from_last = OptimizeCurrentPose();
  // The camera may have moved further than the optimisation finds its way from the last pose
  // (after a gap in the frames, where a turn can be taken for a shift, and the matches that
  // disagree are dropped as outliers): the matches alone give another start, kept when more of
  // them agree with where it leads.
  const std::vector<MapPointPtr> points = current_->points;
  const std::vector<bool> outlier = current_->outlier;
  const Pose T_from_last = current_->T_cam_world;
  int inliers = PoseFromMatchesAlone() ? OptimizeCurrentPose() : 0;
  if (inliers <= from_last) {
    current_->points = points;
    current_->outlier = outlier;
    current_->SetPose(T_from_last);
    inliers = from_last;
  }
  const int in_map = DiscardOutliers(current_.get());
  CCMD_LOG(DEBUG) << "frame " << current_->index << " reference keyframe: " << matches
                  << " matches, " << inliers << " inliers, " << in_map << " in map";
  return in_map >= 10;
}

bool Tracker::PoseFromMatchesAlone() {
  std::vector<cv::Point3f> object;
  std::vector<cv::Point2f> image;
  std::vector<int> index;
  for (int i = 0; i < current_->size(); ++i) {
    if (!current_->points[i]) continue;
    const Eigen::Vector3d& p = current_->points[i]->position();
    object.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()),
                        static_cast<float>(p.z()));
    image.push_back(current_->features.keypoints[i].pt);
    index.push_back(i);
  }
  if (object.size() < 15) return false;
  std::vector<int> inliers;
  const std::optional<Pose> T = SolvePnpRansac(object, image, camera_, {}, &inliers);
  if (!T) return false;
  std::vector<bool> keep(current_->size(), false);
  for (int k : inliers) keep[index[k]] = true;
  for (int i = 0; i < current_->size(); ++i) {
    if (keep[i]) continue;
    current_->points[i] = nullptr;
    current_->outlier[i] = false;
  }
  current_->SetPose(*T);
  return true;
}

bool Tracker::Relocalize() {
  // Candidates: every keyframe of the current segment in the (bounded) map, newest first. An
  // earlier segment's poses are off by the unknown motion while lost: only the server's loop
  // closure can place the two against each other.
  std::vector<KeyframePtr> candidates;
  for (auto it = map_->keyframes().rbegin();
       it != map_->keyframes().rend() && it->first >= segment_start_; ++it)
    candidates.push_back(it->second);
  for (const KeyframePtr& kf : candidates) {
    current_->ClearMatches();
    if (SearchByDescriptor(current_.get(), *kf) < 15) continue;
    if (!PoseFromMatchesAlone()) continue;
    int good = OptimizeCurrentPose();
    if (good < 10) continue;
    DiscardOutliers(current_.get());
    // Add points of the candidate's neighbourhood by projection, then refine again.
    std::vector<MapPointPtr> nearby;
    std::unordered_set<const MapPoint*> seen;
    std::vector<Keyframe*> neighbourhood = kf->BestCovisible(10);
    neighbourhood.push_back(kf.get());
    for (Keyframe* n : neighbourhood) {
      for (const MapPointPtr& p : n->points()) {
        if (p && !p->bad() && seen.insert(p.get()).second) nearby.push_back(p);
      }
    }
    SearchLocalPoints(current_.get(), nearby, 3.0f, *orb_, camera_);
    good = OptimizeCurrentPose();
    if (good < 40) continue;
    DiscardOutliers(current_.get());
    CCMD_LOG(INFO) << "relocalised at frame " << current_->index << " against keyframe " << kf->id()
                   << " with " << good << " inliers";
    last_relocalisation_frame_ = current_->index;
    frames_since_relocalisation_ = 0;
    reference_ = kf;
    return true;
  }
  std::fill(current_->points.begin(), current_->points.end(), nullptr);
  return false;
}

void Tracker::UpdateLocalMap() {
  // Keyframes that see the current matches, weighted by how many they see.
  std::unordered_map<Keyframe*, int> counter;
  for (int i = 0; i < current_->size(); ++i) {
    const MapPointPtr& p = current_->points[i];
    if (!p || p->bad()) {
      current_->points[i] = nullptr;
      continue;
    }
    for (const auto& o : p->observations()) counter[o.keyframe]++;
  }
  if (counter.empty()) return;
  std::vector<std::pair<Keyframe*, int>> ranked(counter.begin(), counter.end());
  std::sort(ranked.begin(), ranked.end(), [](const auto& a, const auto& b) {
    return a.second != b.second ? a.second > b.second : a.first->id() < b.first->id();
  });
  std::vector<Keyframe*> local;
  std::unordered_set<Keyframe*> in_local;
  for (const auto& [kf, n] : ranked) {
    if (!kf->bad() && in_local.insert(kf).second) local.push_back(kf);
  }
  // Their strongest neighbours too, up to 80 keyframes (ORB-SLAM's local map).
  const std::size_t direct = local.size();
  for (std::size_t i = 0; i < direct && local.size() < 80; ++i) {
    for (Keyframe* n : local[i]->BestCovisible(10)) {
      if (in_local.insert(n).second) {
        local.push_back(n);
        break;
      }
    }
    if (Keyframe* parent = local[i]->parent(); parent && in_local.insert(parent).second)
      local.push_back(parent);
  }
  local_keyframes_.clear();
  for (Keyframe* kf : local) local_keyframes_.push_back(map_->keyframe(kf->id()));
  if (KeyframePtr best = map_->keyframe(ranked.front().first->id())) {
    reference_ = best;
    current_->reference = best;
  }
  local_points_.clear();
  std::unordered_set<const MapPoint*> seen;
  for (const KeyframePtr& kf : local_keyframes_) {
    if (!kf) continue;
    for (const MapPointPtr& p : kf->points()) {
      if (p && !p->bad() && seen.insert(p.get()).second) local_points_.push_back(p);
    }
  }
}

bool Tracker::TrackLocalMap(bool depth_may_confirm) {
  UpdateLocalMap();
  // Points already matched are not searched again; they count as seen.
  std::unordered_set<const MapPoint*> matched;
  for (int i = 0; i < current_->size(); ++i) {
    if (const MapPointPtr& p = current_->points[i]) {
      p->IncreaseVisible();
      matched.insert(p.get());
    }
  }
  std::vector<MapPointPtr> candidates;
  candidates.reserve(local_points_.size());
  for (const MapPointPtr& p : local_points_) {
    if (!matched.count(p.get())) candidates.push_back(p);
  }
  const float radius = frames_since_relocalisation_ < 2 ? 5.0f : 3.0f;
  const int found = SearchLocalPoints(current_.get(), candidates, radius, *orb_, camera_);
  const std::optional<PosePrior> prior = FrameDepthPrior();
  int inliers = OptimizeCurrentPose(prior ? &*prior : nullptr);
  if (MoveKeypointsWithOwnMotion()) inliers = OptimizeCurrentPose(prior ? &*prior : nullptr);
  // This frame was tracked against the first keyframe's points as read, so its motion is off by
  // part of what moving them corrects: a second round measures it again from the moved points.
  for (int round = 0; round < 2 && MoveFirstKeyframeWithOwnMotion(); ++round) {
    MoveKeypointsWithOwnMotion();
    inliers = OptimizeCurrentPose(prior ? &*prior : nullptr);
  }
  CCMD_LOG(DEBUG) << "frame " << current_->index << " local map: " << local_keyframes_.size()
                  << " keyframes, " << local_points_.size() << " points, " << candidates.size()
                  << " candidates, " << found << " found, " << inliers << " inliers";
  matches_inliers_ = 0;
  for (int i = 0; i < current_->size(); ++i) {
    const MapPointPtr& p = current_->points[i];
    if (!p) continue;
    if (!current_->outlier[i]) {
      p->IncreaseFound();
      if (p->num_observations() > 0) ++matches_inliers_;
    }
  }
  const bool recently_relocalised =
      frames_since_relocalisation_ < options_.max_frames_between_keyframes;
  if (recently_relocalised && matches_inliers_ < 50) return false;
  if (matches_inliers_ >= 30) return true;
  // Plain walls leave few features, but each has a depth, and the frame's depth image can
  // vouch for the pose they give: lost here, the agent would start a new map segment.
  return depth_may_confirm && matches_inliers_ >= kMinInliersWithDepth && DepthConfirmsPose();
}

bool Tracker::MoveKeypointsWithMotion(TrackingFrame* frame, const TrackingFrame& before,
                                      const TrackingFrame& after) const {
  const double interval = after.timestamp - before.timestamp;
  if (!(interval > 0)) return false;
  const RollingShutter shutter{options_.rolling_shutter_readout,
                               after.T_cam_world * before.T_cam_world.inverse(), interval};
  if (CompensatesLag(*frame))
    frame->SetDepthPose(MotionOver(shutter.velocity, interval, frame->depth_time_offset));
  MoveKeypointsAgain(frame, shutter, *orb_, camera_, options_);
  return true;
}

bool Tracker::MoveKeypointsWithOwnMotion() {
  if (current_->keypoints_as_read.empty() || !last_ || !last_->has_pose) return false;
  return MoveKeypointsWithMotion(current_.get(), *last_, *current_);
}

bool Tracker::MoveFirstKeyframeWithOwnMotion() {
  if (!pending_keyframe_ || !last_ || last_->index != pending_keyframe_->frame_index() ||
      !current_->has_pose)
    return false;
  // The motion over the interval right after the keyframe's frame.
  if (!MoveKeypointsWithMotion(last_.get(), *last_, *current_)) return false;
  Keyframe* keyframe = pending_keyframe_.get();
  keyframe->ReplaceFeatures(last_->features, camera_.width, camera_.height);
  last_->HandDepthTo(keyframe);
  // Its points, seen by it alone, go where its keypoints' new depths put them.
  const Pose& T_world_cam = keyframe->T_world_cam();
  for (int i = 0; i < last_->size(); ++i) {
    const MapPointPtr& p = keyframe->point(i);
    const float z = last_->features.depth[i];
    if (!p || p->bad() || p->num_observations() != 1 || z <= 0) continue;
    const cv::Point2f& pt = last_->features.keypoints[i].pt;
    p->set_position(T_world_cam * camera_.BackProject(pt.x, pt.y, z));
    p->UpdateNormalAndDepth(*orb_);
  }
  return true;
}

bool Tracker::NeedNewKeyframe() const {
  const int keyframes = static_cast<int>(map_->keyframes().size());
  const int max_frames = options_.max_frames_between_keyframes;
  if (frames_since_relocalisation_ < max_frames && keyframes > max_frames) return false;
  if (!mapping_->CanAccept()) return false;
  const int reference_matches = reference_ ? reference_->TrackedPoints(1) : 0;
  int tracked_close = 0, untracked_close = 0;
  for (int i = 0; i < current_->size(); ++i) {
    const float z = current_->features.depth[i];
    if (z <= 0 || z > camera_.far_depth_m) continue;
    if (current_->points[i] && !current_->outlier[i]) {
      ++tracked_close;
    } else {
      ++untracked_close;
    }
  }
  const bool need_close = tracked_close < 100 && untracked_close > 70;
  const double ratio = (keyframes < 2 ? 0.8 : 1.0) * options_.keyframe_tracked_ratio *
                       mapping_->KeyframeRatioScale();
  const int since = current_->index - last_keyframe_frame_;
  const bool c1a = since >= max_frames;
  const bool c1b = mapping_->Idle();
  const bool c1c = matches_inliers_ < 0.25 * reference_matches || need_close;
  const bool c2 =
      (matches_inliers_ < ratio * reference_matches || need_close) && matches_inliers_ > 15;
  return (c1a || c1b || c1c) && c2;
}

void Tracker::CreateKeyframe() {
  InsertPendingKeyframe();
  auto keyframe = std::make_shared<Keyframe>(
      map_->NextKeyframeId(), current_->timestamp, current_->index, current_->features,
      current_->T_cam_world.inverse(), camera_.width, camera_.height);
  keyframe->bgr = current_->bgr;
  // The keyframe's depth moves with the motion measured up to this frame, a frame more recent
  // than the prediction (its keypoints took the same, MoveKeypointsWithOwnMotion, unless the
  // frame was placed by its depth instead of the local map).
  if (current_->T_colour_depth)
    current_->SetDepthPose(DepthCameraPose(current_->depth_time_offset));
  current_->HandDepthTo(keyframe.get());
  map_->AddKeyframe(keyframe);
  for (int i = 0; i < current_->size(); ++i) {
    const MapPointPtr& p = current_->points[i];
    if (p && !current_->outlier[i] && !p->bad()) map_->AddObservation(p, keyframe.get(), i);
  }
  // New points from measured depth: all close ones, or at least the 100 nearest (ORB-SLAM).
  std::vector<std::pair<float, int>> by_depth;
  for (int i = 0; i < current_->size(); ++i) {
    if (current_->features.depth[i] > 0) by_depth.emplace_back(current_->features.depth[i], i);
  }
  std::sort(by_depth.begin(), by_depth.end());
  const Pose T_world_cam = keyframe->T_world_cam();
  int considered = 0;
  for (const auto& [z, i] : by_depth) {
    if (!keyframe->point(i)) AddMapPoint(current_.get(), keyframe.get(), T_world_cam, i);
    // Far points only while fewer than 100 points have been considered in all.
    if (++considered > 100 && z > camera_.far_depth_m) break;
  }
  reference_ = keyframe;
  current_->reference = keyframe;
  last_keyframe_ = keyframe;
  last_keyframe_frame_ = current_->index;
  mapping_->Insert(keyframe);
}

namespace {

// How far a frame at `at` is on the way from `start` to `end`, by where it is rather than by
// when: tracking drifts as the view changes, not as time passes, so a camera that stood still
// took no share of the drift while it did. Its distances to both ends, in position and in
// angle, give the share (the mean of the two when the camera both moved and turned); where it
// did neither (under 1 mm and 0.1 degrees either way), the frame count decides.
double ShareOfTheWay(const Pose& start, const Pose& at, const Pose& end, double by_count) {
  constexpr double kStillMetres = 1e-3, kStillRadians = 0.1 * M_PI / 180;
  const Pose from_start = start.inverse() * at, to_end = at.inverse() * end;
  const double done_m = from_start.translation().norm(), left_m = to_end.translation().norm();
  const double done_rad = RotationAngle(from_start), left_rad = RotationAngle(to_end);
  const bool moved = done_m + left_m > kStillMetres, turned = done_rad + left_rad > kStillRadians;
  if (moved && turned) return 0.5 * (done_m / (done_m + left_m) + done_rad / (done_rad + left_rad));
  if (moved) return done_m / (done_m + left_m);
  if (turned) return done_rad / (done_rad + left_rad);
  return by_count;
}

}  // namespace

Trajectory FrameTrajectoryOf(const std::vector<Tracker::FrameRecord>& records,
                             const std::vector<Tracker::KeyframeRecord>& keyframes,
                             const std::function<std::optional<Pose>(KeyframeId)>& keyframe_pose) {
  std::vector<std::optional<Pose>> poses(records.size());
  for (std::size_t i = 0; i < records.size(); ++i) {
    const auto T_world_ref = keyframe_pose(records[i].reference);
    if (T_world_ref) poses[i] = *T_world_ref * records[i].T_ref_cam();
  }
  // A frame is tracked against the map as it was, and tracking drifts until the next keyframe,
  // whose local BA (with its depth alignments) then moves it by what the drift was. Each
  // keyframe's move, from where tracking put it to where it is now, is spread over the frames
  // since the keyframe before in proportion to their number: the frame right after a keyframe
  // keeps its pose, the one before the next keyframe takes nearly all of that keyframe's move.
  for (std::size_t k = 1; k < keyframes.size(); ++k) {
    const Tracker::KeyframeRecord &kf = keyframes[k], &before = keyframes[k - 1];
    if (!kf.continuous || kf.record <= before.record + 1 || kf.record > poses.size()) continue;
    const auto T_world_ref = keyframe_pose(kf.tracked.reference);
    const auto T_world_kf = keyframe_pose(kf.keyframe);
    if (!T_world_ref || !T_world_kf) continue;
    const Pose tracked = *T_world_ref * kf.tracked.T_ref_cam();
    const Pose move = tracked.inverse() * *T_world_kf;  // in the tracked keyframe's frame
    const std::optional<Pose>& start = poses[before.record];
    for (std::size_t i = before.record + 1; i < kf.record; ++i) {
      if (!poses[i]) continue;
      const double by_count =
          static_cast<double>(i - before.record) / static_cast<double>(kf.record - before.record);
      const double alpha = start ? ShareOfTheWay(*start, *poses[i], tracked, by_count) : by_count;
      *poses[i] =
          tracked * InterpolatePose(Pose::Identity(), move, alpha) * tracked.inverse() * *poses[i];
    }
  }
  Trajectory trajectory;
  for (std::size_t i = 0; i < records.size(); ++i) {
    if (poses[i]) trajectory.push_back({records[i].timestamp, *poses[i]});
  }
  return trajectory;
}

}  // namespace ccmd
