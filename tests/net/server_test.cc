// Loopback integration: many agents at once, exactly once and in order, resume.

#include "libccmd/net/server.h"

#include <condition_variable>
#include <cstdio>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/net/agent_link.h"
#include "libccmd/net/journal.h"
#include "libccmd/net/socket.h"
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
  for (int a = 0; a < kAgents; ++a)
    EXPECT_TRUE(results[a].ok()) << a << ": " << results[a].ToString();
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

namespace ccmd {
namespace {

std::vector<Bytes> SendAll(AgentLink* link, int agent, int from, int to) {
  std::vector<Bytes> sent;
  for (int i = from; i < to; ++i) {
    Bytes m = SyntheticKeyframe(agent, i, 20, 1500);
    EXPECT_TRUE(link->Send(MessageType::kKeyframe, m).ok());
    sent.push_back(std::move(m));
  }
  return sent;
}

TEST(ServerTest, ResumeReplaysTheJournalThenContinuesTheSequence) {
  testing::TempDir dir;
  AgentId first_id;
  {
    RecordingConsumer consumer;
    Server server(LoopbackOptions(dir.File("journal")), &consumer);
    ASSERT_TRUE(server.Start().ok());
    AgentLinkOptions o = LinkOptions(server.port(), "robot");
    o.spill_dir = dir.File("robot.spill");  // keeps the agent's identity for its next run
    auto link = AgentLink::Create(o).value();
    SendAll(link.get(), 1, 0, 30);
    ASSERT_TRUE(link->Flush(10).ok());
    first_id = link->stats().agent;
    link.reset();
    server.Stop();
  }
  // A crash in the middle of the next append: half a record at the end of the journal.
  const std::string journal = dir.File("journal/" + JournalFileName(first_id));
  {
    Bytes half;
    AppendDataFrame(16, 31, SyntheticKeyframe(1, 30, 20, 1500), &half);
    half.resize(half.size() / 2);
    FILE* f = std::fopen(journal.c_str(), "ab");
    std::fwrite(half.data(), 1, half.size(), f);
    std::fclose(f);
  }
  // Without --resume, a folder holding journals is refused.
  {
    RecordingConsumer consumer;
    Server server(LoopbackOptions(dir.File("journal")), &consumer);
    EXPECT_EQ(server.Start().code(), StatusCode::kInvalidArgument);
  }
  RecordingConsumer consumer;
  ServerOptions options = LoopbackOptions(dir.File("journal"));
  options.resume = true;
  Server server(options, &consumer);
  ASSERT_TRUE(server.Start().ok());
  // Everything journaled reached the consumer before Start returned.
  EXPECT_EQ(consumer.total(), 30u);
  EXPECT_EQ(consumer.known_from_journal(), 1);
  ASSERT_EQ(consumer.events().back(), "replay finished 30");
  // A new process of the same agent (its spill folder, so its identity) continues after
  // message 30 with the same id.
  AgentLinkOptions o = LinkOptions(server.port(), "robot");
  o.spill_dir = dir.File("robot.spill");
  auto link = AgentLink::Create(o).value();
  SendAll(link.get(), 1, 30, 50);
  ASSERT_TRUE(link->Flush(10).ok());
  EXPECT_EQ(link->stats().agent, first_id);
  link.reset();
  server.Stop();
  const auto got = consumer.messages().at("robot");
  ASSERT_EQ(got.size(), 50u);
  for (int i = 0; i < 50; ++i) {
    EXPECT_EQ(got[i].seq, static_cast<std::uint64_t>(i + 1));
    EXPECT_EQ(got[i].replayed, i < 30);
    EXPECT_EQ(got[i].payload, SyntheticKeyframe(1, i, 20, 1500)) << i;
  }
  // The torn half record was cut, and the journal now holds exactly messages 1..50.
  StatusOr<JournalScan> scan = ScanJournalFile(journal);
  ASSERT_TRUE(scan.ok()) << scan.status().ToString();
  EXPECT_EQ(scan->records, 50u);
  EXPECT_EQ(scan->torn_bytes, 0u);
}

// An ICL-NUIM-like camera (fy < 0) with TUM fr1's distortion: the server takes it as
// announced, journals it, and restores it on --resume, where the agent is known again.
TEST(ServerTest, NegativeFocalLengthAndDistortionSurviveTheHandshakeAndResume) {
  testing::TempDir dir;
  SessionCamera camera = TestCamera();
  camera.fy = -480.0;
  camera.distortion = {0.262383, -0.953104, -0.005358, 0.002628, 1.163314};
  AgentLinkOptions link_options = LinkOptions(0, "icl");
  link_options.camera = camera;
  {
    RecordingConsumer consumer;
    Server server(LoopbackOptions(dir.File("journal")), &consumer);
    ASSERT_TRUE(server.Start().ok());
    link_options.server = "127.0.0.1:" + std::to_string(server.port());
    auto link = AgentLink::Create(link_options);
    ASSERT_TRUE(link.ok()) << link.status().ToString();
    SendAll(link->get(), 1, 0, 3);
    ASSERT_TRUE((*link)->Flush(10).ok());
    link->reset();
    server.Stop();
    ASSERT_EQ(consumer.known().count("icl"), 1u);
    EXPECT_EQ(consumer.known().at("icl").camera, camera);
  }
  RecordingConsumer consumer;
  ServerOptions options = LoopbackOptions(dir.File("journal"));
  options.resume = true;
  Server server(options, &consumer);
  ASSERT_TRUE(server.Start().ok());
  ASSERT_EQ(consumer.known().count("icl"), 1u);
  EXPECT_EQ(consumer.known().at("icl").camera, camera);
  EXPECT_EQ(consumer.total(), 3u);
  server.Stop();
}

TEST(ServerTest, LinkSpillsToDiskWhileTheServerIsAwayAndDeliversInOrder) {
  testing::TempDir dir;
  // A free port for a server that starts later.
  std::uint16_t port;
  {
    bool loopback;
    UniqueFd probe = ListenTcp(HostPort{"127.0.0.1", 0}, 1, &loopback).value();
    port = LocalPort(probe.get()).value();
  }
  AgentLinkOptions o = LinkOptions(port, "spiller");
  o.memory_limit_bytes = 10000;
  o.spill_dir = dir.File("spill");
  auto link = AgentLink::Create(o).value();
  const std::vector<Bytes> sent = SendAll(link.get(), 2, 0, 40);
  const AgentLinkStats before = link->stats();
  EXPECT_EQ(before.acked, 0u);
  EXPECT_LE(before.memory_bytes, 10000u + sent[0].size());
  EXPECT_GT(before.spilled, 30u);
  EXPECT_GT(before.spill_bytes, 0u);

  RecordingConsumer consumer;
  ServerOptions so = LoopbackOptions(dir.File("journal"));
  so.listen = "127.0.0.1:" + std::to_string(port);
  Server server(so, &consumer);
  ASSERT_TRUE(server.Start().ok());
  ASSERT_TRUE(link->Flush(20).ok());
  const AgentLinkStats after = link->stats();
  EXPECT_EQ(after.acked, 40u);
  EXPECT_EQ(after.spill_bytes, 0u);
  link.reset();
  server.Stop();
  const auto got = consumer.messages().at("spiller");
  ASSERT_EQ(got.size(), sent.size());
  for (std::size_t i = 0; i < sent.size(); ++i) EXPECT_EQ(got[i].payload, sent[i]) << i;
}

TEST(ServerTest, AgentsBeyondTheLimitAreRefusedKnownOnesStillServed) {
  testing::TempDir dir;
  RecordingConsumer consumer;
  ServerOptions o = LoopbackOptions(dir.File("journal"));
  o.max_agents = 2;
  Server server(o, &consumer);
  ASSERT_TRUE(server.Start().ok());
  for (const char* name : {"a", "b"}) {
    AgentLinkOptions lo = LinkOptions(server.port(), name);
    lo.identity_file = dir.File(std::string(name) + ".identity");
    auto link = AgentLink::Create(lo).value();
    SendAll(link.get(), 0, 0, 1);
    ASSERT_TRUE(link->Flush(10).ok());
  }
  // A third name: refused with "server full" (a retryable refusal: the link keeps trying).
  nettest::RawClient c;
  HelloMessage hello;
  hello.name = "c";
  hello.camera = TestCamera();
  const nettest::RawAnswer answer = nettest::RawHandshakeWith(&c, server.port(), hello);
  ASSERT_TRUE(answer.bye.has_value());
  EXPECT_EQ(answer.bye->reason, ByeReason::kServerFull);
  EXPECT_NE(answer.bye->text.find("--max-agents"), std::string::npos) << answer.bye->text;
  // A registered agent reconnecting is still welcome.
  AgentLinkOptions lo = LinkOptions(server.port(), "a");
  lo.identity_file = dir.File("a.identity");
  auto again = AgentLink::Create(lo).value();
  SendAll(again.get(), 0, 1, 2);
  EXPECT_TRUE(again->Flush(10).ok());
  again.reset();
  server.Stop();
  EXPECT_EQ(consumer.messages().at("a").size(), 2u);
}

// Holds the first message until released, so that everything behind it backs up.
class StuckConsumer : public RecordingConsumer {
 public:
  void OnMessage(DeliveredMessage m) override {
    {
      std::unique_lock<std::mutex> lock(mutex_);
      released_cv_.wait(lock, [&] { return released_; });
    }
    RecordingConsumer::OnMessage(std::move(m));
  }
  void Release() {
    std::lock_guard<std::mutex> lock(mutex_);
    released_ = true;
    released_cv_.notify_all();
  }

