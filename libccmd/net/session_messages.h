#pragma once

// Session messages (frame types 1..7) and the data envelope: everything the transport adds
// around the data messages of proto/. Byte layouts: proto/PROTOCOL.md, "Session messages".
//
//   agent                                   server
//   Hello(name, camera, resume point, nonce) ->
//                                           <- Challenge(key required?, nonce)
//   Auth(HMAC proof, masked identity)        ->
//                                           <- Welcome(agent id, last stored seq)   [tagged]
//   Data(seq, Keyframe | PoseUpdate) ...     ->                                     [tagged]
//                                           <- Ack(last stored seq)  (after journaling)
//   Heartbeat                               <-> Heartbeat             (when idle)
//   Bye(reason, text)                       <-> Bye(reason, text)     (before closing)
//
// With a pre-shared key every frame from the Welcome on (each direction) carries a tag
// (frame_auth.h). Within a session every data frame (type >= 16) starts with its u64
// sequence number; the message of proto/messages.h follows unchanged. Parsers return
// kCorrupt (or kUnsupported for another protocol version) on any malformed input and never
// allocate more than the limits below.

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "libccmd/net/agent_identity.h"
#include "libccmd/net/psk.h"
#include "libccmd/util/ids.h"
#include "libccmd/util/status.h"
#include "proto/byte_io.h"
#include "proto/frame.h"

