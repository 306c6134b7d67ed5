#include "libccmd/net/agent_link.h"

#include <poll.h>
#include <sys/socket.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <functional>

#include "libccmd/net/psk.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/random.h"
#include "libccmd/util/timer.h"

namespace ccmd {
namespace {

constexpr std::size_t kReadChunk = 64 << 10;
// Frames prepared for writing at a time: enough to keep the socket busy, small enough that
// an ack is read between batches.
constexpr std::size_t kOutputBatch = 256 << 10;
constexpr double kByeLingerSeconds = 1.0;
// A server rejecting our frames this many times in a row (authenticated byes saying
// "protocol error") will not change its mind.
constexpr int kMaxProtocolErrorsInARow = 5;

int PollMillis(double seconds) {
  return static_cast<int>(std::clamp(std::ceil(seconds * 1e3), 0.0, 1e6));
}

// What a server's Bye means for the link: terminal configuration errors, or retry.
Status StatusFromBye(const ByeMessage& bye) {
  const std::string text = std::string("server closed the session (") + ByeReasonName(bye.reason) +
                           ")" + (bye.text.empty() ? "" : ": " + bye.text);
  switch (bye.reason) {
    case ByeReason::kAuthFailed:
    case ByeReason::kKeyMismatch:
      return PermissionDenied(text);
    case ByeReason::kUnsupportedVersion:
      return Unsupported(text);
    case ByeReason::kRefused:
      return InvalidArgument(text);
    case ByeReason::kProtocolError:
      return Corrupt(text);
    default:
      return Unavailable(text);
  }
}

bool IsTerminal(const Status& s) {
  return s.code() == StatusCode::kPermissionDenied || s.code() == StatusCode::kUnsupported ||
         s.code() == StatusCode::kInvalidArgument;
}

}  // namespace

Status AgentLinkOptions::Validate() const {
  CCMD_RETURN_IF_ERROR(ParseHostPort(server).status());
  CCMD_RETURN_IF_ERROR(ValidateAgentName(name));
  CCMD_RETURN_IF_ERROR(ValidateSessionCamera(camera));
  if (!psk.empty() && psk.size() < kMinPskBytes) {
    return InvalidArgument("the pre-shared key needs at least " + std::to_string(kMinPskBytes) +
                           " bytes");
  }
  if (memory_limit_bytes == 0) return InvalidArgument("memory_limit_bytes must be positive");
  if (!(connect_timeout_s > 0) || !(handshake_timeout_s > 0) || !(heartbeat_interval_s > 0)) {
    return InvalidArgument("time-outs must be positive");
  }
  if (!(backoff_initial_s > 0) || backoff_max_s < backoff_initial_s) {
    return InvalidArgument("backoff needs 0 < initial <= max");
  }
  if (!(max_send_bytes_per_s >= 0)) return InvalidArgument("the send rate limit must be >= 0");
  return Status::Ok();
}

void AgentLinkOptions::Describe(OptionsWriter* out) const {
  out->Add("server", server);
  out->Add("name", name);
  out->Add("camera.fx", camera.fx);
  out->Add("camera.fy", camera.fy);
  out->Add("camera.cx", camera.cx);
  out->Add("camera.cy", camera.cy);
  out->Add("camera.width", camera.width);
  out->Add("camera.height", camera.height);
  out->Add("camera.depth_scale", camera.depth_scale);
  out->Add("camera.distortion",
           std::vector<double>(camera.distortion.begin(), camera.distortion.end()));
  out->Add("psk", psk.empty() ? "none" : "set");
  out->Add("spill_dir", spill_dir);
  out->Add("memory_limit_bytes", memory_limit_bytes);
  out->Add("spill_limit_bytes", spill_limit_bytes);
  out->Add("connect_timeout_s", connect_timeout_s);
  out->Add("handshake_timeout_s", handshake_timeout_s);
  out->Add("backoff_initial_s", backoff_initial_s);
  out->Add("backoff_max_s", backoff_max_s);
  out->Add("heartbeat_interval_s", heartbeat_interval_s);
  out->Add("jitter_seed", jitter_seed);
  out->Add("max_send_bytes_per_s", max_send_bytes_per_s);
}

StatusOr<std::unique_ptr<AgentLink>> AgentLink::Create(AgentLinkOptions options) {
  CCMD_RETURN_IF_ERROR(options.Validate());
  CCMD_ASSIGN_OR_RETURN(HostPort address, ParseHostPort(options.server));
  std::unique_ptr<SpillStore> spill;
  if (!options.spill_dir.empty()) {
    CCMD_ASSIGN_OR_RETURN(spill, SpillStore::Open(options.spill_dir, options.spill_limit_bytes));
  }
  std::string identity_path = options.identity_file;
  if (identity_path.empty() && !options.spill_dir.empty()) {
    identity_path = JoinPath(options.spill_dir, "identity");
  }
  CCMD_ASSIGN_OR_RETURN(const AgentIdentity identity, identity_path.empty()
                                                          ? NewIdentity()
                                                          : LoadOrCreateIdentity(identity_path));
  std::unique_ptr<AgentLink> link(
      new AgentLink(std::move(options), std::move(address), std::move(spill), identity));
  if (!link->wake_.valid()) return IoError("eventfd: " + std::string(std::strerror(errno)));
  link->thread_ = std::thread([l = link.get()] { l->Run(); });
  return link;
}

AgentLink::AgentLink(AgentLinkOptions options, HostPort address, std::unique_ptr<SpillStore> spill,
                     AgentIdentity identity)
    : options_(std::move(options)),
      address_(std::move(address)),
      identity_(identity),
      spill_(std::move(spill)) {}

AgentLink::~AgentLink() { Close(); }

void AgentLink::Close() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (closed_) return;
    closed_ = true;
    stopping_ = true;
  }
  cv_.notify_all();
  wake_.Signal();
  if (thread_.joinable()) thread_.join();
}

