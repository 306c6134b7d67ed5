#include "libccmd/tracking/config.h"

namespace ccmd {

StatusOr<TrackingOptions> ReadTrackingOptions(const ConfigFile& c, TrackingOptions o) {
  CCMD_ASSIGN_OR_RETURN(o.orb.features, c.GetInt("ORBextractor.nFeatures", o.orb.features));
  CCMD_ASSIGN_OR_RETURN(const double scale,
                        c.GetDouble("ORBextractor.scaleFactor", o.orb.scale_factor));
  o.orb.scale_factor = static_cast<float>(scale);
  CCMD_ASSIGN_OR_RETURN(o.orb.levels, c.GetInt("ORBextractor.nLevels", o.orb.levels));
  CCMD_ASSIGN_OR_RETURN(o.orb.fast_threshold,
                        c.GetInt("ORBextractor.iniThFAST", o.orb.fast_threshold));
  CCMD_ASSIGN_OR_RETURN(o.orb.min_fast_threshold,
                        c.GetInt("ORBextractor.minThFAST", o.orb.min_fast_threshold));
  CCMD_ASSIGN_OR_RETURN(o.min_depth, c.GetDouble("Tracking.minDepth", o.min_depth));
  CCMD_ASSIGN_OR_RETURN(o.max_depth, c.GetDouble("Tracking.maxDepth", o.max_depth));
  CCMD_ASSIGN_OR_RETURN(o.depth_noise, ReadDepthNoise(c, o.depth_noise));
  CCMD_ASSIGN_OR_RETURN(
      o.max_frames_between_keyframes,
      c.GetInt("Tracking.maxFramesBetweenKeyframes", o.max_frames_between_keyframes));
  CCMD_ASSIGN_OR_RETURN(o.keyframe_tracked_ratio,
                        c.GetDouble("Tracking.keyframeTrackedRatio", o.keyframe_tracked_ratio));
  CCMD_ASSIGN_OR_RETURN(o.relocalisation_seconds,
                        c.GetDouble("Tracking.relocalisationSeconds", o.relocalisation_seconds));
  CCMD_ASSIGN_OR_RETURN(o.local_ba_window, c.GetInt("Tracking.localBAWindow", o.local_ba_window));
  CCMD_ASSIGN_OR_RETURN(o.local_ba_robust_iterations,
                        c.GetInt("Tracking.localBARobustIterations", o.local_ba_robust_iterations));
  CCMD_ASSIGN_OR_RETURN(o.local_ba_iterations,
                        c.GetInt("Tracking.localBAIterations", o.local_ba_iterations));
  CCMD_ASSIGN_OR_RETURN(
      o.local_ba_function_tolerance,
      c.GetDouble("Tracking.localBAFunctionTolerance", o.local_ba_function_tolerance));
  CCMD_ASSIGN_OR_RETURN(o.cpu_budget, c.GetDouble("Tracking.cpuBudget", o.cpu_budget));
  CCMD_ASSIGN_OR_RETURN(o.depth_alignment_neighbours, c.GetInt("Tracking.depthAlignmentNeighbours",
                                                               o.depth_alignment_neighbours));
  CCMD_ASSIGN_OR_RETURN(o.depth_alignment_weight,
                        c.GetDouble("Tracking.depthAlignmentWeight", o.depth_alignment_weight));
  CCMD_ASSIGN_OR_RETURN(o.frame_depth_weight,
                        c.GetDouble("Tracking.frameDepthWeight", o.frame_depth_weight));
  CCMD_ASSIGN_OR_RETURN(o.depth_bridge_seconds,
                        c.GetDouble("Tracking.depthBridgeSeconds", o.depth_bridge_seconds));
  CCMD_ASSIGN_OR_RETURN(const int lag,
                        c.GetInt("Tracking.depthLagCompensation", o.compensate_depth_lag));
  o.compensate_depth_lag = lag != 0;
  CCMD_ASSIGN_OR_RETURN(o.rolling_shutter_readout,
                        c.GetDouble("Camera.rollingShutterReadout", o.rolling_shutter_readout));
  CCMD_ASSIGN_OR_RETURN(o.triangulation_neighbours,
                        c.GetInt("Tracking.triangulationNeighbours", o.triangulation_neighbours));
  CCMD_ASSIGN_OR_RETURN(o.max_keyframes, c.GetInt("Tracking.maxKeyframes", o.max_keyframes));
  CCMD_ASSIGN_OR_RETURN(const int cull,
                        c.GetInt("Tracking.cullRedundantKeyframes", o.cull_redundant_keyframes));
  CCMD_ASSIGN_OR_RETURN(o.max_new_points_per_keyframe,
                        c.GetInt("Link.maxNewPointsPerKeyframe", o.max_new_points_per_keyframe));
  CCMD_ASSIGN_OR_RETURN(const int unlinked,
                        c.GetInt("Link.sendUnlinkedKeypoints", o.send_unlinked_keypoints));
  o.send_unlinked_keypoints = unlinked != 0;
  CCMD_ASSIGN_OR_RETURN(const int subpixel,
                        c.GetInt("Tracking.subpixelKeypoints", o.subpixel_keypoints));
  o.subpixel_keypoints = subpixel != 0;
  o.cull_redundant_keyframes = cull != 0;
  RgbdSelectionOptions& r = o.rgbd_selection;
  CCMD_ASSIGN_OR_RETURN(const int enabled, c.GetInt("RgbdSelection.enabled", r.enabled));
  r.enabled = enabled != 0;
  CCMD_ASSIGN_OR_RETURN(r.threshold_ratio,
                        c.GetDouble("RgbdSelection.thresholdRatio", r.threshold_ratio));
  CCMD_ASSIGN_OR_RETURN(r.threshold_min_points,
                        c.GetInt("RgbdSelection.thresholdMinPoints", r.threshold_min_points));
  CCMD_ASSIGN_OR_RETURN(r.decrement_ratio,
                        c.GetDouble("RgbdSelection.decrementRatio", r.decrement_ratio));
  CCMD_ASSIGN_OR_RETURN(r.min_threshold, c.GetInt("RgbdSelection.minThreshold", r.min_threshold));
  CCMD_ASSIGN_OR_RETURN(r.required_covering,
                        c.GetInt("RgbdSelection.requiredCovering", r.required_covering));
  CCMD_RETURN_IF_ERROR(o.Validate().WithContext(c.path()));
  return o;
}

}  // namespace ccmd
