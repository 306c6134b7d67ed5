#include "libccmd/tracking/matching.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

namespace ccmd {
namespace {

constexpr int kHistogramBins = 30;

struct Candidate {
  int index = -1;
  int distance = std::numeric_limits<int>::max();
  int second = std::numeric_limits<int>::max();
  int level = -1, second_level = -1;
};

}  // namespace

std::vector<int> RotationOutliers(const std::vector<float>& rotations) {
  std::array<std::vector<int>, kHistogramBins> bins;
  for (int i = 0; i < static_cast<int>(rotations.size()); ++i) {
    float r = rotations[i];
    while (r < 0) r += 360.0f;
    while (r >= 360.0f) r -= 360.0f;
    const int bin = std::min(kHistogramBins - 1, static_cast<int>(r * kHistogramBins / 360.0f));
    bins[bin].push_back(i);
  }
  // The three largest bins; a bin less than a tenth of the largest does not count.
  std::array<int, kHistogramBins> order;
  for (int i = 0; i < kHistogramBins; ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(),
                   [&](int a, int b) { return bins[a].size() > bins[b].size(); });
  std::vector<bool> keep(kHistogramBins, false);
  const std::size_t largest = bins[order[0]].size();
  for (int k = 0; k < 3; ++k) {
    if (k > 0 && bins[order[k]].size() < 0.1 * largest) break;
    keep[order[k]] = true;
  }
  std::vector<int> dropped;
  for (int b = 0; b < kHistogramBins; ++b) {
    if (!keep[b]) dropped.insert(dropped.end(), bins[b].begin(), bins[b].end());
  }
  return dropped;
}

CCMD_POPCNT_CLONES int SearchFromLastFrame(TrackingFrame* current, const TrackingFrame& last,
                                           float radius, const OrbExtractor& orb,
                                           const PinholeCamera& camera) {
  const Pose& Tcw = current->T_cam_world;
  // Moving forward makes points look larger: search the same or finer octaves; backward the
  // same or coarser (ORB-SLAM's RGB-D rule, threshold the virtual baseline).
  const Eigen::Vector3d t_last_current = last.T_cam_world * current->camera_center();
  const double baseline = camera.bf / camera.fx;
  const bool forward = t_last_current.z() > baseline;
  const bool backward = -t_last_current.z() > baseline;
  std::vector<int> matched_keypoint;
  std::vector<float> rotations;
  int matches = 0;
  for (int i = 0; i < last.size(); ++i) {
    const MapPointPtr& point = last.points[i];
    if (!point || last.outlier[i] || point->bad()) continue;
    const Eigen::Vector3d pc = Tcw * point->position();
    if (pc.z() <= 0) continue;
    const Eigen::Vector2d uv = camera.Project(pc);
    if (!camera.InImage(uv)) continue;
    const int last_octave = last.features.keypoints[i].octave;
    const float r = radius * orb.scale()[last_octave];
    int min_level = last_octave - 1, max_level = last_octave + 1;
    if (forward) min_level = last_octave;
    if (backward) max_level = last_octave;
    const std::vector<int> area = current->grid.FeaturesInArea(
        static_cast<float>(uv.x()), static_cast<float>(uv.y()), r, std::max(0, min_level),
        std::min(orb.options().levels - 1, max_level));
    const double u_right_predicted = uv.x() - camera.bf / pc.z();
    int best = kMatchHigh + 1, best_index = -1;
    for (int j : area) {
      if (current->points[j] && current->points[j]->num_observations() > 0) continue;
      if (current->features.u_right[j] > 0 &&
          std::abs(u_right_predicted - current->features.u_right[j]) > r) {
        continue;
      }
      const int d =
          HammingDistance(point->descriptor().data(), current->features.descriptors.ptr<uchar>(j));
      if (d < best) {
        best = d;
        best_index = j;
      }
    }
    if (best_index < 0) continue;
    current->points[best_index] = point;
    current->outlier[best_index] = false;
    matched_keypoint.push_back(best_index);
    rotations.push_back(last.features.keypoints[i].angle -
                        current->features.keypoints[best_index].angle);
    ++matches;
  }
  for (int k : RotationOutliers(rotations)) {
    current->points[matched_keypoint[k]] = nullptr;
    --matches;
  }
  return matches;
}

CCMD_POPCNT_CLONES int SearchLocalPoints(TrackingFrame* current,
                                         const std::vector<MapPointPtr>& candidates, float radius,
                                         const OrbExtractor& orb, const PinholeCamera& camera) {
  const Pose& Tcw = current->T_cam_world;
  const Eigen::Vector3d center = current->camera_center();
  int matches = 0;
  for (const MapPointPtr& point : candidates) {
    if (!point || point->bad()) continue;
    // Frustum test: in front, in the image, within the scale-invariance distance, and seen
    // from a direction not too far from the point's mean viewing direction.
    const Eigen::Vector3d pc = Tcw * point->position();
    if (pc.z() <= 0) continue;
    const Eigen::Vector2d uv = camera.Project(pc);
    if (!camera.InImage(uv)) continue;
    const Eigen::Vector3d ray = point->position() - center;
    const float distance = static_cast<float>(ray.norm());
    if (distance < point->min_distance() || distance > point->max_distance()) continue;
    const double view_cos = ray.dot(point->normal()) / distance;
    if (view_cos < 0.5) continue;
    point->IncreaseVisible();
    const int level = point->PredictScale(distance, orb);
    const float r = radius * (view_cos > 0.998 ? 2.5f : 4.0f) * orb.scale()[level];
    const std::vector<int> area = current->grid.FeaturesInArea(
        static_cast<float>(uv.x()), static_cast<float>(uv.y()), r, std::max(0, level - 1), level);
    const double u_right_predicted = uv.x() - camera.bf / pc.z();
    Candidate c;
    for (int j : area) {
      if (current->points[j] && current->points[j]->num_observations() > 0) continue;
      if (current->features.u_right[j] > 0 &&
          std::abs(u_right_predicted - current->features.u_right[j]) > r) {
        continue;
      }
      const int d =
          HammingDistance(point->descriptor().data(), current->features.descriptors.ptr<uchar>(j));
      const int octave = current->features.keypoints[j].octave;
      if (d < c.distance) {
        c.second = c.distance;
        c.second_level = c.level;
        c.distance = d;
        c.level = octave;
        c.index = j;
      } else if (d < c.second) {
        c.second = d;
        c.second_level = octave;
      }
    }
    if (c.index < 0 || c.distance > kMatchHigh) continue;
    // Ratio test only between candidates of the same octave (ORB-SLAM).
    if (c.level == c.second_level && c.distance > 0.8f * c.second) continue;
    current->points[c.index] = point;
    current->outlier[c.index] = false;
    ++matches;
  }
  return matches;
}

CCMD_POPCNT_CLONES int SearchByDescriptor(TrackingFrame* current, const Keyframe& keyframe,
                                          float ratio) {
  std::vector<int> matched_keypoint;
  std::vector<float> rotations;
  std::vector<int> best_for_keypoint(current->size(), std::numeric_limits<int>::max());
  std::vector<int> owner(current->size(), -1);
  const auto& points = keyframe.points();
  for (int i = 0; i < static_cast<int>(points.size()); ++i) {
    const MapPointPtr& point = points[i];
    if (!point || point->bad()) continue;
    const uchar* d_kf = keyframe.features().descriptors.ptr<uchar>(i);
    int best = std::numeric_limits<int>::max(), second = best, best_index = -1;
    for (int j = 0; j < current->size(); ++j) {
      const int d = HammingDistance(d_kf, current->features.descriptors.ptr<uchar>(j));
      if (d < best) {
        second = best;
        best = d;
        best_index = j;
      } else if (d < second) {
        second = d;
      }
    }
    if (best_index < 0 || best > kMatchLow || best > ratio * second) continue;
    // One map point per keypoint: keep the closer claim.
    if (best >= best_for_keypoint[best_index]) continue;
    best_for_keypoint[best_index] = best;
    owner[best_index] = i;
  }
  int matches = 0;
  for (int j = 0; j < current->size(); ++j) {
    if (owner[j] < 0) continue;
    current->points[j] = points[owner[j]];
    current->outlier[j] = false;
    matched_keypoint.push_back(j);
    rotations.push_back(keyframe.features().keypoints[owner[j]].angle -
                        current->features.keypoints[j].angle);
    ++matches;
  }
  for (int k : RotationOutliers(rotations)) {
    current->points[matched_keypoint[k]] = nullptr;
    --matches;
  }
  return matches;
}

bool WithinReprojectionGate(const FrameFeatures& features, int i, const Eigen::Vector2d& uv,
                            double u_right_predicted, const OrbExtractor& orb) {
  const cv::KeyPoint& kp = features.keypoints[i];
  const double eu = uv.x() - kp.pt.x, ev = uv.y() - kp.pt.y;
  double e2 = eu * eu + ev * ev;
  double gate = kChi2Mono;
  if (features.u_right[i] >= 0) {
    const double er = u_right_predicted - features.u_right[i];
    e2 += er * er;
    gate = kChi2Stereo;
  }
  return e2 * orb.inv_sigma2()[kp.octave] <= gate;
}

CCMD_POPCNT_CLONES int FusePoints(LocalMap* map, Keyframe* keyframe,
                                  const std::vector<MapPointPtr>& points, const OrbExtractor& orb,
                                  const PinholeCamera& camera, float radius) {
  const Pose& Tcw = keyframe->T_cam_world();
  const Eigen::Vector3d center = keyframe->camera_center();
  int fused = 0;
  for (const MapPointPtr& point : points) {
    if (!point || point->bad() || point->KeypointIn(keyframe) >= 0) continue;
    const Eigen::Vector3d pc = Tcw * point->position();
    if (pc.z() <= 0) continue;
    const Eigen::Vector2d uv = camera.Project(pc);
    if (!camera.InImage(uv)) continue;
    const Eigen::Vector3d ray = point->position() - center;
    const float distance = static_cast<float>(ray.norm());
    if (distance < point->min_distance() || distance > point->max_distance()) continue;
    if (ray.dot(point->normal()) < 0.5 * distance) continue;
    const int level = point->PredictScale(distance, orb);
    const float r = radius * orb.scale()[level];
    const std::vector<int> area =
        keyframe->grid().FeaturesInArea(static_cast<float>(uv.x()), static_cast<float>(uv.y()), r);
    const double u_right_predicted = uv.x() - camera.bf / pc.z();
    int best = std::numeric_limits<int>::max(), best_index = -1;
    for (int j : area) {
      const cv::KeyPoint& kp = keyframe->features().keypoints[j];
      if (kp.octave < level - 1 || kp.octave > level) continue;
      if (!WithinReprojectionGate(keyframe->features(), j, uv, u_right_predicted, orb)) continue;
      const int d = HammingDistance(point->descriptor().data(),
                                    keyframe->features().descriptors.ptr<uchar>(j));
      if (d < best) {
        best = d;
        best_index = j;
      }
    }
    if (best_index < 0 || best > kMatchLow) continue;
    const MapPointPtr existing = keyframe->point(best_index);
    if (existing && !existing->bad()) {
      // Keep the better observed of the two.
      if (existing->num_observations() >= point->num_observations()) {
        map->ReplacePoint(point.get(), existing);
      } else {
        map->ReplacePoint(existing.get(), point);
      }
    } else {
      if (existing) continue;
      map->AddObservation(point, keyframe, best_index);
    }
    ++fused;
  }
  return fused;
}

CCMD_POPCNT_CLONES std::vector<std::pair<int, int>> SearchForTriangulation(
    const Keyframe& a, const Keyframe& b, const OrbExtractor& orb, const PinholeCamera& camera,
    float ratio) {
  // Fundamental matrix from a's pixels to b's: F = K^-T [t]x R K^-1, with X_b = R X_a + t.
  const Pose T_b_a = b.T_cam_world() * a.T_world_cam();
  const Eigen::Vector3d& t = T_b_a.translation();
  Eigen::Matrix3d t_cross;
  t_cross << 0, -t.z(), t.y(), t.z(), 0, -t.x(), -t.y(), t.x(), 0;
  const Eigen::Matrix3d K_inv = camera.K().inverse();
  const Eigen::Matrix3d F = K_inv.transpose() * t_cross * T_b_a.linear() * K_inv;

  const FrameFeatures& fa = a.features();
  const FrameFeatures& fb = b.features();
  std::vector<int> candidates_b;
  for (int j = 0; j < fb.size(); ++j) {
    if (!b.point(j)) candidates_b.push_back(j);
  }
  // Best claim on each keypoint of b: (distance, keypoint of a).
  std::vector<std::pair<int, int>> claim(fb.size(), {std::numeric_limits<int>::max(), -1});
  for (int i = 0; i < fa.size(); ++i) {
    if (a.point(i)) continue;
    const cv::Point2f& pa = fa.keypoints[i].pt;
    const Eigen::Vector3d line = F * Eigen::Vector3d(pa.x, pa.y, 1.0);
    const double norm2 = line.x() * line.x() + line.y() * line.y();
    if (norm2 <= 0) continue;
    const uchar* da = fa.descriptors.ptr<uchar>(i);
    Candidate c;
    for (int j : candidates_b) {
      if (fa.depth[i] > 0 && fb.depth[j] > 0) continue;
      const cv::KeyPoint& kb = fb.keypoints[j];
      const double e = line.x() * kb.pt.x + line.y() * kb.pt.y + line.z();
      if (e * e > 3.84 * orb.sigma2()[kb.octave] * norm2) continue;
      const int d = HammingDistance(da, fb.descriptors.ptr<uchar>(j));
      if (d < c.distance) {
        c.second = c.distance;
        c.distance = d;
        c.index = j;
      } else if (d < c.second) {
        c.second = d;
      }
    }
    if (c.index < 0 || c.distance > kMatchLow || c.distance > ratio * c.second) continue;
    if (c.distance < claim[c.index].first) claim[c.index] = {c.distance, i};
  }
  std::vector<std::pair<int, int>> pairs;
  std::vector<float> rotations;
  for (int j = 0; j < fb.size(); ++j) {
    if (claim[j].second < 0) continue;
    pairs.emplace_back(claim[j].second, j);
    rotations.push_back(fa.keypoints[claim[j].second].angle - fb.keypoints[j].angle);
  }
  std::vector<bool> drop(pairs.size(), false);
  for (int k : RotationOutliers(rotations)) drop[k] = true;
  std::vector<std::pair<int, int>> kept;
  for (std::size_t k = 0; k < pairs.size(); ++k) {
    if (!drop[k]) kept.push_back(pairs[k]);
  }
  return kept;
}

}  // namespace ccmd
