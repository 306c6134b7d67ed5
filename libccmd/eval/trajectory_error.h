#pragma once

// Trajectory error as evo computes it (evo_ape tum -a / evo_rpe): poses matched by
// timestamp (nearest within max_time_difference, each used once), the estimate aligned to
// the ground truth with the least-squares rigid transform of the positions (Umeyama
// without scale), then statistics of the position errors.

#include <vector>

#include "libccmd/geometry/alignment.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct ErrorStatistics {
  double rmse = 0, mean = 0, median = 0, std = 0, min = 0, max = 0;
};
ErrorStatistics ComputeStatistics(std::vector<double> errors);

struct AteOptions {
  double max_time_difference = 0.01;  // evo's default
  bool align = true;                  // rigid alignment (-a)
  bool correct_scale = false;         // similarity alignment (-as), for monocular systems
  // Alignment fitted to whole poses instead of positions when the positions cannot fix it:
  // fewer than three, or spread less than this (metres, standard deviation across their main
  // direction: points that close to a line leave the rotation about it to the noise). The fit
  // uses each pose's centre and the points pose_alignment_arm_m along its three axes, so one
  // pose is enough; the errors are still those of the centres. 0: positions only (evo's
  // behaviour).
  double pose_alignment_below_spread_m = 0;
  // How far from each centre those points lie (metres): the longer, the more the poses'
  // orientations count against their centres. A map is aligned with the distance at which its
  // keyframes see it (AlignMap, MapViewingDistance), so that the fit weighs a pose's error by how
  // far it moves the points that pose put in the map.
  double pose_alignment_arm_m = 0.1;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct AteResult {
  std::size_t matched = 0;
  ErrorStatistics error;                         // metres
  Similarity3 alignment;                         // maps the estimate into the ground-truth frame
  std::vector<double> timestamps;                // matched estimate timestamps
  std::vector<std::size_t> groundtruth_indices;  // the ground-truth pose each was compared with
  std::vector<double> errors;                    // per matched pose, metres
  std::vector<Eigen::Vector3d> error_vectors;    // aligned estimate minus ground truth, metres
  bool aligned_by_poses = false;                 // see AteOptions::pose_alignment_below_spread_m
};

StatusOr<AteResult> ComputeAte(const Trajectory& groundtruth, const Trajectory& estimate,
                               const AteOptions& options = {});

// How much of two estimates' errors against one ground truth they share: each estimate is
// aligned to the ground truth on its own (as ComputeAte does), and at the ground-truth poses
// both matched, their error vectors a and b split into the shared (a + b) / 2 and the apart
// (a - b) / 2. Runs of one method in different orders (frames forwards, backwards, every
// other one) drift differently; what they share is fixed to the frames: the reference's own
// error, or a systematic error of the sensor that every run reads alike.
struct SharedErrorResult {
  std::size_t matched = 0;
  double rmse_a = 0, rmse_b = 0;  // metres, over the poses both matched
  double shared_rmse = 0;         // rms of (a + b) / 2
  double apart_rmse = 0;          // rms of (a - b) / 2
  double correlation = 0;         // sum a.b / sqrt(sum |a|^2 sum |b|^2), in [-1, 1]
};

StatusOr<SharedErrorResult> ComputeSharedError(const Trajectory& groundtruth, const Trajectory& a,
                                               const Trajectory& b, const AteOptions& options = {});

struct RpeOptions {
  double max_time_difference = 0.01;
  int delta_frames = 1;  // compare poses this many matched frames apart

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct RpeResult {
  std::size_t pairs = 0;
  ErrorStatistics translation;  // metres
  ErrorStatistics rotation;     // degrees
};

StatusOr<RpeResult> ComputeRpe(const Trajectory& groundtruth, const Trajectory& estimate,
                               const RpeOptions& options = {});

// How far each position is from the straight line between its two neighbours, interpolated
// at its timestamp (metres; the first and last pose get 0). A camera carried by hand moves
// about a millimetre off that line between frames at 30 Hz; a pose that jumps by d and back
// gives d there and d/2 beside it. Finds where a ground truth made by tracking jumps.
std::vector<double> NeighbourDeviations(const Trajectory& trajectory);

// Applies a similarity to every pose of a trajectory (positions scaled, rotations kept).
Trajectory TransformTrajectory(const Trajectory& trajectory, const Similarity3& transform);

}  // namespace ccmd
