#include "libccmd/optim/pose_optimizer.h"

#include <ceres/ceres.h>
#include <gtest/gtest.h>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

const Intrinsics kCamera{525, 525, 319.5, 239.5};
// Depth sigma 5 mm (information 1 / 0.005^2).
constexpr double kDepthInfo = 1.0 / (0.005 * 0.005);

Pose MakePose(const Eigen::Vector3d& axis_angle, const Eigen::Vector3d& t) {
  Pose T = Pose::Identity();
  T.linear() = RotationFromAngleAxis(axis_angle);
  T.translation() = t;
  return T;
}

// Points in front of the camera with observations from the true pose, plus noise.
std::vector<PoseObservation> Observe(const Pose& T_cam_world, int n, double pixel_noise, Rng* rng) {
  std::vector<PoseObservation> obs;
  const Pose T_world_cam = T_cam_world.inverse();
  while (static_cast<int>(obs.size()) < n) {
    const Eigen::Vector3d pc(rng->Uniform(-1.5, 1.5), rng->Uniform(-1, 1), rng->Uniform(1, 4));
    PoseObservation o;
    o.point_world = T_world_cam * pc;
    const double u = kCamera.fx * pc.x() / pc.z() + kCamera.cx;
    const double v = kCamera.fy * pc.y() / pc.z() + kCamera.cy;
    o.uv = Eigen::Vector2d(u + pixel_noise * rng->Normal(), v + pixel_noise * rng->Normal());
    if (obs.size() % 2) {
      o.depth = pc.z() + 0.005 * rng->Normal();
      o.depth_information = kDepthInfo;
    }
    obs.push_back(o);
  }
  return obs;
}

TEST(PoseOptimizerTest, RecoversKnownPoseFromNoisyCorrespondences) {
  Rng rng(21);
  const Pose truth = MakePose({0.1, -0.2, 0.05}, {0.3, -0.1, 0.5});
  const auto obs = Observe(truth, 300, 0.5, &rng);
  const Pose start = MakePose({0.13, -0.16, 0.02}, {0.35, -0.05, 0.42});  // ~3 deg, 10 cm off
  const PoseOptimizationResult r = OptimizePose(start, obs, kCamera);
  EXPECT_LT(TranslationDistance(r.T_cam_world, truth), 0.005);
  EXPECT_LT(RotationDistance(r.T_cam_world, truth), 0.1 * M_PI / 180);
  EXPECT_GT(r.inliers, 280);
}

TEST(PoseOptimizerTest, RejectsGrossOutliers) {
  Rng rng(22);
  const Pose truth = MakePose({-0.05, 0.3, 0.0}, {-0.2, 0.1, 0.0});
  auto obs = Observe(truth, 200, 0.3, &rng);
  // A quarter of the matches are wrong: their pixels are anywhere in the image.
  for (std::size_t i = 0; i < obs.size(); i += 4)
    obs[i].uv = Eigen::Vector2d(rng.Uniform(0, 640), rng.Uniform(0, 480));
  const PoseOptimizationResult r =
      OptimizePose(truth * MakePose({0.02, 0, 0}, {0.05, 0, 0}), obs, kCamera);
  EXPECT_LT(TranslationDistance(r.T_cam_world, truth), 0.005);
  int wrong_kept = 0, right_dropped = 0;
  for (std::size_t i = 0; i < obs.size(); ++i) {
    if (i % 4 == 0)
      wrong_kept += r.inlier[i];
    else
      right_dropped += !r.inlier[i];
  }
  EXPECT_LE(wrong_kept, 2);
  EXPECT_LE(right_dropped, 5);
}

struct FixedPointResidual {
  ReprojectionResidual residual;
  Eigen::Vector3d point;
  template <typename T>
  bool operator()(const T* q, const T* t, T* r) const {
    const T p[3] = {T(point.x()), T(point.y()), T(point.z())};
    return residual(q, t, p, r);
  }
};

struct FixedPriorResidual {
  RelativePoseResidual residual;
  Pose T_b_world;
  template <typename T>
  bool operator()(const T* q, const T* t, T* r) const {
    const Eigen::Quaternion<T> qb(T_b_world.linear().cast<T>());
    const Eigen::Matrix<T, 3, 1> tb = T_b_world.translation().cast<T>();
    return residual(q, t, qb.coeffs().data(), tb.data(), r);
  }
};

// The same least-squares problem solved by Ceres (the solver the optimiser replaced).
Pose CeresLeastSquares(const Pose& start, const std::vector<PoseObservation>& obs,
                       const PosePrior* prior = nullptr) {
  using Fixed = FixedPointResidual;
  Eigen::Quaterniond q(start.linear());
  Eigen::Vector3d t = start.translation();
  ceres::Problem problem;
  problem.AddParameterBlock(q.coeffs().data(), 4, new ceres::EigenQuaternionManifold);
  for (const PoseObservation& o : obs) {
    const ReprojectionResidual r(kCamera, o.uv, o.depth, std::sqrt(o.information),
                                 std::sqrt(o.depth_information));
    ceres::CostFunction* cost =
        o.depth > 0
            ? static_cast<ceres::CostFunction*>(
                  new ceres::AutoDiffCostFunction<Fixed, 3, 4, 3>(new Fixed{r, o.point_world}))
            : new ceres::AutoDiffCostFunction<Fixed, 2, 4, 3>(new Fixed{r, o.point_world});
    problem.AddResidualBlock(cost, nullptr, q.coeffs().data(), t.data());
  }
  if (prior) {
    problem.AddResidualBlock(
        new ceres::AutoDiffCostFunction<FixedPriorResidual, 6, 4, 3>(new FixedPriorResidual{
            RelativePoseResidual(prior->T_b_a, prior->sqrt_information), prior->T_b_world}),
        nullptr, q.coeffs().data(), t.data());
  }
  ceres::Solver::Options options;
  options.function_tolerance = 1e-12;
  options.gradient_tolerance = 1e-14;
  options.parameter_tolerance = 1e-12;
  options.max_num_iterations = 100;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  Pose T = Pose::Identity();
  T.linear() = q.normalized().toRotationMatrix();
  T.translation() = t;
  return T;
}

