#pragma once

// Dense depth alignment between two keyframes: point-to-plane ICP with projective data
// association on reduced-resolution vertex and normal maps. The result is a relative pose
// with its information matrix (the Gauss-Newton Hessian of the point-to-plane residuals, each
// weighted by the depth sensor's noise), which the local BA uses as a constraint beside the
// feature observations: sparse features alone let keyframe poses drift where the depth of the
// whole view says otherwise. Directions the geometry does not constrain (a single plane) get
// little information, so they are left to the features.

#include <optional>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "libccmd/geometry/camera.h"
#include "libccmd/geometry/pose.h"
#include "libccmd/optim/reprojection.h"

namespace ccmd {

using Matrix6d = Eigen::Matrix<double, 6, 6>;

// Vertices and normals of a depth image in its camera's frame, every `step` pixels.
class DepthModel {
 public:
  // `depth_mm`: uint16 millimetres in `camera`'s image (0 = none).
  static DepthModel FromDepth(const cv::Mat& depth_mm, const PinholeCamera& camera, int step,
                              double min_depth, double max_depth);

  bool empty() const { return valid_ == 0; }
  int valid_points() const { return valid_; }
  int width() const { return width_; }
  int height() const { return height_; }
  // Vertex and normal at cell (x, y); the normal is zero where there is none.
  const Eigen::Vector3f& vertex(int x, int y) const { return vertex_[y * width_ + x]; }
  const Eigen::Vector3f& normal(int x, int y) const { return normal_[y * width_ + x]; }
  // The cell a camera-frame point projects to, if inside.
  std::optional<std::pair<int, int>> Cell(const Eigen::Vector3d& p) const;
  // The same surface in the frame of a camera `T_new_old` takes this model's points into (a
  // depth image taken a few milliseconds apart from its colour image, put at the colour
  // image's time): vertices and normals moved rigidly, nothing resampled; a point still finds
  // its cell where the camera that measured the depth saw it.
  DepthModel Moved(const Pose& T_new_old) const;

 private:
  int width_ = 0, height_ = 0, step_ = 1, valid_ = 0;
  Pose T_grid_model_ = Pose::Identity();  // model frame -> the frame the cells were measured in
  PinholeCamera camera_;
  std::vector<Eigen::Vector3f> vertex_, normal_;
};

struct DepthAlignmentOptions {
  int iterations = 12;
  int source_stride = 2;             // every n-th cell of the source, in both directions
  double max_distance = 0.05;        // metres, first iterations; halved for the last ones
  double min_normal_dot = 0.8;       // cosine between matched normals
  double min_inlier_fraction = 0.3;  // of the source's valid cells

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct DepthAlignment {
  Pose T_target_source = Pose::Identity();
  // Information of the perturbation xi = (rotation, translation) in T = exp(xi) * T_hat.
  Matrix6d information = Matrix6d::Zero();
  int inliers = 0;
  double rms = 0;         // metres, point-to-plane
  double mean_range = 0;  // metres, of the matched points from the target camera
};

// Aligns `source` to `target` starting from `T_target_source`; nullopt when too few points
// match or the solution does not settle.
std::optional<DepthAlignment> AlignDepth(const DepthModel& source, const DepthModel& target,
                                         const Pose& T_target_source, const DepthNoise& noise,
                                         const DepthAlignmentOptions& options = {});

// Whether `aligned` ended within 10 cm and 0.1 rad of the pose it started from (the features'
// estimate): further off, the alignment has converged elsewhere and is not trusted.
bool StaysNearStart(const DepthAlignment& aligned, const Pose& T_target_source_start);

// How well the geometry fixes all six directions of the pose: the smallest eigenvalue of the
// information over the largest, with a rotation counted as the displacement it causes at the
// matched points' mean range. 0 for a single plane, or a wall and the floor at its foot (they
// leave the slide along both free); a room's corner (floor and two walls) gives about 0.008
// (with the Kinect noise model's weights), ICL-NUIM's office 0.01-0.035: the weakest
// direction rests on the smallest of the surfaces that fix it.
double Conditioning(const DepthAlignment& aligned);

// The conditioning at which an alignment alone is trusted to place a frame (no features to
// back it): about a room corner's.
constexpr double kMinConditioningAlone = 0.005;

}  // namespace ccmd
