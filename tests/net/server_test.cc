// Loopback integration: many agents at once, exactly once and in order, resume.

#include "libccmd/net/server.h"

#include <memory>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/net/agent_link.h"
#include "libccmd/net/journal.h"
#include "tests/net/net_test_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using nettest::Bytes;
using nettest::RecordingConsumer;
using nettest::SyntheticKeyframe;
using nettest::TestCamera;

ServerOptions LoopbackOptions(const std::string& journal) {
  ServerOptions o;
  o.listen = "127.0.0.1:0";
  o.journal_dir = journal;
  o.fsync = false;  // the tests check process-level durability; fsync costs time on CI disks
  return o;
}

AgentLinkOptions LinkOptions(std::uint16_t port, const std::string& name) {
  AgentLinkOptions o;
  o.server = "127.0.0.1:" + std::to_string(port);
  o.name = name;
  o.camera = TestCamera();
  o.backoff_initial_s = 0.01;
  o.backoff_max_s = 0.1;
  return o;
}

TEST(ServerTest, EightAgentsConcurrentlyExactlyOnceInOrder) {
  testing::TempDir dir;
  RecordingConsumer consumer;
  Server server(LoopbackOptions(dir.File("journal")), &consumer);
  ASSERT_TRUE(server.Start().ok());
  constexpr int kAgents = 8;
  constexpr int kMessages = 60;
  std::vector<std::thread> threads;
  std::vector<Status> results(kAgents);
  for (int a = 0; a < kAgents; ++a) {
    threads.emplace_back([&, a] {
      auto link = AgentLink::Create(LinkOptions(server.port(), "agent" + std::to_string(a)));
      if (!link.ok()) {
        results[a] = link.status();
        return;
      }
      for (int i = 0; i < kMessages; ++i) {
        // Every fifth message a pose update, so both kinds interleave.
        StatusOr<std::uint64_t> seq =
            i % 5 == 4 ? (*link)->Send(MessageType::kPoseUpdate,
                                       SerializePoseUpdate(PoseUpdateMessage{}).value())
                       : (*link)->Send(MessageType::kKeyframe, SyntheticKeyframe(a, i, 30, 2000));
        if (!seq.ok() || *seq != static_cast<std::uint64_t>(i + 1)) {
          results[a] = seq.ok() ? Internal("unexpected link number") : seq.status();
          return;
        }
      }
      results[a] = (*link)->Flush(20.0);
    });
  }
  for (auto& t : threads) t.join();
  for (int a = 0; a < kAgents; ++a) EXPECT_TRUE(results[a].ok()) << a << ": " << results[a].ToString();
  ASSERT_TRUE(consumer.WaitForTotal(kAgents * kMessages, 10.0));
  server.Stop();

  const auto messages = consumer.messages();
  ASSERT_EQ(messages.size(), static_cast<std::size_t>(kAgents));
  for (int a = 0; a < kAgents; ++a) {
    const auto& got = messages.at("agent" + std::to_string(a));
    ASSERT_EQ(got.size(), static_cast<std::size_t>(kMessages)) << "agent " << a;
    for (int i = 0; i < kMessages; ++i) {
      EXPECT_EQ(got[i].seq, static_cast<std::uint64_t>(i + 1));
      if (i % 5 == 4) {
        EXPECT_EQ(got[i].type, 17);
      } else {
        EXPECT_EQ(got[i].type, 16);
        EXPECT_EQ(got[i].payload, SyntheticKeyframe(a, i, 30, 2000)) << a << "/" << i;
      }
    }
  }
  // Accounting: the keyframe parts add up to the keyframe bytes of each agent.
  const Json stats = server.StatsJson();
  ASSERT_EQ(stats.Get("agents")->size(), static_cast<std::size_t>(kAgents));
  for (const Json& agent : stats.Get("agents")->array()) {
    const Json& kf = *agent.Get("messages")->Get("keyframe");
    EXPECT_EQ(kf.Get("count")->number(), 48);
    double parts = 0;
    for (const auto& [name, v] : agent.Get("keyframe_parts_bytes")->object()) parts += v.number();
    EXPECT_EQ(parts, kf.Get("bytes")->number());
    EXPECT_EQ(agent.Get("delivered")->Get("count")->number(), kMessages);
  }
}

}  // namespace
}  // namespace ccmd
