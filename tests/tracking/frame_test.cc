// A tracking frame's features: with lens distortion, detected and given depth on the image as
// recorded, then moved to the ideal pinhole camera's pixels, as ORB-SLAM does; each keypoint's
// depth with its standard deviation.

#include "libccmd/tracking/frame.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "libccmd/sensors/synthetic_source.h"
#include "tests/support/test_cameras.h"

namespace ccmd {
namespace {

// The synthetic room's first frame, its grey image and its camera.
struct SyntheticView {
  RgbdFrame frame;
  cv::Mat gray;
  PinholeCamera camera;
};

void FirstSyntheticView(SyntheticView* view) {
  SyntheticSource source(SyntheticSequenceOptions{});
  ASSERT_TRUE(source.Read(&view->frame).ok());
  cv::cvtColor(view->frame.bgr, view->gray, cv::COLOR_BGR2GRAY);
  view->camera = source.camera();
}

TEST(TrackingFrameTest, KeypointsAreUndistortedAfterTheDepthLookupAtTheRecordedPixel) {
  SyntheticView view;
  ASSERT_NO_FATAL_FAILURE(FirstSyntheticView(&view));
  const cv::Mat& gray = view.gray;
  PinholeCamera plain = view.camera;
  PinholeCamera distorted = plain;
  distorted.distortion = testing::TumFr1Camera().distortion;
  const OrbExtractor orb;
  const FrameFeatures raw =
      ComputeFeatures(gray, view.frame.depth_mm, orb, plain, TrackingOptions{});
  const FrameFeatures undistorted =
      ComputeFeatures(gray, view.frame.depth_mm, orb, distorted, TrackingOptions{});
  ASSERT_EQ(raw.keypoints.size(), undistorted.keypoints.size());
  ASSERT_GT(raw.keypoints.size(), 500u);
  double largest_shift = 0;
  for (std::size_t i = 0; i < raw.keypoints.size(); ++i) {
    const cv::Point2f& r = raw.keypoints[i].pt;
    const cv::Point2f& k = undistorted.keypoints[i].pt;
    // The keypoint is the recorded pixel seen through the lens model backwards...
    const Eigen::Vector2d back = distorted.DistortPixel({k.x, k.y});
    EXPECT_NEAR(back.x(), r.x, 1e-3);
    EXPECT_NEAR(back.y(), r.y, 1e-3);
    largest_shift = std::max(largest_shift, std::hypot(double{k.x - r.x}, double{k.y - r.y}));
    // ... its depth is the one at the recorded pixel, and the virtual right coordinate follows
    // the undistorted u.
    EXPECT_EQ(undistorted.depth[i], raw.depth[i]);
    if (raw.depth[i] > 0) {
      EXPECT_NEAR(undistorted.u_right[i], k.x - plain.bf / raw.depth[i], 1e-3);
    }
  }
  EXPECT_GT(largest_shift, 3.0);  // pixels near the corners move
}

// A rolling shutter read over 30 ms while the camera turns at 1 rad/s about its y axis and
// moves 1 m/s along x: each row sees a plane 2 m ahead from where the camera was at its own
// time. Unrolled, every keypoint is where the frame's time (the middle row's) sees its point,
// through each shipped convention (plain, TUM's lens distortion, ICL-NUIM's negative fy).
// Where a keypoint has no depth the rotation alone moves it, which is exact for a turn.
TEST(TrackingFrameTest, UnrolledKeypointsAreWhereTheFramesTimeSeesThem) {
  constexpr double kReadout = 0.03, kTurn = 1.0, kSpeed = 1.0, kPlane = 2.0;
  for (const bool with_depth : {true, false}) {
    const double speed = with_depth ? kSpeed : 0.0;
    // The camera s seconds after the frame's time, in the frame's camera.
    const auto T_frame_cam = [&](double s) {
      Pose T = Pose::Identity();
      T.linear() = Eigen::AngleAxisd(kTurn * s, Eigen::Vector3d::UnitY()).toRotationMatrix();
      T.translation() = Eigen::Vector3d(speed * s, 0, 0);
      return T;
    };
    for (PinholeCamera camera :
         {PinholeCamera{}, testing::TumFr1Camera(), testing::IclNuimCamera()}) {
      camera.width = 640;
      camera.height = 480;
      const cv::Mat depth(480, 640, CV_16UC1, cv::Scalar(with_depth ? kPlane * 1000 : 0));
      RollingShutter shutter;
      shutter.readout = kReadout;
      shutter.interval = 1.0 / 30;
      shutter.velocity = T_frame_cam(-shutter.interval);  // T_cur_prev
      std::vector<cv::KeyPoint> keypoints;
      std::vector<Eigen::Vector2d> truth;
      for (double u = 40; u < 640; u += 80) {
        for (double v = 20; v < 480; v += 55) {
          const Eigen::Vector3d point = camera.BackProject(u, v, kPlane);  // in the frame's camera
          // The pixel the rolling shutter records: its row's time depends on the row itself.
          Eigen::Vector2d seen = camera.ProjectToImage(point);
          for (int k = 0; k < 20; ++k) {
            const double s = kReadout * ((seen.y() + 0.5) / camera.height - 0.5);
            seen = camera.ProjectToImage(T_frame_cam(s).inverse() * point);
          }
          keypoints.emplace_back(static_cast<float>(seen.x()), static_cast<float>(seen.y()), 8);
          truth.push_back(camera.ProjectToImage(point));
        }
      }
      double before = 0, after = 0;
      for (std::size_t i = 0; i < keypoints.size(); ++i) {
        before = std::max(
            before, (truth[i] - Eigen::Vector2d(keypoints[i].pt.x, keypoints[i].pt.y)).norm());
      }
      UnrollKeypoints(depth, camera, shutter, TrackingOptions{}, &keypoints);
      for (std::size_t i = 0; i < keypoints.size(); ++i) {
        after = std::max(after,
                         (truth[i] - Eigen::Vector2d(keypoints[i].pt.x, keypoints[i].pt.y)).norm());
      }
      EXPECT_GT(before, 5.0) << camera.ToString();
      // (the motion model interpolates rotation and translation apart: 0.1 mm at 15 ms)
      EXPECT_LT(after, with_depth ? 0.1 : 0.01) << camera.ToString() << " " << with_depth;
    }
  }
}

// The keypoints made again with a second motion are those of the frame made with the second
// in the first place: from where they were read (not from where the first motion put them),
// with the depths, sigmas and right coordinates of their new positions; through a
// lens-distorted camera too, whose keypoints as read are raw pixels. Both ways the motion
// enters: a rolling shutter's unrolling, and a depth image taken apart from the colour one
// (the depth camera's pose, T_colour_depth). A frame where neither entered keeps no keypoints
// as read and is left as it is.
TEST(TrackingFrameTest, KeypointsMadeAgainAreThoseOfTheFrameMadeWithThatMotion) {
  SyntheticView view;
  ASSERT_NO_FATAL_FAILURE(FirstSyntheticView(&view));
  const auto motion = [](double turn, double speed) {  // T_cur_prev over 1/30 s
    Pose T = Pose::Identity();
    T.linear() = Eigen::AngleAxisd(turn, Eigen::Vector3d(0.2, 1, 0).normalized()).matrix();
    T.translation() = Eigen::Vector3d(speed, 0.3 * speed, 0);
    return T;
  };
  const RollingShutter predicted{0.03, motion(0.01, 0.01), 1.0 / 30};
  const RollingShutter solved{0.03, motion(0.04, 0.04), 1.0 / 30};
  const RollingShutter global_shutter{0, solved.velocity, solved.interval};
  // The depth camera 13 ms after the colour one, by each motion.
  const Pose depth_predicted = MotionOver(predicted.velocity, predicted.interval, 0.013);
  const Pose depth_solved = MotionOver(solved.velocity, solved.interval, 0.013);
  const OrbExtractor orb;
  const TrackingOptions options;
  PinholeCamera distorted = view.camera;
  distorted.distortion = testing::TumFr1Camera().distortion;
  for (const bool rolling : {true, false}) {
    for (const PinholeCamera& camera : {view.camera, distorted}) {
      const std::string what =
          (rolling ? "rolling shutter, " : "depth apart, ") + camera.ToString();
      auto frame = rolling ? MakeFrame(view.frame, orb, camera, options, std::nullopt, &predicted)
                           : MakeFrame(view.frame, orb, camera, options, depth_predicted);
      const auto direct = rolling
                              ? MakeFrame(view.frame, orb, camera, options, std::nullopt, &solved)
                              : MakeFrame(view.frame, orb, camera, options, depth_solved);
      const FrameFeatures first = frame->features;
      ASSERT_EQ(frame->keypoints_as_read.size(), first.keypoints.size()) << what;
      if (!rolling) frame->SetDepthPose(depth_solved);
      MoveKeypointsAgain(frame.get(), rolling ? solved : global_shutter, orb, camera, options);
      const FrameFeatures& f = frame->features;
      ASSERT_EQ(f.keypoints.size(), direct->features.keypoints.size()) << what;
      double moved = 0;
      int depth_changed = 0;
      for (std::size_t i = 0; i < f.keypoints.size(); ++i) {
        EXPECT_EQ(f.keypoints[i].pt, direct->features.keypoints[i].pt) << what << " " << i;
        EXPECT_EQ(f.depth[i], direct->features.depth[i]) << what << " " << i;
        EXPECT_EQ(f.depth_sigma[i], direct->features.depth_sigma[i]) << what << " " << i;
        EXPECT_EQ(f.u_right[i], direct->features.u_right[i]) << what << " " << i;
        moved = std::max(moved, double{cv::norm(f.keypoints[i].pt - first.keypoints[i].pt)});
        depth_changed += f.depth[i] != first.depth[i];
      }
      // The two motions differ by pixels; the depth's time moves no keypoint.
      EXPECT_TRUE(rolling ? moved > 2.0 : moved == 0.0) << what << ": moved " << moved;
      EXPECT_GT(depth_changed, 100) << what;
    }
  }
  auto global = MakeFrame(view.frame, orb, view.camera, options);
  EXPECT_TRUE(global->keypoints_as_read.empty());
  const std::vector<cv::KeyPoint> before = global->features.keypoints;
  MoveKeypointsAgain(global.get(), solved, orb, view.camera, options);
  ASSERT_EQ(global->features.keypoints.size(), before.size());
  for (std::size_t i = 0; i < before.size(); ++i) {
    EXPECT_EQ(global->features.keypoints[i].pt, before[i].pt);
  }
}

// Depth taken apart from its colour image: a frame that moved its depth to the colour image's
// time (to align it) hands that to a keyframe; once the depth camera's pose is estimated anew
// (the keyframe's, from the motion measured up to its own frame), the keyframe gets the depth
// as taken with the new pose, not the one moved with the old.
TEST(TrackingFrameTest, ANewerDepthPoseReplacesTheDepthMovedWithTheOldOne) {
  SyntheticView view;
  ASSERT_NO_FATAL_FAILURE(FirstSyntheticView(&view));
  Pose predicted = Pose::Identity(), measured = Pose::Identity();
  predicted.translation() = Eigen::Vector3d(0.01, 0, 0);
  measured.translation() = Eigen::Vector3d(0.02, 0, 0);
  const OrbExtractor orb;
  const auto frame = MakeFrame(view.frame, orb, view.camera, TrackingOptions{}, predicted);
  const cv::Mat moved = frame->DepthAtColourTime(view.camera).clone();
  EXPECT_GT(cv::norm(moved, view.frame.depth_mm, cv::NORM_L1), 0);
  Keyframe with_moved(KeyframeId(0), 0.0, 0, frame->features, Pose::Identity(), 640, 480);
  frame->HandDepthTo(&with_moved);
  EXPECT_EQ(cv::norm(with_moved.depth_mm, moved, cv::NORM_L1), 0);
  EXPECT_FALSE(with_moved.T_colour_depth.has_value());

  frame->SetDepthPose(measured);
  Keyframe with_new(KeyframeId(1), 0.0, 0, frame->features, Pose::Identity(), 640, 480);
  frame->HandDepthTo(&with_new);
  EXPECT_EQ(cv::norm(with_new.depth_mm, view.frame.depth_mm, cv::NORM_L1), 0);
  ASSERT_TRUE(with_new.T_colour_depth.has_value());
  EXPECT_TRUE(with_new.T_colour_depth->isApprox(measured));
}

// On a slanted surface a keypoint between pixels takes the depth at its own position, not the
// nearest pixel's (which is off by the slope times up to half a pixel: here up to 2 mm).
TEST(TrackingFrameTest, AKeypointBetweenPixelsTakesTheDepthAtItsPosition) {
  SyntheticView view;
  ASSERT_NO_FATAL_FAILURE(FirstSyntheticView(&view));
  const cv::Mat& gray = view.gray;
  cv::Mat ramp(gray.rows, gray.cols, CV_16UC1);  // z = 1000 mm + 3 mm a column + 1 mm a row
  for (int y = 0; y < ramp.rows; ++y) {
    for (int x = 0; x < ramp.cols; ++x) ramp.at<std::uint16_t>(y, x) = 1000 + 3 * x + y;
  }
  const FrameFeatures f =
      ComputeFeatures(gray, ramp, OrbExtractor(), view.camera, TrackingOptions{});
  int with_depth = 0, between = 0;
  for (std::size_t i = 0; i < f.keypoints.size(); ++i) {
    if (f.depth[i] <= 0) continue;
    const cv::Point2f& p = f.keypoints[i].pt;
    EXPECT_NEAR(f.depth[i], 1e-3 * (1000 + 3 * p.x + p.y), 1e-5) << p;
    ++with_depth;
    between += std::abs(p.x - std::round(p.x)) > 0.2f;
  }
  EXPECT_GT(with_depth, 500);
  EXPECT_GT(between, 100);
}

// A noisy sensor (a D435's sigma at 2 m: 18 mm, independent per pixel) keeps its keypoints'
// depth on a smooth surface: a 5x5 neighbourhood of such depths spans about 70 mm, past the
// fixed 7 cm a slanted surface may span at 2 m, which used to take the depth of half of them.
// A depth edge still takes it, however noisy the sensor is said to be.
TEST(TrackingFrameTest, ANoisySensorKeepsItsKeypointDepthsAndEdgesStillLoseTheirs) {
  SyntheticView view;
  ASSERT_NO_FATAL_FAILURE(FirstSyntheticView(&view));
  TrackingOptions options;
  options.depth_noise.sigma_0 = 0.002;
  options.depth_noise.sigma_2 = 0.004;
  const double sigma_mm = 1e3 * options.depth_noise.Sigma(2.0);
  cv::Mat depth(view.gray.rows, view.gray.cols, CV_16UC1);
  cv::RNG rng(7);
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) {
      depth.at<std::uint16_t>(y, x) =
          static_cast<std::uint16_t>(std::lround(2000 + rng.gaussian(sigma_mm)));
    }
  }
  const OrbExtractor orb;
  const FrameFeatures noisy = ComputeFeatures(view.gray, depth, orb, view.camera, options);
  std::size_t inside = 0, with_depth = 0;
  for (std::size_t i = 0; i < noisy.keypoints.size(); ++i) {
    const cv::Point2f& p = noisy.keypoints[i].pt;
    if (p.x < 3 || p.y < 3 || p.x > depth.cols - 4 || p.y > depth.rows - 4) continue;
    ++inside;
    with_depth += noisy.depth[i] > 0;
  }
  ASSERT_GT(inside, 500u);
  EXPECT_GT(with_depth, inside * 97 / 100);

