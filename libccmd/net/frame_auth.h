#pragma once

// Authentication of every frame of a session (PROTOCOL.md, "Frame authentication").
//
// After the handshake both sides derive the session's keys from the pre-shared key and both
// nonces (HKDF-SHA256, RFC 5869), one key per direction. Every frame after that carries a
// 16-byte tag (flags bit 15, proto/frame.h): the GMAC (AES-256-GCM with no plaintext) of
//   the 20 header bytes | the payload
// under the 96-bit nonce u32 sender (0 agent, 1 server) | u64 counter, where `counter`
// numbers the tagged frames of that direction in this session (0, 1, 2, ...). A forged,
// altered, replayed, reordered, dropped or injected frame fails the check at the receiver,
// which closes the connection. GMAC rather than HMAC-SHA256: a third of the cost per
// keyframe on the server (docs/benchmarks/transport.md). Without a pre-shared key (loopback
// only) the session is keyless: frames carry no tag and a tagged frame is an error.
//
//   SessionKeys keys = DeriveSessionKeys(psk, agent_nonce, server_nonce, hello_payload);
//   SessionAuth auth(FrameRole::kServer, keys, /*keyed=*/!psk.empty());
//   auth.AppendFrame(type, payload, &out);            // header, payload, tag
//   CCMD_RETURN_IF_ERROR(auth.Verify(received_frame)); // kPermissionDenied on a bad tag

#include <array>
#include <cstdint>
#include <memory>
#include <string_view>
#include <vector>

#include "libccmd/net/psk.h"
#include "libccmd/util/status.h"
#include "proto/byte_io.h"
#include "proto/frame.h"

namespace ccmd {

constexpr std::size_t kSessionKeySize = 32;
using SessionKey = std::array<std::uint8_t, kSessionKeySize>;

// HKDF-SHA256 (RFC 5869): extract with `salt`, expand with `info` to `length` bytes
// (at most 255 x 32).
std::vector<std::uint8_t> HkdfSha256(ByteSpan salt, ByteSpan ikm, ByteSpan info,
                                     std::size_t length);

struct SessionKeys {
  SessionKey agent_to_server{};
  SessionKey server_to_agent{};
  SessionKey identity_pad{};  // masks the agent's identity secret in Auth (agent_identity.h)
};

// PRK = HKDF-Extract(salt = agent_nonce | server_nonce, IKM = psk); each key is
// HKDF-Expand(PRK, label | hello, 32) with its own label, `hello` being the payload of the
// agent's Hello as sent (so both sides agree on keys only if they saw the same hello). An
// empty psk (keyless loopback) gives keys anyone can compute: they mask nothing.
SessionKeys DeriveSessionKeys(std::string_view psk, const Nonce& agent_nonce,
                              const Nonce& server_nonce, ByteSpan hello);

enum class FrameRole { kAgent, kServer };

// One session's frame authentication, both directions: tags what this side sends and checks
// what it receives. Not thread-safe (one per connection, used by its I/O thread).
class SessionAuth {
 public:
  // A keyless session: no tags sent, none accepted.
  SessionAuth();
  SessionAuth(FrameRole role, const SessionKeys& keys, bool keyed);
  ~SessionAuth();
  SessionAuth(SessionAuth&&) noexcept;
  SessionAuth& operator=(SessionAuth&&) noexcept;

  bool keyed() const { return keyed_; }
  // Appends a whole frame (tagged when keyed).
  void AppendFrame(std::uint8_t type, ByteSpan payload, std::vector<std::uint8_t>* out);
  // Appends a data frame: payload = u64 seq | message (tagged when keyed).
  void AppendDataFrame(std::uint8_t type, std::uint64_t seq, ByteSpan message,
                       std::vector<std::uint8_t>* out);
  // Checks a received frame: keyed, it must carry the tag expected next (kPermissionDenied
  // otherwise, naming the frame); keyless, it must carry none (kCorrupt).
  Status Verify(const Frame& frame);

  std::uint64_t frames_sent() const { return sent_; }
  std::uint64_t frames_verified() const { return received_; }
  // Time spent computing tags (sending and checking) since the last call, for the
  // statistics (pure computation: measured with the cheap monotonic clock).
  double TakeCpuSeconds() {
    const double s = cpu_seconds_;
    cpu_seconds_ = 0;
    return s;
  }

  // The tag of one frame sent by `sender` (exposed for tests and benchmarks).
  static FrameTag Tag(const SessionKey& key, FrameRole sender, std::uint64_t counter,
                      ByteSpan header, ByteSpan payload);

 private:
  class Mac;
  void SealLast(std::size_t frame_start, std::vector<std::uint8_t>* out);

  bool keyed_ = false;
  std::unique_ptr<Mac> send_mac_;
  std::unique_ptr<Mac> receive_mac_;
  std::uint64_t sent_ = 0;
  std::uint64_t received_ = 0;
  double cpu_seconds_ = 0;
};

}  // namespace ccmd
