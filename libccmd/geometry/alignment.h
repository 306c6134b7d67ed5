#pragma once

// Least-squares similarity/rigid alignment of corresponding point sets
// (Umeyama 1991; the closed form Horn 1987 gives for the rigid case).

#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "libccmd/util/status.h"

namespace ccmd {

// dst ≈ scale * R * src + t
struct Similarity3 {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  double scale = 1.0;

  Eigen::Vector3d operator*(const Eigen::Vector3d& p) const { return scale * (R * p) + t; }
  Eigen::Isometry3d Rigid() const;  // R and t as an isometry (ignores scale)
};

// Finds the transform minimising sum ||dst_i - (s R src_i + t)||^2. With
// `with_scale` false, s = 1 (rigid). Needs at least 3 non-collinear points.
StatusOr<Similarity3> AlignPoints(const std::vector<Eigen::Vector3d>& src,
                                  const std::vector<Eigen::Vector3d>& dst, bool with_scale);

}  // namespace ccmd
