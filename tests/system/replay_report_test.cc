// The sampling-rate / selection table added to a replay's report and results.

#include "libccmd/system/replay_report.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>

#include "libccmd/eval/reconstruction_error.h"
#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

Json RunResults(double colour, double depth, double points, double rgbd_keyframes, double keyframes) {
  Json j;
  j["colour_bytes"] = colour;
  j["depth_bytes"] = depth;
  j["map_points"] = points;
  j["rgbd_keyframes"] = rgbd_keyframes;
  j["keyframes_sent"] = keyframes;
  j["recon_mean_m"] = 0.005;
  j["ate_rmse_m"] = 0.003;
  j["maps_after_fusion"] = 1;
  return j;
}

double MedianOf(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

// With a Depth block the ground-truth reference is built from registered depth, as the agents
// see it: registration by a pure offset t moves every point by t in the camera frame.
TEST(ReplayReportTest, ReferenceCloudUsesTheDepthRegistration) {
  testing::TempDir dir;
  SyntheticSequenceOptions o;
  o.frames = 1;
  o.width = 160;
  o.height = 120;
  o.noise = false;
  o.room.shapes_per_m2 = 20;
  o.surface_spacing = 0.1;
  ASSERT_TRUE(WriteSyntheticSequence(dir.path(), o).ok());
  ASSERT_EQ(std::remove(dir.File("surface.ply").c_str()), 0);  // build the reference from ground truth
  auto dataset = TumSequence::Open(dir.path(), std::nullopt);
  ASSERT_TRUE(dataset.ok()) << dataset.status().ToString();
  ReferenceOptions options;
  options.downsample = 1;
  options.voxel_m = 0.005;
  auto plain = LoadOrBuildReference(*dataset, options, nullptr);
  ASSERT_TRUE(plain.ok()) << plain.status().ToString();

  DepthToColorCalibration calibration;
  calibration.depth = dataset->camera();
  const Eigen::Vector3d t(0.04, 0, 0);
  calibration.T_color_depth.translation() = t;
  options.registration = calibration;
  auto registered = LoadOrBuildReference(*dataset, options, nullptr);
  ASSERT_TRUE(registered.ok()) << registered.status().ToString();
  ASSERT_GT(registered->size(), plain->size() / 2);

  const Pose T_world_cam = *dataset->frame(0).T_world_cam_gt;
  PointCloud moved_back = *registered;
  for (Eigen::Vector3f& p : moved_back.points) p -= (T_world_cam.linear() * t).cast<float>();
  EXPECT_LT(MedianOf(NearestDistances(moved_back, *plain)), 0.004);
  EXPECT_GT(MedianOf(NearestDistances(*registered, *plain)), 0.02);

  calibration.depth = dataset->camera().Resized(80, 60);
  options.registration = calibration;
  EXPECT_EQ(LoadOrBuildReference(*dataset, options, nullptr).status().code(), StatusCode::kInvalidArgument);
}

TEST(ReplayReportTest, AblationTableAddsRowsWithRatiosToTheFullRun) {
  testing::TempDir dir;
  Json main;
  main["ate_rmse_m"] = 0.003;
  ASSERT_TRUE(WriteJsonFile(main, dir.File("results.json")).ok());
  ASSERT_TRUE(WriteFileAtomic(dir.File("report.md"), "# Split-replay report\n").ok());
  // r = 1 without selection is the reference: 8000 + 2000 bytes, 1000 points.
  std::vector<AblationRow> rows;
  rows.push_back({1, false, "ablation/r1_every_keyframe", RunResults(8000, 2000, 1000, 20, 20)});
  rows.push_back({2, true, ".", RunResults(1500, 1000, 400, 5, 20)});
  rows.push_back({4, true, "ablation/r4_selected", RunResults(500, 500, 100, 5, 21)});
  ASSERT_TRUE(AppendAblation(dir.path(), rows).ok());

  auto results = ReadJsonFile(dir.File("results.json"));
  ASSERT_TRUE(results.ok());
  EXPECT_DOUBLE_EQ(results->Get("ate_rmse_m")->number(), 0.003);  // what was there stays
  const Json* ablation = results->Get("ablation");
  ASSERT_NE(ablation, nullptr);
  ASSERT_EQ(ablation->size(), 3u);
  const Json& half = ablation->array()[1];
  EXPECT_DOUBLE_EQ(half.Get("r")->number(), 0.5);
  EXPECT_TRUE(half.Get("selection")->boolean());
  EXPECT_DOUBLE_EQ(half.Get("rgbd_bytes")->number(), 2500);
  EXPECT_DOUBLE_EQ(half.Get("map_points")->number(), 400);
  EXPECT_DOUBLE_EQ(ablation->array()[2].Get("keyframes")->number(), 21);

  auto report = ReadFileToString(dir.File("report.md"));
  ASSERT_TRUE(report.ok());
  EXPECT_EQ(report->rfind("# Split-replay report\n", 0), 0u);  // appended, not replaced
  // 2500 / 10000 bytes and 400 / 1000 points; 1000 / 10000 and 100 / 1000 for r = 1/4.
  EXPECT_NE(report->find("| 1/2 | on | 5 of 20 | 2 kB | 0.12 kB | 0.250 | 400 | 0.400 |"), std::string::npos) << *report;
  EXPECT_NE(report->find("| 1/4 | on | 5 of 21 | 1 kB | 0.05 kB | 0.100 | 100 | 0.100 |"), std::string::npos) << *report;
  EXPECT_NE(report->find("| 1 | off | 20 of 20 | 10 kB | 0.50 kB | 1.000 | 1000 | 1.000 |"), std::string::npos) << *report;
}

TEST(ReplayReportTest, AblationNeedsTheMainRunsFiles) {
  testing::TempDir dir;
  EXPECT_FALSE(AppendAblation(dir.path(), {}).ok());
}

}  // namespace
}  // namespace ccmd
