#include "libccmd/net/psk.h"

#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/hmac.h>
#include <openssl/rand.h>
#include <sys/stat.h>

#include <cstdlib>

#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"

namespace ccmd {
namespace {

std::string TrimTrailingSpace(std::string s) {
  while (!s.empty() &&
         (s.back() == '\n' || s.back() == '\r' || s.back() == ' ' || s.back() == '\t')) {
    s.pop_back();
  }
  return s;
}

Status CheckKeyLength(const std::string& key, const std::string& where) {
  if (key.size() < kMinPskBytes) {
    return InvalidArgument(where + ": the pre-shared key has " + std::to_string(key.size()) +
                           " bytes; at least " + std::to_string(kMinPskBytes) +
                           " are required (e.g. `openssl rand -hex 32 > ccmd.key`)");
  }
  if (key.size() > kMaxPskBytes) {
    return InvalidArgument(where + ": the pre-shared key is longer than " +
                           std::to_string(kMaxPskBytes) + " bytes");
  }
  return Status::Ok();
}

ByteSpan AsBytes(std::string_view s) {
  return ByteSpan(reinterpret_cast<const std::uint8_t*>(s.data()), s.size());
}

}  // namespace

StatusOr<std::string> ReadPskFile(const std::string& path) {
  CCMD_ASSIGN_OR_RETURN(std::string text, ReadFileToString(path, 2 * kMaxPskBytes));
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0 && (st.st_mode & (S_IRWXG | S_IRWXO)) != 0) {
    CCMD_LOG(WARNING) << "key file " << path << " can be read by other users; consider `chmod 600 "
                      << path << "`";
  }
  std::string key = TrimTrailingSpace(std::move(text));
  CCMD_RETURN_IF_ERROR(CheckKeyLength(key, path));
  return key;
}

StatusOr<std::string> ResolvePsk(const std::string& psk_file) {
  if (!psk_file.empty()) return ReadPskFile(psk_file);
  const char* env = std::getenv(kPskEnvironmentVariable);
  if (env == nullptr || *env == '\0') return std::string();
  std::string key = TrimTrailingSpace(env);
  CCMD_RETURN_IF_ERROR(CheckKeyLength(key, std::string("$") + kPskEnvironmentVariable));
  return key;
}

Mac HmacSha256(ByteSpan key, ByteSpan message) {
  Mac mac{};
  unsigned int length = 0;
  // HMAC() accepts a null key pointer only with length 0; give it a valid pointer always.
  static const std::uint8_t kEmpty = 0;
  HMAC(EVP_sha256(), key.empty() ? &kEmpty : key.data(), static_cast<int>(key.size()),
       message.empty() ? &kEmpty : message.data(), message.size(), mac.data(), &length);
  return mac;
}

bool ConstantTimeEquals(ByteSpan a, ByteSpan b) {
  if (a.size() != b.size()) return false;
  if (a.empty()) return true;
  return CRYPTO_memcmp(a.data(), b.data(), a.size()) == 0;
}

Status RandomNonce(Nonce* nonce) {
  if (RAND_bytes(nonce->data(), static_cast<int>(nonce->size())) != 1) {
    return Internal("the system random number generator failed (OpenSSL RAND_bytes)");
  }
  return Status::Ok();
}

Mac AgentProof(std::string_view key, const Nonce& server_nonce, ByteSpan hello) {
  static constexpr std::string_view kLabel = "CCMD agent proof v2";
  ByteWriter w(kLabel.size() + server_nonce.size() + hello.size());
  w.PutBytes(kLabel.data(), kLabel.size());
  w.PutBytes(server_nonce.data(), server_nonce.size());
  w.PutBytes(hello.data(), hello.size());
  return HmacSha256(AsBytes(key), w.bytes());
}

}  // namespace ccmd
