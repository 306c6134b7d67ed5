#include "libccmd/net/session_messages.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "proto/crc32c.h"

namespace ccmd {
namespace {

constexpr std::uint8_t kHelloFresh = 1u << 0;
constexpr std::uint8_t kHelloDistortion = 1u << 1;        // 5 x f64 follow the depth scale
constexpr std::uint8_t kHelloDepthNoise = 1u << 2;        // 2 x f64 follow (after any distortion)
constexpr std::uint8_t kHelloTrajectoryCamera = 1u << 3;  // 7 x f64 follow (after any noise)
constexpr std::uint32_t kMaxImageSide = 16384;

void PutNonce(const std::array<std::uint8_t, 32>& n, ByteWriter* w) {
  w->PutBytes(n.data(), n.size());
}

Status ReadFlags(ByteReader* r, std::uint8_t known, const char* what, std::uint8_t* flags) {
  CCMD_RETURN_IF_ERROR(r->ReadU8(flags));
  if ((*flags & ~known) != 0) {
    return Corrupt(std::string(what) + " has unknown flag bits " + std::to_string(*flags));
  }
  return Status::Ok();
}

Status Finish(const ByteReader& r, const char* what) {
  Status s = r.ExpectEnd();
  if (!s.ok()) return s.WithContext(what);
  return Status::Ok();
}

}  // namespace

const char* ByeReasonName(ByeReason reason) {
  switch (reason) {
    case ByeReason::kNormal:
      return "normal";
    case ByeReason::kProtocolError:
      return "protocol error";
    case ByeReason::kUnsupportedVersion:
      return "unsupported version";
    case ByeReason::kAuthFailed:
      return "authentication failed";
    case ByeReason::kKeyMismatch:
      return "key configuration mismatch";
    case ByeReason::kServerFull:
      return "server full";
    case ByeReason::kTimeout:
      return "time-out";
    case ByeReason::kRefused:
      return "refused";
    case ByeReason::kLimitExceeded:
      return "limit exceeded";
    case ByeReason::kShuttingDown:
      return "shutting down";
    case ByeReason::kServerError:
      return "server error";
    case ByeReason::kReplaced:
      return "replaced";
    case ByeReason::kFrameAuthFailed:
      return "frame authentication failed";
  }
  return "unknown";
}

Status ValidateAgentName(std::string_view name) {
  if (name.empty() || name.size() > kMaxAgentNameBytes) {
    return InvalidArgument("agent name must have 1 to " + std::to_string(kMaxAgentNameBytes) +
                           " characters (got " + std::to_string(name.size()) + ")");
  }
  if (name[0] == '.') return InvalidArgument("agent name must not start with '.'");
  for (char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '.' || c == '_' || c == '-';
    if (!ok) {
      return InvalidArgument("agent name may contain only letters, digits, '.', '_' and '-'");
    }
  }
  return Status::Ok();
}

bool SessionCamera::HasDistortion() const {
  return std::any_of(distortion.begin(), distortion.end(), [](double k) { return k != 0; });
}

bool SessionCamera::HasTrajectoryCamera() const {
  return trajectory_t != std::array<double, 3>{0, 0, 0} ||
         trajectory_q != std::array<double, 4>{0, 0, 0, 1};
}

Status ValidateSessionCamera(const SessionCamera& c) {
  // A negative focal length is a convention (ICL-NUIM), not an error; zero or non-finite is.
  const bool finite = std::isfinite(c.fx) && std::isfinite(c.fy) && std::isfinite(c.cx) &&
                      std::isfinite(c.cy) && std::isfinite(c.depth_scale);
  if (!finite || c.fx == 0 || c.fy == 0 || c.depth_scale <= 0) {
    return InvalidArgument(
        "camera needs finite, non-zero fx and fy (either sign), finite cx, cy and a depth scale > "
        "0 (" +
        DescribeCamera(c) + ")");
  }
  for (const double k : c.distortion) {
    if (!std::isfinite(k)) return InvalidArgument("camera distortion coefficients must be finite");
  }
  if (c.HasDepthNoise() &&
      !(c.depth_sigma0 > 0 && c.depth_sigma0 <= 1 && c.depth_sigma2 >= 0 && c.depth_sigma2 <= 1)) {
    return InvalidArgument(
        "camera depth noise needs 0 < sigma0 <= 1 m and 0 <= sigma2 <= 1 (finite)");
  }
  const auto& t = c.trajectory_t;
  const auto& q = c.trajectory_q;
  const double t_norm = std::sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2]);
  const double q_norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  // Written as !(x <= limit) so that NaN fails too.
  if (!(t_norm <= 1.0) || !(std::fabs(q_norm - 1.0) <= 1e-6)) {
    return InvalidArgument(
        "camera trajectory frame needs a translation of at most 1 m and a unit quaternion");
  }
  if (c.width == 0 || c.height == 0 || c.width > kMaxImageSide || c.height > kMaxImageSide) {
    return InvalidArgument("camera image size must be 1.." + std::to_string(kMaxImageSide) +
                           " pixels per side");
  }
  return Status::Ok();
}

