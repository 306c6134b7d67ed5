#pragma once

// The tracking half of the agent's front-end (runs in the caller's thread): per frame it
// extracts ORB features, predicts the pose with a constant-velocity model and matches the
// previous frame's points by projection (falling back to the reference keyframe, then to
// relocalisation with PnP RANSAC), refines the pose against the local map, and decides
// whether the frame becomes a keyframe, which it hands to the local mapper.

#include <cmath>
#include <functional>
#include <memory>
#include <optional>
#include <vector>

#include "libccmd/geometry/camera.h"
#include "libccmd/io/rgbd_frame.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/optim/pose_optimizer.h"
#include "libccmd/tracking/depth_alignment.h"
#include "libccmd/tracking/frame.h"
#include "libccmd/tracking/map.h"
#include "libccmd/tracking/options.h"
#include "proto/messages.h"

namespace ccmd {

enum class TrackingState { kNotInitialized, kOk, kLost };
const char* TrackingStateName(TrackingState state);

struct TrackResult {
  TrackingState state = TrackingState::kNotInitialized;
  std::optional<Pose> T_world_cam;  // when tracked
  bool new_keyframe = false;
  // Tracked by the depth image alone (too few features matched): no keyframe is made from it.
  bool depth_only = false;
  int tracked_points = 0;
  double extract_ms = 0, track_ms = 0;          // wall time
  double extract_cpu_ms = 0, track_cpu_ms = 0;  // CPU time of the calling thread
};

// What the tracker needs from local mapping.
class MappingQueue {
 public:
  virtual ~MappingQueue() = default;
  virtual bool Idle() const = 0;                         // waiting for work
  virtual bool CanAccept() const = 0;                    // room for another keyframe
  virtual void Insert(const KeyframePtr& keyframe) = 0;  // only called after CanAccept()
  // Multiplies the tracked-point fraction of the keyframe decision (KeyframeSink's).
  virtual double KeyframeRatioScale() const { return 1.0; }
  // How closely this camera's depth fits where surfaces are matched rightly: the tail (mean
  // plus three standard deviations) of the residual RMS, in sigmas of the config's noise
  // model, of the recent depth alignments between keyframes (whose poses the features
  // confirmed); 0 before there are any.
  virtual double DepthFitSigmas() const { return 0.0; }
};

class Tracker {
 public:
  Tracker(const PinholeCamera& camera, const TrackingOptions& options, LocalMap* map,
          const OrbExtractor* orb, MappingQueue* mapping);

  TrackResult Track(const RgbdFrame& input);
  // Hands local mapping a first keyframe still waiting for the next frame's motion (the
  // input ended there). Call before local mapping finishes.
  void Finish();

  TrackingState state() const { return state_; }
  int frames_since_relocalisation() const { return frames_since_relocalisation_; }
  int restarts() const { return restarts_; }
  // Frames whose predicted pose found too few of the last frame's points within the search
  // window (a motion the constant-velocity model did not foresee).
  int motion_model_misses() const { return motion_model_misses_; }

  // Per-frame record for the trajectory (with options.record_trajectory): pose relative to the
  // reference keyframe, so the final trajectory follows the keyframes' optimised poses. Stored
  // in single precision (40 bytes a frame, 4.3 MB an hour at 30 Hz): relative to a keyframe a
  // few metres away at most, that is well under a micrometre and a microradian.
  struct FrameRecord {
    FrameRecord(double timestamp, KeyframeId reference, const Pose& T_ref_cam);
    Pose T_ref_cam() const;

    double timestamp;
    KeyframeId reference;
    Eigen::Quaternion<float, Eigen::DontAlign> q_ref_cam;
    Eigen::Matrix<float, 3, 1, Eigen::DontAlign> t_ref_cam;
  };
  const std::vector<FrameRecord>& records() const { return records_; }