StatusOr<std::uint64_t> AgentLink::Refuse(Status why) {
  ++stats_.refused;
  return why;
}

StatusOr<std::uint64_t> AgentLink::Send(std::uint8_t type, std::vector<std::uint8_t> message) {
  std::uint64_t local;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!IsDataType(type)) {
      return Refuse(
          InvalidArgument("type " + std::to_string(type) + " is not a data message type"));
    }
    if (!terminal_.ok()) return Refuse(terminal_);
    if (stopping_) return Refuse(Cancelled("the link is closed"));
    if (message.size() > max_message_bytes_) {
      return Refuse(InvalidArgument("message of " + std::to_string(message.size()) +
                                    " bytes exceeds the server's limit of " +
                                    std::to_string(max_message_bytes_)));
    }
    local = next_local_;
    const bool fits =
        memory_.empty() || memory_bytes_ + message.size() <= options_.memory_limit_bytes;
    if ((spill_ && !spill_->empty()) || !fits) {
      if (!spill_) {
        return Refuse(OutOfRange("resend buffer full: " + std::to_string(memory_bytes_) +
                                 " bytes unacknowledged (memory limit " +
                                 std::to_string(options_.memory_limit_bytes) +
                                 ", no spill folder)"));
      }
      if (Status pushed = spill_->Push(type, local, message); !pushed.ok()) return Refuse(pushed);
      ++stats_.spilled;
    } else {
      memory_bytes_ += message.size();
      memory_.push_back(Entry{
          local, type, std::make_shared<const std::vector<std::uint8_t>>(std::move(message))});
    }
    ++next_local_;
    ++stats_.queued;
  }
  wake_.Signal();
  return local;
}

Status AgentLink::Flush(double timeout_s) {
  std::unique_lock<std::mutex> lock(mutex_);
  const bool done = cv_.wait_for(lock, std::chrono::duration<double>(timeout_s), [&] {
    return acked_local_ + 1 == next_local_ || !terminal_.ok() || stopping_;
  });
  if (!terminal_.ok()) return terminal_;
  if (acked_local_ + 1 == next_local_) return Status::Ok();
  if (!done) {
    return Timeout(std::to_string(next_local_ - 1 - acked_local_) +
                   " messages still unacknowledged after " + std::to_string(timeout_s) + " s" +
                   (stats_.last_error.empty() ? "" : " (last error: " + stats_.last_error + ")"));
  }
  return Cancelled("the link is closed");
}

