#include "libccmd/net/session_messages.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <string>
#include <vector>

#include <gtest/gtest.h>

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

void PutLe(Bytes* b, std::uint64_t v, int n) {
  for (int i = 0; i < n; ++i) b->push_back(static_cast<std::uint8_t>(v >> (8 * i)));
}
void PutF64(Bytes* b, double d) {
  std::uint64_t bits;
  std::memcpy(&bits, &d, 8);
  PutLe(b, bits, 8);
}

HelloMessage SampleHello() {
  HelloMessage h;
  h.fresh = false;
  h.name = "robot-1";
  h.camera = {517.3, 516.5, 318.6, 255.3, 640, 480, 5000};
  h.first_seq = 3;
  h.next_seq = 9;
  for (int i = 0; i < 32; ++i) h.agent_nonce[i] = static_cast<std::uint8_t>(i);
  return h;
}

TEST(SessionMessagesTest, HelloLayoutByteByByte) {
  Bytes expected = {2, 0, 7, 'r', 'o', 'b', 'o', 't', '-', '1'};  // version 2
  for (double v : {517.3, 516.5, 318.6, 255.3}) PutF64(&expected, v);
  PutLe(&expected, 640, 4);
  PutLe(&expected, 480, 4);
  PutF64(&expected, 5000);
  PutLe(&expected, 3, 8);
  PutLe(&expected, 9, 8);
  for (int i = 0; i < 32; ++i) expected.push_back(static_cast<std::uint8_t>(i));
  EXPECT_EQ(SerializeHello(SampleHello()), expected);
  EXPECT_EQ(expected.size(), 3u + 7 + 32 + 8 + 8 + 16 + 32);

  StatusOr<HelloMessage> parsed = ParseHello(expected);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->name, "robot-1");
  EXPECT_FALSE(parsed->fresh);
  EXPECT_EQ(parsed->camera, SampleHello().camera);
  EXPECT_EQ(parsed->first_seq, 3u);
  EXPECT_EQ(parsed->next_seq, 9u);
  EXPECT_EQ(parsed->agent_nonce, SampleHello().agent_nonce);
}

// ICL-NUIM's convention (fy < 0) is not an error, and lens distortion travels with a flag
// bit: 5 x f64 after the depth scale. Without distortion the layout is the one above.
TEST(SessionMessagesTest, HelloCarriesNegativeFocalLengthAndDistortion) {
  HelloMessage h = SampleHello();
  h.camera.fy = -480.0;
  StatusOr<HelloMessage> parsed = ParseHello(SerializeHello(h));
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera.fy, -480.0);
  EXPECT_FALSE(parsed->camera.HasDistortion());

  h.camera.distortion = {0.262383, -0.953104, -0.005358, 0.002628, 1.163314};
  const Bytes with = SerializeHello(h);
  ASSERT_EQ(with.size(), SerializeHello(SampleHello()).size() + 40);
  EXPECT_EQ(with[1], 0x02);  // not fresh, distortion present
  Bytes expected(with.begin(), with.begin() + 10 + 48);
  for (double k : h.camera.distortion) PutF64(&expected, k);
  EXPECT_TRUE(std::equal(expected.begin(), expected.end(), with.begin()));
  parsed = ParseHello(with);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, h.camera);
  EXPECT_EQ(parsed->first_seq, 3u);
  // The flag without the coefficients is truncated, not misread.
  Bytes flag_only = SerializeHello(SampleHello());
  flag_only[1] |= 0x02;
  EXPECT_EQ(ParseHello(flag_only).status().code(), StatusCode::kCorrupt);
}