std::string DescribeCamera(const SessionCamera& c) {
  char text[160];
  std::snprintf(text, sizeof(text), "fx %.3f fy %.3f cx %.3f cy %.3f %ux%u depth scale %.1f", c.fx,
                c.fy, c.cx, c.cy, c.width, c.height, c.depth_scale);
  std::string out = text;
  if (c.HasDistortion()) {
    std::snprintf(text, sizeof(text), " distortion %.6f %.6f %.6f %.6f %.6f", c.distortion[0],
                  c.distortion[1], c.distortion[2], c.distortion[3], c.distortion[4]);
    out += text;
  }
  if (c.HasDepthNoise()) {
    std::snprintf(text, sizeof(text), " depth noise %.5f + %.5f z^2 m", c.depth_sigma0,
                  c.depth_sigma2);
    out += text;
  }
  if (c.HasTrajectoryCamera()) {
    std::snprintf(text, sizeof(text), " trajectories of the camera at (%.4f, %.4f, %.4f) m",
                  c.trajectory_t[0], c.trajectory_t[1], c.trajectory_t[2]);
    out += text;
  }
  return out;
}

void PutSessionCamera(const SessionCamera& c, ByteWriter* w) {
  w->PutF64(c.fx);
  w->PutF64(c.fy);
  w->PutF64(c.cx);
  w->PutF64(c.cy);
  w->PutU32(c.width);
  w->PutU32(c.height);
  w->PutF64(c.depth_scale);
}

Status ReadSessionCamera(ByteReader* r, SessionCamera* c) {
  CCMD_RETURN_IF_ERROR(r->ReadF64(&c->fx));
  CCMD_RETURN_IF_ERROR(r->ReadF64(&c->fy));
  CCMD_RETURN_IF_ERROR(r->ReadF64(&c->cx));
  CCMD_RETURN_IF_ERROR(r->ReadF64(&c->cy));
  CCMD_RETURN_IF_ERROR(r->ReadU32(&c->width));
  CCMD_RETURN_IF_ERROR(r->ReadU32(&c->height));
  return r->ReadF64(&c->depth_scale);
}

void PutSessionDistortion(const SessionCamera& c, ByteWriter* w) {
  for (const double k : c.distortion) w->PutF64(k);
}

Status ReadSessionDistortion(ByteReader* r, SessionCamera* c) {
  for (double& k : c->distortion) CCMD_RETURN_IF_ERROR(r->ReadF64(&k));
  return Status::Ok();
}

void PutSessionDepthNoise(const SessionCamera& c, ByteWriter* w) {
  w->PutF64(c.depth_sigma0);
  w->PutF64(c.depth_sigma2);
}

Status ReadSessionDepthNoise(ByteReader* r, SessionCamera* c) {
  CCMD_RETURN_IF_ERROR(r->ReadF64(&c->depth_sigma0));
  return r->ReadF64(&c->depth_sigma2);
}

void PutSessionTrajectoryCamera(const SessionCamera& c, ByteWriter* w) {
  for (const double v : c.trajectory_t) w->PutF64(v);
  for (const double v : c.trajectory_q) w->PutF64(v);
}