AgentLinkStats AgentLink::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  AgentLinkStats s = stats_;
  s.acked = acked_local_;
  s.unacked = next_local_ - 1 - acked_local_;
  s.memory_bytes = memory_bytes_;
  s.spill_bytes = spill_ ? spill_->disk_bytes() : 0;
  return s;
}

Status AgentLink::status() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return terminal_;
}

void AgentLink::RefillLocked() {
  while (spill_ && !spill_->empty() &&
         (memory_.empty() ||
          memory_bytes_ + spill_->front_message_bytes() <= options_.memory_limit_bytes)) {
    StatusOr<SpilledMessage> m = spill_->Pop();
    if (!m.ok()) {
      terminal_ = m.status().WithContext("reading back spilled messages");
      return;
    }
    memory_bytes_ += m->message.size();
    memory_.push_back(Entry{
        m->seq, m->type, std::make_shared<const std::vector<std::uint8_t>>(std::move(m->message))});
  }
}

void AgentLink::ReleaseLocked(std::uint64_t last) {
  while (!memory_.empty() && memory_.front().local <= last) {
    memory_bytes_ -= memory_.front().message->size();
    memory_.pop_front();
  }
  acked_local_ = last;
  RefillLocked();
}

void AgentLink::Run() {
  double backoff = options_.backoff_initial_s;
  std::hash<std::string> hash;
  Rng rng(options_.jitter_seed ^ hash(options_.name));
  std::string last_logged;
  while (true) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (stopping_) break;
    }
    const Status s = Session(&backoff);
    double wait = 0;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stats_.connected = false;
      if (stopping_) break;
      ++stats_.failed_attempts;
      stats_.last_error = s.ToString();
      // protocol_errors_in_a_row_ counts the server's authenticated protocol-error byes only:
      // bytes damaged or injected on the way must not end the link.
      if (IsTerminal(s) || protocol_errors_in_a_row_ >= kMaxProtocolErrorsInARow) {
        terminal_ = s;
        CCMD_LOG(ERROR) << "agent '" << options_.name << "': link to " << options_.server
                        << " stopped: " << s.ToString();
        cv_.notify_all();
        break;
      }
      // Full jitter within [backoff/2, backoff]: agents that lost the server together do not
      // come back in lock step.
      wait = backoff * (0.5 + 0.5 * rng.Uniform());
      backoff = std::min(backoff * 2, options_.backoff_max_s);
    }
    if (s.ToString() != last_logged) {
      CCMD_LOG(WARNING) << "agent '" << options_.name << "': " << s.ToString()
                        << "; retrying (backoff up to " << options_.backoff_max_s << " s)";
      last_logged = s.ToString();
    }
    std::unique_lock<std::mutex> lock(mutex_);
    cv_.wait_for(lock, std::chrono::duration<double>(wait), [&] { return stopping_; });
  }
}

Status AgentLink::WriteBlocking(int fd, ByteSpan bytes, double deadline, bool interruptible) {
  std::size_t done = 0;
  while (done < bytes.size()) {
    CCMD_ASSIGN_OR_RETURN(const std::size_t n,
                          WriteSome(fd, bytes.data() + done, bytes.size() - done));
    done += n;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stats_.bytes_sent += n;
    }
    if (done == bytes.size()) break;
    const double left = deadline - MonotonicSeconds();
    if (left <= 0) return Timeout("writing to the server timed out");
    pollfd fds[2] = {{fd, POLLOUT, 0}, {wake_.fd(), POLLIN, 0}};
    if (::poll(fds, interruptible ? 2 : 1, PollMillis(left)) < 0 && errno != EINTR) {
      return IoError(std::string("poll: ") + std::strerror(errno));
    }
    if (interruptible && (fds[1].revents & POLLIN)) {
      wake_.Drain();
      std::lock_guard<std::mutex> lock(mutex_);
      if (stopping_) return Cancelled("link closing");
    }
  }
  return Status::Ok();
}

