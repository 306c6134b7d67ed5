#pragma once

// Distance between a reconstructed point cloud and a reference (ground-truth) cloud, as
// CloudCompare's cloud-to-cloud distance: for every point, the distance to the nearest point
// of the other cloud (KD-tree). When the reference has normals (a sampled surface, as
// ccmd_synth writes), the reconstruction-to-reference distance is measured to the local
// plane of the nearest reference sample, so the reference's own sampling spacing does not
// inflate the error; points beyond the sampled surface's edge, and points whose nearest sample
// has no normal (a zero one: not on a flat patch), fall back to point distance. A reference
// without normals (a cloud back-projected from depth) gets them from its own points
// (EstimateNormals), as CloudCompare's "local model" fits a plane to the nearest neighbours.

#include <string>
#include <vector>

#include "libccmd/eval/trajectory_error.h"
#include "libccmd/io/ply.h"
#include "libccmd/io/trajectory.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"

namespace ccmd {

struct ReconstructionOptions {
  bool point_to_plane = true;            // use reference normals when present
  double completeness_threshold = 0.02;  // metres: reference points "covered" within this
  int threads = 0;                       // 0: all cores

  Status Validate() const;
  void Describe(OptionsWriter* out) const;
};

struct ReconstructionError {
  std::size_t reconstructed_points = 0;
  std::size_t reference_points = 0;
  bool point_to_plane = false;
  // Reconstruction -> reference (accuracy): the paper's "average distance".
  double mean = 0, median = 0, rmse = 0, p95 = 0, max = 0;
  // The same mean as distances to the nearest reference point, normals or not: it includes
  // the reference's sampling (about 0.4 of its spacing for a map on the surface itself).
  double mean_point_to_point = 0;
  // Reference -> reconstruction (completeness).
  double mean_reverse = 0, max_reverse = 0;
  double completeness = 0;  // fraction of reference points within completeness_threshold
  // max of both directed maxima (the paper's eq. 10).
  double hausdorff = 0;
};

// `per_point`, when given, receives each reconstruction point's distance (what `mean`
// averages), in the reconstruction's order.
StatusOr<ReconstructionError> ComputeReconstructionError(const PointCloud& reference,
                                                         const PointCloud& reconstruction,
                                                         const ReconstructionOptions& options = {},
                                                         std::vector<double>* per_point = nullptr);

struct NormalEstimationOptions {
  int neighbours = 12;  // the point and its nearest others (3..64)
  // Flatness: the smallest eigenvalue of the neighbourhood's covariance over their sum (0 on a
  // plane; 1/3 for an isotropic blob; 0.05-0.2 across an edge). Above it the normal is zero.
  double max_surface_variation = 0.05;
  int threads = 0;  // 0: all cores
};

// Gives every point of `cloud` the normal of the plane fitted to its neighbours (principal
// component analysis), or a zero normal where they are not flat or too few. Replaces any
// normals the cloud had. Orientation is arbitrary: the metric uses |offset . n|.
void EstimateNormals(PointCloud* cloud, const NormalEstimationOptions& options = {});

// Points sampled on a triangle mesh at about `spacing` metres (each face gets area / spacing^2
// of them, the fraction drawn at random), with the faces' normals. Deterministic.
PointCloud SampleMesh(const PointCloud& mesh, double spacing);

// A reference as the metric takes it: a mesh sampled every 5 mm with its faces' normals, a
// cloud without normals given them (EstimateNormals), a cloud with normals as it is.
// `how`, when given, says which was done ("" for nothing).
PointCloud AsReferenceSurface(PointCloud reference, std::string* how = nullptr);

// Directed nearest-neighbour distances from every point of `from` to the cloud `to`
// (point-to-point). Exposed for tests and other metrics.
std::vector<double> NearestDistances(const PointCloud& from, const PointCloud& to, int threads = 0);

// How far the keyframes see their map from: the median, over the map's points (at most 20000,
// evenly picked), of the distance to the nearest keyframe centre. 0 when either is empty.
double MapViewingDistance(const PointCloud& map, const Trajectory& keyframes);

// The rigid transform that puts a map built from `keyframes` into the ground truth's frame,
// fitted to the keyframes' whole poses: each centre and the points at the map's viewing
// distance along its axes (AteOptions::pose_alignment_arm_m). A pose whose orientation is a
// degrees off moves the points it put in the map by about a times that distance, so the fit
// weighs orientations as the map feels them; with 10 cm arms a few millimetres of keyframe
// position error (a fusion's join, or the ground truth's own) tilt a room's walls by
// centimetres. The result's errors are the centres' (as ComputeAte's). `arm_m` > 0 sets the
// arms' length instead (0.1 m was the fit before).
StatusOr<AteResult> AlignMap(const Trajectory& groundtruth, const Trajectory& keyframes,
                             const PointCloud& map, double arm_m = 0);

struct IcpOptions {
  int iterations = 30;
  double max_distance = 0.03;      // metres: map points further from the reference are left out
  std::size_t max_points = 50000;  // an even pick of the map's points takes part
};

struct IcpResult {
  Pose T_reference_map = Pose::Identity();  // moves the map onto the reference
  double turn_deg = 0;                      // its rotation angle
  double shift_m = 0;                       // its translation
  std::size_t pairs = 0;                    // point-plane pairs in the last iteration
};

// Point-to-plane ICP of `map` onto `reference` (a surface as AsReferenceSurface gives it; points
// without a normal are not used), from where the map is: the best rigid placement of the map
// on the reference, as CloudCompare's registration that the paper aligns its clouds with.
// Refused when the reference has no normals or fewer than 6 pairs are found.
StatusOr<IcpResult> AlignByIcp(const PointCloud& reference, const PointCloud& map,
                               const IcpOptions& options = {});

}  // namespace ccmd
