#pragma once

// What the front-end hands to the link: each new keyframe once local mapping has refined it,
// and after each local bundle adjustment the new poses of earlier keyframes that moved.

#include <optional>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/features/descriptor.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/util/ids.h"

namespace ccmd {

// What the sink asks of the next keyframe's RGB-D selection: a bandwidth budget
// (libccmd/system/bandwidth_budget.h) makes it stricter or more generous. The default asks
// nothing.
struct RgbdRequest {
  bool allow = true;            // false: no RGB-D for this keyframe (geometry only)
  bool every_keyframe = false;  // RGB-D whatever the selection would say
  double threshold_scale =
      1.0;  // multiplies S_min: below 1 fewer keyframes send RGB-D, above 1 more
};

// One decision of the RGB-D keyframe selection, recorded for statistics.
struct RgbdDecision {
  KeyframeId keyframe;
  bool transmit = true;
  RgbdRequest request;     // what the sink asked
  int tracked_points = 0;  // map points of the keyframe
  int threshold = 0;       // S_min at the start
  int covering = 0;        // transmitted neighbours above the (decreasing) threshold
  std::vector<std::pair<KeyframeId, int>> considered;  // transmitted neighbours and weights
};

struct KeyframeSnapshot {
  KeyframeId id;
  double timestamp = 0;
  double created_wall_s = 0;  // wall clock (Unix seconds) when the tracker made it
  int frame_index = -1;
  Pose T_world_cam = Pose::Identity();  // in the agent's map
  std::optional<KeyframeId> parent;     // spanning tree
  bool restart = false;                 // starts a segment after tracking was lost (Keyframe)
  bool reset = false;                   // ... at once, after a young segment

  std::vector<cv::KeyPoint> keypoints;
  cv::Mat descriptors;                               // N x 32
  std::vector<float> depth;                          // metres, 0 = none
  std::vector<std::optional<MapPointId>> point_ids;  // per keypoint

  // Map points this keyframe is the first to send: position in the keyframe's camera frame,
  // representative descriptor and the keypoint that observes it here.
  struct NewPoint {
    MapPointId id;
    Eigen::Vector3d position_cam;
    Descriptor descriptor;
    int keypoint = -1;
  };
  std::vector<NewPoint> new_points;
  std::vector<std::pair<KeyframeId, int>> covisibility;  // emitted neighbours and weights
  // Dense depth alignments with emitted keyframes: T_this_other and its information (as the
  // local BA weighs it; perturbation order rotation, translation).
  struct DepthLink {
    KeyframeId other;
    Pose T_this_other;
    Eigen::Matrix<double, 6, 6> information;
  };
  std::vector<DepthLink> depth_links;

  bool has_rgbd = false;
  cv::Mat bgr, depth_mm;        // full resolution; the codec downsamples
  int keypoints_extracted = 0;  // before choosing what to send (for bandwidth statistics)
  int image_width = 0, image_height = 0;
  RgbdDecision decision;
};

struct PoseUpdate {
  KeyframeId id;
  Pose T_world_cam = Pose::Identity();
};

// Receives the front-end's output. Called from the local-mapping thread (or the tracking
// thread in synchronous mode), in order; implementations must not block for long.
class KeyframeSink {
 public:
  virtual ~KeyframeSink() = default;
  virtual void OnKeyframe(KeyframeSnapshot keyframe) = 0;
  virtual void OnPoseUpdates(std::vector<PoseUpdate> updates) = 0;
  // Asked just before each keyframe's RGB-D decision (mapping thread, the agent's map
  // locked): must be quick and must not call into the front-end.
  virtual RgbdRequest NextRgbdRequest() { return {}; }
  // Asked by the tracker's keyframe decision on every frame (tracking thread): multiplies the
  // fraction of tracked points under which a frame becomes a keyframe. Below 1: fewer
  // keyframes (a bandwidth budget that geometry alone overflows). Must be quick (the link's
  // sink looks at its budget at most every 0.1 s here).
  virtual double KeyframeRatioScale() { return 1.0; }
};

}  // namespace ccmd
