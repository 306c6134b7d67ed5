// Bad input: every kind of broken or hostile client gets its error (a Bye saying why, then
// a closed connection) while a well-behaved agent keeps being served.

#include <sys/socket.h>

#include <memory>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/net/agent_link.h"
#include "libccmd/net/psk.h"
#include "libccmd/net/server.h"
#include "proto/crc32c.h"
#include "tests/net/net_test_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using nettest::Bytes;
using nettest::FindBye;
using nettest::RawClient;
using nettest::RecordingConsumer;

const std::string kKey = "the deployment key 0123456789";

void PutLe32(Bytes* b, std::size_t at, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) (*b)[at + i] = static_cast<std::uint8_t>(v >> (8 * i));
}
void Reseal(Bytes* frame) { PutLe32(frame, 16, Crc32c(frame->data(), 16)); }

Bytes HelloFrame(const std::string& name, Nonce* nonce = nullptr) {
  HelloMessage h;
  h.name = name;
  h.camera = nettest::TestCamera();
  if (nonce) {
    for (int i = 0; i < 32; ++i) h.agent_nonce[i] = static_cast<std::uint8_t>(i * 3);
    *nonce = h.agent_nonce;
  }
  return EncodeSessionFrame(SessionType::kHello, SerializeHello(h));
}

class BadInputTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ServerOptions o;
    o.listen = "127.0.0.1:0";
    o.journal_dir = dir_.File("journal");
    o.psk = kKey;
    o.fsync = false;
    o.handshake_timeout_s = 0.5;
    o.idle_timeout_s = 1.5;  // the good agent's link heartbeats every 0.5 s
    o.heartbeat_interval_s = 0.5;
    o.max_payload_bytes = 64 << 10;
    o.per_agent_memory_bytes = 1 << 20;
    server_ = std::make_unique<Server>(o, &consumer_);
    ASSERT_TRUE(server_->Start().ok());
    // A good agent that sends throughout.
    AgentLinkOptions lo = Link("good");
    lo.psk = kKey;
    lo.identity_file = dir_.File("good.identity");
    good_ = AgentLink::Create(lo).value();
    SendGood(10);
  }
  void TearDown() override {
    // The good agent was never disturbed: everything arrives, once, in order.
    SendGood(10);
    ASSERT_TRUE(good_->Flush(10).ok());
    EXPECT_EQ(good_->stats().sessions, 1u);
    good_.reset();
    server_->Stop();
    const auto messages = consumer_.messages();
    ASSERT_EQ(messages.at("good").size(), static_cast<std::size_t>(sent_));
    for (int i = 0; i < sent_; ++i) {
      EXPECT_EQ(messages.at("good")[i].seq, static_cast<std::uint64_t>(i + 1));
      EXPECT_EQ(messages.at("good")[i].payload, nettest::SyntheticKeyframe(0, i));
    }
  }
  AgentLinkOptions Link(const std::string& name) {
    AgentLinkOptions o;
    o.server = "127.0.0.1:" + std::to_string(server_->port());
    o.name = name;
    o.camera = nettest::TestCamera();
    o.backoff_initial_s = 0.01;
    o.backoff_max_s = 0.05;
    return o;
  }
  void SendGood(int n) {
    for (int i = 0; i < n; ++i) {
      ASSERT_TRUE(good_->Send(MessageType::kKeyframe, nettest::SyntheticKeyframe(0, sent_)).ok());
      ++sent_;
    }
  }
  // Sends `bytes` on a fresh connection and returns the Bye the server answered with.
  std::optional<ByeMessage> Exchange(const Bytes& bytes, bool close_after = false) {
    RawClient c;
    EXPECT_TRUE(c.Connect(server_->port()));
    EXPECT_TRUE(c.SendBytes(bytes));
    if (close_after) ::shutdown(c.fd(), SHUT_WR);
    std::vector<Frame> frames;
    EXPECT_TRUE(c.ReadUntilClosed(&frames, 10)) << "the server did not close the connection";
    return FindBye(frames);
  }
  // Completes a correct handshake by hand; returns the Welcome.
  WelcomeMessage Handshake(RawClient* c, const std::string& name) {
    std::optional<WelcomeMessage> welcome = nettest::RawHandshake(c, server_->port(), name, kKey);
    EXPECT_TRUE(welcome.has_value());
    return welcome.value_or(WelcomeMessage{});
  }

  testing::TempDir dir_;
  RecordingConsumer consumer_;
  std::unique_ptr<Server> server_;
  std::unique_ptr<AgentLink> good_;
  int sent_ = 0;
};

