#include "libccmd/sensors/depth_registration.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

PinholeCamera Camera(double f, int width = 64, int height = 48) {
  PinholeCamera c;
  c.width = width;
  c.height = height;
  c.fx = c.fy = f;
  c.cx = width / 2.0 - 0.5;
  c.cy = height / 2.0 - 0.5;
  return c;
}

Pose Shift(double tx) {
  Pose T = Pose::Identity();
  T.translation() = Eigen::Vector3d(tx, 0, 0);
  return T;
}

TEST(DepthRegistrationTest, SameCameraIsTheIdentity) {
  cv::Mat depth(48, 64, CV_16UC1);
  cv::randu(depth, 0, 5000);
  const cv::Mat out = RegisterDepthToColor(depth, Camera(50), Camera(50), Pose::Identity());
  EXPECT_EQ(cv::norm(out, depth, cv::NORM_INF), 0);
}

TEST(DepthRegistrationTest, NarrowerColourViewOfAPlaneHasNoCracks) {
  // Depth: wide lens (f = 40 px), colour: narrower (f = 52 px, magnification 1.3), 15 mm to
  // the side. A fronto-parallel plane at 2 m stays at 2 m in the colour frame (the shift is
  // sideways), and the colour view lies inside the depth view, so every colour pixel must
  // get 2000 mm; mapping only pixel centres would leave every third or fourth column empty.
  const cv::Mat plane(48, 64, CV_16UC1, cv::Scalar(2000));
  const cv::Mat out = RegisterDepthToColor(plane, Camera(40), Camera(52), Shift(0.015));
  EXPECT_EQ(cv::countNonZero(out == 2000), 64 * 48);
}

TEST(DepthRegistrationTest, PointsLandWhereTheGeometrySaysAndTheNearestWins) {
  // Background at 3 m; a 4x4 block at 1 m around depth pixel (32, 24); colour 5 cm to the
  // side (+x in the depth frame), same lens.
  cv::Mat depth(48, 64, CV_16UC1, cv::Scalar(3000));
  depth(cv::Rect(30, 22, 4, 4)).setTo(cv::Scalar(1000));
  const PinholeCamera cam = Camera(40);
  const cv::Mat out = RegisterDepthToColor(depth, cam, cam, Shift(0.05));
  // Depth pixel u maps to u + f * tx / z: +2 px at 1 m, +2/3 px at 3 m.
  // Block columns 30..33 -> centres 32..35; the background next to it shifts by less, so
  // the block covers background there and must win.
  for (int u = 32; u <= 35; ++u) EXPECT_EQ(out.at<std::uint16_t>(24, u), 1000) << u;
  EXPECT_EQ(out.at<std::uint16_t>(24, 36), 3000);
  EXPECT_EQ(out.at<std::uint16_t>(24, 10), 3000);
  EXPECT_EQ(out.at<std::uint16_t>(5, 31), 3000);
  // The left edge: colour column 0 sees x = (0 - 31.5) / 40 * z - ... beyond the depth view
  // for the 3 m background shifted right by 2/3 px, so it stays empty.
  EXPECT_EQ(out.at<std::uint16_t>(24, 0), 0);
}

TEST(DepthRegistrationTest, HolesStayHoles) {
  cv::Mat depth(48, 64, CV_16UC1, cv::Scalar(2000));
  depth(cv::Rect(10, 10, 6, 6)).setTo(cv::Scalar(0));
  const cv::Mat out = RegisterDepthToColor(depth, Camera(40), Camera(40), Pose::Identity());
  EXPECT_EQ(out.at<std::uint16_t>(12, 12), 0);
  EXPECT_EQ(cv::countNonZero(out == 0), 36);
}