Status ReadSessionTrajectoryCamera(ByteReader* r, SessionCamera* c) {
  for (double& v : c->trajectory_t) CCMD_RETURN_IF_ERROR(r->ReadF64(&v));
  for (double& v : c->trajectory_q) CCMD_RETURN_IF_ERROR(r->ReadF64(&v));
  return Status::Ok();
}

std::vector<std::uint8_t> SerializeHello(const HelloMessage& m) {
  ByteWriter w(128);
  w.PutU8(m.version);
  const bool distortion = m.camera.HasDistortion(), noise = m.camera.HasDepthNoise(),
             trajectory = m.camera.HasTrajectoryCamera();
  w.PutU8((m.fresh ? kHelloFresh : 0) | (distortion ? kHelloDistortion : 0) |
          (noise ? kHelloDepthNoise : 0) | (trajectory ? kHelloTrajectoryCamera : 0));
  w.PutU8(static_cast<std::uint8_t>(m.name.size()));
  w.PutBytes(m.name.data(), m.name.size());
  PutSessionCamera(m.camera, &w);
  if (distortion) PutSessionDistortion(m.camera, &w);
  if (noise) PutSessionDepthNoise(m.camera, &w);
  if (trajectory) PutSessionTrajectoryCamera(m.camera, &w);
  w.PutU64(m.first_seq);
  w.PutU64(m.next_seq);
  PutNonce(m.agent_nonce, &w);
  return w.Take();
}

StatusOr<HelloMessage> ParseHello(ByteSpan payload) {
  ByteReader r(payload);
  HelloMessage m;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&m.version));
  if (m.version != kProtocolVersion) {
    return Unsupported("agent speaks protocol version " + std::to_string(m.version) +
                       ", this server version " + std::to_string(kProtocolVersion));
  }
  std::uint8_t flags;
  CCMD_RETURN_IF_ERROR(
      ReadFlags(&r, kHelloFresh | kHelloDistortion | kHelloDepthNoise | kHelloTrajectoryCamera,
                "hello", &flags));
  m.fresh = (flags & kHelloFresh) != 0;
  std::uint8_t name_size;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&name_size));
  ByteSpan name;
  CCMD_RETURN_IF_ERROR(r.ReadBytes(name_size, &name));
  m.name.assign(name.begin(), name.end());
  Status name_ok = ValidateAgentName(m.name);
  if (!name_ok.ok()) return Corrupt("hello: " + name_ok.message());
  CCMD_RETURN_IF_ERROR(ReadSessionCamera(&r, &m.camera));
  if (flags & kHelloDistortion) CCMD_RETURN_IF_ERROR(ReadSessionDistortion(&r, &m.camera));
  if (flags & kHelloDepthNoise) {
    CCMD_RETURN_IF_ERROR(ReadSessionDepthNoise(&r, &m.camera));
    if (!m.camera.HasDepthNoise()) return Corrupt("hello: depth noise flagged but zero");
  }
  if (flags & kHelloTrajectoryCamera) {
    CCMD_RETURN_IF_ERROR(ReadSessionTrajectoryCamera(&r, &m.camera));
    if (!m.camera.HasTrajectoryCamera()) {
      return Corrupt("hello: trajectory camera flagged but the colour camera's");
    }
  }
  Status camera_ok = ValidateSessionCamera(m.camera);
  if (!camera_ok.ok()) return Corrupt("hello: " + camera_ok.message());
  CCMD_RETURN_IF_ERROR(r.ReadU64(&m.first_seq));
  CCMD_RETURN_IF_ERROR(r.ReadU64(&m.next_seq));
  if (m.first_seq == 0 || m.next_seq < m.first_seq || m.next_seq > kMaxSequenceNumber) {
    return Corrupt("hello: resume point " + std::to_string(m.first_seq) + ".." +
                   std::to_string(m.next_seq) + " is not a range of sequence numbers >= 1");
  }
  CCMD_RETURN_IF_ERROR(r.ReadBytes(m.agent_nonce.size(), m.agent_nonce.data()));
  CCMD_RETURN_IF_ERROR(Finish(r, "hello"));
  return m;
}

