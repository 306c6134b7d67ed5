// The six gaps an attack run found in protocol version 1, each as an attack: every one gets
// a clear refusal, and the honest agent is unaffected with nothing lost.
//   1. another instance announcing an agent's name (and an absurd resume point)
//   2. a frame header followed by a byte now and then, inside a session
//   3. --resume with a smaller frame limit than the journal was written with
//   4. keyless local processes registering names to fill every agent slot
//   5. a man in the middle forging an acknowledgement, or injecting a keyframe
//   6. a storm of refused connections against the log

#include <sys/socket.h>

#include <atomic>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/net/agent_link.h"
#include "libccmd/net/journal.h"
#include "libccmd/net/refusal_log.h"
#include "libccmd/net/server.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/json.h"
#include "proto/crc32c.h"
#include "tests/net/net_test_util.h"
#include "tests/net/server_process.h"
#include "tests/net/tamper_proxy.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using nettest::Bytes;
using nettest::RawAnswer;
using nettest::RawClient;
using nettest::RecordingConsumer;
using nettest::SyntheticKeyframe;
using nettest::TestCamera;
using nettest::TestIdentity;
using nettest::WireFrame;

const std::string kKey = "the deployment key 0123456789";

std::uint64_t SeqOf(WireFrame& f) {
  std::uint64_t seq = 0;
  for (int i = 7; i >= 0; --i) seq = (seq << 8) | f.payload()[i];
  return seq;
}

class TrustTest : public ::testing::Test {
 protected:
  ServerOptions Options() {
    ServerOptions o;
    o.listen = "127.0.0.1:0";
    o.journal_dir = dir_.File("journal");
    o.psk = kKey;
    o.fsync = false;
    o.handshake_timeout_s = 1.0;
    o.idle_timeout_s = 2.0;
    o.heartbeat_interval_s = 0.5;
    return o;
  }
  void StartServer(const ServerOptions& o) {
    consumer_ = std::make_unique<RecordingConsumer>();
    server_ = std::make_unique<Server>(o, consumer_.get());
    ASSERT_TRUE(server_->Start().ok());
  }
  AgentLinkOptions Link(const std::string& name, std::uint16_t port = 0) {
    AgentLinkOptions o;
    o.server = "127.0.0.1:" + std::to_string(port ? port : server_->port());
    o.name = name;
    o.camera = TestCamera();
    o.psk = kKey;
    o.identity_file = dir_.File(name + ".identity");
    o.backoff_initial_s = 0.01;
    o.backoff_max_s = 0.1;
    return o;
  }
  static void Send(AgentLink* link, int agent, int from, int to, std::size_t rgbd_bytes = 0) {
    for (int i = from; i < to; ++i) {
      ASSERT_TRUE(
          link->Send(MessageType::kKeyframe, SyntheticKeyframe(agent, i, 40, rgbd_bytes)).ok());
    }
  }
  // The consumer holds exactly messages 1..n of `name`, as agent `agent` made them.
  void ExpectExactly(const std::string& name, int agent, int n, std::size_t rgbd_bytes = 0) {
    const auto messages = consumer_->messages();
    ASSERT_EQ(messages.count(name), 1u) << name;
    const auto& got = messages.at(name);
    ASSERT_EQ(got.size(), static_cast<std::size_t>(n)) << name;
    for (int i = 0; i < n; ++i) {
      EXPECT_EQ(got[i].seq, static_cast<std::uint64_t>(i + 1));
      EXPECT_EQ(got[i].payload, SyntheticKeyframe(agent, i, 40, rgbd_bytes)) << name << " " << i;
    }
  }

  testing::TempDir dir_;
  std::unique_ptr<RecordingConsumer> consumer_;
  std::unique_ptr<Server> server_;
};