TEST_F(BadInputTest, GarbageBytes) {
  const std::string http = "GET / HTTP/1.1\r\nHost: x\r\n\r\n";
  std::optional<ByeMessage> bye = Exchange(Bytes(http.begin(), http.end()));
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kProtocolError);
  EXPECT_NE(bye->text.find("magic"), std::string::npos) << bye->text;
}

TEST_F(BadInputTest, HugeLengthField) {
  Bytes frame = HelloFrame("x");
  PutLe32(&frame, 8, 0xFFFFFFF0u);
  Reseal(&frame);
  frame.resize(kFrameHeaderSize);
  std::optional<ByeMessage> bye = Exchange(frame);
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kLimitExceeded);
}

TEST_F(BadInputTest, TruncatedFrameThenClose) {
  Bytes frame = HelloFrame("x");
  frame.resize(frame.size() / 2);
  RawClient c;
  ASSERT_TRUE(c.Connect(server_->port()));
  ASSERT_TRUE(c.SendBytes(frame));
  ::shutdown(c.fd(), SHUT_WR);
  std::vector<Frame> frames;
  EXPECT_TRUE(c.ReadUntilClosed(&frames, 10));
  EXPECT_TRUE(frames.empty());  // nothing to say to a peer that left mid-frame
}

TEST_F(BadInputTest, WrongCrc) {
  Bytes frame = HelloFrame("x");
  frame.back() ^= 0x01;
  std::optional<ByeMessage> bye = Exchange(frame);
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kProtocolError);
  EXPECT_NE(bye->text.find("CRC"), std::string::npos) << bye->text;
}

TEST_F(BadInputTest, WrongVersion) {
  Bytes frame = HelloFrame("x");
  frame[4] = 1;  // an agent of protocol version 1
  Reseal(&frame);
  std::optional<ByeMessage> bye = Exchange(frame);
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kUnsupportedVersion);
}

TEST_F(BadInputTest, WrongKeyIsRefusedOnBothSides) {
  AgentLinkOptions o = Link("intruder");
  o.psk = "not the deployment key, sorry";
  auto link = AgentLink::Create(o).value();
  // The link may have failed already, in which case Send returns that error.
  link->Send(MessageType::kKeyframe, nettest::SyntheticKeyframe(9, 0)).status().IgnoreError();
  const Status s = link->Flush(10);
  EXPECT_EQ(s.code(), StatusCode::kPermissionDenied) << s.ToString();
  EXPECT_NE(s.message().find("authentication failed"), std::string::npos) << s.message();
  EXPECT_EQ(server_->stats().counter("refused_wrong_key"), 1u);
  EXPECT_FALSE(link->Send(MessageType::kKeyframe, {1}).ok());
}

TEST_F(BadInputTest, MissingKeyIsRefusedOnBothSides) {
  auto link = AgentLink::Create(Link("keyless")).value();
  // The link may have failed already, in which case Send returns that error.
  link->Send(MessageType::kKeyframe, nettest::SyntheticKeyframe(9, 0)).status().IgnoreError();
  const Status s = link->Flush(10);
  EXPECT_EQ(s.code(), StatusCode::kPermissionDenied) << s.ToString();
  EXPECT_NE(s.message().find("requires a pre-shared key"), std::string::npos) << s.message();
}

TEST_F(BadInputTest, SilentClientTimesOut) {
  RawClient c;
  ASSERT_TRUE(c.Connect(server_->port()));
  std::vector<Frame> frames;
  EXPECT_TRUE(c.ReadUntilClosed(&frames, 10));
  std::optional<ByeMessage> bye = FindBye(frames);
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kTimeout);
  EXPECT_EQ(server_->stats().counter("handshake_timeouts"), 1u);
}

TEST_F(BadInputTest, SilentSessionTimesOut) {
  RawClient c;
  Handshake(&c, "quiet");
  std::vector<Frame> frames;
  EXPECT_TRUE(c.ReadUntilClosed(&frames, 10));
  std::optional<ByeMessage> bye = FindBye(frames);
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kTimeout);
  EXPECT_EQ(server_->stats().counter("idle_timeouts"), 1u);
  // The server's own heartbeats kept coming while it waited.
  int heartbeats = 0;
  for (const Frame& f : frames)
    heartbeats += f.type == static_cast<std::uint8_t>(SessionType::kHeartbeat);
  EXPECT_GE(heartbeats, 1);
}

TEST_F(BadInputTest, HandshakeOutOfOrder) {
  std::optional<ByeMessage> bye =
      Exchange(EncodeSessionFrame(SessionType::kAuth, SerializeAuth(AuthMessage{})));
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kProtocolError);
}