std::vector<std::uint8_t> SerializeChallenge(const ChallengeMessage& m) {
  ByteWriter w(33);
  w.PutU8(m.key_required ? 1 : 0);
  PutNonce(m.server_nonce, &w);
  return w.Take();
}

StatusOr<ChallengeMessage> ParseChallenge(ByteSpan payload) {
  ByteReader r(payload);
  ChallengeMessage m;
  std::uint8_t mode;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&mode));
  if (mode > 1) return Corrupt("challenge: unknown authentication mode " + std::to_string(mode));
  m.key_required = mode == 1;
  CCMD_RETURN_IF_ERROR(r.ReadBytes(m.server_nonce.size(), m.server_nonce.data()));
  CCMD_RETURN_IF_ERROR(Finish(r, "challenge"));
  return m;
}

std::vector<std::uint8_t> SerializeAuth(const AuthMessage& m) {
  ByteWriter w(kMacSize + kIdentitySize);
  if (m.proof) w.PutBytes(m.proof->data(), m.proof->size());
  w.PutBytes(m.masked_identity.data(), m.masked_identity.size());
  return w.Take();
}

StatusOr<AuthMessage> ParseAuth(ByteSpan payload) {
  AuthMessage m;
  if (payload.size() != kIdentitySize && payload.size() != kMacSize + kIdentitySize) {
    return Corrupt("auth: " + std::to_string(payload.size()) + " bytes (expected " +
                   std::to_string(kIdentitySize) + " without a key or " +
                   std::to_string(kMacSize + kIdentitySize) + " with one)");
  }
  ByteReader r(payload);
  if (payload.size() > kIdentitySize) {
    m.proof.emplace();
    CCMD_RETURN_IF_ERROR(r.ReadBytes(m.proof->size(), m.proof->data()));
  }
  CCMD_RETURN_IF_ERROR(r.ReadBytes(m.masked_identity.size(), m.masked_identity.data()));
  return m;
}

std::vector<std::uint8_t> SerializeWelcome(const WelcomeMessage& m) {
  ByteWriter w(19);
  w.PutU8(0);  // flags
  w.PutU16(m.agent.value());
  w.PutU64(m.last_stored_seq);
  w.PutU32(m.max_payload_bytes);
  w.PutU32(m.idle_timeout_ms);
  return w.Take();
}

StatusOr<WelcomeMessage> ParseWelcome(ByteSpan payload) {
  ByteReader r(payload);
  WelcomeMessage m;
  std::uint8_t flags;
  CCMD_RETURN_IF_ERROR(ReadFlags(&r, 0, "welcome", &flags));
  std::uint16_t id;
  CCMD_RETURN_IF_ERROR(r.ReadU16(&id));
  m.agent = AgentId(id);
  CCMD_RETURN_IF_ERROR(r.ReadU64(&m.last_stored_seq));
  CCMD_RETURN_IF_ERROR(r.ReadU32(&m.max_payload_bytes));
  CCMD_RETURN_IF_ERROR(r.ReadU32(&m.idle_timeout_ms));
  if (m.max_payload_bytes <= kDataEnvelopeBytes) {
    return Corrupt("welcome: maximum payload of " + std::to_string(m.max_payload_bytes) +
                   " bytes leaves no room for a message");
  }
  if (m.last_stored_seq > kMaxSequenceNumber) {
    return Corrupt("welcome: last stored message " + std::to_string(m.last_stored_seq) +
                   " is beyond any sequence number");
  }
  CCMD_RETURN_IF_ERROR(Finish(r, "welcome"));
  return m;
}

std::vector<std::uint8_t> SerializeAck(const AckMessage& m) {
  ByteWriter w(8);
  w.PutU64(m.last_stored_seq);
  return w.Take();
}

StatusOr<AckMessage> ParseAck(ByteSpan payload) {
  ByteReader r(payload);
  AckMessage m;
  CCMD_RETURN_IF_ERROR(r.ReadU64(&m.last_stored_seq));
  CCMD_RETURN_IF_ERROR(Finish(r, "ack"));
  return m;
}

