#include "libccmd/tracking/map.h"

#include <algorithm>
#include <cmath>

#include "libccmd/features/orb_extractor.h"
#include "libccmd/util/logging.h"

namespace ccmd {

// ----- MapPoint -----

int MapPoint::KeypointIn(const Keyframe* keyframe) const {
  for (const Observation& o : observations_) {
    if (o.keyframe == keyframe) return o.keypoint;
  }
  return -1;
}

int MapPoint::WeightedObservations() const {
  int n = 0;
  for (const Observation& o : observations_)
    n += o.keyframe->features().u_right[o.keypoint] >= 0 ? 2 : 1;
  return n;
}

int MapPoint::PredictScale(float distance, const OrbExtractor& orb) const {
  const float ratio = max_distance_ / std::max(distance, 1e-6f);
  const int level = static_cast<int>(std::ceil(std::log(ratio) / orb.log_scale_factor()));
  return std::clamp(level, 0, orb.options().levels - 1);
}

void MapPoint::UpdateDescriptor() {
  std::vector<Descriptor> descriptors;
  descriptors.reserve(observations_.size());
  for (const Observation& o : observations_) {
    if (o.keyframe->bad()) continue;
    descriptors.push_back(DescriptorRow(o.keyframe->features().descriptors, o.keypoint));
  }
  if (!descriptors.empty()) descriptor_ = MedoidDescriptor(descriptors);
}

void MapPoint::UpdateNormalAndDepth(const OrbExtractor& orb) {
  if (observations_.empty() || !reference_) return;
  Eigen::Vector3d normal = Eigen::Vector3d::Zero();
  for (const Observation& o : observations_) {
    normal += (position_ - o.keyframe->camera_center()).normalized();
  }
  normal_ = normal.normalized();
  const int index = KeypointIn(reference_);
  if (index < 0) return;
  const float distance = static_cast<float>((position_ - reference_->camera_center()).norm());
  const int level = reference_->features().keypoints[index].octave;
  max_distance_ = distance * orb.scale()[level];
  min_distance_ = max_distance_ / orb.scale().back();
}

// ----- Keyframe -----

Keyframe::Keyframe(KeyframeId id, double timestamp, int frame_index, FrameFeatures features,
                   const Pose& T_world_cam, int width, int height)
    : id_(id), timestamp_(timestamp), frame_index_(frame_index), features_(std::move(features)) {
  grid_ = FeatureGrid(features_.keypoints, width, height);
  points_.assign(features_.keypoints.size(), nullptr);
  set_T_world_cam(T_world_cam);
}

void Keyframe::ReplaceFeatures(FrameFeatures features, int width, int height) {
  CCMD_CHECK(features.keypoints.size() == features_.keypoints.size())
      << "a keyframe's keypoints are made again one for one";
  features_ = std::move(features);
  grid_ = FeatureGrid(features_.keypoints, width, height);  // it points into features_
}

int Keyframe::TrackedPoints(int min_observations) const {
  int n = 0;
  for (const MapPointPtr& p : points_) {
    if (p && !p->bad() && p->WeightedObservations() >= min_observations) ++n;
  }
  return n;
}

int Keyframe::Weight(const Keyframe* other) const {
  const auto it = weights_.find(other);
  return it == weights_.end() ? 0 : it->second;
}

std::vector<Keyframe*> Keyframe::BestCovisible(int n) const {
  std::vector<Keyframe*> best;
  for (const auto& [kf, w] : ordered_connections_) {
    if (static_cast<int>(best.size()) >= n) break;
    if (!kf->bad()) best.push_back(kf);
  }
  return best;
}

// ----- LocalMap -----

void LocalMap::AddKeyframe(const KeyframePtr& keyframe) { keyframes_[keyframe->id()] = keyframe; }

void LocalMap::AddMapPoint(const MapPointPtr& point) { points_[point->id()] = point; }

void LocalMap::AddObservation(const MapPointPtr& point, Keyframe* keyframe, int keypoint) {
  CCMD_CHECK(!keyframe->points_[keypoint]) << "keypoint already has a map point";
  if (point->KeypointIn(keyframe) >= 0) return;
  point->observations_.push_back({keyframe, keypoint});
  keyframe->points_[keypoint] = point;
  if (!point->reference_) {
    point->reference_ = keyframe;
    point->first_keyframe_ = keyframe->id();
  }
}

void LocalMap::EraseObservation(MapPoint* point, Keyframe* keyframe) {
  auto& obs = point->observations_;
  const auto it = std::find_if(obs.begin(), obs.end(), [&](const MapPoint::Observation& o) {
    return o.keyframe == keyframe;
  });
  if (it == obs.end()) return;
  keyframe->points_[it->keypoint] = nullptr;
  obs.erase(it);
  if (point->reference_ == keyframe)
    point->reference_ = obs.empty() ? nullptr : obs.front().keyframe;
  if (point->WeightedObservations() <= 2) ErasePoint(point);
}

void LocalMap::ErasePoint(MapPoint* point) {
  if (point->bad_) return;
  point->bad_ = true;
  for (const auto& o : point->observations_) {
    if (o.keyframe->points_[o.keypoint].get() == point) o.keyframe->points_[o.keypoint] = nullptr;
  }
  point->observations_.clear();
  point->reference_ = nullptr;
  points_.erase(point->id());  // may free the point: nothing after this line uses it
}

void LocalMap::ReplacePoint(MapPoint* from, const MapPointPtr& into) {
  if (from == into.get() || from->bad_ || into->bad_) return;
  for (const auto& o : from->observations_) {
    if (into->KeypointIn(o.keyframe) < 0) {
      o.keyframe->points_[o.keypoint] = into;
      into->observations_.push_back(o);
    } else {
      o.keyframe->points_[o.keypoint] = nullptr;
    }
  }
  from->observations_.clear();
  into->visible_ += from->visible_;
  into->found_ += from->found_;
  into->UpdateDescriptor();
  from->bad_ = true;
  from->reference_ = nullptr;
  points_.erase(from->id());
}

void LocalMap::UpdateConnections(Keyframe* keyframe) {
  std::unordered_map<Keyframe*, int> counter;
  for (const MapPointPtr& p : keyframe->points_) {
    if (!p || p->bad()) continue;
    for (const auto& o : p->observations()) {
      if (o.keyframe != keyframe && !o.keyframe->bad()) counter[o.keyframe]++;
    }
  }
  constexpr int kMinShared = 15;
  std::vector<std::pair<Keyframe*, int>> connected;
  Keyframe* best = nullptr;
  int best_weight = 0;
  for (const auto& [kf, w] : counter) {
    if (w > best_weight || (w == best_weight && best && kf->id() < best->id())) {
      best = kf;
      best_weight = w;
    }
    if (w >= kMinShared) connected.emplace_back(kf, w);
  }
  if (connected.empty() && best) connected.emplace_back(best, best_weight);
  // Deterministic order: weight, then older keyframe first.
  std::sort(connected.begin(), connected.end(), [](const auto& a, const auto& b) {
    return a.second != b.second ? a.second > b.second : a.first->id() < b.first->id();
  });

  // Drop links to keyframes no longer connected, both ways.
  for (const auto& link : keyframe->ordered_connections_) {
    const auto& old_kf = link.first;  // a plain name: clang 14 cannot capture bindings
    const bool still = std::any_of(connected.begin(), connected.end(),
                                   [&](const auto& c) { return c.first == old_kf; });
    if (still) continue;
    old_kf->weights_.erase(keyframe);
    auto& list = old_kf->ordered_connections_;
    list.erase(std::remove_if(list.begin(), list.end(),
                              [&](const auto& c) { return c.first == keyframe; }),
               list.end());
  }
  keyframe->weights_.clear();
  for (const auto& [kf, w] : connected) keyframe->weights_[kf] = w;
  keyframe->ordered_connections_ = connected;
  for (const auto& [kf, w] : connected) {
    kf->weights_[keyframe] = w;
    auto& list = kf->ordered_connections_;
    list.erase(std::remove_if(list.begin(), list.end(),
                              [&](const auto& c) { return c.first == keyframe; }),
               list.end());
    list.emplace_back(keyframe, w);
    std::sort(list.begin(), list.end(), [](const auto& a, const auto& b) {
      return a.second != b.second ? a.second > b.second : a.first->id() < b.first->id();
    });
  }
  // Spanning tree: the first time a keyframe is connected, its strongest older neighbour
  // becomes its parent.
  if (!keyframe->parent_) {
    for (const auto& [kf, w] : connected) {
      if (kf->id() < keyframe->id()) {
        keyframe->parent_ = kf;
        kf->children_.push_back(keyframe);
        break;
      }
    }
  }
}

void LocalMap::EraseKeyframe(Keyframe* keyframe, bool relative) {
  if (keyframe->bad_) return;
  KeyframeRecord record;
  record.timestamp = keyframe->timestamp();
  if (relative && keyframe->parent_) {
    record.relative = true;
    record.parent = keyframe->parent_->id();
    record.T = keyframe->parent_->T_cam_world() * keyframe->T_world_cam();
  } else {
    record.T = keyframe->T_world_cam();
  }
  if (keep_removed_) removed_[keyframe->id()] = record;

  for (const auto& [kf, w] : keyframe->ordered_connections_) {
    kf->weights_.erase(keyframe);
    auto& list = kf->ordered_connections_;
    list.erase(std::remove_if(list.begin(), list.end(),
                              [&](const auto& c) { return c.first == keyframe; }),
               list.end());
  }
  keyframe->ordered_connections_.clear();
  keyframe->weights_.clear();
  // Children go to this keyframe's parent (or become roots).
  Keyframe* parent = keyframe->parent_;
  if (parent) {
    auto& siblings = parent->children_;
    siblings.erase(std::remove(siblings.begin(), siblings.end(), keyframe), siblings.end());
  }
  for (Keyframe* child : keyframe->children_) {
    child->parent_ = parent;
    if (parent) parent->children_.push_back(child);
  }
  keyframe->children_.clear();
  keyframe->parent_ = nullptr;
  keyframe->bad_ = true;
  for (std::size_t i = 0; i < keyframe->points_.size(); ++i) {
    if (MapPointPtr p = keyframe->points_[i]) EraseObservation(p.get(), keyframe);
  }
  const KeyframeId id = keyframe->id();
  keyframes_.erase(id);  // may free the keyframe
}

KeyframePtr LocalMap::keyframe(KeyframeId id) const {
  const auto it = keyframes_.find(id);
  return it == keyframes_.end() ? nullptr : it->second;
}

MapPointPtr LocalMap::point(MapPointId id) const {
  const auto it = points_.find(id);
  return it == points_.end() ? nullptr : it->second;
}

std::optional<Pose> LocalMap::KeyframePose(KeyframeId id) const {
  Pose relative_chain = Pose::Identity();
  for (int depth = 0; depth < 100000; ++depth) {
    if (const auto live = keyframes_.find(id); live != keyframes_.end()) {
      return live->second->T_world_cam() * relative_chain;
    }
    const auto removed = removed_.find(id);
    if (removed == removed_.end()) return std::nullopt;
    if (!removed->second.relative) return removed->second.T * relative_chain;
    relative_chain = removed->second.T * relative_chain;
    id = removed->second.parent;
  }
  return std::nullopt;
}

std::vector<std::pair<double, Pose>> LocalMap::AllKeyframePoses() const {
  std::vector<std::pair<double, Pose>> poses;
  for (std::uint32_t i = 0; i < next_keyframe_id_; ++i) {
    const KeyframeId id(i);
    const auto pose = KeyframePose(id);
    if (!pose) continue;
    const auto live = keyframes_.find(id);
    const double t =
        live != keyframes_.end() ? live->second->timestamp() : removed_.at(id).timestamp;
    poses.emplace_back(t, *pose);
  }
  return poses;
}

}  // namespace ccmd