  // Per keyframe the tracker made (with options.record_trajectory), in order: where tracking
  // put it, relative to the keyframe it was tracked against (`tracked`), before local BA moved
  // it. The frames tracked since the keyframe before take a share of that move
  // (FrameTrajectoryOf). `continuous`: no frame was lost since the keyframe before, so
  // tracking links the two. `record`: its frame's index in records().
  struct KeyframeRecord {
    KeyframeId keyframe;
    bool continuous;
    std::size_t record;
    FrameRecord tracked;
  };
  const std::vector<KeyframeRecord>& keyframe_records() const { return keyframe_records_; }

 private:
  // Starts the map (or, with `restart`, a new segment of it after tracking was lost) at this
  // frame, placed at `T_world_cam`; `tracked`: that is the frame's own tracked pose.
  bool Initialize(TrackingFrame* frame, const Pose& T_world_cam, bool restart,
                  bool tracked = false);
  // Where the camera was when a depth image taken `offset` seconds after its colour image was
  // taken, in its frame at the colour image's time (TrackingFrame::T_colour_depth): the
  // motion model's motion over the offset, a fraction of the last frame interval's. nullopt
  // when the offset is 0, the compensation is off or the motion is not known (before tracking
  // has two frames, after a loss).
  std::optional<Pose> DepthCameraPose(double offset) const;
  // Whether `frame`'s depth image was taken apart from its colour image and is to be moved to
  // the colour image's time (options.compensate_depth_lag).
  bool CompensatesLag(const TrackingFrame& frame) const;
  // A new map point from keypoint i of `frame` (which has depth), observed by `keyframe` made
  // from that frame (at `T_world_cam`), and matched to the keypoint.
  void AddMapPoint(TrackingFrame* frame, Keyframe* keyframe, const Pose& T_world_cam, int i);
  // Lost, with no relocalisation for options.relocalisation_seconds, or in a segment too
  // young to relocalise against: the next frame with enough features starts a new segment.
  bool RestartDue() const;
  bool YoungSegment() const;  // fewer than kYoungSegmentKeyframes keyframes
  // The motion model's T_current_last for the current frame.
  Pose PredictedMotion() const;
  bool TrackWithMotionModel();
  bool TrackReferenceKeyframe();
  // The current frame's pose from its matches alone (EPnP in RANSAC, no prior pose); keeps the
  // matches it agrees with. False when fewer than 15 agree.
  bool PoseFromMatchesAlone();
  bool Relocalize();
  // `depth_may_confirm`: a frame with fewer than 30 inliers may be tracked if its depth
  // confirms their pose (DepthConfirmsPose); not where the depth gave the pose to start from.
  bool TrackLocalMap(bool depth_may_confirm);
  void UpdateLocalMap();
  // `prior`: a measured pose weighed in beside the matches (FrameDepthPrior).
  int OptimizeCurrentPose(const PosePrior* prior = nullptr);
  // A rolling shutter's keypoints, and the depths of keypoints whose depth image was taken
  // apart, came from the motion predicted from the interval before; once the frame's pose is
  // solved, makes them again with the motion over its own interval (MoveKeypointsAgain).
  // False, changing nothing, where the motion did not enter.
  bool MoveKeypointsWithOwnMotion();
  // Makes `frame`'s keypoints again from those as read (MoveKeypointsAgain), and its depth
  // image's pose where its depth was taken apart, with the constant-velocity motion between
  // `before` and `after` (both with poses). False, changing nothing, when they share a time.
  bool MoveKeypointsWithMotion(TrackingFrame* frame, const TrackingFrame& before,
                               const TrackingFrame& after) const;
  // A map's first keyframe is made before any motion is known, so a rolling shutter's
  // keypoints and the depths from a depth image taken apart stay as read. It waits
  // (pending_keyframe_) for the next frame: once that frame's pose is solved, the motion
  // between the two makes the keyframe's keypoints again and moves the points it made. False
  // when there is no such keyframe. Its frame, last_, must still be the keyframe's.
  bool MoveFirstKeyframeWithOwnMotion();
  // Gives local mapping the waiting first keyframe, if any.
  void InsertPendingKeyframe();
  // The current frame's depth aligned with the newest local keyframe's that has a depth
  // model, from the frame's present pose; nullopt when off, without depth, or when the
  // alignment fails or lands far from the features' pose.
  std::optional<PosePrior> FrameDepthPrior() const;
  // Whether the current frame's depth, aligned with the newest local keyframe's from the pose
  // the features gave, fits as the sensor measures and moves that pose by less than
  // kMaxDepthCorrection_*: the condition on which a frame with fewer inliers than ORB-SLAM's 30
  // (but kMinInliersWithDepth or more) is tracked rather than lost.
  bool DepthConfirmsPose() const;
  static constexpr int kMinInliersWithDepth = 15;
  static constexpr double kMaxDepthCorrection_m = 0.02;
  static constexpr double kMaxDepthCorrection_rad = 0.5 * M_PI / 180;
  const Keyframe* NewestLocalKeyframeWithDepth() const;
  // How far (in the sensor's sigmas) a depth alignment may fit worse than the sensor measures
  // before its surfaces count as matched wrongly.
  double AllowedDepthFitSigmas() const;
  // Features lost (a blank wall, motion blur): the frame's depth aligned with the newest
  // keyframe's that has a depth model, from the constant-velocity prediction, places it when the
  // view's geometry fixes every direction of the pose; the local map's points are then searched
  // again from there. Keeps tracking through stretches without texture instead of relocalising.
  bool BridgeWithDepth();
  // A frame placed by depth alone whose features are back but find none of the local map's
  // points (the bridge has carried the camera out of the view its map holds): once the bridge
  // has lasted as long as a lost camera waits for relocalisation, a new segment starts at that
  // frame, at the pose its depth gave, marked a reset (as good as tracking's).
  bool RestartAtBridgedFrame();
  void EndBridge();
  bool NeedNewKeyframe() const;
  void CreateKeyframe();

