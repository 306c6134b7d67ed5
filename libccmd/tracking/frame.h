#pragma once

// A frame being tracked: its features (with measured depth per keypoint), the map points
// matched to them, and its pose.

#include <memory>
#include <vector>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/tracking/map.h"

namespace ccmd {

struct TrackingFrame {
  int index = -1;
  double timestamp = 0;
  FrameFeatures features;
  FeatureGrid grid;
  std::vector<MapPointPtr> points;  // per keypoint, may be null
  std::vector<bool> outlier;
  Pose T_cam_world = Pose::Identity();
  bool has_pose = false;
  KeyframePtr reference;
  cv::Mat bgr, depth_mm;  // kept so that the frame can become a keyframe

  TrackingFrame() = default;
  TrackingFrame(const TrackingFrame&) = delete;
  TrackingFrame& operator=(const TrackingFrame&) = delete;

  int size() const { return features.size(); }
  Eigen::Vector3d camera_center() const { return T_cam_world.inverse().translation(); }
  // Number of matched, inlier, non-bad map points.
  int TrackedPoints() const;
  void SetPose(const Pose& T_cam_world_new) {
    T_cam_world = T_cam_world_new;
    has_pose = true;
  }
};

// Detects features in the colour image and attaches depth (metres) from the depth image at
// each keypoint; depth outside [min_depth, max_depth] counts as missing.
std::unique_ptr<TrackingFrame> MakeFrame(const RgbdFrame& input, const OrbExtractor& orb,
                                 const PinholeCamera& camera, double min_depth = 0.1,
                                 double max_depth = 10.0);

// The frame's features with depth lookups, for keyframes created directly (tests).
FrameFeatures ComputeFeatures(const cv::Mat& gray, const cv::Mat& depth_mm, const OrbExtractor& orb,
                              const PinholeCamera& camera, double min_depth, double max_depth);

}  // namespace ccmd
