#include "libccmd/net/frame_auth.h"

#include <openssl/core_names.h>
#include <openssl/evp.h>
#include <openssl/params.h>
#include <sys/stat.h>

#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/net/agent_identity.h"
#include "libccmd/net/session_messages.h"
#include "libccmd/util/file_util.h"
#include "tests/support/test_support.h"

namespace ccmd {
namespace {

using Bytes = std::vector<std::uint8_t>;

// The payload of a Hello from `name` (what the keys bind).
Bytes Hello(const std::string& name) {
  HelloMessage h;
  h.name = name;
  h.camera = {525, 525, 319.5, 239.5, 640, 480, 5000};
  h.first_seq = h.next_seq = 1;
  h.agent_nonce.fill(7);
  return SerializeHello(h);
}

Bytes FromHex(const std::string& hex) {
  Bytes b;
  for (std::size_t i = 0; i + 1 < hex.size(); i += 2) {
    b.push_back(static_cast<std::uint8_t>(std::stoi(hex.substr(i, 2), nullptr, 16)));
  }
  return b;
}

// RFC 5869, appendix A, test cases 1 and 3 (SHA-256).
TEST(FrameAuthTest, HkdfMatchesRfc5869) {
  const Bytes ikm(22, 0x0b);
  EXPECT_EQ(
      HkdfSha256(FromHex("000102030405060708090a0b0c"), ikm, FromHex("f0f1f2f3f4f5f6f7f8f9"), 42),
      FromHex("3cb25f25faacd57a90434f64d0362f2a2d2d0a90cf1a5a4c5db02d56ecc4c5bf34007208d5b8"
              "87185865"));
  EXPECT_EQ(HkdfSha256({}, ikm, {}, 42),
            FromHex("8da4e775a563c18f715f802a063c5a31b8a11f5c5ee1879ec3454e5f3c738d2d9d201395faa4"
                    "b61a96c8"));
}

// The tag is AES-256-GCM's over no plaintext (GMAC): NIST's test case 13 (all-zero key and
// nonce, nothing authenticated) is the tag of an empty frame 0 from the agent.
TEST(FrameAuthTest, TagIsGmacUnderSenderAndCounter) {
  const SessionKey zero{};
  const FrameTag empty = SessionAuth::Tag(zero, FrameRole::kAgent, 0, {}, {});
  EXPECT_EQ(Bytes(empty.begin(), empty.end()), FromHex("530f8afbc74536b9a963b4f1c4cb738b"));

  // With data, against OpenSSL's separate GMAC implementation (EVP_MAC "GMAC").
  SessionKey key;
  for (std::size_t i = 0; i < key.size(); ++i) key[i] = static_cast<std::uint8_t>(i * 7);
  const Bytes frame = EncodeFrame(16, kFrameTagged, Bytes{1, 2, 3, 4, 5});
  const ByteSpan header(frame.data(), kFrameHeaderSize);
  const ByteSpan payload(frame.data() + kFrameHeaderSize, 5);
  Bytes nonce = {1, 0, 0, 0, 0x2A, 0x01, 0, 0, 0, 0, 0, 0};  // server, counter 0x012A
  EVP_MAC* mac = EVP_MAC_fetch(nullptr, "GMAC", nullptr);
  ASSERT_NE(mac, nullptr);
  EVP_MAC_CTX* ctx = EVP_MAC_CTX_new(mac);
  char cipher[] = "AES-256-GCM";
  const OSSL_PARAM params[] = {
      OSSL_PARAM_construct_utf8_string(OSSL_MAC_PARAM_CIPHER, cipher, 0),
      OSSL_PARAM_construct_octet_string(OSSL_MAC_PARAM_IV, nonce.data(), nonce.size()),
      OSSL_PARAM_END};
  std::uint8_t expected[16];
  std::size_t length = 0;
  ASSERT_EQ(EVP_MAC_init(ctx, key.data(), key.size(), params), 1);
  ASSERT_EQ(EVP_MAC_update(ctx, frame.data(), frame.size()), 1);
  ASSERT_EQ(EVP_MAC_final(ctx, expected, &length, sizeof(expected)), 1);
  EVP_MAC_CTX_free(ctx);
  EVP_MAC_free(mac);
  ASSERT_EQ(length, 16u);
  const FrameTag tag = SessionAuth::Tag(key, FrameRole::kServer, 0x012A, header, payload);
  EXPECT_EQ(Bytes(tag.begin(), tag.end()), Bytes(expected, expected + 16));
  // The sender and the counter are in the nonce.
  EXPECT_NE(tag, SessionAuth::Tag(key, FrameRole::kAgent, 0x012A, header, payload));
  EXPECT_NE(tag, SessionAuth::Tag(key, FrameRole::kServer, 0x012B, header, payload));
}

TEST(FrameAuthTest, KeysDependOnKeyNoncesHelloAndDirection) {
  Nonce a{}, s{};
  a[0] = 1;
  s[0] = 2;
  const Bytes hello = Hello("robot-1"), other = Hello("robot-2");
  const std::string key = "a deployment key of some length";
  const SessionKeys k = DeriveSessionKeys(key, a, s, hello);
  EXPECT_NE(k.agent_to_server, k.server_to_agent);
  EXPECT_NE(k.agent_to_server, k.identity_pad);
  EXPECT_NE(k.agent_to_server,
            DeriveSessionKeys("another deployment key, longer", a, s, hello).agent_to_server);
  EXPECT_NE(k.agent_to_server, DeriveSessionKeys(key, s, a, hello).agent_to_server);
  EXPECT_NE(k.agent_to_server, DeriveSessionKeys(key, a, s, other).agent_to_server);
  Bytes altered = hello;
  altered.back() ^= 1;  // the last byte of the agent's nonce
  EXPECT_NE(k.agent_to_server, DeriveSessionKeys(key, a, s, altered).agent_to_server);
}

// Frames the agent side seals, as the server side receives them.
std::vector<Frame> Decode(const Bytes& stream) {
  FrameDecoder decoder;
  std::vector<Frame> frames;
  EXPECT_TRUE(decoder.Feed(stream, &frames).ok());
  return frames;
}

class SessionAuthTest : public ::testing::Test {
 protected:
  SessionAuthTest() {
    Nonce a{}, s{};
    a.fill(3);
    s.fill(4);
    keys_ = DeriveSessionKeys("a deployment key of some length", a, s, Hello("robot"));
  }
  // Agent-side frames: data 1, a heartbeat, data 2.
  std::vector<Frame> AgentFrames() {
    SessionAuth agent(FrameRole::kAgent, keys_, true);
    Bytes stream;
    agent.AppendDataFrame(16, 1, Bytes(300, 1), &stream);
    agent.AppendFrame(static_cast<std::uint8_t>(SessionType::kHeartbeat), {}, &stream);
    agent.AppendDataFrame(17, 2, Bytes(40, 2), &stream);
    return Decode(stream);
  }
  SessionKeys keys_;
};

TEST_F(SessionAuthTest, FramesVerifyInOrderOnly) {
  const std::vector<Frame> frames = AgentFrames();
  ASSERT_EQ(frames.size(), 3u);
  for (const Frame& f : frames) ASSERT_TRUE(f.tag.has_value());
  SessionAuth server(FrameRole::kServer, keys_, true);
  for (const Frame& f : frames) EXPECT_TRUE(server.Verify(f).ok());
  EXPECT_EQ(server.frames_verified(), 3u);

  // Replayed: frame 0 again where frame 3 is due.
  EXPECT_EQ(server.Verify(frames[0]).code(), StatusCode::kPermissionDenied);
  // Reordered, or one dropped.
  SessionAuth reordered(FrameRole::kServer, keys_, true);
  EXPECT_EQ(reordered.Verify(frames[1]).code(), StatusCode::kPermissionDenied);
  // Reflected back to the agent: the other direction's key.
  SessionAuth agent(FrameRole::kAgent, keys_, true);
  EXPECT_EQ(agent.Verify(frames[0]).code(), StatusCode::kPermissionDenied);
}

TEST_F(SessionAuthTest, AnyAlterationFailsEvenWithFreshCrcs) {
  const std::vector<Frame> frames = AgentFrames();
  for (std::size_t byte = 0; byte < 24; ++byte) {
    Frame f = frames[0];
    if (byte < kFrameHeaderSize) {
      f.header[byte] ^= 0x10;
    } else {
      f.payload[byte - kFrameHeaderSize] ^= 0x10;  // the sequence number
    }
    SessionAuth server(FrameRole::kServer, keys_, true);
    EXPECT_EQ(server.Verify(f).code(), StatusCode::kPermissionDenied) << byte;
  }
  Frame untagged = frames[0];
  untagged.tag.reset();
  SessionAuth server(FrameRole::kServer, keys_, true);
  const Status s = server.Verify(untagged);
  EXPECT_EQ(s.code(), StatusCode::kPermissionDenied);
  EXPECT_NE(s.message().find("no authentication tag"), std::string::npos) << s.message();
}

TEST_F(SessionAuthTest, KeylessSessionsSendAndAcceptNoTags) {
  SessionAuth keyless;
  Bytes stream;
  keyless.AppendDataFrame(16, 1, Bytes(10, 1), &stream);
  EXPECT_EQ(stream.size(), kFrameHeaderSize + 8 + 10);
  const std::vector<Frame> frames = Decode(stream);
  ASSERT_EQ(frames.size(), 1u);
  EXPECT_FALSE(frames[0].tag.has_value());
  EXPECT_TRUE(keyless.Verify(frames[0]).ok());
  EXPECT_EQ(keyless.Verify(AgentFrames()[0]).code(), StatusCode::kCorrupt);
}

TEST(AgentIdentityTest, CreatedOnceKeptPrivateAndNeverOverwritten) {
  testing::TempDir dir;
  const std::string path = dir.File("identity");
  StatusOr<AgentIdentity> first = LoadOrCreateIdentity(path);
  ASSERT_TRUE(first.ok()) << first.status().ToString();
  struct stat st {};
  ASSERT_EQ(::stat(path.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  StatusOr<AgentIdentity> again = LoadOrCreateIdentity(path);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(*again, *first);
  EXPECT_NE(*first, LoadOrCreateIdentity(dir.File("other")).value());

  std::ofstream(path) << "not an identity\n";
  EXPECT_EQ(LoadOrCreateIdentity(path).status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(ReadFileToString(path).value(), "not an identity\n");  // left as it was
}

TEST(AgentIdentityTest, MaskingTwiceGivesTheIdentityBackAndVerifiersDiffer) {
  AgentIdentity id{}, pad{};
  for (std::size_t i = 0; i < id.size(); ++i) {
    id[i] = static_cast<std::uint8_t>(i);
    pad[i] = static_cast<std::uint8_t>(200 - i);
  }
  EXPECT_NE(MaskIdentity(id, pad), id);
  EXPECT_EQ(MaskIdentity(MaskIdentity(id, pad), pad), id);
  AgentIdentity other = id;
  other[31] ^= 1;
  EXPECT_NE(VerifierOf(id), VerifierOf(other));
  EXPECT_NE(VerifierOf(id), id);
  EXPECT_FALSE(IsZero(VerifierOf(id)));
  EXPECT_TRUE(IsZero(IdentityVerifier{}));
}

}  // namespace
}  // namespace ccmd