// 1. An authenticated client (it has the deployment key) announces the honest agent's name,
// not fresh, with a resume point of 10^12.
TEST_F(TrustTest, AnotherInstanceCannotTakeOverANameNorLearnAboutIt) {
  StartServer(Options());
  auto honest = AgentLink::Create(Link("robot")).value();
  Send(honest.get(), 0, 0, 20);
  ASSERT_TRUE(honest->Flush(10).ok());
  std::string refusals[2];
  for (int variant = 0; variant < 2; ++variant) {
    RawClient attacker;
    attacker.identity = TestIdentity(99);
    HelloMessage hello;
    hello.name = "robot";
    hello.camera = TestCamera();
    if (variant == 1) hello.camera.fx = 600;  // and with another camera
    hello.fresh = false;
    hello.first_seq = hello.next_seq = 1'000'000'000'000ull;
    const RawAnswer answer = nettest::RawHandshakeWith(&attacker, server_->port(), hello, kKey);
    EXPECT_FALSE(answer.welcome.has_value());
    ASSERT_TRUE(answer.bye.has_value());
    EXPECT_EQ(answer.bye->reason, ByeReason::kRefused);
    EXPECT_EQ(answer.bye->text.find("525"), std::string::npos) << answer.bye->text;
    refusals[variant] = answer.bye->text;
  }
  // The same words whatever the attacker announced: it learns nothing about the agent.
  EXPECT_EQ(refusals[0], refusals[1]);
  EXPECT_EQ(server_->stats().counter("refused_identity"), 2u);
  // The honest agent never noticed: one session, and it goes on from message 21.
  Send(honest.get(), 0, 20, 40);
  ASSERT_TRUE(honest->Flush(10).ok()) << honest->stats().last_error;
  EXPECT_EQ(honest->stats().sessions, 1u);
  EXPECT_EQ(honest->stats().refused, 0u);
  honest.reset();
  server_->Stop();
  ExpectExactly("robot", 0, 40);
}

// Sends one byte every 0.2 s until the server closes the connection (at most `max_s`);
// returns what the server sent and the seconds it took.
double DribbleUntilClosed(RawClient* c, double max_s, std::vector<Frame>* frames) {
  const double start = MonotonicSeconds();
  FrameDecoder decoder;
  std::vector<std::uint8_t> buffer(4096);
  while (MonotonicSeconds() - start < max_s) {
    const std::uint8_t byte = 0x42;
    if (!WriteSome(c->fd(), &byte, 1).ok()) break;
    pollfd p{c->fd(), POLLIN, 0};
    ::poll(&p, 1, 200);  // the attacker's pace: waits for an answer at most 0.2 s
    StatusOr<std::size_t> n = ReadSome(c->fd(), buffer.data(), buffer.size());
    if (!n.ok()) break;
    decoder.Feed(ByteSpan(buffer.data(), *n), frames).IgnoreError();
    if (nettest::FindBye(*frames)) break;
  }
  return MonotonicSeconds() - start;
}

// 2. After authentication, a frame header announcing 16 MiB, then one byte now and then.
TEST_F(TrustTest, AFrameDribbledAfterItsHeaderIsCutAtItsDeadline) {
  ServerOptions o = Options();
  o.frame_timeout_s = 1.0;
  StartServer(o);
  auto honest = AgentLink::Create(Link("honest")).value();
  Send(honest.get(), 1, 0, 10);
  RawClient slow;
  slow.identity = TestIdentity(7);
  ASSERT_TRUE(nettest::RawHandshake(&slow, server_->port(), "slow", kKey).has_value());
  WireFrame header = nettest::ForgeFrame(16, Bytes(8, 1), /*tagged=*/true);
  header.PutLe32(8, (16u << 20) - 64);  // a payload just under the 16 MiB limit
  header.PutLe32(16, Crc32c(header.bytes.data(), 16));
  ASSERT_TRUE(slow.SendBytes(Bytes(header.bytes.begin(), header.bytes.begin() + kFrameHeaderSize)));
  std::vector<Frame> frames;
  const double seconds = DribbleUntilClosed(&slow, 15, &frames);
  const std::optional<ByeMessage> bye = nettest::FindBye(frames);
  ASSERT_TRUE(bye.has_value()) << "still connected after " << seconds << " s";
  EXPECT_EQ(bye->reason, ByeReason::kTimeout);
  EXPECT_NE(bye->text.find("frame"), std::string::npos) << bye->text;
  EXPECT_LT(seconds, 15);
  EXPECT_EQ(server_->stats().counter("frame_timeouts"), 1u);
  Send(honest.get(), 1, 10, 20);
  ASSERT_TRUE(honest->Flush(10).ok());
  EXPECT_EQ(honest->stats().sessions, 1u);
  honest.reset();
  server_->Stop();
  ExpectExactly("honest", 1, 20);
}