  // Left of column 320 at 1.5 m, right of it at 2.5 m: a 1 m step, far beyond 6 sigma.
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) depth.at<std::uint16_t>(y, x) = x < 320 ? 1500 : 2500;
  }
  const FrameFeatures edge = ComputeFeatures(view.gray, depth, orb, view.camera, options);
  int near_edge = 0;
  for (std::size_t i = 0; i < edge.keypoints.size(); ++i) {
    const int x = static_cast<int>(std::lround(edge.keypoints[i].pt.x));
    if (x < 318 || x > 321) continue;
    ++near_edge;
    EXPECT_EQ(edge.depth[i], 0.0f) << edge.keypoints[i].pt;
  }
  EXPECT_GT(near_edge, 3);
}

// A depth image (uint16 mm) of z = z0 + slope_x * x + slope_y * y (mm per pixel).
cv::Mat DepthRamp(double z0_mm, double slope_x, double slope_y) {
  cv::Mat depth(60, 80, CV_16UC1);
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) {
      depth.at<std::uint16_t>(y, x) =
          static_cast<std::uint16_t>(std::lround(z0_mm + slope_x * x + slope_y * y));
    }
  }
  return depth;
}

TEST(KeypointDepthSigmaTest, FacingPlaneGivesTheSensorNoise) {
  DepthNoise noise;
  noise.sigma_0 = 0.002;
  noise.sigma_2 = 0.003;
  const cv::Mat depth = DepthRamp(2000, 0, 0);
  // 2 mm + 3 mm * 4 = 14 mm, however uncertain the keypoint's position.
  EXPECT_NEAR(KeypointDepthSigma(depth, 40, 30, 2.0, 1.0, noise), 0.014, 1e-9);
  EXPECT_NEAR(KeypointDepthSigma(depth, 40, 30, 2.0, 4.0, noise), 0.014, 1e-9);
}

