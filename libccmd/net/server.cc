#include "libccmd/net/server.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/file.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <deque>
#include <map>
#include <optional>

#include "libccmd/net/journal_stage.h"
#include "libccmd/net/psk.h"
#include "libccmd/net/session_messages.h"
#include "libccmd/net/socket.h"
#include "libccmd/util/file_util.h"
#include "libccmd/util/logging.h"
#include "libccmd/util/timer.h"
#include "proto/frame.h"
#include "proto/messages.h"

namespace ccmd {

Status ServerOptions::Validate() const {
  if (journal_dir.empty()) return InvalidArgument("the server needs a journal folder");
  if (max_agents < 1 || max_agents > 65535) return InvalidArgument("max_agents must be 1..65535");
  if (max_handshakes < 1) return InvalidArgument("max_handshakes must be positive");
  if (max_payload_bytes < 1024) return InvalidArgument("max_payload_bytes must be >= 1024");
  if (!(handshake_timeout_s > 0) || !(idle_timeout_s > 0) || !(heartbeat_interval_s > 0)) {
    return InvalidArgument("time-outs and the heartbeat interval must be positive");
  }
  if (heartbeat_interval_s >= idle_timeout_s) {
    return InvalidArgument("the heartbeat interval must be shorter than the idle time-out");
  }
  if (per_agent_memory_bytes < max_payload_bytes) {
    return InvalidArgument("per_agent_memory_bytes must hold at least one maximal frame");
  }
  if (journal_queue == 0 || delivery_queue == 0) return InvalidArgument("queues need capacity");
  CCMD_RETURN_IF_ERROR(traffic.Validate());
  if (!psk.empty() && psk.size() < kMinPskBytes) {
    return InvalidArgument("the pre-shared key needs at least " + std::to_string(kMinPskBytes) +
                           " bytes");
  }
  return Status::Ok();
}

void ServerOptions::Describe(OptionsWriter* out) const {
  out->Add("listen", listen);
  out->Add("journal_dir", journal_dir);
  out->Add("resume", resume);
  out->Add("psk", psk.empty() ? "none" : "set");
  out->Add("max_agents", max_agents);
  out->Add("max_handshakes", max_handshakes);
  out->Add("max_payload_bytes", max_payload_bytes);
  out->Add("handshake_timeout_s", handshake_timeout_s);
  out->Add("idle_timeout_s", idle_timeout_s);
  out->Add("heartbeat_interval_s", heartbeat_interval_s);
  out->Add("per_agent_memory_bytes", per_agent_memory_bytes);
  out->Add("max_output_bytes", max_output_bytes);
  out->Add("fsync", fsync);
  out->Add("journal_queue", journal_queue);
  out->Add("delivery_queue", delivery_queue);
  out->Nested("traffic", traffic);
}

namespace {

constexpr std::size_t kReadChunk = 256 << 10;
// Bytes read from one connection per poll round, so one fast agent cannot starve others.
constexpr std::size_t kReadBudget = 1 << 20;
constexpr double kCloseLingerSeconds = 1.0;
constexpr double kDrainSeconds = 2.0;

enum class ConnState { kAwaitHello, kAwaitAuth, kAwaitAttach, kStreaming, kClosing };

bool InHandshake(ConnState s) {
  return s == ConnState::kAwaitHello || s == ConnState::kAwaitAuth || s == ConnState::kAwaitAttach;
}

std::string CounterName(ByeReason reason) {
  std::string name = std::string("closed_") + ByeReasonName(reason);
  for (char& c : name) {
    if (c == ' ' || c == '-') c = '_';
  }
  return name;
}

ByeReason ReasonFor(const Status& s) {
  switch (s.code()) {
    case StatusCode::kUnsupported:
      return ByeReason::kUnsupportedVersion;
    case StatusCode::kOutOfRange:
      return ByeReason::kLimitExceeded;
    default:
      return ByeReason::kProtocolError;
  }
}

}  // namespace

struct Connection {
  std::uint64_t token = 0;
  UniqueFd fd;
  std::string peer;
  ConnState state = ConnState::kAwaitHello;
  bool counted_as_handshake = true;
  double opened = 0, last_rx = 0, last_tx = 0, close_deadline = 0;
  std::unique_ptr<FrameDecoder> decoder;
  HelloMessage hello;
  Nonce server_nonce{};
  bool attached = false;  // welcomed: has an agent id and a session
  AgentId agent;
  std::vector<std::uint8_t> out;
  std::size_t out_pos = 0;
  bool done = false;  // to be removed
  std::string Describe() const {
    if (hello.name.empty()) return "connection from " + peer;
    return "agent '" + hello.name + "' (" + peer + ")";
  }
};

// The I/O thread and the stages behind it.
class ServerIo {
 public:
  ServerIo(const ServerOptions& options, MessageConsumer* consumer, TrafficStats* stats)
      : options_(options),
        stats_(stats),
        delivery_(consumer, options.delivery_queue, stats),
        journal_(JournalStageOptions{.dir = options.journal_dir,
                                     .fsync = options.fsync,
                                     .max_agents = options.max_agents,
                                     .queue_capacity = options.journal_queue,
                                     .max_batch = 64,
                                     .max_payload_bytes = options.max_payload_bytes},
                 &delivery_, &wake_, stats),
        read_buffer_(kReadChunk) {}
  ~ServerIo() { Stop(); }