// 3. A journal of 100 kB records, resumed by a server whose frame limit is 64 KiB.
TEST_F(TrustTest, ResumeWithASmallerFrameLimitReadsTheJournalWithItsOwn) {
  constexpr std::size_t kRgbd = 100000;
  ServerOptions first = Options();
  first.max_payload_bytes = 256 << 10;
  StartServer(first);
  {
    auto link = AgentLink::Create(Link("robot")).value();
    Send(link.get(), 2, 0, 30, kRgbd);
    ASSERT_TRUE(link->Flush(10).ok());
  }
  server_->Stop();
  ServerOptions second = Options();
  second.resume = true;
  second.max_payload_bytes = 64 << 10;
  StartServer(second);
  EXPECT_EQ(consumer_->total(), 30u);  // replayed before Start returned
  // The same agent goes on under the new limit.
  auto link = AgentLink::Create(Link("robot")).value();
  for (int i = 30; i < 35; ++i) {
    ASSERT_TRUE(link->Send(MessageType::kKeyframe, SyntheticKeyframe(2, i, 40, kRgbd / 10)).ok());
  }
  ASSERT_TRUE(link->Flush(10).ok()) << link->stats().last_error;
  link.reset();
  server_->Stop();
  const auto got = consumer_->messages().at("robot");
  ASSERT_EQ(got.size(), 35u);
  for (int i = 0; i < 35; ++i) {
    EXPECT_EQ(got[i].seq, static_cast<std::uint64_t>(i + 1));
    EXPECT_EQ(got[i].payload, SyntheticKeyframe(2, i, 40, i < 30 ? kRgbd : kRgbd / 10)) << i;
  }
  StatusOr<JournalScan> scan = ScanJournalFile(dir_.File("journal/" + JournalFileName(AgentId(1))));
  ASSERT_TRUE(scan.ok()) << scan.status().ToString();
  EXPECT_EQ(scan->records, 35u);
  EXPECT_EQ(scan->torn_bytes, 0u);
}

// 4. Without a key, local processes register names to fill every agent slot.
TEST_F(TrustTest, KeylessNamesFreeTheirSlotsAndAFullServerSaysSo) {
  ServerOptions o = Options();
  o.psk.clear();
  o.max_agents = 4;
  o.slot_timeout_s = 0.5;
  StartServer(o);
  // Names that register and leave without sending anything hold no slot afterwards.
  for (int i = 0; i < 8; ++i) {
    RawClient c;
    c.identity = TestIdentity(100 + i);
    ASSERT_TRUE(nettest::RawHandshake(&c, server_->port(), "probe" + std::to_string(i)))
        << "probe " << i;
  }
  // Four squatters send a keyframe each and stay: every slot is in use.
  std::vector<std::unique_ptr<RawClient>> squatters;
  for (int i = 0; i < 4; ++i) {
    auto c = std::make_unique<RawClient>();
    c->identity = TestIdentity(i);
    ASSERT_TRUE(nettest::RawHandshake(c.get(), server_->port(), "squat" + std::to_string(i)));
    ASSERT_TRUE(c->SendData(16, 1, SyntheticKeyframe(10 + i, 0)));
    squatters.push_back(std::move(c));
  }
  ASSERT_TRUE(consumer_->WaitForTotal(4, 10));
  RawClient late_raw;
  HelloMessage hello;
  hello.name = "late-raw";
  hello.camera = TestCamera();
  const RawAnswer full = nettest::RawHandshakeWith(&late_raw, server_->port(), hello);
  ASSERT_TRUE(full.bye.has_value());
  EXPECT_EQ(full.bye->reason, ByeReason::kServerFull);
  EXPECT_NE(full.bye->text.find("--max-agents"), std::string::npos) << full.bye->text;
  EXPECT_NE(full.bye->text.find("--slot-timeout"), std::string::npos) << full.bye->text;
  // They leave; half a second later their slots are free, and the honest agent, retrying
  // meanwhile, gets one.
  squatters.clear();
  AgentLinkOptions lo = Link("late");
  lo.psk.clear();
  auto late = AgentLink::Create(lo).value();
  Send(late.get(), 3, 0, 5);
  ASSERT_TRUE(late->Flush(20).ok()) << late->stats().last_error;
  // What the squatters sent is kept, and they are still served when they come back.
  RawClient back;
  back.identity = TestIdentity(0);
  const std::optional<WelcomeMessage> welcome =
      nettest::RawHandshake(&back, server_->port(), "squat0");
  ASSERT_TRUE(welcome.has_value());
  EXPECT_EQ(welcome->last_stored_seq, 1u);
  back.Close();
  late.reset();
  server_->Stop();
  ExpectExactly("late", 3, 5);
  for (int i = 0; i < 4; ++i) {
    EXPECT_EQ(consumer_->messages().at("squat" + std::to_string(i)).size(), 1u);
  }
  EXPECT_EQ(consumer_->messages().count("probe0"), 0u);
}

