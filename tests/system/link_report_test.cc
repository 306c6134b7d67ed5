// The link figures of the replay report on a hand-made run folder: agents' keyframe logs, the
// server's arrivals and traffic, with known latencies, a missing and a duplicated keyframe.

#include "libccmd/system/link_report.h"

#include <gtest/gtest.h>

#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

Json Log(std::initializer_list<std::array<double, 5>> rows) {
  Json log = Json::MakeArray();
  for (const auto& r : rows) log.Push(Json(Json::Array{r[0], r[1], r[2], r[3], r[4]}));
  return log;
}

TEST(LinkReportTest, LatenciesDeliveryAndRatesComeFromTheLogs) {
  testing::TempDir dir;
  ASSERT_TRUE(MakeDirectories(dir.File("agents")).ok());
  ASSERT_TRUE(MakeDirectories(dir.File("plots")).ok());
  // agent1: keyframes 0-2 (0 and 2 with RGB-D), under a 50 kB/s budget; agent2: keyframes 0-1.
  Json a1, a2;
  a1["link"]["keyframe_log"] = Log(
      {{0, 1000, 1010, 30000, 12000}, {1, 2000, 2010, 15000, 0}, {2, 3000, 3010, 30000, 12000}});
  a1["link"]["budget"]["budget_kBps"] = 50;
  a1["link"]["budget"]["queue_max_s"] = 0.4;
  a2["link"]["keyframe_log"] = Log({{0, 1500, 1510, 30000, 12000}, {1, 2500, 2510, 15000, 0}});
  ASSERT_TRUE(WriteJsonFile(a1, dir.File("agents/agent1_stats.json")).ok());
  ASSERT_TRUE(WriteJsonFile(a2, dir.File("agents/agent2_stats.json")).ok());
  // The server: agent1's keyframes arrive 200, 300 and 400 ms after creation, their points 500
  // and 900 ms after; agent2's first is received twice and enters the dense map with a
  // fusion 10 s later; agent2's keyframe 1 never arrived.
  ASSERT_TRUE(WriteFileAtomic(dir.File("keyframe_arrivals.csv"),
                              "# agent,keyframe,stage,wall_ms\n"
                              "agent1,0,received,1200.000\nagent1,0,dense,1500.000\n"
                              "agent1,1,received,2300.000\n"
                              "agent1,2,received,3400.000\nagent1,2,dense,3900.000\n"
                              "agent2,0,received,1700.000\nagent2,0,received,1800.000\n"
                              "agent2,0,dense_fused,11500.000\n")
                  .ok());
  Json server;
  Json traffic = Json::MakeArray();
  Json t1;
  t1["name"] = "agent1";
  t1["messages"]["keyframe"]["bytes"] = 75000;
  t1["messages"]["pose_update"]["bytes"] = 5000;
  t1["first_message_s"] = 1.0;
  t1["last_message_s"] = 3.0;  // 80 kB over 2 s
  traffic.Push(t1);
  server["transport"]["agents"] = traffic;
  ASSERT_TRUE(WriteJsonFile(server, dir.File("server_stats.json")).ok());

  Json results;
  Json agents = Json::MakeArray();
  for (const char* name : {"agent1", "agent2"}) {
    Json a;
    a["name"] = name;
    agents.Push(a);
  }
  results["agents"] = agents;
  auto section = AddLinkFigures(dir.path(), LinkRunInfo{"rate=1mbit", Json(), 2}, &results);
  ASSERT_TRUE(section.ok()) << section.status().ToString();
  EXPECT_EQ(results.Get("link")->string(), "rate=1mbit");
  EXPECT_FALSE(results.Get("keyframes_delivered_once")->boolean());
  EXPECT_EQ(results.Get("keyframes_missing")->number(), 1);
  EXPECT_EQ(results.Get("keyframes_duplicated")->number(), 1);
  // Map latency over keyframes whose map was in the world frame: 0.5 and 0.9 s.
  EXPECT_EQ(results.Get("map_latency_keyframes")->number(), 2);
  EXPECT_NEAR(results.Get("map_latency_p50_s")->number(), 0.7, 1e-9);
  EXPECT_NEAR(results.Get("map_latency_p95_s")->number(), 0.5 + 0.95 * 0.4, 1e-9);
  // With the fused keyframe (10 s): three values.
  EXPECT_EQ(results.Get("map_latency_all_keyframes")->number(), 3);
  EXPECT_NEAR(results.Get("map_latency_all_p50_s")->number(), 0.9, 1e-9);
  EXPECT_EQ(results.Get("map_latency_after_fusion_keyframes")->number(), 1);
  // Creation to the server: 0.2, 0.3, 0.4, 0.2 s (the first delivery counts), of which 10 ms
  // on the agent each time.
  EXPECT_NEAR(results.Get("keyframe_latency_p50_s")->number(), 0.25, 1e-9);
  EXPECT_NEAR(results.Get("keyframe_on_agent_p95_s")->number(), 0.01, 1e-9);
  EXPECT_NEAR(results.Get("keyframe_on_link_p50_s")->number(), 0.24, 1e-9);
  const Json& agent1 = results.Get("agents")->at(0);
  EXPECT_NEAR(agent1.Get("kBps")->number(), 40, 1e-9);
  EXPECT_EQ(agent1.Get("budget_kBps")->number(), 50);
  EXPECT_NEAR(agent1.Get("kBps_over_budget")->number(), 0.8, 1e-9);
  EXPECT_FALSE(results.Get("agents")->at(1).Has("budget_kBps"));
  EXPECT_TRUE(FileExists(dir.File("plots/budget.png")));
  EXPECT_NE(section->find("1 missing"), std::string::npos) << *section;
}

TEST(LinkReportTest, PercentileInterpolates) {
  EXPECT_EQ(Percentile({}, 0.5), 0);
  EXPECT_EQ(Percentile({3}, 0.95), 3);
  EXPECT_DOUBLE_EQ(Percentile({4, 1, 3, 2}, 0.5), 2.5);
  EXPECT_DOUBLE_EQ(Percentile({1, 2, 3, 4, 5}, 1.0), 5);
}

}  // namespace
}  // namespace ccmd
