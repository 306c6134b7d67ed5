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

#include "libccmd/net/journal_stage.h"
#include "libccmd/net/psk.h"
#include "libccmd/net/server_io.h"
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
  if (!(handshake_timeout_s > 0) || !(idle_timeout_s > 0) || !(heartbeat_interval_s > 0) ||
      !(frame_timeout_s > 0) || !(slot_timeout_s >= 0) || !(refusal_log_interval_s > 0)) {
    return InvalidArgument("time-outs, intervals and the heartbeat interval must be positive");
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
  out->Add("slot_timeout_s", slot_timeout_s);
  out->Add("max_handshakes", max_handshakes);
  out->Add("max_payload_bytes", max_payload_bytes);
  out->Add("handshake_timeout_s", handshake_timeout_s);
  out->Add("idle_timeout_s", idle_timeout_s);
  out->Add("frame_timeout_s", frame_timeout_s);
  out->Add("heartbeat_interval_s", heartbeat_interval_s);
  out->Add("refusal_log_interval_s", refusal_log_interval_s);
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

// "10.0.0.7:51334" -> "10.0.0.7", "[::1]:7420" -> "[::1]".
std::string SourceOf(const std::string& peer) {
  const std::size_t colon = peer.rfind(':');
  return colon == std::string::npos ? peer : peer.substr(0, colon);
}

}  // namespace

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

ServerIo::ServerIo(const ServerOptions& options, MessageConsumer* consumer, TrafficStats* stats)
    : options_(options),
      stats_(stats),
      delivery_(consumer, options.delivery_queue, stats),
      journal_(JournalStageOptions{.dir = options.journal_dir,
                                   .fsync = options.fsync,
                                   .max_agents = options.max_agents,
                                   .slot_timeout_s = options.slot_timeout_s,
                                   .queue_capacity = options.journal_queue,
                                   .max_batch = 64,
                                   .max_payload_bytes = options.max_payload_bytes},
               &delivery_, &wake_, stats),
      read_buffer_(kReadChunk),
      refusals_(RefusalLogOptions{.interval_s = options.refusal_log_interval_s, .sink = {}}) {}