// 5a. A man in the middle swallows message 5 and acknowledges it in the server's name.
TEST_F(TrustTest, AForgedAcknowledgementIsDetectedAndNothingIsLost) {
  StartServer(Options());
  std::atomic<int> forged{0};
  nettest::TamperProxy proxy([&](bool from_agent, WireFrame f, std::vector<WireFrame>* forward,
                                 std::vector<WireFrame>* back) {
    if (from_agent && f.type() == 16 && SeqOf(f) == 5 && forged.load() == 0) {
      ++forged;
      back->push_back(nettest::ForgeFrame(static_cast<std::uint8_t>(SessionType::kAck),
                                          SerializeAck({5}), f.tagged()));
      return;
    }
    forward->push_back(std::move(f));
  });
  ASSERT_TRUE(proxy.Start(server_->port()));
  auto link = AgentLink::Create(Link("robot", proxy.port())).value();
  Send(link.get(), 4, 0, 20);
  ASSERT_TRUE(link->Flush(20).ok()) << link->stats().last_error;
  EXPECT_EQ(forged.load(), 1);
  EXPECT_GE(link->stats().auth_failures, 1u);
  EXPECT_GE(link->stats().sessions, 2u);  // that connection was closed, the next one resent
  link.reset();
  proxy.Stop();
  server_->Stop();
  ExpectExactly("robot", 4, 20);
}

// 5c. A man in the middle alters the agent's Hello (its camera): the proof and the session
// keys bind the hello as sent, so the server refuses it as a failed authentication before
// registering anything, and the agent reports that refusal instead of streaming.
TEST_F(TrustTest, AnAlteredHelloIsRefusedBeforeAnythingIsRegistered) {
  StartServer(Options());
  std::atomic<int> altered{0};
  nettest::TamperProxy proxy([&](bool from_agent, WireFrame f, std::vector<WireFrame>* forward,
                                 std::vector<WireFrame>*) {
    if (from_agent && f.type() == static_cast<std::uint8_t>(SessionType::kHello)) {
      ++altered;
      f.payload()[3 + 5 + 6] ^= 0x10;  // fx (after version, flags, length, "robot"): 525 -> 1050
      f.Reseal();
    }
    forward->push_back(std::move(f));
  });
  ASSERT_TRUE(proxy.Start(server_->port()));
  auto link = AgentLink::Create(Link("robot", proxy.port())).value();
  Send(link.get(), 6, 0, 3);
  const Status flushed = link->Flush(20);
  EXPECT_EQ(flushed.code(), StatusCode::kPermissionDenied) << flushed.ToString();
  EXPECT_EQ(link->stats().acked, 0u);
  link.reset();
  proxy.Stop();
  server_->Stop();
  EXPECT_GE(altered.load(), 1);
  EXPECT_EQ(server_->stats().counter("refused_wrong_key"),
            static_cast<std::uint64_t>(altered.load()));
  EXPECT_TRUE(consumer_->messages().empty());
  EXPECT_FALSE(FileExists(dir_.File("journal/" + JournalFileName(AgentId(1)))));
}

