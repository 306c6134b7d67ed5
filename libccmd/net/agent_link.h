#pragma once

// The agent's side of the transport: a reliable, authenticated link to the server.
//
//   AgentLinkOptions options;
//   options.server = "192.168.1.10:7420";
//   options.name = "robot-1";
//   options.camera = {fx, fy, cx, cy, width, height, depth_scale};
//   options.psk = key;                       // from ResolvePsk(--psk-file)
//   options.spill_dir = "run/robot-1.spill"; // overflow of the resend buffer
//   CCMD_ASSIGN_OR_RETURN(auto link, AgentLink::Create(options));
//   link->Send(MessageType::kKeyframe, SerializeKeyframe(kf).value());  // returns at once
//   ...
//   link->Flush(10.0);   // waits until the server has stored everything
//   link.reset();        // says bye, joins the link thread
//
// Send() numbers each message and keeps it until the server acknowledges that it is
// journaled: in memory up to memory_limit_bytes, then spilled to disk in order (up to
// spill_limit_bytes; beyond that Send fails with kOutOfRange and the caller decides what to
// drop). The link thread connects, authenticates, sends in order, releases acknowledged
// messages, and on any failure reconnects with exponential backoff (with jitter) and
// resends everything not yet acknowledged; the server drops what it already has.
// With a key every frame after the handshake is tagged both ways (frame_auth.h): a frame
// from the server failing its tag (a forged acknowledgement) is never acted on; the link
// closes that connection and reconnects.
// Configuration errors the server reports (wrong key, no key, other protocol version,
// camera/name conflict, another agent's name) end the link: Send and Flush then return
// that error, and stats() counts the messages Send refused and those never acknowledged.
//
// Identity: the link presents an identity secret (agent_identity.h) that the server ties to
// the name at its first registration. It lives in identity_file, by default in the spill
// folder; without either it exists only as long as the link, so a later process under the
// same name is refused.

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "libccmd/net/agent_identity.h"
#include "libccmd/net/frame_auth.h"
#include "libccmd/net/session_messages.h"
#include "libccmd/net/socket.h"
#include "libccmd/net/spill_store.h"
#include "libccmd/util/options_writer.h"
#include "libccmd/util/status.h"
#include "proto/frame.h"

namespace ccmd {

struct AgentLinkOptions {
  std::string server;  // HOST:PORT
  std::string name;    // the agent's name: letters, digits, '.', '_', '-'
  SessionCamera camera;
  std::string psk;        // the deployment's key; "" only with a keyless loopback server
  std::string spill_dir;  // "" = no spilling: Send fails when memory is full
  // The identity secret's file: "" = <spill_dir>/identity; without a spill folder either,
  // a new secret held in memory only.
  std::string identity_file;
  std::size_t memory_limit_bytes = 64u << 20;
  std::uint64_t spill_limit_bytes = 4ull << 30;
  double connect_timeout_s = 5.0;
  double handshake_timeout_s = 5.0;
  double backoff_initial_s = 0.1;
  double backoff_max_s = 5.0;
  double heartbeat_interval_s = 2.0;  // also at most a third of the server's idle time-out
  std::uint64_t jitter_seed = 0;      // mixed with the name: backoff jitter is reproducible
  // > 0: the link writes at most this many bytes per second to its socket (bursts of at most
  // 50 ms), so a bandwidth budget holds second by second instead of in bursts.
  double max_send_bytes_per_s = 0;
  // Called on the link thread when messages first..last (link numbers, as returned by Send)
  // have been acknowledged. Must not call back into the link.
  std::function<void(std::uint64_t first, std::uint64_t last)> on_acked;

