#include "libccmd/optim/bundle_adjuster.h"

#include <gtest/gtest.h>

#include <memory>
#include <vector>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

const Intrinsics kCamera{525, 525, 319.5, 239.5};
// Depth sigma 5 mm (information 1 / 0.005^2).
constexpr double kDepthInfo = 1.0 / (0.005 * 0.005);

struct Scene {
  std::vector<Pose> T_cam_world;
  std::vector<Eigen::Vector3d> points;
  BaProblem problem;
};

// Five cameras looking at a cloud of points, observations with pixel noise.
Scene MakeScene(double pixel_noise, Rng* rng) {
  Scene s;
  for (int c = 0; c < 5; ++c) {
    Pose T_world_cam = LookAt(Eigen::Vector3d(0.3 * c, 0.1 * c, 0), Eigen::Vector3d(0.5, 0, 3),
                              -Eigen::Vector3d::UnitY());
    s.T_cam_world.push_back(T_world_cam.inverse());
  }
  for (int j = 0; j < 150; ++j) {
    s.points.emplace_back(rng->Uniform(-1, 2), rng->Uniform(-1, 1), rng->Uniform(2.5, 4));
  }
  s.problem.calibrations = {kCamera};
  for (const Pose& T : s.T_cam_world) s.problem.cameras.push_back({T, false});
  for (const auto& p : s.points) s.problem.points.push_back({p});
  for (int c = 0; c < 5; ++c) {
    for (int j = 0; j < 150; ++j) {
      const Eigen::Vector3d pc = s.T_cam_world[c] * s.points[j];
      const double u = kCamera.fx * pc.x() / pc.z() + kCamera.cx;
      const double v = kCamera.fy * pc.y() / pc.z() + kCamera.cy;
      if (u < 0 || v < 0 || u > 640 || v > 480) continue;
      BaObservation o;
      o.camera = c;
      o.point = j;
      o.uv = Eigen::Vector2d(u + pixel_noise * rng->Normal(), v + pixel_noise * rng->Normal());
      o.depth = pc.z() + 0.005 * rng->Normal();
      o.depth_information = kDepthInfo;
      s.problem.observations.push_back(o);
    }
  }
  return s;
}

double MeanReprojection(const BaProblem& p) {
  double sum = 0;
  for (const auto& o : p.observations) {
    sum += std::sqrt(ReprojectionChi2(kCamera, p.cameras[o.camera].T_cam_world,
                                      p.points[o.point].position, o.uv, 0, 1.0, 0));
  }
  return sum / p.observations.size();
}

TEST(BundleAdjusterTest, FixesAPerturbedKeyframeAndLowersReprojectionError) {
  Rng rng(31);
  Scene s = MakeScene(0.5, &rng);
  s.problem.cameras[0].fixed = true;
  // Perturb camera 3 by ~2 degrees and 5 cm, and every point by up to 2 cm.
  Pose delta = Pose::Identity();
  delta.linear() = RotationFromAngleAxis({0.02, -0.03, 0.01});
  delta.translation() = Eigen::Vector3d(0.05, -0.02, 0.03);
  s.problem.cameras[3].T_cam_world = delta * s.problem.cameras[3].T_cam_world;
  for (auto& p : s.problem.points)
    p.position += Eigen::Vector3d(rng.Uniform(-0.02, 0.02), rng.Uniform(-0.02, 0.02),
                                  rng.Uniform(-0.02, 0.02));
  const double before = MeanReprojection(s.problem);
  const BaSummary summary = BundleAdjust(&s.problem, BaOptions());
  const double after = MeanReprojection(s.problem);
  EXPECT_LT(after, before / 5);
  EXPECT_LT(after, 1.0);  // pixel noise is 0.5 px
  EXPECT_LT(TranslationDistance(s.problem.cameras[3].T_cam_world, s.T_cam_world[3]), 0.01);
  EXPECT_LT(RotationDistance(s.problem.cameras[3].T_cam_world, s.T_cam_world[3]), 0.3 * M_PI / 180);
  // The fixed camera did not move.
  EXPECT_LT(TranslationDistance(s.problem.cameras[0].T_cam_world, s.T_cam_world[0]), 1e-12);
  EXPECT_FALSE(summary.aborted);
}

TEST(BundleAdjusterTest, MarksWrongObservationsAsOutliers) {
  Rng rng(32);
  Scene s = MakeScene(0.3, &rng);
  s.problem.cameras[0].fixed = true;
  s.problem.cameras[1].fixed = true;
  std::vector<int> corrupted;
  for (std::size_t i = 7; i < s.problem.observations.size(); i += 37) {
    s.problem.observations[i].uv += Eigen::Vector2d(25, -30);
    corrupted.push_back(static_cast<int>(i));
  }
  const BaSummary summary = BundleAdjust(&s.problem, BaOptions());
  for (int i : corrupted) EXPECT_TRUE(summary.outlier[i]) << i;
  EXPECT_LE(summary.outliers, static_cast<int>(corrupted.size()) + 3);
}

