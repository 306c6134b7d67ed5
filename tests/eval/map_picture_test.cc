// Pictures of a dense map checked against the map they come from: a box room with a red wall
// at one end and a blue one at the other, a grey floor mapped half by each of two agents and a
// white ceiling the pictures must leave out.

#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "libccmd/dense/label.h"
#include "libccmd/eval/map_picture.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

constexpr double kSpacing = 0.02;
const cv::Vec3b kRed(30, 30, 220), kBlue(220, 30, 30), kGreen(30, 200, 30),
    kGrey(128, 128, 128);  // BGR

void AddPatch(PointCloud* cloud, const Eigen::Vector3d& origin, const Eigen::Vector3d& u,
              const Eigen::Vector3d& v, const cv::Vec3b& bgr,
              const std::function<int(const Eigen::Vector3d&)>& agent) {
  const int nu = static_cast<int>(u.norm() / kSpacing), nv = static_cast<int>(v.norm() / kSpacing);
  for (int i = 0; i <= nu; ++i) {
    for (int j = 0; j <= nv; ++j) {
      const Eigen::Vector3d p =
          origin + u * (static_cast<double>(i) / nu) + v * (static_cast<double>(j) / nv);
      cloud->points.push_back(p.cast<float>());
      cloud->colors.push_back({bgr[2], bgr[1], bgr[0]});
      cloud->labels.push_back(
          *EncodeLabel({AgentId(static_cast<std::uint16_t>(agent(p))), KeyframeId(7)}));
    }
  }
}

// 4 m along x, 3 m along y, 2.5 m high; world z up.
PointCloud Room() {
  PointCloud room;
  const auto by_half = [](const Eigen::Vector3d& p) { return p.x() < 0 ? 1 : 2; };
  const auto one = [](const Eigen::Vector3d&) { return 1; };
  const auto two = [](const Eigen::Vector3d&) { return 2; };
  AddPatch(&room, {-2, -1.5, 0}, {4, 0, 0}, {0, 3, 0}, kGrey, by_half);
  AddPatch(&room, {2, -1.5, 0}, {0, 3, 0}, {0, 0, 2.5}, kRed, two);
  AddPatch(&room, {-2, -1.5, 0}, {0, 3, 0}, {0, 0, 2.5}, kBlue, one);
  AddPatch(&room, {-2, -1.5, 0}, {4, 0, 0}, {0, 0, 2.5}, kGreen, one);
  AddPatch(&room, {-2, 1.5, 0}, {4, 0, 0}, {0, 0, 2.5}, kGreen, one);
  AddPatch(&room, {-2, -1.5, 2.5}, {4, 0, 0}, {0, 3, 0}, cv::Vec3b(250, 250, 250), one);  // ceiling
  return room;
}

// Cameras 1.2 m high on a circle, looking outwards and 20 degrees down (camera y is down).
Trajectory Cameras(double radius = 0.5) {
  Trajectory t;
  for (int i = 0; i < 24; ++i) {
    const double yaw = 2 * M_PI * i / 24;
    const Eigen::Matrix3d level =
        (Eigen::Matrix3d() << 0, 0, 1, -1, 0, 0, 0, -1, 0).finished();  // looks along +x
    const Eigen::Matrix3d R =
        Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix() * level *
        Eigen::AngleAxisd(20 * M_PI / 180, Eigen::Vector3d::UnitX()).toRotationMatrix();
    Pose T = Pose::Identity();
    T.linear() = R;
    T.translation() = Eigen::Vector3d(radius * std::cos(yaw), radius * std::sin(yaw), 1.2);
    t.push_back({static_cast<double>(i), T});
  }
  return t;
}

MapPictureOptions Options() {
  MapPictureOptions o;
  o.background = cv::Scalar(0, 0, 0);
  o.point_size_m = kSpacing;
  o.agents[1] = {"one", cv::Scalar(200, 80, 30)};
  o.agents[2] = {"two", cv::Scalar(40, 140, 240)};
  return o;
}

double Fraction(const cv::Mat& image, const cv::Rect& area, const cv::Vec3b& colour,
                int tolerance = 12) {
  int n = 0;
  for (int v = area.y; v < area.y + area.height; ++v) {
    for (int u = area.x; u < area.x + area.width; ++u) {
      const cv::Vec3b c = image.at<cv::Vec3b>(v, u);
      n += std::abs(c[0] - colour[0]) <= tolerance && std::abs(c[1] - colour[1]) <= tolerance &&
           std::abs(c[2] - colour[2]) <= tolerance;
    }
  }
  return static_cast<double>(n) / std::max(1, area.area());
}

cv::Rect Covered(const cv::Mat& image) {
  cv::Mat gray, mask;
  cv::cvtColor(image, gray, cv::COLOR_BGR2GRAY);
  std::vector<cv::Point> points;
  cv::findNonZero(gray > 0, points);
  return cv::boundingRect(points);
}

