#pragma once

// Shared helpers for the transport tests: a consumer that records everything, synthetic
// messages with known content, and a raw client for sending arbitrary bytes.

#include <poll.h>

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "libccmd/net/agent_identity.h"
#include "libccmd/net/frame_auth.h"
#include "libccmd/net/message_consumer.h"
#include "libccmd/net/psk.h"
#include "libccmd/net/session_messages.h"
#include "libccmd/net/socket.h"
#include "libccmd/util/random.h"
#include "libccmd/util/timer.h"
#include "proto/frame.h"
#include "proto/messages.h"

namespace ccmd::nettest {

using Bytes = std::vector<std::uint8_t>;

inline SessionCamera TestCamera() {
  SessionCamera c;
  c.fx = 525;
  c.fy = 525;
  c.cx = 319.5;
  c.cy = 239.5;
  c.width = 640;
  c.height = 480;
  c.depth_scale = 5000;
  return c;
}

// A valid keyframe message whose content depends on (agent, index) only, so that a test can
// regenerate what an agent sent and compare byte for byte. `rgbd_bytes` of opaque colour and
// depth payload make it the size of a real keyframe.
inline Bytes SyntheticKeyframe(int agent, std::uint64_t index, int keypoints = 40,
                               std::size_t rgbd_bytes = 0) {
  Rng rng(MixSeed(static_cast<std::uint64_t>(agent) * 7919 + 1, index));
  KeyframeMessage m;
  m.id = KeyframeId(static_cast<std::uint32_t>(index));
  m.timestamp = 1000.0 + static_cast<double>(index) * 0.2;
  m.T_world_cam.t = {rng.Uniform(-1, 1), rng.Uniform(-1, 1), rng.Uniform(-1, 1)};
  if (index > 0) m.parent = KeyframeId(static_cast<std::uint32_t>(index - 1));
  for (int i = 0; i < keypoints; ++i) {
    WireKeypoint k;
    k.u = static_cast<float>(rng.Uniform(0, 640));
    k.v = static_cast<float>(rng.Uniform(0, 480));
    k.octave = static_cast<std::uint8_t>(rng.UniformInt(0, 7));
    k.angle_deg = static_cast<float>(rng.Uniform(0, 360));
    k.depth_m = static_cast<float>(rng.Uniform(0.5, 4));
    for (auto& b : k.descriptor) b = static_cast<std::uint8_t>(rng.Next());
    if (i % 2 == 0) k.map_point = MapPointId(static_cast<std::uint32_t>(i));
    m.keypoints.push_back(k);
  }
  if (rgbd_bytes > 0) {
    RgbdPayload p;
    p.downsample = 2;
    p.colour_jpeg.resize(rgbd_bytes / 2);
    p.depth.resize(rgbd_bytes - rgbd_bytes / 2);
    for (auto& b : p.colour_jpeg) b = static_cast<std::uint8_t>(rng.Next());
    for (auto& b : p.depth) b = static_cast<std::uint8_t>(rng.Next());
    m.rgbd = std::move(p);
  }
  return SerializeKeyframe(m).value();
}

struct Recorded {
  std::uint64_t seq;
  std::uint8_t type;
  Bytes payload;
  bool replayed;
};

// Records every call; thread-safe; lets a test wait for a number of messages.
class RecordingConsumer : public MessageConsumer {
 public:
  void OnAgentKnown(const AgentDescription& agent, bool from_journal) override {
    std::lock_guard<std::mutex> lock(mutex_);
    known_[agent.name] = agent;
    ids_[agent.id] = agent.name;
    if (from_journal) ++known_from_journal_;
    events_.push_back("known " + agent.name);
  }
  void OnAgentConnected(AgentId agent, std::uint64_t last) override {
    std::lock_guard<std::mutex> lock(mutex_);
    ++connected_[ids_[agent]];
    events_.push_back("connected " + ids_[agent] + " " + std::to_string(last));
  }
  void OnAgentDisconnected(AgentId agent, const std::string& reason) override {
    std::lock_guard<std::mutex> lock(mutex_);
    ++disconnected_[ids_[agent]];
    events_.push_back("disconnected " + ids_[agent] + ": " + reason);
    cv_.notify_all();
  }
  void OnMessage(DeliveredMessage m) override {
    std::lock_guard<std::mutex> lock(mutex_);
    messages_[ids_[m.agent]].push_back({m.seq, m.type, std::move(m.payload), m.replayed});
    ++total_;
    cv_.notify_all();
  }
  void OnReplayFinished(std::uint64_t n) override {
    std::lock_guard<std::mutex> lock(mutex_);
    replay_finished_ = true;
    replayed_count_ = n;
    events_.push_back("replay finished " + std::to_string(n));
  }