// The second pass, which has no robust kernel, must leave the first pass's outliers out:
// one camera's wrong matches, all displaced the same way, would otherwise pull it off.
TEST(BundleAdjusterTest, TheSecondPassLeavesTheOutliersOut) {
  Rng rng(33);
  Scene s = MakeScene(0.3, &rng);
  s.problem.cameras[0].fixed = true;
  s.problem.cameras[1].fixed = true;
  int corrupted = 0;
  for (std::size_t i = 0; i < s.problem.observations.size(); ++i) {
    BaObservation& o = s.problem.observations[i];
    if (o.camera == 3 && i % 5 == 0) {
      o.uv += Eigen::Vector2d(12, 9);
      ++corrupted;
    }
  }
  ASSERT_GT(corrupted, 15);
  BaOptions options;
  options.second_iterations = 20;
  const BaSummary summary = BundleAdjust(&s.problem, options);
  EXPECT_GE(summary.outliers, corrupted);
  EXPECT_GT(summary.pass_iterations[1], 0);
  // With them: 12 mm and 0.16 degrees; without: about 2 mm.
  EXPECT_LT(TranslationDistance(s.problem.cameras[3].T_cam_world, s.T_cam_world[3]), 0.005);
  EXPECT_LT(RotationDistance(s.problem.cameras[3].T_cam_world, s.T_cam_world[3]),
            0.08 * M_PI / 180);
}

// The same problem gives the same solution to the last bit whatever the heap looks like:
// Ceres orders the cameras' parameter blocks by address, and with rotations and translations
// in two arrays their order followed where the allocator put the arrays (an offline run's
// trajectory then depended on, for instance, the length of a path on the command line).
TEST(BundleAdjusterTest, TheSolutionDoesNotDependOnTheHeap) {
  Rng rng(34);
  Scene s = MakeScene(0.3, &rng);
  s.problem.cameras[0].fixed = true;
  for (auto& p : s.problem.points) p.position += Eigen::Vector3d(0.01, -0.01, 0.02);
  const auto solve = [&s] {
    BaProblem problem = s.problem;
    BaOptions ceres;  // the in-tree dense solver keeps its cameras in their order anyway
    ceres.solver = BaLinearSolver::kSparseSchur;
    BundleAdjust(&problem, ceres);
    return problem;
  };
  const BaProblem first = solve();
  // Blocks of the translations' size taken until they come from fresh memory, the last one
  // freed again: the next block of that size is now above everything the first solve used.
  const std::size_t translations = s.problem.cameras.size() * sizeof(Eigen::Vector3d);
  std::vector<std::unique_ptr<char[]>> taken;
  taken.reserve(256);
  for (int i = 0; i < 256; ++i) taken.emplace_back(new char[translations]);
  taken.back().reset();
  const BaProblem second = solve();
  for (std::size_t c = 0; c < first.cameras.size(); ++c) {
    EXPECT_EQ(first.cameras[c].T_cam_world.matrix(), second.cameras[c].T_cam_world.matrix()) << c;
  }
  for (std::size_t j = 0; j < first.points.size(); ++j) {
    EXPECT_EQ(first.points[j].position, second.points[j].position) << j;
  }
}

TEST(BundleAdjusterTest, AbortFlagStopsTheSolver) {
  Rng rng(33);
  Scene s = MakeScene(0.5, &rng);
  s.problem.cameras[0].fixed = true;
  for (auto& p : s.problem.points) p.position.z() += 0.3;
  std::atomic<bool> abort{true};
  BaOptions options;
  options.abort = &abort;
  const BaSummary summary = BundleAdjust(&s.problem, options);
  EXPECT_TRUE(summary.aborted);
  EXPECT_LE(summary.iterations, 2);
}

// Observations with and without depth (2 or 3 measured values) still give Ceres rows of one
// size, so it eliminates the points with its compiled 3x3x3 code; the dynamic path is several
// times slower. The second pass removes the outliers and keeps the problem (with Ceres, and
// with the in-tree dense solver).
TEST(BundleAdjusterTest, MixedObservationsUseTheCompiledSchurEliminator) {
  Rng rng(36);
  Scene s = MakeScene(0.5, &rng);
  s.problem.cameras[0].fixed = true;
  for (std::size_t i = 0; i < s.problem.observations.size(); i += 3) {
    s.problem.observations[i].depth = 0;
    s.problem.observations[i].depth_information = 0;
  }
  s.problem.observations[5].uv += Eigen::Vector2d(40, 0);
  s.problem.cameras[2].T_cam_world.translation() += Eigen::Vector3d(0.03, 0, 0);
  for (BaLinearSolver solver : {BaLinearSolver::kDenseSchur, BaLinearSolver::kSparseSchur}) {
    Scene copy = s;
    BaOptions options;
    options.solver = solver;
    const BaSummary summary = BundleAdjust(&copy.problem, options);
    if (solver == BaLinearSolver::kSparseSchur) {
      EXPECT_EQ(summary.schur_structure, "3,3,3");
    }
    EXPECT_GT(summary.pass_iterations[1], 0);
    EXPECT_TRUE(summary.outlier[5]);
    EXPECT_LT(TranslationDistance(copy.problem.cameras[2].T_cam_world, s.T_cam_world[2]), 0.005);
  }
}

