// Dense depth alignment on depth images ray-cast from planes with exact poses.

#include "libccmd/tracking/depth_alignment.h"
#include "libccmd/tracking/depth_consistency.h"

#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

struct Plane {
  Eigen::Vector3d n;  // world normal
  double k;           // n . x = k
};

PinholeCamera Vga() {
  PinholeCamera c;
  c.fx = c.fy = 525;
  c.cx = 319.5;
  c.cy = 239.5;
  return c;
}

// Depth (mm) seen from T_world_cam: the nearest plane along each pixel's ray, plus noise.
cv::Mat RenderDepth(const std::vector<Plane>& planes, const Pose& T_world_cam, double noise_m,
                    Rng* rng) {
  const PinholeCamera cam = Vga();
  cv::Mat depth(cam.height, cam.width, CV_16UC1, cv::Scalar(0));
  const Eigen::Vector3d c = T_world_cam.translation();
  for (int v = 0; v < cam.height; ++v) {
    for (int u = 0; u < cam.width; ++u) {
      const Eigen::Vector3d ray =
          T_world_cam.linear() * Eigen::Vector3d((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1);
      double best = 1e9;
      for (const Plane& p : planes) {
        const double denom = p.n.dot(ray);
        if (std::abs(denom) < 1e-9) continue;
        const double t = (p.k - p.n.dot(c)) / denom;  // ray z = 1, so t is the depth
        if (t > 0.2 && t < best) best = t;
      }
      if (best < 8)
        depth.at<std::uint16_t>(v, u) =
            static_cast<std::uint16_t>(std::lround(1000 * (best + noise_m * rng->Normal())));
    }
  }
  return depth;
}

// A room corner: floor, back wall and a side wall (camera y points down, z forward).
const std::vector<Plane> kCorner = {{{0, 1, 0}, 1.0}, {{0, 0, 1}, 3.0}, {{1, 0, 0}, 1.2}};

Pose Motion(const Eigen::Vector3d& omega, const Eigen::Vector3d& t) {
  Pose T = Pose::Identity();
  T.linear() = RotationFromAngleAxis(omega);
  T.translation() = t;
  return T;
}

DepthModel Model(const cv::Mat& depth) { return DepthModel::FromDepth(depth, Vga(), 4, 0.1, 10.0); }

TEST(DepthAlignmentTest, RecoversTheRelativePoseOfTwoViews) {
  Rng rng(41);
  const Pose T_world_a = Motion({0.0, 0.2, 0.0}, {0, 0, 0});
  const Pose T_world_b = T_world_a * Motion({0.03, -0.05, 0.02}, {0.04, -0.02, 0.05});
  const DepthModel a = Model(RenderDepth(kCorner, T_world_a, 0, &rng));
  const DepthModel b = Model(RenderDepth(kCorner, T_world_b, 0, &rng));
  ASSERT_GT(a.valid_points(), 5000);
  const Pose truth = T_world_b.inverse() * T_world_a;  // T_b_a
  const Pose guess =
      Motion({0.01, -0.015, 0.01}, {0.02, 0.015, -0.02}) * truth;  // ~3 cm, ~1 degree off
  const auto aligned = AlignDepth(a, b, guess, DepthNoise());
  ASSERT_TRUE(aligned.has_value());
  EXPECT_LT(TranslationDistance(aligned->T_target_source, truth), 0.001);
  EXPECT_LT(RotationDistance(aligned->T_target_source, truth), 0.05 * M_PI / 180);
  EXPECT_GT(aligned->inliers, 1000);
  // Three planes constrain all six directions.
  const Eigen::SelfAdjointEigenSolver<Matrix6d> eigen(aligned->information);
  EXPECT_GT(eigen.eigenvalues()(0), 1e-3 * eigen.eigenvalues()(5));
  EXPECT_GT(Conditioning(*aligned), kMinConditioningAlone);
  EXPECT_NEAR(aligned->mean_range, 2.5, 1.0);  // the corner's surfaces are 1-3.6 m away
}

// A depth image taken 2 cm and 1 degree away from the colour camera (a depth camera a few
// milliseconds late on a moving rig), its model moved rigidly into the colour camera's frame:
// aligned with another view, as the source and as the target, it gives the colour camera's
// pose, not the depth camera's, without the image being resampled.
TEST(DepthAlignmentTest, AModelMovedToAnotherCameraAlignsAsThatCamera) {
  Rng rng(43);
  const Pose T_world_colour = Motion({0.0, 0.2, 0.0}, {0, 0, 0});
  const Pose T_colour_depth = Motion({0.0, 0.017, 0.005}, {0.02, 0.004, 0.003});
  const Pose T_world_b = T_world_colour * Motion({0.03, -0.05, 0.02}, {0.04, -0.02, 0.05});
  const DepthModel taken = Model(RenderDepth(kCorner, T_world_colour * T_colour_depth, 0, &rng));
  const DepthModel colour = taken.Moved(T_colour_depth);
  const DepthModel b = Model(RenderDepth(kCorner, T_world_b, 0, &rng));
  ASSERT_GT(colour.valid_points(), 5000);
  const Pose T_b_colour = T_world_b.inverse() * T_world_colour;
  const auto as_source = AlignDepth(colour, b, T_b_colour, DepthNoise());
  const auto as_target = AlignDepth(b, colour, T_b_colour.inverse(), DepthNoise());
  ASSERT_TRUE(as_source.has_value());
  ASSERT_TRUE(as_target.has_value());
  EXPECT_LT(TranslationDistance(as_source->T_target_source, T_b_colour), 0.001);
  EXPECT_LT(RotationDistance(as_source->T_target_source, T_b_colour), 0.05 * M_PI / 180);
  EXPECT_LT(TranslationDistance(as_target->T_target_source, T_b_colour.inverse()), 0.001);
  EXPECT_LT(RotationDistance(as_target->T_target_source, T_b_colour.inverse()), 0.05 * M_PI / 180);
  // Each vertex is where the colour camera sees it, in the cell the depth camera measured.
  int checked = 0;
  for (int y = 0; y < taken.height(); y += 7) {
    for (int x = 0; x < taken.width(); x += 7) {
      if (taken.vertex(x, y).z() == 0) continue;
      const Eigen::Vector3d v = colour.vertex(x, y).cast<double>();
      EXPECT_LT((v - T_colour_depth * taken.vertex(x, y).cast<double>()).norm(), 1e-5);
      const auto cell = colour.Cell(v);
      ASSERT_TRUE(cell.has_value());
      EXPECT_EQ(*cell, std::make_pair(x, y));
      ++checked;
    }
  }
  EXPECT_GT(checked, 200);
}

TEST(DepthAlignmentTest, NoisyDepthStillAlignsWithinMillimetres) {
  Rng rng(42);
  const Pose T_world_a = Motion({0.0, 0.2, 0.0}, {0, 0, 0});
  const Pose T_world_b = T_world_a * Motion({-0.02, 0.04, 0.01}, {-0.03, 0.01, 0.06});
  const DepthModel a = Model(RenderDepth(kCorner, T_world_a, 0.004, &rng));
  const DepthModel b = Model(RenderDepth(kCorner, T_world_b, 0.004, &rng));
  const Pose truth = T_world_b.inverse() * T_world_a;
  const auto aligned =
      AlignDepth(a, b, Motion({0.01, 0, -0.01}, {0.01, -0.01, 0.01}) * truth, DepthNoise());
  ASSERT_TRUE(aligned.has_value());
  EXPECT_LT(TranslationDistance(aligned->T_target_source, truth), 0.003);
  EXPECT_LT(RotationDistance(aligned->T_target_source, truth), 0.2 * M_PI / 180);
}

// A single wall fixes depth and two tilts only: the information says so, and the free
// directions (sliding along the wall, turning about its normal) keep the guess.
TEST(DepthAlignmentTest, APlaneLeavesThreeDirectionsWithoutInformation) {
  Rng rng(43);
  const std::vector<Plane> wall = {{{0, 0, 1}, 2.0}};
  const Pose T_world_a = Pose::Identity();
  const Pose T_world_b = Motion({0, 0, 0}, {0, 0, 0.1});
  const DepthModel a = Model(RenderDepth(wall, T_world_a, 0, &rng));
  const DepthModel b = Model(RenderDepth(wall, T_world_b, 0, &rng));
  const Pose truth = T_world_b.inverse() * T_world_a;
  const Pose guess =
      Motion({0, 0, 0}, {0.02, 0, 0.03}) * truth;  // 2 cm along the wall, 3 cm in depth
  const auto aligned = AlignDepth(a, b, guess, DepthNoise());
  ASSERT_TRUE(aligned.has_value());
  EXPECT_NEAR(aligned->T_target_source.translation().z(), truth.translation().z(),
              0.001);  // depth fixed
  EXPECT_NEAR(aligned->T_target_source.translation().x(), guess.translation().x(),
              0.001);  // slide kept
  const Eigen::SelfAdjointEigenSolver<Matrix6d> eigen(aligned->information);
  const auto& e = eigen.eigenvalues();  // ascending
  EXPECT_LT(e(2), 1e-6 * e(5));
  EXPECT_GT(e(3), 1e-4 * e(5));
  EXPECT_LT(Conditioning(*aligned), 1e-6);
}

// The same wall with a strip of floor along its foot: the slide along both stays free.
TEST(DepthAlignmentTest, AWallAndFloorLeaveTheSlideAlongThemFree) {
  Rng rng(45);
  const std::vector<Plane> wall_and_floor = {{{0, 0, 1}, 2.0}, {{0, 1, 0}, 1.0}};
  const Pose T_world_b = Motion({0, 0, 0}, {0, 0, 0.05});
  const DepthModel a = Model(RenderDepth(wall_and_floor, Pose::Identity(), 0, &rng));
  const DepthModel b = Model(RenderDepth(wall_and_floor, T_world_b, 0, &rng));
  const auto aligned = AlignDepth(a, b, T_world_b.inverse(), DepthNoise());
  ASSERT_TRUE(aligned.has_value());
  EXPECT_LT(Conditioning(*aligned), 1e-6);
}

TEST(DepthAlignmentTest, RefusesViewsThatDoNotOverlap) {
  Rng rng(44);
  const DepthModel a = Model(RenderDepth(kCorner, Pose::Identity(), 0, &rng));
  const DepthModel b = Model(RenderDepth(kCorner, Motion({0, 0.2, 0}, {0, 0, 0}), 0, &rng));
  // A guess that puts the source 2 m to the side: nothing projects into the target.
  EXPECT_FALSE(AlignDepth(a, b, Motion({0, 0, 0}, {3.0, 0, 0}), DepthNoise()).has_value());
  // No depth at all.
  const DepthModel empty = Model(cv::Mat(480, 640, CV_16UC1, cv::Scalar(0)));
  EXPECT_TRUE(empty.empty());
  EXPECT_FALSE(AlignDepth(empty, b, Pose::Identity(), DepthNoise()).has_value());
}

// A point is looked up in the cell whose block holds the pixel it falls in (pixel centres are
// whole numbers): a cell of step 4 holds pixels 4..7, whose area spans 3.5 to 7.5.
TEST(DepthAlignmentTest, APointFallsInTheCellOfItsPixel) {
  const PinholeCamera cam = Vga();
  const DepthModel m =
      DepthModel::FromDepth(cv::Mat(480, 640, CV_16UC1, cv::Scalar(2000)), cam, 4, 0.3, 5.0);
  const auto at = [&](double u, double v) {
    return m.Cell(Eigen::Vector3d((u - cam.cx) / cam.fx * 2, (v - cam.cy) / cam.fy * 2, 2));
  };
  using C = std::pair<int, int>;
  EXPECT_EQ(at(3.6, 7.6), C(1, 2));
  EXPECT_EQ(at(7.4, 11.4), C(1, 2));
  EXPECT_EQ(at(3.4, 7.4), C(0, 1));
  EXPECT_EQ(at(-0.4, -0.4), C(0, 0));
  EXPECT_FALSE(at(-0.6, 10).has_value());
  EXPECT_EQ(at(639.4, 479.4), C(159, 119));
  EXPECT_FALSE(at(639.6, 10).has_value());
}

// A camera sliding past the room corner while it turns: the depth of frames 10 apart agrees
// with the true motion, and a trajectory that turns 0.1 degree a frame too far is found out by
// the depth alone, 1 degree per pair. A frame the trajectory has no pose for is not paired.
TEST(DepthConsistencyTest, TheDepthAloneFindsATrajectoryThatTurnsTooFar) {
  Rng rng(43);
  std::vector<RgbdFrame> frames;
  Trajectory truth, turned;
  constexpr double kDrift = 0.1 * M_PI / 180;  // per frame
  for (int k = 0; k < 40; ++k) {
    const Pose T_world_cam = Motion({0.0, 0.15 + 0.004 * k, 0.01}, {-0.2 + 0.01 * k, 0, 0.005 * k});
    RgbdFrame frame;
    frame.index = k;
    frame.timestamp = k / 30.0;
    frame.depth_mm = RenderDepth(kCorner, T_world_cam, 0.001, &rng);
    frames.push_back(frame);
    if (k == 21) continue;  // no pose
    truth.push_back({frame.timestamp, T_world_cam});
    turned.push_back({frame.timestamp, T_world_cam * Motion({0, kDrift * k, 0}, {0, 0, 0})});
  }
  DepthConsistencyOptions options;  // frames 10 apart, a pair every 3rd frame: 10 pairs
  const auto exact = MeasureDepthConsistency(frames, truth, Vga(), options);
  ASSERT_TRUE(exact.has_value());
  EXPECT_EQ(exact->pairs, 9);
  EXPECT_EQ(exact->failed, 1);  // frames 21 and 31
  EXPECT_LT(exact->translation_median_m, 0.001);
  EXPECT_LT(exact->rotation_median_rad, 0.05 * M_PI / 180);

  const auto off = MeasureDepthConsistency(frames, turned, Vga(), options);
  ASSERT_TRUE(off.has_value());
  EXPECT_NEAR(off->rotation_median_rad, 10 * kDrift, 0.15 * 10 * kDrift);
  EXPECT_NEAR(off->rotation_mean_rad, 10 * kDrift, 0.15 * 10 * kDrift);
  // The camera turned about its own centre: the depth's correction is that turn, not a shift.
  EXPECT_LT(off->translation_median_m, 0.003);
}

}  // namespace
}  // namespace ccmd
