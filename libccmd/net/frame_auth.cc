#include "libccmd/net/frame_auth.h"

#include <openssl/evp.h>
#include <time.h>

#include <algorithm>

#include "libccmd/net/session_messages.h"
#include "libccmd/util/logging.h"

namespace ccmd {
namespace {

constexpr std::string_view kAgentToServerLabel = "CCMD v2 agent to server";
constexpr std::string_view kServerToAgentLabel = "CCMD v2 server to agent";
constexpr std::string_view kIdentityPadLabel = "CCMD v2 identity pad";
constexpr std::size_t kGcmNonceSize = 12;

ByteSpan AsBytes(std::string_view s) {
  return ByteSpan(reinterpret_cast<const std::uint8_t*>(s.data()), s.size());
}

// HKDF-Expand's info: label | hello payload.
std::vector<std::uint8_t> Info(std::string_view label, ByteSpan hello) {
  ByteWriter info(label.size() + hello.size());
  info.PutBytes(label.data(), label.size());
  info.PutBytes(hello.data(), hello.size());
  return info.Take();
}

// The monotonic clock, not the thread CPU clock: reading it costs tens of nanoseconds (no
// system call), where a tag costs from a fraction of a microsecond; over a few microseconds
// of pure computation the two agree but for a rare preemption.
double Now() {
  timespec t{};
  ::clock_gettime(CLOCK_MONOTONIC, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

void PutCounter(std::uint64_t counter, std::uint8_t* out) {
  for (int i = 0; i < 8; ++i) out[i] = static_cast<std::uint8_t>(counter >> (8 * i));
}

}  // namespace

std::vector<std::uint8_t> HkdfSha256(ByteSpan salt, ByteSpan ikm, ByteSpan info,
                                     std::size_t length) {
  CCMD_CHECK(length <= 255 * kMacSize) << "HKDF output too long";
  const Mac prk = HmacSha256(salt, ikm);
  std::vector<std::uint8_t> okm;
  okm.reserve(length);
  std::vector<std::uint8_t> block;  // T(i - 1) | info | i
  Mac t{};
  for (std::uint8_t i = 1; okm.size() < length; ++i) {
    block.clear();
    if (i > 1) block.insert(block.end(), t.begin(), t.end());
    block.insert(block.end(), info.begin(), info.end());
    block.push_back(i);
    t = HmacSha256(prk, block);
    const std::size_t take = std::min(t.size(), length - okm.size());
    okm.insert(okm.end(), t.begin(), t.begin() + static_cast<std::ptrdiff_t>(take));
  }
  return okm;
}

SessionKeys DeriveSessionKeys(std::string_view psk, const Nonce& agent_nonce,
                              const Nonce& server_nonce, ByteSpan hello) {
  std::array<std::uint8_t, 2 * kNonceSize> salt;
  std::copy(agent_nonce.begin(), agent_nonce.end(), salt.begin());
  std::copy(server_nonce.begin(), server_nonce.end(), salt.begin() + kNonceSize);
  auto derive = [&](std::string_view label, SessionKey* key) {
    const std::vector<std::uint8_t> okm =
        HkdfSha256(salt, AsBytes(psk), Info(label, hello), key->size());
    std::copy(okm.begin(), okm.end(), key->begin());
  };
  SessionKeys keys;
  derive(kAgentToServerLabel, &keys.agent_to_server);
  derive(kServerToAgentLabel, &keys.server_to_agent);
  derive(kIdentityPadLabel, &keys.identity_pad);
  return keys;
}

// The GMAC of a frame: AES-256-GCM over no plaintext with the header and payload as the
// authenticated data, under a 96-bit nonce that no frame of the session repeats (u32 sender
// | u64 counter). The key schedule is computed once per session; a frame then costs one
// GHASH pass (carry-less multiplication) over its bytes.
class SessionAuth::Mac {
 public:
  Mac(const SessionKey& key, FrameRole sender) : sender_(sender == FrameRole::kAgent ? 0 : 1) {
    ctx_ = EVP_CIPHER_CTX_new();
    CCMD_CHECK(ctx_ != nullptr) << "EVP_CIPHER_CTX_new failed";
    CCMD_CHECK(EVP_EncryptInit_ex(ctx_, EVP_aes_256_gcm(), nullptr, key.data(), nullptr) == 1)
        << "AES-256-GCM init failed";
  }
  ~Mac() { EVP_CIPHER_CTX_free(ctx_); }
  Mac(const Mac&) = delete;
  Mac& operator=(const Mac&) = delete;

  FrameTag Tag(std::uint64_t counter, ByteSpan header, ByteSpan payload) {
    std::uint8_t nonce[kGcmNonceSize] = {sender_, 0, 0, 0};
    PutCounter(counter, nonce + 4);
    int length = 0;
    std::uint8_t unused[16];
    FrameTag tag;
    const bool ok = EVP_EncryptInit_ex(ctx_, nullptr, nullptr, nullptr, nonce) == 1 &&
                    EVP_EncryptUpdate(ctx_, nullptr, &length, header.data(),
                                      static_cast<int>(header.size())) == 1 &&
                    (payload.empty() || EVP_EncryptUpdate(ctx_, nullptr, &length, payload.data(),
                                                          static_cast<int>(payload.size())) == 1) &&
                    EVP_EncryptFinal_ex(ctx_, unused, &length) == 1 &&
                    EVP_CIPHER_CTX_ctrl(ctx_, EVP_CTRL_GCM_GET_TAG, kFrameTagSize, tag.data()) == 1;
    CCMD_CHECK(ok) << "AES-256-GCM failed";
    return tag;
  }

 private:
  EVP_CIPHER_CTX* ctx_ = nullptr;
  std::uint8_t sender_;
};

SessionAuth::SessionAuth() = default;

SessionAuth::SessionAuth(FrameRole role, const SessionKeys& keys, bool keyed) : keyed_(keyed) {
  if (!keyed_) return;
  const bool agent = role == FrameRole::kAgent;
  send_mac_ = std::make_unique<Mac>(agent ? keys.agent_to_server : keys.server_to_agent, role);
  receive_mac_ = std::make_unique<Mac>(agent ? keys.server_to_agent : keys.agent_to_server,
                                       agent ? FrameRole::kServer : FrameRole::kAgent);
}

SessionAuth::~SessionAuth() = default;
SessionAuth::SessionAuth(SessionAuth&&) noexcept = default;
SessionAuth& SessionAuth::operator=(SessionAuth&&) noexcept = default;

FrameTag SessionAuth::Tag(const SessionKey& key, FrameRole sender, std::uint64_t counter,
                          ByteSpan header, ByteSpan payload) {
  return Mac(key, sender).Tag(counter, header, payload);
}

void SessionAuth::SealLast(std::size_t frame_start, std::vector<std::uint8_t>* out) {
  const double start = Now();
  const ByteSpan frame(out->data() + frame_start, out->size() - frame_start);
  const FrameTag tag =
      send_mac_->Tag(sent_++, frame.first(kFrameHeaderSize), frame.subspan(kFrameHeaderSize));
  out->insert(out->end(), tag.begin(), tag.end());
  cpu_seconds_ += Now() - start;
}

void SessionAuth::AppendFrame(std::uint8_t type, ByteSpan payload, std::vector<std::uint8_t>* out) {
  const std::size_t start = out->size();
  ::ccmd::AppendFrame(type, keyed_ ? kFrameTagged : 0, payload, out);
  if (keyed_) SealLast(start, out);
}

void SessionAuth::AppendDataFrame(std::uint8_t type, std::uint64_t seq, ByteSpan message,
                                  std::vector<std::uint8_t>* out) {
  const std::size_t start = out->size();
  ::ccmd::AppendDataFrame(type, seq, message, out, keyed_ ? kFrameTagged : 0);
  if (keyed_) SealLast(start, out);
}

Status SessionAuth::Verify(const Frame& frame) {
  if (!keyed_) {
    if (frame.tag) return Corrupt("a tagged frame in a session without a key");
    return Status::Ok();
  }
  const std::string what = "frame " + std::to_string(received_) + " of this session (type " +
                           std::to_string(frame.type) + ", " +
                           std::to_string(frame.payload.size()) + " bytes)";
  if (!frame.tag) return PermissionDenied(what + " carries no authentication tag");
  const double start = Now();
  const FrameTag expected = receive_mac_->Tag(received_, frame.header, frame.payload);
  cpu_seconds_ += Now() - start;
  if (!ConstantTimeEquals(expected, *frame.tag)) {
    return PermissionDenied(what +
                            " failed authentication: forged, altered, replayed or out of order");
  }
  ++received_;
  return Status::Ok();
}

}  // namespace ccmd