// The in-tree dense solver (local BA) and Ceres (global BA) minimise the same cost, so run to
// convergence they reach the same optimum: every camera, every point, the same outliers. A
// wrong sign or factor in the dense solver's pose Jacobians (rotation applied on the left, the
// relative poses' chain through the quaternion) or in its Schur complement would stop it short
// or elsewhere.
TEST(BundleAdjusterTest, TheDenseSolverReachesCeresOptimum) {
  Rng rng(34);
  Scene a = MakeScene(0.5, &rng);
  a.problem.cameras[0].fixed = true;
  for (std::size_t i = 0; i < a.problem.observations.size(); i += 4) {
    a.problem.observations[i].depth = 0;  // a quarter without depth
    a.problem.observations[i].depth_information = 0;
  }
  for (std::size_t i = 3; i < a.problem.observations.size(); i += 41)
    a.problem.observations[i].uv += Eigen::Vector2d(20, -15);
  for (int c = 1; c < 5; ++c) {
    Pose delta = Pose::Identity();
    delta.linear() = RotationFromAngleAxis({0.01 * c, -0.015, 0.005 * c});
    delta.translation() = Eigen::Vector3d(0.02 * c, -0.01, 0.015);
    a.problem.cameras[c].T_cam_world = delta * a.problem.cameras[c].T_cam_world;
  }
  for (auto& p : a.problem.points)
    p.position += Eigen::Vector3d(rng.Uniform(-0.02, 0.02), rng.Uniform(-0.02, 0.02),
                                  rng.Uniform(-0.02, 0.02));
  // Relative poses 1 cm off the truth: between two free cameras, and to the fixed one.
  for (const auto& [ca, cb] : {std::pair{1, 3}, std::pair{0, 4}}) {
    Pose T_b_a = a.T_cam_world[cb] * a.T_cam_world[ca].inverse();
    T_b_a.translation() += Eigen::Vector3d(0.01, 0, -0.005);
    a.problem.relative_poses.push_back(
        {ca, cb, T_b_a, 200 * Eigen::Matrix<double, 6, 6>::Identity()});
  }
  Scene b = a;
  BaOptions dense;
  dense.first_iterations = 15;
  dense.second_iterations = 40;
  dense.function_tolerance = 1e-14;
  BaOptions ceres = dense;
  ceres.solver = BaLinearSolver::kSparseSchur;
  const BaSummary from_dense = BundleAdjust(&a.problem, dense);
  const BaSummary from_ceres = BundleAdjust(&b.problem, ceres);
  EXPECT_EQ(from_dense.outlier, from_ceres.outlier);
  EXPECT_GE(from_dense.outliers, 5);
  EXPECT_NEAR(from_dense.final_cost, from_ceres.final_cost, 1e-6 * from_ceres.final_cost);
  for (std::size_t c = 0; c < a.problem.cameras.size(); ++c) {
    EXPECT_LT(
        TranslationDistance(a.problem.cameras[c].T_cam_world, b.problem.cameras[c].T_cam_world),
        1e-7)
        << c;
    EXPECT_LT(RotationDistance(a.problem.cameras[c].T_cam_world, b.problem.cameras[c].T_cam_world),
              1e-7)
        << c;
  }
  for (std::size_t j = 0; j < a.problem.points.size(); ++j)
    EXPECT_LT((a.problem.points[j].position - b.problem.points[j].position).norm(), 1e-7) << j;
  // And both got there from 2-8 cm off.
  EXPECT_LT(TranslationDistance(a.problem.cameras[4].T_cam_world, a.T_cam_world[4]), 0.01);
}

