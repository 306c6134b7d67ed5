#pragma once

// A frame being tracked: its features (with measured depth per keypoint), the map points
// matched to them, and its pose.

#include <algorithm>
#include <memory>
#include <optional>
#include <vector>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/geometry/camera.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/optim/reprojection.h"
#include "libccmd/tracking/map.h"
#include "libccmd/tracking/options.h"

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
  cv::Mat bgr, depth_mm;  // kept so that the frame can become a keyframe; depth as taken
  // The pose of the camera when the depth image was taken, in its frame at the colour image's
  // time (RgbdFrame::depth_time_offset, moved by the motion model); nullopt: taken together.
  std::optional<Pose> T_colour_depth;
  double depth_time_offset = 0;  // RgbdFrame's
  // The keypoints as detected (raw pixels), kept where the frame's motion moved them (a
  // rolling shutter's unrolling) or chose their depths (T_colour_depth); else empty.
  std::vector<cv::KeyPoint> keypoints_as_read;
  // Made before any motion was known (a map's first frames) although its rolling shutter or
  // its depth taken apart needs one: its keypoints are kept as read and made again once its
  // own motion is solved.
  bool motion_pending = false;

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
  // The depth image as the camera would have taken it with the colour image: depth_mm, or
  // depth_mm moved by T_colour_depth (DepthFromNearbyPose, about 10 ms for 640x480: made
  // once, when asked, for a keyframe or a frame whose depth must be aligned).
  const cv::Mat& DepthAtColourTime(const PinholeCamera& camera);
  // Gives a keyframe made from this frame its depth: at the colour image's time when it has
  // been moved already, else as taken with T_colour_depth (local mapping moves it, off the
  // tracking thread).
  void HandDepthTo(Keyframe* keyframe) const;
  // A newer estimate of T_colour_depth: a depth moved with the old one is dropped.
  void SetDepthPose(const std::optional<Pose>& T_colour_depth_new) {
    T_colour_depth = T_colour_depth_new;
    depth_at_colour_time_.release();
  }
  // Forgets every match (and outlier mark) a search left, before a search from scratch.
  void ClearMatches() {
    std::fill(points.begin(), points.end(), nullptr);
    std::fill(outlier.begin(), outlier.end(), false);
  }

 private:
  cv::Mat depth_at_colour_time_;
};

// The camera's motion over `dt` seconds after a frame's time by the constant-velocity model
// whose `velocity` (T_cur_prev) spans `interval` seconds: that fraction of its rotation (about
// the same axis) and of its translation. Returns T_now_later, which takes a point in the
// camera at the later time into the camera at the frame's time.
Pose MotionOver(const Pose& velocity, double interval, double dt);

// A rolling shutter's readout and the camera's motion meanwhile (TrackingOptions::
// rolling_shutter_readout and the constant-velocity model).
struct RollingShutter {
  double readout = 0;  // seconds, first row to last
  Pose velocity;       // T_cur_prev
  double interval = 0;
};

// Moves each keypoint (raw pixels, as detected) to where the camera would have seen its point
// at the frame's time, the middle row's: row y was read (y + 0.5) / height - 0.5 readouts from
// it. The point is the keypoint's pixel at the depth there (rotation alone where it has none).
void UnrollKeypoints(const cv::Mat& depth_mm, const PinholeCamera& camera,
                     const RollingShutter& shutter, const TrackingOptions& options,
                     std::vector<cv::KeyPoint>* keypoints);

// Detects features in the colour image and attaches depth (metres) from the depth image at
// each keypoint; depth outside [options.min_depth, options.max_depth] counts as missing. Each
// depth gets its standard deviation: the sensor's noise (options.depth_noise) at that depth
// combined with the depth change across the keypoint's own position uncertainty
// (KeypointDepthSigma). With options.subpixel_keypoints, finest-octave keypoints are first
// moved to the sub-pixel corner position.
// `T_colour_depth`: the depth image was taken from that pose (TrackingFrame::T_colour_depth);
// each keypoint then takes the depth where its point lies in the depth image, moved to the
// colour image's time. `shutter`: the colour image came from a rolling shutter; the keypoints
// are moved to the frame's time first (UnrollKeypoints).
std::unique_ptr<TrackingFrame> MakeFrame(const RgbdFrame& input, const OrbExtractor& orb,
                                         const PinholeCamera& camera,
                                         const TrackingOptions& options,
                                         const std::optional<Pose>& T_colour_depth = std::nullopt,
                                         const RollingShutter* shutter = nullptr);

// The frame's features with depth lookups, for keyframes created directly (tests).
// `as_read`: receives the keypoints as detected when `shutter` or `T_colour_depth` is given.
FrameFeatures ComputeFeatures(const cv::Mat& gray, const cv::Mat& depth_mm, const OrbExtractor& orb,
                              const PinholeCamera& camera, const TrackingOptions& options,
                              const Pose* T_colour_depth = nullptr,
                              const RollingShutter* shutter = nullptr,
                              std::vector<cv::KeyPoint>* as_read = nullptr);

// Makes a frame's keypoints again from those as read (TrackingFrame::keypoints_as_read): moved
// to its time with `shutter`'s motion (readout 0: not moved), their depths looked up with the
// frame's present T_colour_depth. Once the frame's own pose is solved, the motion over its own
// interval replaces the one predicted from the interval before. Matches stay (they are per
// keypoint); a frame that kept no keypoints as read is left as it is.
void MoveKeypointsAgain(TrackingFrame* frame, const RollingShutter& shutter,
                        const OrbExtractor& orb, const PinholeCamera& camera,
                        const TrackingOptions& options);

// Standard deviation (metres) of the depth `z` read at pixel (x, y) for a keypoint whose
// position is uncertain by `pixel_sigma` pixels: the sensor's noise, and the depth slope
// there (central differences over +-2 pixels) times `pixel_sigma`. On a surface seen at a
// grazing angle the second term dominates: a corner found one pixel off reads a different
// depth. (x, y) must be at least 2 pixels inside the image.
double KeypointDepthSigma(const cv::Mat& depth_mm, int x, int y, double z, double pixel_sigma,
                          const DepthNoise& noise);

}  // namespace ccmd