TEST(MapPictureTest, UpComesFromThePlaneTheCamerasMoveIn) {
  const MapViewFrame frame = EstimateMapViewFrame(Cameras(), 0.4);
  EXPECT_GT(frame.up.dot(Eigen::Vector3d::UnitZ()), std::cos(0.5 * M_PI / 180));
  EXPECT_NEAR(frame.cut_height, 1.6, 1e-9);
  // On a line there is no plane: the cameras' mean up is used, here tilted by their look down.
  Trajectory line = Cameras();
  for (std::size_t i = 0; i < line.size(); ++i) {
    line[i].T_world_cam = line[0].T_world_cam;
    line[i].T_world_cam.translation() = Eigen::Vector3d(0.1 * i, 0, 1.2);
  }
  const MapViewFrame tilted = EstimateMapViewFrame(line, 0.4);
  EXPECT_LT(tilted.up.dot(Eigen::Vector3d::UnitZ()), std::cos(5 * M_PI / 180));
  EXPECT_TRUE(std::isinf(EstimateMapViewFrame({}, 0.4).cut_height));
}

TEST(MapPictureTest, TopViewShowsTheRoomFromAboveWithoutItsCeiling) {
  const PointCloud room = Room();
  const MapViewFrame frame = EstimateMapViewFrame(Cameras(), 0.4);
  auto rgb = RenderMapTop(room, frame, MapColouring::kRgb, Options());
  ASSERT_TRUE(rgb.ok()) << rgb.status().ToString();
  const cv::Rect box = Covered(*rgb);
  // The footprint: 4 x 3 m, filled (floor), no ceiling.
  EXPECT_NEAR(static_cast<double>(box.width) / box.height, 4.0 / 3.0, 0.06);
  EXPECT_GT(box.width, 0.85 * rgb->cols);
  EXPECT_LT(Fraction(*rgb, box, cv::Vec3b(0, 0, 0), 0), 0.02);
  EXPECT_EQ(Fraction(*rgb, box, cv::Vec3b(250, 250, 250), 4), 0.0);
  EXPECT_GT(Fraction(*rgb, box, kGrey), 0.7);
  // The red wall is at one end of the long side, the blue at the other.
  const cv::Rect left(box.x, box.y, 4, box.height),
      right(box.x + box.width - 4, box.y, 4, box.height);
  const bool red_right = Fraction(*rgb, right, kRed) > Fraction(*rgb, left, kRed);
  EXPECT_GT(Fraction(*rgb, red_right ? right : left, kRed), 0.8);
  EXPECT_GT(Fraction(*rgb, red_right ? left : right, kBlue), 0.8);
  // By agent: the floor half next to the red wall is agent two's.
  auto agents = RenderMapTop(room, frame, MapColouring::kAgent, Options());
  ASSERT_TRUE(agents.ok());
  const cv::Rect near_red(red_right ? box.x + box.width * 3 / 4 : box.x + box.width / 8,
                          box.y + box.height / 4, box.width / 8, box.height / 2);
  const cv::Rect near_blue(red_right ? box.x + box.width / 8 : box.x + box.width * 3 / 4,
                           box.y + box.height / 4, box.width / 8, box.height / 2);
  EXPECT_GT(Fraction(*agents, near_red, cv::Vec3b(40, 140, 240)), 0.95);
  EXPECT_GT(Fraction(*agents, near_blue, cv::Vec3b(200, 80, 30)), 0.95);
  // Without labels there is no agent picture.
  PointCloud unlabelled = room;
  unlabelled.labels.clear();
  EXPECT_FALSE(RenderMapTop(unlabelled, frame, MapColouring::kAgent, Options()).ok());
  EXPECT_FALSE(RenderMapTop(PointCloud(), frame, MapColouring::kRgb, Options()).ok());
}

TEST(MapPictureTest, PerspectiveViewSeesFloorAndWallsButNoCeiling) {
  const PointCloud room = Room();
  const MapViewFrame frame = EstimateMapViewFrame(Cameras(), 0.4);
  auto rgb = RenderMapPerspective(room, frame, MapColouring::kRgb, Options());
  ASSERT_TRUE(rgb.ok());
  const cv::Rect all(0, 0, rgb->cols, rgb->rows);
  EXPECT_GT(1.0 - Fraction(*rgb, all, cv::Vec3b(0, 0, 0), 0), 0.3);
  EXPECT_EQ(Fraction(*rgb, all, cv::Vec3b(250, 250, 250), 4), 0.0);
  EXPECT_GT(Fraction(*rgb, all, kGrey), 0.1);
  EXPECT_GT(Fraction(*rgb, all, kGreen), 0.02);
  EXPECT_GT(Fraction(*rgb, all, kRed), 0.005);
  EXPECT_GT(Fraction(*rgb, all, kBlue), 0.005);
}

TEST(MapPictureTest, WritesBothPicturesWithAnAgentPanel) {
  testing::TempDir dir;
  ASSERT_TRUE(WriteMapPictures(Room(), Cameras(), Options(), dir.path()).ok());
  for (const char* name : {"map_top.png", "map_view.png"}) {
    const cv::Mat image = cv::imread(dir.File(name));
    ASSERT_FALSE(image.empty()) << name;
    EXPECT_EQ(image.cols, 2 * Options().panel_width);
    EXPECT_GT(image.rows, Options().panel_height);
  }
}

}  // namespace
}  // namespace ccmd