StatusOr<Frame> AgentLink::ReadFrameBlocking(Wire* wire, double deadline) {
  std::vector<std::uint8_t> buffer(kReadChunk);
  std::vector<Frame> frames;
  while (wire->inbox.empty()) {
    const double left = deadline - MonotonicSeconds();
    if (left <= 0) return Timeout("the server did not answer the handshake in time");
    pollfd fds[2] = {{wire->fd, POLLIN, 0}, {wake_.fd(), POLLIN, 0}};
    if (::poll(fds, 2, PollMillis(left)) < 0 && errno != EINTR) {
      return IoError(std::string("poll: ") + std::strerror(errno));
    }
    if (fds[1].revents & POLLIN) {
      wake_.Drain();
      std::lock_guard<std::mutex> lock(mutex_);
      if (stopping_) return Cancelled("link closing");
    }
    if (!(fds[0].revents & (POLLIN | POLLHUP | POLLERR))) continue;
    StatusOr<std::size_t> n = ReadSome(wire->fd, buffer.data(), buffer.size());
    if (!n.ok()) {
      if (n.status().code() == StatusCode::kEndOfStream) {
        return Unavailable("the server closed the connection during the handshake");
      }
      return n.status();
    }
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stats_.bytes_received += *n;
    }
    frames.clear();
    const Status fed = wire->decoder.Feed(ByteSpan(buffer.data(), *n), &frames);
    for (Frame& f : frames) wire->inbox.push_back(std::move(f));
    if (!fed.ok() && wire->inbox.empty()) return fed.WithContext("from the server");
  }
  Frame f = std::move(wire->inbox.front());
  wire->inbox.pop_front();
  return f;
}

Status AgentLink::Session(double* backoff) {
  CCMD_ASSIGN_OR_RETURN(UniqueFd socket,
                        ConnectTcp(address_, options_.connect_timeout_s, wake_.fd(), [this] {
                          std::lock_guard<std::mutex> lock(mutex_);
                          return stopping_;
                        }));
  Wire wire;
  wire.fd = socket.get();
  CCMD_RETURN_IF_ERROR(Handshake(&wire));
  *backoff = options_.backoff_initial_s;
  return Stream(&wire);
}

Status AgentLink::ServerBye(const ByeMessage& bye, bool authenticated) {
  if (!authenticated && bye.reason == ByeReason::kRefused) {
    // A refusal ends the link for good: only an authenticated one is believed.
    return Corrupt("an unauthenticated refusal from the server (" + bye.text + ")");
  }
  if (authenticated && bye.reason == ByeReason::kProtocolError) {
    std::lock_guard<std::mutex> lock(mutex_);
    ++protocol_errors_in_a_row_;
  }
  return StatusFromBye(bye);
}