Status ServerIo::Start(UniqueFd listener) {
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

void ServerIo::Stop() {
  stop_.store(true);
  wake_.Signal();
  if (thread_.joinable()) thread_.join();
  journal_.Stop();
  delivery_.Stop();
}

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
    refusals_.Flush(now);
  }
  // Whatever is still connected is cut; whatever was received is stored and delivered.
  for (auto& [token, c] : conns_) {
    if (!c->done) Drop(c.get(), "server stopped");
  }
  conns_.clear();
  refusals_.Flush(MonotonicSeconds(), /*all=*/true);
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
        next = std::min(next, c->last_frame + options_.idle_timeout_s);
        next = std::min(next, c->last_tx + options_.heartbeat_interval_s);
        if (c->decoder->InFrame()) {
          next = std::min(next, c->frame_started + options_.frame_timeout_s);
        }
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
  auto it = slots_.find(c->agent);
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
    c->source = SourceOf(c->peer);
    c->opened = c->last_frame = c->last_tx = now;
    SetNoDelay(fd);
    if (handshakes_ >= options_.max_handshakes) {
      // Said once, without waiting: a flood of connections must not cost us buffers.
      const std::vector<std::uint8_t> bye = EncodeSessionFrame(
          SessionType::kBye,
          SerializeBye({ByeReason::kServerFull, "too many connections in their handshake"}));
      WriteSome(fd, bye.data(), bye.size()).status().IgnoreError();
      stats_->Count("refused_busy");
      refusals_.Note(c->source, c->peer, ByeReasonName(ByeReason::kServerFull),
                     "too many connections in their handshake", now);
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
    if (c->attached) {
      stats_->AddReceivedBytes(c->agent, *got);
    } else {
      stats_->Count("handshake_bytes_received", *got);
    }
    frames.clear();
    const Status fed = c->decoder->Feed(ByteSpan(read_buffer_.data(), *got), &frames);
    NoteProgress(c, !frames.empty(), now);
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

// Progress is a complete frame, not a byte: a peer dribbling one byte a second makes none,
// and the frame it started must be complete within the frame time-out.
void ServerIo::NoteProgress(Connection* c, bool completed, double now) {
  if (completed) c->last_frame = now;
  const FrameDecoder& d = *c->decoder;
  if (d.InFrame() && d.headers_accepted() != c->frame_header) {
    c->frame_started = now;
    c->frame_header = d.headers_accepted();
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
  c->auth.AppendFrame(static_cast<std::uint8_t>(type), payload, &c->out);
  stats_->AddAuthentication(c->auth.TakeCpuSeconds());
  c->last_tx = MonotonicSeconds();
  Write(c);
}

void ServerIo::Close(Connection* c, ByeReason reason, const std::string& text, double now) {
  if (c->done || c->state == ConnState::kClosing) return;
  const bool normal = reason == ByeReason::kNormal || reason == ByeReason::kShuttingDown ||
                      reason == ByeReason::kReplaced;
  if (normal) {
    CCMD_LOG(INFO) << "closing " << c->Describe() << ": " << text;
  } else if (!c->attached) {
    // Refused before a session: summarised per source, so a storm cannot flood the log.
    refusals_.Note(c->source, c->peer, ByeReasonName(reason),
                   (c->hello.name.empty() ? "" : "agent '" + c->hello.name + "': ") +
                       ByeReasonName(reason) + ": " + text,
                   now);
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
  EndSession(c, std::string(ByeReasonName(reason)) + ": " + text, now);
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
  EndSession(c, why, MonotonicSeconds());
  Finish(c);
}

// The journal stage hears that this connection's session (if it had one) is over.
void ServerIo::EndSession(Connection* c, const std::string& why, double now) {
  if (c->attached) {
    StageItem detach;
    detach.kind = StageItem::Kind::kDetach;
    detach.agent = c->agent;
    detach.reason = why;
    detach.received_time = now;
    Enqueue(std::move(detach));
    stats_->AgentDisconnected(c->agent, now);
    c->attached = false;
    auto slot = slots_.find(c->agent);
    if (slot != slots_.end() && slot->second.conn == c->token) slot->second.conn = 0;
  }
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
      CheckStreamingTimers(c, now);
      break;
    case ConnState::kClosing:
      if (now >= c->close_deadline) Finish(c);
      break;
    case ConnState::kAwaitAttach:
      break;
  }
}

void ServerIo::CheckStreamingTimers(Connection* c, double now) {
  const bool in_frame = c->decoder->InFrame();
  // While we are not reading (back-pressure), silence is ours, not the agent's.
  if (Paused(c) || !pending_.empty()) {
    c->last_frame = now;
    if (in_frame) c->frame_started = now;
  }
  if (in_frame && now - c->frame_started >= options_.frame_timeout_s) {
    stats_->Count("frame_timeouts");
    Close(c, ByeReason::kTimeout,
          "a frame started " + std::to_string(options_.frame_timeout_s) +
              " s ago is still incomplete (" + std::to_string(c->decoder->BytesWanted()) +
              " bytes missing)",
          now);
  } else if (now - c->last_frame >= options_.idle_timeout_s) {
    stats_->Count("idle_timeouts");
    Close(c, ByeReason::kTimeout,
          "no complete frame received for " + std::to_string(options_.idle_timeout_s) + " s", now);
  } else if (now - c->last_tx >= options_.heartbeat_interval_s) {
    Send(c, SessionType::kHeartbeat, {});
  }
}

void ServerIo::Enqueue(StageItem item) {
  if (pending_.empty() && journal_.TryPush(item)) return;
  pending_.push_back(std::move(item));
}

void ServerIo::FlushPending() {
  while (!pending_.empty() && journal_.TryPush(pending_.front())) pending_.pop_front();
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

Json Server::StatsJson() const { return stats_->ToJson(MonotonicSeconds()); }

}  // namespace ccmd