TEST(DepthRegistrationTest, CalibrationFromTheCameraConfig) {
  testing::TempDir dir;
  const std::string path = dir.File("d435.yaml");
  ASSERT_TRUE(
      WriteFileAtomic(path,
                      "%YAML:1.0\n"
                      "Camera.fx: 615.0\nCamera.fy: 615.0\nCamera.cx: 320.0\nCamera.cy: 240.0\n"
                      "Depth.fx: 383.5\nDepth.fy: 383.0\nDepth.cx: 319.0\nDepth.cy: 241.0\n"
                      "Depth.width: 640\nDepth.height: 480\n"
                      "Depth.R_color_depth: [0.99999, 0.0044, 0.0, -0.0044, 0.99999, 0.0, "
                      "0.0, 0.0, 1.0]\n"
                      "Depth.t_color_depth: [0.0147, 0.0002, 0.0003]\n")
          .ok());
  auto calibration = LoadDepthToColorCalibration(path);
  ASSERT_TRUE(calibration.ok()) << calibration.status().ToString();
  ASSERT_TRUE(calibration->has_value());
  const DepthToColorCalibration& c = **calibration;
  EXPECT_EQ(c.depth.fx, 383.5);
  EXPECT_EQ(c.depth.cy, 241.0);
  EXPECT_EQ(c.depth.width, 640);
  EXPECT_NEAR(c.T_color_depth.translation().x(), 0.0147, 1e-12);
  EXPECT_NEAR(c.T_color_depth.linear()(0, 1), 0.0044, 1e-4);  // row-major as written
  EXPECT_NEAR(c.T_color_depth.linear()(1, 0), -0.0044, 1e-4);

  const std::string plain = dir.File("plain.yaml");
  ASSERT_TRUE(WriteFileAtomic(plain, "%YAML:1.0\nCamera.fx: 615.0\n").ok());
  auto none = LoadDepthToColorCalibration(plain);
  ASSERT_TRUE(none.ok());
  EXPECT_FALSE(none->has_value());

  const std::string bad = dir.File("bad.yaml");
  ASSERT_TRUE(WriteFileAtomic(bad,
                              "%YAML:1.0\nDepth.fx: 383.5\nDepth.fy: 383.0\nDepth.cx: 319.0\n"
                              "Depth.cy: 241.0\nDepth.width: 640\nDepth.height: 480\n"
                              "Depth.R_color_depth: [1, 2, 3, 4, 5, 6, 7, 8, 9]\n")
                  .ok());
  EXPECT_EQ(LoadDepthToColorCalibration(bad).status().code(), StatusCode::kInvalidArgument);
  const std::string millimetres = dir.File("mm.yaml");
  ASSERT_TRUE(WriteFileAtomic(millimetres,
                              "%YAML:1.0\nDepth.fx: 383.5\nDepth.fy: 383.0\nDepth.cx: 319.0\n"
                              "Depth.cy: 241.0\nDepth.width: 640\nDepth.height: 480\n"
                              "Depth.t_color_depth: [14.7, 0.2, 0.3]\n")
                  .ok());
  EXPECT_EQ(LoadDepthToColorCalibration(millimetres).status().code(), StatusCode::kInvalidArgument);
}

// The registration as first written: every depth pixel alone, in double precision, with the
// library's rounding. The vectorised single-precision version must agree with it.
cv::Mat ReferenceRegistration(const cv::Mat& depth_mm, const PinholeCamera& depth_camera,
                              const PinholeCamera& color_camera, const Pose& T_color_depth,
                              int max_footprint = 8) {
  cv::Mat out(color_camera.height, color_camera.width, CV_16UC1, cv::Scalar(0));
  const auto project = [&](const Eigen::Vector3d& p) { return color_camera.ProjectToImage(p); };
  const auto clamped = [](double x) { return std::clamp(x, -1e9, 1e9); };
  for (int v = 0; v < depth_mm.rows; ++v) {
    for (int u = 0; u < depth_mm.cols; ++u) {
      const int d = depth_mm.at<std::uint16_t>(v, u);
      if (d == 0) continue;
      const double z = d * 1e-3;
      const auto point = [&](double du, double dv) {
        return T_color_depth * Eigen::Vector3d(z * (u + du - depth_camera.cx) / depth_camera.fx,
                                               z * (v + dv - depth_camera.cy) / depth_camera.fy, z);
      };
      const Eigen::Vector3d a = point(-0.5, -0.5), b = point(0.5, 0.5), c = point(0, 0);
      if (a.z() <= 1e-6 || b.z() <= 1e-6 || c.z() <= 1e-6) continue;
      const Eigen::Vector2d pa = project(a), pb = project(b), pc = project(c);
      int x0 = static_cast<int>(std::ceil(clamped(std::min(pa.x(), pb.x()))));
      int x1 = static_cast<int>(std::floor(clamped(std::max(pa.x(), pb.x()))));
      int y0 = static_cast<int>(std::ceil(clamped(std::min(pa.y(), pb.y()))));
      int y1 = static_cast<int>(std::floor(clamped(std::max(pa.y(), pb.y()))));
      if (x1 < x0) x0 = x1 = static_cast<int>(std::lround(clamped(pc.x())));
      if (y1 < y0) y0 = y1 = static_cast<int>(std::lround(clamped(pc.y())));
      if (x1 - x0 >= max_footprint || y1 - y0 >= max_footprint) continue;
      const double z_mm = c.z() * 1e3;
      if (z_mm < 0.5 || z_mm >= 65535.5) continue;
      const auto value = static_cast<std::uint16_t>(std::lround(z_mm));
      for (int y = std::max(y0, 0); y <= std::min(y1, out.rows - 1); ++y) {
        for (int x = std::max(x0, 0); x <= std::min(x1, out.cols - 1); ++x) {
          std::uint16_t& target = out.at<std::uint16_t>(y, x);
          if (target == 0 || value < target) target = value;
        }
      }
    }
  }
  return out;
}

