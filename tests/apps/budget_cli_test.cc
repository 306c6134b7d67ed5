// Bandwidth budgets and shaped links as users run them: an agent under a budget against a
// real server on loopback, and ccmd_replay over a shaped link between network namespaces
// (needs root; skipped with a notice otherwise).

#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include "libccmd/synth/sequence.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "libccmd/util/subprocess.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using testing::ProgramPath;
using testing::RunCommand;

const Json* ServerAgent(const Json& stats, const std::string& name) {
  for (const Json& a : stats.Get("transport")->Get("agents")->array()) {
    if (a.Get("name")->string() == name) return &a;
  }
  return nullptr;
}

// Message bytes per second between the agent's first and last message, as the server saw them.
double ServerSideRate(const Json& agent) {
  const Json* m = agent.Get("messages");
  const double bytes =
      m->Get("keyframe")->Get("bytes")->number() + m->Get("pose_update")->Get("bytes")->number();
  // The first message left before its arrival opened the span.
  return (bytes - agent.Get("first_message_bytes")->number()) /
         (agent.Get("last_message_s")->number() - agent.Get("first_message_s")->number());
}

TEST(BudgetCliTest, AgentUnderABudgetStaysWithinItAndSendsEveryKeyframe) {
  testing::TempDir dir;
  auto server =
      Subprocess::Start({ProgramPath("ccmd_server"), "--listen", "127.0.0.1:0", "--journal",
                         dir.File("journal"), "--out", dir.File("out"), "--no-fsync", "--no-dense"},
                        "", dir.File("server.log"), /*pipe_stdout=*/true);
  ASSERT_TRUE(server.ok());
  std::string port;
  while (port.empty()) {
    auto line = server->ReadLine(60);
    ASSERT_TRUE(line.ok()) << line.status().ToString();
    if (line->find("listening on ") != std::string::npos)
      port = line->substr(line->find_last_of(':') + 1);
  }
  server->DrainStdoutTo(dir.File("server.out"));
  // 10 kB/s is below what the synthetic room's keyframes need (their geometry alone is more
  // than that unless the tracker runs at a third of the camera's rate or slower; the first
  // keyframe, with RGB-D, is 40 kB): the agent must adapt and its link must pace. At 30 kB/s
  // a loaded machine tracked so slowly that the geometry fitted and nothing needed thinning.
  std::string out;
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_agent") +
                           " --source synth:frames=50,seed=3 --rate realtime --server 127.0.0.1:" +
                           port + " --name budgeted --bandwidth-budget 10 --spill-dir " +
                           dir.File("spill") + " --stats " + dir.File("agent.json"),
                       &out),
            0)
      << out;
  ASSERT_TRUE(server->Signal(SIGINT).ok());
  ASSERT_EQ(server->Wait().exit_code, 0);
  auto stats = ReadJsonFile(dir.File("out/server_stats.json"));
  auto agent = ReadJsonFile(dir.File("agent.json"));
  ASSERT_TRUE(stats.ok() && agent.ok());
  const Json* traffic = ServerAgent(*stats, "budgeted");
  ASSERT_NE(traffic, nullptr);
  const double keyframes_sent = agent->Get("link")->Get("keyframes_sent")->number();
  EXPECT_GE(keyframes_sent, 3);
  // Geometry is never dropped: every keyframe reached the server.
  EXPECT_EQ(traffic->Get("messages")->Get("keyframe")->Get("count")->number(), keyframes_sent);
  EXPECT_LE(ServerSideRate(*traffic), 1.1 * 10e3);
  // The budget's decisions, one per keyframe.
  const Json* budget = agent->Get("link")->Get("budget");
  ASSERT_NE(budget, nullptr);
  EXPECT_EQ(budget->Get("decisions")->size(), static_cast<std::size_t>(keyframes_sent));
  EXPECT_EQ(budget->Get("budget_kBps")->number(), 10);
  // The geometry alone is more than the budget at the tracker's own keyframe density: the
  // tracker made keyframes at the thinner densities the budget asked for. That holds only if
  // the keyframes came faster than the budget carries their geometry, seen between the first
  // two (the density can change only after the second); on a machine so loaded that they did
  // not, there was nothing to thin.
  const Json* decisions = budget->Get("decisions");
  ASSERT_GE(decisions->size(), 2u);
  const Json& second = decisions->at(1);
  const double first_interval_s = second.Get("t")->number();
  if (second.Get("bytes")->number() - second.Get("rgbd_bytes")->number() <=
      10e3 * first_interval_s) {
    std::printf(
        "notice: the second keyframe came %.2f s after the first, its geometry fitted "
        "in the budget; the thinning is not checked on this run\n",
        first_interval_s);
    return;
  }
  const Json* densities = budget->Get("keyframes_per_density");
  ASSERT_NE(densities, nullptr);
  double thinned = 0;
  for (std::size_t i = 0; i < densities->size(); ++i) {
    if (densities->at(i).Get("keyframe_scale")->number() < 1)
      thinned += densities->at(i).Get("keyframes")->number();
  }
  EXPECT_GT(thinned, 0);
}

