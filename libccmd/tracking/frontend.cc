#include "libccmd/tracking/frontend.h"

#include <cmath>
#include <cstdio>

#include "libccmd/util/logging.h"

namespace ccmd {

Status TrackingOptions::Validate() const {
  auto fail = [](const char* reason) { return InvalidArgument(reason); };
  CCMD_RETURN_IF_ERROR(orb.Validate());
  if (!(min_depth > 0 && max_depth > min_depth))
    return fail("depth range must satisfy 0 < min < max");
  CCMD_RETURN_IF_ERROR(depth_noise.Validate());
  if (local_ba_window < 1 || local_ba_window > 100)
    return fail("local BA window must be in [1, 100]");
  // Bounds before the sum, which could overflow.
  if (local_ba_robust_iterations < 0 || local_ba_iterations < 0 ||
      local_ba_robust_iterations > 100 || local_ba_iterations > 100 ||
      local_ba_robust_iterations + local_ba_iterations < 1) {
    return fail("local BA iterations must be in [0, 100], at least one in all");
  }
  if (!(local_ba_function_tolerance >= 0 && local_ba_function_tolerance < 1)) {
    return fail("local BA function tolerance must be in [0, 1)");
  }
  if (!(cpu_budget >= 0 && cpu_budget <= 256))
    return fail("CPU budget must be in [0, 256] cores (0: none)");
  if (depth_alignment_neighbours < 0 || depth_alignment_neighbours > 20)
    return fail("depth alignment neighbours must be in [0, 20]");
  if (!(depth_alignment_weight >= 0)) return fail("depth alignment weight must be >= 0");
  if (!(frame_depth_weight >= 0) || !std::isfinite(frame_depth_weight))
    return fail("frame depth weight must be finite and >= 0");
  if (!(rolling_shutter_readout >= 0 && rolling_shutter_readout <= 1))
    return fail("rolling shutter readout must be in [0, 1] s (0: a global shutter)");
  if (!(depth_bridge_seconds >= 0 && depth_bridge_seconds <= 3600))
    return fail("depth bridge seconds must be in [0, 3600] (0: off)");
  if (max_keyframes < local_ba_window + 5)
    return fail("max keyframes must exceed the local BA window by 5");
  if (max_frames_between_keyframes < 0) return fail("max frames between keyframes must be >= 0");
  if (!(relocalisation_seconds >= 0 && relocalisation_seconds <= 3600))
    return fail("relocalisation seconds must be in [0, 3600]");
  if (!(triangulation_neighbours >= 0 && triangulation_neighbours <= 100))
    return fail("triangulation neighbours must be in [0, 100] (0: off)");
  if (max_new_points_per_keyframe < 0)
    return fail("max new points per keyframe must be >= 0 (0: all)");
  if (!(keyframe_tracked_ratio > 0 && keyframe_tracked_ratio < 1))
    return fail("keyframe tracked ratio must be in (0, 1)");
  return rgbd_selection.Validate();
}

void TrackingOptions::Describe(OptionsWriter* out) const {
  out->Nested("orb", orb);
  out->Add("min_depth", min_depth);
  out->Add("max_depth", max_depth);
  out->Add("subpixel_keypoints", subpixel_keypoints);
  out->Nested("depth_noise", depth_noise);
  out->Add("max_frames_between_keyframes", max_frames_between_keyframes);
  out->Add("keyframe_tracked_ratio", keyframe_tracked_ratio);
  out->Add("relocalisation_seconds", relocalisation_seconds);
  out->Add("local_ba_window", local_ba_window);
  out->Add("local_ba_robust_iterations", local_ba_robust_iterations);
  out->Add("local_ba_iterations", local_ba_iterations);
  out->Add("local_ba_function_tolerance", local_ba_function_tolerance);
  out->Add("cpu_budget", cpu_budget);
  out->Add("mapping_follows_budget", mapping_follows_budget);
  out->Add("depth_alignment_neighbours", depth_alignment_neighbours);
  out->Add("depth_alignment_weight", depth_alignment_weight);
  out->Add("frame_depth_weight", frame_depth_weight);
  out->Add("depth_bridge_seconds", depth_bridge_seconds);
  out->Add("compensate_depth_lag", compensate_depth_lag);
  out->Add("rolling_shutter_readout", rolling_shutter_readout);
  out->Add("triangulation_neighbours", triangulation_neighbours);
  out->Add("max_keyframes", max_keyframes);
  out->Add("cull_redundant_keyframes", cull_redundant_keyframes);
  out->Add("synchronous_mapping", synchronous_mapping);
  out->Add("record_trajectory", record_trajectory);
  out->Add("max_new_points_per_keyframe", max_new_points_per_keyframe);
  out->Add("send_unlinked_keypoints", send_unlinked_keypoints);
  out->Add("pose_update_min_translation", pose_update_min_translation);
  out->Add("pose_update_min_rotation", pose_update_min_rotation);
  out->Nested("rgbd_selection", rgbd_selection);
}

StatusOr<std::unique_ptr<Frontend>> Frontend::Create(const PinholeCamera& camera,
                                                     const TrackingOptions& options,
                                                     KeyframeSink* sink) {
  CCMD_RETURN_IF_ERROR(camera.Validate().WithContext("camera"));
  CCMD_RETURN_IF_ERROR(options.Validate().WithContext("tracking options"));
  return std::unique_ptr<Frontend>(new Frontend(camera, options, sink));
}

Frontend::Frontend(const PinholeCamera& camera, const TrackingOptions& options, KeyframeSink* sink)
    : camera_(camera), options_(options), orb_(options.orb) {
  map_.set_keep_removed(options_.record_trajectory);
  mapper_ = std::make_unique<LocalMapper>(camera_, options_, &map_, &orb_, sink);
  tracker_ = std::make_unique<Tracker>(camera_, options_, &map_, &orb_, mapper_.get());
}

Frontend::~Frontend() { Finish(); }

TrackResult Frontend::ProcessFrame(const RgbdFrame& frame) {
  MeasureDepthNoise(frame);
  const TrackResult result = tracker_->Track(frame);
  if (options_.synchronous_mapping) mapper_->ProcessPending();
  ++stats_.frames;
  stats_.extract_ms_total += result.extract_ms;
  stats_.track_ms_total += result.track_ms;
  stats_.extract_cpu_ms_total += result.extract_cpu_ms;
  stats_.track_cpu_ms_total += result.track_cpu_ms;
  mapper_->AddFrameCpu(result.extract_cpu_ms + result.track_cpu_ms);
  if (result.state == TrackingState::kOk) {
    initialised_ = true;
    ++stats_.tracked_frames;
    stats_.depth_only_frames += result.depth_only;
  } else if (initialised_) {
    ++stats_.lost_frames;
  }
  return result;
}

void Frontend::Finish() {
  ReportDepthNoise();
  tracker_->Finish();
  mapper_->Finish();
}

// Every 10th of the first 100 frames: a few seconds of a moving camera see its surfaces at
// several ranges, and cost about a millisecond each.
void Frontend::MeasureDepthNoise(const RgbdFrame& frame) {
  constexpr int kEvery = 10, kSamples = 10;
  if (noise_reported_ || stats_.frames % kEvery != 0 || frame.depth_mm.empty()) return;
  noise_meter_.Add(frame.depth_mm);
  if (noise_meter_.frames() == kSamples) ReportDepthNoise();
}

// A depth model far from the camera's noise costs accuracy (docs/cameras.md, checking a
// camera): said once, with the keys that would describe it.
void Frontend::ReportDepthNoise() {
  if (noise_reported_ || noise_meter_.frames() == 0) return;
  noise_reported_ = true;
  const DepthNoiseMeasurement measured = noise_meter_.Measure();
  noise_meter_ = DepthNoiseMeter();  // its blocks are not needed any more
  if (!measured.Enough()) {
    CCMD_LOG(INFO) << "depth noise: too few planar blocks with every depth to measure it";
    return;
  }
  const DepthNoise& model = options_.depth_noise;
  stats_.depth_noise_ratio = measured.RatioTo(model);
  const DepthNoise& fitted = measured.fitted;
  char line[200];
  std::snprintf(line, sizeof line,
                "%.1f mm at 1 m, %.1f mm at 2 m; the config's model %.1f / %.1f mm (x%.2f)",
                1e3 * fitted.Sigma(1.0), 1e3 * fitted.Sigma(2.0), 1e3 * model.Sigma(1.0),
                1e3 * model.Sigma(2.0), stats_.depth_noise_ratio);
  CCMD_LOG(INFO) << "depth noise measured on the first frames: " << line;
  const std::string advice = DepthNoiseAdvice(measured, model);
  if (!advice.empty()) CCMD_LOG(WARNING) << advice;
}

Trajectory Frontend::FrameTrajectory() {
  const auto lock = map_.Lock();
  return FrameTrajectoryOf(tracker_->records(), tracker_->keyframe_records(),
                           [&](KeyframeId id) { return map_.KeyframePose(id); });
}

Trajectory Frontend::KeyframeTrajectory() {
  const auto lock = map_.Lock();
  Trajectory trajectory;
  for (const auto& [t, pose] : map_.AllKeyframePoses()) trajectory.push_back({t, pose});
  return trajectory;
}

FrontendStats Frontend::stats() {
  FrontendStats s = stats_;
  s.mapping = mapper_->stats();
  const auto lock = map_.Lock();
  s.restarts = tracker_->restarts();
  s.motion_model_misses = tracker_->motion_model_misses();
  s.keyframes = static_cast<int>(map_.keyframes_created());
  s.map_keyframes = static_cast<int>(map_.keyframes().size());
  s.map_points = map_.num_points();
  return s;
}

}  // namespace ccmd
