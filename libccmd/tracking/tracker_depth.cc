// The tracker's uses of the current frame's depth image beside its features: a prior in the
// pose optimisation, the confirmation of a pose found on few features, and the bridge that
// places frames by their depth alone through stretches without texture.

#include <algorithm>
#include <cmath>

#include "libccmd/optim/bundle_adjuster.h"
#include "libccmd/tracking/depth_alignment.h"
#include "libccmd/tracking/tracker.h"
#include "libccmd/util/logging.h"

namespace ccmd {

const Keyframe* Tracker::NewestLocalKeyframeWithDepth() const {
  const Keyframe* newest = nullptr;
  for (const KeyframePtr& kf : local_keyframes_) {
    if (!kf->bad() && kf->depth_model && (!newest || kf->id() > newest->id())) newest = kf.get();
  }
  return newest;
}

double Tracker::AllowedDepthFitSigmas() const {
  // Residuals beyond twice the sensor's noise, or beyond what alignments between keyframes
  // whose poses the features confirmed reach (on rendered depth the cells' planes, not the
  // noise, set the residuals: up to 2.9 sigma of configs/icl_nuim.yaml): surfaces matched
  // wrongly.
  return std::max(2.0, mapping_->DepthFitSigmas());
}

std::optional<PosePrior> Tracker::FrameDepthPrior() const {
  if (options_.frame_depth_weight <= 0 || current_->depth_mm.empty()) return std::nullopt;
  const Keyframe* target = NewestLocalKeyframeWithDepth();
  if (!target) return std::nullopt;
  // Coarser than the keyframes' models (8x8 pixel blocks, every other one used: 1200 cells
  // for VGA) and fewer iterations: the features' pose is close, and this runs every frame.
  const DepthModel model = DepthModel::FromDepth(current_->DepthAtColourTime(camera_), camera_, 8,
                                                 options_.min_depth, options_.max_depth);
  DepthAlignmentOptions alignment;
  alignment.iterations = 6;
  const Pose T_kf_cam = target->T_cam_world() * current_->T_cam_world.inverse();
  const auto aligned =
      AlignDepth(model, *target->depth_model, T_kf_cam, options_.depth_noise, alignment);
  if (!aligned || !StaysNearStart(*aligned, T_kf_cam)) return std::nullopt;
  PosePrior prior;
  prior.T_b_world = target->T_cam_world();
  prior.T_b_a = aligned->T_target_source;
  prior.sqrt_information = SqrtInformation(options_.frame_depth_weight * aligned->information);
  return prior;
}

bool Tracker::DepthConfirmsPose() const {
  if (current_->depth_mm.empty()) return false;
  const Keyframe* target = NewestLocalKeyframeWithDepth();
  if (!target) return false;
  const DepthModel model = DepthModel::FromDepth(current_->DepthAtColourTime(camera_), camera_, 4,
                                                 options_.min_depth, options_.max_depth);
  const Pose start = target->T_cam_world() * current_->T_cam_world.inverse();
  const auto aligned = AlignDepth(model, *target->depth_model, start, options_.depth_noise);
  if (!aligned) return false;
  const double fit_sigmas = aligned->rms / options_.depth_noise.Sigma(aligned->mean_range);
  const double moved = TranslationDistance(aligned->T_target_source, start);
  const double turned = RotationDistance(aligned->T_target_source, start);
  CCMD_LOG(DEBUG) << "frame " << current_->index << ", " << matches_inliers_
                  << " inliers: its depth moves the pose " << moved * 1e3 << " mm, "
                  << turned * 180 / M_PI << " deg, fit " << fit_sigmas << " sigma";
  // Where the view's geometry leaves a direction free the alignment stays at the features'
  // pose; the directions it fixes must agree with them to well under what a wrong pose is off.
  return fit_sigmas <= AllowedDepthFitSigmas() && moved <= kMaxDepthCorrection_m &&
         turned <= kMaxDepthCorrection_rad;
}

void Tracker::EndBridge() {
  bridged_since_.reset();
  bridge_model_.reset();
}

bool Tracker::BridgeWithDepth() {
  if (options_.depth_bridge_seconds <= 0 || current_->depth_mm.empty() || !last_ ||
      !last_->has_pose)
    return false;
  if (bridged_since_ && current_->timestamp - *bridged_since_ > options_.depth_bridge_seconds)
    return false;
  const Pose predicted = velocity_ ? PredictedMotion() * last_->T_cam_world : last_->T_cam_world;
  DepthModel model = DepthModel::FromDepth(current_->DepthAtColourTime(camera_), camera_, 4,
                                           options_.min_depth, options_.max_depth);
  // Without features to back it, the alignment alone must hold: the surfaces it matched must
  // fix every direction of the pose, and fit as well as the sensor measures.
  auto place = [&](const DepthModel& target, const Pose& T_target_world) -> std::optional<Pose> {
    const Pose start = T_target_world * predicted.inverse();
    const auto aligned = AlignDepth(model, target, start, options_.depth_noise);
    if (!aligned || !StaysNearStart(*aligned, start)) return std::nullopt;
    const double conditioning = Conditioning(*aligned);
    const double fit_sigmas = aligned->rms / options_.depth_noise.Sigma(aligned->mean_range);
    const double allowed_sigmas = AllowedDepthFitSigmas();
    CCMD_LOG(DEBUG) << "frame " << current_->index << " depth alone: conditioning " << conditioning
                    << ", " << aligned->inliers << " cells, rms " << aligned->rms * 1e3 << " mm ("
                    << fit_sigmas << " sigma, " << allowed_sigmas << " allowed)";
    if (conditioning < kMinConditioningAlone || fit_sigmas > allowed_sigmas) return std::nullopt;
    // Re-projected onto SO(3): each bridged pose starts the next frame's prediction, and a
    // product's rounding, fed back so frame after frame, would grow into a shear.
    return Orthonormalized(aligned->T_target_source.inverse() * T_target_world);
  };
  // The newest keyframe of this segment whose depth model local mapping has made holds the
  // pose without drift; where the view has left it, the frame before.
  std::optional<Pose> T_cam_world;
  for (auto it = map_->keyframes().rbegin();
       it != map_->keyframes().rend() && it->first >= segment_start_; ++it) {
    if (it->second->bad() || !it->second->depth_model) continue;
    T_cam_world = place(*it->second->depth_model, it->second->T_cam_world());
    break;
  }
  if (!T_cam_world && !last_->depth_mm.empty()) {
    if (!bridge_model_) {
      bridge_model_ = std::make_shared<const DepthModel>(DepthModel::FromDepth(
          last_->DepthAtColourTime(camera_), camera_, 4, options_.min_depth, options_.max_depth));
    }
    T_cam_world = place(*bridge_model_, last_->T_cam_world);
  }
  if (!T_cam_world) return false;
  // From there the local map's points may be found again (the view regained texture).
  current_->SetPose(*T_cam_world);
  current_->ClearMatches();
  if (TrackLocalMap(/*depth_may_confirm=*/false)) return true;
  current_->SetPose(*T_cam_world);
  current_->ClearMatches();
  matches_inliers_ = 0;
  if (!bridged_since_) {
    CCMD_LOG(INFO) << "too few features at frame " << current_->index
                   << ": placed by its depth alone until they come back";
    bridged_since_ = current_->timestamp;
  }
  bridge_model_ = std::make_shared<const DepthModel>(std::move(model));
  return true;
}

bool Tracker::RestartAtBridgedFrame() {
  if (!bridged_since_ || current_->timestamp - *bridged_since_ < options_.relocalisation_seconds ||
      !Initialize(current_.get(), current_->T_cam_world.inverse(), /*restart=*/true,
                  /*tracked=*/true))
    return false;
  CCMD_LOG(WARNING) << "frame " << current_->index << " has features again but the map is not "
                    << "in view: a new map segment starts there, at the pose its depth gave";
  ++restarts_;
  return true;
}

}  // namespace ccmd
