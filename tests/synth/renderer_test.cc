#include "libccmd/synth/renderer.h"

#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/synth/sequence.h"
#include "tests/support/test_cameras.h"

namespace ccmd {
namespace {

// A convex quad in the plane n . x = n . centre, wound so that its front faces `towards`.
ScenePolygon Quad(const Eigen::Vector3d& centre, const Eigen::Vector3d& n, double half,
                  const Eigen::Vector3d& towards) {
  const Eigen::Vector3d u = n.unitOrthogonal(), v = n.cross(u);
  ScenePolygon p;
  p.vertices = {centre - half * u - half * v, centre + half * u - half * v,
                centre + half * u + half * v, centre - half * u + half * v};
  const Eigen::Vector3d winding =
      (p.vertices[1] - p.vertices[0]).cross(p.vertices[2] - p.vertices[0]);
  if (winding.dot(towards - centre) < 0) std::reverse(p.vertices.begin(), p.vertices.end());
  return p;
}

RenderOptions Exact() {
  RenderOptions o;
  o.noise = false;
  return o;
}

TEST(RendererTest, DepthEqualsRayPlaneIntersectionComputedByHand) {
  const Eigen::Vector3d point(0.1, -0.05, 2.0);
  const Eigen::Vector3d n = Eigen::Vector3d(0.2, -0.3, -1.0).normalized();
  const SyntheticScene scene =
      SyntheticScene::FromPolygons({Quad(point, n, 5.0, Eigen::Vector3d::Zero())});
  const PinholeCamera camera = SyntheticCamera(640, 480);
  const RenderedFrame frame = RenderFrame(scene, camera, Pose::Identity(), Exact());
  for (const auto& [u, v] :
       std::vector<std::pair<int, int>>{{0, 0}, {319, 239}, {600, 50}, {37, 471}}) {
    // Ray through the pixel centre, r = ((u - cx)/fx, (v - cy)/fy, 1); the plane n.x = n.point
    // meets it at z = (n . point) / (n . r).
    const Eigen::Vector3d r((u - 319.5) / 525.0, (v - 239.5) / 525.0, 1.0);
    const double z = n.dot(point) / n.dot(r);
    EXPECT_NEAR(frame.depth_true.at<float>(v, u), z, 2e-6 * z) << u << "," << v;
    EXPECT_NEAR(frame.depth_mm.at<std::uint16_t>(v, u), z * 1000.0, 0.5) << u << "," << v;
    EXPECT_EQ(frame.polygon.at<int>(v, u), 0);
  }
}

TEST(RendererTest, NearerPolygonHidesFartherOne) {
  const Eigen::Vector3d back(0, 0, 3), front(0.5, 0, 1.5);
  const SyntheticScene scene = SyntheticScene::FromPolygons(
      {Quad(back, -Eigen::Vector3d::UnitZ(), 5, Eigen::Vector3d::Zero()),
       Quad(front, -Eigen::Vector3d::UnitZ(), 0.3, Eigen::Vector3d::Zero())});
  const PinholeCamera camera = SyntheticCamera(640, 480);
  const RenderedFrame frame = RenderFrame(scene, camera, Pose::Identity(), Exact());
  // Pixel of (0.5, 0, 1.5): u = 525 * 0.5 / 1.5 + 319.5 = 494.5.
  EXPECT_NEAR(frame.depth_true.at<float>(240, 494), 1.5f, 1e-5);
  EXPECT_EQ(frame.polygon.at<int>(240, 494), 1);
  EXPECT_NEAR(frame.depth_true.at<float>(240, 100), 3.0f, 1e-5);
  // Seen from behind, a polygon is culled: move the camera past the back plane.
  Pose behind = Pose::Identity();
  behind.translation() = Eigen::Vector3d(0, 0, 4);
  const RenderedFrame from_behind = RenderFrame(scene, camera, behind, Exact());
  EXPECT_EQ(cv::countNonZero(from_behind.depth_true), 0);
}

TEST(RendererTest, DepthNoiseFollowsTheSensorModel) {
  const SyntheticScene scene = SyntheticScene::FromPolygons(
      {Quad({0, 0, 2.5}, -Eigen::Vector3d::UnitZ(), 5, Eigen::Vector3d::Zero())});
  const PinholeCamera camera = SyntheticCamera(640, 480);
  RenderOptions noisy;
  noisy.seed = 11;
  const RenderedFrame frame = RenderFrame(scene, camera, Pose::Identity(), noisy);
  double sum = 0, sum_sq = 0;
  int n = 0, invalid = 0;
  for (int y = 20; y < 460; ++y) {
    for (int x = 20; x < 620; ++x) {
      const int mm = frame.depth_mm.at<std::uint16_t>(y, x);
      if (mm == 0) {
        ++invalid;
        continue;
      }
      const double e = mm / 1000.0 - frame.depth_true.at<float>(y, x);
      sum += e;
      sum_sq += e * e;
      ++n;
    }
  }
  const DepthSensorModel model;
  // The plane is 2.5 to 2.8 m away over the image: sigma between these two.
  const double sigma_lo = model.sigma_0 + model.sigma_2 * 2.5 * 2.5;
  const double sigma_hi = model.sigma_0 + model.sigma_2 * 2.8 * 2.8;
  const double sigma = std::sqrt(sum_sq / n - (sum / n) * (sum / n));
  EXPECT_GT(sigma, 0.95 * sigma_lo);
  EXPECT_LT(sigma, 1.05 * sigma_hi);
  EXPECT_LT(std::abs(sum / n), 2e-4);  // unbiased
  EXPECT_NEAR(static_cast<double>(invalid) / (n + invalid), model.random_dropout, 0.002);
}

TEST(RendererTest, GrazingSurfacesLoseDepth) {
  // A floor seen almost edge-on: the far part has cos(angle) < 0.12 and must be invalid.
  const SyntheticScene scene = SyntheticScene::FromPolygons(
      {Quad({0, 1.0, 10}, -Eigen::Vector3d::UnitY(), 20, Eigen::Vector3d::Zero())});
  const PinholeCamera camera = SyntheticCamera(640, 480);
  const RenderedFrame frame = RenderFrame(scene, camera, Pose::Identity(), RenderOptions());
  // Row 245: ray y = 5.5 / 525, plane y = 1 -> z = 95 m: beyond range and grazing.
  EXPECT_EQ(frame.depth_mm.at<std::uint16_t>(245, 320), 0);
  // Row 470: z = 1 / (230.5 / 525) = 2.28 m, cos = 0.40: valid.
  EXPECT_NEAR(frame.depth_mm.at<std::uint16_t>(470, 320), 2278, 60);
}

TEST(RendererTest, DeterministicAndIndependentOfThreadCount) {
  RoomSceneOptions room;
  room.shapes_per_m2 = 60;  // faster texture generation; still textured
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  const PinholeCamera camera = SyntheticCamera(320, 240);
  const Trajectory path = MakeLoopPath(10, 30.0);
  RenderOptions one;
  one.seed = 5;
  RenderOptions two = one;
  two.threads = 2;
  const RenderedFrame a = RenderFrame(scene, camera, path[3].T_world_cam, one);
  const RenderedFrame b = RenderFrame(scene, camera, path[3].T_world_cam, two);
  EXPECT_EQ(cv::norm(a.bgr, b.bgr, cv::NORM_INF), 0);
  EXPECT_EQ(cv::norm(a.depth_mm, b.depth_mm, cv::NORM_INF), 0);
  RenderOptions other = one;
  other.seed = 6;
  const RenderedFrame c = RenderFrame(scene, camera, path[3].T_world_cam, other);
  EXPECT_GT(cv::norm(a.depth_mm, c.depth_mm, cv::NORM_L1), 0);  // the seed drives the noise
}

// A band of rows rendered alone (a rolling shutter's) is those rows of the whole image, noise,
// depth edges and optical blur included, through a plain and a lens-distorted camera, at the
// top, in the middle and at the bottom.
TEST(RendererTest, ABandOfRowsAloneIsThoseRowsOfTheWholeImage) {
  RoomSceneOptions room;
  room.shapes_per_m2 = 60;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  const Trajectory path = MakeLoopPath(10, 30.0);
  PinholeCamera distorted = testing::TumFr1Camera();
  distorted.width = 320;
  distorted.height = 240;
  distorted.cx /= 2;
  distorted.cy /= 2;
  distorted.fx /= 2;
  distorted.fy /= 2;
  for (const PinholeCamera& camera : {SyntheticCamera(320, 240), distorted}) {
    RenderOptions whole;
    whole.seed = 5;
    whole.threads = 2;
    const RenderedFrame full = RenderFrame(scene, camera, path[3].T_world_cam, whole);
    for (const auto& [first, last] : {std::pair{0, 7}, std::pair{100, 107}, std::pair{232, 239}}) {
      RenderOptions band = whole;
      band.row_first = first;
      band.row_last = last;
      const RenderedFrame part = RenderFrame(scene, camera, path[3].T_world_cam, band);
      const cv::Range rows(first, last + 1);
      EXPECT_EQ(cv::norm(part.bgr.rowRange(rows), full.bgr.rowRange(rows), cv::NORM_INF), 0)
          << camera.ToString() << " rows " << first;
      EXPECT_EQ(cv::norm(part.depth_mm.rowRange(rows), full.depth_mm.rowRange(rows), cv::NORM_INF),
                0)
          << camera.ToString() << " rows " << first;
      EXPECT_GT(cv::norm(full.bgr.rowRange(rows), cv::NORM_L1), 0);
      if (first > 20) {
        EXPECT_EQ(cv::norm(part.bgr.rowRange(0, 10), cv::NORM_INF), 0);  // not drawn
      }
    }
  }
  RenderOptions backwards;
  backwards.row_first = 10;
  backwards.row_last = 5;
  EXPECT_FALSE(backwards.Validate().ok());
}

TEST(RendererTest, RoomTextureGivesManyWellSpreadOrbFeatures) {
  const SyntheticScene scene = SyntheticScene::MakeRoom(RoomSceneOptions());
  const PinholeCamera camera = SyntheticCamera(640, 480);
  const Trajectory path = MakeLoopPath(480, 30.0);
  auto orb = cv::ORB::create(1000);
  ASSERT_FALSE(orb.empty());
  for (int i : {0, 120, 240, 360}) {
    const RenderedFrame frame = RenderFrame(scene, camera, path[i].T_world_cam, RenderOptions());
    cv::Mat gray;
    cv::cvtColor(frame.bgr, gray, cv::COLOR_BGR2GRAY);
    std::vector<cv::KeyPoint> keypoints;
    orb->detect(gray, keypoints);
    EXPECT_GE(keypoints.size(), 900u) << "frame " << i;
    // Texture everywhere: FAST corners in nearly every cell of an 8x6 grid.
    std::vector<cv::KeyPoint> corners;
    cv::FAST(gray, corners, 20);
    std::vector<int> cells(48, 0);
    for (const auto& k : corners)
      cells[static_cast<int>(k.pt.y / 80) * 8 + static_cast<int>(k.pt.x / 80)]++;
    EXPECT_GE(std::count_if(cells.begin(), cells.end(), [](int c) { return c >= 10; }), 40)
        << "frame " << i;
    // Valid depth on most of the image.
    EXPECT_GT(cv::countNonZero(frame.depth_mm), 0.85 * 640 * 480) << "frame " << i;
  }
}

// The depth of a distorted camera's pixel is the plane's depth along the pixel's undistorted
// ray, here found with OpenCV's undistortPoints (an implementation independent of ours).
TEST(RendererTest, DistortedCameraSeesAlongEachRawPixelsRay) {
  const Eigen::Vector3d point(0.1, -0.05, 2.0);
  const Eigen::Vector3d n = Eigen::Vector3d(0.3, -0.2, -1.0).normalized();
  const SyntheticScene scene =
      SyntheticScene::FromPolygons({Quad(point, n, 5.0, Eigen::Vector3d::Zero())});
  const PinholeCamera camera = testing::TumFr1Camera();
  const RenderedFrame frame = RenderFrame(scene, camera, Pose::Identity(), Exact());
  const cv::Mat K =
      (cv::Mat_<double>(3, 3) << camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1);
  const cv::Mat dist(camera.distortion, true);
  std::vector<cv::Point2d> raw = {{2, 3}, {319, 239}, {630, 20}, {40, 470}, {600, 450}};
  std::vector<cv::Point2d> normalised;
  cv::undistortPoints(
      raw, normalised, K, dist.reshape(1, 1), cv::noArray(), cv::noArray(),
      cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 100, 1e-14));
  for (std::size_t i = 0; i < raw.size(); ++i) {
    const Eigen::Vector3d r(normalised[i].x, normalised[i].y, 1.0);
    const double z = n.dot(point) / n.dot(r);
    const int u = static_cast<int>(raw[i].x), v = static_cast<int>(raw[i].y);
    EXPECT_NEAR(frame.depth_true.at<float>(v, u), z, 2e-6 * z) << u << "," << v;
    // Without distortion the same pixel would look elsewhere: at the corners by centimetres.
    const Eigen::Vector3d pinhole((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0);
    if (i != 1) {
      EXPECT_GT(std::abs(n.dot(point) / n.dot(pinhole) - z), 2e-3) << u << "," << v;
    }
  }
}

// A small square in front of a wall lands where OpenCV's projection (with distortion) puts it.
TEST(RendererTest, DistortedCameraImagesObjectsWhereTheLensPutsThem) {
  const Eigen::Vector3d centre(-0.62, -0.45, 1.5);  // near the top-left corner: ~9 px of distortion
  const SyntheticScene scene = SyntheticScene::FromPolygons(
      {Quad({0, 0, 3}, -Eigen::Vector3d::UnitZ(), 5, Eigen::Vector3d::Zero()),
       Quad(centre, -Eigen::Vector3d::UnitZ(), 0.03, Eigen::Vector3d::Zero())});
  const PinholeCamera camera = testing::TumFr1Camera();
  const RenderedFrame frame = RenderFrame(scene, camera, Pose::Identity(), Exact());
  double su = 0, sv = 0;
  int count = 0;
  for (int v = 0; v < frame.polygon.rows; ++v) {
    for (int u = 0; u < frame.polygon.cols; ++u) {
      if (frame.polygon.at<int>(v, u) != 1) continue;
      su += u;
      sv += v;
      ++count;
    }
  }
  ASSERT_GT(count, 50);
  const cv::Mat K =
      (cv::Mat_<double>(3, 3) << camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1);
  std::vector<cv::Point2d> projected;
  cv::projectPoints(std::vector<cv::Point3d>{{centre.x(), centre.y(), centre.z()}},
                    cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K,
                    cv::Mat(camera.distortion, true).reshape(1, 1), projected);
  EXPECT_NEAR(su / count, projected[0].x, 0.5);
  EXPECT_NEAR(sv / count, projected[0].y, 0.5);
  const Eigen::Vector2d pinhole = camera.Project(centre);
  EXPECT_GT(std::hypot(pinhole.x() - projected[0].x, pinhole.y() - projected[0].y), 5.0);
}

// ICL-NUIM's convention: with fy < 0 the image rows run opposite to the camera's y axis, so
// the image is the other one upside down (cy mirrored as well).
TEST(RendererTest, NegativeFyFlipsTheRows) {
  RoomSceneOptions room;
  room.shapes_per_m2 = 60;
  const SyntheticScene scene = SyntheticScene::MakeRoom(room);
  const Trajectory path = MakeLoopPath(10, 30.0);
  PinholeCamera up = SyntheticCamera(320, 240);
  up.cy = 100.25;  // off-centre, to see that cy flips too
  PinholeCamera down = up;
  down.fy = -up.fy;
  down.cy = up.height - 1 - up.cy;
  const RenderedFrame a = RenderFrame(scene, up, path[4].T_world_cam, Exact());
  const RenderedFrame b = RenderFrame(scene, down, path[4].T_world_cam, Exact());
  cv::Mat flipped;
  cv::flip(b.depth_true, flipped, 0);
  cv::Mat difference = cv::abs(a.depth_true - flipped);
  // Equal up to rounding, except along polygon edges where a pixel may change sides.
  EXPECT_GT(cv::countNonZero(difference < 1e-4f), 0.99 * up.width * up.height);
  cv::flip(b.bgr, flipped, 0);
  EXPECT_LT(cv::norm(a.bgr, flipped, cv::NORM_L1) / (3.0 * up.width * up.height), 1.0);
}

}  // namespace
}  // namespace ccmd
