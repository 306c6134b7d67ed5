#pragma once

// The agent's local map: keyframes, map points, their observations and the covisibility
// graph. One mutex, taken with LocalMap::Lock(), guards the whole graph; the tracker holds it while
// it works on a frame and the local mapper while it edits the graph, and neither holds it during
// feature extraction or a bundle-adjustment solve. Objects are owned through shared_ptr so a
// frame that still refers to a map point the mapper has removed sees a "bad" object, never a
// dangling one; links inside the graph are raw pointers that removal always unlinks.

#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <unordered_map>
#include <vector>

#include <opencv2/core.hpp>

#include "libccmd/features/descriptor.h"
#include "libccmd/features/feature_grid.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/util/ids.h"

namespace ccmd {

class DepthModel;
class Keyframe;
class OrbExtractor;

class MapPoint {
 public:
  MapPoint(MapPointId id, const Eigen::Vector3d& position) : id_(id), position_(position) {}

  MapPointId id() const { return id_; }
  const Eigen::Vector3d& position() const { return position_; }
  void set_position(const Eigen::Vector3d& p) { position_ = p; }
  const Descriptor& descriptor() const { return descriptor_; }
  const Eigen::Vector3d& normal() const { return normal_; }
  float min_distance() const { return 0.8f * min_distance_; }  // ORB-SLAM's scale margins
  float max_distance() const { return 1.2f * max_distance_; }
  bool bad() const { return bad_; }

  struct Observation {
    Keyframe* keyframe;
    int keypoint;
  };
  const std::vector<Observation>& observations() const { return observations_; }
  int num_observations() const { return static_cast<int>(observations_.size()); }
  // Observations as ORB-SLAM counts them for RGB-D: a keypoint with depth counts twice.
  int WeightedObservations() const;
  int KeypointIn(const Keyframe* keyframe) const;  // -1 if not observed there
  Keyframe* reference() const { return reference_; }
  KeyframeId first_keyframe() const { return first_keyframe_; }

  // Tracking statistics: how often the point was predicted visible and actually matched.
  void IncreaseVisible(int n = 1) { visible_ += n; }
  void IncreaseFound(int n = 1) { found_ += n; }
  float FoundRatio() const { return static_cast<float>(found_) / visible_; }

  // Whether the server already has this point (its descriptor and position were sent).
  bool sent() const { return sent_; }
  void set_sent() { sent_ = true; }

  // Octave a keypoint of this point would have at `distance`, per ORB-SLAM's scale model.
  int PredictScale(float distance, const OrbExtractor& orb) const;

  // Recomputes the representative descriptor (medoid of its observations) and the mean
  // viewing direction and distance range. Needs the keyframes' descriptors.
  void UpdateDescriptor();
  void UpdateNormalAndDepth(const OrbExtractor& orb);

 private:
  friend class LocalMap;
  MapPointId id_;
  Eigen::Vector3d position_;
  Descriptor descriptor_{};
  Eigen::Vector3d normal_ = Eigen::Vector3d::Zero();
  float min_distance_ = 0, max_distance_ = 0;
  std::vector<Observation> observations_;
  Keyframe* reference_ = nullptr;
  KeyframeId first_keyframe_;
  int visible_ = 1, found_ = 1;
  bool bad_ = false;
  bool sent_ = false;
};

using MapPointPtr = std::shared_ptr<MapPoint>;

// Keyframe features as extracted: keypoints, descriptors, measured depth with its standard
// deviation, and the virtual right coordinate u - bf / depth (negative when there is no depth).
struct FrameFeatures {
  std::vector<cv::KeyPoint> keypoints;
  cv::Mat descriptors;
  std::vector<float> depth;        // metres, 0 = none
  std::vector<float> depth_sigma;  // metres, where there is depth
  std::vector<float> u_right;      // < 0 = none
  int size() const { return static_cast<int>(keypoints.size()); }
  // 1 / sigma^2 of keypoint i's depth (0 without depth), for the optimisers' residuals.
  double DepthInformation(int i) const {
    return depth[i] > 0 ? 1.0 / (static_cast<double>(depth_sigma[i]) * depth_sigma[i]) : 0.0;
  }
};

class Keyframe {
 public:
  Keyframe(KeyframeId id, double timestamp, int frame_index, FrameFeatures features,
           const Pose& T_world_cam, int width, int height);

  KeyframeId id() const { return id_; }
  double timestamp() const { return timestamp_; }
  int frame_index() const { return frame_index_; }
  const FrameFeatures& features() const { return features_; }
  const FeatureGrid& grid() const { return grid_; }
  // The same keypoints made again (MoveKeypointsAgain: moved, depths looked up again), for a
  // keyframe local mapping has not been given yet; the image is width x height.
  void ReplaceFeatures(FrameFeatures features, int width, int height);
  const Pose& T_world_cam() const { return T_world_cam_; }
  const Pose& T_cam_world() const { return T_cam_world_; }
  void set_T_world_cam(const Pose& T) {
    T_world_cam_ = T;
    T_cam_world_ = T.inverse();
  }
  Eigen::Vector3d camera_center() const { return T_world_cam_.translation(); }
  bool bad() const { return bad_; }

  const std::vector<MapPointPtr>& points() const { return points_; }
  MapPointPtr point(int keypoint) const { return points_[keypoint]; }
  // Map points with at least `min_observations` (weighted) observations.
  int TrackedPoints(int min_observations) const;