  Status Start(UniqueFd listener) {
    if (!wake_.valid()) return IoError("eventfd: " + std::string(std::strerror(errno)));
    listener_ = std::move(listener);
    delivery_.Start();
    if (options_.resume) {
      CCMD_ASSIGN_OR_RETURN(const std::uint64_t replayed, journal_.Resume());
      DeliveryItem done;
      done.kind = DeliveryItem::Kind::kReplayFinished;
      done.value = replayed;
      delivery_.Push(std::move(done));
      delivery_.WaitReplayFinished();
      CCMD_LOG(INFO) << "replayed " << replayed << " journaled messages from "
                     << options_.journal_dir;
    } else {
      CCMD_RETURN_IF_ERROR(journal_.CheckNoJournals());
    }
    journal_.Start();
    thread_ = std::thread([this] { Run(); });
    return Status::Ok();
  }

  void Stop() {
    stop_.store(true);
    wake_.Signal();
    if (thread_.joinable()) thread_.join();
    journal_.Stop();
    delivery_.Stop();
  }

 private:
  void Run();
  void Accept(double now);
  void Read(Connection* c, double now);
  void Write(Connection* c);
  void Send(Connection* c, SessionType type, ByteSpan payload);
  void HandleFrame(Connection* c, Frame& frame, double now);
  void HandleHello(Connection* c, const Frame& frame);
  void HandleAuth(Connection* c, const Frame& frame);
  void HandleData(Connection* c, Frame& frame, double now);
  void HandleFeedback(double now);
  void CheckTimers(Connection* c, double now);
  // Says Bye (reason and text), then closes once it is sent (or after a short linger).
  void Close(Connection* c, ByeReason reason, const std::string& text, double now);
  // Closes at once, without a Bye (the peer is gone or not reading).
  void Drop(Connection* c, const std::string& why, bool quiet = false);
  void Finish(Connection* c);
  void Enqueue(StageItem item);
  void FlushPending();
  bool Paused(const Connection* c) const;
  double NextDeadline(double now) const;

  struct Slot {              // per agent name
    std::uint64_t conn = 0;  // current connection, 0 = none
    AgentId agent;
    std::uint64_t received_seq = 0;  // highest sequence number passed to the journal stage
    std::uint64_t inflight_bytes = 0;
    std::optional<SessionCamera> camera;  // as registered, once known
  };