  PinholeCamera camera_;
  TrackingOptions options_;
  LocalMap* map_;
  const OrbExtractor* orb_;
  MappingQueue* mapping_;

  TrackingState state_ = TrackingState::kNotInitialized;
  std::optional<Pose> last_T_world_cam_;  // of the last tracked frame
  double last_tracked_timestamp_ = 0;
  double lost_since_ = 0;        // timestamp of the first frame not tracked
  KeyframeId segment_start_{0};  // first keyframe of the current segment
  int restarts_ = 0;
  int motion_model_misses_ = 0;
  std::unique_ptr<TrackingFrame> current_, last_;
  std::optional<Pose> velocity_;  // T_current_last
  double velocity_interval_ = 0;  // seconds between the two frames velocity_ was measured on
  KeyframePtr reference_;
  KeyframePtr last_keyframe_;
  KeyframePtr pending_keyframe_;  // first keyframe, held from local mapping until moved
  int last_keyframe_frame_ = -1;
  int last_relocalisation_frame_ = -1000;
  int frames_since_relocalisation_ = 1000;
  int matches_inliers_ = 0;
  std::vector<KeyframePtr> local_keyframes_;
  std::vector<MapPointPtr> local_points_;
  std::vector<FrameRecord> records_;
  std::vector<KeyframeRecord> keyframe_records_;
  bool tracked_since_keyframe_ = false;  // every frame since the last keyframe was tracked
  // While frames are placed by depth alone: since when, and the last such frame's depth.
  std::optional<double> bridged_since_;
  std::shared_ptr<const DepthModel> bridge_model_;
};

// The frames' trajectory: each record's pose relative to its reference keyframe, at that
// keyframe's current pose (`keyframe_pose`: nullopt for a keyframe it does not know), with each
// keyframe's move since tracking placed it spread over the frames since the keyframe before.
Trajectory FrameTrajectoryOf(const std::vector<Tracker::FrameRecord>& records,
                             const std::vector<Tracker::KeyframeRecord>& keyframes,
                             const std::function<std::optional<Pose>(KeyframeId)>& keyframe_pose);

}  // namespace ccmd
