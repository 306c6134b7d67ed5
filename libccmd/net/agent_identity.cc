#include "libccmd/net/agent_identity.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <string_view>
#include <type_traits>

#include "libccmd/net/psk.h"
#include "libccmd/util/file_util.h"

namespace ccmd {
namespace {

constexpr std::string_view kVerifierLabel = "CCMD identity verifier v2";
constexpr char kHexDigits[] = "0123456789abcdef";

int HexValue(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

StatusOr<AgentIdentity> ParseIdentity(const std::string& text, const std::string& path) {
  std::string_view hex = text;
  while (!hex.empty() && (hex.back() == '\n' || hex.back() == '\r' || hex.back() == ' ')) {
    hex.remove_suffix(1);
  }
  AgentIdentity identity{};
  bool ok = hex.size() == 2 * kIdentitySize;
  for (std::size_t i = 0; ok && i < kIdentitySize; ++i) {
    const int hi = HexValue(hex[2 * i]), lo = HexValue(hex[2 * i + 1]);
    ok = hi >= 0 && lo >= 0;
    identity[i] = static_cast<std::uint8_t>(ok ? hi * 16 + lo : 0);
  }
  if (!ok) {
    return InvalidArgument("agent identity file " + path + " is not " +
                           std::to_string(2 * kIdentitySize) +
                           " hexadecimal digits; it is left as it is (the agent's name at the "
                           "server depends on it): restore it, or use another spill folder "
                           "and agent name");
  }
  return identity;
}

Status WriteIdentity(const std::string& path, const AgentIdentity& identity) {
  std::string text;
  for (std::uint8_t b : identity) {
    text.push_back(kHexDigits[b >> 4]);
    text.push_back(kHexDigits[b & 15]);
  }
  text.push_back('\n');
  return WriteFileAtomicWith(path, [&](const std::string& temp) -> Status {
    // Readable by the owner only: whoever reads it can use the agent's name.
    const int fd = ::open(temp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
    if (fd < 0) return IoError("creating " + temp + ": " + std::strerror(errno));
    const bool written = ::write(fd, text.data(), text.size()) == static_cast<ssize_t>(text.size());
    ::close(fd);
    if (!written) return IoError("writing " + temp);
    return Status::Ok();
  });
}

}  // namespace

StatusOr<AgentIdentity> NewIdentity() {
  static_assert(std::is_same_v<AgentIdentity, Nonce>);
  AgentIdentity identity;
  CCMD_RETURN_IF_ERROR(RandomNonce(&identity));
  return identity;
}

StatusOr<AgentIdentity> LoadOrCreateIdentity(const std::string& path) {
  if (FileExists(path)) {
    CCMD_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, 1024));
    return ParseIdentity(text, path);
  }
  CCMD_ASSIGN_OR_RETURN(const AgentIdentity identity, NewIdentity());
  CCMD_RETURN_IF_ERROR(WriteIdentity(path, identity));
  return identity;
}

IdentityVerifier VerifierOf(const AgentIdentity& identity) {
  const Mac mac =
      HmacSha256(identity, ByteSpan(reinterpret_cast<const std::uint8_t*>(kVerifierLabel.data()),
                                    kVerifierLabel.size()));
  IdentityVerifier verifier;
  std::copy(mac.begin(), mac.end(), verifier.begin());
  return verifier;
}

AgentIdentity MaskIdentity(const AgentIdentity& identity,
                           const std::array<std::uint8_t, kIdentitySize>& pad) {
  AgentIdentity out;
  for (std::size_t i = 0; i < kIdentitySize; ++i) out[i] = identity[i] ^ pad[i];
  return out;
}

bool IsZero(const IdentityVerifier& verifier) {
  std::uint8_t any = 0;
  for (std::uint8_t b : verifier) any |= b;
  return any == 0;
}

}  // namespace ccmd