  const ServerOptions& options_;
  TrafficStats* stats_;
  WakeFd wake_;
  DeliveryStage delivery_;
  JournalStage journal_;
  UniqueFd listener_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  bool draining_ = false;
  double drain_deadline_ = 0;
  std::map<std::uint64_t, std::unique_ptr<Connection>> conns_;
  std::map<std::string, Slot> slots_;
  std::map<AgentId, std::string> names_;
  std::deque<StageItem> pending_;
  std::uint64_t next_token_ = 1;
  int handshakes_ = 0;
  std::vector<std::uint8_t> read_buffer_;
};

void ServerIo::Run() {
  std::vector<pollfd> fds;
  std::vector<Connection*> polled;
  while (true) {
    double now = MonotonicSeconds();
    if (stop_.load() && !draining_) {
      draining_ = true;
      drain_deadline_ = now + kDrainSeconds;
      listener_.Reset();
      for (auto& [token, c] : conns_) {
        if (c->state != ConnState::kClosing && !c->done) {
          Close(c.get(), ByeReason::kShuttingDown, "the server is shutting down", now);
        }
      }
    }
    if (draining_ && (conns_.empty() || now >= drain_deadline_)) break;

    fds.clear();
    polled.clear();
    fds.push_back({wake_.fd(), POLLIN, 0});
    const bool accepting = listener_.valid() && handshakes_ < options_.max_handshakes;
    if (accepting) fds.push_back({listener_.get(), POLLIN, 0});
    const bool reading = pending_.empty();
    for (auto& [token, c] : conns_) {
      short events = 0;
      if (reading && c->state != ConnState::kClosing && c->state != ConnState::kAwaitAttach &&
          !Paused(c.get())) {
        events |= POLLIN;
      }
      if (c->out_pos < c->out.size()) events |= POLLOUT;
      fds.push_back({c->fd.get(), events, 0});
      polled.push_back(c.get());
    }
    const double wait = std::max(0.0, NextDeadline(now) - now);
    const int timeout_ms = static_cast<int>(std::min(1000.0, std::ceil(wait * 1e3)));
    const int n = ::poll(fds.data(), fds.size(), timeout_ms);
    if (n < 0 && errno != EINTR) {
      CCMD_LOG(ERROR) << "poll failed: " << std::strerror(errno);
      break;
    }
    now = MonotonicSeconds();
    if (fds[0].revents & POLLIN) wake_.Drain();
    HandleFeedback(now);
    FlushPending();
    std::size_t index = 1;
    if (accepting) {
      if (fds[index].revents & POLLIN) Accept(now);
      ++index;
    }
    for (Connection* c : polled) {
      const short revents = fds[index++].revents;
      if (c->done) continue;
      if (revents & (POLLIN | POLLHUP | POLLERR)) {
        if (revents & POLLIN) {
          Read(c, now);
        } else if (c->state != ConnState::kClosing) {
          Drop(c, "connection lost");
        } else {
          Finish(c);
        }
      }
      if (!c->done && (revents & POLLOUT)) Write(c);
    }
    for (auto& [token, c] : conns_) {
      if (!c->done) CheckTimers(c.get(), now);
    }
    for (auto it = conns_.begin(); it != conns_.end();) {
      it = it->second->done ? conns_.erase(it) : std::next(it);
    }
  }
  // Whatever is still connected is cut; whatever was received is stored and delivered.
  for (auto& [token, c] : conns_) {
    if (!c->done) Drop(c.get(), "server stopped");
  }
  conns_.clear();
  while (!pending_.empty()) {
    journal_.Push(std::move(pending_.front()));
    pending_.pop_front();
  }
}

double ServerIo::NextDeadline(double now) const {
  double next = now + 1.0;
  for (const auto& [token, c] : conns_) {
    if (c->done) continue;
    switch (c->state) {
      case ConnState::kAwaitHello:
      case ConnState::kAwaitAuth:
        next = std::min(next, c->opened + options_.handshake_timeout_s);
        break;
      case ConnState::kStreaming:
        next = std::min(next, c->last_rx + options_.idle_timeout_s);
        next = std::min(next, c->last_tx + options_.heartbeat_interval_s);
        break;
      case ConnState::kClosing:
        next = std::min(next, c->close_deadline);
        break;
      case ConnState::kAwaitAttach:
        break;
    }
  }
  if (draining_) next = std::min(next, drain_deadline_);
  return next;
}

bool ServerIo::Paused(const Connection* c) const {
  if (!c->attached) return false;
  auto it = slots_.find(c->hello.name);
  return it != slots_.end() && it->second.inflight_bytes >= options_.per_agent_memory_bytes;
}

void ServerIo::Accept(double now) {
  while (true) {
    const int fd = ::accept4(listener_.get(), nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      if (errno == EINTR) continue;
      if (errno != EAGAIN && errno != EWOULDBLOCK) {
        CCMD_LOG(WARNING) << "accept failed: " << std::strerror(errno);
      }
      return;
    }
    stats_->Count("connections_accepted");
    auto c = std::make_unique<Connection>();
    c->token = next_token_++;
    c->fd = UniqueFd(fd);
    c->peer = PeerName(fd);
    c->opened = c->last_rx = c->last_tx = now;
    SetNoDelay(fd);
    if (handshakes_ >= options_.max_handshakes) {
      // Said once, without waiting: a flood of connections must not cost us buffers.
      const std::vector<std::uint8_t> bye = EncodeSessionFrame(
          SessionType::kBye,
          SerializeBye({ByeReason::kServerFull, "too many connections in their handshake"}));
      WriteSome(fd, bye.data(), bye.size()).status().IgnoreError();
      stats_->Count("refused_busy");
      CCMD_LOG(WARNING) << "refused connection from " << c->peer
                        << ": too many connections in their handshake";
      continue;
    }
    ++handshakes_;
    c->decoder =
        std::make_unique<FrameDecoder>(FrameLimits{.max_payload_bytes = kMaxHandshakePayloadBytes});
    CCMD_LOG(DEBUG) << "connection from " << c->peer;
    conns_[c->token] = std::move(c);
  }
}

void ServerIo::Read(Connection* c, double now) {
  std::size_t budget = kReadBudget;
  std::vector<Frame> frames;
  while (budget > 0 && !c->done && c->state != ConnState::kClosing &&
         c->state != ConnState::kAwaitAttach && pending_.empty() && !Paused(c)) {
    // During the handshake, read exactly up to the end of the current frame: the decoder is
    // replaced (with the session's larger limit) once the agent is welcomed.
    const std::size_t want = InHandshake(c->state)
                                 ? std::min(c->decoder->BytesWanted(), read_buffer_.size())
                                 : read_buffer_.size();
    StatusOr<std::size_t> got = ReadSome(c->fd.get(), read_buffer_.data(), want);
    if (!got.ok()) {
      if (got.status().code() == StatusCode::kEndOfStream) {
        if (InHandshake(c->state)) stats_->Count("handshakes_abandoned");
        Drop(c, c->decoder->Idle() ? "the peer closed the connection"
                                   : "the peer closed the connection in the middle of a frame");
      } else {
        Drop(c, got.status().message());
      }
      return;
    }
    if (*got == 0) return;
    budget -= std::min(budget, *got);
    c->last_rx = now;
    if (c->attached) {
      stats_->AddReceivedBytes(c->agent, *got);
    } else {
      stats_->Count("handshake_bytes_received", *got);
    }
    frames.clear();
    const Status fed = c->decoder->Feed(ByteSpan(read_buffer_.data(), *got), &frames);
    for (Frame& f : frames) {
      HandleFrame(c, f, now);
      if (c->done || c->state == ConnState::kClosing) return;
    }
    if (!fed.ok()) {
      Close(c, ReasonFor(fed), "bad frame: " + fed.message(), now);
      return;
    }
  }
}

void ServerIo::Write(Connection* c) {
  while (c->out_pos < c->out.size()) {
    StatusOr<std::size_t> n =
        WriteSome(c->fd.get(), c->out.data() + c->out_pos, c->out.size() - c->out_pos);
    if (!n.ok()) {
      Drop(c, n.status().message());
      return;
    }
    if (*n == 0) break;
    c->out_pos += *n;
    if (c->attached) stats_->AddSentBytes(c->agent, *n);
  }
  if (c->out_pos == c->out.size()) {
    c->out.clear();
    c->out_pos = 0;
    if (c->state == ConnState::kClosing) Finish(c);
  } else if (c->out_pos > (1u << 20)) {
    c->out.erase(c->out.begin(), c->out.begin() + static_cast<std::ptrdiff_t>(c->out_pos));
    c->out_pos = 0;
  }
}

void ServerIo::Send(Connection* c, SessionType type, ByteSpan payload) {
  if (c->done) return;
  if (c->out.size() - c->out_pos > options_.max_output_bytes) {
    Drop(c, "the peer does not read what the server sends");
    return;
  }
  AppendFrame(static_cast<std::uint8_t>(type), 0, payload, &c->out);
  c->last_tx = MonotonicSeconds();
  Write(c);
}

void ServerIo::Close(Connection* c, ByeReason reason, const std::string& text, double now) {
  if (c->done || c->state == ConnState::kClosing) return;
  const bool normal = reason == ByeReason::kNormal || reason == ByeReason::kShuttingDown ||
                      reason == ByeReason::kReplaced;
  if (normal) {
    CCMD_LOG(INFO) << "closing " << c->Describe() << ": " << text;
  } else {
    CCMD_LOG(WARNING) << "closing " << c->Describe() << ": " << ByeReasonName(reason) << ": "
                      << text;
  }
  stats_->Count(CounterName(reason));
  Send(c, SessionType::kBye, SerializeBye({reason, text}));
  if (c->done) return;
  if (c->counted_as_handshake) {
    c->counted_as_handshake = false;
    --handshakes_;
  }
  if (c->attached) {
    StageItem detach;
    detach.kind = StageItem::Kind::kDetach;
    detach.agent = c->agent;
    detach.reason = std::string(ByeReasonName(reason)) + ": " + text;
    Enqueue(std::move(detach));
    stats_->AgentDisconnected(c->agent, now);
    c->attached = false;
  }
  auto slot = slots_.find(c->hello.name);
  if (slot != slots_.end() && slot->second.conn == c->token) slot->second.conn = 0;
  c->state = ConnState::kClosing;
  c->close_deadline = now + kCloseLingerSeconds;
  if (c->out_pos == c->out.size()) Finish(c);
}

void ServerIo::Drop(Connection* c, const std::string& why, bool quiet) {
  if (c->done) return;
  if (c->state != ConnState::kClosing && !quiet) {
    if (c->attached) {
      CCMD_LOG(INFO) << "lost " << c->Describe() << ": " << why;
    } else {
      CCMD_LOG(DEBUG) << "lost " << c->Describe() << ": " << why;
    }
  }
  if (c->attached) {
    StageItem detach;
    detach.kind = StageItem::Kind::kDetach;
    detach.agent = c->agent;
    detach.reason = why;
    Enqueue(std::move(detach));
    stats_->AgentDisconnected(c->agent, MonotonicSeconds());
    c->attached = false;
  }
  auto slot = slots_.find(c->hello.name);
  if (slot != slots_.end() && slot->second.conn == c->token) slot->second.conn = 0;
  Finish(c);
}

void ServerIo::Finish(Connection* c) {
  if (c->counted_as_handshake) {
    c->counted_as_handshake = false;
    --handshakes_;
  }
  if (c->fd.valid()) ::shutdown(c->fd.get(), SHUT_RDWR);
  c->fd.Reset();
  c->done = true;
}

void ServerIo::CheckTimers(Connection* c, double now) {
  switch (c->state) {
    case ConnState::kAwaitHello:
    case ConnState::kAwaitAuth:
      if (now - c->opened >= options_.handshake_timeout_s) {
        stats_->Count("handshake_timeouts");
        Close(c, ByeReason::kTimeout,
              "no complete handshake within " + std::to_string(options_.handshake_timeout_s) + " s",
              now);
      }
      break;
    case ConnState::kStreaming:
      // While we are not reading (back-pressure), silence is ours, not the agent's.
      if (Paused(c) || !pending_.empty()) c->last_rx = now;
      if (now - c->last_rx >= options_.idle_timeout_s) {
        stats_->Count("idle_timeouts");
        Close(c, ByeReason::kTimeout,
              "nothing received for " + std::to_string(options_.idle_timeout_s) + " s", now);
      } else if (now - c->last_tx >= options_.heartbeat_interval_s) {
        Send(c, SessionType::kHeartbeat, {});
      }
      break;
    case ConnState::kClosing:
      if (now >= c->close_deadline) Finish(c);
      break;
    case ConnState::kAwaitAttach:
      break;
  }
}

void ServerIo::Enqueue(StageItem item) {
  if (pending_.empty() && journal_.TryPush(item)) return;
  pending_.push_back(std::move(item));
}

void ServerIo::FlushPending() {
  while (!pending_.empty() && journal_.TryPush(pending_.front())) pending_.pop_front();
}

void ServerIo::HandleFrame(Connection* c, Frame& frame, double now) {
  const std::uint8_t type = frame.type;
  if (type == static_cast<std::uint8_t>(SessionType::kBye)) {
    StatusOr<ByeMessage> bye = ParseBye(frame.payload);
    if (bye.ok()) {
      const bool normal = bye->reason == ByeReason::kNormal;
      const std::string what = c->Describe() + " said bye (" + ByeReasonName(bye->reason) + ")" +
                               (bye->text.empty() ? "" : ": " + bye->text);
      if (normal) {
        CCMD_LOG(INFO) << what;
      } else {
        CCMD_LOG(WARNING) << what;
        stats_->Count("agent_bye_" + CounterName(bye->reason).substr(7));
      }
      Drop(c, "the agent said bye", /*quiet=*/true);
    } else {
      Close(c, ByeReason::kProtocolError, "malformed bye: " + bye.status().message(), now);
    }
    return;
  }
  switch (c->state) {
    case ConnState::kAwaitHello:
      if (type != static_cast<std::uint8_t>(SessionType::kHello)) {
        Close(c, ByeReason::kProtocolError,
              "expected a hello, got a message of type " + std::to_string(type), now);
        return;
      }
      HandleHello(c, frame);
      return;
    case ConnState::kAwaitAuth:
      if (type != static_cast<std::uint8_t>(SessionType::kAuth)) {
        Close(c, ByeReason::kProtocolError,
              "expected an auth message, got type " + std::to_string(type), now);
        return;
      }
      HandleAuth(c, frame);
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
    case ConnState::kAwaitAttach:
    case ConnState::kClosing:
      return;
  }
}

void ServerIo::HandleHello(Connection* c, const Frame& frame) {
  const double now = MonotonicSeconds();
  StatusOr<HelloMessage> hello = ParseHello(frame.payload);
  if (!hello.ok()) {
    Close(c, ReasonFor(hello.status()), "bad hello: " + hello.status().message(), now);
    return;
  }
  c->hello = std::move(*hello);
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

void ServerIo::HandleAuth(Connection* c, const Frame& frame) {
  const double now = MonotonicSeconds();
  StatusOr<AuthMessage> auth = ParseAuth(frame.payload);
  if (!auth.ok()) {
    Close(c, ByeReason::kProtocolError, "bad auth message: " + auth.status().message(), now);
    return;
  }
  if (!options_.psk.empty()) {
    if (!auth->proof) {
      stats_->Count("refused_no_key");
      Close(c, ByeReason::kAuthFailed,
            "this server requires a pre-shared key and the agent has none (give the agent the "
            "deployment's key with --psk-file FILE or CCMD_PSK)",
            now);
      return;
    }
    const Mac expected =
        AgentProof(options_.psk, c->server_nonce, c->hello.agent_nonce, c->hello.name);
    if (!ConstantTimeEquals(expected, *auth->proof)) {
      stats_->Count("refused_wrong_key");
      Close(c, ByeReason::kAuthFailed,
            "authentication failed: the agent's pre-shared key is not this server's", now);
      return;
    }
  } else if (auth->proof) {
    stats_->Count("refused_key_mismatch");
    Close(c, ByeReason::kKeyMismatch,
          "this server runs without a pre-shared key but the agent has one; give both the same "
          "key (or neither, on loopback)",
          now);
    return;
  }
  Slot& slot = slots_[c->hello.name];
  // A conflicting camera must not cost the registered agent its connection (the journal
  // stage refuses it in any case).
  if (slot.camera && !(*slot.camera == c->hello.camera)) {
    stats_->Count("refused_refused");
    Close(c, ByeReason::kRefused,
          "agent '" + c->hello.name + "' is registered with camera " +
              DescribeCamera(*slot.camera) + " but announces " + DescribeCamera(c->hello.camera) +
              "; a different camera needs a new agent name",
          now);
    return;
  }
  if (slot.conn != 0) {
    auto old = conns_.find(slot.conn);
    if (old != conns_.end() && !old->second->done) {
      Close(old->second.get(), ByeReason::kReplaced,
            "replaced by a new connection of the same agent from " + c->peer, now);
    }
  }
  slot.conn = c->token;
  StageItem attach;
  attach.kind = StageItem::Kind::kAttach;
  attach.conn = c->token;
  attach.hello = c->hello;
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
  Slot& slot = slots_[c->hello.name];
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
  if (keyframe) {
    StatusOr<KeyframeMessage> kf = ParseKeyframe(env->message);
    if (!kf.ok()) {
      Close(
          c, ReasonFor(kf.status()),
          "malformed keyframe (message " + std::to_string(env->seq) + "): " + kf.status().message(),
          now);
      return;
    }
    // The bytes per part, by serializing what arrived again (the format is canonical).
    StatusOr<std::vector<std::uint8_t>> again = SerializeKeyframe(*kf, &parts);
    const std::size_t counted = again.ok() ? parts.total() : 0;
    if (counted < env->message.size()) parts.other += env->message.size() - counted;
  } else {
    StatusOr<PoseUpdateMessage> pu = ParsePoseUpdate(env->message);
    if (!pu.ok()) {
      Close(c, ReasonFor(pu.status()),
            "malformed pose update (message " + std::to_string(env->seq) +
                "): " + pu.status().message(),
            now);
      return;
    }
  }
  stats_->AddDataMessage(c->agent, type, env->message.size(), keyframe ? &parts : nullptr, now);
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
        Enqueue(std::move(detach));
      }
      continue;
    }
    if (!r.status.ok()) {
      stats_->Count("refused_" + CounterName(r.reason).substr(7));
      Close(c, r.reason, r.status.message(), now);
      continue;
    }
    Slot& slot = slots_[c->hello.name];
    slot.agent = r.agent;
    slot.received_seq = r.last_stored;
    slot.camera = c->hello.camera;
    names_[r.agent] = c->hello.name;
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
    if (!options_.psk.empty()) {
      welcome.server_proof = ServerProof(options_.psk, c->hello.agent_nonce, c->server_nonce,
                                         r.agent.value(), r.last_stored);
    }
    c->state = ConnState::kStreaming;
    c->decoder = std::make_unique<FrameDecoder>(
        FrameLimits{.max_payload_bytes = options_.max_payload_bytes});
    c->last_rx = now;
    stats_->AgentConnected(r.agent, c->hello.name, now);
    stats_->Count("sessions");
    CCMD_LOG(INFO) << "agent " << r.agent << " '" << c->hello.name << "' connected from " << c->peer
                   << "; stored up to message " << r.last_stored;
    Send(c, SessionType::kWelcome, SerializeWelcome(welcome));
  }
  for (const auto& [agent, n] : fb.freed_bytes) {
    auto name = names_.find(agent);
    if (name == names_.end()) continue;
    Slot& slot = slots_[name->second];
    slot.inflight_bytes -= std::min<std::uint64_t>(slot.inflight_bytes, n);
  }
  for (const auto& [agent, seq] : fb.stored) {
    auto name = names_.find(agent);
    if (name == names_.end()) continue;
    const Slot& slot = slots_[name->second];
    auto it = conns_.find(slot.conn);
    if (it == conns_.end() || it->second->state != ConnState::kStreaming) continue;
    Send(it->second.get(), SessionType::kAck, SerializeAck({seq}));
  }
  for (const auto& [agent, status] : fb.failed) {
    auto name = names_.find(agent);
    if (name == names_.end()) continue;
    Slot& slot = slots_[name->second];
    auto it = conns_.find(slot.conn);
    if (it != conns_.end() && !it->second->done) {
      Close(it->second.get(), ByeReason::kServerError,
            "the server could not store the data: " + status.message(), now);
    }
  }
}