TEST(KeypointDepthSigmaTest, SlopeTimesPositionUncertaintyAddsInQuadrature) {
  DepthNoise noise;
  noise.sigma_0 = 0.001;
  noise.sigma_2 = 0.0;
  // Depth rises 3 mm per pixel to the right and 4 mm per pixel downwards: 5 mm per pixel
  // along the gradient. A keypoint uncertain by 2 pixels reads depth uncertain by 10 mm.
  const cv::Mat depth = DepthRamp(1500, 3, 4);
  const double z = 1e-3 * depth.at<std::uint16_t>(30, 40);
  EXPECT_NEAR(KeypointDepthSigma(depth, 40, 30, z, 2.0, noise),
              std::sqrt(0.001 * 0.001 + 0.010 * 0.010), 1e-9);
  // The finer the keypoint's octave, the less its depth is in doubt.
  EXPECT_LT(KeypointDepthSigma(depth, 40, 30, z, 1.0, noise),
            KeypointDepthSigma(depth, 40, 30, z, 2.0, noise));
}

TEST(KeypointDepthSigmaTest, DepthInformationIsOneOverVariance) {
  FrameFeatures f;
  f.depth = {0.0f, 2.0f};
  f.depth_sigma = {0.0f, 0.01f};
  EXPECT_EQ(f.DepthInformation(0), 0.0);  // no depth: no information
  EXPECT_NEAR(f.DepthInformation(1), 1e4, 1e-3 * 1e4);
}

}  // namespace
}  // namespace ccmd
