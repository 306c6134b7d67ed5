#pragma once

// The agent's front-end: ORB RGB-D tracking in the caller's thread and local mapping in its
// own thread (or inline, in synchronous mode), feeding a KeyframeSink.

#include <memory>
#include <vector>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/tracking/depth_noise_meter.h"
#include "libccmd/tracking/keyframe_sink.h"
#include "libccmd/tracking/local_mapper.h"
#include "libccmd/tracking/map.h"
#include "libccmd/tracking/options.h"
#include "libccmd/tracking/tracker.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct FrontendStats {
  int frames = 0;
  int tracked_frames = 0;
  int lost_frames = 0;          // frames after initialisation that could not be tracked
  int depth_only_frames = 0;    // tracked frames placed by their depth alone
  int restarts = 0;             // map segments started after tracking was lost
  int motion_model_misses = 0;  // frames the motion model's prediction did not find (Tracker)
  int keyframes = 0;            // keyframes created
  int map_keyframes = 0;        // keyframes in the bounded map now
  std::size_t map_points = 0;
  double extract_ms_total = 0;
  double track_ms_total = 0;
  double extract_cpu_ms_total = 0;  // CPU time: meaningful on a machine shared with other work
  double track_cpu_ms_total = 0;
  // The depth noise measured on the first frames (DepthNoiseMeter) over the config's
  // DepthNoise model: about 1 when the model describes the camera; 0 until measured.
  double depth_noise_ratio = 0;
  MappingStats mapping;
};

class Frontend {
 public:
  // `sink` may be null (offline runs that only want the trajectory).
  static StatusOr<std::unique_ptr<Frontend>> Create(const PinholeCamera& camera,
                                                    const TrackingOptions& options,
                                                    KeyframeSink* sink);
  ~Frontend();

  TrackResult ProcessFrame(const RgbdFrame& frame);
  // Lets local mapping finish the queued keyframes and stops it.
  void Finish();

  // Every tracked frame, placed relative to its reference keyframe's final pose.
  Trajectory FrameTrajectory();
  // Every keyframe created, at its final pose.
  Trajectory KeyframeTrajectory();
  FrontendStats stats();
  std::vector<RgbdDecision> decisions() const { return mapper_->decisions(); }
  TrackingState state() const { return tracker_->state(); }

 private:
  Frontend(const PinholeCamera& camera, const TrackingOptions& options, KeyframeSink* sink);
  void MeasureDepthNoise(const RgbdFrame& frame);
  void ReportDepthNoise();

  PinholeCamera camera_;
  TrackingOptions options_;
  OrbExtractor orb_;
  LocalMap map_;
  std::unique_ptr<LocalMapper> mapper_;
  std::unique_ptr<Tracker> tracker_;
  FrontendStats stats_;
  bool initialised_ = false;
  DepthNoiseMeter noise_meter_;  // the first frames only
  bool noise_reported_ = false;
};

}  // namespace ccmd