// A tilted wall with boxes in front of it (depth edges), some very close, sensor-like noise and
// holes.
cv::Mat ClutteredDepth(int width, int height, unsigned seed) {
  cv::RNG rng(seed);
  cv::Mat depth(height, width, CV_16UC1);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) depth.at<std::uint16_t>(y, x) = 1500 + 2 * x + 1.5 * y;
  }
  for (int i = 0; i < 40; ++i) {
    const int w = rng.uniform(10, 120), h = rng.uniform(10, 120);
    const cv::Rect box(rng.uniform(0, width - w), rng.uniform(0, height - h), w, h);
    depth(box).setTo(i < 4 ? rng.uniform(150, 400) : rng.uniform(500, 4000));
  }
  cv::Mat noise(height, width, CV_16SC1);
  rng.fill(noise, cv::RNG::UNIFORM, -4, 5);
  cv::add(depth, noise, depth, cv::noArray(), CV_16UC1);
  for (int i = 0; i < width * height / 50; ++i)
    depth.at<std::uint16_t>(rng.uniform(0, height), rng.uniform(0, width)) = 0;
  return depth;
}

TEST(DepthRegistrationTest, AgreesWithTheDoublePrecisionDefinitionPixelForPixel) {
  // Three rigs: a Kinect v1 as 7-Scenes has it (wide depth lens into a narrower colour image,
  // footprints under a pixel), a D435 (colour magnifies the depth 1.6 times, the two turned
  // by a fraction of a degree), and the same with a distorted colour lens.
  const auto camera = [](double f) {
    PinholeCamera c = Camera(f, 640, 480);
    c.cx = 319.5;
    c.cy = 239.5;
    return c;
  };
  Pose kinect = Shift(-0.025);
  Pose d435 = Shift(0.0147);
  d435.translation().y() = 0.0002;
  d435.translation().z() = 0.0003;
  d435.linear() = (Eigen::AngleAxisd(0.004, Eigen::Vector3d::UnitZ()) *
                   Eigen::AngleAxisd(-0.003, Eigen::Vector3d::UnitY()) *
                   Eigen::AngleAxisd(0.002, Eigen::Vector3d::UnitX()))
                      .toRotationMatrix();
  PinholeCamera distorted = camera(615);
  distorted.distortion = {0.08, -0.15, 0.001, -0.0005, 0.02};
  struct Rig {
    PinholeCamera depth, color;
    Pose T_color_depth;
  };
  for (const Rig& rig :
       {Rig{camera(585), camera(525), kinect}, Rig{camera(383.5), camera(615), d435},
        Rig{camera(383.5), distorted, d435}}) {
    for (unsigned seed : {1u, 2u}) {
      const cv::Mat depth = ClutteredDepth(640, 480, seed);
      const cv::Mat ours = RegisterDepthToColor(depth, rig.depth, rig.color, rig.T_color_depth);
      const cv::Mat reference =
          ReferenceRegistration(depth, rig.depth, rig.color, rig.T_color_depth);
      const int covered = cv::countNonZero(reference);
      ASSERT_GT(covered, 640 * 480 / 2);
      // Single precision moves a projected corner by about 1e-4 pixel, so a footprint border
      // that falls that close to a pixel centre may take or leave that pixel: a few tens of
      // pixels in a frame (11 and 76 at most over these rigs when written), never a pattern.
      const int differ = 640 * 480 - cv::countNonZero(ours == reference);
      const int only_one = cv::countNonZero((ours == 0) != (reference == 0));
      EXPECT_LT(differ, covered / 1000) << "seed " << seed << ", colour f " << rig.color.fx;
      EXPECT_LT(only_one, covered / 5000) << "seed " << seed << ", colour f " << rig.color.fx;
    }
  }
}

// A bright box in front of a dark wall: the score is highest when the box's depth outline lies
// on its colour outline, and falls as the depth moves sideways (as a wrong offset moves it).
TEST(DepthRegistrationTest, EdgeAlignmentScorePeaksWhenDepthEdgesMeetColourEdges) {
  cv::Mat bgr(240, 320, CV_8UC3, cv::Scalar(40, 40, 40));
  bgr(cv::Rect(100, 60, 120, 100)).setTo(cv::Scalar(200, 200, 200));
  const auto depth_with_box_at = [](int x) {
    cv::Mat depth(240, 320, CV_16UC1, cv::Scalar(2000));
    depth(cv::Rect(x, 60, 120, 100)).setTo(1000);
    return depth;
  };
  const double aligned = EdgeAlignmentScore(bgr, depth_with_box_at(100));
  const double off_by_3 = EdgeAlignmentScore(bgr, depth_with_box_at(103));
  const double off_by_8 = EdgeAlignmentScore(bgr, depth_with_box_at(108));
  EXPECT_GT(aligned, 1.5 * off_by_3);
  EXPECT_GT(off_by_3, off_by_8);
  // No depth edge, or images that do not match: nothing to score.
  EXPECT_EQ(EdgeAlignmentScore(bgr, cv::Mat(240, 320, CV_16UC1, cv::Scalar(1500))), 0);
  EXPECT_EQ(EdgeAlignmentScore(bgr, cv::Mat(120, 160, CV_16UC1, cv::Scalar(1500))), 0);
}

