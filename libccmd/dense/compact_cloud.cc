#include "libccmd/dense/compact_cloud.h"

#include <algorithm>
#include <cmath>

namespace ccmd {

CompactCloud CompactCloud::Encode(const CameraCloud& cloud,
                                  const std::vector<std::uint32_t>& indices) {
  CompactCloud c;
  float largest = 0;
  for (const std::uint32_t i : indices)
    largest = std::max(largest, cloud.points[i].cwiseAbs().maxCoeff());
  // A step that maps the largest coordinate to 32767 (at least a micrometre, for empty or
  // degenerate clouds).
  c.step_ = std::max(largest / 32767.0f, 1e-6f);
  const float inverse = 1.0f / c.step_;
  c.xyz_.reserve(indices.size());
  c.colors_.reserve(indices.size());
  for (const std::uint32_t i : indices) {
    const Eigen::Vector3f q =
        (cloud.points[i] * inverse).array().round().cwiseMax(-32767.0f).cwiseMin(32767.0f);
    c.xyz_.push_back({static_cast<std::int16_t>(q.x()), static_cast<std::int16_t>(q.y()),
                      static_cast<std::int16_t>(q.z())});
    c.colors_.push_back(cloud.colors[i]);
  }
  return c;
}

void CompactCloud::Transform(const Pose& T_world_cam, std::vector<Eigen::Vector3f>* out) const {
  // The step folds into the rotation: one matrix product per point.
  const Eigen::Matrix3f r = T_world_cam.linear().cast<float>() * step_;
  const Eigen::Vector3f t = T_world_cam.translation().cast<float>();
  out->resize(xyz_.size());
  for (std::size_t i = 0; i < xyz_.size(); ++i) {
    (*out)[i] = r * Eigen::Vector3f(xyz_[i][0], xyz_[i][1], xyz_[i][2]) + t;
  }
}

void CompactCloud::Keep(const std::vector<std::uint32_t>& indices) {
  std::size_t n = 0;
  for (const std::uint32_t i : indices) {
    xyz_[n] = xyz_[i];
    colors_[n] = colors_[i];
    ++n;
  }
  xyz_.resize(n);
  colors_.resize(n);
  xyz_.shrink_to_fit();
  colors_.shrink_to_fit();
}

CameraCloud CompactCloud::Decode() const {
  CameraCloud cloud;
  cloud.points.reserve(size());
  for (std::size_t i = 0; i < size(); ++i) cloud.points.push_back(Point(i));
  cloud.colors = colors_;
  return cloud;
}

}  // namespace ccmd