// 5b. A man in the middle injects a keyframe of its own as the agent's message 4.
TEST_F(TrustTest, AnInjectedKeyframeIsRefusedAndItsConnectionClosed) {
  StartServer(Options());
  std::atomic<int> injected{0};
  nettest::TamperProxy proxy(
      [&](bool from_agent, WireFrame f, std::vector<WireFrame>* forward, std::vector<WireFrame>*) {
        const bool after_third = from_agent && f.type() == 16 && SeqOf(f) == 3;
        forward->push_back(std::move(f));
        if (after_third && injected.load() == 0) {
          ++injected;
          WireFrame forged;
          AppendDataFrame(16, 4, SyntheticKeyframe(66, 4), &forged.bytes, kFrameTagged);
          forged.bytes.insert(forged.bytes.end(), kFrameTagSize, 0x5A);
          forward->push_back(std::move(forged));
        }
      });
  ASSERT_TRUE(proxy.Start(server_->port()));
  auto link = AgentLink::Create(Link("robot", proxy.port())).value();
  Send(link.get(), 5, 0, 12);
  ASSERT_TRUE(link->Flush(20).ok()) << link->stats().last_error;
  EXPECT_EQ(injected.load(), 1);
  link.reset();
  proxy.Stop();
  server_->Stop();
  EXPECT_EQ(server_->stats().counter("frame_auth_failures"), 1u);
  EXPECT_EQ(server_->stats().counter("closed_frame_authentication_failed"), 1u);
  ExpectExactly("robot", 5, 12);  // the agent's own messages, none of the forger's
}

// 6a. The refusal log: per source, the first refusal of an interval in full, then one
// summary line with the count per reason.
TEST(RefusalLogTest, SummarisesPerSourceAndInterval) {
  std::vector<std::string> lines;
  RefusalLog log({.interval_s = 10, .max_sources = 2, .sink = [&](const std::string& line) {
                    lines.push_back(line);
                  }});
  for (int i = 0; i < 1000; ++i) {
    log.Note("10.0.0.1", "10.0.0.1:" + std::to_string(1000 + i),
             i % 4 ? "time-out" : "protocol error", "details " + std::to_string(i), 0.001 * i);
  }
  log.Note("10.0.0.2", "10.0.0.2:5", "time-out", "other", 2);
  log.Note("10.0.0.3", "10.0.0.3:5", "time-out", "third", 3);  // beyond max_sources
  ASSERT_EQ(lines.size(), 2u);
  EXPECT_EQ(lines[0], "refused connection from 10.0.0.1:1000: details 0");
  EXPECT_EQ(lines[1], "refused connection from 10.0.0.2:5: other");
  log.Flush(9.9);
  EXPECT_EQ(lines.size(), 2u);  // no interval has ended yet
  log.Flush(10.0);              // 10.0.0.1's has
  ASSERT_EQ(lines.size(), 3u);
  EXPECT_EQ(lines[2],
            "10.0.0.1: 999 more connection(s) refused in the last 10.0 s (249 protocol error, "
            "750 time-out)");
  log.Note("10.0.0.1", "10.0.0.1:9", "time-out", "again", 11);  // a new interval: in full
  log.Flush(11, /*all=*/true);
  ASSERT_EQ(lines.size(), 5u);
  EXPECT_EQ(lines[3], "refused connection from 10.0.0.1:9: again");
  EXPECT_EQ(lines[4], "other sources: 1 more connection(s) refused in the last 8.0 s (1 time-out)");
}