  // Covisibility: keyframes sharing at least 15 map points (or the best one), by weight.
  const std::vector<std::pair<Keyframe*, int>>& connections() const { return ordered_connections_; }
  int Weight(const Keyframe* other) const;
  std::vector<Keyframe*> BestCovisible(int n) const;
  Keyframe* parent() const { return parent_; }

  // Images kept until the keyframe has been handed to the link (then released).
  cv::Mat bgr, depth_mm;
  // Set while depth_mm is still the depth image as taken apart from the colour image: the
  // pose it was taken from (TrackingFrame::T_colour_depth). Local mapping first moves the
  // depth to the keyframe's own time (LocalMapper::MoveDepthToColourTime) and clears it.
  std::optional<Pose> T_colour_depth;
  // Reduced depth for dense alignment with later keyframes (kept while in the map).
  std::shared_ptr<const DepthModel> depth_model;
  // First keyframe of a map segment started after tracking was lost (Tracker::RestartDue):
  // its pose is the last tracked frame's, a guess, and it shares no points with earlier ones.
  bool restart = false;
  bool reset = false;  // a restart at once after a young segment (KeyframeMessage::reset)
  // Link bookkeeping.
  bool emitted = false;       // sent to the link
  bool rgbd_sent = false;     // its RGB-D data went with it
  double created_wall_s = 0;  // wall clock (Unix seconds) when the tracker made it
  Pose emitted_T_world_cam = Pose::Identity();  // pose last sent (for pose updates)

 private:
  friend class LocalMap;
  KeyframeId id_;
  double timestamp_;
  int frame_index_;
  FrameFeatures features_;
  FeatureGrid grid_;
  Pose T_world_cam_, T_cam_world_;
  std::vector<MapPointPtr> points_;
  std::unordered_map<const Keyframe*, int> weights_;
  std::vector<std::pair<Keyframe*, int>> ordered_connections_;
  Keyframe* parent_ = nullptr;
  std::vector<Keyframe*> children_;
  bool bad_ = false;
};

using KeyframePtr = std::shared_ptr<Keyframe>;

// Where the final pose of a keyframe comes from after it left the map: frozen absolute pose
// (evicted from the bounded map) or relative to its spanning-tree parent (culled as redundant).
struct KeyframeRecord {
  double timestamp = 0;
  bool relative = false;
  KeyframeId parent;
  Pose T = Pose::Identity();  // T_world_kf, or T_parent_kf when relative
};

class LocalMap {
 public:
  // Holds the whole graph until the returned lock goes out of scope. A frame's tracking and
  // each step of local mapping are transactions over many keyframes and points, so the caller
  // scopes the lock; the mutex itself stays inside the map.
  [[nodiscard]] std::unique_lock<std::mutex> Lock() { return std::unique_lock<std::mutex>(mutex_); }

  KeyframeId NextKeyframeId() { return KeyframeId(next_keyframe_id_++); }
  MapPointId NextMapPointId() { return MapPointId(next_point_id_++); }

  void AddKeyframe(const KeyframePtr& keyframe);
  void AddMapPoint(const MapPointPtr& point);

  // Links point <-> keypoint of keyframe (the keyframe's slot must be free).
  void AddObservation(const MapPointPtr& point, Keyframe* keyframe, int keypoint);
  void EraseObservation(MapPoint* point, Keyframe* keyframe);
  // Removes a point from every keyframe and the map; it is marked bad.
  void ErasePoint(MapPoint* point);
  // Fuses `from` into `into`: observations move over, `from` is erased.
  void ReplacePoint(MapPoint* from, const MapPointPtr& into);

  // Recomputes the keyframe's covisibility weights and those of its neighbours, and sets its
  // spanning-tree parent to the strongest earlier neighbour.
  void UpdateConnections(Keyframe* keyframe);

  // Removes a keyframe: its observations, covisibility links; children re-parented to its
  // parent. `relative` records the pose relative to the parent (culling) or absolute
  // (eviction from the bounded map). Points left without observations are erased.
  void EraseKeyframe(Keyframe* keyframe, bool relative);

  KeyframePtr keyframe(KeyframeId id) const;
  MapPointPtr point(MapPointId id) const;
  const std::map<KeyframeId, KeyframePtr>& keyframes() const { return keyframes_; }
  std::size_t num_points() const { return points_.size(); }
  const std::unordered_map<MapPointId, MapPointPtr>& points() const { return points_; }

  // Whether removed keyframes leave their final pose (a KeyframeRecord) for the trajectories;
  // without, KeyframePose and AllKeyframePoses know only the live keyframes.
  void set_keep_removed(bool keep) { keep_removed_ = keep; }
  // Final T_world_cam of any keyframe this map ever had (live or removed).
  std::optional<Pose> KeyframePose(KeyframeId id) const;
  // Every keyframe ever created (live or removed) with its current best pose, by id.
  std::vector<std::pair<double, Pose>> AllKeyframePoses() const;
  std::uint32_t keyframes_created() const { return next_keyframe_id_; }

 private:
  std::mutex mutex_;
  std::map<KeyframeId, KeyframePtr> keyframes_;  // ordered: oldest first
  std::unordered_map<MapPointId, MapPointPtr> points_;
  std::unordered_map<KeyframeId, KeyframeRecord> removed_;
  bool keep_removed_ = true;
  std::uint32_t next_keyframe_id_ = 0;
  std::uint32_t next_point_id_ = 0;
};

}  // namespace ccmd