TEST(PoseOptimizerTest, ReachesTheLeastSquaresOptimumCeresFinds) {
  Rng rng(23);
  const Pose truth = MakePose({0.2, 0.1, -0.1}, {-0.1, 0.2, 0.3});
  const auto obs = Observe(truth, 400, 1.0, &rng);  // noisy, no outliers: all stay inliers
  const Pose start = truth * MakePose({0.03, -0.02, 0.01}, {0.04, 0.03, -0.05});
  const PoseOptimizationResult r = OptimizePose(start, obs, kCamera);
  ASSERT_EQ(r.inliers, static_cast<int>(obs.size()) -
                           static_cast<int>(std::count(r.inlier.begin(), r.inlier.end(), false)));
  std::vector<PoseObservation> inliers;
  for (std::size_t i = 0; i < obs.size(); ++i) {
    if (r.inlier[i]) inliers.push_back(obs[i]);
  }
  const Pose reference = CeresLeastSquares(start, inliers);
  // The noise moves the optimum away from the truth by far more than this.
  EXPECT_GT(TranslationDistance(reference, truth), 1e-4);
  EXPECT_LT(TranslationDistance(r.T_cam_world, reference), 2e-6);
  EXPECT_LT(RotationDistance(r.T_cam_world, reference), 2e-7);
}

// A prior at camera pose T_a_world, measured relative to a fixed camera b (as a depth alignment
// with a keyframe gives it).
PosePrior PriorAt(const Pose& T_a_world, double sqrt_information) {
  PosePrior prior;
  prior.T_b_world = MakePose({-0.1, 0.05, 0.2}, {0.2, 0.1, -0.3});
  prior.T_b_a = prior.T_b_world * T_a_world.inverse();
  prior.sqrt_information = sqrt_information * Eigen::Matrix<double, 6, 6>::Identity();
  return prior;
}

TEST(PoseOptimizerTest, APriorIsWeighedAsCeresWeighsIt) {
  Rng rng(24);
  const Pose truth = MakePose({0.1, 0.2, -0.1}, {0.1, -0.2, 0.4});
  const auto obs = Observe(truth, 300, 1.0, &rng);
  const PosePrior prior = PriorAt(MakePose({0.002, 0, 0}, {0.003, 0, 0}) * truth, 1000);
  const Pose start = truth * MakePose({0.02, -0.01, 0.01}, {0.03, 0.02, -0.04});
  const PoseOptimizationResult with = OptimizePose(start, obs, kCamera, {}, &prior);
  const PoseOptimizationResult without = OptimizePose(start, obs, kCamera);
  std::vector<PoseObservation> inliers;
  for (std::size_t i = 0; i < obs.size(); ++i) {
    if (with.inlier[i]) inliers.push_back(obs[i]);
  }
  const Pose reference = CeresLeastSquares(start, inliers, &prior);
  // The prior moves the optimum by a millimetre; the two solvers agree to micrometres.
  EXPECT_GT(TranslationDistance(with.T_cam_world, without.T_cam_world), 5e-4);
  EXPECT_LT(TranslationDistance(with.T_cam_world, reference), 2e-6);
  EXPECT_LT(RotationDistance(with.T_cam_world, reference), 2e-7);
}

// Weighed far above the observations, the prior decides the pose: the measured relative pose is
// read as T_b * T_a^-1.
TEST(PoseOptimizerTest, AStrongPriorHoldsTheMeasuredPose) {
  Rng rng(25);
  const Pose truth = MakePose({-0.1, 0.1, 0.05}, {0.2, 0.1, 0.2});
  const auto obs = Observe(truth, 200, 0.5, &rng);
  const Pose measured = MakePose({0, 0.01, 0}, {0, 0, 0.01}) * truth;
  const PosePrior prior = PriorAt(measured, 1e6);
  const PoseOptimizationResult r = OptimizePose(truth, obs, kCamera, {}, &prior);
  EXPECT_LT(TranslationDistance(r.T_cam_world, measured), 1e-5);
  EXPECT_LT(RotationDistance(r.T_cam_world, measured), 1e-5);
}

TEST(PoseOptimizerTest, TooFewObservationsAreAllOutliers) {
  std::vector<PoseObservation> two(2);
  const PoseOptimizationResult r = OptimizePose(Pose::Identity(), two, kCamera);
  EXPECT_EQ(r.inliers, 0);
}

}  // namespace
}  // namespace ccmd
