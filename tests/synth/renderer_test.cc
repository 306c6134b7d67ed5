#include "libccmd/synth/renderer.h"

#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/synth/sequence.h"

namespace ccmd {
namespace {

// A convex quad in the plane n . x = n . centre, wound so that its front faces `towards`.
ScenePolygon Quad(const Eigen::Vector3d& centre, const Eigen::Vector3d& n, double half,
                  const Eigen::Vector3d& towards) {
  const Eigen::Vector3d u = n.unitOrthogonal(), v = n.cross(u);
  ScenePolygon p;
  p.vertices = {centre - half * u - half * v, centre + half * u - half * v,
                centre + half * u + half * v, centre - half * u + half * v};
  const Eigen::Vector3d winding = (p.vertices[1] - p.vertices[0]).cross(p.vertices[2] - p.vertices[0]);
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
  for (const auto& [u, v] : std::vector<std::pair<int, int>>{{0, 0}, {319, 239}, {600, 50}, {37, 471}}) {
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
  EXPECT_LT(std::abs(sum / n), 2e-4);                       // unbiased
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
    for (const auto& k : corners) cells[static_cast<int>(k.pt.y / 80) * 8 + static_cast<int>(k.pt.x / 80)]++;
    EXPECT_GE(std::count_if(cells.begin(), cells.end(), [](int c) { return c >= 10; }), 40) << "frame " << i;
    // Valid depth on most of the image.
    EXPECT_GT(cv::countNonZero(frame.depth_mm), 0.85 * 640 * 480) << "frame " << i;
  }
}

}  // namespace
}  // namespace ccmd