TEST(BudgetCliTest, RefusesABudgetWithoutAServerABadLinkAndAViewOverALink) {
  std::string out;
  EXPECT_NE(RunCommand(ProgramPath("ccmd_agent") +
                           " --source synth:frames=5 --offline --bandwidth-budget 50",
                       &out),
            0);
  EXPECT_NE(out.find("--bandwidth-budget"), std::string::npos) << out;
  EXPECT_NE(RunCommand(ProgramPath("ccmd_replay") +
                           " --dataset /nonexistent --out /tmp/x --link rate=fast",
                       &out),
            0);
  EXPECT_NE(out.find("rate"), std::string::npos) << out;
  // The live view would serve inside the server's namespace, out of every browser's reach.
  EXPECT_NE(RunCommand(ProgramPath("ccmd_replay") +
                           " --dataset /nonexistent --out /tmp/x --link rate=1mbit --view",
                       &out),
            0);
  EXPECT_NE(out.find("its own network namespace"), std::string::npos) << out;
}

TEST(BudgetCliTest, ReplayOverAShapedLinkDeliversEveryKeyframeAndRemovesTheLink) {
  if (::geteuid() != 0) GTEST_SKIP() << "not root: no network namespaces here; skipping";
  testing::TempDir dir;
  SyntheticSequenceOptions synth;
  synth.frames = 80;
  synth.width = 320;
  synth.height = 240;
  synth.surface_spacing = 0.05;
  ASSERT_TRUE(WriteSyntheticSequence(dir.File("seq"), synth).ok());
  const std::string spec = "rate=3mbit,delay=20ms,jitter=5ms,loss=0.01";
  std::string out;
  ASSERT_EQ(RunCommand(ProgramPath("ccmd_replay") + " --dataset " + dir.File("seq") +
                           " --agents 2 --rate realtime --out " + dir.File("run") + " --link " +
                           spec + " --agent-arg=--bandwidth-budget --agent-arg=40",
                       &out),
            0)
      << out;
  auto results = ReadJsonFile(dir.File("run/results.json"));
  ASSERT_TRUE(results.ok()) << out;
  EXPECT_EQ(results->Get("link")->string(), spec);
  EXPECT_TRUE(results->Get("keyframes_delivered_once")->boolean());
  for (const char* key : {"map_latency_p50_s", "map_latency_p95_s", "keyframe_latency_p95_s"}) {
    ASSERT_TRUE(results->Has(key)) << key;
  }
  EXPECT_GT(results->Get("keyframe_latency_p50_s")->number(), 0.02);  // the link's delay is there
  for (const Json& a : results->Get("agents")->array()) {
    ASSERT_TRUE(a.Has("kBps"));
    EXPECT_EQ(a.Get("budget_kBps")->number(), 40);
    EXPECT_LE(a.Get("kBps")->number(), 1.1 * 40);
  }
  // Traffic crossed the link, and the run removed its namespaces.
  const Json* link = results->Get("link_stats");
  ASSERT_NE(link, nullptr);
  EXPECT_GT(link->Get("forwarder")->Get("uplink")->Get("packets")->number(), 100);
  for (const char* ns : {"agents_namespace", "link_namespace", "server_namespace"}) {
    EXPECT_FALSE(FileExists("/run/netns/" + link->Get(ns)->string())) << ns;
  }
  EXPECT_TRUE(FileExists(dir.File("run/plots/budget.png")));
}

}  // namespace
}  // namespace ccmd