// Depth (mm) of a scene seen from `T_world_cam`: a wall at 1.5 m turned 40 degrees about the
// vertical, and in front of it a square board at 0.8 m, 0.4 m wide.
cv::Mat SceneDepth(const PinholeCamera& camera, const Pose& T_world_cam) {
  const Eigen::Vector3d wall_normal(std::sin(0.7), 0, -std::cos(0.7));  // n . X = -1.5 cos
  const double wall_offset = wall_normal.dot(Eigen::Vector3d(0, 0, 1.5));
  cv::Mat depth(camera.height, camera.width, CV_16UC1, cv::Scalar(0));
  const Eigen::Vector3d centre = T_world_cam.translation();
  for (int v = 0; v < camera.height; ++v) {
    for (int u = 0; u < camera.width; ++u) {
      const Eigen::Vector3d ray_cam((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1);
      const Eigen::Vector3d ray = T_world_cam.linear() * ray_cam;  // z = 1 in the camera
      double z = (wall_offset - wall_normal.dot(centre)) / wall_normal.dot(ray);
      const double s = (0.8 - centre.z()) / ray.z();
      const Eigen::Vector3d on_board = centre + s * ray;
      if (std::abs(on_board.x()) < 0.2 && std::abs(on_board.y()) < 0.2 && s > 0) z = std::min(z, s);
      depth.at<std::uint16_t>(v, u) = static_cast<std::uint16_t>(std::lround(z * 1e3));
    }
  }
  return depth;
}

// A camera's depth seen a few milliseconds later (turned 1 degree, moved 1 cm): moved back to the
// first pose it is that pose's depth, to the sensor's millimetre, everywhere but at the board's
// edges (which the motion uncovers or hides) and where the view leaves the image. The depth as
// taken is centimetres off there.
TEST(DepthRegistrationTest, DepthFromANearbyPoseIsTheDepthSeenFromHere) {
  const PinholeCamera camera = Camera(150, 160, 120);
  const Pose T_world_here = Pose::Identity();
  Pose T_world_there = Pose::Identity();
  T_world_there.linear() =
      RotationFromAngleAxis(0.0175 * Eigen::Vector3d(0.3, 1.0, 0.0).normalized());
  T_world_there.translation() = Eigen::Vector3d(0.008, -0.003, 0.005);
  const cv::Mat here = SceneDepth(camera, T_world_here);
  const cv::Mat there = SceneDepth(camera, T_world_there);
  const Pose T_there_here = T_world_there.inverse() * T_world_here;
  EXPECT_EQ(cv::norm(DepthFromNearbyPose(here, camera, Pose::Identity()), here, cv::NORM_INF), 0);

  const cv::Mat moved = DepthFromNearbyPose(there, camera, T_there_here);
  // The board's edges in this view, widened by the few pixels the motion shifts them.
  cv::Mat edges(here.size(), CV_8UC1, cv::Scalar(0));
  for (int v = 0; v + 1 < here.rows; ++v) {
    for (int u = 0; u + 1 < here.cols; ++u) {
      const int d = here.at<std::uint16_t>(v, u);
      if (std::abs(d - here.at<std::uint16_t>(v, u + 1)) > 50 ||
          std::abs(d - here.at<std::uint16_t>(v + 1, u)) > 50)
        edges.at<std::uint8_t>(v, u) = 255;
    }
  }
  cv::dilate(edges, edges, cv::Mat(), cv::Point(-1, -1), 5);
  int checked = 0, within_1mm = 0, holes = 0;
  double raw_error = 0;
  for (int v = 8; v < here.rows - 8; ++v) {
    for (int u = 8; u < here.cols - 8; ++u) {
      if (edges.at<std::uint8_t>(v, u)) continue;
      const int truth = here.at<std::uint16_t>(v, u), got = moved.at<std::uint16_t>(v, u);
      ++checked;
      holes += got == 0;
      within_1mm += got != 0 && std::abs(got - truth) <= 1;
      raw_error += std::abs(there.at<std::uint16_t>(v, u) - truth);
    }
  }
  ASSERT_GT(checked, 8000);
  EXPECT_EQ(holes, 0);
  EXPECT_GE(within_1mm, 0.99 * checked);
  EXPECT_GT(raw_error / checked, 10.0);  // mm: what the motion does to the depth as taken
}

}  // namespace
}  // namespace ccmd