  // Waits until `total` messages have arrived over all agents (false on time-out).
  bool WaitForTotal(std::uint64_t total, double timeout_s) {
    std::unique_lock<std::mutex> lock(mutex_);
    return cv_.wait_for(lock, std::chrono::duration<double>(timeout_s),
                        [&] { return total_ >= total; });
  }
  bool WaitForDisconnects(const std::string& name, int n, double timeout_s) {
    std::unique_lock<std::mutex> lock(mutex_);
    return cv_.wait_for(lock, std::chrono::duration<double>(timeout_s),
                        [&] { return disconnected_[name] >= n; });
  }

  std::map<std::string, std::vector<Recorded>> messages() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return messages_;
  }
  std::vector<std::string> events() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return events_;
  }
  std::map<std::string, AgentDescription> known() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return known_;
  }
  std::uint64_t total() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return total_;
  }
  int known_from_journal() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return known_from_journal_;
  }

 private:
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::map<std::string, AgentDescription> known_;
  std::map<AgentId, std::string> ids_;
  std::map<std::string, std::vector<Recorded>> messages_;
  std::map<std::string, int> connected_, disconnected_;
  std::vector<std::string> events_;
  std::uint64_t total_ = 0;
  int known_from_journal_ = 0;
  bool replay_finished_ = false;
  std::uint64_t replayed_count_ = 0;
};

// A blocking raw TCP client for feeding the server arbitrary bytes.
class RawClient {
 public:
  bool Connect(std::uint16_t port) {
    StatusOr<UniqueFd> fd = ConnectTcp(HostPort{"127.0.0.1", port}, 5.0);
    if (!fd.ok()) return false;
    fd_ = std::move(*fd);
    return true;
  }
  bool SendBytes(const Bytes& bytes) {
    std::size_t done = 0;
    const double deadline = MonotonicSeconds() + 5;
    while (done < bytes.size() && MonotonicSeconds() < deadline) {
      StatusOr<std::size_t> n = WriteSome(fd_.get(), bytes.data() + done, bytes.size() - done);
      if (!n.ok()) return false;
      done += *n;
      if (*n == 0) {
        pollfd p{fd_.get(), POLLOUT, 0};
        ::poll(&p, 1, 100);
      }
    }
    return done == bytes.size();
  }
  // Reads frames until the server closes the connection (or timeout_s passes).
  // Returns false on time-out.
  bool ReadUntilClosed(std::vector<Frame>* frames, double timeout_s) {
    FrameDecoder decoder;
    std::vector<std::uint8_t> buffer(1 << 16);
    const double deadline = MonotonicSeconds() + timeout_s;
    while (true) {
      const double left = deadline - MonotonicSeconds();
      if (left <= 0) return false;
      pollfd p{fd_.get(), POLLIN, 0};
      ::poll(&p, 1, static_cast<int>(left * 1e3) + 1);
      StatusOr<std::size_t> n = ReadSome(fd_.get(), buffer.data(), buffer.size());
      if (!n.ok()) return true;  // closed (or reset) by the server
      if (*n == 0) continue;
      decoder.Feed(ByteSpan(buffer.data(), *n), frames).IgnoreError();
    }
  }
  // Reads until one frame has arrived.
  std::optional<Frame> ReadFrame(double timeout_s) {
    std::vector<std::uint8_t> buffer(1);
    const double deadline = MonotonicSeconds() + timeout_s;
    while (pending_.empty()) {
      const double left = deadline - MonotonicSeconds();
      if (left <= 0) return std::nullopt;
      pollfd p{fd_.get(), POLLIN, 0};
      ::poll(&p, 1, static_cast<int>(left * 1e3) + 1);
      StatusOr<std::size_t> n = ReadSome(fd_.get(), buffer.data(), buffer.size());
      if (!n.ok()) return std::nullopt;
      if (*n == 0) continue;
      std::vector<Frame> frames;
      decoder_.Feed(ByteSpan(buffer.data(), *n), &frames).IgnoreError();
      for (Frame& f : frames) pending_.push_back(std::move(f));
    }
    Frame f = std::move(pending_.front());
    pending_.erase(pending_.begin());
    return f;
  }
  int fd() const { return fd_.get(); }
  void Close() { fd_.Reset(); }