  Status Validate() const;
  void Describe(OptionsWriter* out) const;  // the key is shown as set or not, never its bytes
};

struct AgentLinkStats {
  bool connected = false;
  AgentId agent;                   // assigned by the server (valid after the first welcome)
  std::uint64_t queued = 0;        // messages accepted by Send
  std::uint64_t acked = 0;         // messages the server has stored
  std::uint64_t unacked = 0;       // queued - acked
  std::uint64_t memory_bytes = 0;  // message bytes held in memory
  std::uint64_t spilled = 0;       // messages that went to disk
  std::uint64_t spill_bytes = 0;   // bytes on disk now
  std::uint64_t frames_sent = 0;
  std::uint64_t resent = 0;  // messages sent more than once (after reconnects)
  std::uint64_t bytes_sent = 0;
  std::uint64_t bytes_received = 0;
  std::uint64_t sessions = 0;         // successful handshakes
  std::uint64_t failed_attempts = 0;  // connections or sessions that failed
  std::uint64_t refused = 0;          // messages Send did not accept (link ended, full, ...)
  std::uint64_t auth_failures = 0;    // frames from the server that failed their tag
  std::string last_error;
};

class AgentLink {
 public:
  static StatusOr<std::unique_ptr<AgentLink>> Create(AgentLinkOptions options);
  ~AgentLink();
  AgentLink(const AgentLink&) = delete;
  AgentLink& operator=(const AgentLink&) = delete;

  // Queues a data message (type >= 16); returns its link number (1, 2, 3, ...). Never waits
  // for the network; may write to the spill folder. Fails with the link's terminal error,
  // kOutOfRange when memory and spill are full, kInvalidArgument for an oversized message.
  StatusOr<std::uint64_t> Send(std::uint8_t type, std::vector<std::uint8_t> message);
  StatusOr<std::uint64_t> Send(MessageType type, std::vector<std::uint8_t> message) {
    return Send(static_cast<std::uint8_t>(type), std::move(message));
  }

  // Waits until every queued message is acknowledged: Ok, kTimeout, or the terminal error.
  Status Flush(double timeout_s);
  // Says bye and joins the link thread. Unacknowledged messages are dropped (Flush first).
  void Close();

  AgentLinkStats stats() const;
  // Ok while the link works (connected or retrying); the error that ended it otherwise.
  Status status() const;

 private:
  struct Entry {
    std::uint64_t local = 0;
    std::uint8_t type = 0;
    std::shared_ptr<const std::vector<std::uint8_t>> message;
  };

  // One connection's state on the link thread.
  struct Wire {
    int fd = -1;
    FrameDecoder decoder{FrameLimits{.max_payload_bytes = kDefaultMaxPayloadBytes}};
    std::deque<Frame> inbox;  // decoded, not yet handled (nor verified)
    SessionAuth auth;         // keyed after the Auth is sent
    double idle_timeout_s = 30;
  };

  AgentLink(AgentLinkOptions options, HostPort address, std::unique_ptr<SpillStore> spill,
            AgentIdentity identity);
  StatusOr<std::uint64_t> Refuse(Status why);  // counts a refused Send (mutex held)
  void Run();
  Status Session(double* backoff);
  Status Handshake(Wire* wire);
  // The Welcome (or Bye) answering the Auth, verified.
  StatusOr<WelcomeMessage> AwaitWelcome(Wire* wire, double deadline);
  Status Stream(Wire* wire);
  // Verifies and handles the frames in the inbox, in order.
  Status HandleInbox(Wire* wire);
  Status WriteBlocking(int fd, ByteSpan bytes, double deadline, bool interruptible = true);
  StatusOr<Frame> ReadFrameBlocking(Wire* wire, double deadline);
  Status HandleServerFrame(const Frame& frame);
  // What a Bye from the server means; `authenticated`: tagged and verified (or keyless).
  Status ServerBye(const ByeMessage& bye, bool authenticated);
  // Releases messages up to link number `last` (mutex held); returns the first released.
  void ReleaseLocked(std::uint64_t last);
  void RefillLocked();

  const AgentLinkOptions options_;
  const HostPort address_;
  const AgentIdentity identity_;
  WakeFd wake_;
  std::thread thread_;

  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<Entry> memory_;  // oldest unacknowledged first
  std::size_t memory_bytes_ = 0;
  std::unique_ptr<SpillStore> spill_;
  std::uint64_t next_local_ = 1;
  std::uint64_t acked_local_ = 0;
  bool welcomed_once_ = false;
  std::uint64_t offset_ = 0;  // wire sequence number = link number + offset_
  std::size_t max_message_bytes_ = kDefaultMaxPayloadBytes - kDataEnvelopeBytes;
  Status terminal_;
  bool stopping_ = false;
  bool closed_ = false;
  AgentLinkStats stats_;

  // Link thread only.
  std::uint64_t next_send_ = 1;
  std::uint64_t highest_sent_ = 0;
  int protocol_errors_in_a_row_ = 0;
};

}  // namespace ccmd