TEST_F(BadInputTest, UnknownTypeInASession) {
  RawClient c;
  Handshake(&c, "raw");
  ASSERT_TRUE(c.SendSessionFrame(static_cast<SessionType>(9), Bytes{1, 2, 3}));
  std::vector<Frame> frames;
  EXPECT_TRUE(c.ReadUntilClosed(&frames, 10));
  std::optional<ByeMessage> bye = FindBye(frames);
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kProtocolError);
  EXPECT_NE(bye->text.find("type 9"), std::string::npos) << bye->text;
}

TEST_F(BadInputTest, DuplicatesDroppedGapsAndMalformedMessagesRefused) {
  RawClient c;
  const WelcomeMessage w = Handshake(&c, "raw");
  EXPECT_EQ(w.last_stored_seq, 0u);
  ASSERT_TRUE(c.SendData(16, 1, nettest::SyntheticKeyframe(5, 1)));
  ASSERT_TRUE(c.SendData(16, 1, nettest::SyntheticKeyframe(5, 1)));  // duplicate: dropped
  ASSERT_TRUE(c.SendData(16, 2, nettest::SyntheticKeyframe(5, 2)));
  // Acks are cumulative: wait for the one covering message 2.
  std::uint64_t acked = 0;
  while (acked < 2) {
    std::optional<Frame> f = c.ReadFrame(5);
    ASSERT_TRUE(f.has_value());
    ASSERT_TRUE(c.auth.Verify(*f).ok());
    if (f->type == static_cast<std::uint8_t>(SessionType::kAck)) {
      acked = ParseAck(f->payload)->last_stored_seq;
    }
  }
  ASSERT_TRUE(c.SendData(16, 3, Bytes{0xFF, 0xFF}));  // not a keyframe
  std::vector<Frame> rest;
  EXPECT_TRUE(c.ReadUntilClosed(&rest, 10));
  std::optional<ByeMessage> bye = FindBye(rest);
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kProtocolError);
  EXPECT_NE(bye->text.find("malformed keyframe"), std::string::npos) << bye->text;

  RawClient again;
  again.identity = c.identity;  // the same agent instance
  const WelcomeMessage w2 = Handshake(&again, "raw");
  EXPECT_EQ(w2.agent, w.agent);  // the same agent id for the same name
  EXPECT_EQ(w2.last_stored_seq, 2u);
  ASSERT_TRUE(again.SendData(16, 5, nettest::SyntheticKeyframe(5, 5)));
  std::vector<Frame> after_gap;
  EXPECT_TRUE(again.ReadUntilClosed(&after_gap, 10));
  bye = FindBye(after_gap);
  ASSERT_TRUE(bye.has_value());
  EXPECT_NE(bye->text.find("sequence gap"), std::string::npos) << bye->text;

  ASSERT_TRUE(consumer_.WaitForDisconnects("raw", 2, 10));
  const auto messages = consumer_.messages();
  ASSERT_EQ(messages.at("raw").size(), 2u);
  EXPECT_EQ(messages.at("raw")[1].payload, nettest::SyntheticKeyframe(5, 2));
  EXPECT_EQ(server_->stats().agent(w.agent).duplicates.count, 1u);
}

TEST_F(BadInputTest, OversizedDataFrame) {
  RawClient c;
  Handshake(&c, "big");
  ASSERT_TRUE(c.SendData(16, 1, Bytes(70 << 10, 0)));  // over the 64 KiB test limit
  std::vector<Frame> frames;
  EXPECT_TRUE(c.ReadUntilClosed(&frames, 10));
  std::optional<ByeMessage> bye = FindBye(frames);
  ASSERT_TRUE(bye.has_value());
  EXPECT_EQ(bye->reason, ByeReason::kLimitExceeded);
}

TEST_F(BadInputTest, DifferentCameraUnderAKnownNameIsRefused) {
  ASSERT_TRUE(good_->Flush(10).ok());  // "good" is registered
  AgentLinkOptions o = Link("good");
  o.psk = kKey;
  o.identity_file = dir_.File("good.identity");  // the same instance as "good"
  o.camera.fx = 600;
  auto link = AgentLink::Create(o).value();
  // The link may have failed already, in which case Send returns that error.
  link->Send(MessageType::kKeyframe, nettest::SyntheticKeyframe(9, 0)).status().IgnoreError();
  const Status s = link->Flush(10);
  EXPECT_EQ(s.code(), StatusCode::kInvalidArgument) << s.ToString();
  EXPECT_NE(s.message().find("camera"), std::string::npos);
}

}  // namespace
}  // namespace ccmd