  // After RawHandshake: frames in the session, tagged when it is keyed.
  bool SendSessionFrame(SessionType type, const Bytes& payload) {
    Bytes out;
    auth.AppendFrame(static_cast<std::uint8_t>(type), payload, &out);
    return SendBytes(out);
  }
  bool SendData(std::uint8_t type, std::uint64_t seq, const Bytes& message) {
    Bytes out;
    auth.AppendDataFrame(type, seq, message, &out);
    return SendBytes(out);
  }

  SessionAuth auth;  // the session's frame authentication (keyless until a keyed welcome)
  AgentIdentity identity{};

 private:
  UniqueFd fd_;
  FrameDecoder decoder_;
  std::vector<Frame> pending_;
};

// A deterministic identity for raw clients: the same `seed`, the same agent instance.
inline AgentIdentity TestIdentity(int seed) {
  AgentIdentity id;
  for (std::size_t i = 0; i < id.size(); ++i) id[i] = static_cast<std::uint8_t>(seed * 131 + i);
  return id;
}

// The server's answer to a raw handshake: the Welcome, or the Bye refusing it.
struct RawAnswer {
  std::optional<WelcomeMessage> welcome;
  std::optional<ByeMessage> bye;
};

// Completes a handshake by hand (key "" for a keyless server) as the agent instance
// c->identity, announcing `hello` (its nonce is set here). Leaves c->auth ready for the
// session.
inline RawAnswer RawHandshakeWith(RawClient* c, std::uint16_t port, HelloMessage hello,
                                  const std::string& key = "") {
  RawAnswer answer;
  if (!c->Connect(port)) return answer;
  for (int i = 0; i < 32; ++i) hello.agent_nonce[i] = static_cast<std::uint8_t>(i * 3);
  const Bytes hello_payload = SerializeHello(hello);
  if (!c->SendBytes(EncodeSessionFrame(SessionType::kHello, hello_payload))) return answer;
  std::optional<Frame> challenge = c->ReadFrame(5);
  if (!challenge) return answer;
  StatusOr<ChallengeMessage> ch = ParseChallenge(challenge->payload);
  if (!ch.ok()) return answer;
  const SessionKeys keys =
      DeriveSessionKeys(key, hello.agent_nonce, ch->server_nonce, hello_payload);
  AuthMessage auth;
  if (!key.empty()) auth.proof = AgentProof(key, ch->server_nonce, hello_payload);
  auth.masked_identity = MaskIdentity(c->identity, keys.identity_pad);
  if (!c->SendBytes(EncodeSessionFrame(SessionType::kAuth, SerializeAuth(auth)))) {
    return answer;
  }
  c->auth = SessionAuth(FrameRole::kAgent, keys, !key.empty());
  std::optional<Frame> reply = c->ReadFrame(5);
  if (!reply || !c->auth.Verify(*reply).ok()) return answer;
  if (reply->type == static_cast<std::uint8_t>(SessionType::kBye)) {
    StatusOr<ByeMessage> bye = ParseBye(reply->payload);
    if (bye.ok()) answer.bye = *bye;
    return answer;
  }
  if (reply->type != static_cast<std::uint8_t>(SessionType::kWelcome)) return answer;
  StatusOr<WelcomeMessage> w = ParseWelcome(reply->payload);
  if (w.ok()) answer.welcome = *w;
  return answer;
}

// A fresh agent named `name` with the test camera; returns the Welcome.
inline std::optional<WelcomeMessage> RawHandshake(RawClient* c, std::uint16_t port,
                                                  const std::string& name,
                                                  const std::string& key = "") {
  HelloMessage hello;
  hello.name = name;
  hello.camera = TestCamera();
  return RawHandshakeWith(c, port, hello, key).welcome;
}

// The Bye in a list of frames, if any.
inline std::optional<ByeMessage> FindBye(const std::vector<Frame>& frames) {
  for (const Frame& f : frames) {
    if (f.type == static_cast<std::uint8_t>(SessionType::kBye)) {
      StatusOr<ByeMessage> bye = ParseBye(f.payload);
      if (bye.ok()) return *bye;
    }
  }
  return std::nullopt;
}

}  // namespace ccmd::nettest
