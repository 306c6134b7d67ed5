#pragma once

// The server's I/O thread (internal to libccmd/net; see server.h): connections, handshakes,
// frame authentication, time-outs, and the hand-off to the journal stage. server.cc holds
// the poll loop and connection plumbing, server_session.cc the protocol (what each frame
// means in each state).

#include <atomic>
#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/net/frame_auth.h"
#include "libccmd/net/journal_stage.h"
#include "libccmd/net/refusal_log.h"
#include "libccmd/net/server.h"
#include "libccmd/net/session_messages.h"
#include "libccmd/net/socket.h"
#include "proto/frame.h"

namespace ccmd {

enum class ConnState { kAwaitHello, kAwaitAuth, kAwaitAttach, kStreaming, kClosing };

inline bool InHandshake(ConnState s) {
  return s == ConnState::kAwaitHello || s == ConnState::kAwaitAuth || s == ConnState::kAwaitAttach;
}

// "closed_time_out" etc.: the statistics counter for a Bye reason.
std::string CounterName(ByeReason reason);
// The Bye reason for a frame or message the server rejects.
ByeReason ReasonFor(const Status& s);

struct Connection {
  std::uint64_t token = 0;
  UniqueFd fd;
  std::string peer;    // address:port
  std::string source;  // address, for the refusal log
  ConnState state = ConnState::kAwaitHello;
  bool counted_as_handshake = true;
  double opened = 0, last_tx = 0, close_deadline = 0;
  double last_frame = 0;           // the last complete frame (idle time-out)
  double frame_started = 0;        // when the header of the frame in progress arrived
  std::uint64_t frame_header = 0;  // decoder's headers_accepted() at frame_started
  std::unique_ptr<FrameDecoder> decoder;
  HelloMessage hello;
  std::vector<std::uint8_t> hello_payload;  // as received: bound into the proof and keys
  Nonce server_nonce{};
  SessionAuth auth;  // keyed once the agent's Auth is verified
  IdentityVerifier verifier{};
  bool attached = false;  // welcomed: has an agent id and a session
  AgentId agent;
  std::vector<std::uint8_t> out;
  std::size_t out_pos = 0;
  bool done = false;  // dropped: erased from the connection map after this poll round
  std::string Describe() const {
    if (hello.name.empty()) return "connection from " + peer;
    return "agent '" + hello.name + "' (" + peer + ")";
  }
};

class ServerIo {
 public:
  ServerIo(const ServerOptions& options, MessageConsumer* consumer, TrafficStats* stats);
  ~ServerIo() { Stop(); }

  Status Start(UniqueFd listener);
  void Stop();

 private:
  struct Slot {                      // per registered agent
    std::uint64_t conn = 0;          // current connection, 0 = none
    std::uint64_t received_seq = 0;  // highest sequence number passed to the journal stage
    std::uint64_t inflight_bytes = 0;
  };

  // server.cc
  void Run();
  void Accept(double now);
  void Read(Connection* c, double now);
  void NoteProgress(Connection* c, bool completed, double now);
  void Write(Connection* c);
  // Sends a frame: tagged when the connection's session is keyed.
  void Send(Connection* c, SessionType type, ByteSpan payload);
  // Says Bye (reason and text), then closes once it is sent (or after a short linger).
  void Close(Connection* c, ByeReason reason, const std::string& text, double now);
  // Closes at once, without a Bye (the peer is gone or not reading).
  void Drop(Connection* c, const std::string& why, bool quiet = false);
  void EndSession(Connection* c, const std::string& why, double now);
  void Finish(Connection* c);
  void CheckTimers(Connection* c, double now);
  void CheckStreamingTimers(Connection* c, double now);
  void Enqueue(StageItem item);
  void FlushPending();
  bool Paused(const Connection* c) const;
  double NextDeadline(double now) const;

  // server_session.cc
  void HandleFrame(Connection* c, Frame& frame, double now);
  void HandleBye(Connection* c, const Frame& frame, double now);
  void HandleHello(Connection* c, const Frame& frame, double now);
  void HandleAuth(Connection* c, const Frame& frame, double now);
  void HandleData(Connection* c, Frame& frame, double now);
  void HandleFeedback(double now);
  void Welcome(Connection* c, const AttachResult& r, double now);
  void ForgetAgent(AgentId agent);

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
  std::map<AgentId, Slot> slots_;
  std::deque<StageItem> pending_;
  std::uint64_t next_token_ = 1;
  int handshakes_ = 0;
  std::vector<std::uint8_t> read_buffer_;
  RefusalLog refusals_;
};

}  // namespace ccmd