std::vector<std::uint8_t> SerializeBye(const ByeMessage& m) {
  const std::size_t n = std::min(m.text.size(), kMaxByeTextBytes);
  ByteWriter w(4 + n);
  w.PutU8(static_cast<std::uint8_t>(m.reason));
  w.PutU16(static_cast<std::uint16_t>(n));
  w.PutBytes(m.text.data(), n);
  return w.Take();
}

StatusOr<ByeMessage> ParseBye(ByteSpan payload) {
  ByteReader r(payload);
  ByeMessage m;
  std::uint8_t reason;
  CCMD_RETURN_IF_ERROR(r.ReadU8(&reason));
  if (reason > kLastByeReason) return Corrupt("bye: unknown reason " + std::to_string(reason));
  m.reason = static_cast<ByeReason>(reason);
  std::uint16_t n;
  CCMD_RETURN_IF_ERROR(r.ReadU16(&n));
  if (n > kMaxByeTextBytes) return Corrupt("bye: text of " + std::to_string(n) + " bytes");
  ByteSpan text;
  CCMD_RETURN_IF_ERROR(r.ReadBytes(n, &text));
  // The text goes into logs: keep printable ASCII only.
  m.text.reserve(n);
  for (std::uint8_t c : text) m.text.push_back(c >= 0x20 && c < 0x7F ? static_cast<char>(c) : '?');
  CCMD_RETURN_IF_ERROR(Finish(r, "bye"));
  return m;
}

Status ParseHeartbeat(ByteSpan payload) {
  if (!payload.empty()) return Corrupt("heartbeat with a payload");
  return Status::Ok();
}

std::vector<std::uint8_t> EncodeSessionFrame(SessionType type, ByteSpan payload) {
  return EncodeFrame(static_cast<std::uint8_t>(type), 0, payload);
}

void AppendDataFrame(std::uint8_t type, std::uint64_t seq, ByteSpan message,
                     std::vector<std::uint8_t>* out, std::uint16_t flags) {
  std::uint8_t seq_bytes[kDataEnvelopeBytes];
  for (std::size_t i = 0; i < kDataEnvelopeBytes; ++i) {
    seq_bytes[i] = static_cast<std::uint8_t>(seq >> (8 * i));
  }
  // Header and payload written in place (no copy of the message); the buffer grows
  // geometrically, room left for a tag, so appending many frames stays linear.
  const std::size_t payload_size = kDataEnvelopeBytes + message.size();
  const std::size_t needed = out->size() + kFrameHeaderSize + payload_size + kFrameTagSize;
  if (out->capacity() < needed) out->reserve(std::max(needed, 2 * out->capacity()));
  ByteWriter h(kFrameHeaderSize);
  h.PutBytes(kFrameMagic, sizeof(kFrameMagic));
  h.PutU8(kProtocolVersion);
  h.PutU8(type);
  h.PutU16(flags);
  h.PutU32(static_cast<std::uint32_t>(payload_size));
  h.PutU32(Crc32cExtend(Crc32c(seq_bytes, sizeof(seq_bytes)), message.data(), message.size()));
  h.PutU32(Crc32c(h.data(), 16));
  out->insert(out->end(), h.data(), h.data() + h.size());
  out->insert(out->end(), seq_bytes, seq_bytes + sizeof(seq_bytes));
  out->insert(out->end(), message.begin(), message.end());
}

StatusOr<DataEnvelope> ParseDataEnvelope(ByteSpan payload) {
  ByteReader r(payload);
  DataEnvelope e;
  CCMD_RETURN_IF_ERROR(r.ReadU64(&e.seq));
  if (e.seq == 0) return Corrupt("data message with sequence number 0");
  if (e.seq > kMaxSequenceNumber) {
    return Corrupt("data message with sequence number " + std::to_string(e.seq) + " (above 2^62)");
  }
  e.message = payload.subspan(kDataEnvelopeBytes);
  return e;
}

}  // namespace ccmd
