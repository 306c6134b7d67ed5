#include "libccmd/eval/reconstruction_error.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <thread>

#include <Eigen/Eigenvalues>

#include "libccmd/eval/trajectory_error.h"
#include "libccmd/geometry/kdtree.h"
#include "libccmd/util/random.h"

namespace ccmd {

Status ReconstructionOptions::Validate() const {
  if (!(completeness_threshold > 0) || !std::isfinite(completeness_threshold)) {
    return InvalidArgument("completeness threshold must be positive");
  }
  if (threads < 0) return InvalidArgument("threads must be >= 0 (0: all cores)");
  return Status::Ok();
}

void ReconstructionOptions::Describe(OptionsWriter* out) const {
  out->Add("point_to_plane", point_to_plane);
  out->Add("completeness_threshold", completeness_threshold);
  out->Add("threads", threads);
}
namespace {

int ThreadCount(int requested) {
  return requested > 0 ? requested : std::max(1u, std::thread::hardware_concurrency());
}

template <typename Fn>
void ParallelFor(std::size_t n, int threads, Fn&& fn) {
  threads = std::max(1, std::min<int>(threads, static_cast<int>(n / 4096) + 1));
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t) {
    pool.emplace_back([&, t] {
      for (std::size_t i = t; i < n; i += threads) fn(i);
    });
  }
  for (auto& th : pool) th.join();
}

// How far apart a point set's samples lie: the 95th percentile of the distance from a sample
// to its nearest other sample, over a random subset. On a grid (a voxel-filtered cloud) that
// is the grid's step; on randomly drawn samples (a sampled mesh) the median would leave a
// fifth of the surface further from its nearest sample than 1.5 times it.
double EstimateSpacing(const PointCloud& cloud, const PointKdTree& tree) {
  Rng rng(7);
  std::vector<double> d;
  for (int i = 0; i < 512 && cloud.size() > 1; ++i) {
    const auto& p = cloud.points[static_cast<std::size_t>(rng.Uniform() * cloud.size())];
    std::uint32_t idx[2];
    float dist[2];
    if (tree.Nearest(p, 2, idx, dist) == 2) d.push_back(std::sqrt(dist[1]));
  }
  if (d.empty()) return 0.0;
  const std::size_t k = d.size() * 95 / 100;
  std::nth_element(d.begin(), d.begin() + k, d.end());
  return d[k];
}

}  // namespace

void EstimateNormals(PointCloud* cloud, const NormalEstimationOptions& options) {
  const std::size_t n = cloud->size();
  cloud->normals.assign(n, Eigen::Vector3f::Zero());
  constexpr int kMaxNeighbours = 64;
  const auto k = static_cast<std::size_t>(std::clamp(options.neighbours, 3, kMaxNeighbours));
  if (n < k) return;
  const PointKdTree tree(cloud->points);
  ParallelFor(n, ThreadCount(options.threads), [&](std::size_t i) {
    std::array<std::uint32_t, kMaxNeighbours> index;
    std::array<float, kMaxNeighbours> d2;
    const std::size_t found = tree.Nearest(cloud->points[i], k, index.data(), d2.data());
    if (found < k) return;
    Eigen::Vector3d mean = Eigen::Vector3d::Zero();
    for (std::size_t j = 0; j < found; ++j) mean += cloud->points[index[j]].cast<double>();
    mean /= static_cast<double>(found);
    Eigen::Matrix3d covariance = Eigen::Matrix3d::Zero();
    for (std::size_t j = 0; j < found; ++j) {
      const Eigen::Vector3d d = cloud->points[index[j]].cast<double>() - mean;
      covariance += d * d.transpose();
    }
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen(covariance);
    const double total = eigen.eigenvalues().sum();
    if (!(total > 0) || eigen.eigenvalues()(0) > options.max_surface_variation * total) return;
    cloud->normals[i] = eigen.eigenvectors().col(0).cast<float>();  // ascending eigenvalues
  });
}