Status AgentLink::Handshake(Wire* wire) {
  const double deadline = MonotonicSeconds() + options_.handshake_timeout_s;
  const bool keyed = !options_.psk.empty();
  HelloMessage hello;
  hello.name = options_.name;
  hello.camera = options_.camera;
  CCMD_RETURN_IF_ERROR(RandomNonce(&hello.agent_nonce));
  {
    std::lock_guard<std::mutex> lock(mutex_);
    hello.fresh = !welcomed_once_;
    hello.first_seq = acked_local_ + 1 + offset_;
    hello.next_seq = next_local_ + offset_;
  }
  const int fd = wire->fd;
  // The proof and the session keys bind these exact bytes: a hello altered on the way fails.
  const std::vector<std::uint8_t> hello_payload = SerializeHello(hello);
  CCMD_RETURN_IF_ERROR(
      WriteBlocking(fd, EncodeSessionFrame(SessionType::kHello, hello_payload), deadline));
  auto refuse = [&](const std::string& text, ByeReason reason) {
    const std::vector<std::uint8_t> bye =
        EncodeSessionFrame(SessionType::kBye, SerializeBye({reason, text}));
    WriteBlocking(fd, bye, deadline).IgnoreError();
    return PermissionDenied(text);
  };

  CCMD_ASSIGN_OR_RETURN(const Frame challenge_frame, ReadFrameBlocking(wire, deadline));
  if (challenge_frame.tag) return Corrupt("a tagged frame from the server before the auth");
  if (challenge_frame.type == static_cast<std::uint8_t>(SessionType::kBye)) {
    CCMD_ASSIGN_OR_RETURN(const ByeMessage bye, ParseBye(challenge_frame.payload));
    return ServerBye(bye, /*authenticated=*/!keyed);
  }
  if (challenge_frame.type != static_cast<std::uint8_t>(SessionType::kChallenge)) {
    return Corrupt("the server sent message type " + std::to_string(challenge_frame.type) +
                   " instead of a challenge");
  }
  CCMD_ASSIGN_OR_RETURN(const ChallengeMessage challenge, ParseChallenge(challenge_frame.payload));
  if (challenge.key_required && !keyed) {
    return refuse(
        "the server requires a pre-shared key and this agent has none: give it the "
        "deployment's key with --psk-file FILE or the environment variable CCMD_PSK",
        ByeReason::kKeyMismatch);
  }
  if (!challenge.key_required && keyed) {
    return refuse(
        "this agent has a pre-shared key but the server runs without one, so it cannot prove "
        "who it is; start the server with the same key (or run both without a key on "
        "loopback)",
        ByeReason::kKeyMismatch);
  }
  const SessionKeys keys =
      DeriveSessionKeys(options_.psk, hello.agent_nonce, challenge.server_nonce, hello_payload);
  AuthMessage auth;
  if (keyed) {
    auth.proof = AgentProof(options_.psk, challenge.server_nonce, hello_payload);
  }
  auth.masked_identity = MaskIdentity(identity_, keys.identity_pad);
  CCMD_RETURN_IF_ERROR(
      WriteBlocking(fd, EncodeSessionFrame(SessionType::kAuth, SerializeAuth(auth)), deadline));
  wire->auth = SessionAuth(FrameRole::kAgent, keys, keyed);
  CCMD_ASSIGN_OR_RETURN(const WelcomeMessage welcome, AwaitWelcome(wire, deadline));
  wire->idle_timeout_s = std::max(0.1, welcome.idle_timeout_ms / 1e3);

  std::uint64_t released_first = 0, released_last = 0;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!welcomed_once_) {
      // A fresh link continues the numbering the server has for this agent name.
      offset_ = welcome.last_stored_seq - acked_local_;
      welcomed_once_ = true;
    } else {
      const std::uint64_t last_local =
          welcome.last_stored_seq >= offset_ ? welcome.last_stored_seq - offset_ : 0;
      if (last_local >= next_local_) {
        return Corrupt("the server says it stored message " +
                       std::to_string(welcome.last_stored_seq) + ", beyond what this agent sent");
      }
      if (last_local > acked_local_) {
        released_first = acked_local_ + 1;
        released_last = last_local;
        ReleaseLocked(last_local);
      }
    }
    max_message_bytes_ = welcome.max_payload_bytes - kDataEnvelopeBytes;
    stats_.connected = true;
    stats_.agent = welcome.agent;
    ++stats_.sessions;
    next_send_ = acked_local_ + 1;
    protocol_errors_in_a_row_ = 0;
  }
  cv_.notify_all();
  if (released_last > 0 && options_.on_acked) options_.on_acked(released_first, released_last);
  CCMD_LOG(INFO) << "agent '" << options_.name << "' connected to " << options_.server
                 << " as agent " << welcome.agent << "; server stored up to message "
                 << welcome.last_stored_seq << (keyed ? "" : " (no key: frames not authenticated)");
  return Status::Ok();
}

StatusOr<WelcomeMessage> AgentLink::AwaitWelcome(Wire* wire, double deadline) {
  CCMD_ASSIGN_OR_RETURN(const Frame f, ReadFrameBlocking(wire, deadline));
  const bool keyed = wire->auth.keyed();
  bool authenticated = !keyed;
  if (f.tag) {
    const Status verified = wire->auth.Verify(f);
    if (!verified.ok()) {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.auth_failures;
      // The server would have refused our proof had its key differed: this is tampering on
      // the way (or a broken server), not a configuration error, so the link retries.
      return Unavailable("the server's answer failed authentication: " + verified.message());
    }
    authenticated = true;
  }
  if (f.type == static_cast<std::uint8_t>(SessionType::kBye)) {
    CCMD_ASSIGN_OR_RETURN(const ByeMessage bye, ParseBye(f.payload));
    return ServerBye(bye, authenticated);
  }
  if (!authenticated) return Corrupt("the server's welcome carries no authentication tag");
  if (f.type != static_cast<std::uint8_t>(SessionType::kWelcome)) {
    return Corrupt("the server sent message type " + std::to_string(f.type) +
                   " instead of a welcome");
  }
  return ParseWelcome(f.payload);
}

