// Faults: connections cut at random points (mid-frame too) and delayed by a proxy; the
// server process killed with SIGKILL mid-run and restarted from its journal. Afterwards the
// server holds exactly the messages the agents sent, count and content.

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <condition_variable>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/net/agent_link.h"
#include "libccmd/net/journal.h"
#include "libccmd/net/server.h"
#include "libccmd/util/json.h"
#include "tests/net/fault_proxy.h"
#include "tests/net/net_test_util.h"
#include "tests/net/server_process.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using nettest::Bytes;
using nettest::FaultProxy;
using nettest::FaultProxyOptions;
using nettest::RecordingConsumer;
using nettest::ServerProcess;
using nettest::SyntheticKeyframe;

AgentLinkOptions LinkVia(std::uint16_t port, const std::string& name) {
  AgentLinkOptions o;
  o.server = "127.0.0.1:" + std::to_string(port);
  o.name = name;
  o.camera = nettest::TestCamera();
  o.backoff_initial_s = 0.005;
  o.backoff_max_s = 0.05;
  o.connect_timeout_s = 2;
  return o;
}

TEST(FaultTest, ProxyCutsConnectionsMidFrameAndDelaysTraffic) {
  testing::TempDir dir;
  RecordingConsumer consumer;
  ServerOptions so;
  so.listen = "127.0.0.1:0";
  so.journal_dir = dir.File("journal");
  so.fsync = false;
  Server server(so, &consumer);
  ASSERT_TRUE(server.Start().ok());
  FaultProxy proxy(
      {.seed = 7, .min_cut_bytes = 3000, .max_cut_bytes = 60000, .max_delay_s = 0.0005});
  ASSERT_TRUE(proxy.Start(server.port()));

  constexpr int kAgents = 4;
  constexpr int kMessages = 80;
  std::vector<std::unique_ptr<AgentLink>> links;
  for (int a = 0; a < kAgents; ++a) {
    links.push_back(AgentLink::Create(LinkVia(proxy.port(), "cut" + std::to_string(a))).value());
  }
  for (int i = 0; i < kMessages; ++i) {
    for (int a = 0; a < kAgents; ++a) {
      ASSERT_TRUE(links[a]->Send(MessageType::kKeyframe, SyntheticKeyframe(a, i, 20, 3000)).ok());
    }
  }
  std::uint64_t resent = 0;
  for (auto& link : links) {
    ASSERT_TRUE(link->Flush(60).ok());
    resent += link->stats().resent;
  }
  links.clear();
  proxy.Stop();
  server.Stop();
  // Each agent sent ~300 kB through connections cut after 3..60 kB: many cuts, many resends.
  EXPECT_GT(proxy.cuts(), kAgents);
  EXPECT_GT(resent, 0u);
  const auto got = consumer.messages();
  for (int a = 0; a < kAgents; ++a) {
    const auto& m = got.at("cut" + std::to_string(a));
    ASSERT_EQ(m.size(), static_cast<std::size_t>(kMessages));
    for (int i = 0; i < kMessages; ++i) {
      EXPECT_EQ(m[i].seq, static_cast<std::uint64_t>(i + 1));
      EXPECT_EQ(m[i].payload, SyntheticKeyframe(a, i, 20, 3000)) << a << "/" << i;
    }
  }
}

