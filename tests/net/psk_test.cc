#include "libccmd/net/psk.h"

#include <cstdlib>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "tests/support/test_support.h"

namespace ccmd {
namespace {

std::string Hex(const Mac& mac) {
  static const char* digits = "0123456789abcdef";
  std::string s;
  for (std::uint8_t b : mac) {
    s.push_back(digits[b >> 4]);
    s.push_back(digits[b & 15]);
  }
  return s;
}

ByteSpan Span(const std::string& s) {
  return ByteSpan(reinterpret_cast<const std::uint8_t*>(s.data()), s.size());
}

// RFC 4231, test cases 1, 2 and 6 (a key longer than the SHA-256 block).
TEST(PskTest, HmacSha256MatchesRfc4231) {
  const std::string key1(20, '\x0b');
  EXPECT_EQ(Hex(HmacSha256(Span(key1), Span("Hi There"))),
            "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7");
  EXPECT_EQ(Hex(HmacSha256(Span("Jefe"), Span("what do ya want for nothing?"))),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843");
  const std::string key6(131, '\xaa');
  EXPECT_EQ(
      Hex(HmacSha256(Span(key6), Span("Test Using Larger Than Block-Size Key - Hash Key First"))),
      "60e431591ee0b67f0d8a26aacbf5b77f8e0bc6213728c5140546040f0ee37f54");
}

TEST(PskTest, ConstantTimeEqualsComparesWholeSpans) {
  const std::string a = "0123456789abcdef", b = "0123456789abcdeX";
  EXPECT_TRUE(ConstantTimeEquals(Span(a), Span(a)));
  EXPECT_FALSE(ConstantTimeEquals(Span(a), Span(b)));
  EXPECT_FALSE(ConstantTimeEquals(Span(a), Span(a.substr(0, 15))));
}

TEST(PskTest, ProofsBindTheServerNonceAndTheWholeHello) {
  const std::string key = "a deployment key of some length";
  Nonce s{}, t{};
  s[0] = 1;
  t[0] = 2;
  const std::string hello = "the hello of robot-1, its camera and resume point";
  std::string altered = hello;
  altered[30] ^= 1;  // one bit anywhere in the hello (a camera, a resume point)
  const Mac p = AgentProof(key, s, Span(hello));
  EXPECT_EQ(p, AgentProof(key, s, Span(hello)));
  EXPECT_NE(p, AgentProof(key, s, Span(altered)));
  EXPECT_NE(p, AgentProof(key, t, Span(hello)));  // another handshake's server nonce
  EXPECT_NE(p, AgentProof("another deployment key", s, Span(hello)));
}

TEST(PskTest, KeyFileIsTrimmedAndChecked) {
  testing::TempDir dir;
  std::ofstream(dir.File("good.key")) << "0123456789abcdef0123\n";
  std::ofstream(dir.File("short.key")) << "short\n";
  StatusOr<std::string> good = ReadPskFile(dir.File("good.key"));
  ASSERT_TRUE(good.ok()) << good.status().ToString();
  EXPECT_EQ(*good, "0123456789abcdef0123");
  EXPECT_EQ(ReadPskFile(dir.File("short.key")).status().code(), StatusCode::kInvalidArgument);
  EXPECT_FALSE(ReadPskFile(dir.File("missing.key")).ok());
}

TEST(PskTest, ResolveUsesFileThenEnvironment) {
  testing::TempDir dir;
  std::ofstream(dir.File("k")) << "file-key-0123456789";
  ::setenv(kPskEnvironmentVariable, "environment-key-0123", 1);
  EXPECT_EQ(ResolvePsk(dir.File("k")).value(), "file-key-0123456789");
  EXPECT_EQ(ResolvePsk("").value(), "environment-key-0123");
  ::unsetenv(kPskEnvironmentVariable);
  EXPECT_EQ(ResolvePsk("").value(), "");
}

}  // namespace
}  // namespace ccmd