Status AgentLink::HandleServerFrame(const Frame& frame) {
  switch (frame.type) {
    case static_cast<std::uint8_t>(SessionType::kAck): {
      CCMD_ASSIGN_OR_RETURN(const AckMessage ack, ParseAck(frame.payload));
      std::uint64_t first = 0, last = 0;
      {
        std::lock_guard<std::mutex> lock(mutex_);
        if (ack.last_stored_seq < offset_) break;
        const std::uint64_t local = ack.last_stored_seq - offset_;
        if (local > highest_sent_) {
          return Corrupt("the server acknowledged message " + std::to_string(ack.last_stored_seq) +
                         " which was never sent");
        }
        if (local <= acked_local_) break;
        first = acked_local_ + 1;
        last = local;
        ReleaseLocked(local);
        protocol_errors_in_a_row_ = 0;
      }
      cv_.notify_all();
      if (options_.on_acked) options_.on_acked(first, last);
      break;
    }
    case static_cast<std::uint8_t>(SessionType::kHeartbeat):
      CCMD_RETURN_IF_ERROR(ParseHeartbeat(frame.payload));
      break;
    case static_cast<std::uint8_t>(SessionType::kBye): {
      CCMD_ASSIGN_OR_RETURN(const ByeMessage bye, ParseBye(frame.payload));
      return ServerBye(bye, /*authenticated=*/true);
    }
    default:
      if (IsKnownDataType(frame.type)) {
        // Messages from the server to agents are not used yet: accepted and ignored.
        CCMD_LOG(DEBUG) << "ignoring a data message of type " << int{frame.type}
                        << " from the server";
        break;
      }
      return Corrupt("unexpected message type " + std::to_string(frame.type) + " from the server");
  }
  return Status::Ok();
}

Status AgentLink::HandleInbox(Wire* wire) {
  while (!wire->inbox.empty()) {
    const Frame f = std::move(wire->inbox.front());
    wire->inbox.pop_front();
    // Nothing is acted on before its tag is checked: a forged ack would drop data the
    // server never stored.
    const Status verified = wire->auth.Verify(f);
    if (!verified.ok()) {
      if (verified.code() != StatusCode::kPermissionDenied) return verified;
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.auth_failures;
      return Unavailable("a frame from the server failed authentication (" + verified.message() +
                         "); reconnecting");
    }
    CCMD_RETURN_IF_ERROR(HandleServerFrame(f));
  }
  return Status::Ok();
}