// Acknowledged link numbers per agent, for waiting without polling.
class AckCounter {
 public:
  std::function<void(std::uint64_t, std::uint64_t)> For(int agent) {
    return [this, agent](std::uint64_t, std::uint64_t last) {
      std::lock_guard<std::mutex> lock(mutex_);
      acked_[agent] = last;
      cv_.notify_all();
    };
  }
  bool WaitAll(int agents, std::uint64_t at_least, double timeout_s) {
    std::unique_lock<std::mutex> lock(mutex_);
    return cv_.wait_for(lock, std::chrono::duration<double>(timeout_s), [&] {
      for (int a = 0; a < agents; ++a) {
        if (acked_[a] < at_least) return false;
      }
      return true;
    });
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  std::map<int, std::uint64_t> acked_;
};

TEST(FaultTest, ServerKilledWithSigkillResumesFromItsJournal) {
  testing::TempDir dir;
  const std::string journal = dir.File("journal");
  const std::string stats = dir.File("stats.json");
  const std::string log = dir.File("server.log");
  auto first = std::make_unique<ServerProcess>();
  ASSERT_TRUE(first->Start({"--listen", "127.0.0.1:0", "--journal", journal}, log));
  FaultProxy proxy({.seed = 3});
  ASSERT_TRUE(proxy.Start(first->port()));

  constexpr int kAgents = 3;
  constexpr int kMessages = 120;
  AckCounter acks;
  std::vector<std::unique_ptr<AgentLink>> links;
  for (int a = 0; a < kAgents; ++a) {
    AgentLinkOptions o = LinkVia(proxy.port(), "robot" + std::to_string(a));
    o.on_acked = acks.For(a);
    links.push_back(AgentLink::Create(o).value());
  }
  for (int i = 0; i < kMessages / 2; ++i) {
    for (int a = 0; a < kAgents; ++a) {
      ASSERT_TRUE(links[a]->Send(MessageType::kKeyframe, SyntheticKeyframe(a, i, 20, 4000)).ok());
    }
  }
  // Kill while traffic is flowing: some messages acknowledged, others on the wire.
  ASSERT_TRUE(acks.WaitAll(kAgents, 20, 30));
  first->Signal(SIGKILL);
  EXPECT_EQ(first->Wait(), 128 + SIGKILL);
  first.reset();
  // The agents go on while the server is down; their links buffer and retry.
  for (int i = kMessages / 2; i < kMessages; ++i) {
    for (int a = 0; a < kAgents; ++a) {
      ASSERT_TRUE(links[a]->Send(MessageType::kKeyframe, SyntheticKeyframe(a, i, 20, 4000)).ok());
    }
  }
  ServerProcess second;
  ASSERT_TRUE(
      second.Start({"--listen", "127.0.0.1:0", "--resume", journal, "--stats", stats}, log));
  proxy.SetTarget(second.port());
  for (auto& link : links) ASSERT_TRUE(link->Flush(60).ok()) << link->stats().last_error;
  links.clear();
  second.Signal(SIGTERM);
  EXPECT_EQ(second.Wait(), 0);
  proxy.Stop();

  // The journals hold exactly what the agents sent, once, in order.
  for (int a = 0; a < kAgents; ++a) {
    std::string name;
    std::vector<std::pair<std::uint64_t, Bytes>> records;
    JournalVisitor v;
    v.on_info = [&](const JournalAgentInfo& info) {
      name = info.name;
      return Status::Ok();
    };
    v.on_record = [&](const JournalRecord& r) {
      records.emplace_back(r.seq, Bytes(r.message.begin(), r.message.end()));
      return Status::Ok();
    };
    StatusOr<JournalScan> scan =
        ScanJournalFile(journal + "/" + JournalFileName(AgentId(a + 1)), v);
    ASSERT_TRUE(scan.ok()) << scan.status().ToString();
    const int agent = name.back() - '0';
    ASSERT_EQ(records.size(), static_cast<std::size_t>(kMessages)) << name;
    for (int i = 0; i < kMessages; ++i) {
      EXPECT_EQ(records[i].first, static_cast<std::uint64_t>(i + 1));
      EXPECT_EQ(records[i].second, SyntheticKeyframe(agent, i, 20, 4000)) << name << " " << i;
    }
  }
  // The restarted server's consumer saw every message once: replayed plus received.
  StatusOr<Json> json = ReadJsonFile(stats);
  ASSERT_TRUE(json.ok()) << json.status().ToString();
  ASSERT_EQ(json->Get("agents")->size(), static_cast<std::size_t>(kAgents));
  for (const Json& agent : json->Get("agents")->array()) {
    EXPECT_EQ(agent.Get("delivered")->Get("count")->number(), kMessages);
    EXPECT_EQ(agent.Get("delivered")->Get("last_seq")->number(), kMessages);
    EXPECT_GE(agent.Get("delivered")->Get("replayed")->number(), 20);
  }
}

}  // namespace
}  // namespace ccmd