// ---------------------------------------------------------------- Server

Server::Server(ServerOptions options, MessageConsumer* consumer)
    : options_(std::move(options)),
      consumer_(consumer),
      stats_(std::make_unique<TrafficStats>(options_.traffic)) {}

Server::~Server() { Stop(); }

Status Server::Start() {
  CCMD_CHECK(!started_) << "Server::Start called twice";
  started_ = true;
  CCMD_RETURN_IF_ERROR(options_.Validate());
  CCMD_ASSIGN_OR_RETURN(const HostPort address, ParseHostPort(options_.listen));
  bool loopback = false;
  CCMD_ASSIGN_OR_RETURN(UniqueFd listener, ListenTcp(address, 64, &loopback));
  if (!loopback && options_.psk.empty()) {
    return PermissionDenied(
        "refusing to listen on " + options_.listen +
        " without a pre-shared key: anyone on that network could connect. Give the server and "
        "every agent the same key (--psk-file FILE, or the environment variable CCMD_PSK; e.g. "
        "`openssl rand -hex 32 > ccmd.key`), or listen on 127.0.0.1");
  }
  CCMD_ASSIGN_OR_RETURN(port_, LocalPort(listener.get()));
  CCMD_RETURN_IF_ERROR(MakeDirectories(options_.journal_dir));
  const std::string lock_path = JoinPath(options_.journal_dir, "LOCK");
  journal_lock_ = ::open(lock_path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (journal_lock_ < 0) return IoError("cannot open " + lock_path + ": " + std::strerror(errno));
  if (::flock(journal_lock_, LOCK_EX | LOCK_NB) != 0) {
    return Unavailable("journal folder " + options_.journal_dir +
                       " is in use by another running server");
  }
  io_ = std::make_unique<ServerIo>(options_, consumer_, stats_.get());
  Status s = io_->Start(std::move(listener));
  if (!s.ok()) {
    io_->Stop();
    io_.reset();
    return s;
  }
  CCMD_LOG(INFO) << "listening on " << address.host << ":" << port_
                 << (options_.psk.empty() ? " (no key: loopback only)" : " (pre-shared key)")
                 << ", journal " << options_.journal_dir;
  return Status::Ok();
}

void Server::Stop() {
  if (io_) {
    io_->Stop();
    io_.reset();
  }
  if (journal_lock_ >= 0) {
    ::close(journal_lock_);  // releases the flock
    journal_lock_ = -1;
  }
}

Json Server::StatsJson() const {
  return stats_->ToJson(MonotonicSeconds());
}

}  // namespace ccmd