Status AgentLink::Stream(Wire* wire) {
  const int fd = wire->fd;
  const double idle_timeout_s = wire->idle_timeout_s;
  const double heartbeat = std::min(options_.heartbeat_interval_s, idle_timeout_s / 3);
  std::vector<std::uint8_t> out;
  std::size_t out_pos = 0;
  std::vector<std::uint8_t> buffer(kReadChunk);
  std::vector<Frame> frames;
  double last_frame = MonotonicSeconds();  // the last complete frame from the server
  double last_tx = last_frame;
  // Pacing under a rate limit, in user space: the kernel's SO_MAX_PACING_RATE does not hold on
  // loopback or with large offloaded segments. Writes of at most `pace_chunk` bytes each, the
  // next one not before `pace_ready`.
  const double rate = options_.max_send_bytes_per_s;
  const std::size_t pace_chunk =
      rate > 0 ? static_cast<std::size_t>(std::clamp(rate * 0.02, 1024.0, 65536.0)) : 0;
  double pace_ready = last_frame;
  while (true) {
    CCMD_RETURN_IF_ERROR(HandleInbox(wire));
    // Fill the output with the next messages in order.
    if (out_pos == out.size()) {
      out.clear();
      out_pos = 0;
    }
    {
      std::unique_lock<std::mutex> lock(mutex_);
      if (stopping_) {
        lock.unlock();
        // Finish the frame in progress, then say bye, so the server logs an orderly end.
        wire->auth.AppendFrame(static_cast<std::uint8_t>(SessionType::kBye),
                               SerializeBye({ByeReason::kNormal, "agent closing"}), &out);
        WriteBlocking(fd, ByteSpan(out).subspan(out_pos), MonotonicSeconds() + kByeLingerSeconds,
                      /*interruptible=*/false)
            .IgnoreError();
        return Cancelled("link closing");
      }
      if (!terminal_.ok()) return terminal_;
      while (out.size() - out_pos < kOutputBatch && !memory_.empty()) {
        const std::uint64_t index = next_send_ - memory_.front().local;
        if (index >= memory_.size()) break;
        const Entry& e = memory_[index];
        wire->auth.AppendDataFrame(e.type, e.local + offset_, *e.message, &out);
        if (e.local <= highest_sent_) ++stats_.resent;
        highest_sent_ = std::max(highest_sent_, e.local);
        ++stats_.frames_sent;
        ++next_send_;
      }
    }
    double now = MonotonicSeconds();
    if (out_pos == out.size() && now - last_tx >= heartbeat) {
      wire->auth.AppendFrame(static_cast<std::uint8_t>(SessionType::kHeartbeat), {}, &out);
    }
    const bool pending = out_pos < out.size();
    const bool writing = pending && (rate <= 0 || now >= pace_ready);
    double next_deadline = std::min(last_frame + idle_timeout_s, last_tx + heartbeat);
    if (pending && !writing) next_deadline = std::min(next_deadline, pace_ready);
    pollfd fds[2] = {{fd, static_cast<short>(POLLIN | (writing ? POLLOUT : 0)), 0},
                     {wake_.fd(), POLLIN, 0}};
    if (::poll(fds, 2, PollMillis(next_deadline - now)) < 0 && errno != EINTR) {
      return IoError(std::string("poll: ") + std::strerror(errno));
    }
    if (fds[1].revents & POLLIN) wake_.Drain();
    if (fds[0].revents & (POLLIN | POLLHUP | POLLERR)) {
      StatusOr<std::size_t> n = ReadSome(fd, buffer.data(), buffer.size());
      if (!n.ok()) {
        if (n.status().code() == StatusCode::kEndOfStream) {
          return Unavailable("the server closed the connection");
        }
        return n.status();
      }
      if (*n > 0) {
        {
          std::lock_guard<std::mutex> lock(mutex_);
          stats_.bytes_received += *n;
        }
        frames.clear();
        const Status fed = wire->decoder.Feed(ByteSpan(buffer.data(), *n), &frames);
        // Progress is a complete frame: a peer dribbling bytes does not keep us waiting.
        if (!frames.empty()) last_frame = MonotonicSeconds();
        for (Frame& f : frames) wire->inbox.push_back(std::move(f));
        if (!fed.ok()) {
          // Handle what arrived intact first (a bye explains more than the bad frame).
          CCMD_RETURN_IF_ERROR(HandleInbox(wire));
          return fed.WithContext("from the server");
        }
      }
    }
    if (writing && (fds[0].revents & POLLOUT)) {
      const std::size_t want = out.size() - out_pos;
      StatusOr<std::size_t> n =
          WriteSome(fd, out.data() + out_pos, rate > 0 ? std::min(want, pace_chunk) : want);
      if (!n.ok()) return n.status();
      out_pos += *n;
      if (*n > 0) {
        last_tx = MonotonicSeconds();
        if (rate > 0) pace_ready = std::max(pace_ready, last_tx - 0.05) + *n / rate;
        std::lock_guard<std::mutex> lock(mutex_);
        stats_.bytes_sent += *n;
      }
    }
    if (MonotonicSeconds() - last_frame >= idle_timeout_s) {
      return Timeout("no complete frame from the server for " + std::to_string(idle_timeout_s) +
                     " s");
    }
  }
}

}  // namespace ccmd
