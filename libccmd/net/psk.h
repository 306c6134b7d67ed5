#pragma once

// Pre-shared key authentication. A deployment has one key, given to the server and every
// agent as a file (--psk-file) or in the environment (CCMD_PSK). The key never crosses the
// wire: the agent proves it knows the key by an HMAC-SHA256 over both sides' random nonces,
// the server by tagging its Welcome with a key derived from it (PROTOCOL.md "Session
// messages"; frame_auth.h).
//
//   CCMD_ASSIGN_OR_RETURN(std::string key, ResolvePsk(psk_file));   // "" = no key
//   Mac proof = AgentProof(key, server_nonce, hello_payload);
//   if (!ConstantTimeEquals(proof, received)) refuse;

#include <array>
#include <cstdint>
#include <string>
#include <string_view>

#include "libccmd/util/status.h"
#include "proto/byte_io.h"

namespace ccmd {

constexpr std::size_t kNonceSize = 32;
constexpr std::size_t kMacSize = 32;
using Nonce = std::array<std::uint8_t, kNonceSize>;
using Mac = std::array<std::uint8_t, kMacSize>;

// A key shorter than this is refused: a guessable key gives no protection.
constexpr std::size_t kMinPskBytes = 16;
constexpr std::size_t kMaxPskBytes = 4096;
constexpr const char* kPskEnvironmentVariable = "CCMD_PSK";

// Reads a key file: its bytes with trailing whitespace (the newline an editor adds) removed.
// kInvalidArgument if shorter than kMinPskBytes or longer than kMaxPskBytes.
StatusOr<std::string> ReadPskFile(const std::string& path);

// The key from `psk_file` if given, else from $CCMD_PSK, else "" (no key).
StatusOr<std::string> ResolvePsk(const std::string& psk_file);

// HMAC-SHA256 (RFC 2104 with SHA-256), from OpenSSL's libcrypto.
Mac HmacSha256(ByteSpan key, ByteSpan message);

// Compares without an early exit, so the time taken does not reveal where a guess differs.
bool ConstantTimeEquals(ByteSpan a, ByteSpan b);

// Cryptographically random bytes (OpenSSL RAND_bytes).
Status RandomNonce(Nonce* nonce);

// What the agent sends to prove the key: HMAC(key, "CCMD agent proof v2" | server_nonce |
// hello), `hello` being the payload of the agent's Hello exactly as sent. Both nonces (the
// agent's is in the hello) prevent replays; binding the whole hello stops a proof made for
// one agent from serving another, and a hello altered on the way (camera, resume point,
// name) from being accepted.
Mac AgentProof(std::string_view key, const Nonce& server_nonce, ByteSpan hello);

// The server proves the key in turn with the tag of its Welcome, the first frame it tags
// with the session's keys (frame_auth.h).

}  // namespace ccmd
