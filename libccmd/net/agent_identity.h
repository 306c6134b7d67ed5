#pragma once

// An agent's identity: a random 32-byte secret the agent creates once and keeps with its
// spill folder. The server learns it at the name's first registration and keeps only a
// verifier (a one-way function of it) in the agent's journal; later connections under that
// name must present the same secret, so a name alone cannot take over an agent.
//
// On the wire the secret travels in Auth masked (XOR) with a pad derived from the session
// (frame_auth.h, SessionKeys::identity_pad): only holders of the pre-shared key who saw
// that handshake could unmask it. Without a key (loopback only) the pad is public.
//
//   CCMD_ASSIGN_OR_RETURN(AgentIdentity id, LoadOrCreateIdentity(spill_dir + "/identity"));
//   auth.masked_identity = MaskIdentity(id, keys.identity_pad);     // agent
//   IdentityVerifier v = VerifierOf(MaskIdentity(auth.masked_identity, keys.identity_pad));

#include <array>
#include <cstdint>
#include <string>

#include "libccmd/util/status.h"

namespace ccmd {

constexpr std::size_t kIdentitySize = 32;
using AgentIdentity = std::array<std::uint8_t, kIdentitySize>;
using IdentityVerifier = std::array<std::uint8_t, kIdentitySize>;

// A fresh random identity (OpenSSL RAND_bytes).
StatusOr<AgentIdentity> NewIdentity();

// Reads the identity file at `path` (64 hexadecimal digits), or creates it (mode 0600,
// written atomically) when it does not exist. A file of any other form is kInvalidArgument:
// it is never overwritten, since that would cost the agent its name.
StatusOr<AgentIdentity> LoadOrCreateIdentity(const std::string& path);

// HMAC-SHA256(identity, "CCMD identity verifier v2"): what the server stores.
IdentityVerifier VerifierOf(const AgentIdentity& identity);

// XOR with the pad; applying it twice gives the identity back.
AgentIdentity MaskIdentity(const AgentIdentity& identity,
                           const std::array<std::uint8_t, kIdentitySize>& pad);

// True when every byte is zero (journals of protocol version 1 record no verifier).
bool IsZero(const IdentityVerifier& verifier);

}  // namespace ccmd