// A point that has drifted behind the camera observing it, or onto its centre plane (a
// residual that divides by zero), is marked an outlier and does not stop the rest of the
// problem from being solved, with either solver; nothing non-finite reaches the estimate.
TEST(BundleAdjusterTest, APointBehindItsCameraIsAnOutlierAndTheRestIsSolved) {
  for (const double depth_in_camera : {-0.5, 0.0}) {
    for (BaLinearSolver solver : {BaLinearSolver::kDenseSchur, BaLinearSolver::kSparseSchur}) {
      Rng rng(37);
      Scene s = MakeScene(0.3, &rng);
      s.problem.cameras[0].fixed = true;
      s.problem.cameras[3].T_cam_world.translation() += Eigen::Vector3d(0.02, -0.01, 0.01);
      const Eigen::Vector3d in_camera(0.1, 0.1, depth_in_camera);
      s.problem.points.push_back({s.T_cam_world[2].inverse() * in_camera});
      BaObservation o;
      o.camera = 2;
      o.point = static_cast<int>(s.problem.points.size()) - 1;
      o.uv = Eigen::Vector2d(340, 260);
      o.depth = 2.0;
      o.depth_information = kDepthInfo;
      s.problem.observations.push_back(o);
      BaOptions options;
      options.solver = solver;
      const BaSummary summary = BundleAdjust(&s.problem, options);
      const std::string where = "z " + std::to_string(depth_in_camera) + ", solver " +
                                std::to_string(static_cast<int>(solver));
      EXPECT_TRUE(summary.outlier.back()) << where;
      EXPECT_LT(TranslationDistance(s.problem.cameras[3].T_cam_world, s.T_cam_world[3]), 0.005)
          << where;
      for (const BaCamera& c : s.problem.cameras) EXPECT_TRUE(c.T_cam_world.matrix().allFinite());
      for (const BaPoint& p : s.problem.points) EXPECT_TRUE(p.position.allFinite()) << where;
    }
  }
}

// A relative pose places a camera that has no observation at all: T_b = T_b_a * T_a. The
// inverse convention (T_a_b) would put it elsewhere, so this pins the residual's meaning.
TEST(BundleAdjusterTest, RelativePosePlacesACameraWithoutObservations) {
  Rng rng(35);
  Scene s = MakeScene(0.3, &rng);
  s.problem.cameras[0].fixed = true;
  Pose T_b_a = Pose::Identity();
  T_b_a.linear() = RotationFromAngleAxis({0.05, 0.1, -0.02});
  T_b_a.translation() = Eigen::Vector3d(0.2, -0.1, 0.05);
  const Pose truth = T_b_a * s.T_cam_world[2];
  BaCamera extra;
  extra.T_cam_world = truth;
  extra.T_cam_world.translation() += Eigen::Vector3d(0.1, 0.05, -0.08);  // start 14 cm off
  s.problem.cameras.push_back(extra);
  const int b = static_cast<int>(s.problem.cameras.size()) - 1;
  s.problem.relative_poses.push_back({2, b, T_b_a, 100 * Eigen::Matrix<double, 6, 6>::Identity()});
  BundleAdjust(&s.problem, BaOptions());
  const Pose expected = T_b_a * s.problem.cameras[2].T_cam_world;  // from camera 2 as estimated
  EXPECT_LT(TranslationDistance(s.problem.cameras[b].T_cam_world, expected), 1e-5);
  EXPECT_LT(RotationDistance(s.problem.cameras[b].T_cam_world, expected), 1e-5);
  // Camera 2 itself stays where its observations put it.
  EXPECT_LT(TranslationDistance(s.problem.cameras[2].T_cam_world, s.T_cam_world[2]), 0.005);
}

// A relative pose agreeing with the observations pulls a camera with few observations back
// to the truth; a wrong measurement with a weak weight barely moves a well observed one.
TEST(BundleAdjusterTest, RelativePoseIsWeighedByItsInformation) {
  Rng rng(36);
  Scene s = MakeScene(0.3, &rng);
  s.problem.cameras[0].fixed = true;
  Pose wrong = s.T_cam_world[3] * s.T_cam_world[1].inverse();  // T_3_1, true
  wrong.translation() += Eigen::Vector3d(0.05, 0, 0);          // 5 cm off
  Scene weak = s, strong = s;
  weak.problem.relative_poses.push_back(
      {1, 3, wrong, 0.01 * Eigen::Matrix<double, 6, 6>::Identity()});
  strong.problem.relative_poses.push_back(
      {1, 3, wrong, 1e5 * Eigen::Matrix<double, 6, 6>::Identity()});
  BundleAdjust(&weak.problem, BaOptions());
  BundleAdjust(&strong.problem, BaOptions());
  const auto relative = [](const BaProblem& p) {
    return p.cameras[3].T_cam_world * p.cameras[1].T_cam_world.inverse();
  };
  // Weak: the observations win, the relative pose stays near the truth (5 cm from `wrong`).
  EXPECT_GT(TranslationDistance(relative(weak.problem), wrong), 0.04);
  // Strong: the relative pose is met.
  EXPECT_LT(TranslationDistance(relative(strong.problem), wrong), 0.005);
}

}  // namespace
}  // namespace ccmd