namespace ccmd {

enum class SessionType : std::uint8_t {
  kHello = 1,      // agent -> server
  kChallenge = 2,  // server -> agent
  kAuth = 3,       // agent -> server
  kWelcome = 4,    // server -> agent
  kAck = 5,        // server -> agent
  kBye = 6,        // either
  kHeartbeat = 7,  // either
};
constexpr std::uint8_t kLastDefinedSessionType = 7;

// Why a side closes a session (sent in Bye, logged on both sides).
enum class ByeReason : std::uint8_t {
  kNormal = 0,              // orderly end
  kProtocolError = 1,       // malformed, unexpected or unknown message
  kUnsupportedVersion = 2,  // protocol version mismatch
  kAuthFailed = 3,          // wrong pre-shared key
  kKeyMismatch = 4,         // one side has a key, the other none
  kServerFull = 5,          // too many agents or connections
  kTimeout = 6,             // handshake or idle time-out
  kRefused = 7,             // not the agent registered under that name, or its camera or
                            // resume point contradicts the registration
  kLimitExceeded = 8,       // frame too large, peer not reading
  kShuttingDown = 9,        // server stopping
  kServerError = 10,        // the server could not store the data (journal failure)
  kReplaced = 11,           // a newer connection of the same agent took over
  kFrameAuthFailed = 12,    // a frame of the session failed its tag check
};
constexpr std::uint8_t kLastByeReason = 12;
const char* ByeReasonName(ByeReason reason);

constexpr std::size_t kMaxAgentNameBytes = 64;
constexpr std::size_t kMaxByeTextBytes = 1024;
// Handshake frames are small; a server reads them with this payload limit.
constexpr std::uint32_t kMaxHandshakePayloadBytes = 1024;
// Bytes a data frame adds in front of the message: the u64 sequence number.
constexpr std::size_t kDataEnvelopeBytes = 8;
// Sequence numbers (and resume points) above this are corrupt: no agent sends 2^62
// messages, and the bound keeps every sum of them far from overflowing.
constexpr std::uint64_t kMaxSequenceNumber = 1ull << 62;

// Letters, digits, '.', '_', '-'; 1..64 bytes; not starting with '.'. Names become file
// names on the server, so nothing else is allowed.
Status ValidateAgentName(std::string_view name);

// The agent's camera as announced in Hello: pinhole intrinsics of the images it sends (either
// focal length may be negative: ICL-NUIM's rows run opposite to the camera's y axis), their
// lens distortion k1 k2 p1 p2 k3 (keypoints arrive undistorted; the server needs it for the
// RGB-D images, which are sent as recorded), the depth scale of its sensor (raw depth
// units per metre, e.g. 5000 for TUM files), and its sensor's depth noise, sigma(z) =
// depth_sigma0 + depth_sigma2 z^2 metres, with which the server weighs the keypoints' depth
// (both 0: not announced, the server keeps its default), and the trajectory camera: the camera
// whose poses the agent's trajectories give, in the colour camera's frame (translation in
// metres, unit quaternion x y z w; the colour camera itself unless the agent's config says
// otherwise, e.g. 7-Scenes, whose ground truth gives the depth camera's poses).
struct SessionCamera {
  double fx = 0, fy = 0, cx = 0, cy = 0;
  std::uint32_t width = 0, height = 0;
  double depth_scale = 0;
  std::array<double, 5> distortion{0, 0, 0, 0, 0};
  double depth_sigma0 = 0, depth_sigma2 = 0;
  std::array<double, 3> trajectory_t{0, 0, 0};
  std::array<double, 4> trajectory_q{0, 0, 0, 1};
  bool operator==(const SessionCamera&) const = default;
  bool HasDistortion() const;
  bool HasDepthNoise() const { return depth_sigma0 != 0 || depth_sigma2 != 0; }
  bool HasTrajectoryCamera() const;
};
// Refuses zero focal lengths, a depth scale <= 0, non-finite values, sizes beyond limits, a
// depth noise outside 0 < sigma0 <= 1 m, 0 <= sigma2 <= 1 (when announced), and a trajectory
// camera more than 1 m away or whose quaternion is not of unit length.
Status ValidateSessionCamera(const SessionCamera& camera);
std::string DescribeCamera(const SessionCamera& camera);
// The camera's fixed fields (fx fy cx cy, width height, depth scale) as Hello and the journal's
// info record lay them out; distortion and depth noise travel separately, only when given.
void PutSessionCamera(const SessionCamera& camera, ByteWriter* w);
Status ReadSessionCamera(ByteReader* r, SessionCamera* camera);
void PutSessionDistortion(const SessionCamera& camera, ByteWriter* w);  // 5 x f64
Status ReadSessionDistortion(ByteReader* r, SessionCamera* camera);
void PutSessionDepthNoise(const SessionCamera& camera, ByteWriter* w);  // 2 x f64
Status ReadSessionDepthNoise(ByteReader* r, SessionCamera* camera);
void PutSessionTrajectoryCamera(const SessionCamera& camera, ByteWriter* w);  // 7 x f64
Status ReadSessionTrajectoryCamera(ByteReader* r, SessionCamera* camera);

struct HelloMessage {
  std::uint8_t version = kProtocolVersion;
  // True until the agent's link has been welcomed once: the server then tells it where its
  // numbering continues (the agent may be a restarted process under a known name).
  bool fresh = true;
  std::string name;
  SessionCamera camera;
  // Resume point: the agent still holds messages first_seq .. next_seq - 1 (none if equal).
  std::uint64_t first_seq = 1;
  std::uint64_t next_seq = 1;
  Nonce agent_nonce{};
};

struct ChallengeMessage {
  bool key_required = false;
  Nonce server_nonce{};
};

struct AuthMessage {
  std::optional<Mac> proof;         // empty when the server requires no key
  AgentIdentity masked_identity{};  // the agent's identity XOR the session's identity pad
};

// With a key, the Welcome is the server's first tagged frame: its tag proves the key.
struct WelcomeMessage {
  AgentId agent;
  std::uint64_t last_stored_seq = 0;  // 0 = nothing stored yet
  std::uint32_t max_payload_bytes = 0;
  std::uint32_t idle_timeout_ms = 0;  // the server closes a session without frames this long
};

struct AckMessage {
  std::uint64_t last_stored_seq = 0;  // every message up to this one is journaled
};

struct ByeMessage {
  ByeReason reason = ByeReason::kNormal;
  std::string text;
};

std::vector<std::uint8_t> SerializeHello(const HelloMessage& m);
std::vector<std::uint8_t> SerializeChallenge(const ChallengeMessage& m);
std::vector<std::uint8_t> SerializeAuth(const AuthMessage& m);
std::vector<std::uint8_t> SerializeWelcome(const WelcomeMessage& m);
std::vector<std::uint8_t> SerializeAck(const AckMessage& m);
std::vector<std::uint8_t> SerializeBye(const ByeMessage& m);  // text cut to kMaxByeTextBytes

StatusOr<HelloMessage> ParseHello(ByteSpan payload);
StatusOr<ChallengeMessage> ParseChallenge(ByteSpan payload);
StatusOr<AuthMessage> ParseAuth(ByteSpan payload);
StatusOr<WelcomeMessage> ParseWelcome(ByteSpan payload);
StatusOr<AckMessage> ParseAck(ByteSpan payload);
StatusOr<ByeMessage> ParseBye(ByteSpan payload);
Status ParseHeartbeat(ByteSpan payload);  // must be empty

// A whole frame for a session message.
std::vector<std::uint8_t> EncodeSessionFrame(SessionType type, ByteSpan payload);

// Data frames: payload = u64 seq (little-endian) followed by the message bytes.
constexpr bool IsDataType(std::uint8_t type) { return type >= kFirstDataMessageType; }
constexpr bool IsKnownDataType(std::uint8_t type) {
  return type == static_cast<std::uint8_t>(MessageType::kKeyframe) ||
         type == static_cast<std::uint8_t>(MessageType::kPoseUpdate);
}
// `flags` only sets the frame header's flags (kFrameTagged: the caller appends the tag).
void AppendDataFrame(std::uint8_t type, std::uint64_t seq, ByteSpan message,
                     std::vector<std::uint8_t>* out, std::uint16_t flags = 0);
struct DataEnvelope {
  std::uint64_t seq = 0;
  ByteSpan message;  // a view into the payload
};
// kCorrupt if shorter than the sequence number, if seq is 0 (sequence numbers start at 1)
// or above kMaxSequenceNumber.
StatusOr<DataEnvelope> ParseDataEnvelope(ByteSpan payload);

}  // namespace ccmd