// The sensor's depth noise travels with flag bit 2 as 2 x f64 after any distortion, so the
// server weighs the agent's depths as the agent does (rendered ICL-NUIM depth: 0.5 mm flat).
TEST(SessionMessagesTest, HelloCarriesTheDepthNoiseAfterTheDistortion) {
  HelloMessage h = SampleHello();
  h.camera.depth_sigma0 = 0.0005;
  Bytes with = SerializeHello(h);
  ASSERT_EQ(with.size(), SerializeHello(SampleHello()).size() + 16);
  EXPECT_EQ(with[1], 0x04);
  Bytes expected(with.begin(), with.begin() + 10 + 48);
  PutF64(&expected, 0.0005);
  PutF64(&expected, 0.0);
  EXPECT_TRUE(std::equal(expected.begin(), expected.end(), with.begin()));
  StatusOr<HelloMessage> parsed = ParseHello(with);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, h.camera);

  h.camera.distortion = {0.262383, -0.953104, -0.005358, 0.002628, 1.163314};
  h.camera.depth_sigma2 = 0.0015;
  with = SerializeHello(h);
  EXPECT_EQ(with[1], 0x06);
  parsed = ParseHello(with);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, h.camera);
  EXPECT_NE(DescribeCamera(h.camera).find("depth noise 0.00050 + 0.00150 z^2"), std::string::npos);

  // Nonsense is refused: no sigma0, a negative or non-finite term, metres of noise.
  for (const auto& [s0, s2] : std::vector<std::pair<double, double>>{{0, 0.002},
                                                                     {-0.001, 0},
                                                                     {0.001, -0.002},
                                                                     {std::nan(""), 0},
                                                                     {0.001, HUGE_VAL},
                                                                     {2.0, 0}}) {
    HelloMessage bad = SampleHello();
    bad.camera.depth_sigma0 = s0;
    bad.camera.depth_sigma2 = s2;
    EXPECT_EQ(ParseHello(SerializeHello(bad)).status().code(), StatusCode::kCorrupt) << s0 << s2;
  }
  // The flag with zeros, or without its two values, is refused.
  Bytes zeros = SerializeHello(SampleHello());
  zeros[1] |= 0x04;
  Bytes tail(zeros.begin() + 10 + 48, zeros.end());
  zeros.resize(10 + 48);
  PutF64(&zeros, 0.0);
  PutF64(&zeros, 0.0);
  zeros.insert(zeros.end(), tail.begin(), tail.end());
  EXPECT_EQ(ParseHello(zeros).status().code(), StatusCode::kCorrupt);
  Bytes flag_only = SerializeHello(SampleHello());
  flag_only[1] |= 0x04;
  EXPECT_EQ(ParseHello(flag_only).status().code(), StatusCode::kCorrupt);
}

TEST(SessionMessagesTest, HelloCarriesTheTrajectoryCameraLast) {
  // 7-Scenes: trajectories of the depth camera, 25 mm to the colour camera's left.
  HelloMessage h = SampleHello();
  h.camera.depth_sigma0 = 0.0005;
  h.camera.trajectory_t = {-0.025, 0, 0};
  const double half = std::sqrt(0.5);  // 90 degrees about z, for a rotation that shows
  h.camera.trajectory_q = {0, 0, half, half};
  const Bytes plain = SerializeHello(SampleHello());
  const Bytes with = SerializeHello(h);
  ASSERT_EQ(with.size(), plain.size() + 16 + 56);
  EXPECT_EQ(with[1], 0x0c);
  Bytes expected;
  for (const double v : {-0.025, 0.0, 0.0, 0.0, 0.0, half, half}) PutF64(&expected, v);
  EXPECT_TRUE(std::equal(expected.begin(), expected.end(), with.begin() + 10 + 48 + 16));
  StatusOr<HelloMessage> parsed = ParseHello(with);
  ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
  EXPECT_EQ(parsed->camera, h.camera);
  EXPECT_TRUE(parsed->camera.HasTrajectoryCamera());
  EXPECT_FALSE(SampleHello().camera.HasTrajectoryCamera());
  EXPECT_NE(DescribeCamera(h.camera).find("(-0.0250, 0.0000, 0.0000) m"), std::string::npos);

  // A quaternion that is no rotation, a camera metres away, or NaN is refused.
  for (const auto& [t, q] : std::vector<std::pair<std::array<double, 3>, std::array<double, 4>>>{
           {{0, 0, 0}, {0, 0, 0, 2}},
           {{0, 0, 0}, {0, 0, 0, 0}},
           {{1.5, 0, 0}, {0, 0, 0, 1}},
           {{std::nan(""), 0, 0}, {0, 0, 0, 1}},
           {{0, 0, 0}, {std::nan(""), 0, 0, 1}}}) {
    HelloMessage bad = SampleHello();
    bad.camera.trajectory_t = t;
    bad.camera.trajectory_q = q;
    EXPECT_EQ(ParseHello(SerializeHello(bad)).status().code(), StatusCode::kCorrupt)
        << t[0] << " " << q[3];
  }
  // The flag with the colour camera itself, or without its values, is refused.
  Bytes identity = SerializeHello(SampleHello());
  identity[1] |= 0x08;
  Bytes tail(identity.begin() + 10 + 48, identity.end());
  identity.resize(10 + 48);
  for (const double v : {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0}) PutF64(&identity, v);
  identity.insert(identity.end(), tail.begin(), tail.end());
  EXPECT_EQ(ParseHello(identity).status().code(), StatusCode::kCorrupt);
  Bytes flag_only = SerializeHello(SampleHello());
  flag_only[1] |= 0x08;
  EXPECT_EQ(ParseHello(flag_only).status().code(), StatusCode::kCorrupt);
}