 private:
  std::mutex mutex_;
  std::condition_variable released_cv_;
  bool released_ = false;
};

TEST(ServerTest, ASlowConsumerStopsTheServerReadingInsteadOfBuffering) {
  testing::TempDir dir;
  StuckConsumer consumer;
  ServerOptions o = LoopbackOptions(dir.File("journal"));
  o.max_payload_bytes = 64 << 10;
  o.per_agent_memory_bytes = 128 << 10;
  o.journal_queue = 2;
  o.delivery_queue = 2;
  Server server(o, &consumer);
  ASSERT_TRUE(server.Start().ok());
  nettest::RawClient c;
  const std::optional<WelcomeMessage> welcome = nettest::RawHandshake(&c, server.port(), "flood");
  ASSERT_TRUE(welcome.has_value());
  // 32 MB of keyframes: far more than the socket buffers hold. The send gives up after 5 s
  // once the server has stopped reading.
  const Bytes message = SyntheticKeyframe(3, 0, 20, 16000);
  Bytes stream;
  for (int i = 1; i <= 2000; ++i) AppendDataFrame(16, i, message, &stream);
  EXPECT_FALSE(c.SendBytes(stream));
  // What the server took in is bounded by its queues and the per-agent limit, not by what
  // the agent sent: 2 delivery + 2 journal queue entries + the batch in progress + 128 kB in
  // flight + one 256 kB read, about 30 messages of 16 kB.
  const AgentTraffic t = server.stats().agent(welcome->agent);
  EXPECT_LT(t.keyframes.count, 40u);
  EXPECT_GT(t.keyframes.count, 0u);
  consumer.Release();
  c.Close();
  server.Stop();
  // Released, the server read on until the connection closed; whatever it accepted, it
  // delivered.
  EXPECT_EQ(consumer.total(), server.stats().agent(welcome->agent).keyframes.count);
}

TEST(ServerTest, AServerWithoutTheOldJournalContinuesAfterTheGap) {
  testing::TempDir dir;
  RecordingConsumer first_consumer;
  Server first(LoopbackOptions(dir.File("journal1")), &first_consumer);
  ASSERT_TRUE(first.Start().ok());
  const std::uint16_t port = first.port();
  auto link = AgentLink::Create(LinkOptions(port, "robot")).value();
  SendAll(link.get(), 4, 0, 10);
  ASSERT_TRUE(link->Flush(10).ok());
  first.Stop();
  // Restarted on the same port but with a fresh folder (the operator forgot --resume): the
  // acknowledged messages 1..10 are not there, and the link no longer has them.
  RecordingConsumer consumer;
  ServerOptions o = LoopbackOptions(dir.File("journal2"));
  o.listen = "127.0.0.1:" + std::to_string(port);
  Server second(o, &consumer);
  ASSERT_TRUE(second.Start().ok());
  SendAll(link.get(), 4, 10, 15);
  ASSERT_TRUE(link->Flush(10).ok()) << link->stats().last_error;
  link.reset();
  second.Stop();
  const auto got = consumer.messages().at("robot");
  ASSERT_EQ(got.size(), 5u);
  for (int i = 0; i < 5; ++i) {
    EXPECT_EQ(got[i].seq, static_cast<std::uint64_t>(11 + i));
    EXPECT_EQ(got[i].payload, SyntheticKeyframe(4, 10 + i, 20, 1500));
  }
  EXPECT_EQ(second.stats().counter("sequence_gaps"), 1u);
}

TEST(ServerTest, RefusesNonLoopbackWithoutKey) {
  testing::TempDir dir;
  RecordingConsumer consumer;
  ServerOptions o = LoopbackOptions(dir.File("journal"));
  o.listen = "0.0.0.0:0";
  Server server(o, &consumer);
  const Status s = server.Start();
  EXPECT_EQ(s.code(), StatusCode::kPermissionDenied);
  EXPECT_NE(s.message().find("--psk-file"), std::string::npos);
}

}  // namespace
}  // namespace ccmd