// 6b. A storm of 400 refused connections against a real server process: a handful of lines.
TEST(TrustStormTest, RefusedConnectionsDoNotFloodTheLog) {
  testing::TempDir dir;
  const std::string log = dir.File("server.log");
  nettest::ServerProcess server;
  ASSERT_TRUE(server.Start({"--listen", "127.0.0.1:0", "--journal", dir.File("journal"),
                            "--handshake-timeout", "0.2", "--no-dense"},
                           log));
  // 20 silent connections (closed after the 0.2 s handshake time-out) and 380 that send
  // garbage (refused at once).
  std::vector<std::unique_ptr<RawClient>> silent;
  for (int i = 0; i < 20; ++i) {
    silent.push_back(std::make_unique<RawClient>());
    ASSERT_TRUE(silent.back()->Connect(server.port()));
  }
  const std::string http = "GET / HTTP/1.1\r\n\r\n";
  for (int i = 0; i < 380; ++i) {
    RawClient c;
    ASSERT_TRUE(c.Connect(server.port()));
    ASSERT_TRUE(c.SendBytes(Bytes(http.begin(), http.end())));
    std::vector<Frame> frames;
    ASSERT_TRUE(c.ReadUntilClosed(&frames, 10));
  }
  for (auto& c : silent) {
    std::vector<Frame> frames;
    ASSERT_TRUE(c->ReadUntilClosed(&frames, 10));
  }
  server.Signal(SIGTERM);
  EXPECT_EQ(server.Wait(), 0);
  std::ifstream in(log);
  int lines = 0, refusal_lines = 0;
  for (std::string line; std::getline(in, line);) {
    if (line.find("options_writer.h") != std::string::npos) continue;  // the start-up record
    ++lines;
    refusal_lines += line.find("refused") != std::string::npos;
  }
  // The first refusal in full, then one summary of the other 399 (by reason).
  EXPECT_LE(refusal_lines, 3) << "of " << lines << " lines";
  EXPECT_LT(lines, 40);
}

// An agent whose messages the server refuses says so and exits non-zero, with the counts in
// its statistics (it used to print "0 messages not acknowledged" and exit 0).
TEST(TrustCliTest, AnAgentWhoseNameIsTakenExitsNonZeroAndSaysSo) {
  testing::TempDir dir;
  nettest::ServerProcess server;
  ASSERT_TRUE(
      server.Start({"--listen", "127.0.0.1:0", "--journal", dir.File("journal"), "--no-dense"},
                   dir.File("server.log")));
  RawClient owner;
  owner.identity = TestIdentity(1);
  HelloMessage hello;
  hello.name = "robot";
  hello.camera = {525, 525, 319.5, 239.5, 640, 480, 5000};
  ASSERT_TRUE(nettest::RawHandshakeWith(&owner, server.port(), hello).welcome.has_value());
  ASSERT_TRUE(owner.SendData(16, 1, SyntheticKeyframe(1, 0)));
  std::optional<Frame> ack = owner.ReadFrame(10);
  ASSERT_TRUE(ack.has_value());
  owner.Close();

  std::string out;
  const int code = testing::RunCommand(
      testing::ProgramPath("ccmd_agent") + " --source synth:frames=25,seed=2 --synchronous" +
          " --server 127.0.0.1:" + std::to_string(server.port()) + " --name robot --spill-dir " +
          dir.File("spill") + " --stats " + dir.File("stats.json") + " --flush-timeout 20",
      &out);
  EXPECT_EQ(code, 3) << out;
  EXPECT_NE(out.find("refused by the link"), std::string::npos) << out;
  StatusOr<Json> stats = ReadJsonFile(dir.File("stats.json"));
  ASSERT_TRUE(stats.ok()) << stats.status().ToString();
  const Json& link = *stats->Get("link");
  EXPECT_GT(link.Get("refused")->number() + link.Get("unacked")->number(), 0);
  EXPECT_EQ(link.Get("acked")->number(), 0);
  EXPECT_NE(link.Get("link_error")->string().find("belongs to an agent registered earlier"),
            std::string::npos)
      << link.Get("link_error")->string();
  server.Signal(SIGTERM);
  EXPECT_EQ(server.Wait(), 0);
}

}  // namespace
}  // namespace ccmd
