// The sampling-rate / selection table added to a replay's report and results.

#include "libccmd/system/replay_report.h"

#include <gtest/gtest.h>

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
