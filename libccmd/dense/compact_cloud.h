#pragma once

// A keyframe's points in its own camera frame, stored compactly once the keyframe has left
// the filter window: each coordinate as a 16-bit integer times a step chosen per keyframe
// (the largest coordinate over 32767: 0.09 mm for points up to 3 m), and the colour: 9 bytes
// a point, against 27 for float coordinates in camera and map frames and a colour. The
// points stay in the camera frame, so a pose update moves them exactly; the rounding (half a
// step per axis) is far below the voxel the map is filtered with.

#include <array>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "libccmd/dense/backprojection.h"
#include "libccmd/geometry/pose.h"

namespace ccmd {

class CompactCloud {
 public:
  CompactCloud() = default;
  // The points of `cloud` listed in `indices` (in that order).
  static CompactCloud Encode(const CameraCloud& cloud, const std::vector<std::uint32_t>& indices);

  std::size_t size() const { return xyz_.size(); }
  float step() const { return step_; }
  Eigen::Vector3f Point(std::size_t i) const {
    return step_ * Eigen::Vector3f(xyz_[i][0], xyz_[i][1], xyz_[i][2]);
  }
  const std::vector<std::array<std::uint8_t, 3>>& colors() const { return colors_; }

  // Every point under T_world_cam (out is resized).
  void Transform(const Pose& T_world_cam, std::vector<Eigen::Vector3f>* out) const;
  // Keeps the listed points (ascending indices), drops the others and frees their memory.
  void Keep(const std::vector<std::uint32_t>& indices);
  CameraCloud Decode() const;
  std::size_t MemoryBytes() const {
    return xyz_.capacity() * sizeof(xyz_[0]) + colors_.capacity() * sizeof(colors_[0]);
  }

 private:
  float step_ = 1.0f;
  std::vector<std::array<std::int16_t, 3>> xyz_;
  std::vector<std::array<std::uint8_t, 3>> colors_;
};

}  // namespace ccmd
