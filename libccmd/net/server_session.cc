// The server's side of the session protocol (PROTOCOL.md, "Session messages"): what each
// frame means in each connection state, and what the journal stage's answers become.

#include <algorithm>

#include "libccmd/net/agent_identity.h"
#include "libccmd/net/psk.h"
#include "libccmd/net/server_io.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"
#include "proto/messages.h"

namespace ccmd {
namespace {

// Parses a data message; for a keyframe, *parts gets its bytes per part.
Status ValidateDataMessage(bool keyframe, ByteSpan message, KeyframeSizeBreakdown* parts) {
  if (!keyframe) return ParsePoseUpdate(message).status();
  CCMD_ASSIGN_OR_RETURN(const KeyframeMessage kf, ParseKeyframe(message));
  // The bytes per part, by serializing what arrived again (the format is canonical).
  StatusOr<std::vector<std::uint8_t>> again = SerializeKeyframe(kf, parts);
  const std::size_t counted = again.ok() ? parts->total() : 0;
  if (counted < message.size()) parts->other += message.size() - counted;
  return Status::Ok();
}

}  // namespace

void ServerIo::HandleFrame(Connection* c, Frame& frame, double now) {
  if (c->state == ConnState::kStreaming) {
    const Status verified = c->auth.Verify(frame);
    stats_->AddAuthentication(c->auth.TakeCpuSeconds());
    if (!verified.ok()) {
      const bool forged = verified.code() == StatusCode::kPermissionDenied;
      if (forged) stats_->Count("frame_auth_failures");
      Close(c, forged ? ByeReason::kFrameAuthFailed : ByeReason::kProtocolError, verified.message(),
            now);
      return;
    }
  } else if (frame.tag) {
    Close(c, ByeReason::kProtocolError, "a tagged frame during the handshake", now);
    return;
  }
  const std::uint8_t type = frame.type;
  if (type == static_cast<std::uint8_t>(SessionType::kBye)) {
    HandleBye(c, frame, now);
    return;
  }
  switch (c->state) {
    case ConnState::kAwaitHello:
      if (type != static_cast<std::uint8_t>(SessionType::kHello)) {
        Close(c, ByeReason::kProtocolError,
              "expected a hello, got a message of type " + std::to_string(type), now);
        return;
      }
      HandleHello(c, frame, now);
      return;
    case ConnState::kAwaitAuth:
      if (type != static_cast<std::uint8_t>(SessionType::kAuth)) {
        Close(c, ByeReason::kProtocolError,
              "expected an auth message, got type " + std::to_string(type), now);
        return;
      }
      HandleAuth(c, frame, now);
      return;
    case ConnState::kAwaitAttach:
      Close(c, ByeReason::kProtocolError,
            "a message of type " + std::to_string(type) + " before the welcome", now);
      return;
    case ConnState::kStreaming:
      if (IsDataType(type)) {
        HandleData(c, frame, now);
      } else if (type == static_cast<std::uint8_t>(SessionType::kHeartbeat)) {
        Status s = ParseHeartbeat(frame.payload);
        if (!s.ok()) Close(c, ByeReason::kProtocolError, s.message(), now);
      } else if (type <= kLastDefinedSessionType) {
        Close(c, ByeReason::kProtocolError,
              "unexpected session message of type " + std::to_string(type) + " in a session", now);
      } else {
        Close(c, ByeReason::kProtocolError, "unknown message type " + std::to_string(type), now);
      }
      return;
    case ConnState::kClosing:
      return;
  }
}

void ServerIo::HandleBye(Connection* c, const Frame& frame, double now) {
  StatusOr<ByeMessage> bye = ParseBye(frame.payload);
  if (!bye.ok()) {
    Close(c, ByeReason::kProtocolError, "malformed bye: " + bye.status().message(), now);
    return;
  }
  const std::string what = c->Describe() + " said bye (" + ByeReasonName(bye->reason) + ")" +
                           (bye->text.empty() ? "" : ": " + bye->text);
  if (bye->reason == ByeReason::kNormal) {
    CCMD_LOG(INFO) << what;
  } else {
    stats_->Count("agent_bye_" + CounterName(bye->reason).substr(7));
    if (c->attached) {
      CCMD_LOG(WARNING) << what;
    } else {
      refusals_.Note(c->source, c->peer, "bye in the handshake", what, now);
    }
  }
  Drop(c, "the agent said bye", /*quiet=*/true);
}

void ServerIo::HandleHello(Connection* c, const Frame& frame, double now) {
  StatusOr<HelloMessage> hello = ParseHello(frame.payload);
  if (!hello.ok()) {
    Close(c, ReasonFor(hello.status()), "bad hello: " + hello.status().message(), now);
    return;
  }
  c->hello = std::move(*hello);
  c->hello_payload.assign(frame.payload.begin(), frame.payload.end());
  Status nonce = RandomNonce(&c->server_nonce);
  if (!nonce.ok()) {
    Close(c, ByeReason::kServerError, nonce.message(), now);
    return;
  }
  ChallengeMessage challenge;
  challenge.key_required = !options_.psk.empty();
  challenge.server_nonce = c->server_nonce;
  c->state = ConnState::kAwaitAuth;
  Send(c, SessionType::kChallenge, SerializeChallenge(challenge));
}

void ServerIo::HandleAuth(Connection* c, const Frame& frame, double now) {
  StatusOr<AuthMessage> auth = ParseAuth(frame.payload);
  if (!auth.ok()) {
    Close(c, ByeReason::kProtocolError, "bad auth message: " + auth.status().message(), now);
    return;
  }
  const bool keyed = !options_.psk.empty();
  if (keyed && !auth->proof) {
    stats_->Count("refused_no_key");
    Close(c, ByeReason::kAuthFailed,
          "this server requires a pre-shared key and the agent has none (give the agent the "
          "deployment's key with --psk-file FILE or CCMD_PSK)",
          now);
    return;
  }
  if (keyed && !ConstantTimeEquals(AgentProof(options_.psk, c->server_nonce, c->hello_payload),
                                   *auth->proof)) {
    stats_->Count("refused_wrong_key");
    Close(c, ByeReason::kAuthFailed,
          "authentication failed: the agent's pre-shared key is not this server's", now);
    return;
  }
  if (!keyed && auth->proof) {
    stats_->Count("refused_key_mismatch");
    Close(c, ByeReason::kKeyMismatch,
          "this server runs without a pre-shared key but the agent has one; give both the same "
          "key (or neither, on loopback)",
          now);
    return;
  }
  // The key is proven: from here on every frame the server sends on this connection (the
  // Welcome, or a Bye refusing the agent) is tagged.
  const SessionKeys keys =
      DeriveSessionKeys(options_.psk, c->hello.agent_nonce, c->server_nonce, c->hello_payload);
  c->verifier = VerifierOf(MaskIdentity(auth->masked_identity, keys.identity_pad));
  c->auth = SessionAuth(FrameRole::kServer, keys, keyed);
  StageItem attach;
  attach.kind = StageItem::Kind::kAttach;
  attach.conn = c->token;
  attach.hello = c->hello;
  attach.verifier = c->verifier;
  attach.received_time = now;
  c->state = ConnState::kAwaitAttach;
  Enqueue(std::move(attach));
}

void ServerIo::HandleData(Connection* c, Frame& frame, double now) {
  const std::uint8_t type = frame.type;
  const std::size_t frame_bytes = kFrameHeaderSize + frame.payload.size();
  if (!IsKnownDataType(type)) {
    Close(c, ByeReason::kProtocolError, "unknown message type " + std::to_string(type), now);
    return;
  }
  StatusOr<DataEnvelope> env = ParseDataEnvelope(frame.payload);
  if (!env.ok()) {
    Close(c, ByeReason::kProtocolError, env.status().message(), now);
    return;
  }
  Slot& slot = slots_[c->agent];
  if (env->seq <= slot.received_seq) {
    // Sent again after a reconnect, or pipelined before the agent saw our ack: stored already.
    stats_->AddDuplicate(c->agent, frame_bytes);
    return;
  }
  if (env->seq != slot.received_seq + 1) {
    Close(c, ByeReason::kProtocolError,
          "sequence gap: expected message " + std::to_string(slot.received_seq + 1) + ", got " +
              std::to_string(env->seq),
          now);
    return;
  }
  // Validate before storing: a message we acknowledge must be one the back-end can read.
  KeyframeSizeBreakdown parts;
  const bool keyframe = type == static_cast<std::uint8_t>(MessageType::kKeyframe);
  const Status valid = ValidateDataMessage(keyframe, env->message, &parts);
  if (!valid.ok()) {
    Close(c, ReasonFor(valid),
          std::string(keyframe ? "malformed keyframe" : "malformed pose update") + " (message " +
              std::to_string(env->seq) + "): " + valid.message(),
          now);
    return;
  }
  stats_->AddDataMessage(c->agent, type, env->message.size(), keyframe ? &parts : nullptr, now,
                         frame.tag ? kFrameTagSize : 0);
  slot.received_seq = env->seq;
  slot.inflight_bytes += env->message.size();
  StageItem item;
  item.kind = StageItem::Kind::kData;
  item.conn = c->token;
  item.agent = c->agent;
  item.seq = env->seq;
  item.type = type;
  // Drop the 8-byte sequence number in place rather than copying the message.
  frame.payload.erase(frame.payload.begin(),
                      frame.payload.begin() + static_cast<std::ptrdiff_t>(kDataEnvelopeBytes));
  item.message = std::move(frame.payload);
  item.received_time = now;
  Enqueue(std::move(item));
}

void ServerIo::Welcome(Connection* c, const AttachResult& r, double now) {
  Slot& slot = slots_[r.agent];
  if (slot.conn != 0 && slot.conn != c->token) {
    // Only a connection that proved the agent's identity replaces the one it had.
    auto old = conns_.find(slot.conn);
    if (old != conns_.end() && !old->second->done) {
      Close(old->second.get(), ByeReason::kReplaced,
            "replaced by a new connection of the same agent from " + c->peer, now);
    }
  }
  slot.conn = c->token;
  slot.received_seq = r.last_stored;
  c->agent = r.agent;
  c->attached = true;
  if (c->counted_as_handshake) {
    c->counted_as_handshake = false;
    --handshakes_;
  }
  WelcomeMessage welcome;
  welcome.agent = r.agent;
  welcome.last_stored_seq = r.last_stored;
  welcome.max_payload_bytes = options_.max_payload_bytes;
  welcome.idle_timeout_ms = static_cast<std::uint32_t>(options_.idle_timeout_s * 1e3);
  c->state = ConnState::kStreaming;
  c->decoder =
      std::make_unique<FrameDecoder>(FrameLimits{.max_payload_bytes = options_.max_payload_bytes});
  c->frame_header = 0;
  c->last_frame = now;
  stats_->AgentConnected(r.agent, c->hello.name, now);
  stats_->Count("sessions");
  CCMD_LOG(INFO) << "agent " << r.agent << " '" << c->hello.name << "' connected from " << c->peer
                 << "; stored up to message " << r.last_stored
                 << (c->auth.keyed() ? "" : " (no key: frames not authenticated)");
  Send(c, SessionType::kWelcome, SerializeWelcome(welcome));
}

void ServerIo::ForgetAgent(AgentId agent) {
  slots_.erase(agent);
  stats_->ForgetAgent(agent);
}

void ServerIo::HandleFeedback(double now) {
  StageFeedback fb;
  journal_.TakeFeedback(&fb);
  if (fb.empty()) return;
  for (const AttachResult& r : fb.attached) {
    auto it = conns_.find(r.conn);
    Connection* c = it == conns_.end() ? nullptr : it->second.get();
    if (c == nullptr || c->done || c->state != ConnState::kAwaitAttach) {
      if (r.status.ok()) {
        // Registered, but the connection went away meanwhile: end the session we opened.
        StageItem detach;
        detach.kind = StageItem::Kind::kDetach;
        detach.agent = r.agent;
        detach.reason = "connection closed during the handshake";
        detach.received_time = now;
        Enqueue(std::move(detach));
      }
      continue;
    }
    if (!r.status.ok()) {
      stats_->Count("refused_" + CounterName(r.reason).substr(7));
      Close(c, r.reason, r.status.message(), now);
      continue;
    }
    Welcome(c, r, now);
  }
  for (const auto& [agent, n] : fb.freed_bytes) {
    auto slot = slots_.find(agent);
    if (slot == slots_.end()) continue;
    slot->second.inflight_bytes -= std::min<std::uint64_t>(slot->second.inflight_bytes, n);
  }
  for (const auto& [agent, seq] : fb.stored) {
    auto slot = slots_.find(agent);
    if (slot == slots_.end()) continue;
    auto it = conns_.find(slot->second.conn);
    if (it == conns_.end() || it->second->state != ConnState::kStreaming) continue;
    Send(it->second.get(), SessionType::kAck, SerializeAck({seq}));
  }
  for (const auto& [agent, status] : fb.failed) {
    auto slot = slots_.find(agent);
    if (slot == slots_.end()) continue;
    auto it = conns_.find(slot->second.conn);
    if (it != conns_.end() && !it->second->done) {
      Close(it->second.get(), ByeReason::kServerError,
            "the server could not store the data: " + status.message(), now);
    }
  }
  for (AgentId agent : fb.forgotten) ForgetAgent(agent);
}

}  // namespace ccmd