PointCloud SampleMesh(const PointCloud& mesh, double spacing) {
  PointCloud out;
  Rng rng(17);
  for (const auto& t : mesh.triangles) {
    const Eigen::Vector3f a = mesh.points[t[0]], b = mesh.points[t[1]], c = mesh.points[t[2]];
    const Eigen::Vector3f cross = (b - a).cross(c - a);
    const double area = 0.5 * cross.norm();
    if (area <= 0) continue;
    const Eigen::Vector3f normal = cross.normalized();
    // Expected count area / spacing^2, the fraction drawn at random so small faces count too.
    const double expected = area / (spacing * spacing);
    int n = static_cast<int>(expected);
    if (rng.Uniform() < expected - n) ++n;
    for (int i = 0; i < n; ++i) {
      double u = rng.Uniform(), v = rng.Uniform();
      if (u + v > 1) u = 1 - u, v = 1 - v;
      out.points.push_back(a + static_cast<float>(u) * (b - a) + static_cast<float>(v) * (c - a));
      out.normals.push_back(normal);
    }
  }
  return out;
}

PointCloud AsReferenceSurface(PointCloud reference, std::string* how) {
  std::string done;
  if (!reference.triangles.empty()) {
    reference = SampleMesh(reference, 0.005);
    done = "mesh, sampled every 5 mm";
  } else if (!reference.HasNormals()) {
    EstimateNormals(&reference);
    done = "normals from " + std::to_string(NormalEstimationOptions().neighbours) + " neighbours";
  }
  if (how) *how = done;
  return reference;
}

std::vector<double> NearestDistances(const PointCloud& from, const PointCloud& to, int threads) {
  std::vector<double> distances(from.size(), 0.0);
  if (to.size() == 0) return distances;
  const PointKdTree tree(to.points);
  ParallelFor(from.size(), ThreadCount(threads), [&](std::size_t i) {
    float d2 = 0;
    tree.Nearest(from.points[i], &d2);
    distances[i] = std::sqrt(d2);
  });
  return distances;
}

StatusOr<ReconstructionError> ComputeReconstructionError(const PointCloud& reference,
                                                         const PointCloud& reconstruction,
                                                         const ReconstructionOptions& options,
                                                         std::vector<double>* per_point) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  if (reference.size() == 0) return InvalidArgument("the reference cloud is empty");
  if (reconstruction.size() == 0) return InvalidArgument("the reconstructed cloud is empty");
  const int threads = ThreadCount(options.threads);
  ReconstructionError result;
  result.reconstructed_points = reconstruction.size();
  result.reference_points = reference.size();
  result.point_to_plane = options.point_to_plane && reference.HasNormals();

  const PointKdTree reference_tree(reference.points);
  const double tangential_limit = 1.5 * EstimateSpacing(reference, reference_tree);
  std::vector<double> accuracy(reconstruction.size()), point_distance(reconstruction.size());
  ParallelFor(reconstruction.size(), threads, [&](std::size_t i) {
    float d2 = 0;
    const std::uint32_t j = reference_tree.Nearest(reconstruction.points[i], &d2);
    double d = std::sqrt(d2);
    point_distance[i] = d;
    if (result.point_to_plane && reference.normals[j].squaredNorm() > 0) {
      const Eigen::Vector3f offset = reconstruction.points[i] - reference.points[j];
      const double normal_part = std::abs(offset.dot(reference.normals[j].normalized()));
      const double tangential =
          std::sqrt(std::max(0.0, static_cast<double>(d2) - normal_part * normal_part));
      if (tangential <= tangential_limit) d = normal_part;
    }
    accuracy[i] = d;
  });
  const std::vector<double> completeness = NearestDistances(reference, reconstruction, threads);

  const ErrorStatistics a = ComputeStatistics(accuracy);
  result.mean = a.mean;
  result.median = a.median;
  result.rmse = a.rmse;
  result.max = a.max;
  result.mean_point_to_point = ComputeStatistics(point_distance).mean;
  if (per_point) *per_point = accuracy;
  std::vector<double> sorted = accuracy;
  const std::size_t k95 =
      std::min(sorted.size() - 1, static_cast<std::size_t>(0.95 * sorted.size()));
  std::nth_element(sorted.begin(), sorted.begin() + k95, sorted.end());
  result.p95 = sorted[k95];
  const ErrorStatistics c = ComputeStatistics(completeness);
  result.mean_reverse = c.mean;
  result.max_reverse = c.max;
  std::size_t covered = 0;
  for (double d : completeness) covered += d <= options.completeness_threshold;
  result.completeness = static_cast<double>(covered) / completeness.size();
  result.hausdorff = std::max(result.max, result.max_reverse);
  return result;
}