TEST(SessionMessagesTest, HelloRejectsBadFields) {
  const Bytes good = SerializeHello(SampleHello());
  Bytes version = good;
  version[0] = 1;
  EXPECT_EQ(ParseHello(version).status().code(), StatusCode::kUnsupported);
  Bytes flags = good;
  flags[1] = 0x80;
  EXPECT_EQ(ParseHello(flags).status().code(), StatusCode::kCorrupt);
  Bytes name = good;
  name[3] = '/';  // "/obot-1" would become a path
  EXPECT_EQ(ParseHello(name).status().code(), StatusCode::kCorrupt);
  Bytes long_name = good;
  long_name[2] = 200;  // more bytes than present
  EXPECT_EQ(ParseHello(long_name).status().code(), StatusCode::kCorrupt);
  HelloMessage bad_range = SampleHello();
  bad_range.next_seq = 2;  // before first_seq
  EXPECT_FALSE(ParseHello(SerializeHello(bad_range)).ok());
  HelloMessage absurd = SampleHello();
  absurd.first_seq = absurd.next_seq = (1ull << 62) + 1;
  EXPECT_EQ(ParseHello(SerializeHello(absurd)).status().code(), StatusCode::kCorrupt);
  HelloMessage bad_camera = SampleHello();
  bad_camera.camera.fx = 0;
  EXPECT_FALSE(ParseHello(SerializeHello(bad_camera)).ok());
  bad_camera = SampleHello();
  bad_camera.camera.fy = std::nan("");
  EXPECT_FALSE(ParseHello(SerializeHello(bad_camera)).ok());
  bad_camera = SampleHello();
  bad_camera.camera.distortion[4] = HUGE_VAL;
  EXPECT_FALSE(ParseHello(SerializeHello(bad_camera)).ok());
  bad_camera = SampleHello();
  bad_camera.camera.depth_scale = -5000;
  EXPECT_FALSE(ParseHello(SerializeHello(bad_camera)).ok());
  Bytes trailing = good;
  trailing.push_back(0);
  EXPECT_EQ(ParseHello(trailing).status().code(), StatusCode::kCorrupt);
  for (std::size_t n = 0; n < good.size(); ++n) {
    EXPECT_FALSE(ParseHello(ByteSpan(good.data(), n)).ok()) << n;
  }
}

