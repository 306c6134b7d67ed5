#include "libccmd/eval/trajectory_error.h"

#include <gtest/gtest.h>

#include <functional>

namespace ccmd {
namespace {

Trajectory Circle(int n) {
  Trajectory t;
  for (int i = 0; i < n; ++i) {
    const double a = 2 * M_PI * i / n;
    Pose p = Pose::Identity();
    p.linear() = Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    p.translation() = Eigen::Vector3d(std::cos(a), std::sin(a), 0.3 * std::sin(3 * a));
    t.push_back({100.0 + i / 30.0, p});
  }
  return t;
}

TEST(AteTest, RigidlyMovedCopyHasZeroError) {
  const Trajectory gt = Circle(200);
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(1.1, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(4, -2, 1);
  Trajectory est = gt;
  for (auto& p : est) p.T_world_cam = T * p.T_world_cam;
  auto ate = ComputeAte(gt, est);
  ASSERT_TRUE(ate.ok());
  EXPECT_EQ(ate->matched, 200u);
  EXPECT_LT(ate->error.rmse, 1e-9);
  EXPECT_LT((ate->alignment.R - T.linear().transpose()).norm(), 1e-9);
}

// One or two poses (an agent's map that never fused) cannot be aligned by positions; their
// whole poses can. A trajectory with spread is aligned by positions as before.
TEST(AteTest, PoseAlignmentForTrajectoriesTooShortForPositions) {
  const Trajectory gt = Circle(200);
  Pose T = Pose::Identity();
  T.linear() = Eigen::AngleAxisd(0.7, Eigen::Vector3d(-1, 2, 0.5).normalized()).toRotationMatrix();
  T.translation() = Eigen::Vector3d(1, 2, -3);
  Trajectory est;
  for (int i : {10, 11}) est.push_back({gt[i].timestamp, T * gt[i].T_world_cam});
  EXPECT_FALSE(ComputeAte(gt, est).ok());
  AteOptions options;
  options.pose_alignment_below_spread_m = 0.1;
  auto ate = ComputeAte(gt, est, options);
  ASSERT_TRUE(ate.ok()) << ate.status().ToString();
  EXPECT_TRUE(ate->aligned_by_poses);
  EXPECT_LT(ate->error.rmse, 1e-9);
  EXPECT_LT((ate->alignment.R - T.linear().transpose()).norm(), 1e-9);
  // An error of the second pose shows (half of it, split by the fit between the two).
  est[1].T_world_cam.translation() += Eigen::Vector3d(0, 0, 0.01);
  ate = ComputeAte(gt, est, options);
  ASSERT_TRUE(ate.ok());
  EXPECT_GT(ate->error.max, 0.003);

  Trajectory whole = gt;
  for (auto& p : whole) p.T_world_cam = T * p.T_world_cam;
  whole[5].T_world_cam.translation().x() += 0.05;
  auto by_positions = ComputeAte(gt, whole);
  auto with_option = ComputeAte(gt, whole, options);
  ASSERT_TRUE(by_positions.ok() && with_option.ok());
  EXPECT_FALSE(with_option->aligned_by_poses);
  EXPECT_EQ(with_option->error.rmse, by_positions->error.rmse);
}

TEST(AteTest, KnownPerturbationGivesItsMagnitude) {
  // Alternating +-d along z: zero mean, uncorrelated with the circle, so alignment cannot
  // remove it; every error is d, so RMSE = mean = max = d.
  const Trajectory gt = Circle(400);
  const double d = 0.02;
  Trajectory est = gt;
  for (std::size_t i = 0; i < est.size(); ++i) {
    est[i].T_world_cam.translation().z() += (i % 2 ? d : -d);
  }
  auto ate = ComputeAte(gt, est);
  ASSERT_TRUE(ate.ok());
  EXPECT_NEAR(ate->error.rmse, d, 1e-4);
  EXPECT_NEAR(ate->error.mean, d, 1e-4);
  EXPECT_NEAR(ate->error.max, d, 2e-4);
}

// Two estimates with known error patterns along z, each uncorrelated with the circle so that
// alignment removes none of it: p alternates +-d frame by frame, q goes +d, +d, -d, -d
// (orthogonal to p over the whole circle). Each estimate is moved rigidly on its own, so
// the split is between the errors after each one's alignment.
TEST(SharedErrorTest, SplitsTwoEstimatesErrorsIntoSharedAndApart) {
  const Trajectory gt = Circle(400);
  const double d = 0.02;
  const auto with_error = [&](const std::function<double(std::size_t)>& dz, double turn) {
    Pose T = Pose::Identity();
    T.linear() = Eigen::AngleAxisd(turn, Eigen::Vector3d(1, -2, 1).normalized()).toRotationMatrix();
    T.translation() = Eigen::Vector3d(turn, 1, -2);
    Trajectory est = gt;
    for (std::size_t i = 0; i < est.size(); ++i) {
      est[i].T_world_cam.translation().z() += dz(i);
      est[i].T_world_cam = T * est[i].T_world_cam;
    }
    return est;
  };
  const auto p = [&](std::size_t i) { return i % 2 ? d : -d; };
  const auto q = [&](std::size_t i) { return i % 4 < 2 ? d : -d; };
  // The same error in both: all of it shared.
  auto same = ComputeSharedError(gt, with_error(p, 0.3), with_error(p, -1.2));
  ASSERT_TRUE(same.ok()) << same.status().ToString();
  EXPECT_EQ(same->matched, 400u);
  EXPECT_NEAR(same->rmse_a, d, 1e-4);
  EXPECT_NEAR(same->shared_rmse, d, 1e-4);
  EXPECT_NEAR(same->apart_rmse, 0, 1e-4);
  EXPECT_NEAR(same->correlation, 1, 1e-3);
  // Opposite errors: none shared.
  auto opposite = ComputeSharedError(gt, with_error(p, 0.3),
                                     with_error([&](std::size_t i) { return -p(i); }, 2));
  ASSERT_TRUE(opposite.ok());
  EXPECT_NEAR(opposite->shared_rmse, 0, 1e-4);
  EXPECT_NEAR(opposite->apart_rmse, d, 1e-4);
  EXPECT_NEAR(opposite->correlation, -1, 1e-3);
  // Unrelated errors of the same size: half of each error's energy either way.
  auto unrelated = ComputeSharedError(gt, with_error(p, 0.3), with_error(q, 0.7));
  ASSERT_TRUE(unrelated.ok());
  EXPECT_NEAR(unrelated->shared_rmse, d / std::sqrt(2.0), 1e-4);
  EXPECT_NEAR(unrelated->apart_rmse, d / std::sqrt(2.0), 1e-4);
  EXPECT_NEAR(unrelated->correlation, 0, 1e-2);
  // Only the ground-truth poses both estimates matched count.
  Trajectory part = with_error(p, 0.3);
  part.erase(part.begin() + 100, part.end());
  auto common = ComputeSharedError(gt, part, with_error(p, 0.1));
  ASSERT_TRUE(common.ok());
  EXPECT_EQ(common->matched, 100u);
  Trajectory elsewhere = gt;
  for (auto& pose : elsewhere) pose.timestamp += 1000;
  EXPECT_FALSE(ComputeSharedError(gt, gt, elsewhere).ok());
}

TEST(AteTest, WithoutAlignmentAnOffsetCountsFully) {
  const Trajectory gt = Circle(50);
  Trajectory est = gt;
  for (auto& p : est) p.T_world_cam.translation() += Eigen::Vector3d(0.3, 0.4, 0);
  AteOptions no_align;
  no_align.align = false;
  EXPECT_NEAR(ComputeAte(gt, est, no_align)->error.rmse, 0.5, 1e-12);
  EXPECT_LT(ComputeAte(gt, est)->error.rmse, 1e-9);
}

TEST(AteTest, MatchesByTimestampWithinTolerance) {
  const Trajectory gt = Circle(100);
  Trajectory est(gt.begin() + 10, gt.begin() + 60);  // a part of it
  for (auto& p : est) p.timestamp += 0.004;          // 4 ms late: still matched
  auto ate = ComputeAte(gt, est);
  ASSERT_TRUE(ate.ok());
  EXPECT_EQ(ate->matched, 50u);
  // Now 16.7 ms late: half way between two 30 Hz samples, more than 10 ms from both.
  for (auto& p : est) p.timestamp += 0.0127;
  EXPECT_FALSE(ComputeAte(gt, est).ok());
}

TEST(RpeTest, ConstantExtraStepShowsPerPair) {
  const Trajectory gt = Circle(100);
  Trajectory est = gt;
  // The estimate drifts 1 mm per frame along x: every one-frame pair is off by 1 mm.
  for (std::size_t i = 0; i < est.size(); ++i) est[i].T_world_cam.translation().x() += 0.001 * i;
  auto rpe = ComputeRpe(gt, est);
  ASSERT_TRUE(rpe.ok());
  EXPECT_EQ(rpe->pairs, 99u);
  EXPECT_NEAR(rpe->translation.rmse, 0.001, 1e-9);
  EXPECT_LT(rpe->rotation.max, 1e-6);
}

TEST(StatisticsTest, MedianAndStd) {
  const ErrorStatistics s = ComputeStatistics({1, 2, 3, 4});
  EXPECT_DOUBLE_EQ(s.median, 2.5);
  EXPECT_DOUBLE_EQ(s.mean, 2.5);
  EXPECT_DOUBLE_EQ(s.rmse, std::sqrt(7.5));
  EXPECT_DOUBLE_EQ(s.std, std::sqrt(1.25));
}

// A camera moving on a parabola at uneven frame times leaves the line between its neighbours
// by the parabola's sagitta only; one pose pushed 3 cm aside shows there as 3 cm (plus that
// sagitta) and as about half of it beside it.
TEST(NeighbourDeviationsTest, FindsTheOnePoseThatJumps) {
  Trajectory t;
  const double a = 0.4;  // m/s^2 across the path
  double time = 10.0;
  for (int i = 0; i < 40; ++i) {
    time += (i % 3 == 0) ? 1.0 / 30 : 1.0 / 25;
    Pose p = Pose::Identity();
    p.translation() = Eigen::Vector3d(0.3 * time, 0.5 * a * time * time, 0);
    t.push_back({time, p});
  }
  std::vector<double> smooth = NeighbourDeviations(t);
  ASSERT_EQ(smooth.size(), t.size());
  EXPECT_EQ(smooth.front(), 0);
  EXPECT_EQ(smooth.back(), 0);
  for (std::size_t i = 1; i + 1 < t.size(); ++i) {
    // Sagitta of a parabola over the span: a/2 * (t - t0)(t1 - t), under a millimetre here.
    const double t0 = t[i - 1].timestamp, t1 = t[i + 1].timestamp, ti = t[i].timestamp;
    EXPECT_NEAR(smooth[i], 0.5 * a * (ti - t0) * (t1 - ti), 1e-9) << i;
  }
  t[20].T_world_cam.translation().z() += 0.03;
  const std::vector<double> jumped = NeighbourDeviations(t);
  EXPECT_NEAR(jumped[20], std::hypot(0.03, smooth[20]), 1e-9);
  EXPECT_GT(jumped[19], 0.012);
  EXPECT_LT(jumped[19], 0.018);
  EXPECT_GT(jumped[21], 0.012);
  EXPECT_LT(jumped[21], 0.018);
  EXPECT_NEAR(jumped[10], smooth[10], 1e-12);
}

}  // namespace
}  // namespace ccmd