double MapViewingDistance(const PointCloud& map, const Trajectory& keyframes) {
  if (map.size() == 0 || keyframes.empty()) return 0;
  std::vector<Eigen::Vector3f> centres;
  for (const StampedPose& k : keyframes)
    centres.push_back(k.T_world_cam.translation().cast<float>());
  const PointKdTree tree(centres);
  const std::size_t step = std::max<std::size_t>(1, map.size() / 20000);
  std::vector<double> distances;
  for (std::size_t i = 0; i < map.size(); i += step) {
    float d2 = 0;
    tree.Nearest(map.points[i], &d2);
    distances.push_back(std::sqrt(d2));
  }
  auto middle = distances.begin() + static_cast<std::ptrdiff_t>(distances.size() / 2);
  std::nth_element(distances.begin(), middle, distances.end());
  return *middle;
}

StatusOr<AteResult> AlignMap(const Trajectory& groundtruth, const Trajectory& keyframes,
                             const PointCloud& map, double arm_m) {
  AteOptions by_poses;
  by_poses.pose_alignment_below_spread_m = std::numeric_limits<double>::infinity();
  const double arm = arm_m > 0 ? arm_m : MapViewingDistance(map, keyframes);
  if (arm > 0) by_poses.pose_alignment_arm_m = arm;
  return ComputeAte(groundtruth, keyframes, by_poses);
}

StatusOr<IcpResult> AlignByIcp(const PointCloud& reference, const PointCloud& map,
                               const IcpOptions& options) {
  if (!reference.HasNormals()) return InvalidArgument("ICP needs the reference's normals");
  const PointKdTree tree(reference.points);
  std::vector<Eigen::Vector3d> points;
  const std::size_t step =
      std::max<std::size_t>(1, map.size() / std::max<std::size_t>(1, options.max_points));
  for (std::size_t i = 0; i < map.size(); i += step) points.push_back(map.points[i].cast<double>());
  IcpResult result;
  const float max_d2 = static_cast<float>(options.max_distance * options.max_distance);
  for (int iteration = 0; iteration < options.iterations; ++iteration) {
    // Linearised about the current placement: a small rotation w and shift v move point p
    // along the reference's normal n by n . (w x p + v) = (p x n) . w + n . v.
    Eigen::Matrix<double, 6, 6> H = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> g = Eigen::Matrix<double, 6, 1>::Zero();
    result.pairs = 0;
    for (const Eigen::Vector3d& p : points) {
      float d2 = 0;
      const std::uint32_t i = tree.Nearest(p.cast<float>(), &d2);
      const Eigen::Vector3d n = reference.normals[i].cast<double>();
      if (d2 > max_d2 || n.squaredNorm() < 0.5) continue;
      Eigen::Matrix<double, 6, 1> J;
      J << p.cross(n), n;
      H += J * J.transpose();
      g += J * n.dot(p - reference.points[i].cast<double>());
      ++result.pairs;
    }
    if (result.pairs < 6) return InvalidArgument("ICP found too few map points near the reference");
    // A little damping leaves the directions the reference does not hold (a single wall's
    // slide along itself) where they are instead of solving for them.
    H.diagonal().array() += 1e-9 * H.trace();
    const Eigen::Matrix<double, 6, 1> x = -H.ldlt().solve(g);
    if (!x.allFinite()) return InvalidArgument("ICP did not converge");
    Pose step_pose = Pose::Identity();
    if (x.head<3>().norm() > 0) {
      step_pose.linear() =
          Eigen::AngleAxisd(x.head<3>().norm(), x.head<3>().normalized()).toRotationMatrix();
    }
    step_pose.translation() = x.tail<3>();
    for (Eigen::Vector3d& p : points) p = step_pose * p;
    result.T_reference_map = step_pose * result.T_reference_map;
    if (x.norm() < 1e-9) break;
  }
  result.turn_deg = Eigen::AngleAxisd(result.T_reference_map.linear()).angle() * 180 / M_PI;
  result.shift_m = result.T_reference_map.translation().norm();
  return result;
}

}  // namespace ccmd