TEST(SessionMessagesTest, ChallengeAuthWelcomeAckByeLayouts) {
  ChallengeMessage c;
  c.key_required = true;
  c.server_nonce.fill(0xAB);
  Bytes expected_c = {1};
  expected_c.insert(expected_c.end(), 32, 0xAB);
  EXPECT_EQ(SerializeChallenge(c), expected_c);
  EXPECT_TRUE(ParseChallenge(expected_c)->key_required);
  expected_c[0] = 2;
  EXPECT_FALSE(ParseChallenge(expected_c).ok());

  // Auth: [32-byte proof, with a key] then the 32-byte masked identity.
  AuthMessage keyless;
  keyless.masked_identity.fill(0x11);
  EXPECT_EQ(SerializeAuth(keyless), Bytes(32, 0x11));
  AuthMessage keyed = keyless;
  keyed.proof.emplace();
  keyed.proof->fill(0x22);
  Bytes expected_a(32, 0x22);
  expected_a.insert(expected_a.end(), 32, 0x11);
  EXPECT_EQ(SerializeAuth(keyed), expected_a);
  StatusOr<AuthMessage> pa = ParseAuth(expected_a);
  ASSERT_TRUE(pa.ok());
  EXPECT_EQ(*pa->proof, *keyed.proof);
  EXPECT_EQ(pa->masked_identity, keyed.masked_identity);
  EXPECT_FALSE(ParseAuth(Bytes(32, 0x11))->proof.has_value());
  for (std::size_t n : {0, 31, 33, 63, 65}) EXPECT_FALSE(ParseAuth(Bytes(n, 0)).ok()) << n;

  WelcomeMessage w;
  w.agent = AgentId(0x0203);
  w.last_stored_seq = 0x1122334455667788ull;
  w.max_payload_bytes = 0x01000000;
  w.idle_timeout_ms = 30000;
  Bytes expected_w;
  w.last_stored_seq = 0x0122334455667788ull;  // within 2^62
  expected_w = {0, 0x03, 0x02};
  PutLe(&expected_w, 0x0122334455667788ull, 8);
  PutLe(&expected_w, 0x01000000, 4);
  PutLe(&expected_w, 30000, 4);
  EXPECT_EQ(SerializeWelcome(w), expected_w);
  StatusOr<WelcomeMessage> pw = ParseWelcome(expected_w);
  ASSERT_TRUE(pw.ok());
  EXPECT_EQ(pw->agent, AgentId(0x0203));
  EXPECT_EQ(pw->last_stored_seq, 0x0122334455667788ull);
  Bytes flagged = expected_w;
  flagged[0] = 1;  // version 1's "server proof" flag is gone: the tag proves the key
  EXPECT_FALSE(ParseWelcome(flagged).ok());

  EXPECT_EQ(SerializeAck({0x0102030405060708ull}),
            (Bytes{0x08, 0x07, 0x06, 0x05, 0x04, 0x03, 0x02, 0x01}));
  EXPECT_EQ(ParseAck(Bytes{1, 0, 0, 0, 0, 0, 0, 0})->last_stored_seq, 1u);
  EXPECT_FALSE(ParseAck(Bytes{1, 0, 0}).ok());

  EXPECT_EQ(SerializeBye({ByeReason::kAuthFailed, "no"}), (Bytes{3, 2, 0, 'n', 'o'}));
  StatusOr<ByeMessage> bye = ParseBye(Bytes{11, 3, 0, 'a', 0x01, 'z'});
  ASSERT_TRUE(bye.ok());
  EXPECT_EQ(bye->reason, ByeReason::kReplaced);
  EXPECT_EQ(bye->text, "a?z");  // control characters never reach the logs
  EXPECT_EQ(ParseBye(Bytes{12, 0, 0})->reason, ByeReason::kFrameAuthFailed);
  EXPECT_FALSE(ParseBye(Bytes{13, 0, 0}).ok());       // unknown reason
  EXPECT_FALSE(ParseBye(Bytes{0, 0xFF, 0xFF}).ok());  // text longer than allowed
  EXPECT_TRUE(ParseHeartbeat(Bytes{}).ok());
  EXPECT_FALSE(ParseHeartbeat(Bytes{0}).ok());
}

TEST(SessionMessagesTest, DataEnvelopeCarriesTheSequenceNumberFirst) {
  const Bytes message = {9, 8, 7};
  Bytes frame;
  AppendDataFrame(16, 0x0102, message, &frame);
  ASSERT_EQ(frame.size(), kFrameHeaderSize + 8 + 3);
  StatusOr<Frame> decoded = DecodeFrame(frame);
  ASSERT_TRUE(decoded.ok());
  EXPECT_EQ(decoded->type, 16);
  EXPECT_EQ(decoded->payload, (Bytes{0x02, 0x01, 0, 0, 0, 0, 0, 0, 9, 8, 7}));
  StatusOr<DataEnvelope> env = ParseDataEnvelope(decoded->payload);
  ASSERT_TRUE(env.ok());
  EXPECT_EQ(env->seq, 0x0102u);
  EXPECT_EQ(Bytes(env->message.begin(), env->message.end()), message);
  EXPECT_FALSE(ParseDataEnvelope(Bytes{0, 0, 0, 0, 0, 0, 0, 0}).ok());  // seq 0
  EXPECT_FALSE(ParseDataEnvelope(Bytes{1, 0, 0}).ok());
  EXPECT_FALSE(ParseDataEnvelope(Bytes{1, 0, 0, 0, 0, 0, 0, 0x40}).ok());  // 2^62 + 1
  EXPECT_TRUE(ParseDataEnvelope(Bytes{0, 0, 0, 0, 0, 0, 0, 0x40}).ok());   // 2^62
}

TEST(SessionMessagesTest, AgentNames) {
  EXPECT_TRUE(ValidateAgentName("robot_1.a-b").ok());
  EXPECT_FALSE(ValidateAgentName("").ok());
  EXPECT_FALSE(ValidateAgentName(".hidden").ok());
  EXPECT_FALSE(ValidateAgentName("a/b").ok());
  EXPECT_FALSE(ValidateAgentName("a b").ok());
  EXPECT_FALSE(ValidateAgentName(std::string(65, 'a')).ok());
  EXPECT_TRUE(ValidateAgentName(std::string(64, 'a')).ok());
}

}  // namespace
}  // namespace ccmd
