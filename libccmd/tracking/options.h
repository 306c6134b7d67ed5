#pragma once

#include <string>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

// RGB-D keyframe selection (the CCMD-SLAM paper's Algorithm 1). A keyframe's RGB-D data is
// skipped when enough already-transmitted keyframes share many map points with it.
// The connected keyframes that were transmitted are visited from the strongest link down;
// one whose shared-point weight exceeds the threshold S counts as "covering", and each
// covering keyframe lowers S by `decrement` (never below `min_threshold`). The RGB-D data is
// skipped when at least `required_covering` keyframes cover it. With required_covering = 1
// this is exactly Algorithm 1; more makes the test stricter, and the decrement then lets the
// second and later covering keyframes share fewer points than the first.
struct RgbdSelectionOptions {
  bool enabled = true;
  // S_min as a fraction of the keyframe's own tracked map points (adapts to how textured the
  // view is) and as an absolute floor.
  double threshold_ratio = 0.3;
  int threshold_min_points = 60;
  double decrement_ratio = 0.1;  // of the keyframe's tracked points, per covering keyframe
  int min_threshold = 30;
  int required_covering = 1;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct TrackingOptions {
  OrbOptions orb;
  double min_depth = 0.1;  // metres; keypoint depth outside [min, max] counts as missing
  double max_depth = 10.0;
  // Moves the finest octave's keypoints to their sub-pixel corner position (frame.h).
  bool subpixel_keypoints = false;
  // Depth sensor noise used to weigh depth in pose optimisation and bundle adjustment.
  DepthNoise depth_noise;
  // Keyframe decision (ORB-SLAM): at most this many frames without a keyframe (0: the fps).
  int max_frames_between_keyframes = 0;
  // A new keyframe is due when the frame tracks fewer than this fraction of the reference
  // keyframe's map points (ORB-SLAM: 0.75 of the points seen in 3+ observations; here of all
  // of them, which keeps keyframes coming when new points have few observations yet).
  double keyframe_tracked_ratio = 0.5;
  // Lost for this long without relocalising (seconds of frame time), the tracker starts a new
  // map segment at the last tracked pose; the server joins it to the rest by loop closure.
  double relocalisation_seconds = 1.0;
  // Local bundle adjustment window: the new keyframe and this many best covisible keyframes
  // are optimised; keyframes that see their points are held fixed.
  int local_ba_window = 10;
  // Iterations of its robust pass and of its pass without outliers; each stops early when an
  // iteration lowers the cost by less than `local_ba_function_tolerance` (relative).
  int local_ba_robust_iterations = 5;
  int local_ba_iterations = 10;
  double local_ba_function_tolerance = 1e-6;
  // CPU budget of the agent in cores (0: none). Tracking takes what it needs; local mapping
  // gets the rest of cores / fps per frame and shrinks its local BA (half the window and the
  // iterations) while over, or skips it when far over (cpu_budget.h).
  double cpu_budget = 0;
  // Whether local mapping keeps to `cpu_budget` by shrinking its BA. A recording mapped in the
  // tracking thread has no sensor to keep up with: ccmd_agent paces it to the budget instead
  // and keeps every BA whole, so its trajectory does not depend on the machine's speed.
  bool mapping_follows_budget = true;
  // Dense depth alignment (depth_alignment.h): each new keyframe's depth is aligned with that
  // of this many best covisible keyframes, and the local BA weighs each alignment by its
  // information times `depth_alignment_weight` (0 turns it off).
  int depth_alignment_neighbours = 3;
  double depth_alignment_weight = 0.1;
  // Each tracked frame's depth is aligned with that of the newest keyframe that has a depth
  // model, from the pose the features give, and the pose optimisation against the local map
  // weighs that alignment by its information times this (0 turns it off).
  double frame_depth_weight = 0.0;
  // Frames whose features cannot be tracked are placed by their depth alone when it fixes the
  // pose (Tracker::BridgeWithDepth), for at most this many seconds in a row (0: off); needs
  // the keyframes' depth models (depth alignment on). Then tracking counts as lost.
  double depth_bridge_seconds = 3.0;
  // A depth image taken after (or before) its colour image (RgbdFrame::depth_time_offset) is
  // moved to the colour image's time by the constant-velocity model's motion over the offset
  // before anything reads it (the keypoints' depth, the depth alignments, the keyframes' dense
  // depth). Off by default: it needs timestamps that say when each image was taken, which
  // TUM RGB-D's do not show they are (docs/benchmarks/frontend.md#depth-taken-after-colour);
  // a rendered sequence's camera.yaml turns it on.
  bool compensate_depth_lag = false;
  // Rolling shutter (the config's Camera.rollingShutterReadout): the colour image's rows were
  // read out one after another over this time (seconds, first row to last), so each row shows
  // the scene from where the camera was at its own time. Each keypoint is moved to where the
  // middle row's time would have seen it, by the constant-velocity model's motion over its
  // row's offset (docs/frontend.md). 0: a global shutter.
  double rolling_shutter_readout = 0;
  // Keypoints without a map point and without depth at one end are matched with this many
  // best covisible keyframes along epipolar lines and triangulated into new points (ORB-SLAM's
  // CreateNewMapPoints; 0: off). Off by default: it gains on exact depth and loses on
  // Kinect v1 data (docs/benchmarks/frontend.md#points-without-depth-triangulated).
  int triangulation_neighbours = 0;
  // Bounded local map: keyframes beyond this many (oldest first, outside the current local
  // window) are dropped from the agent's memory, so memory and CPU stay flat.
  int max_keyframes = 60;
  bool cull_redundant_keyframes = true;
  // Run local mapping in the tracking thread (deterministic; for tests and measurements).
  bool synchronous_mapping = false;
  // Keep what the trajectories need (Frontend::FrameTrajectory, KeyframeTrajectory): a record
  // of every tracked frame (40 bytes) and the final pose of every keyframe that leaves the
  // map (about 0.2 kB). Off, nothing in the front-end grows with the frames; ccmd_agent turns
  // it off unless a trajectory file is asked for.
  bool record_trajectory = true;
  // Bandwidth: new map points sent per keyframe (0: all), and whether keypoints without a map
  // point the server knows are sent at all (with their descriptors).
  int max_new_points_per_keyframe = 250;
  bool send_unlinked_keypoints = false;
  // Pose updates are sent for emitted keyframes that moved more than this after a local BA.
  double pose_update_min_translation = 0.0005;  // metres
  double pose_update_min_rotation = 0.0002;     // radians
  RgbdSelectionOptions rgbd_selection;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

}  // namespace ccmd
